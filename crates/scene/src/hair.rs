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

/// True when `spec` names a scene with curves (`builtin:hair...`, a `.hair` file), which
/// a renderer traces with the tree that holds curves ([`bvhtrace_core::CurveBvh`]).
pub fn has_curves(spec: &str) -> bool {
    let base = spec.split('#').next().unwrap_or(spec);
    let tubes = base.starts_with("builtin:hair:tubes");
    let builtin = base == "builtin:hair" || (base.starts_with("builtin:hair:") && !tubes);
    builtin || base.to_ascii_lowercase().ends_with(".hair")
}

/// The bits of a `.hair` header's field of arrays: segments, points, thickness,
/// transparency, colour.
const HAIR_SEGMENTS: u32 = 1;
const HAIR_POINTS: u32 = 2;
const HAIR_THICKNESS: u32 = 4;
const HAIR_TRANSPARENCY: u32 = 8;
const HAIR_COLOR: u32 = 16;
/// The header's size in bytes.
const HAIR_HEADER: usize = 128;

/// Loads a `.hair` file (Cem Yuksel's format: a 128-byte header, then per-strand segment
/// counts, points, and per-point thickness, transparency and colour, each optional) as a
/// scene of round linear strands, each point's radius half its thickness. A scene with
/// curves and no triangles; the camera frames it.
pub fn load_hair_file(path: &std::path::Path) -> Result<Scene, SceneError> {
    let label = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| {
        SceneError::new(
            &label,
            ErrorKind::Io {
                what: "cannot read the file".into(),
                source,
            },
        )
    })?;
    let curves = parse_hair(&bytes).map_err(|e| SceneError::new(&label, e))?;
    let name = path
        .file_stem()
        .map_or("hair".into(), |s| s.to_string_lossy().into_owned());
    let scene = Scene {
        description: format!(
            "{name}: {} round linear curve segments from a .hair file",
            curves.len()
        ),
        name,
        curves: Some(curves),
        ..Scene::default()
    };
    scene.finish(&label)
}

/// Cem Yuksel's `.hair` format from `bytes`: its strands as round linear curves.
fn parse_hair(bytes: &[u8]) -> Result<Curves, ErrorKind> {
    if bytes.len() < HAIR_HEADER || &bytes[..4] != b"HAIR" {
        let found = String::from_utf8_lossy(&bytes[..bytes.len().min(4)]).into_owned();
        return Err(ErrorKind::Hair(format!(
            "no HAIR magic and 128-byte header (found {found:?})"
        )));
    }
    let word =
        |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
    let (strands, total, arrays, default_segments) = (word(4), word(8), word(12), word(16));
    let default_thickness = f32::from_bits(word(20));
    if arrays & HAIR_POINTS == 0 {
        return Err(ErrorKind::Hair("the file has no points array".into()));
    }
    let per_point = |bit: u32, floats: u64| if arrays & bit != 0 { floats } else { 0 };
    let floats =
        per_point(HAIR_THICKNESS, 1) + per_point(HAIR_TRANSPARENCY, 1) + per_point(HAIR_COLOR, 3);
    let need = HAIR_HEADER as u64
        + per_point(HAIR_SEGMENTS, 2) * u64::from(strands)
        + u64::from(total) * (12 + 4 * floats);
    if (bytes.len() as u64) < need {
        return Err(ErrorKind::Truncated(format!(
            "{strands} strands of {total} points need {need} bytes, the file has {}",
            bytes.len()
        )));
    }
    if strands > total {
        return Err(ErrorKind::Hair(format!(
            "{strands} strands cannot share {total} points"
        )));
    }
    let mut at = HAIR_HEADER;
    let counts: Vec<u32> = match arrays & HAIR_SEGMENTS {
        0 => vec![default_segments; strands as usize],
        _ => (0..strands as usize)
            .map(|i| {
                u32::from(u16::from_le_bytes([
                    bytes[at + 2 * i],
                    bytes[at + 2 * i + 1],
                ]))
            })
            .collect(),
    };
    if arrays & HAIR_SEGMENTS != 0 {
        at += 2 * strands as usize;
    }
    let used: u64 = counts.iter().map(|&c| u64::from(c) + 1).sum();
    if used != u64::from(total) {
        return Err(ErrorKind::Hair(format!(
            "the strands' segments need {used} points, the header says {total}"
        )));
    }
    let float = |i: usize| f32::from_bits(word(i));
    let pts = at;
    let thick = pts + 12 * total as usize;
    let points: Vec<Vec4> = (0..total as usize)
        .map(|i| {
            let p = Vec3::new(
                float(pts + 12 * i),
                float(pts + 12 * i + 4),
                float(pts + 12 * i + 8),
            );
            let t = match arrays & HAIR_THICKNESS {
                0 => default_thickness,
                _ => float(thick + 4 * i),
            };
            p.extend(0.5 * t)
        })
        .collect();
    let mut segments = Vec::with_capacity(total as usize);
    let mut first = 0u32;
    for c in counts {
        segments.extend(first..first + c);
        first += c + 1;
    }
    Ok(Curves {
        kind: CurveKind::RoundLinear,
        points,
        segments,
    })
}

/// `curves`' strands (runs of linear segments that share points; a cubic segment's
/// control points alone) in Cem Yuksel's `.hair` format, with a thickness per point (twice
/// its radius) and no transparency or colour. Strands of more than 65,535 segments are
/// split.
pub fn hair_file_bytes(curves: &Curves) -> Vec<u8> {
    // Each strand as its points' range.
    let mut strands: Vec<(usize, usize)> = Vec::new();
    for s in 0..curves.len() {
        let first = curves.segments[s] as usize;
        let d = curves.kind.degree();
        let continues = d == 1 && curves.neighbours(s).0;
        match strands.last_mut() {
            Some((start, end)) if continues && *end - *start < 65_535 => *end = first + d,
            _ => strands.push((first, first + d)),
        }
    }
    let total: usize = strands.iter().map(|(a, b)| b - a + 1).sum();
    let mut out = Vec::with_capacity(HAIR_HEADER + 2 * strands.len() + 16 * total);
    out.extend_from_slice(b"HAIR");
    for v in [
        strands.len() as u32,
        total as u32,
        HAIR_SEGMENTS | HAIR_POINTS | HAIR_THICKNESS,
        0,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for f in [0.0f32, 1.0, 1.0, 1.0, 1.0] {
        out.extend_from_slice(&f.to_le_bytes());
    }
    out.resize(HAIR_HEADER, 0);
    for (a, b) in &strands {
        out.extend_from_slice(&((b - a) as u16).to_le_bytes());
    }
    let points = || strands.iter().flat_map(|&(a, b)| &curves.points[a..=b]);
    for p in points() {
        for c in p.truncate().to_array() {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    for p in points() {
        out.extend_from_slice(&(2.0 * p.w).to_le_bytes());
    }
    out
}

/// Parses `KIND[:N]` (after `hair:`; empty for the defaults) and makes the scene.
pub(crate) fn hair(rest: &str, spec: &str) -> Result<Scene, SceneError> {
    let bad = |msg: String| SceneError::new(spec, ErrorKind::Spec(msg));
    let mut parts = rest.split(':').filter(|p| !p.is_empty());
    // `None`: the round linear strands as tubes of triangles.
    let kind = match parts.next() {
        None => Some(CurveKind::RoundBSpline),
        Some("tubes") => None,
        Some(k) => Some(
            CurveKind::ALL
                .into_iter()
                .find(|c| c.name() == k)
                .ok_or_else(|| {
                    let names: Vec<&str> = CurveKind::ALL.iter().map(|c| c.name()).collect();
                    bad(format!(
                        "hair:{k}: KIND is one of {} or tubes",
                        names.join(", ")
                    ))
                })?,
        ),
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
    Ok(match kind {
        Some(kind) => head_of_hair(kind, strands),
        None => head_of_tubes(strands),
    })
}

/// Sides of a strand's tube in `hair:tubes`.
const TUBE_SIDES: usize = 8;

/// `hair:tubes:N`: the head and the round linear strands of `hair:round-linear:N` as
/// tubes of triangles, `TUBE_SIDES` sides around each point (the same strands as curves
/// and as triangles, for comparing the two).
fn head_of_tubes(n: u32) -> Scene {
    let mut scene = head_of_hair(CurveKind::RoundLinear, n);
    let Some(curves) = scene.curves.take() else {
        return scene;
    };
    let mut tubes = crate::Mesh {
        name: "strands".into(),
        ..Default::default()
    };
    for strand in curves.points.chunks(POINTS) {
        let first = tubes.positions.len() as u32;
        for (i, p) in strand.iter().enumerate() {
            let (a, b) = (strand[i.saturating_sub(1)], strand[(i + 1).min(POINTS - 1)]);
            let tangent = (b - a).truncate().normalize_or(Vec3::Y);
            let across = tangent.any_orthonormal_vector();
            let up = tangent.cross(across);
            tubes.positions.extend((0..TUBE_SIDES).map(|k| {
                let angle = k as f32 * std::f32::consts::TAU / TUBE_SIDES as f32;
                p.truncate() + p.w * (angle.cos() * across + angle.sin() * up)
            }));
        }
        for i in 0..POINTS as u32 - 1 {
            for k in 0..TUBE_SIDES as u32 {
                let ring = |i: u32, k: u32| first + i * TUBE_SIDES as u32 + k % TUBE_SIDES as u32;
                let (a, b) = (ring(i, k), ring(i, k + 1));
                let (c, d) = (ring(i + 1, k), ring(i + 1, k + 1));
                tubes.indices.extend([[a, b, d], [a, d, c]]);
            }
        }
    }
    tubes.materials = vec![0; tubes.indices.len()];
    let (segments, triangles) = (curves.len(), tubes.indices.len());
    scene.meshes.push(tubes);
    scene.instances.push(Instance {
        mesh: 1,
        transform: Mat4::IDENTITY,
    });
    scene.name = format!("hair:tubes:{n}");
    scene.description = format!(
        "synthetic hair as triangles: the {segments} round linear segments of {n} strands as {TUBE_SIDES}-sided tubes ({triangles} triangles) on a head"
    );
    scene
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
