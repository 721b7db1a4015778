// entry_walk.wgsl: the entry point of one walk, one thread per ray (see `entry.wgsl`).
// Every entry point is this file, specialised by `ModuleSet::files`
// (`bvhtrace_engine::key`), which replaces the three upper-case names below: the entry
// point's own (`KernelKey::entry_point`), what it stores (`bvh_store_hits_only`, or
// `bvh_store_counted` of `entry_counters.wgsl`: hits and counters), and the walk's call
// on ray `i` with invocation `lid`'s stack (the full stack, the short stack with
// `SHORT_STACK_SIZE`, or the wide walk). So the entry points differ only in their walk.

@compute @workgroup_size(BVH_WORKGROUP_SIZE)
fn BVH_ENTRY_POINT(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = bvh_ray_index(gid, groups);
    if (i >= bvh_batch_len()) {
        return;
    }
    BVH_STORE(i, BVH_WALK);
}
