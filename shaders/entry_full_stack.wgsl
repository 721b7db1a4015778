// entry_full_stack.wgsl: the full-stack entry point, hits only (see `entry.wgsl`).

@compute @workgroup_size(WORKGROUP_SIZE)
fn trace_full_stack_main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = ray_index(gid, groups);
    if (i >= batch_len()) {
        return;
    }
    store_hit(i, trace_full_stack(load_ray(i), ANY_HIT, lid).hit);
}
