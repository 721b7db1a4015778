//! Checks that need no GPU: the composed WGSL parses, its shared structs have exactly the
//! Rust types' layout, its constants match the Rust ones, and every kernel variant
//! validates and compiles to SPIR-V once its override constants are given values.

use std::mem::{offset_of, size_of};

use bvhtrace_core::Traversal;
use bvhtrace_core::flat::{ESCAPE_BLOCK, NO_ESCAPE, OCTANTS};
use bvhtrace_core::intersect::{BOX_CULL_SLACK, BOX_TFAR_SCALE, BOX_TFAR_SCALE_NEG};
use bvhtrace_core::surface::{OFFSET_FLOAT_SCALE, OFFSET_INT_SCALE, OFFSET_ORIGIN};
use bvhtrace_core::traverse::MAX_SHORT_STACK;
use bvhtrace_core::{
    Counters, FlatInstance, FlatNode, FlatTriangle, Hit, INVALID_RAY, MISS, Ray, WideNode,
};
use bvhtrace_engine::compose::{Entries, ModuleSet, WORKGROUP_SIZE, kernel_source};
use bvhtrace_engine::storage::TEXEL_ROW;
use bvhtrace_engine::walks::{FULL_STACK_SIZE, STACK_LANES, WIDE_STACK_GROUPS};
use bvhtrace_engine::{BvhStorage, KernelKey, LibraryShape, wgsl_library};

const STORAGES: [BvhStorage; 2] = [BvhStorage::Buffers, BvhStorage::Textures];
use naga::{Expression, Literal, Module, TypeInner};

mod common;
use common::{SHARED_FILES, compile_entry, compile_variant, parse, validate};

/// `(name, offset)` of each member of the struct type called `name`, and its size.
fn struct_layout(module: &Module, name: &str) -> (Vec<(String, u32)>, u32) {
    let ty = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("no WGSL struct {name}"))
        .1;
    match &ty.inner {
        TypeInner::Struct { members, span } => (
            members
                .iter()
                .map(|m| (m.name.clone().unwrap_or_default(), m.offset))
                .collect(),
            *span,
        ),
        other => panic!("{name} is not a struct: {other:?}"),
    }
}

fn check_struct(module: &Module, name: &str, size: usize, fields: &[(&str, usize)]) {
    let (members, span) = struct_layout(module, name);
    assert_eq!(span as usize, size, "size of {name}");
    let got: Vec<(&str, usize)> = members
        .iter()
        .map(|(n, o)| (n.as_str(), *o as usize))
        .collect();
    assert_eq!(got, fields, "fields (name, offset) of {name}");
}

#[test]
fn shared_structs_match_rust_layout() {
    for storage in STORAGES {
        check_structs(&parse(&kernel_source(storage)));
    }
    let wide = parse(&wide_source(false));
    check_structs(&wide);
    check_struct(
        &wide,
        "BvhWideNode",
        size_of::<WideNode>(),
        &[
            ("origin", offset_of!(WideNode, origin)),
            ("exponents", offset_of!(WideNode, exponents)),
            ("child_base", offset_of!(WideNode, child_base)),
            ("triangle_base", offset_of!(WideNode, triangle_base)),
            ("counts", offset_of!(WideNode, counts)),
            ("q_lo", offset_of!(WideNode, q_lo)),
            ("q_hi", offset_of!(WideNode, q_hi)),
        ],
    );
    // The node array's stride is the Rust size too (no padding between nodes).
    let (_, stride) = group0_array(&wide, "bvh_wide_nodes");
    assert_eq!(stride as usize, size_of::<WideNode>());
}

/// The everything-on module of the wide layout (its two entry points), one mesh or two
/// levels.
fn wide_source(instances: bool) -> String {
    ModuleSet {
        instances,
        ..ModuleSet::wide(bvhtrace_core::Precision::WatertightF32, Entries::All)
    }
    .compose(0)
}

/// The element type's name and the stride of the storage array `name`.
fn group0_array(module: &Module, name: &str) -> (String, u32) {
    let (_, g) = module
        .global_variables
        .iter()
        .find(|(_, g)| g.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("no {name}"));
    match module.types[g.ty].inner {
        TypeInner::Array { base, stride, .. } => {
            (module.types[base].name.clone().unwrap_or_default(), stride)
        }
        ref other => panic!("{name} is not an array: {other:?}"),
    }
}

/// The alpha masks' records, read word by word from `bvh_masks`, have the Rust layout
/// (`MaskTables::words` writes them with bytemuck), and the loaders' strides are theirs.
#[test]
fn mask_structs_match_rust_layout() {
    use bvhtrace_core::masks::{MaskHeader, MaskMaterial, MaskTriangle};
    use bvhtrace_engine::KernelKey;
    let key = KernelKey::new(BvhStorage::Buffers, &Default::default()).with_masks(true);
    let module = parse(&key.source());
    check_struct(
        &module,
        "BvhMaskHeader",
        size_of::<MaskHeader>(),
        &[
            ("instance_bases", offset_of!(MaskHeader, instance_bases)),
            ("states", offset_of!(MaskHeader, states)),
            ("triangles", offset_of!(MaskHeader, triangles)),
            ("materials", offset_of!(MaskHeader, materials)),
            ("texels", offset_of!(MaskHeader, texels)),
        ],
    );
    let uv = offset_of!(MaskTriangle, uv);
    check_struct(
        &module,
        "BvhMaskTriangle",
        size_of::<MaskTriangle>(),
        &[
            ("u0", uv),
            ("v0", uv + 4),
            ("u1", uv + 8),
            ("v1", uv + 12),
            ("u2", uv + 16),
            ("v2", uv + 20),
            ("material", offset_of!(MaskTriangle, material)),
            ("micro", offset_of!(MaskTriangle, micro)),
        ],
    );
    check_struct(
        &module,
        "BvhMaskMaterial",
        size_of::<MaskMaterial>(),
        &[
            ("first_texel", offset_of!(MaskMaterial, first_texel)),
            ("width", offset_of!(MaskMaterial, width)),
            ("height", offset_of!(MaskMaterial, height)),
            ("wrap", offset_of!(MaskMaterial, wrap)),
            ("min_texel", offset_of!(MaskMaterial, min_texel)),
        ],
    );
    for (name, size) in [
        ("BVH_MASK_TRIANGLE_WORDS", size_of::<MaskTriangle>()),
        ("BVH_MASK_MATERIAL_WORDS", size_of::<MaskMaterial>()),
    ] {
        assert_eq!(
            constant(&module, name),
            Literal::U32((size / 4) as u32),
            "{name}"
        );
    }
    use bvhtrace_core::masks as m;
    for (name, value) in [
        ("BVH_MICRO_CELLS", m::MICRO_CELLS),
        (
            "BVH_MICRO_WORD",
            (offset_of!(MaskTriangle, micro) / 4) as u32,
        ),
        ("BVH_MICRO_TEST", m::MICRO_TEST),
        ("BVH_MICRO_OPAQUE", m::MICRO_OPAQUE),
        ("BVH_MASK_OPAQUE", bvhtrace_core::masks::MASK_OPAQUE),
        (
            "BVH_MASK_TRANSPARENT",
            bvhtrace_core::masks::MASK_TRANSPARENT,
        ),
        ("BVH_NO_MASKS", bvhtrace_core::masks::NO_MASKS),
    ] {
        assert_eq!(constant(&module, name), Literal::U32(value), "{name}");
    }
}

fn check_structs(module: &Module) {
    check_struct(
        module,
        "BvhNode",
        size_of::<FlatNode>(),
        &[
            ("min", offset_of!(FlatNode, min)),
            ("right_or_first", offset_of!(FlatNode, right_or_first)),
            ("max", offset_of!(FlatNode, max)),
            // `meta` is a reserved word in WGSL.
            ("meta_bits", offset_of!(FlatNode, meta)),
        ],
    );
    check_struct(
        module,
        "BvhTriangle",
        size_of::<FlatTriangle>(),
        &[
            ("v0", offset_of!(FlatTriangle, v0)),
            ("prim", offset_of!(FlatTriangle, prim)),
            ("v1", offset_of!(FlatTriangle, v1)),
            ("pad1", offset_of!(FlatTriangle, _pad1)),
            ("v2", offset_of!(FlatTriangle, v2)),
            ("pad2", offset_of!(FlatTriangle, _pad2)),
        ],
    );
    check_struct(
        module,
        "BvhInstance",
        size_of::<FlatInstance>(),
        &[
            ("world_to_object", offset_of!(FlatInstance, world_to_object)),
            ("root", offset_of!(FlatInstance, root)),
            ("prim_base", offset_of!(FlatInstance, prim_base)),
            ("mask", offset_of!(FlatInstance, mask)),
            ("user_id", offset_of!(FlatInstance, user_id)),
        ],
    );
    check_struct(
        module,
        "BvhRay",
        size_of::<Ray>(),
        &[
            ("origin", offset_of!(Ray, origin)),
            ("t_min", offset_of!(Ray, t_min)),
            ("dir", offset_of!(Ray, dir)),
            ("t_max", offset_of!(Ray, t_max)),
        ],
    );
    check_struct(
        module,
        "BvhHit",
        size_of::<Hit>(),
        &[
            ("t", offset_of!(Hit, t)),
            ("prim", offset_of!(Hit, prim)),
            ("u", offset_of!(Hit, u)),
            ("v", offset_of!(Hit, v)),
        ],
    );
    check_struct(
        module,
        "BvhCounters",
        size_of::<Counters>(),
        &[
            ("nodes", offset_of!(Counters, nodes)),
            ("tris", offset_of!(Counters, tris)),
        ],
    );
}

fn constant(module: &Module, name: &str) -> Literal {
    let (_, c) = module
        .constants
        .iter()
        .find(|(_, c)| c.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("no WGSL constant {name}"));
    match module.global_expressions[c.init] {
        Expression::Literal(l) => l,
        ref e => panic!("{name} is not a literal: {e:?}"),
    }
}

#[test]
fn constants_match_rust() {
    let module = parse(&kernel_source(BvhStorage::Textures));
    assert_eq!(
        constant(&module, "BVH_TEXEL_ROW_MASK"),
        Literal::U32(TEXEL_ROW - 1)
    );
    assert_eq!(
        constant(&module, "BVH_TEXEL_ROW_LOG2"),
        Literal::U32(TEXEL_ROW.trailing_zeros())
    );
    assert!(TEXEL_ROW.is_power_of_two());
    match constant(&module, "BVH_BOX_TFAR_SCALE") {
        Literal::F32(v) => assert_eq!(v.to_bits(), BOX_TFAR_SCALE.to_bits(), "BOX_TFAR_SCALE"),
        l => panic!("BOX_TFAR_SCALE: {l:?}"),
    }
    match constant(&module, "BVH_BOX_TFAR_SCALE_NEG") {
        Literal::F32(v) => assert_eq!(
            v.to_bits(),
            BOX_TFAR_SCALE_NEG.to_bits(),
            "BOX_TFAR_SCALE_NEG"
        ),
        l => panic!("BOX_TFAR_SCALE_NEG: {l:?}"),
    }
    match constant(&module, "BVH_BOX_CULL_SLACK") {
        Literal::F32(v) => assert_eq!(v.to_bits(), BOX_CULL_SLACK.to_bits(), "BOX_CULL_SLACK"),
        l => panic!("BOX_CULL_SLACK: {l:?}"),
    }
    // The escape links' layout (`flat::escape_index`), which the walks index themselves.
    assert_eq!(
        constant(&module, "BVH_ESCAPE_BLOCK_LOG2"),
        Literal::U32(ESCAPE_BLOCK.trailing_zeros())
    );
    assert!(ESCAPE_BLOCK.is_power_of_two());
    assert_eq!(
        constant(&module, "BVH_ESCAPE_BLOCK"),
        Literal::U32(ESCAPE_BLOCK as u32)
    );
    assert_eq!(
        constant(&module, "BVH_OCTANTS"),
        Literal::U32(OCTANTS as u32)
    );
    assert_eq!(constant(&module, "BVH_NO_ESCAPE"), Literal::U32(NO_ESCAPE));
    assert_eq!(constant(&module, "BVH_MISS"), Literal::U32(MISS));
    // The secondary-ray origin offset (`surface::offset_ray_origin`).
    for (name, value) in [
        ("BVH_OFFSET_ORIGIN", OFFSET_ORIGIN),
        ("BVH_OFFSET_FLOAT_SCALE", OFFSET_FLOAT_SCALE),
        ("BVH_OFFSET_INT_SCALE", OFFSET_INT_SCALE),
    ] {
        match constant(&module, name) {
            Literal::F32(v) => assert_eq!(v.to_bits(), value.to_bits(), "{name}"),
            l => panic!("{name}: {l:?}"),
        }
    }
    assert_eq!(
        constant(&module, "BVH_INVALID_RAY"),
        Literal::U32(INVALID_RAY)
    );
    assert_eq!(
        constant(&module, "BVH_MAX_SHORT_STACK"),
        Literal::U32(MAX_SHORT_STACK)
    );
    assert_eq!(
        constant(&module, "BVH_FULL_STACK_SIZE"),
        Literal::U32(FULL_STACK_SIZE)
    );
    assert_eq!(
        constant(&module, "BVH_WORKGROUP_SIZE"),
        Literal::U32(WORKGROUP_SIZE)
    );
    // The wide walk's stack: node groups of two entries in the same per-lane stacks.
    let wide = parse(&wide_source(true));
    assert_eq!(
        constant(&wide, "BVH_WIDE_STACK_GROUPS"),
        Literal::U32(WIDE_STACK_GROUPS)
    );
    assert_eq!(2 * WIDE_STACK_GROUPS, FULL_STACK_SIZE);
    // The wide layout in textures: whole texels per node, the binary layout's rows.
    let wide_texels = parse(
        wgsl_library(
            LibraryShape::new(BvhStorage::Textures, false, Traversal::Wide),
            0,
        )
        .source(),
    );
    assert_eq!(size_of::<WideNode>() % 16, 0);
    assert_eq!(
        constant(&wide_texels, "BVH_WIDE_NODE_TEXELS"),
        Literal::U32((size_of::<WideNode>() / 16) as u32)
    );
    assert_eq!(
        constant(&wide_texels, "BVH_TEXEL_ROW_MASK"),
        Literal::U32(TEXEL_ROW - 1)
    );
    // The per-lane stacks: one per invocation of an entry point's workgroup, deep enough
    // for the full stack and the short stack's largest ring.
    assert_eq!(
        constant(&module, "BVH_STACK_LANES"),
        Literal::U32(STACK_LANES)
    );
    const { assert!(WORKGROUP_SIZE <= STACK_LANES) };
    const { assert!(FULL_STACK_SIZE >= MAX_SHORT_STACK) };
    for ep in &module.entry_points {
        assert_eq!(ep.workgroup_size, [WORKGROUP_SIZE, 1, 1], "{}", ep.name);
    }
}

/// Every traversal (full stack, stackless, short stack with k = 1, 6, 32, wide) x query x
/// counters: overrides resolved as the pipelines resolve them, validated, and compiled to
/// SPIR-V (what wgpu hands the Vulkan driver).
#[test]
fn every_variant_validates_and_compiles() {
    let mut seen = std::collections::HashSet::new();
    for storage in STORAGES {
        compile_variants(storage, &mut seen);
    }
    // 2 storages; full stack, stackless, 3 short-stack sizes; 2 queries; 2 counter
    // settings; one mesh or two levels. The wide walk's keys are one set per storage
    // whatever `k` (no ring): 2 queries, 2 counter settings, 2 levels.
    assert_eq!(seen.len(), 2 * 5 * 2 * 2 * 2 + 2 * 2 * 2 * 2);
    for storage in STORAGES {
        assert_eq!(
            seen.iter()
                .filter(|k| k.traversal == bvhtrace_core::Traversal::Wide && k.storage == storage)
                .count(),
            8,
            "{storage:?}"
        );
    }
}

fn compile_variants(storage: BvhStorage, seen: &mut std::collections::HashSet<KernelKey>) {
    // The everything-on modules of one mesh (`kernel_source`) and of two levels, for the
    // binary walks and for the wide one (a module of its own: its nodes are binding 0).
    let modules = [false, true].map(|wide| {
        [false, true].map(|instances| {
            let mut opts = bvhtrace_core::TraceOptions::default();
            if wide {
                opts.traversal = bvhtrace_core::Traversal::Wide;
            }
            let m = parse(
                &KernelKey::new(storage, &opts)
                    .with_instances(instances)
                    .with_composition(bvhtrace_engine::key::Composition::EverythingOn)
                    .source(),
            );
            let info = validate(&m);
            (m, info)
        })
    });
    assert_eq!(
        KernelKey::new(storage, &Default::default())
            .with_composition(bvhtrace_engine::key::Composition::EverythingOn)
            .source(),
        kernel_source(storage)
    );
    for k in [1, 6, MAX_SHORT_STACK] {
        for v in KernelKey::all_for_k(storage, k) {
            if !seen.insert(v) {
                continue;
            }
            let wide = v.traversal == bvhtrace_core::Traversal::Wide;
            let (module, info) = &modules[usize::from(wide)][usize::from(v.instances)];
            compile_variant(module, info, &v);
        }
    }
}

/// The one-mesh wide library in `storage`, bound at group 3.
fn wide_library(storage: BvhStorage) -> String {
    wgsl_library(LibraryShape::new(storage, false, Traversal::Wide), 3).to_string()
}

/// The wide library `lib` (bound at group 3) called from a compute shader of ours: it
/// validates, and declares `bindings` in group 3.
fn wide_library_module(lib: &str, bindings: [(u32, &str); 2]) -> naga::Module {
    let module = parse(&format!(
        "{lib}\n@group(0) @binding(0) var<storage, read_write> out: array<u32>;\n\
         @compute @workgroup_size(1) fn main(@builtin(local_invocation_index) lane: u32) {{\n\
             let ray = BvhRay(vec3<f32>(0.0), 0.0, vec3<f32>(0.0, 0.0, 1.0), 1.0);\n\
             out[0] = bvh_trace_wide(ray, false, lane).hit.prim;\n\
         }}"
    ));
    validate(&module);
    for (binding, name) in bindings {
        let found = module.global_variables.iter().any(|(_, g)| {
            g.name.as_deref() == Some(name)
                && g.binding == Some(naga::ResourceBinding { group: 3, binding })
        });
        assert!(found, "{name} at group 3 binding {binding}");
    }
    module
}

#[test]
fn the_refit_params_match_rust_layout() {
    use bvhtrace_engine::programs::{RefitParams, refit_source};
    let module = parse(&refit_source());
    check_struct(
        &module,
        "RefitParams",
        size_of::<RefitParams>(),
        &[
            ("first", offset_of!(RefitParams, first)),
            ("count", offset_of!(RefitParams, count)),
            ("row", offset_of!(RefitParams, row)),
            ("stride", offset_of!(RefitParams, stride)),
            ("vertices", offset_of!(RefitParams, vertices)),
            ("triangles", offset_of!(RefitParams, triangles)),
            ("indexed", offset_of!(RefitParams, indexed)),
            ("pad", offset_of!(RefitParams, pad)),
        ],
    );
}

#[test]
fn the_skin_params_match_rust_layout() {
    use bvhtrace_engine::programs::{SkinParams, skin_source};
    let module = parse(&skin_source());
    check_struct(
        &module,
        "SkinParams",
        size_of::<SkinParams>(),
        &[
            ("vertices", offset_of!(SkinParams, vertices)),
            ("joints", offset_of!(SkinParams, joints)),
            ("row", offset_of!(SkinParams, row)),
            ("pad", offset_of!(SkinParams, pad)),
        ],
    );
}

#[test]
fn the_morph_params_match_rust_layout() {
    use bvhtrace_engine::programs::{MorphParams, morph_source};
    let module = parse(&morph_source());
    check_struct(
        &module,
        "MorphParams",
        size_of::<MorphParams>(),
        &[
            ("vertices", offset_of!(MorphParams, vertices)),
            ("targets", offset_of!(MorphParams, targets)),
            ("row", offset_of!(MorphParams, row)),
            ("pad", offset_of!(MorphParams, pad)),
        ],
    );
}

#[test]
fn every_file_is_composed_and_the_library_rebinds_its_group() {
    for storage in STORAGES {
        check_library(storage);
    }
    // The wide library: the shared files and its own, no binary walk, its bindings
    // rebound too.
    let lib = wide_library(BvhStorage::Buffers);
    for (name, _) in SHARED_FILES
        .iter()
        .filter(|(n, _)| !["traverse_full_stack.wgsl", "traverse_short_stack.wgsl"].contains(n))
    {
        assert!(lib.contains(&format!("// ---- {name} ----")), "{name}");
    }
    for name in [
        "bvh_buffers_wide.wgsl",
        "bvh_buffers_triangles.wgsl",
        "traverse_wide.wgsl",
    ] {
        assert!(lib.contains(&format!("// ---- {name} ----")), "{name}");
    }
    assert!(!lib.contains("@compute"), "the library has no entry points");
    assert!(!lib.contains("fn bvh_trace_full_stack") && !lib.contains("fn bvh_trace_short_stack"));
    let module = wide_library_module(&lib, [(0, "bvh_wide_nodes"), (1, "bvh_triangles")]);
    assert_eq!(group0_array(&module, "bvh_wide_nodes").0, "BvhWideNode");
    // In textures: the texel files in place of the buffer ones, the same walk.
    let lib = wide_library(BvhStorage::Textures);
    for (name, composed) in [
        ("bvh_textures_wide.wgsl", true),
        ("bvh_textures_triangles.wgsl", true),
        ("traverse_wide.wgsl", true),
        ("bvh_buffers_wide.wgsl", false),
        ("bvh_buffers_triangles.wgsl", false),
        ("bvh_textures.wgsl", false),
    ] {
        let found = lib.contains(&format!("// ---- {name} ----"));
        assert_eq!(found, composed, "{name}");
    }
    wide_library_module(
        &lib,
        [(0, "bvh_wide_node_texels"), (1, "bvh_triangle_texels")],
    );
}

fn check_library(storage: BvhStorage) {
    let src = kernel_source(storage);
    for (name, _) in SHARED_FILES.iter().chain([&storage.wgsl()]) {
        assert!(src.contains(&format!("// ---- {name} ----")), "{name}");
    }
    let lib = ModuleSet::everything(storage, Default::default(), Entries::None).compose(3);
    assert!(!lib.contains("@compute"), "the library has no entry points");
    let module = parse(&format!(
        "{lib}\n@group(0) @binding(0) var<storage, read_write> out: array<u32>;\n\
         @compute @workgroup_size(1) fn main(@builtin(local_invocation_index) lane: u32) {{\n\
             let ray = BvhRay(vec3<f32>(0.0), 0.0, vec3<f32>(0.0, 0.0, 1.0), 1.0);\n\
             out[0] = bvh_trace_short_stack(ray, false, 0u, lane).hit.prim + bvh_trace_full_stack(ray, true, lane).hit.prim;\n\
         }}"
    ));
    validate(&module);
    let groups: Vec<(String, u32)> = module
        .global_variables
        .iter()
        .filter_map(|(_, g)| Some((g.name.clone()?, g.binding.as_ref()?.group)))
        .collect();
    let names = match storage {
        BvhStorage::Buffers => ["bvh_nodes", "bvh_triangles", "bvh_escapes"],
        BvhStorage::Textures => [
            "bvh_node_texels",
            "bvh_triangle_texels",
            "bvh_escape_texels",
        ],
    };
    for (binding, name) in names.iter().enumerate() {
        let found = module.global_variables.iter().any(|(_, g)| {
            g.name.as_deref() == Some(*name)
                && g.binding
                    == Some(naga::ResourceBinding {
                        group: 3,
                        binding: binding as u32,
                    })
        });
        assert!(found, "{name} at group 3 binding {binding}: {groups:?}");
    }
}

/// Compiles entry point `main` of `module` to SPIR-V (its overrides at their defaults).
fn compile_main(module: &Module, what: &str) {
    let info = validate(module);
    compile_entry(module, &info, "main", &Default::default(), what);
}

/// Every library shape (storage, one mesh or two levels, each walk) gives the same calls:
/// one user shader validates and compiles with each, and each declares exactly the
/// bindings its upload's bind group has (the instances only for two levels, the escape
/// links only for the walks that read them) and composes one walk.
#[test]
fn every_library_shape_has_the_same_calls_and_its_upload_bindings() {
    let user = "\n@group(0) @binding(0) var<storage, read_write> out: array<u32>;\n\
        @compute @workgroup_size(64) fn main(@builtin(local_invocation_index) lane: u32) {\n\
            let ray = BvhRay(vec3<f32>(0.0), 0.0, vec3<f32>(0.0, 0.0, 1.0), 1.0);\n\
            let c = bvh_trace_closest(ray, lane);\n\
            let s = bvh_hit_surface(ray, c.hit);\n\
            let a = bvh_trace_any(BvhRay(s.origin, 0.0, s.normal, 1.0), lane);\n\
            out[lane] = bvh_hit_user_id() + bvh_hit_instance_index() + bvh_hit_mesh_prim(c.hit) + a.hit.prim;\n\
        }";
    let walks = [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(6),
        Traversal::Wide,
    ];
    for storage in STORAGES {
        for instanced in [false, true] {
            for traversal in walks {
                let shape = LibraryShape::new(storage, instanced, traversal);
                let lib = wgsl_library(shape, 2);
                assert_eq!((lib.shape(), lib.group()), (shape, 2));
                let src = lib.source();
                assert!(!src.contains("@compute"), "{shape}: no entry point");
                let walks_in = [
                    "fn bvh_trace_full_stack",
                    "fn bvh_trace_short_stack",
                    "fn bvh_trace_wide",
                ]
                .iter()
                .filter(|w| src.contains(*w))
                .count();
                assert_eq!(walks_in, 1, "{shape}: one walk composed");
                let module = parse(&format!("{src}{user}"));
                let bindings: Vec<u32> = module
                    .global_variables
                    .iter()
                    .filter_map(|(_, g)| g.binding.as_ref())
                    .filter(|b| b.group == 2)
                    .map(|b| b.binding)
                    .collect();
                let mut want = vec![0, 1];
                if traversal.needs_escapes() {
                    want.push(2);
                }
                if instanced {
                    want.push(4);
                }
                let mut got = bindings.clone();
                got.sort();
                assert_eq!(got, want, "{shape}: bindings of group 2");
                compile_main(&module, &shape.to_string());
            }
        }
    }
}

/// The moving mesh's module (`ModuleSet::motion`): the step boxes have `MotionBox`'s
/// layout, the nodes and triangles the static layout's, the ray times are f32; its one
/// entry point validates and compiles for both queries, both bounds and several step
/// counts, with the driver's constants.
#[test]
fn the_motion_module_matches_rust_and_compiles() {
    use bvhtrace_core::motion::MotionBox;
    let src = ModuleSet::motion().compose(0);
    for (name, composed) in [
        ("bvh_motion_buffers.wgsl", true),
        ("entry_ray_times.wgsl", true),
        ("traverse_full_stack.wgsl", true),
        ("bvh_buffers.wgsl", false),
        ("bvh_buffers_triangles.wgsl", false),
        ("traverse_short_stack.wgsl", false),
    ] {
        assert_eq!(
            src.contains(&format!("// ---- {name} ----")),
            composed,
            "{name}"
        );
    }
    let module = parse(&src);
    check_structs(&module);
    check_struct(
        &module,
        "BvhMotionBox",
        size_of::<MotionBox>(),
        &[
            ("min", offset_of!(MotionBox, min)),
            ("max", offset_of!(MotionBox, max)),
        ],
    );
    for (name, ty, stride) in [
        ("bvh_step_boxes", "BvhMotionBox", size_of::<MotionBox>()),
        ("bvh_nodes", "BvhNode", size_of::<FlatNode>()),
        ("bvh_triangles", "BvhTriangle", size_of::<FlatTriangle>()),
    ] {
        let (t, s) = group0_array(&module, name);
        assert_eq!((t.as_str(), s as usize), (ty, stride), "{name}");
    }
    compile_moving(&module, "motion");
}

/// Validates a moving tree's module and compiles its one entry point for both queries,
/// both bounds and several step counts, with the driver's constants.
fn compile_moving(module: &naga::Module, what: &str) {
    let info = validate(module);
    for any in [0.0, 1.0] {
        for linear in [0.0, 1.0] {
            for steps in [2.0, 9.0, 129.0] {
                let mut c = naga::back::PipelineConstants::default();
                for (k, v) in [
                    ("BVH_ANY_HIT", any),
                    ("BVH_LINEAR_BOUNDS", linear),
                    ("BVH_TIME_STEPS", steps),
                    ("BVH_TRIP_LIMIT", 65535.0),
                ] {
                    c.insert(k.to_string(), v);
                }
                compile_entry(module, &info, "bvh_trace_full_stack_main", &c, what);
            }
        }
    }
}

/// Moving instances' module (`ModuleSet::motion_instances`): the moving tree's files with
/// `bvh_motion_instances.wgsl` in place of the static instances; the instances have
/// `MovingInstanceRecord`'s layout, the transforms three rows of 16 bytes; it compiles as
/// the moving mesh's does.
#[test]
fn the_moving_instances_module_matches_rust_and_compiles() {
    use bvhtrace_core::motion::{MotionBox, MovingInstanceRecord};
    let src = ModuleSet::motion_instances().compose(0);
    for (name, composed) in [
        ("bvh_motion_buffers.wgsl", true),
        ("bvh_motion_instances.wgsl", true),
        ("traverse_instances.wgsl", true),
        ("bvh_instances.wgsl", false),
        ("bvh_no_instances.wgsl", false),
    ] {
        let here = src.contains(&format!("// ---- {name} ----"));
        assert_eq!(here, composed, "{name}");
    }
    let module = parse(&src);
    check_structs(&module);
    check_struct(
        &module,
        "BvhMovingInstance",
        size_of::<MovingInstanceRecord>(),
        &[
            ("root", offset_of!(MovingInstanceRecord, root)),
            ("prim_base", offset_of!(MovingInstanceRecord, prim_base)),
            (
                "first_transform",
                offset_of!(MovingInstanceRecord, first_transform),
            ),
            ("transforms", offset_of!(MovingInstanceRecord, transforms)),
        ],
    );
    check_struct(
        &module,
        "BvhRows",
        size_of::<[[f32; 4]; 3]>(),
        &[("rows", 0)],
    );
    for (name, ty, stride) in [
        ("bvh_moving_instances", "BvhMovingInstance", 16),
        ("bvh_instance_transforms", "BvhRows", 48),
        ("bvh_step_boxes", "BvhMotionBox", size_of::<MotionBox>()),
        ("bvh_nodes", "BvhNode", size_of::<FlatNode>()),
        ("bvh_triangles", "BvhTriangle", size_of::<FlatTriangle>()),
    ] {
        let (t, s) = group0_array(&module, name);
        assert_eq!((t.as_str(), s as usize), (ty, stride), "{name}");
    }
    compile_moving(&module, "moving instances");
}

/// The curves' module (`ModuleSet::curves`): the segments have `CurveSegment`'s layout,
/// the points are 16 bytes, the nodes and triangles the static layout's; the leaf visit
/// tests slots; its entry point validates and compiles for both queries and every kind.
#[test]
fn the_curves_module_matches_rust_and_compiles() {
    use bvhtrace_core::CurveSegment;
    let src = ModuleSet::curves().compose(0);
    for (name, composed) in [
        ("bvh_curve_buffers.wgsl", true),
        ("curve.wgsl", true),
        ("traverse_full_stack.wgsl", true),
        ("bvh_buffers.wgsl", false),
        ("bvh_buffers_triangles.wgsl", false),
        ("entry_ray_times.wgsl", false),
    ] {
        assert_eq!(
            src.contains(&format!("// ---- {name} ----")),
            composed,
            "{name}"
        );
    }
    assert!(src.contains("let slot = bvh_test_slot(r, i, (*best).t);"));
    assert!(!src.contains("let tri = bvh_load_triangle(i);"));
    let module = parse(&src);
    check_structs(&module);
    check_struct(
        &module,
        "BvhCurveSegment",
        size_of::<CurveSegment>(),
        &[
            ("first", offset_of!(CurveSegment, first)),
            ("neighbours", offset_of!(CurveSegment, neighbours)),
        ],
    );
    for (name, ty, stride) in [
        (
            "bvh_curve_segments",
            "BvhCurveSegment",
            size_of::<CurveSegment>(),
        ),
        ("bvh_nodes", "BvhNode", size_of::<FlatNode>()),
        ("bvh_triangles", "BvhTriangle", size_of::<FlatTriangle>()),
    ] {
        let (t, s) = group0_array(&module, name);
        assert_eq!((t.as_str(), s as usize), (ty, stride), "{name}");
    }
    let info = validate(&module);
    for any in [0.0, 1.0] {
        for kind in [0.0, 1.0, 2.0, 3.0] {
            let mut c = naga::back::PipelineConstants::default();
            for (k, v) in [
                ("BVH_ANY_HIT", any),
                ("BVH_CURVE_KIND", kind),
                ("BVH_CURVE_TRIANGLES", 1280.0),
                ("BVH_TRIP_LIMIT", 65535.0),
            ] {
                c.insert(k.to_string(), v);
            }
            compile_entry(&module, &info, "bvh_trace_full_stack_main", &c, "curves");
        }
    }
}
