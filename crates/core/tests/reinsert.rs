//! Tree optimisation by reinsertion (`build::reinsert`): the same primitives, a valid
//! tree, a SAH cost never higher, the same hits, the same tree on any thread count, and
//! the stop rule.

mod common;

use bvhtrace_core::build::reinsert::ReinsertReport;
use bvhtrace_core::build::{BuildNode, BuildTree};
use bvhtrace_core::oracle;
use bvhtrace_core::*;
use glam::Vec3;
use proptest::prelude::*;

/// A mesh-like scene: spheres of different sizes, some overlapping, and a scatter of
/// small triangles (about 5,000 triangles).
fn scene() -> Vec<Triangle> {
    let mut tris = common::uv_sphere(24, 1.0, Vec3::ZERO);
    tris.extend(common::uv_sphere(16, 0.4, Vec3::new(1.2, 0.3, 0.0)));
    tris.extend(common::uv_sphere(12, 2.5, Vec3::new(-4.0, 1.0, 3.0)));
    let mut rnd = common::xorshift(0x9E37_79B9_7F4A_7C15u64);
    for _ in 0..1500 {
        let p = Vec3::new(rnd(), rnd(), rnd()) * 12.0 - Vec3::splat(6.0);
        let e = |r: &mut dyn FnMut() -> f32| Vec3::new(r(), r(), r()) * 0.3;
        tris.push([p, p + e(&mut rnd), p + e(&mut rnd)]);
    }
    tris
}

/// The SAH cost in `BvhStats`' conventions (traversal 1 and 1/8, intersection 1).
fn costs(tree: &BuildTree, tris: &[Triangle]) -> (f64, f64) {
    let s = BvhStats::of(&FlatBvh::flatten(tree, tris));
    (s.sah_cost, s.sah_cost_pbrt)
}

fn sorted(v: &[u32]) -> Vec<u32> {
    let mut v = v.to_vec();
    v.sort_unstable();
    v
}

/// Interior boxes hold their children's; leaves hold their triangles' parts (an SBVH leaf
/// may hold the clipped part of one, so only "meets its box" is asked of leaves then).
fn check_boxes(tree: &BuildTree, tris: &[Triangle], whole: bool) -> Result<(), String> {
    let mut stack = vec![&tree.root];
    while let Some(n) = stack.pop() {
        match n {
            BuildNode::Leaf {
                bounds,
                first,
                count,
            } => {
                for &p in &tree.prim_order[*first as usize..(*first + *count) as usize] {
                    let tb = Aabb::from_triangle(&tris[p as usize]);
                    let meets = bounds.min.cmple(tb.max).all() && tb.min.cmple(bounds.max).all();
                    if (whole && !bounds.contains(&tb)) || !meets {
                        return Err(format!("leaf box {bounds:?} and triangle {p}"));
                    }
                }
            }
            BuildNode::Interior {
                bounds, children, ..
            } => {
                for c in children.iter() {
                    if !bounds.contains(c.bounds()) {
                        return Err(format!("box {bounds:?} does not hold {:?}", c.bounds()));
                    }
                    stack.push(c);
                }
            }
        }
    }
    Ok(())
}

fn count_nodes(n: &BuildNode) -> usize {
    match n {
        BuildNode::Leaf { .. } => 1,
        BuildNode::Interior { children, .. } => {
            1 + count_nodes(&children[0]) + count_nodes(&children[1])
        }
    }
}

/// Everything the optimiser promises about one tree.
fn check_optimised(
    before: &BuildTree,
    after: &BuildTree,
    report: &ReinsertReport,
    tris: &[Triangle],
    opts: &BuildOptions,
) -> Result<(), String> {
    let label = opts.builder;
    if sorted(&before.prim_order) != sorted(&after.prim_order) {
        return Err(format!("{label}: the primitives changed"));
    }
    if after.node_count != before.node_count || count_nodes(&after.root) != after.node_count {
        return Err(format!("{label}: node count"));
    }
    check_boxes(after, tris, opts.builder != BuilderKind::Sbvh)
        .map_err(|e| format!("{label}: {e}"))?;
    let flat = FlatBvh::flatten(after, tris);
    flat.check_invariants()
        .map_err(|e| format!("{label}: {e}"))?;
    let (b, a) = (costs(before, tris), costs(after, tris));
    // Both conventions fall together: only interior areas change.
    if !(a.0 <= b.0 * (1.0 + 1e-12) && a.1 <= b.1 * (1.0 + 1e-12)) {
        return Err(format!("{label}: SAH {b:?} -> {a:?}"));
    }
    let no_higher = report.cost_after <= report.cost_before;
    if !no_higher {
        return Err(format!("{label}: report {report:?}"));
    }
    if flat.depth() > (FlatBvh::flatten(before, tris).depth()).max(40) {
        return Err(format!("{label}: depth {}", flat.depth()));
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn random_soups_keep_every_promise(tris in common::soup(), leaf in 1usize..6) {
        for b in BuilderKind::ALL {
            let opts = BuildOptions { builder: b, max_leaf_size: leaf, ..Default::default() };
            let tree = build(&tris, &opts).unwrap();
            let (opt, report) = optimize_with(&tree, &opts, &ReinsertOptions::default());
            if let Err(e) = check_optimised(&tree, &opt, &report, &tris, &opts) {
                return Err(TestCaseError::fail(e));
            }
        }
    }
}

#[test]
fn every_builder_keeps_its_primitives_and_never_costs_more() {
    let tris = scene();
    for b in BuilderKind::ALL {
        for ct in [0.125, 1.0] {
            let opts = BuildOptions {
                builder: b,
                cost_traversal: ct,
                ..Default::default()
            };
            let tree = build(&tris, &opts).unwrap();
            let (opt, report) = optimize_with(&tree, &opts, &ReinsertOptions::default());
            check_optimised(&tree, &opt, &report, &tris, &opts).unwrap();
            let (b0, a0) = (costs(&tree, &tris), costs(&opt, &tris));
            println!(
                "{b} ct {ct}: {b0:?} -> {a0:?} in {} rounds",
                report.rounds.len()
            );
            // The report's cost is BvhStats' with the build's costs.
            let own = if ct == 1.0 { a0.0 } else { a0.1 };
            assert!(
                (report.cost_after - own).abs() <= 1e-9 * own,
                "{report:?} vs {own}"
            );
            // The median and midpoint trees have plenty to gain.
            if matches!(b, BuilderKind::Median | BuilderKind::Midpoint) {
                assert!(a0.0 < 0.97 * b0.0, "{b}: {b0:?} -> {a0:?}");
            }
        }
    }
}

#[test]
fn build_option_optimises_the_tree_build_returns() {
    let tris = scene();
    for b in [BuilderKind::Sah, BuilderKind::Median] {
        let plain = BuildOptions::with_builder(b);
        let opts = BuildOptions {
            optimize: true,
            ..plain
        };
        let direct = FlatBvh::flatten(&optimize(&build(&tris, &plain).unwrap(), &opts), &tris);
        assert_eq!(
            FlatBvh::flatten(&build(&tris, &opts).unwrap(), &tris),
            direct
        );
        assert_eq!(FlatBvh::build(&tris, &opts).unwrap(), direct);
        assert!(
            BvhStats::of(&direct).sah_cost
                < BvhStats::of(&FlatBvh::build(&tris, &plain).unwrap()).sah_cost
        );
    }
    // The top level over boxes, too.
    let boxes: Vec<Aabb> = tris.iter().map(Aabb::from_triangle).collect();
    let opts = BuildOptions {
        builder: BuilderKind::Midpoint,
        optimize: true,
        ..Default::default()
    };
    let tree = build::build_boxes(&boxes, &opts).unwrap();
    let plain =
        build::build_boxes(&boxes, &BuildOptions::with_builder(BuilderKind::Midpoint)).unwrap();
    assert_eq!(sorted(&tree.prim_order), sorted(&plain.prim_order));
    assert!(costs(&tree, &tris).0 < costs(&plain, &tris).0);
}

#[test]
fn hits_match_the_oracle_and_the_unoptimised_tree() {
    let tris = scene();
    let rays = common::rays_for(&tris, 7, 3000);
    let walks = [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(2),
        Traversal::Wide,
    ];
    // Neither answer depends on the tree.
    let oracle: Vec<_> = rays.iter().map(|r| oracle::closest_hit(&tris, r)).collect();
    let mut brute = None;
    for b in BuilderKind::ALL {
        let opts = BuildOptions::with_builder(b);
        let plain = FlatBvh::build(&tris, &opts).unwrap().with_wide();
        let opt =
            FlatBvh::flatten(&optimize(&build(&tris, &opts).unwrap(), &opts), &tris).with_wide();
        let brute = brute.get_or_insert_with(|| {
            rays.iter()
                .map(|r| brute_force(&opt, r, Precision::WatertightF32))
                .collect::<Vec<_>>()
        });
        for w in walks {
            let closest = trace_rays(&opt, &rays, &TraceOptions::closest(w)).hits;
            let before = trace_rays(&plain, &rays, &TraceOptions::closest(w)).hits;
            let any = trace_rays(&opt, &rays, &TraceOptions::new(w, Query::Any)).hits;
            for (i, ray) in rays.iter().enumerate() {
                let (h, p) = (&closest[i], &before[i]);
                // Ties go to the lower primitive, so the tree's shape cannot change the
                // answer: the same hit to the bit.
                assert!(
                    h.prim == p.prim && h.t.to_bits() == p.t.to_bits(),
                    "{b} {w} ray {i}: {h:?} vs unoptimised {p:?}"
                );
                assert_eq!(*h, brute[i], "{b} {w} ray {i}: brute force");
                let o = &oracle[i];
                let excused = [o.prim, h.prim].iter().any(|&q| {
                    tris.get(q as usize)
                        .is_some_and(|t| oracle::f32_indeterminate(t, ray))
                });
                assert!(
                    o.prim == h.prim || excused,
                    "{b} {w} ray {i}: {h:?} vs oracle {o:?}"
                );
                assert_eq!(any[i].is_hit(), h.is_hit(), "{b} {w} any-hit ray {i}");
            }
        }
    }
}

#[test]
fn the_same_tree_on_one_thread_and_two() {
    let tris = scene();
    for b in BuilderKind::ALL {
        let opts = BuildOptions::with_builder(b);
        let tree = build(&tris, &opts).unwrap();
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let (t, r) = optimize_with(&tree, &opts, &ReinsertOptions::default());
                (FlatBvh::flatten(&t, &tris), t.prim_order, r)
            })
        };
        let (a, b2) = (on(1), on(2));
        assert!(
            a.0 == b2.0 && a.1 == b2.1 && a.2 == b2.2,
            "{b}: trees differ"
        );
        assert!(!a.2.rounds.is_empty());
    }
}

#[test]
fn a_round_gaining_less_than_min_gain_is_the_last() {
    let tris = scene();
    let opts = BuildOptions::with_builder(BuilderKind::Median);
    let tree = build(&tris, &opts).unwrap();
    let gain = |from: f64, to: f64| (from - to) / from;
    // The default rule: every round but the last gains at least `min_gain`.
    for min_gain in [1e-4, 1e-3, 1e-2] {
        let s = ReinsertOptions {
            min_gain,
            ..Default::default()
        };
        let (_, r) = optimize_with(&tree, &opts, &s);
        let mut from = r.cost_before;
        for (k, round) in r.rounds.iter().enumerate() {
            let g = gain(from, round.cost);
            assert!(g >= 0.0, "{min_gain}: round {k} raised the cost");
            let last = k + 1 == r.rounds.len();
            assert!(
                last || g >= min_gain,
                "{min_gain}: round {k} gained {g} and was not the last"
            );
            if last && r.rounds.len() < s.max_rounds && round.moves > 0 {
                assert!(
                    g < min_gain,
                    "{min_gain}: stopped after round {k} gaining {g}"
                );
            }
            from = round.cost;
        }
        assert_eq!(r.cost_after, from);
    }
    // A bar no round can clear: one round. No rounds at all: the tree as it was.
    let s = ReinsertOptions {
        min_gain: 0.9,
        ..Default::default()
    };
    let (_, r) = optimize_with(&tree, &opts, &s);
    assert_eq!(r.rounds.len(), 1);
    assert!(r.rounds[0].moves > 0 && r.cost_after < r.cost_before);
    let s = ReinsertOptions {
        max_rounds: 0,
        ..Default::default()
    };
    let (t, r) = optimize_with(&tree, &opts, &s);
    assert!(r.rounds.is_empty());
    assert_eq!(FlatBvh::flatten(&t, &tris), FlatBvh::flatten(&tree, &tris));
    // More rounds never end higher than fewer.
    let few = optimize_with(
        &tree,
        &opts,
        &ReinsertOptions {
            max_rounds: 2,
            min_gain: 0.0,
            ..Default::default()
        },
    )
    .1;
    let many = optimize_with(
        &tree,
        &opts,
        &ReinsertOptions {
            max_rounds: 8,
            min_gain: 0.0,
            ..Default::default()
        },
    )
    .1;
    assert_eq!(few.rounds.len(), 2);
    assert!(many.cost_after <= few.cost_after);
}

#[test]
fn the_depth_stays_within_the_limit() {
    let tris = scene();
    for b in [BuilderKind::Median, BuilderKind::Midpoint] {
        let opts = BuildOptions::with_builder(b);
        let tree = build(&tris, &opts).unwrap();
        let depth = FlatBvh::flatten(&tree, &tris).depth();
        // A limit below the depth: the depth may not grow at all.
        let s = ReinsertOptions {
            depth_limit: 0,
            ..Default::default()
        };
        let (t, r) = optimize_with(&tree, &opts, &s);
        assert!(FlatBvh::flatten(&t, &tris).depth() <= depth, "{b}");
        assert!(
            r.cost_after < r.cost_before,
            "{b}: nothing to gain within the depth?"
        );
    }
}

#[test]
fn nothing_to_gain_returns_the_tree_as_it_was() {
    let tris = scene();
    // Interior nodes cost nothing: no move can lower the cost.
    let opts = BuildOptions {
        builder: BuilderKind::Median,
        cost_traversal: 0.0,
        ..Default::default()
    };
    let tree = build(&tris, &opts).unwrap();
    let (t, r) = optimize_with(&tree, &opts, &ReinsertOptions::default());
    assert!(r.rounds.is_empty());
    assert_eq!(t.prim_order, tree.prim_order);
    assert_eq!(FlatBvh::flatten(&t, &tris), FlatBvh::flatten(&tree, &tris));
    // Trees too small to have a move, and a single leaf.
    for n in [1, 2, 3, 9] {
        let small = &tris[..n];
        for leaf in [1, 8] {
            let opts = BuildOptions {
                max_leaf_size: leaf,
                ..BuildOptions::with_builder(BuilderKind::Midpoint)
            };
            let tree = build(small, &opts).unwrap();
            let t = optimize(&tree, &opts);
            assert_eq!(sorted(&t.prim_order), sorted(&tree.prim_order));
            FlatBvh::flatten(&t, small).check_invariants().unwrap();
        }
    }
}
