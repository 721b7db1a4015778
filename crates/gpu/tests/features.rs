//! Leaving out what a job does not need, on a GPU (lavapipe in CI): the pipeline cache does
//! not recompile when a job switches back to a kernel, the specialised and everything-on
//! pipelines give the same hits, and the bytes uploaded are exactly the bytes the kernel's
//! bindings declare (for the wide layout too).

use bvhtrace_core::{BuildOptions, FlatBvh, Query, Ray, TraceOptions, Traversal};
use bvhtrace_gpu::engine::plan::{COUNTERS_BYTES, HIT_BYTES, RAY_BYTES};
use bvhtrace_gpu::engine::storage::{RayInput, TEXEL_ROW};
use bvhtrace_gpu::{
    BvhStorage, Composition, ContextOptions, GpuBvh, GpuContext, KernelKey, Tracer, UploadOptions,
    VertexAttributes,
};
use glam::Vec3;
use naga::{Module, TypeInner};

#[path = "../../engine/tests/common/mod.rs"]
mod kernels_common;
use kernels_common::{STORAGES, TRAVERSALS};

mod support;

fn parse(source: &str) -> Module {
    naga::front::wgsl::parse_str(source).unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)))
}

fn scene() -> (FlatBvh, Vec<Ray>) {
    let mesh = bvhtrace_scene::load("builtin:icosphere:3").expect("builtin scene");
    let tris = mesh.flatten().triangles().expect("triangles");
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let mut rays = Vec::new();
    for y in 0..24 {
        for x in 0..32 {
            let o = Vec3::new(x as f32 / 16.0 - 1.0, y as f32 / 12.0 - 1.0, 5.0);
            rays.push(Ray::new(o, Vec3::new(0.01 * x as f32, 0.0, -1.0)));
        }
    }
    (bvh, rays)
}

#[test]
fn switching_back_to_a_feature_set_does_not_recompile() {
    let Some(ctx) = support::context("features (GPU part)") else {
        return;
    };
    let (bvh, rays) = scene();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    let opts =
        |traversal, query, counters| TraceOptions::new(traversal, query).with_counters(counters);
    let a = opts(Traversal::FullStack, Query::Closest, false);
    let b = opts(Traversal::Stackless, Query::Any, true);
    assert_eq!(ctx.compile_counts(), (0, 0));
    let first = gpu.trace(&rays, &a).expect("trace a");
    assert_eq!(ctx.compile_counts(), (1, 1));
    // No counter buffers until a trace asks for counters.
    let n = rays.len() as u64;
    // Rays and hits: buffers (and the hits' readback), or whole rows of a ray texture (two
    // texels per ray) and of a hit texture (one), and the hit rows' readback
    // (`RayInput::for_storage`).
    let plain = match RayInput::for_storage(gpu.tree().storage) {
        RayInput::Buffer => n * RAY_BYTES + 2 * n * HIT_BYTES,
        RayInput::Texture => {
            let row = u64::from(TEXEL_ROW);
            let rows = |texels: u64| texels.div_ceil(row) * row * 16;
            rows(2 * n) + 2 * rows(n)
        }
    };
    assert_eq!(gpu.scratch_bytes(), plain);
    let counted = gpu.trace(&rays, &b).expect("trace b");
    assert_eq!(ctx.compile_counts(), (2, 2), "b has its own module");
    assert_eq!(counted.counters.map(|c| c.len()), Some(rays.len()));
    assert_eq!(gpu.scratch_bytes(), plain + 2 * n * COUNTERS_BYTES);
    // Back to a: cached.
    let again = gpu.trace(&rays, &a).expect("trace a again");
    assert_eq!(ctx.compile_counts(), (2, 2), "switching back recompiled");
    assert_eq!(first.hits, again.hits);
    // Any hit shares a's module (an override constant): a new pipeline, no new module.
    gpu.trace(&rays, &opts(Traversal::FullStack, Query::Any, false))
        .expect("trace");
    assert_eq!(ctx.compile_counts(), (2, 3));

    // Everything on (a context of its own on the same device): the same answers.
    let everything = ContextOptions {
        composition: Composition::EverythingOn,
        ..ContextOptions::default()
    };
    let all_ctx = GpuContext::from_device_with(
        ctx.device().clone(),
        ctx.queue().clone(),
        ctx.adapter_info().clone(),
        &everything,
    )
    .expect("context");
    let all_gpu = GpuBvh::upload(&all_ctx, &bvh, &UploadOptions::all()).expect("upload");
    let all = all_gpu.trace(&rays, &a).expect("everything on");
    assert_eq!(all_ctx.compile_counts(), (1, 1));
    assert_eq!(all.hits, first.hits, "everything-on and specialised differ");
    gpu.trace(&rays, &a).expect("specialised again");
    gpu.trace(&rays, &b).expect("b again");
    assert_eq!(ctx.compile_counts(), (2, 3), "switching back recompiled");
    assert!(
        first.hits.iter().any(|h| h.is_hit()),
        "the rays hit nothing"
    );
}

/// Element bytes (the array stride) of each storage-buffer binding of group 0.
fn group0_strides(module: &Module) -> Vec<(String, u64)> {
    module
        .global_variables
        .iter()
        .filter(|(_, g)| g.binding.as_ref().is_some_and(|b| b.group == 0))
        .map(|(_, g)| {
            let stride = match module.types[g.ty].inner {
                TypeInner::Array { stride, .. } => u64::from(stride),
                ref other => panic!("{:?} is not an array: {other:?}", g.name),
            };
            (g.name.clone().unwrap_or_default(), stride)
        })
        .collect()
}

#[test]
fn the_upload_is_exactly_what_the_kernel_reads() {
    let Some(ctx) = support::context("features (GPU part)") else {
        return;
    };
    let (bvh, rays) = scene();
    let wide = bvhtrace_core::WideBvh::collapse(&bvh);
    for traversal in TRAVERSALS {
        // The wide walk's key counts the wide tree's nodes.
        let (nodes, tris) = if traversal.is_wide() {
            (wide.nodes.len() as u64, wide.triangles.len() as u64)
        } else {
            (bvh.nodes().len() as u64, bvh.triangles().len() as u64)
        };
        for storage in STORAGES {
            let opts = TraceOptions::closest(traversal);
            let f = KernelKey::for_job(
                storage,
                &opts,
                VertexAttributes::NONE,
                VertexAttributes::NONE,
            );
            let upload = UploadOptions::for_traversal(traversal).with_storage(storage);
            let Ok(gpu) = GpuBvh::upload(&ctx, &bvh, &upload) else {
                panic!("upload {f:?}")
            };
            let stats = *gpu.stats();
            let module = parse(&f.source());
            let declared = f.declared_bvh_bytes(nodes, tris, 0);
            let planned = f.upload_bytes(nodes, tris, 0);
            assert_eq!(
                (
                    stats.nodes_bytes,
                    stats.triangles_bytes,
                    stats.escapes_bytes
                ),
                (
                    planned.nodes_bytes,
                    planned.triangles_bytes,
                    planned.escapes_bytes
                ),
                "{f:?}: uploaded vs KernelKey::upload_bytes"
            );
            assert_eq!(
                stats.escapes_bytes > 0,
                traversal.needs_escapes(),
                "{f:?}: {stats:?}"
            );
            // Both layouts are in the storage asked for.
            assert_eq!((f.storage, gpu.tree().storage), (storage, storage), "{f:?}");
            assert_eq!(
                (gpu.wide_buffers().is_some(), gpu.wide_textures().is_some()),
                (
                    traversal.is_wide() && storage == BvhStorage::Buffers,
                    traversal.is_wide() && storage == BvhStorage::Textures
                ),
                "{f:?}"
            );
            match f.storage {
                BvhStorage::Buffers => {
                    // Bytes the bindings declare (array stride x element count), from the
                    // reflected module, against the bytes uploaded.
                    let from_module: u64 = group0_strides(&module)
                        .iter()
                        .map(|(name, stride)| {
                            stride
                                * match name.as_str() {
                                    "bvh_nodes" | "bvh_wide_nodes" => nodes,
                                    // `array<u32>`: eight links per node, whole blocks.
                                    "bvh_escapes" => {
                                        bvhtrace_core::flat::escape_links_len(nodes as usize) as u64
                                    }
                                    "bvh_triangles" => tris,
                                    other => panic!("unexpected binding {other}"),
                                }
                        })
                        .sum();
                    assert_eq!(stats.total_bytes(), from_module, "{f:?}: {stats:?}");
                    assert_eq!(stats.total_bytes(), declared, "{f:?}");
                }
                BvhStorage::Textures => {
                    // The same texels: exactly, when each texture is one row (the nodes and
                    // triangles here: two texels per binary node, five per wide one); taller
                    // ones (the eight escape links per node) pad at most their last row.
                    let row = u64::from(TEXEL_ROW);
                    let node_texels = if traversal.is_wide() { 5 } else { 2 };
                    assert!(
                        node_texels * nodes <= row && 3 * tris <= row,
                        "scene too large"
                    );
                    let pad = stats.total_bytes() - declared;
                    if traversal.needs_escapes() {
                        assert!(8 * nodes > row && pad < 4 * row, "{f:?}: {stats:?}");
                    } else {
                        assert_eq!(pad, 0, "{f:?}: {stats:?}");
                    }
                    let tall = f.upload_bytes(100 * row, 100 * row, 0);
                    assert!(tall.total_bytes() >= f.declared_bvh_bytes(100 * row, 100 * row, 0));
                    assert!(
                        tall.total_bytes()
                            < f.declared_bvh_bytes(100 * row, 100 * row, 0) + 36 * row
                    );
                }
            }
            // The upload traces its job.
            let out = gpu.trace(&rays, &opts).expect("trace");
            assert_eq!(out.hits.len(), rays.len());
        }
    }
}

/// `Tracer::update` works out what changed: after new transforms (top level only) and
/// after a refit (everything) the tracer answers as a fresh upload of the new tree does,
/// for the binary and the wide walk; `kernels_used` lists each kernel that ran once.
#[test]
fn tracer_update_answers_as_a_fresh_upload() {
    use bvhtrace_gpu::Tracer;
    let Some(ctx) = support::context("features (GPU part)") else {
        return;
    };
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    let mut ib = scene
        .instanced_bvh(&BuildOptions::default())
        .expect("two levels");
    let opts = UploadOptions::all().with_traversal(Traversal::Wide);
    let mut gpu = GpuBvh::upload(&ctx, ib.bvh(), &opts).expect("upload");
    let root = ib.bvh().nodes()[0];
    let (lo, hi) = (Vec3::from(root.min), Vec3::from(root.max));
    let rays: Vec<Ray> = (0..32 * 32)
        .map(|i| {
            let f = Vec3::new((i % 32) as f32 / 31.0, (i / 32) as f32 / 31.0, 0.0);
            let o = lo + (hi - lo) * f + Vec3::Z * (hi.z - lo.z + 1.0);
            Ray::new(o, Vec3::new(0.05, 0.02, -1.0))
        })
        .collect();
    let walks = [Traversal::Stackless, Traversal::Wide].map(TraceOptions::closest);
    let check = |gpu: &GpuBvh, bvh: &FlatBvh, what: &str| {
        let fresh = GpuBvh::upload(&ctx, bvh, &opts).expect("fresh upload");
        for o in &walks {
            let got = Tracer::trace(gpu, &rays, o).expect("trace").hits;
            let want = fresh.trace(&rays, o).expect("trace").hits;
            assert!(got.iter().filter(|h| h.is_hit()).count() > 50, "{what}");
            assert!(got == want, "{what}, {}", o.traversal);
        }
    };
    let moved: Vec<glam::Affine3A> = ib
        .instances()
        .iter()
        .enumerate()
        .map(|(k, i)| glam::Affine3A::from_rotation_z(0.3 * k as f32) * i.transform)
        .collect();
    ib.set_transforms(&moved).expect("new transforms");
    Tracer::update(&mut gpu, ib.bvh()).expect("top-level update");
    check(&gpu, ib.bvh(), "after new transforms");
    let mut tris = ib.mesh_bvh(0).triangles().to_vec();
    tris.sort_by_key(|t| t.prim);
    let bent: Vec<_> = tris
        .iter()
        .map(|t| t.corners().map(|p| p * Vec3::new(1.3, 0.6, 1.0)))
        .collect();
    ib.refit_mesh(0, &bent).expect("refit");
    Tracer::update(&mut gpu, ib.bvh()).expect("update after a refit");
    check(&gpu, ib.bvh(), "after a refit");
    let used = gpu.kernels_used();
    assert_eq!(used.len(), 2, "{used:?}");
    assert!(used[0].traversal == Traversal::Stackless && used[1].traversal.is_wide());
    assert!(
        used.iter()
            .all(|k| k.instances && k.storage == gpu.tree().storage)
    );
}
