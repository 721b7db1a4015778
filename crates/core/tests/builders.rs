//! Builder invariants on random, degenerate and extreme inputs.

mod common;

use bvhtrace_core::*;
use glam::Vec3;
use proptest::prelude::*;

fn depth_bound(n: usize, opts: &BuildOptions) -> u32 {
    (opts.max_depth + (n as f64).log2().ceil() as usize + 1) as u32
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn every_builder_keeps_the_invariants(tris in common::soup(), bins in 2usize..48, leaf in 1usize..12) {
        for b in BuilderKind::ALL {
            let opts = BuildOptions { builder: b, bins, max_leaf_size: leaf, ..Default::default() };
            let bvh = FlatBvh::build(&tris, &opts).unwrap();
            prop_assert_eq!(bvh.check_invariants(), Ok(()), "builder {}", b);
            // One slot per triangle, but for the SBVH's references (within its budget).
            let refs = bvh.triangles().len();
            if b == BuilderKind::Sbvh {
                prop_assert!(refs >= tris.len() && refs as f64 <= tris.len() as f64 * (1.0 + f64::from(opts.split_budget)));
            } else {
                prop_assert_eq!(refs, tris.len());
            }
            prop_assert!(bvh.nodes().len() < 2 * refs);
            prop_assert!(bvh.depth() <= depth_bound(refs, &opts));
            for n in bvh.nodes() {
                prop_assert!((n.count() as usize) <= leaf);
            }
        }
    }
}

#[test]
fn leaves_respect_the_maximum_size() {
    let tris: Vec<Triangle> = (0..5000)
        .map(|i| {
            let p = Vec3::new((i % 17) as f32, (i % 31) as f32 * 0.5, (i / 100) as f32);
            [p, p + Vec3::X, p + Vec3::Y]
        })
        .collect();
    for b in BuilderKind::ALL {
        let opts = BuildOptions::with_builder(b);
        let bvh = FlatBvh::build(&tris, &opts).unwrap();
        bvh.check_invariants().unwrap();
        assert!(
            bvh.nodes()
                .iter()
                .all(|n| n.count() as usize <= opts.max_leaf_size),
            "{b}"
        );
    }
}

#[test]
fn identical_primitives_terminate_with_bounded_depth() {
    let t = [
        Vec3::new(1.0, 2.0, 3.0),
        Vec3::new(2.0, 2.0, 3.0),
        Vec3::new(1.0, 3.0, 3.0),
    ];
    let tris = vec![t; 100_000];
    for b in BuilderKind::ALL {
        let opts = BuildOptions::with_builder(b);
        let bvh = FlatBvh::build(&tris, &opts).unwrap();
        bvh.check_invariants().unwrap();
        // All centroids equal: only balanced splits are possible.
        assert!(bvh.depth() <= 17, "{b}: depth {}", bvh.depth());
    }
}

#[test]
fn zero_area_and_point_triangles_build() {
    let mut tris = Vec::new();
    for i in 0..3000 {
        let p = Vec3::new(i as f32 * 0.01, (i % 7) as f32, 0.0);
        tris.push([p, p, p]);
        tris.push([p, p + Vec3::X, p + 2.0 * Vec3::X]);
    }
    for b in BuilderKind::ALL {
        let bvh = FlatBvh::build(&tris, &BuildOptions::with_builder(b)).unwrap();
        bvh.check_invariants().unwrap();
    }
}

#[test]
fn bad_input_names_the_primitive() {
    let ok = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let mut tris = vec![ok; 10];
    tris[7][2].y = f32::NAN;
    let e = FlatBvh::build(&tris, &BuildOptions::default()).unwrap_err();
    assert!(e.to_string().contains("triangle 7"), "{e}");
    tris[7][2].y = f32::INFINITY;
    let e = FlatBvh::build(&tris, &BuildOptions::default()).unwrap_err();
    assert!(
        e.to_string().contains("triangle 7") && e.to_string().contains("corner 2"),
        "{e}"
    );

    let mesh = TriangleMesh {
        positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
        indices: vec![[0, 1, 2], [0, 1, 3]],
    };
    let e = mesh.triangles().unwrap_err();
    assert!(
        matches!(
            e,
            MeshError::IndexOutOfRange {
                triangle: 1,
                index: 3,
                vertices: 3
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("triangle 1"));

    assert_eq!(
        FlatBvh::build(&[], &BuildOptions::default()).unwrap_err(),
        BuildError::Empty
    );
    let bad = BuildOptions {
        bins: 1,
        ..Default::default()
    };
    assert!(matches!(
        FlatBvh::build(&[ok], &bad),
        Err(BuildError::Options(_))
    ));
}

fn random_soup(n: usize, seed: u64) -> Vec<Triangle> {
    let mut s = seed;
    let mut r = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    (0..n)
        .map(|_| {
            let c = Vec3::new(r(), r(), r()) * 100.0;
            [
                c,
                c + Vec3::new(r(), r(), r()),
                c + Vec3::new(r(), r(), r()),
            ]
        })
        .collect()
}

#[test]
fn the_tree_does_not_depend_on_the_thread_count() {
    let tris = random_soup(200_000, 7);
    for b in BuilderKind::ALL {
        let opts = BuildOptions {
            parallel_threshold: 1024,
            ..BuildOptions::with_builder(b)
        };
        let build_with = |threads| common::build_on_threads(&tris, &opts, threads);
        let one = build_with(1);
        assert!(
            one == build_with(4),
            "{b}: trees differ between 1 and 4 threads"
        );
        assert!(
            one == build_with(3),
            "{b}: trees differ between 1 and 3 threads"
        );
    }
}

/// `FlatBvh::build` writes the flat layout straight from the recursion; laying out the
/// boxed tree `build` returns must give the same nodes and triangles, including trees
/// whose leaves hold several triangles (the slots they leave unused are compacted away).
#[test]
fn the_direct_flat_build_is_the_flattened_tree() {
    let tris = random_soup(30_000, 11);
    for b in BuilderKind::ALL {
        for cost_traversal in [0.125, 1.0, 4.0] {
            let opts = BuildOptions {
                cost_traversal,
                parallel_threshold: 1024,
                ..BuildOptions::with_builder(b)
            };
            let direct = FlatBvh::build(&tris, &opts).unwrap();
            let tree = bvhtrace_core::build(&tris, &opts).unwrap();
            let laid_out = FlatBvh::flatten(&tree, &tris);
            assert_eq!(
                direct.nodes(),
                laid_out.nodes(),
                "{b}, traversal cost {cost_traversal}"
            );
            assert_eq!(direct.triangles(), laid_out.triangles(), "{b}");
            assert_eq!(direct.depth(), laid_out.depth(), "{b}");
            assert_eq!(tree.node_count, direct.nodes().len(), "{b}");
            direct.check_invariants().unwrap();
            if cost_traversal > 1.0 {
                assert!(
                    direct.nodes().iter().any(|n| n.count() > 1),
                    "{b}: no multi-triangle leaf"
                );
            }
        }
    }
}

#[test]
fn sah_beats_the_naive_splits_on_a_real_distribution() {
    let tris = random_soup(50_000, 3);
    let cost = |b| {
        BvhStats::of(&FlatBvh::build(&tris, &BuildOptions::with_builder(b)).unwrap()).sah_cost_pbrt
    };
    let (sah, sweep, median, mid) = (
        cost(BuilderKind::Sah),
        cost(BuilderKind::SweepSah),
        cost(BuilderKind::Median),
        cost(BuilderKind::Midpoint),
    );
    assert!(
        sweep <= sah * 1.01 && sah < median && sah < mid,
        "sah {sah} sweep {sweep} median {median} midpoint {mid}"
    );
}

#[test]
fn stats_match_a_hand_computed_tree() {
    // Two unit triangles far apart: one interior node over two leaves.
    let tris = vec![
        [Vec3::ZERO, Vec3::X, Vec3::Y],
        [
            Vec3::new(10.0, 0.0, 0.0),
            Vec3::new(11.0, 0.0, 0.0),
            Vec3::new(10.0, 1.0, 0.0),
        ],
    ];
    let opts = BuildOptions {
        max_leaf_size: 1,
        ..Default::default()
    };
    let bvh = FlatBvh::build(&tris, &opts).unwrap();
    let s = BvhStats::of(&bvh);
    assert_eq!((s.nodes, s.leaves, s.depth), (3, 2, 1));
    assert_eq!(s.leaf_sizes, vec![0, 2]);
    // Flat boxes: root 11x1x0 has area 22, each leaf 1x1x0 has area 2.
    assert!(
        (s.sah_cost - (22.0 + 2.0 + 2.0) / 22.0).abs() < 1e-9,
        "{}",
        s.sah_cost
    );
    assert!((s.sah_cost_pbrt - (22.0 * 0.125 + 2.0 + 2.0) / 22.0).abs() < 1e-9);
}
