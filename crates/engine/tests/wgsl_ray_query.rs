//! The ray-query kernels and libraries, validated by naga without a device: one mesh and
//! two levels, with the bindings the wgpu backend binds.

use bvhtrace_engine::pages::Pages;
use bvhtrace_engine::ray_query::{ENTRY_POINT, kernel_source};
use bvhtrace_engine::{LibraryShape, wgsl_library};

fn validate(source: &str) -> naga::Module {
    let module = naga::front::wgsl::parse_str(source)
        .unwrap_or_else(|e| panic!("parse: {}", e.emit_to_string(source)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("validate: {}", e.emit_to_string(source)));
    module
}

/// `(group, binding, name)` of every global with a binding.
fn bindings(module: &naga::Module) -> Vec<(u32, u32, String)> {
    let mut out: Vec<_> = module
        .global_variables
        .iter()
        .filter_map(|(_, g)| {
            let b = g.binding.as_ref()?;
            Some((b.group, b.binding, g.name.clone().unwrap_or_default()))
        })
        .collect();
    out.sort();
    out
}

#[test]
fn the_kernel_binds_the_tlas_triangles_and_for_two_levels_meshes_and_instances() {
    for instanced in [false, true] {
        let source = kernel_source(instanced, false, Pages::ONE);
        assert!(source.starts_with("enable wgpu_ray_query;"), "{source:.80}");
        let module = validate(&source);
        assert!(
            module.entry_points.iter().any(|e| e.name == ENTRY_POINT),
            "no {ENTRY_POINT}"
        );
        let names: Vec<(u32, u32)> = bindings(&module).iter().map(|b| (b.0, b.1)).collect();
        let want: &[(u32, u32)] = if instanced {
            &[(0, 0), (0, 1), (0, 2), (0, 4), (1, 0), (1, 1)]
        } else {
            &[(0, 0), (0, 1), (1, 0), (1, 1)]
        };
        assert_eq!(names, want, "instanced {instanced}");
        let tlas = module
            .global_variables
            .iter()
            .find(|(_, g)| g.name.as_deref() == Some("bvh_tlas"))
            .expect("the TLAS binding");
        assert!(
            matches!(
                module.types[tlas.1.ty].inner,
                naga::TypeInner::AccelerationStructure { .. }
            ),
            "binding 0 is an acceleration structure"
        );
    }
}

#[test]
fn the_library_offers_the_walks_calls_over_ray_queries_in_any_group() {
    let user = r#"
@group(1) @binding(0) var<storage, read_write> out: array<vec4<f32>>;
@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let ray = BvhRay(vec3<f32>(f32(gid.x), 0.0, 5.0), 0.0, vec3<f32>(0.0, 0.0, -1.0), 1e30);
    let c = bvh_trace_closest(ray, lane);
    var s = BvhSurface(vec3<f32>(0.0), vec3<f32>(0.0));
    if (c.hit.prim < BVH_INVALID_RAY) {
        s = bvh_hit_surface(ray, c.hit);
    }
    let a = bvh_trace_any(BvhRay(s.origin, 0.0, s.normal, 1e30), lane);
    out[gid.x] = vec4<f32>(c.hit.t, f32(bvh_hit_user_id()), f32(bvh_hit_mesh_prim(c.hit)), a.hit.t);
}
"#;
    for instanced in [false, true] {
        let library = wgsl_library(LibraryShape::ray_queries(instanced), 2);
        assert!(library.shape().ray_queries);
        let module = validate(&format!("{library}\n{user}"));
        let groups: Vec<u32> = bindings(&module).iter().map(|b| b.0).collect();
        assert!(
            groups.iter().filter(|&&g| g == 2).count() >= 2,
            "the BVH bindings moved to group 2: {groups:?}"
        );
        assert_eq!(
            library.shape().to_string(),
            if instanced {
                "two levels, the device's ray queries"
            } else {
                "one mesh, the device's ray queries"
            }
        );
    }
}

#[test]
fn a_masked_kernel_binds_the_masks_at_5_and_confirms_candidates_by_the_walks_test() {
    for instanced in [false, true] {
        let source = kernel_source(instanced, true, Pages::ONE);
        let module = validate(&source);
        let names: Vec<(u32, u32)> = bindings(&module).iter().map(|b| (b.0, b.1)).collect();
        let want: &[(u32, u32)] = if instanced {
            &[(0, 0), (0, 1), (0, 2), (0, 4), (0, 5), (1, 0), (1, 1)]
        } else {
            &[(0, 0), (0, 1), (0, 5), (1, 0), (1, 1)]
        };
        assert_eq!(names, want, "instanced {instanced}");
        // The walks' file, composed once, not a copy; the candidates go to its test.
        assert_eq!(source.matches("fn bvh_alpha_accept(").count(), 1);
        assert!(source.contains("// ---- bvh_alpha_masks.wgsl ----"));
        assert!(source.contains("rayQueryConfirmIntersection(&rq)"));
        assert!(source.contains("const BVH_RAY_QUERY_OPAQUE: bool = false;"));
        let plain = kernel_source(instanced, false, Pages::ONE);
        assert!(
            !plain.contains("bvh_alpha") && !plain.contains("bvh_masks"),
            "an unmasked kernel composes nothing of the masks"
        );
        assert!(plain.contains("const BVH_RAY_QUERY_OPAQUE: bool = true;"));
    }
}

#[test]
fn a_masked_library_over_ray_queries_moves_the_masks_binding_with_the_group() {
    let user = r#"
@group(0) @binding(0) var<storage, read_write> out: array<u32>;
@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let ray = BvhRay(vec3<f32>(f32(gid.x), 0.0, 5.0), 0.0, vec3<f32>(0.0, 0.0, -1.0), 1e30);
    out[gid.x] = bvh_trace_closest(ray, lane).hit.prim + bvh_trace_any(ray, lane).hit.prim;
}
"#;
    for instanced in [false, true] {
        let shape = LibraryShape {
            masks: true,
            ..LibraryShape::ray_queries(instanced)
        };
        let library = wgsl_library(shape, 3);
        let module = validate(&format!("{library}\n{user}"));
        assert!(
            bindings(&module)
                .iter()
                .any(|b| (b.0, b.1, b.2.as_str()) == (3, 5, "bvh_masks")),
            "{:?}",
            bindings(&module)
        );
    }
}

/// Triangles split over three bindings: the kernel declares pages 1 and 2 of them at
/// bindings 9 and 17 (and nothing else more), reads them through the page function, and
/// validates; the library for such an upload declares the same.
#[test]
fn split_triangles_are_bound_a_page_each() {
    let pages = Pages {
        log2_bytes: 20,
        triangles: 3,
        ..Pages::ONE
    };
    for instanced in [false, true] {
        let whole = bindings(&validate(&kernel_source(instanced, false, Pages::ONE)));
        let source = kernel_source(instanced, false, pages);
        assert!(source.contains("fn bvh_triangles_at("), "no page function");
        let split = bindings(&validate(&source));
        let extra: Vec<_> = split.iter().filter(|b| !whole.contains(b)).collect();
        let want = [(0, 9, "bvh_triangles_1"), (0, 17, "bvh_triangles_2")];
        assert_eq!(extra.len(), 2, "{extra:?}");
        for ((g, b, n), (wg, wb, wn)) in extra.iter().map(|x| (x.0, x.1, &x.2)).zip(want) {
            assert_eq!((g, b, n.as_str()), (wg, wb, wn));
        }
        let shape = LibraryShape {
            pages,
            ..LibraryShape::ray_queries(instanced)
        };
        let library = wgsl_library(shape, 0);
        assert!(library.source().contains("bvh_triangles_2"));
    }
}
