// bvh_bindings.wgsl: the uploaded BVH (see `bvhtrace_core::flat`).
//
// The group number is written `@group(0)` here; `bvhtrace_gpu::wgsl_library(group)`
// rewrites it for shaders that keep group 0 for themselves. `bvh_parents` is only read by
// the stackless and short-stack walks, so a shader that calls only `trace_full_stack`
// need not bind it.

@group(0) @binding(0) var<storage, read> bvh_nodes: array<Node>;
@group(0) @binding(1) var<storage, read> bvh_triangles: array<Triangle>;
@group(0) @binding(2) var<storage, read> bvh_parents: array<u32>;

fn load_node(i: u32) -> Node {
    return bvh_nodes[i];
}
