//! Every traversal against brute force (exactly) and against the f64 oracle.

mod common;

use bvhtrace_core::oracle;
use bvhtrace_core::*;
use glam::Vec3;
use proptest::prelude::*;

const TRAVERSALS: [Traversal; 6] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(1),
    Traversal::ShortStack(2),
    Traversal::ShortStack(6),
    Traversal::Wide,
];

/// Largest coordinate magnitude involved: f32 rounding errors scale with it.
fn scale_of(tri: &Triangle, ray: &Ray) -> f64 {
    tri.iter()
        .chain(std::iter::once(&Vec3::from(ray.origin)))
        .map(|p| p.abs().max_element() as f64)
        .fold(f64::MIN_POSITIVE, f64::max)
}

/// f32 rounding tolerance, relative to the coordinates' magnitude.
const TOL: f64 = 4e-6;

/// Checks an f32 closest hit against the oracle; near-ties and rays grazing an edge of the
/// triangles involved (within f32 rounding of the coordinates) may differ.
fn agrees_with_oracle(tris: &[Triangle], ray: &Ray, hit: &Hit) -> Result<(), String> {
    let o = oracle::closest_hit(tris, ray);
    let dlen = Vec3::from(ray.dir).length() as f64;
    if o.prim == hit.prim {
        if hit.is_hit() {
            let tri = &tris[o.prim as usize];
            let bound = (TOL * scale_of(tri, ray) / dlen).max(oracle::f32_t_error_bound(tri, ray));
            if (hit.t as f64 - o.t).abs() > bound {
                return Err(format!("t {} vs oracle {}", hit.t, o.t));
            }
        }
        return Ok(());
    }
    for p in [o.prim, hit.prim] {
        if let Some(t) = tris.get(p as usize)
            && oracle::f32_indeterminate(t, ray)
        {
            return Ok(());
        }
    }
    if o.is_hit() && hit.is_hit() {
        let scale =
            scale_of(&tris[hit.prim as usize], ray).max(scale_of(&tris[o.prim as usize], ray));
        let all = oracle::all_hits(tris, ray);
        let bound = TOL * scale / dlen
            + oracle::f32_t_error_bound(&tris[hit.prim as usize], ray)
            + oracle::f32_t_error_bound(&tris[o.prim as usize], ray);
        if let Some(&(t64, _)) = all.iter().find(|h| h.1 == hit.prim)
            && (t64 - o.t).abs() <= bound
        {
            return Ok(());
        }
    }
    Err(format!(
        "prim {} (t {}) vs oracle prim {} (t {})",
        hit.prim, hit.t, o.prim, o.t
    ))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    #[test]
    fn traversals_match_brute_force_and_the_oracle(tris in common::soup(), seed in any::<u64>(), b in 0usize..BuilderKind::ALL.len()) {
        let opts = BuildOptions { max_leaf_size: 3, ..BuildOptions::with_builder(BuilderKind::ALL[b]) };
        let bvh = FlatBvh::build(&tris, &opts).unwrap().with_wide();
        if let Some(w) = &bvh.wide() {
            prop_assert!(w.check_invariants(&bvh).is_ok(), "{:?}", w.check_invariants(&bvh));
        }
        let rays = common::rays_for(&tris, seed, 48);
        for ray in &rays {
            let expect = brute_force(&bvh, ray, Precision::WatertightF32);
            prop_assert!(!expect.t.is_nan() && !expect.u.is_nan() && !expect.v.is_nan());
            if let Err(e) = agrees_with_oracle(&tris, ray, &expect) {
                return Err(TestCaseError::fail(format!("{e}\nray {ray:?}")));
            }
            let (full, _) = trace_ray(&bvh, ray, &TraceOptions::closest(Traversal::FullStack));
            for tr in TRAVERSALS {
                let (h, _) = trace_ray(&bvh, ray, &TraceOptions::closest(tr));
                // Equal to brute force, except where the f32 test is indeterminate or its t
                // ill-conditioned for a triangle involved (both answers then agree with the
                // oracle within f32's error): the box test may rightly cull an f32 hit whose
                // t lies outside the triangle's own box by more than its slack.
                let excused = h != expect
                    && agrees_with_oracle(&tris, ray, &h).is_ok()
                    && agrees_with_oracle(&tris, ray, &expect).is_ok()
                    && common::f32_departure(&tris, ray, &h, &expect);
                prop_assert!(h == expect || excused, "{} on {:?}: {:?} vs brute force {:?}", tr, ray, h, expect);
                // The visit order does not matter: the same hit as the full stack's, to the
                // bit, under the same documented exception.
                let same = h.prim == full.prim && h.t.to_bits() == full.t.to_bits();
                prop_assert!(same || common::f32_departure(&tris, ray, &h, &full),
                    "{} on {:?}: {:?} vs full stack {:?}", tr, ray, h, full);
                let (a, _) = trace_ray(&bvh, ray, &TraceOptions::new(tr, Query::Any));
                prop_assert_eq!(a.is_hit(), h.is_hit(), "any-hit {} on {:?}", tr, ray);
                if a.is_hit() {
                    prop_assert!(a.t >= ray.t_min && a.t < ray.t_max);
                }
            }
        }
    }
}

#[test]
fn exact_ties_go_to_the_lower_primitive() {
    // Three copies of the same triangle, and two triangles sharing an edge hit on the edge.
    let t = [
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ];
    let mut tris = vec![
        [
            Vec3::splat(50.0),
            Vec3::splat(51.0),
            Vec3::new(50.0, 52.0, 50.0),
        ],
        t,
        t,
        t,
    ];
    tris.push([
        Vec3::new(-1.0, 0.0, 5.0),
        Vec3::new(1.0, 0.0, 5.0),
        Vec3::new(0.0, 1.0, 5.0),
    ]);
    tris.push([
        Vec3::new(1.0, 0.0, 5.0),
        Vec3::new(-1.0, 0.0, 5.0),
        Vec3::new(0.0, -1.0, 5.0),
    ]);
    for b in BuilderKind::ALL {
        let bvh = FlatBvh::build(
            &tris,
            &BuildOptions {
                max_leaf_size: 1,
                ..BuildOptions::with_builder(b)
            },
        )
        .unwrap()
        .with_wide();
        for tr in TRAVERSALS {
            let (h, _) = trace_ray(
                &bvh,
                &Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::Z),
                &TraceOptions::closest(tr),
            );
            assert_eq!((h.prim, h.t), (1, 5.0), "{tr}");
            // Along the shared edge y = 0 at z = 5, from behind: both hit at t = 5; 4 wins.
            let (h, _) = trace_ray(
                &bvh,
                &Ray::new(Vec3::new(0.0, 0.0, 10.0), -Vec3::Z),
                &TraceOptions::closest(tr),
            );
            assert_eq!((h.prim, h.t), (4, 5.0), "{tr}");
        }
    }
    let o = oracle::closest_hit(&tris, &Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::Z));
    assert_eq!(o.prim, 1);
}

/// A large triangle hit very close to the ray's origin: its f32 `t` lands hundreds of ulps
/// before its own (flat) box's entry distance, because the watertight test's error scales
/// with the corners' distances along the ray's dominant axis (the triangle's extent), not
/// with `t`. A smaller coplanar triangle overlapping it ("just behind" in f32: a slightly
/// larger `t`, still before that entry) sits in a leaf every traversal visits first. Before
/// the box test's culling slack (`intersect::BOX_CULL_SLACK`), every walk then culled the
/// large triangle's subtree against the small one's hit and returned the wrong triangle.
#[test]
fn closest_hit_does_not_depend_on_visit_order_near_the_origin() {
    use bvhtrace_core::build::{BuildNode, BuildTree};
    use bvhtrace_core::intersect::{
        BOX_TFAR_SCALE, PreparedRay, intersect_box, intersect_triangle,
    };
    // W (prim 0): large, in the plane z = 0. L (prim 1): smaller, coplanar, around the hit
    // point. O (prim 2): small, below the plane and off the ray, sharing W's subtree.
    let w = [
        Vec3::new(-12.0, -9.0, 0.0),
        Vec3::new(14.0, -7.0, 0.0),
        Vec3::new(1.0, 13.0, 0.0),
    ];
    let l = [
        Vec3::new(-1.4, -1.1, 0.0),
        Vec3::new(0.1, -0.9, 0.0),
        Vec3::new(-0.7, 0.4, 0.0),
    ];
    let o = [
        Vec3::new(-8.0, 7.0, -1.0),
        Vec3::new(-7.0, 7.0, -1.0),
        Vec3::new(-8.0, 8.0, -1.0),
    ];
    let tris = vec![w, l, o];
    // Origin 0.003031 above the plane (bits pinned: the f32 errors depend on them); the
    // dominant axis is x, along which W spans 26 units.
    let origin = Vec3::new(-0.5, -0.4, f32::from_bits(0x3b46_a3be));
    let dir = Vec3::new(1.0, 0.25, -0.3);
    let ray = Ray::new(origin, dir);
    let bounds = |ts: &[Triangle]| {
        ts.iter()
            .map(Aabb::from_triangle)
            .fold(Aabb::EMPTY, |a, b| a.union(&b))
    };
    // The tree, pinned: root split on x into [leaf L, X = [leaf W, leaf O]]. The full stack
    // enters L and X at the same distance (the plane) and takes the left one first; the
    // stackless and short-stack walks take the near side along x, also L. X (or W's leaf)
    // is then tested against L's hit.
    let leaf = |ts: &[Triangle], first: u32| BuildNode::Leaf {
        bounds: bounds(ts),
        first,
        count: 1,
    };
    let tree = BuildTree {
        root: BuildNode::Interior {
            bounds: bounds(&tris),
            axis: 0,
            children: Box::new([
                leaf(&[l], 0),
                BuildNode::Interior {
                    bounds: bounds(&[w, o]),
                    axis: 0,
                    children: Box::new([leaf(&[w], 1), leaf(&[o], 2)]),
                },
            ]),
        },
        prim_order: vec![1, 0, 2],
        node_count: 5,
    };
    let bvh = FlatBvh::flatten(&tree, &tris).with_wide();
    bvh.check_invariants().unwrap();

    // The situation: t_W < t_L, and t_L is before W's box (and X's) by more than the
    // conservative scale of the box test.
    let r = PreparedRay::new(&ray);
    let tw = intersect_triangle(&r, w[0], w[1], w[2]).unwrap().t;
    let tl = intersect_triangle(&r, l[0], l[1], l[2]).unwrap().t;
    let entry = |b: Aabb| intersect_box(&r, b.min, b.max, f32::INFINITY).unwrap();
    let (entry_w, entry_x) = (entry(bounds(&[w])), entry(bounds(&[w, o])));
    assert!(tw < tl, "t_W {tw:e} t_L {tl:e}");
    assert!(
        tl * BOX_TFAR_SCALE < entry_w.min(entry_x),
        "t_L {tl:e} entries {entry_w:e} {entry_x:e}"
    );
    assert!(
        entry_w.to_bits() - tw.to_bits() > 100,
        "t_W {tw:e} is only a few ulps before its box's entry {entry_w:e}"
    );

    let expect = brute_force(&bvh, &ray, Precision::WatertightF32);
    assert_eq!((expect.prim, expect.t), (0, tw));
    let wrong: Vec<String> = TRAVERSALS
        .iter()
        .map(|&tr| (tr, trace_ray(&bvh, &ray, &TraceOptions::closest(tr)).0))
        .filter(|(_, h)| *h != expect || h.t.to_bits() != tw.to_bits())
        .map(|(tr, h)| format!("{tr}: prim {} t {:e}", h.prim, h.t))
        .collect();
    assert!(
        wrong.is_empty(),
        "expected prim 0 at t {tw:e}, got\n{}",
        wrong.join("\n")
    );
    // The culling slack keeps W's box against L's hit, but never widens the ray's own
    // t_max: before any hit, the box is culled against it as before.
    let wb = bounds(&[w]);
    assert!(intersect_box(&r, wb.min, wb.max, tl).is_some());
    let short = PreparedRay::new(&Ray::with_interval(origin, dir, 0.0, tl));
    assert!(intersect_box(&short, wb.min, wb.max, short.t_max).is_none());
}

/// A batch's hits and each ray's counters.
fn trace_counted(
    bvh: &FlatBvh,
    rays: &[Ray],
    traversal: Traversal,
    query: Query,
) -> (Vec<Hit>, Vec<Counters>) {
    let out = trace_rays(
        bvh,
        rays,
        &TraceOptions::new(traversal, query).with_counters(true),
    );
    let counters = out.counters.expect("counters were asked for");
    assert_eq!(counters.len(), rays.len());
    (out.hits, counters)
}

/// Triangles at exponentially spaced positions make the midpoint split peel one at a time.
fn deep_soup(n: usize) -> Vec<Triangle> {
    (0..n)
        .map(|i| {
            let x = 2f32.powi(i as i32 - 60);
            let p = Vec3::new(x, 0.0, 0.0);
            [
                p + Vec3::new(0.0, -1.0, -1.0),
                p + Vec3::new(0.0, 1.0, -1.0),
                p + Vec3::new(0.0, 0.0, 1.0),
            ]
        })
        .collect()
}

#[test]
fn deep_trees_are_traversed_correctly_without_a_deep_stack() {
    let tris = deep_soup(120);
    let opts = BuildOptions {
        builder: BuilderKind::Midpoint,
        max_depth: 1000,
        max_leaf_size: 1,
        ..Default::default()
    };
    let bvh = FlatBvh::build(&tris, &opts).unwrap().with_wide();
    bvh.check_invariants().unwrap();
    // Deeper than any fixed 64-entry stack.
    assert!(bvh.depth() > 64, "depth {}", bvh.depth());
    let mut rays = Vec::new();
    for i in 0..120 {
        let x = 2f32.powi(i - 60);
        rays.push(Ray::new(
            Vec3::new(x, 0.0, 0.0) + Vec3::new(-1e-30, 0.1, 0.0),
            Vec3::X,
        ));
        rays.push(Ray::new(Vec3::new(2.0, 0.2, 0.1), -Vec3::X));
        rays.push(Ray::with_interval(
            Vec3::new(-1.0, 0.0, 0.0),
            Vec3::X,
            0.0,
            1.0 + x,
        ));
    }
    // Rays through every box that miss every triangle (inside the boxes' corners): every
    // leaf is visited, every interior node leaves a far child pending, and the short
    // stacks' rings overflow, so they follow escape links from deep in the tree.
    for (y, z) in [(0.9f32, 0.9f32), (-0.9, 0.8), (0.95, -0.0)] {
        for dir in [Vec3::X, -Vec3::X, Vec3::new(1.0, 1e-9, -1e-9)] {
            let o = Vec3::new(if dir.x > 0.0 { -1.0 } else { 2.0 }, y, z);
            rays.push(Ray::new(o, dir));
            rays.push(Ray::with_interval(o, dir, 0.5, 1.0 + 2f32.powi(-20)));
        }
    }
    for ray in &rays {
        let expect = brute_force(&bvh, ray, Precision::WatertightF32);
        for tr in TRAVERSALS {
            let (h, c) = trace_ray(&bvh, ray, &TraceOptions::closest(tr));
            assert_eq!(h, expect, "{tr} {ray:?}");
            // No leaf is visited twice.
            assert!(c.tris as usize <= tris.len(), "{tr} {ray:?}: {c:?}");
            assert_eq!(
                trace_ray(&bvh, ray, &TraceOptions::new(tr, Query::Any))
                    .0
                    .is_hit(),
                expect.is_hit()
            );
        }
    }
}

#[test]
fn stackless_and_short_stack_visit_no_more_nodes_than_the_full_stack_allows() {
    // On a structured scene the deterministic near/far order costs little against the
    // distance order (the GPU goal is 1.15x the full stack's box tests).
    let tris: Vec<Triangle> = (0..20_000)
        .map(|i| {
            let (x, y) = ((i % 141) as f32, (i / 141) as f32);
            let z = ((x * 0.3).sin() + (y * 0.2).cos()) * 3.0;
            let p = Vec3::new(x, y, z);
            [
                p,
                p + Vec3::new(1.0, 0.0, 0.1),
                p + Vec3::new(0.0, 1.0, -0.1),
            ]
        })
        .collect();
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())
        .unwrap()
        .with_wide();
    let eye = Vec3::new(70.0, -60.0, 80.0);
    let rays: Vec<Ray> = (0..64 * 64)
        .map(|i| {
            let target = Vec3::new((i % 64) as f32 * 2.2, (i / 64) as f32 * 2.2, 0.0);
            Ray::new(eye, target - eye)
        })
        .collect();
    let nodes = |tr| {
        let (_, c) = trace_counted(&bvh, &rays, tr, Query::Closest);
        c.iter().map(|c| c.nodes as u64).sum::<u64>() as f64
    };
    let full = nodes(Traversal::FullStack);
    for tr in [Traversal::Stackless, Traversal::ShortStack(6)] {
        let n = nodes(tr);
        assert!(n <= 1.15 * full, "{tr}: {n} box tests vs {full}");
    }
}

#[test]
fn batch_equals_single_rays() {
    let tris = deep_soup(40);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())
        .unwrap()
        .with_wide();
    let rays = common::rays_for(&tris, 99, 500);
    for tr in TRAVERSALS {
        let out = trace_rays(&bvh, &rays, &TraceOptions::closest(tr));
        // Counters only when asked for; no device time, nothing finished elsewhere.
        assert_eq!(out.counters, None, "{tr}");
        assert_eq!((out.gpu_ms, out.incomplete), (None, 0), "{tr}");
        assert!(out.wall_ms >= 0.0, "{tr}: {}", out.wall_ms);
        let batch = out.hits;
        assert_eq!(batch.len(), rays.len());
        for (r, h) in rays.iter().zip(&batch) {
            assert_eq!(*h, trace_ray(&bvh, r, &TraceOptions::closest(tr)).0);
        }
        // With counters, for both queries and every precision: the same as one ray at a
        // time, with a stack reused across rays or not.
        for q in [Query::Closest, Query::Any] {
            for p in Precision::ALL {
                let opts = TraceOptions::new(tr, q).with_precision(p);
                let (hits, counters) = {
                    let out = trace_rays(&bvh, &rays, &opts.with_counters(true));
                    (out.hits, out.counters.expect("counters were asked for"))
                };
                assert_eq!(hits.len(), rays.len());
                assert_eq!(counters.len(), rays.len());
                let mut stack = Vec::new();
                for (i, r) in rays.iter().enumerate() {
                    let one = trace_ray(&bvh, r, &opts);
                    assert_eq!((hits[i], counters[i]), one, "{tr} {q:?} {p} ray {i}");
                    assert_eq!(trace_ray_with(&bvh, r, &opts, &mut stack), one);
                }
            }
        }
    }
}

#[test]
fn short_stacks_walk_exactly_the_stackless_order() {
    // The ring only saves escape-link reads: every ring size visits the same nodes and
    // triangles in the same order as the stackless walk, so the counters are equal and
    // even any-hit queries (which stop at the first hit found) agree. The deep soup makes
    // small rings overflow and run dry, so the escape links are followed from mid-walk.
    let tris = deep_soup(120);
    let bvh = FlatBvh::build(&tris, &peeling()).unwrap();
    assert!(bvh.depth() > 64, "depth {}", bvh.depth());
    let rays = common::rays_for(&tris, 7, 2000);
    for q in [Query::Closest, Query::Any] {
        let (hits, counters) = trace_counted(&bvh, &rays, Traversal::Stackless, q);
        for k in [1, 2, 3, 6, traverse::MAX_SHORT_STACK] {
            let (h, c) = trace_counted(&bvh, &rays, Traversal::ShortStack(k), q);
            assert_eq!(h, hits, "short-stack({k}) {q:?}: hits");
            assert_eq!(c, counters, "short-stack({k}) {q:?}: counters");
        }
    }
}

#[test]
fn escape_links_lead_to_the_next_node_of_each_octant_order() {
    // Against a walk with an explicit stack in the same near/far order.
    let bvh = FlatBvh::build(&deep_soup(120), &peeling()).unwrap();
    for oct in 0..flat::OCTANTS {
        let mut order = Vec::new();
        let mut stack = vec![0u32];
        while let Some(i) = stack.pop() {
            order.push(i);
            let n = &bvh.nodes()[i as usize];
            if !n.is_leaf() {
                let (near, far) = flat::near_far(oct, i, n);
                stack.extend([far, near]);
            }
        }
        assert_eq!(order.len(), bvh.nodes().len());
        // A subtree is a contiguous run of the order: its escape is the node after the run.
        let mut pos = vec![0usize; bvh.nodes().len()];
        for (p, &i) in order.iter().enumerate() {
            pos[i as usize] = p;
        }
        for (p, &i) in order.iter().enumerate() {
            let size = subtree_size(&bvh, i);
            let want = order.get(p + size).copied().unwrap_or(flat::NO_ESCAPE);
            let got = bvh.escapes()[flat::escape_index(i, oct)];
            assert_eq!(got, want, "node {i}, octant {oct}");
            assert!(got == flat::NO_ESCAPE || pos[got as usize] > p);
        }
    }
}

fn subtree_size(bvh: &FlatBvh, i: u32) -> usize {
    let n = &bvh.nodes()[i as usize];
    if n.is_leaf() {
        1
    } else {
        1 + subtree_size(bvh, i + 1) + subtree_size(bvh, n.right_or_first)
    }
}

/// Midpoint splits down to single triangles: on `deep_soup` a tree as deep as it has
/// triangles.
fn peeling() -> BuildOptions {
    BuildOptions {
        builder: BuilderKind::Midpoint,
        max_depth: 1000,
        max_leaf_size: 1,
        ..Default::default()
    }
}

/// A tree whose escape links were set by hand to none: the full stack, which does not
/// read them, traces it; the walks that do refuse it with the mismatch's message instead
/// of indexing past the links (they build links only when there are none yet).
#[test]
fn walks_name_missing_escape_links() {
    let tris = deep_soup(10);
    let mut bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let rays = common::rays_for(&tris, 3, 16);
    let full = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::FullStack)).hits;
    let err = std::panic::catch_unwind(|| {
        trace_ray(&bvh, &rays[0], &TraceOptions::closest(Traversal::Wide))
    })
    .expect_err("the wide walk ran without a wide layout");
    let msg = err.downcast_ref::<String>().cloned().unwrap_or_default();
    assert!(msg.contains("FlatBvh::build_wide"), "{msg}");
    bvh.set_escapes(Vec::new());
    assert_eq!(
        trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::FullStack)).hits,
        full
    );
    for tr in [Traversal::Stackless, Traversal::ShortStack(4)] {
        let err =
            std::panic::catch_unwind(|| trace_ray(&bvh, &rays[0], &TraceOptions::closest(tr)))
                .expect_err("a walk read escape links the tree does not have");
        let msg = err.downcast_ref::<String>().cloned().unwrap_or_default();
        assert!(
            msg.contains("escape links for") && msg.contains("flat::escape_links"),
            "{tr}: {msg}"
        );
    }
}

/// Every walk reads back as it prints (`short-stack(6)`), and as the command lines write
/// it (`short-stack:6`); sizes out of range and unknown names are errors.
#[test]
fn traversals_parse_as_they_print() {
    for t in [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(6),
        Traversal::Wide,
    ] {
        assert_eq!(t.to_string().parse::<Traversal>(), Ok(t), "{t}");
    }
    assert_eq!(
        "short-stack:6".parse::<Traversal>(),
        Ok(Traversal::ShortStack(6))
    );
    for bad in [
        "short-stack(0)",
        "short-stack:x",
        "short-stack(6",
        "sideways",
    ] {
        assert!(bad.parse::<Traversal>().is_err(), "{bad}");
    }
}
