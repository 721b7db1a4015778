//! `builtin:hair[:KIND[:N]]`: a head of `N` strands of curves of one kind.
//!
//! Every kind is made from the same strands: each strand is a polyline of control points
//! grown from a root on the head, bent down by gravity and a little noise. Linear kinds
//! take the polyline's points; B-splines take them as control points; Bezier curves take
//! the B-spline's Bezier form, chained (each segment's last point is the next one's
//! first), so all four kinds draw about the same hair.

use bvhtrace_core::curves::{CurveKind, Curves, bspline_to_bezier};
use glam::{Mat4, Vec3, Vec4};

use crate::builtin::{Rng, icosphere};
use crate::error::{ErrorKind, SceneError};
use crate::{Camera, Instance, Material, Scene};

/// Strands when the spec does not say.
pub const DEFAULT_STRANDS: u32 = 10_000;
/// Control points of a strand's polyline.
const POINTS: usize = 10;

/// True when `spec` names a scene with curves (`builtin:hair...`), which a renderer
/// traces with the tree that holds curves ([`bvhtrace_core::CurveBvh`]).
pub fn has_curves(spec: &str) -> bool {
    spec == "builtin:hair" || spec.starts_with("builtin:hair:")
}

/// Parses `KIND[:N]` (after `hair:`; empty for the defaults) and makes the scene.
pub(crate) fn hair(rest: &str, spec: &str) -> Result<Scene, SceneError> {
    let bad = |msg: String| SceneError::new(spec, ErrorKind::Spec(msg));
    let mut parts = rest.split(':').filter(|p| !p.is_empty());
    let kind = match parts.next() {
        None => CurveKind::RoundBSpline,
        Some(k) => CurveKind::ALL
            .into_iter()
            .find(|c| c.name() == k)
            .ok_or_else(|| {
                let names: Vec<&str> = CurveKind::ALL.iter().map(|c| c.name()).collect();
                bad(format!("hair:{k}: KIND is one of {}", names.join(", ")))
            })?,
    };
    let strands = match parts.next() {
        None => DEFAULT_STRANDS,
        Some(n) => n
            .parse()
            .ok()
            .filter(|n| (1..=1_000_000).contains(n))
            .ok_or_else(|| bad(format!("hair: N must be 1 to 1,000,000 strands, got {n}")))?,
    };
    if let Some(extra) = parts.next() {
        return Err(bad(format!(
            "hair: unexpected {extra:?} after the strand count"
        )));
    }
    Ok(head_of_hair(kind, strands))
}

/// The strands' polylines, seeded, each `POINTS` points from a root on the unit head.
fn strands(n: u32) -> Vec<[Vec4; POINTS]> {
    let mut rng = Rng::new(0x4A1B_2C3D);
    (0..n)
        .map(|_| {
            // A root on the top and back of the head.
            let normal = loop {
                let v = Vec3::new(
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                );
                let l = v.length();
                if l > 1e-2 && l <= 1.0 && v.y / l > -0.1 && v.z / l < 0.6 {
                    break v / l;
                }
            };
            let length = rng.range(0.8, 1.3);
            let step = length / (POINTS - 1) as f32;
            let mut p = normal * 0.97;
            let mut dir = normal;
            std::array::from_fn(|i| {
                let radius = 0.012 * (1.0 - 0.7 * i as f32 / (POINTS - 1) as f32);
                let here = p.extend(radius);
                let wiggle = Vec3::new(
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                );
                dir = (dir + Vec3::new(0.0, -0.35, 0.0) + 0.15 * wiggle).normalize();
                p += dir * step;
                // Hair lies on the head: a point inside it is pushed out to its surface.
                if p.length() < 1.03 {
                    p = p.normalize() * 1.03;
                }
                here
            })
        })
        .collect()
}

/// The head (an icosphere) and `n` strands of `kind`.
fn head_of_hair(kind: CurveKind, n: u32) -> Scene {
    let mut points = Vec::new();
    let mut segments = Vec::new();
    for s in strands(n) {
        let first = points.len() as u32;
        match kind {
            CurveKind::RoundLinear | CurveKind::FlatLinear | CurveKind::RoundBSpline => {
                points.extend(s);
                let count = POINTS - kind.degree();
                segments.extend((0..count as u32).map(|i| first + i));
            }
            CurveKind::RoundBezier => {
                // The B-spline's segments in Bezier form, chained.
                points.push(bspline_to_bezier([s[0], s[1], s[2], s[3]])[0]);
                for i in 0..POINTS - 3 {
                    segments.push(first + 3 * i as u32);
                    points.extend_from_slice(
                        &bspline_to_bezier([s[i], s[i + 1], s[i + 2], s[i + 3]])[1..],
                    );
                }
            }
        }
    }
    let mut head = icosphere(3);
    head.name = "head".into();
    head.materials = vec![0; head.len()];
    let curves = Curves {
        kind,
        points,
        segments,
    };
    Scene {
        name: format!("hair:{}:{n}", kind.name()),
        description: format!(
            "synthetic hair: {n} strands of {} curves ({} segments) on a head of {} triangles",
            kind.name(),
            curves.len(),
            head.len()
        ),
        synthetic: true,
        meshes: vec![head],
        instances: vec![Instance {
            mesh: 0,
            transform: Mat4::IDENTITY,
        }],
        materials: vec![Material::opaque("skin", Vec4::new(0.85, 0.65, 0.55, 1.0))],
        camera: Some(Camera {
            eye: Vec3::new(2.8, 1.3, 4.6),
            target: Vec3::new(0.0, 0.1, 0.0),
            fov_y_deg: 40.0,
        }),
        curves: Some(curves),
        ..Scene::default()
    }
}
