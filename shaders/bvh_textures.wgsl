// bvh_textures.wgsl: the binary layout's nodes as a read-only `Rgba32Uint` storage texture
// (`BvhStorage::Textures`, with the triangles and escape links in textures too), and the
// same fetch functions as `bvh_buffers.wgsl`.
//
// Why: on lavapipe (and other CPU Vulkan drivers) a storage-buffer load with a per-lane
// index is a scalar loop over the 8 lanes with a bounds check per component, while a
// texel load is one address computation and a vector gather. Storage textures rather than
// sampled ones: a sampled texel fetch goes through per-lane mip-level lookups (about 140
// instructions a fetch on lavapipe), and was 1.35-1.5x slower on the whole walk
// (crates/gpu/README.md). The values are the same bits, so the results are identical.
//
// Texel `t` of each texture is at `(t % 8192, t / 8192)` (`bvh_texel_coord`).
// * `bvh_node_texels`: two texels per node, reordered so the links share a texel:
//   `(min.x, min.y, min.z, max.x)` and `(max.y, max.z, right_or_first, meta)`.
// * `bvh_triangle_texels` and the texel addressing are `bvh_textures_triangles.wgsl`,
//   composed after this file (and after the wide layout's `bvh_textures_wide.wgsl`).
// * `bvh_escape_texels` (`R32Uint`, eight texels per node) is `bvh_textures_escapes.wgsl`,
//   composed in only when the traversal reads the escape links.

// The binary layout (`bvh_instances.wgsl` counts its top-level nodes by it).
const BVH_WIDE_LAYOUT: bool = false;

@group(0) @binding(0) var bvh_node_texels: texture_storage_2d<rgba32uint, read>;

fn bvh_load_node(i: u32) -> BvhNode {
    // 2i is even and rows are even, so both texels are on one row.
    let c = bvh_texel_coord(2u * i);
    let a = textureLoad(bvh_node_texels, c);
    let b = textureLoad(bvh_node_texels, c + vec2<u32>(1u, 0u));
    return BvhNode(bitcast<vec3<f32>>(a.xyz), b.z, bitcast<vec3<f32>>(vec3<u32>(a.w, b.xy)), b.w);
}

// `vec2(right_or_first, meta_bits)` of node `i`: one texel.
fn bvh_load_node_links(i: u32) -> vec2<u32> {
    return textureLoad(bvh_node_texels, bvh_texel_coord(2u * i + 1u)).zw;
}
