//! Hit filters (`trace_rays_filtered`): every walk, closest and any hit, one level and two,
//! answers what brute force answers with the same filter, bit for bit; a rejected triangle
//! is as if it were not there; the filter sees the instance and the mesh's primitive.

use bvhtrace_core::{
    BuildOptions, Candidate, FlatBvh, Hit, Instance, InstancedBvh, Query, Ray, TraceOptions,
    Triangle, brute_force, brute_force_filtered, trace_rays, trace_rays_filtered,
};
use glam::{Affine3A, Quat, Vec3};

mod common;

use common::{WALKS, same};

/// Random overlapping triangles in a 10-unit cube: most rays cross several.
fn soup(n: usize, seed: u64) -> Vec<Triangle> {
    let mut rnd = common::xorshift(seed);
    (0..n)
        .map(|_| {
            let c = Vec3::new(rnd(), rnd(), rnd()) * 10.0;
            let p = |r: &mut dyn FnMut() -> f32| c + Vec3::new(r(), r(), r()) * 2.0 - Vec3::ONE;
            [p(&mut rnd), p(&mut rnd), p(&mut rnd)]
        })
        .collect()
}

fn rays(n: usize) -> Vec<Ray> {
    let mut rnd = common::xorshift(0x5eed);
    (0..n)
        .map(|_| {
            let o = Vec3::new(rnd(), rnd(), rnd()) * 30.0 - Vec3::splat(10.0);
            let target = Vec3::new(rnd(), rnd(), rnd()) * 10.0;
            Ray::new(o, target - o)
        })
        .collect()
}

/// Every walk with `filter` against brute force with it; returns the filtered hits and how
/// many hits the filter changed.
fn check(
    bvh: &FlatBvh,
    rays: &[Ray],
    filter: &(dyn Fn(&Candidate) -> bool + Sync),
) -> (usize, usize) {
    let bvh = bvh.clone().with_wide();
    let f = &filter;
    let want: Vec<Hit> = (rays.iter())
        .map(|r| brute_force_filtered(&bvh, r, Default::default(), Some(&f)))
        .collect();
    let plain: Vec<Hit> = rays
        .iter()
        .map(|r| brute_force(&bvh, r, Default::default()))
        .collect();
    for w in WALKS {
        let got = trace_rays_filtered(&bvh, rays, &TraceOptions::closest(w), Some(&f)).hits;
        for (k, (g, e)) in got.iter().zip(&want).enumerate() {
            assert!(same(g, e), "{w} ray {k}: {g:?} != brute force {e:?}");
        }
        let any = trace_rays_filtered(&bvh, rays, &TraceOptions::new(w, Query::Any), Some(&f));
        for (k, (g, e)) in any.hits.iter().zip(&want).enumerate() {
            assert_eq!(g.is_hit(), e.is_hit(), "{w} any-hit ray {k}");
        }
        // Without a filter, the walks answer as before.
        let unfiltered = trace_rays(&bvh, rays, &TraceOptions::closest(w)).hits;
        assert!(
            unfiltered.iter().zip(&plain).all(|(a, b)| same(a, b)),
            "{w} unfiltered"
        );
    }
    let hits = want.iter().filter(|h| h.is_hit()).count();
    let changed = want.iter().zip(&plain).filter(|(a, b)| !same(a, b)).count();
    (hits, changed)
}

#[test]
fn every_walk_filters_as_brute_force_does() {
    let tris = soup(600, 7);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let rays = rays(3000);
    // By primitive, by position on the triangle, by distance: three kinds of rule.
    let rules: [&(dyn Fn(&Candidate) -> bool + Sync); 3] =
        [&|c| c.prim % 3 != 0, &|c| c.u + 0.5 * c.v < 0.6, &|c| {
            c.t.to_bits() % 2 == 0
        }];
    for (i, rule) in rules.into_iter().enumerate() {
        let (hits, changed) = check(&bvh, &rays, rule);
        assert!(
            hits > 500 && changed > 100,
            "rule {i}: {hits} hits, {changed} changed"
        );
    }
    // Rejecting everything is a scene without triangles.
    let (hits, _) = check(&bvh, &rays, &|_| false);
    assert_eq!(hits, 0);
}

#[test]
fn two_level_filters_see_the_instance_and_the_mesh_primitive() {
    let meshes = vec![soup(200, 11), soup(150, 12)];
    let instances: Vec<Instance> = (0..6)
        .map(|k| {
            let m = Affine3A::from_rotation_translation(
                Quat::from_rotation_y(0.7 * k as f32),
                Vec3::new(k as f32 * 3.0 - 8.0, 0.0, 0.0),
            );
            Instance::new(k % 2, m)
        })
        .collect();
    let ib = InstancedBvh::build(&meshes, instances, &BuildOptions::default()).unwrap();
    let bvh = ib.bvh();
    let rays = rays(3000);
    // Instance 2 only on its mesh's even triangles; the others whole.
    let rule = |c: &Candidate| {
        let inst = c.instance.expect("two levels name the instance");
        let base = bvh.instances()[inst as usize].prim_base;
        assert_eq!(c.prim, base + c.mesh_prim);
        inst != 2 || c.mesh_prim.is_multiple_of(2)
    };
    let (hits, changed) = check(bvh, &rays, &rule);
    assert!(hits > 500 && changed > 20, "{hits} hits, {changed} changed");
}
