//! The top level of a two-level BVH rebuilt on the device (`set_transforms_on_device`): the
//! tree it reads back passes every check, answers every ray as the CPU's top level does
//! (closest hits do not depend on the tree), on the CPU and, against the CPU's top level
//! uploaded, on the device; a bad transform is refused with the BVH kept. Without a Vulkan adapter the tests print SKIP.

use bvhtrace_core::{
    BuildOptions, FlatBvh, Instance, InstancedBvh, Ray, TraceOptions, Traversal, Triangle,
    trace_rays,
};
use bvhtrace_gpu::{
    BvhStorage, GpuBuildOptions, GpuBuilderKind, GpuBvh, GpuContext, Tracer, UploadOptions,
};
use glam::{Affine3A, Quat, Vec3};

mod support;

/// 300 instances of a small icosphere on a 20 x 15 grid, each turned and scaled its own way
/// at time `t`.
fn poses(n: usize, t: f32) -> Vec<Affine3A> {
    (0..n)
        .map(|i| {
            let (x, z) = ((i % 20) as f32, (i / 20) as f32);
            let turn = Quat::from_rotation_y(t + 0.37 * i as f32);
            let at = Vec3::new(x * 1.5, (t * 2.0 + i as f32).sin(), z * 1.5);
            Affine3A::from_scale_rotation_translation(
                Vec3::splat(0.5 + 0.05 * (i % 7) as f32),
                turn,
                at,
            )
        })
        .collect()
}

/// Rays from above the grid down at it, some missing it.
fn rays() -> Vec<Ray> {
    (0..4096)
        .map(|k| {
            let (u, v) = ((k % 64) as f32 / 63.0, (k / 64) as f32 / 63.0);
            let target = Vec3::new(-2.0 + 33.0 * u, 0.0, -2.0 + 25.0 * v);
            let origin = Vec3::new(14.0, 30.0, -20.0);
            Ray::new(origin, (target - origin).normalize())
        })
        .collect()
}

fn upload(ctx: &GpuContext, bvh: &FlatBvh) -> GpuBvh {
    let opts = UploadOptions::for_traversal(Traversal::Stackless).with_storage(BvhStorage::Buffers);
    GpuBvh::upload(ctx, bvh, &opts).expect("upload")
}

#[test]
fn a_top_level_built_on_the_device_traces_as_the_cpus() {
    let Some(ctx) = support::context("device top level") else {
        return;
    };
    let sphere = bvhtrace_scene::icosphere(1);
    let tris: Vec<Triangle> = (sphere.indices.iter())
        .map(|t| t.map(|i| sphere.positions[i as usize]))
        .collect();
    let n = 300;
    let instances: Vec<Instance> = (poses(n, 0.0).into_iter())
        .map(|m| Instance::new(0, m))
        .collect();
    let built = InstancedBvh::build(&[tris], instances, &BuildOptions::default()).expect("build");
    let rays = rays();
    let closest = TraceOptions::closest(Traversal::Stackless);
    for builder in [GpuBuilderKind::Ploc, GpuBuilderKind::Lbvh] {
        let moved = poses(n, 1.0);
        let mut cpu = built.clone();
        cpu.set_transforms(&moved).expect("CPU top level");
        let mut dev = built.clone();
        let opts = GpuBuildOptions::with_builder(builder);
        ctx.set_transforms_on_device(&mut dev, &moved, &opts)
            .expect("device top level");
        dev.bvh().check_invariants().expect("invariants");
        let (top, all) = (dev.bvh().top_nodes() as usize, dev.bvh().nodes().len());
        assert_eq!(
            &dev.bvh().nodes()[top..all],
            &cpu.bvh().nodes()[top..all],
            "meshes kept"
        );
        assert_ne!(
            &dev.bvh().nodes()[..top],
            &cpu.bvh().nodes()[..top],
            "{builder:?}: same tree"
        );
        let want = trace_rays(cpu.bvh(), &rays, &closest).hits;
        assert!(
            want.iter().filter(|h| h.is_hit()).count() > 1000,
            "the rays hit the grid"
        );
        assert_eq!(
            trace_rays(dev.bvh(), &rays, &closest).hits,
            want,
            "{builder:?} on the CPU"
        );
        // The same device's arithmetic on both: a GPU that fuses multiply-adds answers
        // the CPU's walks only within f32 bounds.
        let on_device = |b: &InstancedBvh| upload(&ctx, b.bvh()).trace(&rays, &closest);
        let (got, want) = (
            on_device(&dev).expect("trace"),
            on_device(&cpu).expect("trace"),
        );
        assert_eq!(got.hits, want.hits, "{builder:?} on the GPU");
    }
    // A NaN transform: refused by name, the BVH kept.
    let mut dev = built.clone();
    let mut bad = poses(n, 1.0);
    bad[17] = Affine3A::from_translation(Vec3::NAN);
    let e = ctx
        .set_transforms_on_device(&mut dev, &bad, &GpuBuildOptions::default())
        .expect_err("a NaN transform");
    assert!(e.to_string().contains("17"), "{e}");
    assert_eq!(dev, built, "a refused pose changed the BVH");
}
