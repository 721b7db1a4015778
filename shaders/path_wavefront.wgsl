// path_wavefront.wgsl: the path tracer as waves (composed after path_trace.wgsl). Instead
// of one invocation following its path to the end (`path_main`), each wave takes every
// live path one vertex further (`path_wave_extend`), keeps the paths between waves in
// `path_states` and queues the ones that go on, so that a wave's invocations all have a
// path to follow. The same `path_vertex` runs in the same order on each path: the sums
// equal the single kernel's bit for bit.
//
// Per sample and run of `path_wave.pixels` pixels from `path_wave.first`: `path_wave_start`
// makes the camera paths, then per bounce `path_wave_extend` (dispatched indirectly, one
// invocation per queued path) and `path_wave_prepare` (path_wave_prepare.wgsl: the next
// wave's size), then `path_wave_finish` adds the radiance to the sums.

// `bvhtrace_path::device::WaveParams`.
struct PathWave {
    first: u32,
    pixels: u32,
    capacity: u32,
    pad: u32,
}

@group(2) @binding(0) var<uniform> path_wave: PathWave;
@group(2) @binding(1) var<storage, read_write> path_states: array<PathState>;
// Two queues of `path_wave.capacity` path indices: the wave's, and the next one's.
@group(2) @binding(2) var<storage, read_write> path_queues: array<u32>;
// The paths in the wave's queue, those queued for the next wave, and which half of
// `path_queues` is the wave's.
@group(2) @binding(3) var<storage, read_write> path_wave_ctl: array<atomic<u32>, 4>;

@compute @workgroup_size(64)
fn path_wave_start(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = id.x;
    if (j >= path_wave.pixels) {
        return;
    }
    let pixel = path_wave.first + j;
    path_states[j] = path_camera(pixel % path_params.width, pixel / path_params.width);
    path_queues[j] = j;
}

// 64 invocations: the walks' stacks are laid out for at most 64 lanes a workgroup.
@compute @workgroup_size(64)
fn path_wave_extend(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let half = atomicLoad(&path_wave_ctl[2]);
    if (id.x >= atomicLoad(&path_wave_ctl[0])) {
        return;
    }
    let j = path_queues[half * path_wave.capacity + id.x];
    var st = path_states[j];
    path_rays = 0u;
    let more = path_vertex(&st, lane);
    path_states[j] = st;
    atomicAdd(&path_stats[2], path_rays);
    if (more) {
        let slot = atomicAdd(&path_wave_ctl[1], 1u);
        path_queues[(half ^ 1u) * path_wave.capacity + slot] = j;
    }
}

@compute @workgroup_size(64)
fn path_wave_finish(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= path_wave.pixels) {
        return;
    }
    path_accumulate(path_wave.first + id.x, path_states[id.x].radiance);
}
