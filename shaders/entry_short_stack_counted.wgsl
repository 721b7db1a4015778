// entry_short_stack_counted.wgsl: the short-stack / stackless entry point writing hits and
// counters (needs `entry_counters.wgsl`).

@compute @workgroup_size(BVH_WORKGROUP_SIZE)
fn bvh_trace_short_stack_counted(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = bvh_ray_index(gid, groups);
    if (i >= bvh_batch_len()) {
        return;
    }
    bvh_store_counted(i, bvh_trace_short_stack(bvh_load_ray(i), BVH_ANY_HIT, BVH_SHORT_STACK_SIZE, lid));
}
