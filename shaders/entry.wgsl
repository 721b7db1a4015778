// entry.wgsl: what every batch entry point shares (one thread per ray).
//
// Group 0 is the BVH (`bvh_buffers.wgsl` or `bvh_textures.wgsl`), group 1 the ray batch.
// The host binds one chunk of at most a few million rays at a time, so
// `arrayLength(&hits)` is the chunk's size; the grid is 2D when a chunk needs more than
// `max_compute_workgroups_per_dimension` groups.
//
// The entry points themselves are one file each, and a specialised module composes exactly
// one of them (`bvhtrace_gpu::PipelineFeatures`):
// - `entry_full_stack.wgsl` / `entry_short_stack.wgsl`: hits only;
// - `entry_full_stack_counted.wgsl` / `entry_short_stack_counted.wgsl`: hits and counters,
//   composed with `entry_counters.wgsl` (the `counters` binding) only when counters are on.
// `bvhtrace_gpu::kernel_source` composes all four (the everything-on module).
//
// Specialisation (pipeline-overridable constants, folded by the driver's compiler):
// - `ANY_HIT`: any-hit (occlusion) query instead of closest hit;
// - `SHORT_STACK_SIZE`: the ring size `k` of the short-stack walk; 0 is the stackless walk
//   (not used by the full-stack entry points).

override ANY_HIT: bool = false;
override SHORT_STACK_SIZE: u32 = 6u;

const WORKGROUP_SIZE: u32 = 64u;

// The rays (binding 0) are read with `load_ray(i)`, declared by one of
// `entry_rays_buffer.wgsl` (a storage buffer, the default) or `entry_rays_texture.wgsl`
// (a storage texture, for CPU drivers; `bvhtrace_gpu::RayInput`). The hits binding holds
// exactly the chunk's rays, so its length is the ray count.
@group(1) @binding(1) var<storage, read_write> hits: array<Hit>;

fn ray_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * WORKGROUP_SIZE;
}
