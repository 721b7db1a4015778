// entry.wgsl: what every batch entry point shares (one thread per ray).
//
// Group 0 is the BVH (`bvh_buffers.wgsl` or `bvh_textures.wgsl`), group 1 the ray batch.
// The host binds one chunk of at most a few million rays at a time (`batch_len()`); the
// grid is 2D when a chunk needs more than `max_compute_workgroups_per_dimension` groups.
//
// The entry points are `entry_walk.wgsl`, specialised per walk (full stack, short stack,
// wide) and per output, and a specialised module composes exactly one of them
// (`bvhtrace_engine::KernelKey`):
// - `bvh_trace_{full_stack,short_stack,wide}_main`: hits only (`bvh_store_hits_only`);
// - `bvh_trace_{full_stack,short_stack,wide}_counted`: hits and counters, composed with
//   `entry_counters.wgsl` (the `counters` binding) only when counters are on.
// `bvhtrace_engine::kernel_source` composes the four of the binary walks (the
// everything-on module); the wide walk's module holds its own two.
//
// Specialisation (pipeline-overridable constants, folded by the driver's compiler):
// - `ANY_HIT`: any-hit (occlusion) query instead of closest hit;
// - `SHORT_STACK_SIZE`: the ring size `k` of the short-stack walk; 0 is the stackless walk
//   (not used by the full-stack entry points).

override BVH_ANY_HIT: bool = false;
override BVH_SHORT_STACK_SIZE: u32 = 8u;

const BVH_WORKGROUP_SIZE: u32 = 64u;

// The rays (binding 0) and the hits (binding 1) are declared by one of
// `entry_rays_buffer.wgsl` (storage buffers, the default) or `entry_rays_texture.wgsl`
// (storage textures, for CPU drivers; `bvhtrace_gpu::RayInput`), with `load_ray(i)`,
// `store_hit(i, hit)` and `batch_len()`: the rays an entry point may trace (the chunk's
// size for buffers; for textures, whole rows, past the rays the host reads back).

// Worker threads among which a CPU driver splits each dispatch, as contiguous ranges of
// workgroups in linear order (lavapipe: `LP_NUM_THREADS`, by default one per CPU); 1 on
// GPUs, which hand out workgroups as they go (`bvhtrace_gpu::dispatch_threads_for`).
override BVH_DISPATCH_THREADS: u32 = 1u;

// The batch ray of invocation `gid`: lane `l` of workgroup `w` (of `n`) traces ray
// `interleave(w, n) * WORKGROUP_SIZE + l`.
fn bvh_ray_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    let w = gid.x / BVH_WORKGROUP_SIZE + gid.y * groups.x;
    return bvh_interleave(w, groups.x * groups.y) * BVH_WORKGROUP_SIZE + gid.x % BVH_WORKGROUP_SIZE;
}

// The ray block workgroup `w` of `n` traces. With `t` threads each taking `n / t`
// consecutive workgroups, thread `k` traces blocks `k, k + t, k + 2t, ...`: every thread
// gets its share of every part of the frame (the lower half of `bunny_69k`'s frame holds
// two thirds of its work) and keeps to neighbouring blocks. The `n % t` workgroups left
// over keep their own block. A bijection on `0..n`; the identity when `t` is 1.
fn bvh_interleave(w: u32, n: u32) -> u32 {
    let t = max(BVH_DISPATCH_THREADS, 1u);
    let q = n / t;
    if (w >= q * t) {
        return w;
    }
    return (w % q) * t + w / q;
}

// What a hits-only entry point stores of its walk's answer.
fn bvh_store_hits_only(i: u32, res: BvhTraceResult) {
    bvh_store_hit(i, res.hit);
}
