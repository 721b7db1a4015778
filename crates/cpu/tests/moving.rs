//! Moving meshes in the CPU layout answer as the core's moving walk (`MotionBvh::trace`):
//! closest hits bit for bit (but for the walks' one documented exception, judged with the
//! triangles at the ray's time), any hits a hit where the closest is, on every
//! instruction set.

mod common;

use bvhtrace_core::motion::{MotionBvh, MotionInstancedBvh, MovingInstance};
use bvhtrace_core::{BuildOptions, BuilderKind, Hit, MotionMesh, Query, Ray, TimeBounds, Triangle};
use bvhtrace_cpu::{Isa, MovingCpuBvh, MovingInstancesCpuBvh};
use common::{f32_departure, rays_for, same, uv_sphere, xorshift};
use glam::{Mat4, Vec3};
use proptest::prelude::*;

/// Times that cover the shutter's ends, the steps, between them, outside and NaN.
fn times_for(n: usize, steps: usize, seed: u64) -> Vec<f32> {
    let mut rnd = xorshift(seed | 1);
    let fixed = [0.0, 1.0, -0.5, 1.5, f32::NAN, 0.5, 1.0 / (steps - 1) as f32];
    (0..n)
        .map(|i| match i % 9 {
            k if k < fixed.len() && i % 2 == 0 => fixed[k],
            _ => rnd(),
        })
        .collect()
}

/// Every instruction set's answers, equal to the bit, and the first of them.
fn every_isa(bvh: &MovingCpuBvh, rays: &[Ray], times: &[f32], q: Query) -> Vec<Hit> {
    let isas = Isa::all_available();
    let first = bvh.trace_rays_with(rays, times, q, isas[0]);
    for &isa in &isas[1..] {
        let h = bvh.trace_rays_with(rays, times, q, isa);
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

/// Checks the layout of `mesh` (built with `opts`, both bounds) against the core walk on
/// `rays` at `times` (with `strict`, closest hits to the bit, no exception); returns the
/// closest hits found.
fn check_as(
    mesh: &MotionMesh,
    opts: &BuildOptions,
    rays: &[Ray],
    times: &[f32],
    strict: bool,
) -> usize {
    let mut found = 0;
    for bounds in [TimeBounds::Linear, TimeBounds::Merged] {
        let m = MotionBvh::build(mesh, opts, bounds).expect("built");
        let bvh = MovingCpuBvh::from_motion(&m).expect("converted");
        assert_eq!(bvh.time_steps(), mesh.time_steps());
        let want = m.trace_rays(rays, times, Query::Closest);
        let got = every_isa(&bvh, rays, times, Query::Closest);
        for i in 0..rays.len() {
            let (g, w) = (&got[i], &want[i]);
            if !same(g, w) {
                let at = mesh.at(times[i]);
                assert!(
                    !strict && f32_departure(&at, &rays[i], g, w),
                    "{bounds:?}: ray {i} {:?} at {}: {g:?}, the core walk {w:?}",
                    rays[i],
                    times[i]
                );
            }
        }
        found += got.iter().filter(|h| h.is_hit()).count();
        // Any hits agree with the closest hit on hit or miss (and so with the core walk's
        // wherever the closest hits are the same).
        let got_any = every_isa(&bvh, rays, times, Query::Any);
        for i in 0..rays.len() {
            assert_eq!(
                got_any[i].is_hit(),
                got[i].is_hit(),
                "{bounds:?}: any hit, ray {i} {:?} at {}",
                rays[i],
                times[i]
            );
        }
    }
    found
}

/// [`check_as`] with the walks' exception.
fn check(mesh: &MotionMesh, opts: &BuildOptions, rays: &[Ray], times: &[f32]) -> usize {
    check_as(mesh, opts, rays, times, false)
}

/// `tris` at `steps` steps, each corner moved by its own random offset up to `reach`.
fn moved(tris: &[Triangle], steps: usize, reach: f32, seed: u64) -> MotionMesh {
    let mut rnd = xorshift(seed | 1);
    let mut jitter = || (Vec3::new(rnd(), rnd(), rnd()) - 0.5) * 2.0 * reach;
    let out = (0..steps)
        .map(|k| match k {
            0 => tris.to_vec(),
            _ => tris.iter().map(|t| t.map(|v| v + jitter())).collect(),
        })
        .collect();
    MotionMesh::new(out).expect("finite steps")
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn moving_soups_give_the_core_walks_hits(
        tris in common::soup(),
        steps in 2usize..5,
        reach in prop::sample::select(vec![0.0f32, 1e-3, 0.5, 20.0]),
        seed in 1u64..1000,
    ) {
        let mesh = moved(&tris, steps, reach, seed);
        let rays = rays_for(&tris, seed, 300);
        let times = times_for(rays.len(), steps, seed);
        check(&mesh, &BuildOptions::default(), &rays, &times);
    }
}

#[test]
fn a_moving_sphere_gives_the_core_walks_hits() {
    // A sphere that travels its own size and grows, over 5 steps; rays at it from around.
    let sphere = uv_sphere(24, 1.0, Vec3::ZERO);
    let steps: Vec<Vec<Triangle>> = (0..5)
        .map(|k| {
            let (shift, grow) = (Vec3::new(0.6 * k as f32, 0.1, 0.0), 1.0 + 0.1 * k as f32);
            sphere.iter().map(|t| t.map(|v| v * grow + shift)).collect()
        })
        .collect();
    let mesh = MotionMesh::new(steps).expect("finite");
    let rays = rays_for(&mesh.at(0.5), 7, 4000);
    let times = times_for(rays.len(), 5, 7);
    let found = check(&mesh, &BuildOptions::default(), &rays, &times);
    assert!(found > 2000, "{found} hits of 2 x 4000 rays");
}

#[test]
fn long_leaves_split_into_runs_keep_their_leaf_boxes() {
    // One leaf of 300 triangles: the layout splits it into runs under a node, each boxed
    // by the leaf's boxes at every step.
    let tris = uv_sphere(10, 1.0, Vec3::ZERO);
    let mesh = moved(&tris, 3, 0.05, 5);
    let opts = BuildOptions {
        max_leaf_size: 512,
        builder: BuilderKind::Median,
        ..BuildOptions::default()
    };
    let rays = rays_for(&tris, 5, 2000);
    let times = times_for(rays.len(), 3, 5);
    assert!(check(&mesh, &opts, &rays, &times) > 1000);
}

#[test]
fn hits_at_the_origin_take_their_leaf_boxes_at_the_rays_time() {
    // Planes at `x = 3^(i - 40)` drifting along x, rays from just beside them: hits at or
    // behind the origin that f32 rounds into the interval, which only the binary leaf's
    // box at the ray's time refuses, as the core walk does.
    let (flat, rays) = common::planes_at_origins();
    let tris: Vec<Triangle> = (flat.triangles().iter()).map(|t| t.corners()).collect();
    let later: Vec<Triangle> = tris.iter().map(|t| t.map(|v| v * 1.0000005)).collect();
    let mesh = MotionMesh::new(vec![tris, later]).expect("finite");
    let opts = BuildOptions {
        builder: BuilderKind::Midpoint,
        max_depth: 1000,
        max_leaf_size: 1,
        ..BuildOptions::default()
    };
    let mut rnd = xorshift(23);
    let times: Vec<f32> = rays.iter().map(|_| rnd()).collect();
    check_as(&mesh, &opts, &rays, &times, true);
}

#[test]
fn empty_and_one_triangle_meshes() {
    let tri = [
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ];
    let up = tri.map(|v| v + Vec3::Y);
    let mesh = MotionMesh::new(vec![vec![tri], vec![up]]).expect("finite");
    let rays = vec![Ray::new(Vec3::new(0.0, 0.5, 5.0), Vec3::NEG_Z); 4];
    let times = [0.0, 1.0, 0.5, f32::NAN];
    check(&mesh, &BuildOptions::default(), &rays, &times);
    let bvh = MovingCpuBvh::from_motion(
        &MotionBvh::build(&mesh, &BuildOptions::default(), TimeBounds::Linear).expect("built"),
    )
    .expect("converted");
    let hits = bvh.trace_rays(&rays, &times, Query::Closest);
    assert_eq!(hits[0].t, 5.0);
    assert!(
        hits[1].is_hit() && hits[1].v < hits[0].v,
        "moved up: {hits:?}"
    );
    assert!(!hits[3].is_hit(), "a NaN time is not traced");
}

/// Checks moving instances in the layout against the core walk on `rays` at `times`, with
/// both bounds (merged only where nothing moves); returns the closest hits found.
fn check_instances(
    meshes: &[Vec<Triangle>],
    instances: &[MovingInstance],
    rays: &[Ray],
    times: &[f32],
) -> usize {
    let still = instances.iter().all(|i| i.transforms.len() == 1);
    let bounds: &[TimeBounds] = match still {
        true => &[TimeBounds::Merged],
        false => &[TimeBounds::Linear, TimeBounds::Merged],
    };
    let mut found = 0;
    for &b in bounds {
        let opts = BuildOptions::default();
        let m = MotionInstancedBvh::build(meshes, instances.to_vec(), &opts, b).expect("built");
        let bvh = MovingInstancesCpuBvh::from_motion(&m).expect("converted");
        assert_eq!(bvh.time_steps(), m.time_steps());
        let want = m.trace_rays(rays, times, Query::Closest);
        let isas = Isa::all_available();
        let got = bvh.trace_rays_with(rays, times, Query::Closest, isas[0]);
        for &isa in &isas[1..] {
            let h = bvh.trace_rays_with(rays, times, Query::Closest, isa);
            assert!(got.iter().zip(&h).all(|(a, b)| same(a, b)), "{isa} differs");
        }
        for i in 0..rays.len() {
            let (g, w) = (&got[i], &want[i]);
            if !same(g, w) {
                let at = m.at(times[i]);
                assert!(
                    f32_departure(&at, &rays[i], g, w),
                    "{b:?}: ray {i} {:?} at {}: {g:?}, the core walk {w:?}",
                    rays[i],
                    times[i]
                );
            }
        }
        found += got.iter().filter(|h| h.is_hit()).count();
        let any = bvh.trace_rays(rays, times, Query::Any);
        for i in 0..rays.len() {
            assert_eq!(any[i].is_hit(), got[i].is_hit(), "{b:?}: any hit, ray {i}");
        }
    }
    found
}

/// `n` random triangles in the unit cube, from `seed`.
fn soup(n: usize, seed: u64) -> Vec<Triangle> {
    let mut rnd = xorshift(seed);
    let mut p = || Vec3::new(rnd(), rnd(), rnd()) * 2.0 - 1.0;
    (0..n).map(|_| [p(), p(), p()]).collect()
}

/// An instance of `mesh` at `steps` steps: turned about `axis` by up to `turn`, moved to
/// `at` plus up to `reach`, scaled by up to `grow`.
fn placed(
    mesh: usize,
    steps: usize,
    (axis, turn): (Vec3, f32),
    (at, reach): (Vec3, Vec3),
    grow: f32,
) -> MovingInstance {
    let transforms = (0..steps)
        .map(|k| {
            let f = k as f32 / (steps.max(2) - 1) as f32;
            Mat4::from_translation(at + reach * f)
                * Mat4::from_axis_angle(axis.normalize(), turn * f)
                * Mat4::from_scale(Vec3::splat(1.0 + (grow - 1.0) * f))
        })
        .collect();
    MovingInstance { mesh, transforms }
}

/// `i` mirrored in x at every step.
fn mirrored(mut i: MovingInstance) -> MovingInstance {
    for t in &mut i.transforms {
        *t *= Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0));
    }
    i
}

#[test]
fn moving_instances_give_the_core_walks_hits() {
    let meshes = vec![
        uv_sphere(12, 1.0, Vec3::ZERO),
        uv_sphere(6, 0.7, Vec3::new(0.2, 0.0, 0.0)),
        soup(40, 5),
    ];
    let (x, y, z) = (Vec3::X, Vec3::Y, Vec3::Z);
    let instances = vec![
        placed(0, 5, (y, 0.8), (Vec3::ZERO, 2.0 * x), 1.3),
        placed(0, 5, (x, -1.0), (2.5 * y, Vec3::ZERO), 1.0),
        mirrored(placed(1, 5, (z, 0.3), (z - 2.0 * x, -2.0 * z), 0.8)),
        placed(2, 1, (y, 0.0), (x - 2.0 * y, Vec3::ZERO), 1.0),
        placed(
            1,
            5,
            (Vec3::ONE, 2.0),
            (Vec3::splat(0.5), Vec3::splat(0.1)),
            0.5,
        ),
    ];
    let world: Vec<Triangle> = MotionInstancedBvh::build(
        &meshes,
        instances.clone(),
        &BuildOptions::default(),
        TimeBounds::Linear,
    )
    .expect("built")
    .at(0.5);
    let rays = rays_for(&world, 11, 6000);
    let times = times_for(rays.len(), 5, 11);
    let found = check_instances(&meshes, &instances, &rays, &times);
    assert!(found > 3000, "{found} hits of 2 x 6000 rays");
    // Nothing moves: one step, merged bounds.
    let still: Vec<MovingInstance> = (instances.iter())
        .map(|i| MovingInstance {
            mesh: i.mesh,
            transforms: vec![i.transforms[i.transforms.len() / 2]],
        })
        .collect();
    assert!(check_instances(&meshes, &still, &rays, &times) > 1000);
}
