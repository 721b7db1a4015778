// entry_short_stack_counted.wgsl: the short-stack / stackless entry point writing hits and
// counters (needs `entry_counters.wgsl`).

@compute @workgroup_size(WORKGROUP_SIZE)
fn trace_short_stack_counted(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = ray_index(gid, groups);
    if (i >= batch_len()) {
        return;
    }
    store_counted(i, trace_short_stack(load_ray(i), ANY_HIT, SHORT_STACK_SIZE, lid));
}
