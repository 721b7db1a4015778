//! The wide layout: its quantised boxes are conservative at any offset and scale (closed
//! meshes leak no ray), its lanes are the scalar box test's, it is smaller than the binary
//! upload, and the cost model tallies walks as documented.

use bvhtrace_core::cost::{BOX_TEST_TRIPS, WARP, warp_cost};
use bvhtrace_core::intersect::{PreparedRay, intersect_box};
use bvhtrace_core::wide::{WIDTH, hit_children};
use bvhtrace_core::{
    BuildOptions, FlatBvh, Query, Ray, TraceOptions, Traversal, Triangle, trace_ray, trace_rays,
};
use glam::Vec3;

mod common;

fn rnd(seed: &mut u64) -> f32 {
    *seed ^= *seed << 13;
    *seed ^= *seed >> 7;
    *seed ^= *seed << 17;
    (*seed >> 40) as f32 / (1u64 << 24) as f32
}

/// Rays from outside the sphere's box towards points inside it: every one must hit.
fn rays_into(c: Vec3, r: f32, n: usize) -> Vec<Ray> {
    let mut s = 0x9e37_79b9_7f4a_7c15;
    (0..n)
        .map(|_| {
            let d = Vec3::new(rnd(&mut s) - 0.5, rnd(&mut s) - 0.5, rnd(&mut s) - 0.5);
            let d = if d.length() < 1e-3 {
                Vec3::X
            } else {
                d.normalize()
            };
            let aim = c + Vec3::new(rnd(&mut s) - 0.5, rnd(&mut s) - 0.5, rnd(&mut s) - 0.5) * r;
            Ray::new(aim - d * (3.0 * r), d)
        })
        .collect()
}

/// No crack at offsets up to 1e7 and scales 1e-9..1e9: every ray aimed inside a closed
/// sphere hits it through the wide walk, and it hits what the binary full stack hits.
#[test]
fn closed_meshes_leak_no_ray_at_any_offset_and_scale() {
    let mut checked = 0;
    for scale in [1e-9f32, 1e-4, 1.0, 1e4, 1e9] {
        for offset in [0.0f32, 1.0, 1e4, 1e7] {
            // f32 cannot place a sphere far smaller than the spacing of its coordinates.
            if scale < offset * 1e-4 {
                continue;
            }
            let c = Vec3::new(offset, -0.5 * offset, 0.25 * offset);
            let tris = common::uv_sphere(10, scale, c);
            let bvh = FlatBvh::build(&tris, &BuildOptions::default())
                .unwrap()
                .with_wide();
            let wide = bvh.wide().unwrap();
            wide.check_invariants(&bvh).unwrap();
            let rays = rays_into(c, scale, 400);
            for q in [Query::Closest, Query::Any] {
                let got = trace_rays(&bvh, &rays, &TraceOptions::new(Traversal::Wide, q)).hits;
                let binary =
                    trace_rays(&bvh, &rays, &TraceOptions::new(Traversal::FullStack, q)).hits;
                for (i, (g, b)) in got.iter().zip(&binary).enumerate() {
                    assert!(
                        g.is_hit(),
                        "scale {scale}, offset {offset}: ray {i} escaped {:?}",
                        rays[i]
                    );
                    if q == Query::Closest {
                        assert_eq!(
                            (g.prim, g.t.to_bits()),
                            (b.prim, b.t.to_bits()),
                            "scale {scale}, offset {offset}, ray {i}"
                        );
                    }
                }
                checked += got.len();
            }
        }
    }
    assert_eq!(checked, 14 * 2 * 400);
}

/// Each lane of the eight-box test is exactly the scalar box test of the decoded box, on
/// rays of every octant and axis-parallel ones; the AVX2 version gives the same bits.
#[test]
fn lanes_are_the_scalar_box_test() {
    let tris = common::uv_sphere(16, 1.0, Vec3::ZERO);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())
        .unwrap()
        .with_wide();
    let wide = bvh.wide().unwrap();
    let mut s = 7u64;
    let mut rays = rays_into(Vec3::ZERO, 1.0, 300);
    rays.push(Ray::new(Vec3::new(-3.0, 0.1, 0.2), Vec3::X));
    rays.push(Ray::new(Vec3::new(0.1, 3.0, -0.0), -Vec3::Y));
    let mut hits = 0;
    for ray in &rays {
        let r = PreparedRay::new(ray);
        for node in &wide.nodes {
            let t_best = if rnd(&mut s) < 0.5 {
                f32::INFINITY
            } else {
                2.0 * rnd(&mut s) + 1.0
            };
            let oct = bvhtrace_core::flat::octant(r.dir);
            let (mask, first) = hit_children(node, &r, t_best, oct);
            let mut want = 0u32;
            let mut nearest: Option<(f32, u32)> = None;
            for slot in 0..WIDTH {
                if !node.is_used(slot) {
                    continue;
                }
                let (lo, hi) = node.child_box(slot);
                if let Some(t) = intersect_box(&r, lo, hi, t_best) {
                    let j = (slot ^ oct) as u32;
                    want |= 1 << j;
                    if nearest.is_none_or(|(tn, jn)| t < tn || (t == tn && j < jn)) {
                        nearest = Some((t, j));
                    }
                }
            }
            assert_eq!(mask, want, "{ray:?}");
            assert_eq!(first, nearest.map_or(32, |n| n.1), "{ray:?}");
            hits += mask.count_ones();
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: AVX2 was just detected.
                let (m, f, used) =
                    unsafe { bvhtrace_core::wide::hit_children_avx2(node, &r, t_best, oct) };
                assert_eq!((m, f, used), (mask, first, node.used_mask()), "{ray:?}");
            }
        }
    }
    assert!(hits > 1000, "only {hits} child hits");
}

/// The wide upload is at most 0.6 times the binary full-stack one (nodes and triangles).
#[test]
fn wide_layout_is_smaller_than_the_binary_one() {
    let tris = common::uv_sphere(60, 1.0, Vec3::ZERO);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())
        .unwrap()
        .with_wide();
    let (wn, wt) = bvh.wide().unwrap().byte_sizes();
    let (bn, _, bt) = bvh.byte_sizes();
    let ratio = (wn + wt) as f64 / (bn + bt) as f64;
    assert!(ratio <= 0.6, "wide/binary bytes {ratio:.3}");
}

/// Leaves bigger than a wide leaf can hold are split, and every triangle is still found.
#[test]
fn big_binary_leaves_are_split_into_wide_leaves() {
    let tris = common::uv_sphere(8, 1.0, Vec3::ZERO);
    let opts = BuildOptions {
        max_leaf_size: 200,
        cost_intersection: 1e-6,
        ..BuildOptions::default()
    };
    let bvh = FlatBvh::build(&tris, &opts).unwrap().with_wide();
    assert!(
        bvh.nodes().len() < 4,
        "expected one big leaf, got {} nodes",
        bvh.nodes().len()
    );
    bvh.wide().unwrap().check_invariants(&bvh).unwrap();
    for ray in rays_into(Vec3::ZERO, 1.0, 200) {
        let w = trace_ray(&bvh, &ray, &TraceOptions::closest(Traversal::Wide)).0;
        let b = trace_ray(&bvh, &ray, &TraceOptions::closest(Traversal::FullStack)).0;
        assert_eq!((w.prim, w.t.to_bits()), (b.prim, b.t.to_bits()));
    }
}

/// The cost model: a warp of identical rays is fully used; mixing hits and misses in one
/// warp lowers the utilisation; bytes follow the documented sizes.
#[test]
fn warp_cost_counts_lock_step_and_bytes() {
    let tris = common::uv_sphere(12, 1.0, Vec3::ZERO);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())
        .unwrap()
        .with_wide();
    let hit = Ray::new(Vec3::new(0.1, 0.2, -5.0), Vec3::Z);
    let miss = Ray::new(Vec3::new(5.0, 5.0, -5.0), Vec3::Z);
    for walk in [Traversal::FullStack, Traversal::Stackless, Traversal::Wide] {
        let opts = TraceOptions::closest(walk);
        let same = warp_cost(&bvh, &vec![hit; WARP], &opts);
        assert_eq!(same.warps, 1);
        assert!(
            (same.lane_utilisation - 1.0).abs() < 1e-12,
            "{walk}: {same:?}"
        );
        assert_eq!(same.trips_per_warp, same.trips_per_ray);
        // Every lane alike: the warp's work is one lane's trips and weighted box tests.
        let work = same.trips_per_ray + BOX_TEST_TRIPS * same.nodes_per_ray;
        assert!((same.work_per_warp - work).abs() < 1e-9, "{walk}: {same:?}");
        let mixed: Vec<Ray> = (0..WARP)
            .map(|i| if i % 2 == 0 { hit } else { miss })
            .collect();
        let m = warp_cost(&bvh, &mixed, &opts);
        assert!(m.lane_utilisation < 0.9, "{walk}: {m:?}");
        assert!(m.trips_per_warp >= m.trips_per_ray);
        let mean_work = m.trips_per_ray + BOX_TEST_TRIPS * m.nodes_per_ray;
        assert!(
            m.work_per_warp > mean_work,
            "{walk}: the slowest lane's, not the mean"
        );
        assert_eq!(m.triangle_bytes_per_ray, 48.0 * m.tris_per_ray);
        if walk == Traversal::FullStack {
            assert_eq!(m.node_bytes_per_ray, 32.0 * m.nodes_per_ray);
        }
        if walk == Traversal::Wide {
            // One 80-byte node per group of up to eight box tests.
            assert!(m.node_bytes_per_ray >= 80.0 * m.nodes_per_ray / 8.0);
            assert!(m.node_bytes_per_ray < 80.0 * m.nodes_per_ray);
        }
    }
}

/// A chain 400 nodes deep (each node a wall and the rest of the chain) hit end to end: the
/// wide walk holds more groups than its local stack and spills, and stays exact.
#[test]
fn deep_chains_spill_the_group_stack_and_stay_exact() {
    use bvhtrace_core::Aabb;
    use bvhtrace_core::build::{BuildNode, BuildTree};
    let n = 400u32;
    let tris: Vec<Triangle> = (0..n)
        .map(|i| {
            let x = i as f32;
            [
                Vec3::new(x, -1.0, -1.0),
                Vec3::new(x, 1.0, -1.0),
                Vec3::new(x, 0.0, 1.0),
            ]
        })
        .collect();
    let bounds = |range: std::ops::Range<u32>| {
        range
            .map(|i| Aabb::from_triangle(&tris[i as usize]))
            .fold(Aabb::EMPTY, |a, b| a.union(&b))
    };
    let mut node = BuildNode::Leaf {
        bounds: bounds(n - 1..n),
        first: n - 1,
        count: 1,
    };
    for k in (0..n - 1).rev() {
        node = BuildNode::Interior {
            bounds: bounds(k..n),
            axis: 0,
            children: Box::new([
                BuildNode::Leaf {
                    bounds: bounds(k..k + 1),
                    first: k,
                    count: 1,
                },
                node,
            ]),
        };
    }
    let tree = BuildTree {
        root: node,
        prim_order: (0..n).collect(),
        node_count: 2 * n as usize - 1,
    };
    let bvh = FlatBvh::flatten(&tree, &tris).with_wide();
    let wide = bvh.wide().unwrap();
    wide.check_invariants(&bvh).unwrap();
    assert!(wide.depth > 40, "wide depth {}", wide.depth);
    // From beyond the far end, towards the start: the nearest child of every node is the
    // rest of the chain, so each level pushes its walls.
    let rays = [
        Ray::new(Vec3::new(1000.0, 0.1, 0.0), -Vec3::X),
        Ray::new(Vec3::new(-5.0, 0.1, 0.0), Vec3::X),
        Ray::with_interval(Vec3::new(1000.0, 0.1, 0.0), -Vec3::X, 0.0, 700.5),
    ];
    for ray in rays {
        for q in [Query::Closest, Query::Any] {
            let (w, c) = trace_ray(&bvh, &ray, &TraceOptions::new(Traversal::Wide, q));
            let (b, _) = trace_ray(&bvh, &ray, &TraceOptions::new(Traversal::FullStack, q));
            assert_eq!(w.is_hit(), b.is_hit(), "{q:?} {ray:?}");
            if q == Query::Closest {
                assert_eq!((w.prim, w.t.to_bits()), (b.prim, b.t.to_bits()), "{ray:?}");
            }
            assert!(c.nodes > 0);
        }
    }
    // Tested: the closest walk from the far end visits every wall.
    let (_, c) = trace_ray(&bvh, &rays[0], &TraceOptions::closest(Traversal::Wide));
    assert_eq!(c.tris, n, "every wall is tested once");
}
