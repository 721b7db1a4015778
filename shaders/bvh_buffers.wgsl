// bvh_buffers.wgsl: the uploaded BVH as storage buffers (`BvhStorage::Buffers`), in the
// exact byte layout of `bvhtrace_core::flat` (see `types.wgsl`), and the fetch functions
// the traversals call. `bvh_textures.wgsl` defines the same functions over textures; the
// host composes one or the other.
//
// The group number is written `@group(0)` here; `bvhtrace_gpu::wgsl_library` rewrites it
// for shaders that keep group 0 for themselves. `bvh_parents` is only read by the
// stackless and short-stack walks, so a shader that calls only `trace_full_stack` need
// not bind it.

@group(0) @binding(0) var<storage, read> bvh_nodes: array<Node>;
@group(0) @binding(1) var<storage, read> bvh_triangles: array<Triangle>;
@group(0) @binding(2) var<storage, read> bvh_parents: array<u32>;

fn load_node(i: u32) -> Node {
    return bvh_nodes[i];
}

// `vec2(right_or_first, meta_bits)` of node `i`: all a walk needs to move on.
fn load_node_links(i: u32) -> vec2<u32> {
    return vec2<u32>(bvh_nodes[i].right_or_first, bvh_nodes[i].meta_bits);
}

fn load_triangle(i: u32) -> Triangle {
    return bvh_triangles[i];
}

fn load_parent(i: u32) -> u32 {
    return bvh_parents[i];
}
