//! The spatial-split builder (`BuilderKind::Sbvh`): the same answers as the binned SAH
//! tree and the f64 oracle on scenes where splits matter, every triangle covered by its
//! references, the memory budget, a lower SAH cost, determinism, and two levels.

mod common;

use bvhtrace_core::oracle;
use bvhtrace_core::*;
use glam::{Affine3A, Quat, Vec3};

const WALKS: [Traversal; 5] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(1),
    Traversal::ShortStack(6),
    Traversal::Wide,
];

fn sbvh(budget: f32) -> BuildOptions {
    BuildOptions {
        split_budget: budget,
        ..BuildOptions::with_builder(BuilderKind::Sbvh)
    }
}

/// A tiny xorshift in [0, 1).
fn rng(seed: u64) -> impl FnMut() -> f32 {
    let mut s = seed | 1;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A grid of small triangles crossed by a few huge ones (long, thin, at angles): the
/// huge ones' boxes overlap everything, which is what spatial splits are for.
fn big_over_small() -> Vec<Triangle> {
    let mut t = Vec::new();
    for i in 0..40 {
        for j in 0..40 {
            let p = Vec3::new(i as f32, j as f32, ((i * 7 + j * 3) % 5) as f32 * 0.1);
            t.push([p, p + Vec3::X * 0.6, p + Vec3::Y * 0.6]);
        }
    }
    for k in 0..12 {
        let y = k as f32 * 3.3;
        let z = 0.05 + k as f32 * 0.07;
        t.push([
            Vec3::new(-1.0, y, z),
            Vec3::new(41.0, 40.0 - y, z + 0.3),
            Vec3::new(-1.0, y + 0.4, z),
        ]);
        // A huge triangle standing across the grid.
        t.push([
            Vec3::new(y, -1.0, -2.0),
            Vec3::new(40.0 - y, 41.0, -2.0),
            Vec3::new(20.0, 20.0, 6.0 + k as f32),
        ]);
    }
    t
}

/// Random slivers: long, needle-thin triangles in every direction.
fn slivers(n: usize, seed: u64) -> Vec<Triangle> {
    let mut r = rng(seed);
    (0..n)
        .map(|_| {
            let a = Vec3::new(r(), r(), r()) * 20.0;
            let d = (Vec3::new(r(), r(), r()) - 0.5).normalize_or(Vec3::X) * (5.0 + 15.0 * r());
            let side = (Vec3::new(r(), r(), r()) - 0.5) * 0.05;
            [a, a + d, a + d * 0.5 + side]
        })
        .collect()
}

fn few_huge(k: usize) -> Vec<Triangle> {
    let mut t = Vec::new();
    for i in 0..50 {
        for j in 0..50 {
            let p = Vec3::new(i as f32, j as f32, ((i * 7 + j * 3) % 5) as f32 * 0.1);
            t.push([p, p + Vec3::X * 0.6, p + Vec3::Y * 0.6]);
        }
    }
    for q in 0..k {
        let y = q as f32 * 50.0 / k as f32;
        t.push([
            Vec3::new(y, -1.0, -2.0),
            Vec3::new(50.0 - y, 51.0, -2.0),
            Vec3::new(25.0, 25.0, 6.0 + q as f32),
        ]);
    }
    t
}

/// Long thin triangles along the diagonal of the xy square, side by side: every box is
/// the whole square, the triangles themselves are disjoint.
fn diagonals(n: usize) -> Vec<Triangle> {
    (0..n)
        .map(|i| {
            let o = Vec3::new(i as f32 * 0.5, -(i as f32) * 0.5, 0.0);
            [
                o,
                o + Vec3::new(100.0, 100.0, 0.0),
                o + Vec3::new(0.3, 0.0, 0.1),
            ]
        })
        .collect()
}

/// Two triangles of the quad `a, b, c, d` (in order around it).
fn quad(t: &mut Vec<Triangle>, a: Vec3, b: Vec3, c: Vec3, d: Vec3) {
    t.push([a, b, c]);
    t.push([a, c, d]);
}

/// An axis-aligned box rotated about y by `angle`, standing on the floor at `centre`.
fn block(t: &mut Vec<Triangle>, centre: Vec3, half: Vec3, angle: f32) {
    let m = Affine3A::from_rotation_translation(Quat::from_rotation_y(angle), centre);
    let p = |x: f32, y: f32, z: f32| m.transform_point3(Vec3::new(x, y, z) * half);
    let c = [
        p(-1.0, 0.0, -1.0),
        p(1.0, 0.0, -1.0),
        p(1.0, 0.0, 1.0),
        p(-1.0, 0.0, 1.0),
        p(-1.0, 2.0, -1.0),
        p(1.0, 2.0, -1.0),
        p(1.0, 2.0, 1.0),
        p(-1.0, 2.0, 1.0),
    ];
    for [a, b, cc, d] in [
        [0, 1, 2, 3],
        [4, 7, 6, 5],
        [0, 4, 5, 1],
        [1, 5, 6, 2],
        [2, 6, 7, 3],
        [3, 7, 4, 0],
    ] {
        quad(t, c[a], c[b], c[cc], c[d]);
    }
}

/// A Cornell box: five walls of two triangles each, a light and two rotated blocks (as
/// `bvhtrace_scene`'s `builtin:cornell`).
fn cornell() -> Vec<Triangle> {
    let mut t = Vec::new();
    let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    let (h, l) = (0.25, 1.99);
    for [a, b, c, d] in [
        [
            v(-1., 0., -1.),
            v(1., 0., -1.),
            v(1., 0., 1.),
            v(-1., 0., 1.),
        ],
        [
            v(-1., 2., -1.),
            v(-1., 2., 1.),
            v(1., 2., 1.),
            v(1., 2., -1.),
        ],
        [
            v(-1., 0., -1.),
            v(-1., 2., -1.),
            v(1., 2., -1.),
            v(1., 0., -1.),
        ],
        [
            v(-1., 0., -1.),
            v(-1., 0., 1.),
            v(-1., 2., 1.),
            v(-1., 2., -1.),
        ],
        [v(1., 0., -1.), v(1., 2., -1.), v(1., 2., 1.), v(1., 0., 1.)],
        [v(-h, l, -h), v(h, l, -h), v(h, l, h), v(-h, l, h)],
    ] {
        quad(&mut t, a, b, c, d);
    }
    block(&mut t, v(0.35, 0.0, 0.3), v(0.3, 0.3, 0.3), 0.3);
    block(&mut t, v(-0.35, 0.0, -0.3), v(0.3, 0.6, 0.3), -0.3);
    t
}

/// Degenerate references: zero-area triangles (points, segments), triangles lying in an
/// axis plane (flat boxes), exact copies, all crossing each other.
fn degenerate() -> Vec<Triangle> {
    let mut t = Vec::new();
    for i in 0..60 {
        let x = i as f32 * 0.25;
        let p = Vec3::new(x, 1.0, 2.0);
        t.push([p, p, p]);
        t.push([
            Vec3::new(x, 0.0, 0.0),
            Vec3::new(x, 5.0, 5.0),
            Vec3::new(x, 2.5, 2.5),
        ]);
        t.push([
            Vec3::new(0.0, x, 0.0),
            Vec3::new(15.0, x, 0.0),
            Vec3::new(7.0, x, 15.0),
        ]);
        t.push([
            Vec3::new(0.0, 0.0, x),
            Vec3::new(15.0, 15.0, x),
            Vec3::new(15.0, 0.0, x),
        ]);
    }
    let copy = t[2];
    t.extend([copy; 5]);
    t
}

fn scenes() -> Vec<(&'static str, Vec<Triangle>)> {
    vec![
        ("big over small", big_over_small()),
        ("slivers", slivers(600, 5)),
        ("cornell", cornell()),
        ("degenerate", degenerate()),
    ]
}

/// Rays at the scene's triangles (with axis-parallel ones), and a camera's rays.
fn rays(tris: &[Triangle], seed: u64) -> Vec<Ray> {
    let mut out = common::rays_for(tris, seed, 3000);
    let (lo, hi) = tris
        .iter()
        .flatten()
        .fold((Vec3::MAX, Vec3::MIN), |(l, h), p| (l.min(*p), h.max(*p)));
    let c = (lo + hi) * 0.5;
    let eye = c + Vec3::new(0.3, 0.4, 1.7) * (hi - lo).max_element().max(1e-3);
    for y in 0..40 {
        for x in 0..40 {
            let target = lo + (hi - lo) * Vec3::new(x as f32 / 39.0, y as f32 / 39.0, 0.5);
            out.push(Ray::new(eye, target - eye));
        }
    }
    out
}

/// An f32 closest hit against the f64 oracle: the same primitive at about the same `t`,
/// or a difference f32 cannot decide.
fn agrees_with_oracle(tris: &[Triangle], ray: &Ray, hit: &Hit) -> bool {
    let o = oracle::closest_hit(tris, ray);
    if o.prim == hit.prim {
        return !hit.is_hit()
            || (hit.t as f64 - o.t).abs()
                <= 1e-5 * (o.t.abs() + 1.0)
                    + oracle::f32_t_error_bound(&tris[o.prim as usize], ray);
    }
    let hits = oracle::all_hits(tris, ray);
    let indeterminate = |p: u32| {
        tris.get(p as usize)
            .is_some_and(|t| oracle::f32_indeterminate(t, ray))
    };
    indeterminate(o.prim)
        || indeterminate(hit.prim)
        || (o.is_hit()
            && hit.is_hit()
            && hits.iter().find(|h| h.1 == hit.prim).is_some_and(|h| {
                (h.0 - o.t).abs()
                    <= 1e-5 * (o.t.abs() + 1.0)
                        + oracle::f32_t_error_bound(&tris[o.prim as usize], ray)
                        + oracle::f32_t_error_bound(&tris[hit.prim as usize], ray)
            }))
}

#[test]
fn closest_and_any_hits_equal_the_oracle_and_binned_sah() {
    for (name, tris) in scenes() {
        let sah = FlatBvh::build(&tris, &BuildOptions::default())
            .unwrap()
            .with_wide();
        for (budget, leaf) in [(0.3, 8), (1.0, 1), (4.0, 3)] {
            let opts = BuildOptions {
                max_leaf_size: leaf,
                ..sbvh(budget)
            };
            let bvh = FlatBvh::build(&tris, &opts).unwrap().with_wide();
            bvh.check_invariants().unwrap();
            let w = bvh.wide().unwrap();
            w.check_invariants(&bvh).unwrap();
            let (mut hits, mut departures, mut sah_departures) = (0, 0, 0);
            for ray in rays(&tris, 0x5b1 + leaf as u64) {
                // Brute force over the references equals brute force over the triangles:
                // duplicates tie exactly, and the tie rule is order-free.
                let want = brute_force(&sah, &ray, Precision::WatertightF32);
                let brute = brute_force(&bvh, &ray, Precision::WatertightF32);
                assert_eq!(
                    (
                        brute.prim,
                        brute.t.to_bits(),
                        brute.u.to_bits(),
                        brute.v.to_bits()
                    ),
                    (
                        want.prim,
                        want.t.to_bits(),
                        want.u.to_bits(),
                        want.v.to_bits()
                    ),
                    "{name}: brute force over the references for {ray:?}"
                );
                assert!(agrees_with_oracle(&tris, &ray, &want), "{name}: {ray:?}");
                hits += usize::from(want.is_hit());
                for walk in WALKS {
                    let (h, _) = trace_ray(&bvh, &ray, &TraceOptions::closest(walk));
                    let (s, _) = trace_ray(&sah, &ray, &TraceOptions::closest(walk));
                    let same =
                        |a: &Hit, b: &Hit| a.prim == b.prim && a.t.to_bits() == b.t.to_bits();
                    if !same(&h, &want) {
                        // Only where f32 cannot decide, as between walks of one tree.
                        assert!(
                            common::f32_departure(&tris, &ray, &h, &want)
                                && agrees_with_oracle(&tris, &ray, &h),
                            "{name} budget {budget} {walk}: {h:?} vs {want:?} for {ray:?}"
                        );
                        departures += 1;
                    }
                    if !same(&s, &want) {
                        assert!(
                            common::f32_departure(&tris, &ray, &s, &want),
                            "{name}: SAH {walk}"
                        );
                        sah_departures += 1;
                    }
                    // Any-hit finds a hit exactly when the same walk's closest hit does.
                    let (a, _) = trace_ray(&bvh, &ray, &TraceOptions::new(walk, Query::Any));
                    assert_eq!(a.is_hit(), h.is_hit(), "{name} {walk} any-hit {ray:?}");
                    if a.is_hit() {
                        assert!(a.t >= ray.t_min && a.t < ray.t_max);
                    }
                }
            }
            assert!(hits > 1000, "{name}: only {hits} hits");
            // As rare as the binned SAH tree's (each needs a ray within f32 rounding of an
            // edge, or of another triangle).
            eprintln!(
                "{name} budget {budget}: {hits} hits, departures: {departures} (SAH {sah_departures})"
            );
            assert!(
                departures <= sah_departures + hits / 1000,
                "{name}: {departures} departures, binned SAH {sah_departures}"
            );
        }
    }
}

#[test]
fn every_triangle_is_referenced_within_the_budget() {
    for (name, tris) in scenes() {
        let n = tris.len();
        for budget in [0.0, 0.05, 0.3, 1.0, 16.0] {
            let bvh = FlatBvh::build(&tris, &sbvh(budget)).unwrap();
            bvh.check_invariants().unwrap();
            let refs = bvh.triangles().len();
            assert!(
                refs <= n + (budget as f64 * n as f64).floor() as usize,
                "{name} budget {budget}: {refs} references for {n} triangles"
            );
            let mut seen = vec![0; n];
            for t in bvh.triangles() {
                seen[t.prim as usize] += 1;
                assert_eq!(t.corners(), tris[t.prim as usize], "{name}: corners");
            }
            assert!(seen.iter().all(|&c| c >= 1), "{name}: a triangle is lost");
            let s = BvhStats::of(&bvh);
            assert_eq!((s.triangles, s.primitives), (refs, n));
            if budget == 0.0 {
                assert_eq!(refs, n, "{name}: no budget, no duplicates");
            }
        }
    }
    // Splits do happen where they pay.
    let t = big_over_small();
    assert!(FlatBvh::build(&t, &sbvh(0.3)).unwrap().triangles().len() > t.len());
}

/// The leaves that hold each triangle, with their boxes.
fn leaf_boxes(bvh: &FlatBvh, n: usize) -> Vec<Vec<Aabb>> {
    let mut out = vec![Vec::new(); n];
    for node in bvh.nodes() {
        if node.is_leaf() {
            let f = node.right_or_first as usize;
            for t in &bvh.triangles()[f..f + node.count() as usize] {
                out[t.prim as usize].push(node.aabb());
            }
        }
    }
    out
}

#[test]
fn every_point_of_a_triangle_lies_in_one_of_its_leaves() {
    for (name, tris) in scenes() {
        for budget in [0.3, 4.0] {
            let bvh = FlatBvh::build(&tris, &sbvh(budget)).unwrap();
            let boxes = leaf_boxes(&bvh, tris.len());
            let mut clipped = 0;
            for (p, t) in tris.iter().enumerate() {
                let full = Aabb::from_triangle(t);
                clipped += boxes[p].iter().filter(|b| !b.contains(&full)).count();
                let [a, b, c] = t.map(|v| v.as_dvec3());
                // Barycentric grid with steps of 1/32 (exact in f64), corners and edges
                // included; a point counts as inside a box within 1e-12 of its magnitude.
                for i in 0..=32 {
                    for j in 0..=32 - i {
                        let (u, v) = (i as f64 / 32.0, j as f64 / 32.0);
                        let q = a + (b - a) * u + (c - a) * v;
                        let slack = 1e-12 * q.abs().max_element().max(1e-30);
                        let inside = boxes[p].iter().any(|bx| {
                            (0..3).all(|k| {
                                bx.min[k] as f64 - slack <= q[k] && q[k] <= bx.max[k] as f64 + slack
                            })
                        });
                        assert!(inside, "{name}: point {q:?} of triangle {p} in no leaf");
                    }
                }
            }
            if name != "cornell" && name != "degenerate" {
                assert!(clipped > 0, "{name}: no reference was clipped");
            }
        }
    }
}

#[test]
fn spatial_splits_lower_the_sah_cost_of_overlapping_triangles() {
    for (name, tris) in [
        ("big over small", big_over_small()),
        ("few huge", few_huge(6)),
    ] {
        // Each cost convention with the builds that optimise it: PBRT's (the default
        // options) and traversal 1 (tinybvh's figure).
        for (ct, bound) in [(0.125, 0.9), (1.0, 0.95)] {
            let cost = |b| {
                let opts = BuildOptions {
                    cost_traversal: ct,
                    ..BuildOptions::with_builder(b)
                };
                let s = BvhStats::of(&FlatBvh::build(&tris, &opts).unwrap());
                if ct == 1.0 {
                    s.sah_cost
                } else {
                    s.sah_cost_pbrt
                }
            };
            let (sah, sbvh) = (cost(BuilderKind::Sah), cost(BuilderKind::Sbvh));
            eprintln!("{name}, traversal cost {ct}: SAH {sah:.3}, SBVH {sbvh:.3}");
            assert!(
                sbvh < bound * sah,
                "{name} ({ct}): SBVH {sbvh} against SAH {sah}"
            );
        }
    }
    // A bigger budget buys a lower cost where the duplicates are what it takes.
    let tris = diagonals(200);
    let cost = |budget| BvhStats::of(&FlatBvh::build(&tris, &sbvh(budget)).unwrap()).sah_cost_pbrt;
    let (none, some, more) = (cost(0.0), cost(1.0), cost(4.0));
    eprintln!("diagonals: budget 0 {none:.3}, 1 {some:.3}, 4 {more:.3}");
    assert!(more < some && some < 0.6 * none);
    // Where the boxes hardly overlap, the SBVH is about binned SAH.
    let tris = cornell();
    let s = |b| BvhStats::of(&FlatBvh::build(&tris, &BuildOptions::with_builder(b)).unwrap());
    let (sah, sbvh) = (
        s(BuilderKind::Sah).sah_cost_pbrt,
        s(BuilderKind::Sbvh).sah_cost_pbrt,
    );
    eprintln!("cornell: SAH {sah:.3}, SBVH {sbvh:.3}");
    assert!(sbvh <= sah * 1.05, "cornell: SBVH {sbvh} against SAH {sah}");
}

#[test]
fn the_tree_does_not_depend_on_the_thread_count() {
    // Big enough for the parallel binning (32K references) and forks everywhere.
    let mut tris = slivers(40_000, 3);
    tris.extend(big_over_small());
    let opts = BuildOptions {
        parallel_threshold: 256,
        ..sbvh(0.3)
    };
    let build_with = |threads| common::build_on_threads(&tris, &opts, threads);
    let one = build_with(1);
    assert!(one.triangles().len() > tris.len());
    assert!(one == build_with(2), "trees differ between 1 and 2 threads");
    assert!(one == build_with(3), "trees differ between 1 and 3 threads");
}

#[test]
fn depth_and_leaf_size_bounds_hold() {
    let tris = big_over_small();
    for (max_depth, leaf) in [(3, 8), (10, 1), (64, 2)] {
        let opts = BuildOptions {
            max_depth,
            max_leaf_size: leaf,
            ..sbvh(1.0)
        };
        let bvh = FlatBvh::build(&tris, &opts).unwrap();
        bvh.check_invariants().unwrap();
        let refs = bvh.triangles().len();
        let bound = max_depth + (refs as f64).log2().ceil() as usize + 1;
        assert!(
            bvh.depth() as usize <= bound,
            "depth {} > {bound}",
            bvh.depth()
        );
        assert!(bvh.nodes().iter().all(|n| n.count() as usize <= leaf));
    }
    // Identical triangles: no spatial split separates them, only balanced object splits.
    let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let bvh = FlatBvh::build(&vec![t; 20_000], &sbvh(0.3)).unwrap();
    bvh.check_invariants().unwrap();
    assert!(bvh.depth() <= 16, "depth {}", bvh.depth());
}

#[test]
fn bad_budgets_are_refused() {
    let tris = cornell();
    for b in [-0.1, f32::NAN, f32::INFINITY, 16.5] {
        let e = FlatBvh::build(&tris, &sbvh(b)).unwrap_err();
        assert!(matches!(e, BuildError::Options(_)), "{b}: {e}");
        assert!(e.to_string().contains("split_budget"), "{e}");
    }
    assert!("sbvh".parse::<BuilderKind>() == Ok(BuilderKind::Sbvh));
    assert!("sbhv".parse::<BuilderKind>().unwrap_err().contains("sbvh"));
}

#[test]
fn two_levels_over_sbvh_meshes_answer_as_the_flattened_scene() {
    let meshes = vec![big_over_small(), cornell()];
    let instances = vec![
        Instance::new(0, Affine3A::IDENTITY),
        Instance::new(
            1,
            Affine3A::from_scale_rotation_translation(
                Vec3::splat(5.0),
                Quat::from_rotation_y(0.4),
                Vec3::new(10.0, 10.0, 3.0),
            ),
        ),
        Instance::new(0, Affine3A::from_translation(Vec3::new(0.0, 0.0, 20.0))),
    ];
    let ib = InstancedBvh::build(&meshes, instances.clone(), &sbvh(0.3)).unwrap();
    ib.bvh().check_invariants().unwrap();
    let slot = ib.meshes()[0];
    assert!(slot.triangles > slot.primitives, "mesh 0 has no duplicate");
    assert_eq!(slot.primitives as usize, meshes[0].len());
    let n: usize = instances
        .iter()
        .map(|i| meshes[i.mesh as usize].len())
        .sum();
    assert_eq!(ib.instanced_primitives(), n as u64);
    // Primitive ids as the flattened scene numbers them.
    assert_eq!(ib.locate(meshes[0].len() as u32), Some((1, 0)));
    let world: Vec<Triangle> = instances
        .iter()
        .flat_map(|i| {
            meshes[i.mesh as usize]
                .iter()
                .map(move |t| t.map(|p| i.transform.transform_point3(p)))
        })
        .collect();
    let rays = rays(&world, 77);
    let check = |ib: &InstancedBvh| {
        let bvh = ib.bvh().clone().with_wide();
        bvh.wide().unwrap().check_invariants(&bvh).unwrap();
        let mut hits = 0;
        for ray in &rays {
            let want = brute_force(&bvh, ray, Precision::WatertightF32);
            hits += usize::from(want.is_hit());
            if want.is_hit() {
                let w = ib.world_triangle(want.prim).unwrap();
                assert!(
                    w.iter()
                        .zip(&world[want.prim as usize])
                        .all(|(a, b)| (*a - *b).length() < 1e-3)
                );
            }
            for walk in WALKS {
                let (h, _) = trace_ray(&bvh, ray, &TraceOptions::closest(walk));
                assert!(
                    (h.prim == want.prim && h.t.to_bits() == want.t.to_bits())
                        || common::f32_departure(&world, ray, &h, &want),
                    "{walk}: {h:?} vs brute force {want:?}"
                );
            }
        }
        assert!(hits > 1000, "{hits} hits");
    };
    check(&ib);
    // Refit (vertices moved: the boxes grow back to whole triangles) and move.
    let mut moved = ib.clone();
    let shifted: Vec<Triangle> = meshes[0]
        .iter()
        .map(|t| t.map(|p| p + Vec3::new(0.0, 0.0, 0.5 * (p.x * 0.1).sin())))
        .collect();
    moved.refit_mesh(0, &shifted).unwrap();
    moved.bvh().check_invariants().unwrap();
    assert!(moved.refit_mesh(0, &shifted[1..]).is_err());
    moved
        .set_transforms(&instances.iter().map(|i| i.transform).collect::<Vec<_>>())
        .unwrap();
    moved.bvh().check_invariants().unwrap();
}
