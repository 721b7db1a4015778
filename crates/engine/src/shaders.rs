//! Every WGSL file of the repository's `shaders/` folder, each included once, here: the
//! rest of the crate composes them by these names. A file is `(name, source)`; the name
//! labels it in a composed module.
//!
//! How the kernels are composed from them is in [`crate::compose`]; the walks' own files
//! are named by the table of walks ([`crate::walks::WALKS`]).

/// One WGSL file: its name in `shaders/` and its text.
pub type Wgsl = (&'static str, &'static str);

/// Declares each file's constant from its name in `shaders/`, and [`ALL`].
macro_rules! wgsl_files {
    ($($(#[$doc:meta])* $name:ident = $file:literal,)*) => {
        $(
            $(#[$doc])*
            pub const $name: Wgsl = ($file, include_str!(concat!("../shaders/", $file)));
        )*
        /// Every file above: a test checks that nothing in `shaders/` is left out.
        pub const ALL: &[Wgsl] = &[$($name),*];
    };
}

wgsl_files! {
    /// `BvhNode`, `BvhWideNode`, `BvhTriangle`, `BvhRay`, `BvhHit`, `BvhCounters`,
    /// `BvhTraceResult`: the Rust types of `bvhtrace_core`, field for field.
    TYPES = "types.wgsl",
    /// Ray validity, `bvh_safe_inverse`, `bvh_prepare_ray`, `bvh_octant`.
    RAY = "ray.wgsl",
    /// `bvh_offset_ray_origin`, for secondary rays.
    SURFACE = "surface.wgsl",
    /// `bvh_texel_index`: the nearest texel along an axis, for the masks and your textures.
    TEXEL = "texel.wgsl",
    /// The conservative slab test.
    BOX = "box.wgsl",
    /// `BvhTriHit`, what every triangle test returns.
    TRIANGLE_HIT = "triangle_hit.wgsl",
    /// The watertight f32 triangle test (the default precision).
    TRIANGLE = "triangle.wgsl",
    /// Möller–Trumbore in f32.
    TRIANGLE_MOLLER_TRUMBORE = "triangle_moller_trumbore.wgsl",
    /// The watertight test in f64 (`SHADER_F64`).
    TRIANGLE_F64 = "triangle_f64.wgsl",
    /// The hit rule and the leaf visit every walk shares.
    TRAVERSE_COMMON = "traverse_common.wgsl",
    /// Entering and leaving the instances of a two-level tree.
    TRAVERSE_INSTANCES = "traverse_instances.wgsl",
    /// The per-lane stacks in workgroup memory.
    TRAVERSE_STACK = "traverse_stack.wgsl",
    /// `bvh_trace_full_stack`.
    TRAVERSE_FULL_STACK = "traverse_full_stack.wgsl",
    /// `bvh_trace_short_stack` (the stackless walk with `k = 0`).
    TRAVERSE_SHORT_STACK = "traverse_short_stack.wgsl",
    /// `bvh_trace_wide`.
    TRAVERSE_WIDE = "traverse_wide.wgsl",
    /// The binary layout's nodes in a storage buffer.
    BVH_BUFFERS = "bvh_buffers.wgsl",
    /// The binary layout's nodes in a texel texture.
    BVH_TEXTURES = "bvh_textures.wgsl",
    /// A moving mesh's tree in storage buffers, its boxes and triangles at the ray's time.
    BVH_MOTION_BUFFERS = "bvh_motion_buffers.wgsl",
    /// A tree over triangles and curve segments in storage buffers, and its leaf test.
    BVH_CURVE_BUFFERS = "bvh_curve_buffers.wgsl",
    /// A ray against one curve segment: round and flat linear, round cubic.
    CURVE = "curve.wgsl",
    /// The wide layout's nodes in a storage buffer.
    BVH_BUFFERS_WIDE = "bvh_buffers_wide.wgsl",
    /// The wide layout's nodes in a texel texture, five texels each.
    BVH_TEXTURES_WIDE = "bvh_textures_wide.wgsl",
    /// The triangles (either layout) in a storage buffer.
    BVH_BUFFERS_TRIANGLES = "bvh_buffers_triangles.wgsl",
    /// The triangles in a texel texture, and the texel addressing every texture uses.
    BVH_TEXTURES_TRIANGLES = "bvh_textures_triangles.wgsl",
    /// The escape links in a storage buffer.
    BVH_BUFFERS_ESCAPES = "bvh_buffers_escapes.wgsl",
    /// The escape links in a texel texture.
    BVH_TEXTURES_ESCAPES = "bvh_textures_escapes.wgsl",
    /// The instances of a two-level tree (binding 4).
    BVH_INSTANCES = "bvh_instances.wgsl",
    /// The same names for one mesh, folded away.
    BVH_NO_INSTANCES = "bvh_no_instances.wgsl",
    /// Moving instances (bindings 4 and 7): each one's transform at the ray's time, inverted.
    BVH_MOTION_INSTANCES = "bvh_motion_instances.wgsl",
    /// The alpha masks (binding 5) and `bvh_alpha_accept`.
    BVH_ALPHA_MASKS = "bvh_alpha_masks.wgsl",
    /// `BvhCandidate`, what a library's hit filter is asked about.
    CANDIDATE = "candidate.wgsl",
    /// Per-vertex normals, for a job that shades with them.
    ATTRIBUTE_NORMALS = "attribute_normals.wgsl",
    /// What every entry point shares: the override constants, `bvh_ray_index`.
    ENTRY = "entry.wgsl",
    /// The batch's rays and hits in storage buffers.
    ENTRY_RAYS_BUFFER = "entry_rays_buffer.wgsl",
    /// The batch's rays and hits in storage textures.
    ENTRY_RAYS_TEXTURE = "entry_rays_texture.wgsl",
    /// The `counters` binding, for counted entry points.
    ENTRY_COUNTERS = "entry_counters.wgsl",
    /// Each ray's time, for a moving mesh's tree.
    ENTRY_RAY_TIMES = "entry_ray_times.wgsl",
    /// Every entry point, specialised per walk and output.
    ENTRY_WALK = "entry_walk.wgsl",
    /// `bvh_trace_closest`, `bvh_trace_any` and the hit helpers of a user's library.
    LIBRARY = "library.wgsl",
    /// The TLAS binding and `bvh_trace_ray_query(ray, any_hit)`.
    BVH_RAY_QUERY = "bvh_ray_query.wgsl",
    /// Each mesh's first triangle slot, for ray queries over two levels.
    BVH_RAY_QUERY_MESHES = "bvh_ray_query_meshes.wgsl",
    /// The same name for one mesh.
    BVH_RAY_QUERY_ONE_MESH = "bvh_ray_query_one_mesh.wgsl",
    /// Ray-query candidates put to the alpha masks' test.
    BVH_RAY_QUERY_MASKS = "bvh_ray_query_masks.wgsl",
    /// The same names for a tree without masks (every triangle opaque).
    BVH_RAY_QUERY_NO_MASKS = "bvh_ray_query_no_masks.wgsl",
    /// Bounds, Morton codes and the radix sort every device builder starts with.
    BUILD_MORTON = "build_morton.wgsl",
    /// The linear BVH builder (Karras 2012).
    BUILD_LBVH = "build_lbvh.wgsl",
    /// The clustering builder (PLOC, Meister and Bittner 2018).
    BUILD_PLOC = "build_ploc.wgsl",
    /// The refit of a built tree's corners and boxes.
    REFIT = "refit.wgsl",
    /// Morph targets.
    MORPH = "morph.wgsl",
    /// Linear blend skinning.
    SKIN = "skin.wgsl",
    /// The path tracer's random numbers, frames and metallic-roughness material
    /// (bvhtrace-path), composed after a traversal library like a user's shader.
    PATH_SAMPLING = "path_sampling.wgsl",
    /// The path tracer's kernel: camera rays, next-event estimation, bounces, the
    /// progressive sum (bvhtrace-path).
    PATH_TRACE = "path_trace.wgsl",
    /// The path tracer's environment map: octahedral, looked up and sampled by
    /// luminance without a transcendental function (bvhtrace-path).
    PATH_ENVIRONMENT = "path_environment.wgsl",
    /// The path tracer as waves of one vertex per live path (bvhtrace-path's
    /// `PathKernel::Wavefront`), composed after its kernel.
    PATH_WAVEFRONT = "path_wavefront.wgsl",
    /// Between two waves: the next wave's size and indirect dispatch.
    PATH_WAVE_PREPARE = "path_wave_prepare.wgsl",
    /// The path tracer's sums tone mapped into a texture, shown without a readback.
    PATH_DISPLAY = "path_display.wgsl",
}

#[cfg(test)]
mod tests {
    /// Every file of `shaders/` is one of [`super::ALL`], once.
    #[test]
    fn every_file_of_the_folder_is_included() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
        let mut on_disk: Vec<String> = std::fs::read_dir(&dir)
            .expect("the shaders folder")
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .filter(|n| n.ends_with(".wgsl"))
            .collect();
        on_disk.sort();
        let mut listed: Vec<String> = super::ALL.iter().map(|(n, _)| n.to_string()).collect();
        listed.sort();
        assert_eq!(listed, on_disk);
    }
}
