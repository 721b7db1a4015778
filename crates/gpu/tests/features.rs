//! Leaving out what a job does not need: the specialised modules are reflected with naga
//! (no GPU needed) and must declare exactly the bindings [`PipelineFeatures::bindings`]
//! lists: no attribute binding for a positions-only scene, no `counters` unless counters
//! are on, no escape links for the full stack, one entry point. On a GPU (lavapipe in CI):
//! the pipeline cache does not recompile when a job switches back to a feature set, the
//! specialised and everything-on pipelines give the same hits, and the bytes uploaded are
//! exactly the bytes the kernel's bindings declare.

use std::collections::BTreeSet;

use bvhtrace_core::{BuildOptions, FlatBvh, Precision, Query, Ray, Traversal};
use bvhtrace_gpu::{
    AdapterChoice, BvhStorage, Composition, Entries, GpuBvh, GpuContext, GpuError, ModuleSet,
    PipelineFeatures, RayInput, TraceOptions, UploadOptions, VertexAttributes, kernel_source,
};
use glam::Vec3;
use naga::{Module, TypeInner};

mod common;
use common::{compile_variant, parse, validate};

const STORAGES: [BvhStorage; 2] = [BvhStorage::Buffers, BvhStorage::Textures];
const TRAVERSALS: [Traversal; 3] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(6),
];
const NORMALS: VertexAttributes = VertexAttributes { normals: true };

/// `(group, binding, name)` of every resource the module declares.
fn declared(module: &Module) -> BTreeSet<(u32, u32, String)> {
    module
        .global_variables
        .iter()
        .filter_map(|(_, g)| {
            let b = g.binding.as_ref()?;
            Some((b.group, b.binding, g.name.clone().unwrap_or_default()))
        })
        .collect()
}

fn has_function(module: &Module, name: &str) -> bool {
    module
        .functions
        .iter()
        .any(|(_, f)| f.name.as_deref() == Some(name))
}

/// Every job a positions-only scene can be traced with.
fn every_job(storage: BvhStorage) -> Vec<PipelineFeatures> {
    let mut v = Vec::new();
    for traversal in TRAVERSALS {
        for query in [Query::Closest, Query::Any] {
            for counters in [false, true] {
                // The job would shade with normals; the scene has none.
                let f = PipelineFeatures::for_job(
                    storage,
                    traversal,
                    query,
                    counters,
                    VertexAttributes::NONE,
                    NORMALS,
                );
                v.push(f);
                // `GpuBvh::trace` reads the rays from a texture with the BVH in textures;
                // `GpuBvh::record` from the caller's buffer.
                if storage == BvhStorage::Textures {
                    assert_eq!(f.variant.rays, RayInput::Texture);
                    let mut b = f;
                    b.variant = b.variant.with_rays(RayInput::Buffer);
                    v.push(b);
                }
            }
        }
    }
    v
}

/// Validates `module` and compiles its one entry point to SPIR-V with `f`'s overrides.
fn compile(module: &Module, f: &PipelineFeatures) {
    compile_variant(module, &validate(module), &f.variant);
}

#[test]
fn positions_only_pipelines_declare_only_what_the_job_reads() {
    for storage in STORAGES {
        for f in every_job(storage) {
            let module = parse(&f.source());
            let got = declared(&module);
            let listed: BTreeSet<(u32, u32, String)> = f
                .bindings()
                .iter()
                .map(|b| (b.group, b.binding, b.name.to_string()))
                .collect();
            assert_eq!(got, listed, "{f:?}: declared vs PipelineFeatures::bindings");

            let names: Vec<&str> = got.iter().map(|(_, _, n)| n.as_str()).collect();
            // No attribute binding: the scene has positions only.
            assert!(!names.contains(&"vertex_normals"), "{f:?}: {names:?}");
            assert!(!got.iter().any(|(g, b, _)| *g == 0 && *b >= 3), "{f:?}");
            // Counters only when asked for.
            assert_eq!(
                names.contains(&"counters"),
                f.variant.counters,
                "{f:?}: {names:?}"
            );
            // Escape links only for the walks that read them; and the other walk's code is
            // not in the module at all.
            let escapes = names.iter().any(|n| n.contains("escape"));
            let full = f.traversal() == Traversal::FullStack;
            assert_eq!(escapes, !full, "{f:?}: {names:?}");
            assert_eq!(has_function(&module, "trace_short_stack"), !full, "{f:?}");
            assert_eq!(has_function(&module, "trace_full_stack"), full, "{f:?}");
            assert_eq!(has_function(&module, "load_escape"), !full, "{f:?}");
            // One entry point, the variant's.
            let eps: Vec<&str> = module
                .entry_points
                .iter()
                .map(|e| e.name.as_str())
                .collect();
            assert_eq!(eps, [f.variant.entry_point()], "{f:?}");
            assert_eq!(
                has_function(&module, "store_counted"),
                f.variant.counters,
                "{f:?}"
            );
            compile(&module, &f);
        }
    }
}

#[test]
fn attributes_are_composed_only_when_the_scene_has_them_and_the_job_uses_them() {
    for storage in STORAGES {
        for (scene, job, expected) in [
            (VertexAttributes::NONE, VertexAttributes::NONE, false),
            (VertexAttributes::NONE, NORMALS, false),
            (NORMALS, VertexAttributes::NONE, false),
            (NORMALS, NORMALS, true),
        ] {
            let f = PipelineFeatures::for_job(
                storage,
                Traversal::Stackless,
                Query::Closest,
                false,
                scene,
                job,
            );
            let module = parse(&f.source());
            let normals = declared(&module).contains(&(0, 3, "vertex_normals".to_string()));
            assert_eq!(normals, expected, "{storage:?} scene {scene:?} job {job:?}");
            assert_eq!(has_function(&module, "shading_normal"), expected);
            assert_eq!(f.names().contains(&"vertex-normals"), expected);
            assert_eq!(
                f.bindings().iter().any(|b| b.name == "vertex_normals"),
                expected
            );
            compile(&module, &f);
        }
    }
}

#[test]
fn everything_on_declares_everything_and_is_kernel_source() {
    for storage in STORAGES {
        for f in every_job(storage) {
            let all = f.with_composition(Composition::EverythingOn);
            // `kernel_source` reads the rays from a buffer; a ray texture swaps that file.
            let expected = match f.variant.rays {
                RayInput::Buffer => kernel_source(storage),
                RayInput::Texture => ModuleSet {
                    rays: RayInput::Texture,
                    ..ModuleSet::everything(storage, Precision::WatertightF32, Entries::All)
                }
                .compose(bvhtrace_gpu::shaders::BVH_GROUP),
            };
            assert_eq!(all.source(), expected, "{f:?}");
            let module = parse(&all.source());
            let names: BTreeSet<String> =
                declared(&module).into_iter().map(|(_, _, n)| n).collect();
            assert!(names.contains("counters"), "{names:?}");
            assert!(names.iter().any(|n| n.contains("escape")), "{names:?}");
            assert_eq!(module.entry_points.len(), 4);
            // The specialised module is strictly smaller.
            assert!(f.source().len() < all.source().len());
            assert!(declared(&parse(&f.source())).len() <= names.len());
        }
    }
    // Precision is part of the module: a variant's triangle test is the one composed.
    let f = PipelineFeatures::new(
        bvhtrace_gpu::shaders::KernelVariant::new(
            BvhStorage::Buffers,
            Traversal::FullStack,
            Query::Closest,
            false,
        )
        .with_precision(Precision::MollerTrumboreF32),
    );
    let name = bvhtrace_gpu::shaders::triangle_wgsl(Precision::MollerTrumboreF32).0;
    assert!(f.source().contains(&format!("// ---- {name} ----")));
}

// ---- on a GPU ----

fn context() -> Option<GpuContext> {
    match GpuContext::new(AdapterChoice::Auto) {
        Ok(ctx) => Some(ctx),
        Err(e @ GpuError::NoAdapter { .. }) => {
            eprintln!("SKIP features (GPU part): {e}");
            None
        }
        Err(e) => panic!("cannot open a GPU: {e}"),
    }
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
    let Some(ctx) = context() else { return };
    let (bvh, rays) = scene();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    let opts = |traversal, query, counters| TraceOptions {
        traversal,
        query,
        counters,
    };
    let a = opts(Traversal::FullStack, Query::Closest, false);
    let b = opts(Traversal::Stackless, Query::Any, true);
    assert_eq!(ctx.compile_counts(), (0, 0));
    let first = gpu.trace_with(&rays, &a).expect("trace a");
    assert_eq!(ctx.compile_counts(), (1, 1));
    // No counter buffers until a trace asks for counters.
    let n = rays.len() as u64;
    // Rays and hits: buffers (and the hits' readback), or whole rows of a ray texture (two
    // texels per ray) and of a hit texture (one), and the hit rows' readback
    // (`RayInput::for_storage`).
    let plain = match RayInput::for_storage(gpu.storage()) {
        RayInput::Buffer => n * bvhtrace_gpu::RAY_BYTES + 2 * n * bvhtrace_gpu::HIT_BYTES,
        RayInput::Texture => {
            let row = u64::from(bvhtrace_gpu::TEXEL_ROW);
            let rows = |texels: u64| texels.div_ceil(row) * row * 16;
            rows(2 * n) + 2 * rows(n)
        }
    };
    assert_eq!(gpu.scratch_bytes(), plain);
    let counted = gpu.trace_with(&rays, &b).expect("trace b");
    assert_eq!(ctx.compile_counts(), (2, 2), "b has its own module");
    assert_eq!(counted.counters.map(|c| c.len()), Some(rays.len()));
    assert_eq!(
        gpu.scratch_bytes(),
        plain + 2 * n * bvhtrace_gpu::COUNTERS_BYTES
    );
    // Back to a: cached.
    let again = gpu.trace_with(&rays, &a).expect("trace a again");
    assert_eq!(ctx.compile_counts(), (2, 2), "switching back recompiled");
    assert_eq!(first.hits, again.hits);
    // Any hit shares a's module (an override constant): a new pipeline, no new module.
    gpu.trace_with(&rays, &opts(Traversal::FullStack, Query::Any, false))
        .expect("trace");
    assert_eq!(ctx.compile_counts(), (2, 3));

    // Everything on: one more module and pipeline, the same answers; and back.
    ctx.set_composition(Composition::EverythingOn);
    let all = gpu.trace_with(&rays, &a).expect("everything on");
    assert_eq!(ctx.compile_counts(), (3, 4));
    assert_eq!(all.hits, first.hits, "everything-on and specialised differ");
    ctx.set_composition(Composition::Specialised);
    gpu.trace_with(&rays, &a).expect("specialised again");
    gpu.trace_with(&rays, &b).expect("b again");
    assert_eq!(ctx.compile_counts(), (3, 4), "switching back recompiled");
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
    let Some(ctx) = context() else { return };
    let (bvh, rays) = scene();
    let (nodes, tris) = (bvh.nodes.len() as u64, bvh.triangles.len() as u64);
    for traversal in TRAVERSALS {
        for storage in STORAGES {
            let f = PipelineFeatures::for_job(
                storage,
                traversal,
                Query::Closest,
                false,
                VertexAttributes::NONE,
                VertexAttributes::NONE,
            );
            let gpu = GpuBvh::upload(&ctx, &bvh, &f.upload_options()).expect("upload");
            let stats = *gpu.stats();
            let module = parse(&f.source());
            let declared = f.declared_bvh_bytes(nodes, tris);
            let planned = f.upload_bytes(nodes, tris);
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
                "{f:?}: uploaded vs PipelineFeatures::upload_bytes"
            );
            assert_eq!(
                stats.escapes_bytes > 0,
                traversal.needs_escapes(),
                "{f:?}: {stats:?}"
            );
            match storage {
                BvhStorage::Buffers => {
                    // Bytes the bindings declare (array stride x element count), from the
                    // reflected module, against the bytes uploaded.
                    let from_module: u64 = group0_strides(&module)
                        .iter()
                        .map(|(name, stride)| {
                            stride
                                * match name.as_str() {
                                    "bvh_nodes" => nodes,
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
                    // triangles here); taller ones (the eight escape links per node) pad at
                    // most their last row.
                    let row = u64::from(bvhtrace_gpu::TEXEL_ROW);
                    assert!(2 * nodes <= row && 3 * tris <= row, "scene too large");
                    let pad = stats.total_bytes() - declared;
                    if traversal.needs_escapes() {
                        assert!(8 * nodes > row && pad < 4 * row, "{f:?}: {stats:?}");
                    } else {
                        assert_eq!(pad, 0, "{f:?}: {stats:?}");
                    }
                    let tall = f.upload_bytes(100 * row, 100 * row);
                    assert!(tall.total_bytes() >= f.declared_bvh_bytes(100 * row, 100 * row));
                    assert!(
                        tall.total_bytes() < f.declared_bvh_bytes(100 * row, 100 * row) + 36 * row
                    );
                }
            }
            // The upload traces its job.
            let out = gpu.trace(&rays, traversal, Query::Closest).expect("trace");
            assert_eq!(out.hits.len(), rays.len());
        }
    }
}
