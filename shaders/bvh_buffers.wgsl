// bvh_buffers.wgsl: the uploaded BVH's nodes as a storage buffer (`BvhStorage::Buffers`),
// in the exact byte layout of `bvhtrace_core::flat` (see `types.wgsl`), and the fetch
// functions the binary walks call. `bvh_textures.wgsl` defines the same functions over
// textures; the host composes one or the other. The triangles are
// `bvh_buffers_triangles.wgsl`, composed after this file (and after the wide layout's
// `bvh_buffers_wide.wgsl`, which reads the same triangle binding).
//
// The group number is written `@group(0)` here; `bvhtrace_gpu::wgsl_library` rewrites it
// for shaders that keep group 0 for themselves. The escape links (binding 2, read only by
// the stackless and short-stack walks) are `bvh_buffers_escapes.wgsl`, composed in only
// when the traversal reads them.

// The binary layout (`bvh_instances.wgsl` counts its top-level nodes by it).
const BVH_WIDE_LAYOUT: bool = false;

@group(0) @binding(0) var<storage, read> bvh_nodes: array<BvhNode>;

fn bvh_load_node(i: u32) -> BvhNode {
    return bvh_nodes[i];
}

// `vec2(right_or_first, meta_bits)` of node `i`: all a walk needs to move on.
fn bvh_load_node_links(i: u32) -> vec2<u32> {
    return vec2<u32>(bvh_nodes[i].right_or_first, bvh_nodes[i].meta_bits);
}
