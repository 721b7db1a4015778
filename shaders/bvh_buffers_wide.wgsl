// bvh_buffers_wide.wgsl: the wide layout's nodes (`bvhtrace_core::wide`, `WideBvh::nodes`,
// 80-byte `BvhWideNode`s) as a storage buffer at binding 0, where the binary layouts keep
// theirs, and their fetch functions. Composed for `Traversal::Wide` with
// `BvhStorage::Buffers` in place of `bvh_buffers.wgsl`, followed by
// `bvh_buffers_triangles.wgsl` (the wide tree's triangles, in its leaf order) and the
// instances file (its instances, in its top level's order). `bvh_textures_wide.wgsl`
// defines the same functions over textures.

// The wide layout (`bvh_instances.wgsl` counts its top-level nodes by it).
const BVH_WIDE_LAYOUT: bool = true;

@group(0) @binding(0) var<storage, read> bvh_wide_nodes: array<BvhWideNode>;

fn bvh_load_wide_node(i: u32) -> BvhWideNode {
    return bvh_wide_nodes[i];
}

// What the walk reads of node `i` when it goes back to a group it pushed: where its
// children are (`traverse_wide.wgsl`), not their boxes.
fn bvh_load_wide_links(i: u32) -> BvhWideLinks {
    return BvhWideLinks(
        bvh_wide_nodes[i].exponents >> 24u,
        bvh_wide_nodes[i].child_base,
        bvh_wide_nodes[i].triangle_base,
        bvh_wide_nodes[i].counts,
    );
}
