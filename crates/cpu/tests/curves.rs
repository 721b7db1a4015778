//! Curves in the CPU layout answer as the core's curve walk (`CurveBvh::trace`): closest
//! hits bit for bit, any hits a hit where the closest is, on every instruction set, for
//! every kind of curve, with triangles beside them.

mod common;

use std::sync::Arc;

use bvhtrace_core::{BuildOptions, BuilderKind, CurveBvh, CurveKind, Curves, Hit, Query, Ray};
use bvhtrace_cpu::{CurveCpuBvh, Isa};
use common::{rays_for, same, uv_sphere, xorshift};
use glam::Vec3;

/// Every instruction set's answers, equal to the bit, and the first of them.
fn every_isa(bvh: &CurveCpuBvh, rays: &[Ray], q: Query) -> Vec<Hit> {
    let isas = Isa::all_available();
    let first = bvh.trace_rays_with(rays, q, isas[0]);
    for &isa in &isas[1..] {
        let h = bvh.trace_rays_with(rays, q, isa);
        for (i, (a, b)) in first.iter().zip(&h).enumerate() {
            assert!(
                same(a, b),
                "{isa} differs on ray {i} {:?}: {b:?} vs {a:?}",
                rays[i]
            );
        }
    }
    first
}

/// Checks the layout of `bvh` against the core walk on `rays`; returns the closest hits
/// found.
fn check(bvh: CurveBvh, rays: &[Ray]) -> usize {
    let bvh = Arc::new(bvh);
    let layout = CurveCpuBvh::from_curves(bvh.clone()).expect("converted");
    let want = bvh.trace_rays(rays, Query::Closest);
    let got = every_isa(&layout, rays, Query::Closest);
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(
            same(g, w),
            "ray {i} {:?}: {g:?}, the core walk {w:?}",
            rays[i]
        );
    }
    let any = every_isa(&layout, rays, Query::Any);
    for (i, (a, g)) in any.iter().zip(&got).enumerate() {
        assert_eq!(a.is_hit(), g.is_hit(), "ray {i} {:?}: any {a:?}", rays[i]);
        // An any hit is a hit of the tree: the prim it names is hit at its `t`.
        if a.is_hit() {
            assert!(
                a.t >= rays[i].t_min && a.t <= rays[i].t_max,
                "ray {i}: {a:?}"
            );
        }
    }
    got.iter().filter(|h| h.is_hit()).count()
}

/// Strands of `kind` in a ball around a sphere of triangles: `n` strands of `segs`
/// segments each, radii from `r0` at the root to a tenth of it at the tip.
fn ball(kind: CurveKind, n: usize, segs: usize, r0: f32, seed: u64) -> (Vec<[Vec3; 3]>, Curves) {
    let mut rnd = xorshift(seed | 1);
    let mut points = Vec::new();
    let mut segments = Vec::new();
    let per = segs * kind.degree() + 1;
    for _ in 0..n {
        let d = Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5).normalize_or(Vec3::Y);
        let bend = Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5) * 0.4;
        let first = points.len() as u32;
        for k in 0..per {
            let s = k as f32 / (per - 1) as f32;
            let p = d * (1.0 + 0.8 * s) + bend * s * s;
            points.push(p.extend(r0 * (1.0 - 0.9 * s)));
        }
        for s in 0..segs {
            segments.push(first + (s * kind.degree()) as u32);
        }
    }
    let tris = uv_sphere(12, 0.95, Vec3::ZERO);
    (
        tris,
        Curves {
            kind,
            points,
            segments,
        },
    )
}

/// Rays at the ball from around it, rays from inside it, rays along the axes, and rays
/// aimed at control points (which graze the strands).
fn rays_at(tris: &[[Vec3; 3]], curves: &Curves, seed: u64) -> Vec<Ray> {
    let mut rays = rays_for(tris, seed, 1500);
    let mut rnd = xorshift(seed ^ 0x9e37_79b9);
    for p in curves.points.iter().step_by(3) {
        let from = Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5) * 8.0;
        let to = p.truncate() + Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5) * 2.0 * p.w;
        rays.push(Ray::new(from, to - from));
    }
    rays
}

#[test]
fn every_kind_gives_the_core_walks_hits() {
    for (k, kind) in CurveKind::ALL.into_iter().enumerate() {
        let (tris, curves) = ball(kind, 400, 6, 0.02, 7 + k as u64);
        let rays = rays_at(&tris, &curves, 11 + k as u64);
        for builder in [BuilderKind::Sah, BuilderKind::Median] {
            let opts = BuildOptions {
                builder,
                ..BuildOptions::default()
            };
            let bvh = CurveBvh::build(&tris, curves.clone(), &opts).expect("built");
            let found = check(bvh, &rays);
            assert!(found > rays.len() / 4, "{kind:?} {builder:?}: {found} hits");
        }
    }
}

/// Long leaves (split into runs of wide slots), no triangles, and the stress suite's odd
/// strands: zero-length segments, radius 0, a radius far above the segment's length.
#[test]
fn long_leaves_and_odd_strands_give_the_core_walks_hits() {
    for kind in CurveKind::ALL {
        let (_, mut curves) = ball(kind, 60, 5, 0.05, 3);
        let n = curves.points.len();
        // Zero length: every control point of the first strand at one place.
        let p0 = curves.points[0];
        for p in &mut curves.points[..5 * kind.degree() + 1] {
            *p = p0;
        }
        // Radius 0 along the second strand, huge along the last.
        let per = 5 * kind.degree() + 1;
        for p in &mut curves.points[per..2 * per] {
            p.w = 0.0;
        }
        for p in &mut curves.points[n - per..] {
            p.w = 3.0;
        }
        let opts = BuildOptions {
            max_leaf_size: 200,
            cost_intersection: 1e6,
            ..BuildOptions::default()
        };
        let rays = rays_at(&uv_sphere(6, 2.0, Vec3::ZERO), &curves, 5);
        let bvh = CurveBvh::build(&[], curves.clone(), &opts).expect("built");
        let found = check(bvh, &rays);
        let bvh = CurveBvh::build(&[], curves, &BuildOptions::default()).expect("built");
        assert_eq!(check(bvh, &rays), found, "{kind:?}");
    }
}

/// A strand far from the origin, and one tiny strand: the core test's scaling, reached
/// through the layout's boxes.
#[test]
fn far_and_tiny_strands_give_the_core_walks_hits() {
    for (offset, scale) in [(Vec3::new(3.0e5, -2.0e5, 1.0e5), 1.0), (Vec3::ZERO, 1.0e-4)] {
        let (_, curves) = ball(CurveKind::RoundLinear, 50, 4, 0.05, 9);
        let moved = Curves {
            points: (curves.points.iter())
                .map(|p| (p.truncate() * scale + offset).extend(p.w * scale))
                .collect(),
            ..curves
        };
        let tri = uv_sphere(6, 2.0 * scale, offset);
        let rays = rays_at(&tri, &moved, 21);
        let bvh = CurveBvh::build(&[], moved, &BuildOptions::default()).expect("built");
        assert!(check(bvh, &rays) > 0);
    }
}

#[test]
fn the_layout_is_small_beside_the_primitives() {
    let (tris, curves) = ball(CurveKind::RoundBezier, 300, 4, 0.02, 1);
    let bvh = Arc::new(CurveBvh::build(&tris, curves, &BuildOptions::default()).expect("built"));
    let layout = CurveCpuBvh::from_curves(bvh.clone()).expect("converted");
    let (nodes, blocks) = layout.byte_sizes();
    let prims = bvh.triangle_count() + bvh.curves().len();
    // One node per leaf child of up to eight primitives: at most one per primitive.
    let node = std::mem::size_of::<bvhtrace_cpu::Node8>();
    assert!(
        blocks <= prims * node && blocks % node == 0,
        "{blocks} bytes of leaf nodes for {prims}"
    );
    assert!(
        nodes > 0 && layout.depth() >= 2,
        "{nodes} {}",
        layout.depth()
    );
    assert!(Arc::ptr_eq(layout.curves(), &bvh));
}
