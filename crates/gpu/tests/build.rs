//! The BVHs built on the device (`GpuContext::build_bvh` and `build_bvh_async`, both
//! builders), read back: every structural invariant of the flat layout (every triangle
//! once, boxes holding their children and triangles), the same tree for the same input
//! (blocking and awaited), degenerate inputs, and the same closest hits as the CPU's SAH
//! tree, traced by the CPU walks and by the GPU. Without a Vulkan adapter the tests print
//! SKIP.

use bvhtrace_core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal, Triangle, trace_rays};
use bvhtrace_gpu::{
    GpuBuildOptions, GpuBuilderKind, GpuBvh, GpuContext, GpuError, Tracer, UploadOptions,
};
use glam::Vec3;

mod support;

fn scene(spec: &str) -> Vec<Triangle> {
    bvhtrace_scene::load(spec)
        .expect("builtin scene")
        .flattened_triangles()
        .expect("triangles")
}

/// Rays through the bounds from outside and from inside.
fn rays(bvh: &FlatBvh) -> Vec<Ray> {
    let b = bvh.bounds();
    let (lo, hi) = (b.min, b.max);
    let size = (hi - lo).max(Vec3::splat(1e-3));
    let mut out = Vec::new();
    for i in 0..40 {
        for j in 0..40 {
            let target = lo + size * Vec3::new(i as f32 / 39.0, j as f32 / 39.0, 0.5);
            let eye = (lo + hi) * 0.5 + size * Vec3::new(0.3, 0.4, 2.0);
            out.push(Ray::new(eye, target - eye));
            out.push(Ray::new(
                (lo + hi) * 0.5,
                target - (lo + hi) * 0.5 + Vec3::Y * 0.1,
            ));
        }
    }
    out
}

/// Builds `tris` on the device with each builder and checks the tree, its determinism and
/// its hits; returns the trees.
fn check(ctx: &GpuContext, name: &str, tris: &[Triangle]) -> Vec<FlatBvh> {
    GpuBuilderKind::ALL
        .iter()
        .map(|&kind| check_one(ctx, &format!("{name} ({kind})"), tris, kind))
        .collect()
}

fn check_one(ctx: &GpuContext, name: &str, tris: &[Triangle], kind: GpuBuilderKind) -> FlatBvh {
    let opts = GpuBuildOptions::with_builder(kind);
    let (bvh, times) = ctx.build_bvh(tris, &opts).expect("device build");
    bvh.check_invariants()
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(
        bvh.triangles().len(),
        tris.len(),
        "{name}: every triangle once"
    );
    let leaves = bvh.nodes().iter().filter(|n| n.count() > 0).count();
    assert_eq!(bvh.nodes().len(), 2 * leaves - 1, "{name}: a binary tree");
    if kind == GpuBuilderKind::Lbvh {
        assert_eq!(leaves, tris.len(), "{name}: one triangle a leaf");
    }
    // The second build through the future (what a browser awaits), reading the cluster
    // count back after each iteration's batch: the same tree.
    let batched = GpuBuildOptions {
        first_iterations: Some(1),
        ..opts
    };
    let (again, at) =
        pollster::block_on(ctx.build_bvh_async(tris, &batched)).expect("device build");
    assert_eq!(at.iterations, times.iterations, "{name}: iterations");
    assert!(
        bytemuck::cast_slice::<_, u8>(bvh.nodes()) == bytemuck::cast_slice::<_, u8>(again.nodes())
            && bytemuck::cast_slice::<_, u8>(bvh.triangles())
                == bytemuck::cast_slice::<_, u8>(again.triangles())
            && bvh.depth() == again.depth(),
        "{name}: two builds of the same input differ"
    );
    // The hit rule does not depend on the tree: the SAH tree's hits, bit for bit.
    let sah = FlatBvh::build(tris, &BuildOptions::default()).expect("CPU build");
    let rays = rays(&sah);
    let opts = TraceOptions::closest(Traversal::FullStack);
    let want = trace_rays(&sah, &rays, &opts).hits;
    let got = trace_rays(&bvh, &rays, &opts).hits;
    assert!(
        bytemuck::cast_slice::<_, u8>(&want) == bytemuck::cast_slice::<_, u8>(&got),
        "{name}: the CPU walks on the device-built tree answer otherwise"
    );
    eprintln!(
        "{name}: {} triangles, {leaves} leaves, depth {}, {} iterations, {:.1} ms upload, \
         {:.1} ms build, {:.1} ms read back; {} hits",
        tris.len(),
        bvh.depth(),
        times.iterations,
        times.upload_ms,
        times.build_ms,
        times.readback_ms,
        got.iter().filter(|h| h.is_hit()).count()
    );
    bvh
}

#[test]
fn device_built_trees_hold_every_invariant_and_the_sah_trees_hits() {
    let Some(ctx) = support::context("device builds") else {
        return;
    };
    for spec in [
        "builtin:cornell",
        "builtin:icosphere:4",
        "builtin:degenerate",
        "builtin:grid:icosphere:5x4",
    ] {
        let tris = scene(spec);
        let trees = check(&ctx, spec, &tris);
        if spec == "builtin:icosphere:4" {
            // Every walk on the GPU over them, as over any tree.
            for bvh in &trees {
                // The wide layout by the CPU collapse, as for any tree.
                let mut bvh = bvh.clone();
                bvh.build_wide();
                let bvh = &bvh;
                let gpu = GpuBvh::upload(&ctx, bvh, &UploadOptions::fitting(bvh)).expect("upload");
                let rays = rays(bvh);
                for walk in [Traversal::Stackless, Traversal::FullStack, Traversal::Wide] {
                    let opts = TraceOptions::closest(walk);
                    let g = gpu.trace(&rays, &opts).expect("trace").hits;
                    let c = trace_rays(bvh, &rays, &opts).hits;
                    assert_eq!(g, c, "{walk}: GPU and CPU walks on the device-built tree");
                }
            }
        }
    }
}

#[test]
fn degenerate_inputs_build() {
    let Some(ctx) = support::context("device builds") else {
        return;
    };
    let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
    // Every centroid equal: the index breaks every tie.
    check(&ctx, "1000 copies of one triangle", &vec![t; 1000]);
    // Nested boxes chain one merge an iteration unless places are paired: the
    // iterations stay logarithmic.
    let nested: Vec<Triangle> = (1..=2000)
        .map(|i| [Vec3::ZERO, Vec3::X * i as f32, Vec3::Y * i as f32])
        .collect();
    check(&ctx, "2000 nested triangles", &nested);
    for tris in [vec![t; 1000], nested] {
        let opts = GpuBuildOptions::with_builder(GpuBuilderKind::Ploc);
        let (_, times) = ctx.build_bvh(&tris, &opts).expect("device build");
        assert!(times.iterations <= 200, "{} iterations", times.iterations);
    }
    check(&ctx, "two triangles", &[t, t.map(|p| p + Vec3::Z)]);
    let huge: Vec<Triangle> = (0..300)
        .map(|i| t.map(|p| p * 1e30 + Vec3::new(i as f32 * 1e33, -1e35, 3e36)))
        .collect();
    check(&ctx, "huge coordinates", &huge);
    // A long line of slivers: many equal Morton codes along two axes.
    let line: Vec<Triangle> = (0..5000)
        .map(|i| {
            let x = i as f32 * 0.001;
            [
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(x + 0.0005, 0.0, 0.0),
                Vec3::new(x, 1e-7, 0.0),
            ]
        })
        .collect();
    check(&ctx, "slivers on a line", &line);
    for kind in GpuBuilderKind::ALL {
        let opts = GpuBuildOptions::with_builder(kind);
        let (one, _) = ctx.build_bvh(&[t], &opts).expect("one triangle");
        one.check_invariants().expect("one triangle's tree");
        assert!(matches!(ctx.build_bvh(&[], &opts), Err(GpuError::EmptyBvh)));
        let err = ctx
            .build_bvh(&[t, [Vec3::ZERO, Vec3::NAN, Vec3::Y]], &opts)
            .expect_err("a NaN corner");
        assert!(err.to_string().contains("triangle 1"), "{err}");
    }
}

#[test]
fn the_clustering_tree_is_within_the_sah_trees_cost() {
    let Some(ctx) = support::context("device builds") else {
        return;
    };
    for spec in [
        "builtin:icosphere:4",
        "builtin:grid:icosphere:5x4",
        "builtin:cornell",
    ] {
        let tris = scene(spec);
        let cpu = bvhtrace_core::BvhStats::of(
            &FlatBvh::build(&tris, &BuildOptions::default()).expect("CPU build"),
        );
        let opts = GpuBuildOptions::with_builder(GpuBuilderKind::Ploc);
        let (ploc, _) = ctx.build_bvh(&tris, &opts).expect("device build");
        let got = bvhtrace_core::BvhStats::of(&ploc);
        eprintln!(
            "{spec}: SAH {:.2} against the CPU's {:.2} (PBRT costs {:.3} against {:.3})",
            got.sah_cost, cpu.sah_cost, got.sah_cost_pbrt, cpu.sah_cost_pbrt
        );
        assert!(got.sah_cost <= 1.15 * cpu.sah_cost, "{spec}");
        assert!(got.sah_cost_pbrt <= 1.15 * cpu.sah_cost_pbrt, "{spec}");
    }
}
