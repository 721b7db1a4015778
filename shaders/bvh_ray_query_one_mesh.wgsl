// bvh_ray_query_one_mesh.wgsl: one mesh, whose BLAS starts at triangle slot 0
// (`bvh_ray_query_meshes.wgsl`'s name, without a binding).

fn bvh_mesh_first(mesh: u32) -> u32 {
    return 0u;
}
