// bvh_ray_query_meshes.wgsl: the first triangle slot of each mesh of a two-level BVH
// (binding 2), indexed by a TLAS instance's custom data, for `bvh_ray_query.wgsl`.
// `bvh_ray_query_one_mesh.wgsl` answers 0 for one mesh.

@group(0) @binding(2) var<storage, read> bvh_mesh_firsts: array<u32>;

fn bvh_mesh_first(mesh: u32) -> u32 {
    return bvh_mesh_firsts[mesh];
}
