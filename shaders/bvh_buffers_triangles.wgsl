// bvh_buffers_triangles.wgsl: the triangles as a storage buffer (binding 1), 48 bytes each
// (`FlatTriangle`), in the leaf order of the layout composed before it: the binary tree's
// (`bvh_buffers.wgsl`) or the wide tree's (`bvh_buffers_wide.wgsl`, `WideBvh::triangles`).

@group(0) @binding(1) var<storage, read> bvh_triangles: array<BvhTriangle>;

fn bvh_load_triangle(i: u32) -> BvhTriangle {
    return bvh_triangles[i];
}
