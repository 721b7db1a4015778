//! The curve cases (`curves-*`), one for each kind of curve: straight strands whose
//! segments have known answers (a ray aimed at a segment's axis from beside it hits that
//! segment; one passing at 2.5 radii misses), two triangles under them (rays between the
//! strands hit the triangle below), and the strands Embree's users make by accident:
//! zero-length segments, radius 0, a radius 50 times a segment's length, rays along a
//! strand, and a camera. There is no f64 oracle for curves: the runner holds every walk to
//! the known answers, the output contract and the tree's brute force.

use bvhtrace_core::{CurveKind, Curves, Ray, Triangle};
use glam::Vec3;

use crate::cases::quick;
use crate::geom::camera_rays;
use crate::{Case, Expect, Size};

/// A strand's segments' radius in the grid of strands.
const RADIUS: f32 = 0.1;

/// Every `curves-*` case.
pub(crate) fn curve_cases(size: Size) -> Vec<Case> {
    CurveKind::ALL
        .iter()
        .map(|&k| curve_case(k, size))
        .collect()
}

/// Curves of one kind, strand by strand.
struct Strands(Curves);

impl Strands {
    /// A straight strand of `n` segments from `a`, each `d` long, radius `r` at every
    /// control point: its segments' indices. Cubic control points are spaced so that the
    /// curve runs at constant speed and segment `k` covers `a + [k, k + 1] d`.
    fn straight(&mut self, a: Vec3, d: Vec3, n: u32, r: f32) -> std::ops::Range<u32> {
        let c = &mut self.0;
        let (first_seg, base) = (c.segments.len() as u32, c.points.len() as u32);
        let at = |s: f32| (a + s * d).extend(r);
        match c.kind {
            CurveKind::RoundLinear | CurveKind::FlatLinear => {
                c.points.extend((0..=n).map(|k| at(k as f32)));
                c.segments.extend((0..n).map(|k| base + k));
            }
            CurveKind::RoundBezier => {
                c.points.extend((0..=3 * n).map(|k| at(k as f32 / 3.0)));
                c.segments.extend((0..n).map(|k| base + 3 * k));
            }
            CurveKind::RoundBSpline => {
                c.points.extend((0..n + 3).map(|k| at(k as f32 - 1.0)));
                c.segments.extend((0..n).map(|k| base + k));
            }
        }
        first_seg..first_seg + n
    }
}

/// A ray from `o` along `d` up to `t_max`.
fn ray(o: Vec3, d: Vec3, t_max: f32) -> Ray {
    Ray {
        t_max,
        ..Ray::new(o, d)
    }
}

/// The case of `kind`.
fn curve_case(kind: CurveKind, size: Size) -> Case {
    let mut c = Case::new(
        format!("curves-{}", kind.name()),
        format!(
            "{} curves: straight strands (radius {RADIUS}) with rays at each segment and past it, two triangles under them, zero-length segments, radius 0, radius 50 on a segment 1 long, rays along the strands, a camera",
            kind.name()
        ),
    );
    let mut strands = Strands(Curves {
        kind,
        points: Vec::new(),
        segments: Vec::new(),
    });
    let (grid, segs) = if quick(size) { (3, 3) } else { (8, 6) };
    ground(&mut c, grid, segs);
    grid_of_strands(&mut c, &mut strands, grid, segs);
    degenerate_strands(&mut c, &mut strands);
    let (w, h) = if quick(size) { (24, 24) } else { (96, 96) };
    let mid = glam::DVec3::new(grid as f64 / 2.0, segs as f64 / 2.0, grid as f64 / 2.0);
    let eye = mid + glam::DVec3::new(0.5, 1.0, -(grid as f64) - 3.0);
    c.push_rays(camera_rays(eye, mid, 50.0, w, h), Expect::Unspecified);
    c.curves = Some(strands.0);
    c
}

/// The two triangles under the grid (`y = -0.5`), and rays straight down between the
/// strands onto them: triangle 0 holds the points with `x >= z`, triangle 1 the others.
fn ground(c: &mut Case, grid: u32, segs: u32) {
    let (lo, hi, y) = (-0.5, grid as f32 - 0.5, -0.5);
    let p = |x: f32, z: f32| Vec3::new(x, y, z);
    let quad: [Triangle; 2] = [
        [p(lo, lo), p(hi, lo), p(hi, hi)],
        [p(lo, lo), p(hi, hi), p(lo, hi)],
    ];
    c.tris.extend(quad);
    let down = Vec3::new(0.0, -1.0, 0.0);
    for i in 0..grid - 1 {
        for j in 0..grid {
            let (x, z) = (i as f32 + 0.5, j as f32 + 0.25);
            let r = ray(Vec3::new(x, segs as f32 + 1.0, z), down, f32::INFINITY);
            c.push_rays([r], Expect::Prim(if x >= z { 0 } else { 1 }));
        }
    }
}

/// A grid of vertical strands one unit apart, `segs` segments each: rays at each
/// segment's axis from half a unit away (straight, tilted, from behind, with 1e-30
/// components) hit it; rays passing 2.5 radii from the axis miss; rays along the axes
/// and grazing them have no known answer.
fn grid_of_strands(c: &mut Case, strands: &mut Strands, grid: u32, segs: u32) {
    let first = c.tris.len() as u32;
    let up = Vec3::Y;
    for i in 0..grid {
        for j in 0..grid {
            let foot = Vec3::new(i as f32, 0.0, j as f32);
            let ids = strands.straight(foot, up, segs, RADIUS);
            for (k, s) in ids.enumerate() {
                let target = foot + Vec3::new(0.0, k as f32 + 0.5, 0.0);
                let hit = Expect::Prim(first + s);
                for d in [
                    Vec3::Z,
                    Vec3::new(0.3, 0.2, 1.0),
                    Vec3::new(-0.2, -0.3, -1.0),
                    Vec3::new(1e-30, -1e-30, 1.0),
                ] {
                    c.push_rays([ray(target - 0.5 * d, d, 1.0)], hit);
                }
                let past = Vec3::new(2.5 * RADIUS, 0.0, 0.0);
                for d in [Vec3::Z, Vec3::new(0.0, 0.2, 1.0)] {
                    c.push_rays([ray(target + past - 0.5 * d, d, 1.0)], Expect::Miss);
                }
            }
            // Along the axis and grazing it, from below the strand's foot.
            for off in [Vec3::ZERO, Vec3::new(RADIUS, 0.0, 0.0)] {
                let r = ray(foot + off - 0.25 * up, up, segs as f32 + 1.0);
                c.push_rays([r], Expect::Unspecified);
            }
        }
    }
}

/// Far to the side of the grid: zero-length segments, radius 0, both, and a radius 50
/// on a segment 1 long, each with rays at it (no known answer where the surface is
/// degenerate) and past it (misses), and rays at the huge one's side (hits).
fn degenerate_strands(c: &mut Case, strands: &mut Strands) {
    let first = c.tris.len() as u32;
    let z = Vec3::Z;
    let at = |p: Vec3| ray(p - 0.5 * z, z, 1.0);
    // Zero length, radius 0.1: at it unknown, 0.3 away a miss.
    let p = Vec3::new(100.0, 0.0, 0.0);
    strands.straight(p, Vec3::ZERO, 2, RADIUS);
    c.push_rays([at(p)], Expect::Unspecified);
    c.push_rays([at(p + Vec3::new(0.3, 0.0, 0.0))], Expect::Miss);
    // Radius 0: at its axis unknown, 0.05 away a miss.
    let p = Vec3::new(102.0, 0.0, 0.0);
    strands.straight(p, Vec3::Y, 2, 0.0);
    for y in [0.5, 1.0, 1.5] {
        c.push_rays([at(p + Vec3::new(0.0, y, 0.0))], Expect::Unspecified);
        c.push_rays([at(p + Vec3::new(0.05, y, 0.0))], Expect::Miss);
    }
    // Zero length and radius 0.
    let p = Vec3::new(104.0, 0.0, 0.0);
    strands.straight(p, Vec3::ZERO, 1, 0.0);
    c.push_rays([at(p)], Expect::Unspecified);
    // Radius 50 on a segment 1 long: from the side, at the axis and 30 off it, a hit;
    // 60 off it a miss; along the axis unknown.
    let p = Vec3::new(1000.0, 0.0, 0.0);
    let s = strands.straight(p, Vec3::Y, 1, 50.0).start;
    let side = |dx: f32| ray(p + Vec3::new(dx, 0.5, -200.0), z, 400.0);
    c.push_rays(
        [side(0.0), side(30.0), side(-30.0)],
        Expect::Prim(first + s),
    );
    c.push_rays([side(60.0)], Expect::Miss);
    let along = ray(p - Vec3::new(0.0, 200.0, 0.0), Vec3::Y, 400.0);
    c.push_rays([along], Expect::Unspecified);
}
