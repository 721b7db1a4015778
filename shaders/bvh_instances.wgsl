// bvh_instances.wgsl: the instances of a two-level BVH (`FlatBvh::instances`, binding 4),
// composed after the BVH bindings only for a BVH that has them. `bvh_no_instances.wgsl`
// defines the same names for one mesh, where the walks' instance code folds away.

const BVH_INSTANCED: bool = true;

@group(0) @binding(4) var<storage, read> bvh_instances: array<BvhInstance>;

fn bvh_load_instance(i: u32) -> BvhInstance {
    return bvh_instances[i];
}

fn bvh_instance_count() -> u32 {
    return arrayLength(&bvh_instances);
}

// The nodes before this index are the top level's. The binary top level has `2n - 1`
// nodes for `n` instances (one instance per leaf). The wide one has no fixed count, but
// `WideBvh::collapse` lays the meshes out right after it, the first instance's mesh first,
// so its root is the first node past the top level (the uploads check it).
fn bvh_top_nodes() -> u32 {
    if (BVH_WIDE_LAYOUT) {
        return bvh_instances[0].root;
    }
    return 2u * arrayLength(&bvh_instances) - 1u;
}
