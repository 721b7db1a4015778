// entry_full_stack.wgsl: the full-stack entry point, hits only (see `entry.wgsl`).

@compute @workgroup_size(BVH_WORKGROUP_SIZE)
fn bvh_trace_full_stack_main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = bvh_ray_index(gid, groups);
    if (i >= bvh_batch_len()) {
        return;
    }
    bvh_store_hit(i, bvh_trace_full_stack(bvh_load_ray(i), BVH_ANY_HIT, lid).hit);
}
