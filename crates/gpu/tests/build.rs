//! The linear BVH built on the device (`GpuContext::build_lbvh`), read back: every
//! structural invariant of the flat layout (every triangle once, boxes holding their
//! children and triangles), the same tree for the same input, degenerate inputs, and the
//! same closest hits as the CPU's SAH tree, traced by the CPU walks and by the GPU. Without
//! a Vulkan adapter the tests print SKIP.

use bvhtrace_core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal, Triangle, trace_rays};
use bvhtrace_gpu::{AdapterChoice, GpuBvh, GpuContext, GpuError, Tracer, UploadOptions};
use glam::Vec3;

fn context() -> Option<GpuContext> {
    match GpuContext::new(AdapterChoice::Auto) {
        Ok(c) => Some(c),
        Err(e @ GpuError::NoAdapter { .. }) => {
            eprintln!("SKIP device builds: {e}");
            None
        }
        Err(e) => panic!("cannot open a GPU: {e}"),
    }
}

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

/// Builds `tris` on the device and checks the tree, its determinism and its hits.
fn check(ctx: &GpuContext, name: &str, tris: &[Triangle]) -> FlatBvh {
    let (bvh, times) = ctx.build_lbvh(tris).expect("device build");
    bvh.check_invariants()
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(
        bvh.triangles().len(),
        tris.len(),
        "{name}: one triangle a leaf"
    );
    assert_eq!(bvh.nodes().len(), 2 * tris.len() - 1, "{name}");
    let (again, _) = ctx.build_lbvh(tris).expect("device build");
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
        "{name}: {} triangles, depth {}, {:.1} ms upload, {:.1} ms build, {:.1} ms read back; \
         {} hits",
        tris.len(),
        bvh.depth(),
        times.upload_ms,
        times.build_ms,
        times.readback_ms,
        got.iter().filter(|h| h.is_hit()).count()
    );
    bvh
}

#[test]
fn device_built_trees_hold_every_invariant_and_the_sah_trees_hits() {
    let Some(ctx) = context() else { return };
    for spec in [
        "builtin:cornell",
        "builtin:icosphere:4",
        "builtin:degenerate",
        "builtin:grid:icosphere:5x4",
    ] {
        let tris = scene(spec);
        let bvh = check(&ctx, spec, &tris);
        if spec == "builtin:icosphere:4" {
            // Every walk on the GPU over it, as over any tree.
            let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
            let rays = rays(&bvh);
            for walk in [Traversal::Stackless, Traversal::FullStack] {
                let opts = TraceOptions::closest(walk);
                let g = gpu.trace(&rays, &opts).expect("trace").hits;
                let c = trace_rays(&bvh, &rays, &opts).hits;
                assert_eq!(g, c, "{walk}: GPU and CPU walks on the device-built tree");
            }
        }
    }
}

#[test]
fn degenerate_inputs_build() {
    let Some(ctx) = context() else { return };
    let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
    // Every centroid equal: the index breaks every tie.
    check(&ctx, "1000 copies of one triangle", &vec![t; 1000]);
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
    let (one, _) = ctx.build_lbvh(&[t]).expect("one triangle");
    one.check_invariants().expect("one triangle's tree");
    assert!(matches!(ctx.build_lbvh(&[]), Err(GpuError::EmptyBvh)));
    let err = ctx
        .build_lbvh(&[t, [Vec3::ZERO, Vec3::NAN, Vec3::Y]])
        .expect_err("a NaN corner");
    assert!(err.to_string().contains("triangle 1"), "{err}");
}
