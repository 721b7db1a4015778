//! Leaving out what a job does not need, without a GPU: the specialised modules are
//! reflected with naga and must declare exactly the bindings [`KernelKey::bindings`]
//! lists: no attribute binding for a positions-only scene, no `counters` unless counters
//! are on, no escape links for the full stack, one entry point.

use std::collections::BTreeSet;

use bvhtrace_core::{Precision, Query, TraceOptions, Traversal};
use bvhtrace_engine::compose::{
    BVH_GROUP, Entries, ModuleSet, VertexAttributes, kernel_source, triangle_wgsl,
};
use bvhtrace_engine::key::Composition;
use bvhtrace_engine::storage::{RayInput, TEXEL_ROW};
use bvhtrace_engine::{BvhStorage, KernelKey};
use naga::Module;

mod common;
use common::{STORAGES, TRAVERSALS, compile_variant, parse, validate};

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

/// The bindings `f` lists, as [`declared`] gives a module's.
fn listed(f: &KernelKey) -> BTreeSet<(u32, u32, String)> {
    f.bindings()
        .iter()
        .map(|b| (b.group, b.binding, b.name.to_string()))
        .collect()
}

/// Every job a positions-only scene can be traced with.
fn every_job(storage: BvhStorage) -> Vec<KernelKey> {
    let mut v = Vec::new();
    for traversal in TRAVERSALS {
        for query in [Query::Closest, Query::Any] {
            for counters in [false, true] {
                // The job would shade with normals; the scene has none.
                let opts = TraceOptions::new(traversal, query).with_counters(counters);
                let f = KernelKey::for_job(storage, &opts, VertexAttributes::NONE, NORMALS);
                v.push(f);
                // `GpuBvh::trace` reads the rays from a texture with the BVH in textures;
                // `GpuBvh::record` from the caller's buffer.
                if storage == BvhStorage::Textures {
                    assert_eq!(f.rays, RayInput::Texture);
                    v.push(f.with_rays(RayInput::Buffer));
                }
            }
        }
    }
    v
}

/// Validates `module` and compiles its one entry point to SPIR-V with `f`'s overrides.
fn compile(module: &Module, f: &KernelKey) {
    compile_variant(module, &validate(module), f);
}

#[test]
fn positions_only_pipelines_declare_only_what_the_job_reads() {
    for storage in STORAGES {
        for f in every_job(storage) {
            let module = parse(&f.source());
            let got = declared(&module);
            assert_eq!(got, listed(&f), "{f:?}: declared vs KernelKey::bindings");

            let names: Vec<&str> = got.iter().map(|(_, _, n)| n.as_str()).collect();
            // No attribute binding: the scene has positions only.
            assert!(!names.contains(&"vertex_normals"), "{f:?}: {names:?}");
            assert!(!got.iter().any(|(g, b, _)| *g == 0 && *b >= 3), "{f:?}");
            // Counters only when asked for.
            assert_eq!(names.contains(&"counters"), f.counters, "{f:?}: {names:?}");
            // Escape links only for the walks that read them; and the other walks' code is
            // not in the module at all.
            let escapes = names.iter().any(|n| n.contains("escape"));
            let full = f.traversal == Traversal::FullStack;
            let wide = f.traversal == Traversal::Wide;
            let short = !full && !wide;
            assert_eq!(escapes, short, "{f:?}: {names:?}");
            assert_eq!(
                has_function(&module, "bvh_trace_short_stack"),
                short,
                "{f:?}"
            );
            assert_eq!(has_function(&module, "bvh_trace_full_stack"), full, "{f:?}");
            assert_eq!(has_function(&module, "bvh_trace_wide"), wide, "{f:?}");
            assert_eq!(has_function(&module, "bvh_load_escape"), short, "{f:?}");
            // Either layout in the storage the key asked for: the wide layout's nodes and
            // triangles in buffers or textures, never both kinds.
            assert_eq!(f.storage, storage, "{f:?}");
            let textures = storage == BvhStorage::Textures;
            let (wide_nodes, tris) = if textures {
                ("bvh_wide_node_texels", "bvh_triangle_texels")
            } else {
                ("bvh_wide_nodes", "bvh_triangles")
            };
            assert_eq!(names.contains(&wide_nodes), wide, "{f:?}: {names:?}");
            assert!(names.contains(&tris), "{f:?}: {names:?}");
            let bvh_texels = names
                .iter()
                .filter(|n| n.starts_with("bvh_") && n.ends_with("_texels"))
                .count();
            let bvh_arrays = names
                .iter()
                .filter(|n| {
                    [
                        "bvh_nodes",
                        "bvh_wide_nodes",
                        "bvh_triangles",
                        "bvh_escapes",
                    ]
                    .contains(n)
                })
                .count();
            assert_eq!(
                (bvh_texels > 0, bvh_arrays > 0),
                (textures, !textures),
                "{f:?}: {names:?}"
            );
            assert_eq!(has_function(&module, "bvh_load_wide_links"), wide, "{f:?}");
            assert_eq!(has_function(&module, "bvh_load_node"), !wide, "{f:?}");
            // One entry point, the variant's.
            let eps: Vec<&str> = module
                .entry_points
                .iter()
                .map(|e| e.name.as_str())
                .collect();
            assert_eq!(eps, [f.entry_point()], "{f:?}");
            assert_eq!(
                has_function(&module, "bvh_store_counted"),
                f.counters,
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
            let opts = TraceOptions::closest(Traversal::Stackless);
            let f = KernelKey::for_job(storage, &opts, scene, job);
            let module = parse(&f.source());
            let normals = declared(&module).contains(&(0, 3, "vertex_normals".to_string()));
            assert_eq!(normals, expected, "{storage:?} scene {scene:?} job {job:?}");
            assert_eq!(has_function(&module, "bvh_shading_normal"), expected);
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
            let wide = f.traversal == Traversal::Wide;
            // `kernel_source` reads the rays from a buffer; a ray texture swaps that file.
            // The wide walk's everything is its own module (its nodes are binding 0).
            let expected = match (wide, f.rays) {
                (false, RayInput::Buffer) => kernel_source(storage),
                (false, RayInput::Texture) => ModuleSet {
                    rays: RayInput::Texture,
                    ..ModuleSet::everything(storage, Precision::WatertightF32, Entries::All)
                }
                .compose(BVH_GROUP),
                (true, rays) => ModuleSet {
                    rays,
                    ..ModuleSet::wide_in(storage, Precision::WatertightF32, Entries::All)
                }
                .compose(BVH_GROUP),
            };
            assert_eq!(all.source(), expected, "{f:?}");
            let module = parse(&all.source());
            let names: BTreeSet<String> =
                declared(&module).into_iter().map(|(_, _, n)| n).collect();
            assert!(names.contains("counters"), "{names:?}");
            assert_eq!(
                names.iter().any(|n| n.contains("escape")),
                !wide,
                "{names:?}"
            );
            let eps: BTreeSet<&str> = module
                .entry_points
                .iter()
                .map(|e| e.name.as_str())
                .collect();
            let expected_eps: BTreeSet<&str> = if wide {
                ["bvh_trace_wide_main", "bvh_trace_wide_counted"].into()
            } else {
                [
                    "bvh_trace_full_stack_main",
                    "bvh_trace_full_stack_counted",
                    "bvh_trace_short_stack_main",
                    "bvh_trace_short_stack_counted",
                ]
                .into()
            };
            assert_eq!(eps, expected_eps, "{f:?}");
            assert!(eps.contains(f.entry_point()), "{f:?}");
            // The specialised module is strictly smaller.
            assert!(f.source().len() < all.source().len());
            assert!(declared(&parse(&f.source())).len() <= names.len());
        }
    }
    // Precision is part of the module: a variant's triangle test is the one composed.
    let opts =
        TraceOptions::closest(Traversal::FullStack).with_precision(Precision::MollerTrumboreF32);
    let f = KernelKey::new(BvhStorage::Buffers, &opts);
    let name = triangle_wgsl(Precision::MollerTrumboreF32).0;
    assert!(f.source().contains(&format!("// ---- {name} ----")));
}

#[test]
fn the_instances_binding_is_declared_only_for_two_levels() {
    for storage in STORAGES {
        for traversal in TRAVERSALS {
            let opts = TraceOptions::closest(traversal).with_mask(5);
            for instances in [false, true] {
                let f = KernelKey::new(storage, &opts).with_instances(instances);
                let module = parse(&f.source());
                let got = declared(&module);
                assert_eq!(got, listed(&f), "{f:?}: declared vs KernelKey::bindings");
                let has = got
                    .iter()
                    .any(|(g, b, n)| (*g, *b) == (0, 4) && n == "bvh_instances");
                assert_eq!(has, instances, "{f:?}");
                let mask = f
                    .constants()
                    .iter()
                    .find(|(n, _)| *n == "BVH_RAY_MASK")
                    .map(|c| c.1);
                assert_eq!(mask, instances.then_some(5.0), "{f:?}");
                assert_eq!(f.names().contains(&"instances"), instances, "{f:?}");
                compile(&module, &f);
            }
        }
    }
}

/// The alpha masks' binding (5) and test are composed only for a masked BVH, in every walk,
/// one mesh and two levels, both queries; the module validates and compiles with them, and
/// without them the source is what it was (no masks binding, the leaf visit untouched).
#[test]
fn the_masks_are_composed_only_for_masked_trees() {
    for storage in STORAGES {
        for traversal in TRAVERSALS {
            for query in [Query::Closest, Query::Any] {
                for instances in [false, true] {
                    let plain = KernelKey::new(storage, &TraceOptions::new(traversal, query))
                        .with_instances(instances);
                    for masks in [false, true] {
                        let f = plain.with_masks(masks);
                        let module = parse(&f.source());
                        let got = declared(&module);
                        assert_eq!(got, listed(&f), "{f:?}: declared vs KernelKey::bindings");
                        let has = got
                            .iter()
                            .any(|(g, b, n)| (*g, *b) == (0, 5) && n == "bvh_masks");
                        assert_eq!(has, masks, "{f:?}");
                        assert_eq!(has_function(&module, "bvh_alpha_accept"), masks, "{f:?}");
                        assert_eq!(f.names().contains(&"alpha-masks"), masks, "{f:?}");
                        compile(&module, &f);
                    }
                    assert!(
                        plain
                            .source()
                            .contains("prim < (*best).prim))/*BVH_ACCEPT*/) {")
                    );
                }
            }
        }
    }
}

/// An upload in textures holds whole texels per element (two per binary node, five per
/// wide one, three per triangle) and, past one row, whole rows of `TEXEL_ROW`: the bytes
/// of buffers while one row holds them, whole rows from the element that starts a second.
#[test]
fn texture_uploads_count_whole_rows_for_either_layout() {
    let row = u64::from(TEXEL_ROW);
    for (traversal, node_texels) in [(Traversal::FullStack, 2), (Traversal::Wide, 5)] {
        let opts = TraceOptions::closest(traversal);
        let [buffers, textures] = STORAGES.map(|s| KernelKey::new(s, &opts));
        let fit = row / node_texels;
        for (nodes, tris, texel_rows) in [(fit, row / 3, (1, 1)), (fit + 1, row / 3 + 1, (2, 2))] {
            let b = buffers.upload_bytes(nodes, tris, 0);
            let t = textures.upload_bytes(nodes, tris, 0);
            assert_eq!(b.nodes_bytes, nodes * node_texels * 16, "{traversal}");
            assert_eq!(b.triangles_bytes, tris * 48, "{traversal}");
            assert_eq!(b.total_bytes(), buffers.declared_bvh_bytes(nodes, tris, 0));
            let (node_rows, tri_rows) = texel_rows;
            let expected = |rows: u64, bytes: u64| if rows == 1 { bytes } else { rows * row * 16 };
            assert_eq!(
                (t.nodes_bytes, t.triangles_bytes),
                (
                    expected(node_rows, b.nodes_bytes),
                    expected(tri_rows, b.triangles_bytes)
                ),
                "{traversal}: {nodes} nodes, {tris} triangles"
            );
            assert_eq!(t.storage, BvhStorage::Textures);
        }
    }
}

/// A tree split into pages (`bvhtrace_engine::pages`): every walk's kernel, one mesh and
/// two levels, declares a binding per page of each split array (and nothing more), reads
/// every element through the page function, validates and compiles; a key that splits
/// nothing composes the module it always did.
#[test]
fn split_trees_declare_a_binding_per_page() {
    use bvhtrace_engine::pages::{PAGE_BINDING_STRIDE, Pages};
    let pages = Pages {
        log2_bytes: 20,
        nodes: 3,
        triangles: 2,
        escapes: 4,
    };
    for traversal in TRAVERSALS {
        for instances in [false, true] {
            let opts = TraceOptions::new(traversal, Query::Any).with_counters(true);
            let whole = KernelKey::new(BvhStorage::Buffers, &opts).with_instances(instances);
            let split = whole.with_pages(pages);
            assert_eq!(whole.with_pages(Pages::ONE).source(), whole.source());
            let module = parse(&split.source());
            let got = declared(&module);
            assert_eq!(
                got,
                listed(&split),
                "{split:?}: declared vs KernelKey::bindings"
            );
            let extra = got.len() - declared(&parse(&whole.source())).len();
            let wide = traversal == Traversal::Wide;
            let escapes = !wide && traversal != Traversal::FullStack;
            let want = 2 + 1 + if escapes { 3 } else { 0 };
            assert_eq!(extra, want, "{split:?}");
            for (g, b, name) in &got {
                if *g == 0 && *b >= PAGE_BINDING_STRIDE {
                    assert!(
                        name.ends_with(&format!("_{}", b / PAGE_BINDING_STRIDE)),
                        "{name}"
                    );
                }
            }
            let nodes = if wide { "bvh_wide_nodes" } else { "bvh_nodes" };
            assert!(has_function(&module, &format!("{nodes}_at")), "{split:?}");
            assert!(has_function(&module, "bvh_triangles_at"), "{split:?}");
            compile(&module, &split);
        }
    }
}
