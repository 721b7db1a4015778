//! Every traversal against brute force (exactly) and against the f64 oracle.

mod common;

use bvhtrace_core::oracle;
use bvhtrace_core::traverse::brute_force;
use bvhtrace_core::*;
use glam::Vec3;
use proptest::prelude::*;

const TRAVERSALS: [Traversal; 5] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(1),
    Traversal::ShortStack(2),
    Traversal::ShortStack(6),
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
    fn traversals_match_brute_force_and_the_oracle(tris in common::soup(), seed in any::<u64>(), b in 0usize..4) {
        let opts = BuildOptions { max_leaf_size: 3, ..BuildOptions::with_builder(BuilderKind::ALL[b]) };
        let bvh = FlatBvh::build(&tris, &opts).unwrap();
        let rays = common::rays_for(&tris, seed, 48);
        for ray in &rays {
            let expect = brute_force(&bvh, ray);
            prop_assert!(!expect.t.is_nan() && !expect.u.is_nan() && !expect.v.is_nan());
            if let Err(e) = agrees_with_oracle(&tris, ray, &expect) {
                return Err(TestCaseError::fail(format!("{e}\nray {ray:?}")));
            }
            for tr in TRAVERSALS {
                let (h, _) = trace_ray(&bvh, ray, tr, Query::Closest);
                // Equal to brute force, except where the f32 test is indeterminate or its t
                // ill-conditioned for a triangle involved (both answers then agree with the
                // oracle within f32's error): the box test may rightly cull an f32 hit whose
                // t lies outside the triangle's own box.
                let terr = |p: u32| tris.get(p as usize).map_or(0.0, |t| oracle::f32_t_error_bound(t, ray));
                let excused = h != expect
                    && agrees_with_oracle(&tris, ray, &h).is_ok()
                    && agrees_with_oracle(&tris, ray, &expect).is_ok()
                    && ([h.prim, expect.prim].iter().any(|&p| tris.get(p as usize).is_some_and(|t| oracle::f32_indeterminate(t, ray)))
                        || (h.t as f64 - expect.t as f64).abs() <= terr(h.prim) + terr(expect.prim));
                prop_assert!(h == expect || excused, "{} on {:?}: {:?} vs brute force {:?}", tr, ray, h, expect);
                let (a, _) = trace_ray(&bvh, ray, tr, Query::Any);
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
        .unwrap();
        for tr in TRAVERSALS {
            let (h, _) = trace_ray(
                &bvh,
                &Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::Z),
                tr,
                Query::Closest,
            );
            assert_eq!((h.prim, h.t), (1, 5.0), "{tr}");
            // Along the shared edge y = 0 at z = 5, from behind: both hit at t = 5; 4 wins.
            let (h, _) = trace_ray(
                &bvh,
                &Ray::new(Vec3::new(0.0, 0.0, 10.0), -Vec3::Z),
                tr,
                Query::Closest,
            );
            assert_eq!((h.prim, h.t), (4, 5.0), "{tr}");
        }
    }
    let o = oracle::closest_hit(&tris, &Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::Z));
    assert_eq!(o.prim, 1);
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
    let bvh = FlatBvh::build(&tris, &opts).unwrap();
    bvh.check_invariants().unwrap();
    // Deeper than any fixed 64-entry stack.
    assert!(bvh.depth > 64, "depth {}", bvh.depth);
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
    for ray in &rays {
        let expect = brute_force(&bvh, ray);
        for tr in TRAVERSALS {
            assert_eq!(
                trace_ray(&bvh, ray, tr, Query::Closest).0,
                expect,
                "{tr} {ray:?}"
            );
            assert_eq!(
                trace_ray(&bvh, ray, tr, Query::Any).0.is_hit(),
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
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let eye = Vec3::new(70.0, -60.0, 80.0);
    let rays: Vec<Ray> = (0..64 * 64)
        .map(|i| {
            let target = Vec3::new((i % 64) as f32 * 2.2, (i / 64) as f32 * 2.2, 0.0);
            Ray::new(eye, target - eye)
        })
        .collect();
    let nodes = |tr| {
        let (_, c) = trace_batch_counted(&bvh, &rays, tr, Query::Closest);
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
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let rays = common::rays_for(&tris, 99, 500);
    for tr in TRAVERSALS {
        let batch = trace_batch(&bvh, &rays, tr, Query::Closest);
        for (r, h) in rays.iter().zip(&batch) {
            assert_eq!(*h, trace_ray(&bvh, r, tr, Query::Closest).0);
        }
    }
}
