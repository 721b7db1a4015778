// entry.wgsl: the batch compute entry points (one thread per ray).
//
// Group 0 is the BVH (`bvh_bindings.wgsl`), group 1 the ray batch. The host binds one chunk
// of at most a few million rays at a time, so `arrayLength(&rays)` is the chunk's size; the
// grid is 2D when a chunk needs more than `max_compute_workgroups_per_dimension` groups.
//
// Specialisation (pipeline-overridable constants, folded by the driver's compiler):
// - `ANY_HIT`: any-hit (occlusion) query instead of closest hit;
// - `SHORT_STACK_SIZE`: the ring size `k` of the short-stack walk; 0 is the stackless walk.
// Counters are written only by the `*_counted` entry points, which alone use binding 2.

override ANY_HIT: bool = false;
override SHORT_STACK_SIZE: u32 = 6u;

const WORKGROUP_SIZE: u32 = 64u;

@group(1) @binding(0) var<storage, read> rays: array<Ray>;
@group(1) @binding(1) var<storage, read_write> hits: array<Hit>;
@group(1) @binding(2) var<storage, read_write> counters: array<Counters>;

fn ray_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * WORKGROUP_SIZE;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn trace_full_stack_main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let i = ray_index(gid, groups);
    if (i >= arrayLength(&rays)) {
        return;
    }
    hits[i] = trace_full_stack(rays[i], ANY_HIT).hit;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn trace_full_stack_counted(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let i = ray_index(gid, groups);
    if (i >= arrayLength(&rays)) {
        return;
    }
    let res = trace_full_stack(rays[i], ANY_HIT);
    hits[i] = res.hit;
    counters[i] = res.counters;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn trace_short_stack_main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let i = ray_index(gid, groups);
    if (i >= arrayLength(&rays)) {
        return;
    }
    hits[i] = trace_short_stack(rays[i], ANY_HIT, SHORT_STACK_SIZE).hit;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn trace_short_stack_counted(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let i = ray_index(gid, groups);
    if (i >= arrayLength(&rays)) {
        return;
    }
    let res = trace_short_stack(rays[i], ANY_HIT, SHORT_STACK_SIZE);
    hits[i] = res.hit;
    counters[i] = res.counters;
}
