//! The WGSL of the builders that run on the device: `build_lbvh.wgsl` (a linear BVH,
//! Karras 2012) after the shared types. The wgpu backend runs it
//! (`GpuContext::build_lbvh` in bvhtrace-gpu).

/// `build_lbvh.wgsl`.
const BUILD_LBVH_WGSL: &str = include_str!("../shaders/build_lbvh.wgsl");

/// The entry points of [`lbvh_source`], in the order they run (the radix passes'
/// three four times).
pub const LBVH_ENTRIES: [&str; 8] = [
    "lbvh_bounds",
    "lbvh_morton",
    "lbvh_radix_count",
    "lbvh_radix_scan",
    "lbvh_radix_scatter",
    "lbvh_hierarchy",
    "lbvh_boxes",
    "lbvh_flatten",
];

/// The LBVH builder's module: `types.wgsl` (`BvhNode`, `BvhTriangle`), then
/// `build_lbvh.wgsl`.
pub fn lbvh_source() -> String {
    let types = crate::wgsl::SHADER_FILES
        .iter()
        .find(|(name, _)| *name == "types.wgsl")
        .map_or("", |(_, src)| src);
    format!("{types}\n// ---- build_lbvh.wgsl ----\n{BUILD_LBVH_WGSL}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lbvh_module_validates_with_every_entry_point() {
        let source = lbvh_source();
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(&source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::all(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{}", e.emit_to_string(&source)));
        for e in LBVH_ENTRIES {
            assert!(module.entry_points.iter().any(|p| p.name == e), "{e}");
        }
    }
}
