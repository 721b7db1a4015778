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
// The run's paths, 20 words each (a `PathState`) by their pixel's place in the run, then
// two queues of `path_wave.capacity` path indices: the wave's and the next one's. One
// array, and the control words in `path_stats`, so that the waves bind one storage buffer
// more than the single kernel (WebGPU allows 8 to 10 a stage).
@group(2) @binding(1) var<storage, read_write> path_paths: array<u32>;
// `path_stats` words: the paths in the wave's queue, those queued for the next, and
// which queue is the wave's.
const PATH_WAVE_COUNT: u32 = 4u;
const PATH_WAVE_NEXT: u32 = 5u;
const PATH_WAVE_HALF: u32 = 6u;

fn path_paths_f32(i: u32) -> f32 {
    return bitcast<f32>(path_paths[i]);
}

fn path_paths_vec3(i: u32) -> vec3<f32> {
    return vec3<f32>(path_paths_f32(i), path_paths_f32(i + 1u), path_paths_f32(i + 2u));
}

fn path_paths_set_vec3(i: u32, v: vec3<f32>, w: u32) {
    path_paths[i] = bitcast<u32>(v.x);
    path_paths[i + 1u] = bitcast<u32>(v.y);
    path_paths[i + 2u] = bitcast<u32>(v.z);
    path_paths[i + 3u] = w;
}

// Path `j`, in the order of `PathState`'s members.
fn path_wave_load(j: u32) -> PathState {
    let b = 20u * j;
    return PathState(
        path_paths_vec3(b), path_paths[b + 3u],
        path_paths_vec3(b + 4u), path_paths_f32(b + 7u),
        path_paths_vec3(b + 8u), path_paths[b + 11u],
        path_paths_vec3(b + 12u), path_paths[b + 15u],
        path_paths_vec3(b + 16u), 0u,
    );
}

fn path_wave_store(j: u32, st: PathState) {
    let b = 20u * j;
    path_paths_set_vec3(b, st.origin, st.depth);
    path_paths_set_vec3(b + 4u, st.dir, bitcast<u32>(st.last_pdf));
    path_paths_set_vec3(b + 8u, st.throughput, st.key);
    path_paths_set_vec3(b + 12u, st.last_n, st.count);
    path_paths_set_vec3(b + 16u, st.radiance, 0u);
}

// Path `j` of the run one vertex further: kept and queued if it goes on, else its
// radiance added to its pixel's sum.
fn path_wave_vertex(j: u32, path: PathState, half: u32, lane: u32) {
    var st = path;
    path_rays = 0u;
    let more = path_vertex(&st, lane);
    atomicAdd(&path_stats[2], path_rays);
    if (more) {
        path_wave_store(j, st);
        let slot = atomicAdd(&path_stats[PATH_WAVE_NEXT], 1u);
        path_paths[(20u + (half ^ 1u)) * path_wave.capacity + slot] = j;
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
    let half = atomicLoad(&path_stats[PATH_WAVE_HALF]);
    if (id.x >= atomicLoad(&path_stats[PATH_WAVE_COUNT])) {
        return;
    }
    let j = path_paths[(20u + half) * path_wave.capacity + id.x];
    path_wave_vertex(j, path_wave_load(j), half, lane);
}
