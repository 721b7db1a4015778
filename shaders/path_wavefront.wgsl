// path_wavefront.wgsl: the path tracer as waves (composed after path_trace.wgsl). Instead
// of one invocation following its path to the end (`path_main`), each wave takes every
// live path one vertex further, keeps the paths that go on in `path_states` and queues
// them for the next wave, so that a wave's invocations all have a path to follow. The
// same `path_vertex` runs in the same order on each path, and a path's radiance is added
// to its pixel's sum when it ends: the sums equal the single kernel's bit for bit.
//
// Per sample and run of `path_wave.rows` rows from `path_wave.first_row`: `path_wave_start`
// makes the camera paths and their first vertex (8 x 8 pixels a workgroup, as
// `path_main`), then per further bounce `path_wave_prepare` (path_wave_prepare.wgsl: the
// next wave's size) and `path_wave_extend` (dispatched indirectly, one invocation per
// queued path).

// `bvhtrace_path::wavefront::WaveParams`.
struct PathWave {
    first_row: u32,
    rows: u32,
    capacity: u32,
    pad: u32,
}

@group(2) @binding(0) var<uniform> path_wave: PathWave;
// The run's paths, by their pixel's place in the run.
@group(2) @binding(1) var<storage, read_write> path_states: array<PathState>;
// Two queues of `path_wave.capacity` path indices: the wave's, and the next one's.
@group(2) @binding(2) var<storage, read_write> path_queues: array<u32>;
// The paths in the wave's queue, those queued for the next, and which half of
// `path_queues` is the wave's.
@group(2) @binding(3) var<storage, read_write> path_wave_ctl: array<atomic<u32>, 4>;

// Path `j` of the run one vertex further: kept and queued if it goes on, else its
// radiance added to its pixel's sum.
fn path_wave_vertex(j: u32, path: PathState, half: u32, lane: u32) {
    var st = path;
    path_rays = 0u;
    let more = path_vertex(&st, lane);
    atomicAdd(&path_stats[2], path_rays);
    if (more) {
        path_states[j] = st;
        let slot = atomicAdd(&path_wave_ctl[1], 1u);
        path_queues[(half ^ 1u) * path_wave.capacity + slot] = j;
    } else {
        path_accumulate(path_wave.first_row * path_params.width + j, st.radiance);
    }
}

// 8 x 8 invocations: the walks' stacks are laid out for at most 64 lanes a workgroup.
@compute @workgroup_size(8, 8)
fn path_wave_start(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let p = path_params;
    if (id.x >= p.width || id.y >= path_wave.rows) {
        return;
    }
    let st = path_camera(id.x, path_wave.first_row + id.y);
    let j = id.y * p.width + id.x;
    if (p.max_depth == 0u) {
        path_accumulate(path_wave.first_row * p.width + j, st.radiance);
        return;
    }
    path_wave_vertex(j, st, 0u, lane);
}

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
    path_wave_vertex(j, path_states[j], half, lane);
}
