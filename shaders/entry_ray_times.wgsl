// entry_ray_times.wgsl: each ray's time (binding 3 of the batch, one f32 in [0, 1] per ray),
// for a moving mesh's tree (`bvh_motion_buffers.wgsl`). The entry points of such a module
// load their rays with `bvh_timed_ray`, which sets the time the tree's fetch functions
// answer for before the walk starts.

@group(1) @binding(3) var<storage, read> bvh_ray_times: array<f32>;

fn bvh_timed_ray(i: u32) -> BvhRay {
    bvh_set_time(bvh_ray_times[i]);
    return bvh_load_ray(i);
}
