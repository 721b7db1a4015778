// bvh_no_instances.wgsl: one mesh, no instances: `bvh_instances.wgsl`'s names, for a
// module whose walks never meet an instance leaf (`BVH_INSTANCED` folds their instance
// code away).

const BVH_INSTANCED: bool = false;

fn bvh_load_instance(i: u32) -> BvhInstance {
    return BvhInstance();
}

fn bvh_instance_count() -> u32 {
    return 0u;
}

fn bvh_top_nodes() -> u32 {
    return 0u;
}
