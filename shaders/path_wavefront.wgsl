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
// The run's paths, five vec4 words each (a `PathState`) by their pixel's place in the
// run, then two queues of `path_wave.capacity` path indices (four to a vec4): the wave's
// and the next one's. One array, and the control words in `path_stats`, so that the waves
// bind one storage buffer more than the single kernel (WebGPU allows 8 to 10 a stage).
@group(2) @binding(1) var<storage, read_write> path_paths: array<vec4<u32>>;
// `path_stats` words: the paths in the wave's queue, those queued for the next, and
// which queue is the wave's.
const PATH_WAVE_COUNT: u32 = 4u;
const PATH_WAVE_NEXT: u32 = 5u;
const PATH_WAVE_HALF: u32 = 6u;

fn path_paths_vec3(v: vec4<u32>) -> vec3<f32> {
    return vec3<f32>(bitcast<f32>(v.x), bitcast<f32>(v.y), bitcast<f32>(v.z));
}

fn path_paths_word(v: vec3<f32>, w: u32) -> vec4<u32> {
    return vec4<u32>(bitcast<u32>(v.x), bitcast<u32>(v.y), bitcast<u32>(v.z), w);
}

// Path `j`, in the order of `PathState`'s members: five vec4 words.
fn path_wave_load(j: u32) -> PathState {
    let b = 5u * j;
    let a0 = path_paths[b];
    let a1 = path_paths[b + 1u];
    let a2 = path_paths[b + 2u];
    let a3 = path_paths[b + 3u];
    let a4 = path_paths[b + 4u];
    return PathState(
        path_paths_vec3(a0), a0.w,
        path_paths_vec3(a1), bitcast<f32>(a1.w),
        path_paths_vec3(a2), a2.w,
        path_paths_vec3(a3), a3.w,
        path_paths_vec3(a4), 0u,
    );
}

fn path_wave_store(j: u32, st: PathState) {
    let b = 5u * j;
    path_paths[b] = path_paths_word(st.origin, st.depth);
    path_paths[b + 1u] = path_paths_word(st.dir, bitcast<u32>(st.last_pdf));
    path_paths[b + 2u] = path_paths_word(st.throughput, st.key);
    path_paths[b + 3u] = path_paths_word(st.last_n, st.count);
    path_paths[b + 4u] = path_paths_word(st.radiance, 0u);
}

// Entry `i` of queue `half`: the queues follow the states, four entries a vec4.
fn path_queue_entry(half: u32, i: u32) -> u32 {
    let k = (5u * 4u + half) * path_wave.capacity + i;
    return path_paths[k / 4u][k % 4u];
}

fn path_queue_set(half: u32, i: u32, j: u32) {
    let k = (5u * 4u + half) * path_wave.capacity + i;
    path_paths[k / 4u][k % 4u] = j;
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
        path_queue_set(half ^ 1u, slot, j);
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
    let j = path_queue_entry(half, id.x);
    path_wave_vertex(j, path_wave_load(j), half, lane);
}
