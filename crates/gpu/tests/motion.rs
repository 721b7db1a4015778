//! Motion blur on the device (`GpuMotionBvh`): the kernel answers as the CPU twin
//! (`MotionBvh::trace`) does, bit for bit, closest and any hit, with linear and merged
//! bounds, on a skinned glTF over a shutter, a moving builtin and a moving soup of
//! slivers, at every time including the shutter's ends, times outside it and NaN.
//! Without a Vulkan adapter the tests print SKIP.

use std::sync::Arc;

use bvhtrace_core::motion::{MotionBvh, MotionMesh, TimeBounds};
use bvhtrace_core::{BuildOptions, Hit, Query, Ray, Triangle};
use bvhtrace_gpu::{GpuError, GpuMotionBvh};
use glam::Vec3;

mod support;

/// Camera rays of `scene` over `w` x `h` pixels, each at several times, and a few rays at
/// the awkward times.
fn timed_rays(scene: &bvhtrace_scene::Scene, w: u32, h: u32) -> (Vec<Ray>, Vec<f32>) {
    let cam = scene.camera_or_frame(w as f32 / h as f32);
    let base = cam.rays(w, h);
    let (mut rays, mut times) = (Vec::new(), Vec::new());
    for s in 0..3u32 {
        for (i, r) in base.iter().enumerate() {
            rays.push(*r);
            times.push(((i as u32 * 7919 + s * 104_729) % 1000) as f32 / 999.0);
        }
    }
    for (i, t) in [0.0, 1.0, -0.5, 3.0, f32::NAN, f32::INFINITY, 0.5]
        .into_iter()
        .enumerate()
    {
        rays.push(base[base.len() / 2 + i]);
        times.push(t);
    }
    (rays, times)
}

fn same_bits(a: &[Hit], b: &[Hit]) -> Vec<usize> {
    (0..a.len())
        .filter(|&i| bytemuck::bytes_of(&a[i]) != bytemuck::bytes_of(&b[i]))
        .collect()
}

/// `got` (the device's) is `want` (the CPU twin's) bit for bit, and the rays hit.
fn assert_twins(what: &str, (got, want): (&[Hit], &[Hit]), times: &[f32]) {
    let differ = same_bits(got, want);
    let hits = want.iter().filter(|h| h.is_hit()).count();
    eprintln!(
        "{what}: {} rays, {hits} hits, {} differ",
        want.len(),
        differ.len()
    );
    assert!(hits > want.len() / 20, "{what}: the rays miss");
    if let Some(&i) = differ.first() {
        panic!(
            "{what}: {} rays differ, first {i} at time {}: device {:?}, CPU {:?}",
            differ.len(),
            times[i],
            got[i],
            want[i]
        );
    }
}

/// Both bounds, both queries: the device's hits are the CPU twin's.
fn check(
    what: &str,
    ctx: &bvhtrace_gpu::GpuContext,
    mesh: &MotionMesh,
    rays: &[Ray],
    times: &[f32],
) {
    for bounds in [TimeBounds::Linear, TimeBounds::Merged] {
        let bvh = Arc::new(MotionBvh::build(mesh, &BuildOptions::default(), bounds).unwrap());
        let gpu = GpuMotionBvh::upload(ctx, bvh.clone()).expect("upload");
        for query in [Query::Closest, Query::Any] {
            let want = bvh.trace_rays(rays, times, query);
            let got = gpu.trace(rays, times, query).expect("trace");
            assert_twins(
                &format!("{what} {bounds:?} {query:?}"),
                (&got, &want),
                times,
            );
        }
    }
}

#[test]
fn moving_scenes_answer_as_the_cpu_twin_bit_for_bit() {
    let Some(ctx) = support::context("motion") else {
        return;
    };
    let scenes = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes");
    for (spec, open, close) in [
        (format!("{scenes}/skinned.gltf"), 0.1, 0.7),
        ("builtin:moving:icosphere".to_string(), 0.0, 1.0),
    ] {
        let scene = bvhtrace_scene::load(&spec).unwrap_or_else(|e| panic!("{e}"));
        let mesh = scene.motion(open, close).unwrap();
        let (rays, times) = timed_rays(&scene, 96, 72);
        check(&spec, &ctx, &mesh, &rays, &times);
    }
}

#[test]
fn a_moving_soup_of_slivers_answers_as_the_cpu_twin() {
    let Some(ctx) = support::context("motion soup") else {
        return;
    };
    // A deterministic soup: ordinary triangles, slivers and repeated corners, moving by
    // amounts from nothing to far more than their size, one flipping.
    let mut s = 0x2545_F491u32;
    let mut rnd = move || {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        (s >> 8) as f32 / (1 << 24) as f32
    };
    let mut a: Vec<Triangle> = Vec::new();
    let mut b: Vec<Triangle> = Vec::new();
    for i in 0..3000 {
        let p = Vec3::new(rnd(), rnd(), rnd()) * 10.0;
        let e = Vec3::new(rnd(), rnd(), rnd()) - 0.5;
        let t = match i % 4 {
            0 => [p, p + e, p + Vec3::new(e.y, -e.x, e.z)],
            1 => [p, p + e * 1e-5, p + Vec3::new(1.0, 0.0, 0.0)],
            2 => [p, p, p + e],
            _ => [p, p + Vec3::X, p + Vec3::Y],
        };
        let shift = Vec3::new(rnd(), rnd(), rnd()) * [0.0, 0.01, 1.0, 8.0][i % 4];
        let mut u = t.map(|c| c + shift);
        if i % 97 == 0 {
            u.swap(1, 2);
        }
        a.push(t);
        b.push(u);
    }
    let mid: Vec<Triangle> = a
        .iter()
        .zip(&b)
        .map(|(x, y)| [0, 1, 2].map(|k| (x[k] + y[k]) * 0.5 + Vec3::Y))
        .collect();
    let mesh = MotionMesh::new(vec![a, mid, b]).unwrap();
    let (mut rays, mut times) = (Vec::new(), Vec::new());
    for i in 0..20_000 {
        let o = Vec3::new(rnd() * 14.0 - 2.0, rnd() * 14.0 - 2.0, -5.0);
        let d = Vec3::new(rnd() - 0.5, rnd() - 0.5, 1.0);
        let d = if i % 50 == 0 { Vec3::Z } else { d };
        rays.push(Ray::new(o, d));
        times.push(rnd());
    }
    check("soup", &ctx, &mesh, &rays, &times);
}

#[test]
fn a_tree_too_deep_for_the_stack_is_refused_by_name() {
    let Some(ctx) = support::context("motion depth") else {
        return;
    };
    // Triangles ever farther along +x (each twice the last's distance): midpoint
    // splits peel one off at a time, a tree deeper than the kernel's stack.
    let tris: Vec<Triangle> = (0..126)
        .map(|i| {
            let p = Vec3::X * 2f32.powi(i);
            [p, p * 1.001, p + Vec3::Y * p.x * 1e-3]
        })
        .collect();
    let mesh = MotionMesh::new(vec![tris.clone(), tris]).unwrap();
    let opts = BuildOptions {
        builder: bvhtrace_core::BuilderKind::Midpoint,
        max_leaf_size: 1,
        ..Default::default()
    };
    let bvh = MotionBvh::build(&mesh, &opts, TimeBounds::Linear).unwrap();
    assert!(bvh.depth() > 64, "the chain is {} levels deep", bvh.depth());
    match GpuMotionBvh::upload(&ctx, Arc::new(bvh)) {
        Err(e @ GpuError::TooDeep { .. }) => assert!(e.to_string().contains("levels deep")),
        other => panic!("expected TooDeep, got {other:?}"),
    }
}

/// Moving instances (`GpuMotionInstancedBvh`): the joined tree's walk enters each instance
/// with its transform at the ray's time, as the CPU twin (`MotionInstancedBvh::trace`)
/// does, bit for bit, closest and any hit, both bounds: node animations over 129 steps
/// (instances that move and instances that stay), and a moving builtin.
#[test]
fn moving_instances_answer_as_the_cpu_twin_bit_for_bit() {
    use bvhtrace_core::motion::MotionInstancedBvh;
    use bvhtrace_gpu::GpuMotionInstancedBvh;
    let Some(ctx) = support::context("moving instances") else {
        return;
    };
    let scenes = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes");
    for (spec, open, close) in [
        (format!("{scenes}/animated.gltf"), 0.2, 1.9),
        ("builtin:moving:icosphere".to_string(), 0.0, 1.0),
    ] {
        let scene = bvhtrace_scene::load(&spec).unwrap_or_else(|e| panic!("{e}"));
        let (meshes, instances) = scene.moving_instances(open, close).unwrap();
        assert!(
            instances.iter().any(|i| i.transforms.len() > 1),
            "{spec}: nothing moves"
        );
        let (rays, times) = timed_rays(&scene, 96, 72);
        for bounds in [TimeBounds::Linear, TimeBounds::Merged] {
            let opts = BuildOptions::default();
            let bvh = MotionInstancedBvh::build(&meshes, instances.clone(), &opts, bounds).unwrap();
            let bvh = Arc::new(bvh);
            let gpu = GpuMotionInstancedBvh::upload(&ctx, bvh.clone()).expect("upload");
            for query in [Query::Closest, Query::Any] {
                let want = bvh.trace_rays(&rays, &times, query);
                let got = gpu.trace(&rays, &times, query).expect("trace");
                let what = format!("{spec} {bounds:?} {query:?}");
                assert_twins(&what, (&got, &want), &times);
            }
        }
    }
}
