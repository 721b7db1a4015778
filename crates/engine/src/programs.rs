//! The WGSL of the builders that run on the device, each composed after the shared types
//! and `build_morton.wgsl` (bounds, Morton codes and a radix sort):
//! `build_lbvh.wgsl` (a linear BVH, Karras 2012) and `build_ploc.wgsl` (locally-ordered
//! clustering, Meister and Bittner 2018); and the programs that move a built tree's
//! vertices, `refit.wgsl` (corners and boxes refitted), `morph.wgsl` (morph targets) and
//! `skin.wgsl` (linear blend skinning). The builders' host side is [`crate::builder`],
//! which both device backends run (`GpuContext::build_bvh` in bvhtrace-gpu,
//! `VkContext::build_bvh` in bvhtrace-vk); the wgpu backend also runs the others
//! (`GpuRefit`, `GpuMorph`, `GpuSkin`). Each entry point's bindings are listed here and
//! checked against the WGSL by naga, so a host binds exactly what each step reads.

use crate::shaders::{self, Wgsl};

/// The skinning step (`skin.wgsl`) and its bindings.
pub const SKIN_STEP: Step = ("skin_vertices", &[0, 1, 2, 3, 4, 5]);

/// The uniform block of the skinning dispatch (`SkinParams` in `skin.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct SkinParams {
    /// Vertices.
    pub vertices: u32,
    /// Joints.
    pub joints: u32,
    /// Invocations per row of the dispatch grid.
    pub row: u32,
    /// Padding to 16 bytes.
    pub pad: u32,
}

/// The skinning module: `skin.wgsl` alone.
pub fn skin_source() -> String {
    shaders::SKIN.1.to_string()
}

/// The morph step (`morph.wgsl`) and its bindings.
pub const MORPH_STEP: Step = ("morph_vertices", &[0, 1, 2, 3, 4]);

/// The uniform block of the morph dispatch (`MorphParams` in `morph.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct MorphParams {
    /// Vertices.
    pub vertices: u32,
    /// Morph targets.
    pub targets: u32,
    /// Invocations per row of the dispatch grid.
    pub row: u32,
    /// Padding to 16 bytes.
    pub pad: u32,
}

/// The morph module: `morph.wgsl` alone.
pub fn morph_source() -> String {
    shaders::MORPH.1.to_string()
}

/// A builder step: its entry point and the bindings of group 0 it uses.
pub type Step = (&'static str, &'static [u32]);

/// The Morton-order steps every device builder starts with, in the order they run (the
/// radix sort's three four times, one 8-bit digit a pass).
pub const MORTON_STEPS: [Step; 5] = [
    ("morton_bounds", &[0, 1, 2]),
    ("morton_codes", &[0, 1, 2, 3, 4]),
    ("morton_radix_count", &[0, 3, 7]),
    ("morton_radix_scan", &[0, 7]),
    ("morton_radix_scatter", &[0, 3, 4, 5, 6, 7]),
];

/// The linear BVH's steps after the sort, in the order they run.
pub const LBVH_STEPS: [Step; 3] = [
    ("lbvh_hierarchy", &[0, 3, 8]),
    ("lbvh_boxes", &[0, 1, 4, 8, 9, 10]),
    ("lbvh_flatten", &[0, 1, 4, 8, 9, 11, 12, 13]),
];

/// The clustering builder's steps after the sort: `ploc_leaves`, then one iteration
/// (prepare to compact, repeated until one cluster is left), then `ploc_flatten`.
pub const PLOC_STEPS: [Step; 8] = [
    ("ploc_leaves", &[0, 1, 4, 8, 11, 15, 16, 17]),
    ("ploc_prepare", &[9, 10]),
    ("ploc_neighbours", &[8, 9, 11, 13, 15]),
    ("ploc_merge", &[8, 9, 11, 12, 13, 15, 16, 17]),
    ("ploc_block_sums", &[9, 12, 14]),
    ("ploc_scan", &[9, 14]),
    ("ploc_compact", &[9, 11, 12, 14]),
    ("ploc_flatten", &[0, 1, 4, 9, 15, 16, 17, 18, 19]),
];

/// The uniform block of the device refit's dispatches (`RefitParams` in `refit.wgsl`), one
/// per dispatch at 256-byte offsets.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RefitParams {
    /// `refit_boxes`: this dispatch's nodes are `order[first .. first + count]`.
    pub first: u32,
    /// Nodes (or triangles) this dispatch covers.
    pub count: u32,
    /// Invocations per row of the dispatch grid.
    pub row: u32,
    /// Floats from one vertex to the next in the positions (3 or more).
    pub stride: u32,
    /// Vertices in the positions.
    pub vertices: u32,
    /// Input triangles (and leaf slots).
    pub triangles: u32,
    /// 1 when corners are read through the index buffer.
    pub indexed: u32,
    /// Padding to 32 bytes.
    pub pad: u32,
}

/// The device refit's steps (`refit.wgsl`), in the order they run: the check, the
/// corners, the boxes once per level, and for a BVH in textures the nodes as texels.
pub const REFIT_STEPS: [Step; 4] = [
    ("refit_check", &[0, 4, 5, 6]),
    ("refit_corners", &[0, 2, 4, 5, 6]),
    ("refit_boxes", &[0, 1, 2, 3, 6]),
    ("refit_node_texels_step", &[0, 1, 7]),
];

/// The most storage buffers any builder step binds: a device needs this many per stage.
pub const BUILD_STORAGE_BUFFERS: u32 = 8;

/// `types.wgsl`, `build_morton.wgsl`, then `builder`'s file.
fn compose((builder, source): Wgsl) -> String {
    let (types, morton) = (shaders::TYPES.1, shaders::BUILD_MORTON.1);
    format!("{types}\n// ---- build_morton.wgsl ----\n{morton}\n// ---- {builder} ----\n{source}")
}

/// The linear BVH builder's module: `types.wgsl` (`BvhNode`, `BvhTriangle`),
/// `build_morton.wgsl`, then `build_lbvh.wgsl`.
pub fn lbvh_source() -> String {
    compose(shaders::BUILD_LBVH)
}

/// The clustering builder's module: `types.wgsl`, `build_morton.wgsl`, then
/// `build_ploc.wgsl`.
pub fn ploc_source() -> String {
    compose(shaders::BUILD_PLOC)
}

/// The device refit's module: `types.wgsl` (`BvhNode`, `BvhTriangle`), then
/// `refit.wgsl`.
pub fn refit_source() -> String {
    let (types, refit) = (shaders::TYPES.1, shaders::REFIT.1);
    format!("{types}\n// ---- refit.wgsl ----\n{refit}")
}

/// [`refit_source`] for a tree split as `pages` says: the nodes (binding 1) and triangles
/// (binding 2) it writes in place read and written page by page; page `p` of binding `b`
/// at `b + PAGE_BINDING_STRIDE * p` ([`REFIT_STEPS`] lists the first pages only).
pub fn refit_source_for(pages: crate::pages::Pages) -> String {
    let s = refit_source();
    let s = pages.specialise_read_write(&s, (1, "refit_nodes", "BvhNode"), 32, pages.nodes);
    pages.specialise_read_write(
        &s,
        (2, "refit_triangles", "BvhTriangle"),
        48,
        pages.triangles,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    fn validated(source: &str) -> (naga::Module, naga::valid::ModuleInfo) {
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)));
        let info = naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::all(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)));
        (module, info)
    }

    /// Each step's listed bindings are exactly those its entry point uses, and no step
    /// binds more storage buffers than [`BUILD_STORAGE_BUFFERS`].
    fn check_steps(source: &str, steps: &[Step]) {
        let (module, info) = validated(source);
        for (entry, bindings) in steps {
            let (index, _) = module
                .entry_points
                .iter()
                .enumerate()
                .find(|(_, p)| p.name == *entry)
                .unwrap_or_else(|| panic!("no entry point {entry}"));
            let used = info.get_entry_point(index);
            let mut got = BTreeSet::new();
            let mut storage = 0;
            for (handle, var) in module.global_variables.iter() {
                if used[handle].is_empty() {
                    continue;
                }
                if let Some(b) = &var.binding {
                    got.insert(b.binding);
                    storage += u32::from(matches!(var.space, naga::AddressSpace::Storage { .. }));
                }
            }
            let want: BTreeSet<u32> = bindings.iter().copied().collect();
            assert_eq!(got, want, "{entry}'s bindings");
            assert!(
                storage <= BUILD_STORAGE_BUFFERS,
                "{entry}: {storage} storage buffers"
            );
        }
    }

    #[test]
    fn the_lbvh_module_validates_and_lists_each_steps_bindings() {
        let source = lbvh_source();
        check_steps(&source, &MORTON_STEPS);
        check_steps(&source, &LBVH_STEPS);
    }

    #[test]
    fn the_ploc_module_validates_and_lists_each_steps_bindings() {
        let source = ploc_source();
        check_steps(&source, &MORTON_STEPS);
        check_steps(&source, &PLOC_STEPS);
    }

    #[test]
    fn the_skin_module_validates_and_lists_its_bindings() {
        check_steps(&skin_source(), &[SKIN_STEP]);
    }

    #[test]
    fn the_morph_module_validates_and_lists_its_bindings() {
        check_steps(&morph_source(), &[MORPH_STEP]);
    }

    #[test]
    fn the_refit_module_validates_and_lists_each_steps_bindings() {
        check_steps(&refit_source(), &REFIT_STEPS);
    }

    /// Split into pages, the refit module validates, and the steps that write the tree
    /// bind its further pages as well.
    #[test]
    fn the_refit_module_split_into_pages_validates() {
        use crate::pages::{PAGE_BINDING_STRIDE, Pages};
        let pages = Pages {
            log2_bytes: 20,
            nodes: 3,
            triangles: 2,
            escapes: 1,
        };
        let source = refit_source_for(pages);
        assert!(source.contains("fn refit_nodes_put(") && source.contains("refit_triangles_1"));
        let (module, info) = validated(&source);
        let bound = |entry: &str| -> BTreeSet<u32> {
            let i = module
                .entry_points
                .iter()
                .position(|e| e.name == entry)
                .unwrap();
            let f = info.get_entry_point(i);
            module
                .global_variables
                .iter()
                .filter(|(h, _)| !f[*h].is_empty())
                .filter_map(|(_, v)| v.binding.as_ref().map(|b| b.binding))
                .collect()
        };
        let (s1, s2) = (PAGE_BINDING_STRIDE, 2 * PAGE_BINDING_STRIDE);
        assert!(bound("refit_boxes").is_superset(&[1, 1 + s1, 1 + s2, 2, 2 + s1].into()));
        assert!(bound("refit_corners").is_superset(&[2, 2 + s1].into()));
        assert_eq!(refit_source_for(Pages::ONE), refit_source());
    }
}
