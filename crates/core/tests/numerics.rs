//! Numerical robustness of the tests and traversals.

use bvhtrace_core::intersect::{PreparedRay, intersect_box};
use bvhtrace_core::*;
use glam::Vec3;

#[path = "../../../tests/support/rays.rs"]
mod support_rays;
use support_rays::{edge_rays, scaled};

const TRAVERSALS: [Traversal; 4] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(1),
    Traversal::ShortStack(6),
];

/// A closed icosphere (shared vertices) of radius `r` around `c`.
fn icosphere(subdiv: u32, c: Vec3, r: f32) -> Vec<Triangle> {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut v: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut f: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdiv {
        let mut mid = std::collections::HashMap::new();
        let mut m = |a: usize, b: usize, v: &mut Vec<Vec3>| {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a] + v[b]) * 0.5).normalize());
                v.len() - 1
            })
        };
        f = f
            .iter()
            .flat_map(|&[a, b, cc]| {
                let (ab, bc, ca) = (m(a, b, &mut v), m(b, cc, &mut v), m(cc, a, &mut v));
                [[a, ab, ca], [b, bc, ab], [cc, ca, bc], [ab, bc, ca]]
            })
            .collect();
    }
    f.iter().map(|t| t.map(|i| c + v[i] * r)).collect()
}

#[test]
fn no_ray_escapes_a_closed_mesh_at_any_scale_or_offset() {
    for (scale, offset) in [
        (1.0, 0.0),
        (1e-9, 0.0),
        (1e-3, 0.0),
        (1e4, 0.0),
        (1e9, 0.0),
        (1.0, 1e2),
        (1.0, 1e5),
        (1.0, 1e7),
    ] {
        let c = Vec3::new(offset, -offset * 0.5, offset * 0.25);
        let tris = icosphere(3, c, scale);
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
        // Inside points: the centre and an off-centre point.
        for from in [c, c + Vec3::new(0.3, -0.2, 0.1) * scale] {
            let rays = edge_rays(&tris, from);
            for tr in TRAVERSALS {
                let hits = trace_rays(&bvh, &rays, &TraceOptions::closest(tr)).hits;
                let escapes = hits.iter().filter(|h| !h.is_hit()).count();
                assert_eq!(
                    escapes,
                    0,
                    "scale {scale} offset {offset} {tr}: {escapes} of {} rays escaped",
                    rays.len()
                );
                assert!(
                    hits.iter()
                        .all(|h| h.t.is_finite() && !h.u.is_nan() && !h.v.is_nan())
                );
            }
        }
    }
}

/// A unit square in z = 0 split into two triangles.
fn unit_square() -> [Triangle; 2] {
    [
        [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
        ],
        [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ],
    ]
}

#[test]
fn axis_parallel_rays_with_signed_zeros_give_no_nan() {
    // A unit square in z = 0 split into two triangles, hit straight on, on its edges and corners.
    let tris = unit_square().to_vec();
    let bvh = FlatBvh::build(
        &tris,
        &BuildOptions {
            max_leaf_size: 1,
            ..Default::default()
        },
    )
    .unwrap();
    for &(x, y) in &[
        (0.5f32, 0.25f32),
        (0.0, 0.0),
        (1.0, 1.0),
        (0.5, 0.5),
        (0.0, 0.5),
        (1.0, 0.3),
    ] {
        for dir in [
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(-0.0, -0.0, 1.0),
            Vec3::new(-0.0, 0.0, 1.0),
        ] {
            let ray = Ray::new(Vec3::new(x, y, -2.0), dir);
            for tr in TRAVERSALS {
                let (h, _) = trace_ray(&bvh, &ray, &TraceOptions::closest(tr));
                assert!(h.is_hit(), "({x},{y}) {dir:?} {tr}");
                assert_eq!(h.t, 2.0);
                assert!(!h.u.is_nan() && !h.v.is_nan());
            }
        }
    }
    // Grazing: a ray in the square's plane never returns NaN.
    for tr in TRAVERSALS {
        let (h, _) = trace_ray(
            &bvh,
            &Ray::new(Vec3::new(-1.0, 0.5, 0.0), Vec3::X),
            &TraceOptions::closest(tr),
        );
        assert!(!h.t.is_nan());
    }
}

#[test]
fn box_test_is_conservative_on_boundaries_and_zero_directions() {
    let (lo, hi) = (Vec3::ZERO, Vec3::ONE);
    // Origin on the slab plane x = 0 with a zero x direction: inside (boundary included).
    for dx in [0.0f32, -0.0] {
        let r = PreparedRay::new(&Ray::new(
            Vec3::new(0.0, 0.5, -1.0),
            Vec3::new(dx, 0.0, 1.0),
        ));
        assert!(intersect_box(&r, lo, hi, f32::INFINITY).is_some());
        let r = PreparedRay::new(&Ray::new(
            Vec3::new(-1e-30, 0.5, -1.0),
            Vec3::new(dx, 0.0, 1.0),
        ));
        assert!(intersect_box(&r, lo, hi, f32::INFINITY).is_none());
    }
    // A flat box (zero thickness) is still hit.
    let r = PreparedRay::new(&Ray::new(Vec3::new(0.5, 0.5, -1.0), Vec3::Z));
    assert_eq!(
        intersect_box(
            &r,
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            f32::INFINITY
        ),
        Some(1.0)
    );
    // Tiny direction components work at any scale.
    let r = PreparedRay::new(&Ray::new(
        Vec3::new(-1.0, 0.5, 0.5),
        Vec3::new(1.0, 1e-30, -1e-30),
    ));
    assert!(
        intersect_box(
            &r,
            lo * 1e-9,
            hi * 1e-9 + Vec3::new(0.0, 1.0, 1.0),
            f32::INFINITY
        )
        .is_some()
    );
}

#[test]
fn degenerate_rays_have_defined_answers() {
    let tris = vec![[
        Vec3::new(-1.0, -1.0, 1.0),
        Vec3::new(1.0, -1.0, 1.0),
        Vec3::new(0.0, 1.0, 1.0),
    ]];
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let invalid = [
        Ray::new(Vec3::new(f32::NAN, 0.0, 0.0), Vec3::Z),
        Ray::new(Vec3::ZERO, Vec3::new(0.0, f32::INFINITY, 1.0)),
        Ray::new(Vec3::ZERO, Vec3::ZERO),
        Ray::with_interval(Vec3::ZERO, Vec3::Z, f32::NAN, 1.0),
    ];
    for tr in TRAVERSALS {
        for r in &invalid {
            let (h, c) = trace_ray(&bvh, r, &TraceOptions::closest(tr));
            assert_eq!(h.prim, INVALID_RAY);
            assert!(!h.t.is_nan() && c == Counters::default());
        }
        // t_min = t_max: the interval [t, t) is empty.
        let (h, _) = trace_ray(
            &bvh,
            &Ray::with_interval(Vec3::ZERO, Vec3::Z, 1.0, 1.0),
            &TraceOptions::closest(tr),
        );
        assert_eq!(h.prim, MISS);
        // The hit at exactly t_max is excluded, just past it included.
        let (h, _) = trace_ray(
            &bvh,
            &Ray::with_interval(Vec3::ZERO, Vec3::Z, 0.0, 1.0),
            &TraceOptions::closest(tr),
        );
        assert_eq!(h.prim, MISS);
        let (h, _) = trace_ray(
            &bvh,
            &Ray::with_interval(Vec3::ZERO, Vec3::Z, 1.0, 1.0000001),
            &TraceOptions::closest(tr),
        );
        assert_eq!((h.prim, h.t), (0, 1.0));
        // A direction component of 1e-30 is not zero.
        let (h, _) = trace_ray(
            &bvh,
            &Ray::new(Vec3::ZERO, Vec3::new(1e-30, -1e-30, 1.0)),
            &TraceOptions::closest(tr),
        );
        assert_eq!(h.prim, 0);
    }
}

#[test]
fn hits_scale_with_the_scene() {
    // Power-of-two scales are exact in f32: identical primitives and t scaled exactly.
    let tris = icosphere(4, Vec3::new(0.3, 0.1, -0.2), 1.0);
    let rays: Vec<Ray> = (0..2000)
        .map(|i| {
            let a = i as f32 * 0.7;
            Ray::new(
                Vec3::new(3.0 * a.cos(), (i % 13) as f32 * 0.1 - 0.6, 3.0 * a.sin()),
                Vec3::new(-a.cos(), 0.05, -a.sin()),
            )
        })
        .collect();
    let base = trace_rays(
        &FlatBvh::build(&tris, &BuildOptions::default()).unwrap(),
        &rays,
        &TraceOptions::closest(Traversal::Stackless),
    )
    .hits;
    for s in [2f32.powi(-30), 2f32.powi(-10), 2f32.powi(13), 2f32.powi(30)] {
        let (st, sr) = scaled(&tris, &rays, s);
        let bvh = FlatBvh::build(&st, &BuildOptions::default()).unwrap();
        let h = trace_rays(&bvh, &sr, &TraceOptions::closest(Traversal::Stackless)).hits;
        for (a, b) in base.iter().zip(&h) {
            assert_eq!(a.prim, b.prim, "scale {s}");
            assert_eq!(a.t * s, b.t, "scale {s}");
        }
    }
}

/// Regression: a hit behind the origin (negative `t_min`) on a box that is flat along the
/// ray. Scaling a negative exit distance by `BOX_TFAR_SCALE` moved it towards zero, so
/// `tnear > tfar` and the quad was culled on every traversal.
#[test]
fn hits_behind_the_origin_on_flat_boxes_are_found() {
    let quad = unit_square();
    let bvh = FlatBvh::build(&quad, &BuildOptions::default()).unwrap();
    // The flat box alone, behind the origin.
    let r = PreparedRay::new(&Ray::with_interval(
        Vec3::new(0.75, 0.25, 2.0),
        Vec3::Z,
        -2.0,
        0.0,
    ));
    assert_eq!(
        intersect_box(&r, Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0), 0.0),
        Some(-2.0)
    );
    for dir in [Vec3::Z, -Vec3::Z] {
        let org = Vec3::new(0.75, 0.25, 2.0 * dir.z);
        let ray = Ray::with_interval(org, dir, -2.0, 0.0);
        for traversal in TRAVERSALS {
            let (hit, _) = trace_ray(&bvh, &ray, &TraceOptions::closest(traversal));
            assert_eq!((hit.prim, hit.t), (0, -2.0), "{traversal:?} dir {dir}");
            let (hit, _) = trace_ray(&bvh, &ray, &TraceOptions::new(traversal, Query::Any));
            assert_ne!(hit.prim, MISS, "{traversal:?} any-hit dir {dir}");
        }
    }
}
