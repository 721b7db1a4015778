// refit.wgsl: a one-mesh BVH's corners and boxes refitted on the device after its vertices
// moved, the tree kept; twin of `bvhtrace_core::FlatBvh::refit` (`GpuRefit` in
// bvhtrace-gpu runs it). Composed after `types.wgsl`. Three steps, in one submission:
// `refit_check` (every input triangle's corners readable and finite, else the whole refit
// writes nothing), `refit_corners` (each leaf slot's corners from its input triangle), then
// `refit_boxes` once per level, leaves first, then the interior nodes deepest first: a
// node's children are refitted by an earlier dispatch, so no atomics order the work. A BVH
// in textures adds `refit_node_texels_step` (below) before the host's copies.

struct RefitParams {
    // This dispatch's nodes: `refit_order[first .. first + count]` (`refit_boxes`).
    first: u32,
    count: u32,
    // Invocations per row of the dispatch grid.
    row: u32,
    // Floats from one vertex to the next in `refit_positions` (3 or more).
    stride: u32,
    // Vertices in `refit_positions`.
    vertices: u32,
    // Input triangles (and leaf slots).
    triangles: u32,
    // 1: triangle `t`'s corners are vertices `refit_indices[3t .. 3t + 3]`; 0: `3t .. 3t + 3`.
    indexed: u32,
    pad: u32,
}

@group(0) @binding(0) var<uniform> refit_params: RefitParams;
@group(0) @binding(1) var<storage, read_write> refit_nodes: array<BvhNode>;
@group(0) @binding(2) var<storage, read_write> refit_triangles: array<BvhTriangle>;
@group(0) @binding(3) var<storage, read> refit_order: array<u32>;
@group(0) @binding(4) var<storage, read> refit_positions: array<f32>;
@group(0) @binding(5) var<storage, read> refit_indices: array<u32>;
// 0 while every triangle is good; else the largest `0xffffffff - (4t + why)` over bad
// triangles `t` (`why`: 1 a corner not finite, 2 a vertex index out of range), so the host
// learns the first bad triangle whatever the order the invocations ran in.
@group(0) @binding(6) var<storage, read_write> refit_status: atomic<u32>;

fn refit_invocation(gid: vec3<u32>) -> u32 {
    return gid.x + gid.y * refit_params.row;
}

fn refit_vertex(t: u32, k: u32) -> u32 {
    if (refit_params.indexed != 0u) {
        return refit_indices[3u * t + k];
    }
    return 3u * t + k;
}

fn refit_position(v: u32) -> vec3<f32> {
    let o = v * refit_params.stride;
    return vec3<f32>(refit_positions[o], refit_positions[o + 1u], refit_positions[o + 2u]);
}

// Finite by the bits (a compiler may assume no NaN in a comparison).
fn refit_is_finite(p: vec3<f32>) -> bool {
    let e = vec3<u32>(0x7f800000u);
    return all((bitcast<vec3<u32>>(p) & e) != e);
}

@compute @workgroup_size(256)
fn refit_check(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = refit_invocation(gid);
    if (t >= refit_params.triangles) {
        return;
    }
    var why = 0u;
    for (var k = 0u; k < 3u && why == 0u; k++) {
        let v = refit_vertex(t, k);
        if (v >= refit_params.vertices) {
            why = 2u;
        } else if (!refit_is_finite(refit_position(v))) {
            why = 1u;
        }
    }
    if (why != 0u) {
        atomicMax(&refit_status, 0xffffffffu - (4u * t + why));
    }
}

@compute @workgroup_size(256)
fn refit_corners(@builtin(global_invocation_id) gid: vec3<u32>) {
    let s = refit_invocation(gid);
    if (s >= refit_params.triangles || atomicLoad(&refit_status) != 0u) {
        return;
    }
    // Whole elements read and written: a tree split into pages reads and writes them
    // through functions (`Pages::specialise_read_write`).
    var tri = refit_triangles[s];
    tri.v0 = refit_position(refit_vertex(tri.prim, 0u));
    tri.v1 = refit_position(refit_vertex(tri.prim, 1u));
    tri.v2 = refit_position(refit_vertex(tri.prim, 2u));
    refit_triangles[s] = tri;
}

@compute @workgroup_size(256)
fn refit_boxes(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = refit_invocation(gid);
    if (k >= refit_params.count || atomicLoad(&refit_status) != 0u) {
        return;
    }
    let i = refit_order[refit_params.first + k];
    var n = refit_nodes[i];
    let count = n.meta_bits >> 2u;
    var lo: vec3<f32>;
    var hi: vec3<f32>;
    if (count != 0u) {
        let first = refit_triangles[n.right_or_first];
        lo = min(first.v0, min(first.v1, first.v2));
        hi = max(first.v0, max(first.v1, first.v2));
        for (var j = 1u; j < count; j++) {
            let tri = refit_triangles[n.right_or_first + j];
            lo = min(lo, min(tri.v0, min(tri.v1, tri.v2)));
            hi = max(hi, max(tri.v0, max(tri.v1, tri.v2)));
        }
    } else {
        let l = refit_nodes[i + 1u];
        let r = refit_nodes[n.right_or_first];
        lo = min(l.min, r.min);
        hi = max(l.max, r.max);
    }
    n.min = lo;
    n.max = hi;
    refit_nodes[i] = n;
}

// A BVH in textures (`BvhStorage::Textures`) keeps each node as two texels,
// `(min.xyz, max.x)` and `(max.yz, right_or_first, meta)` (`bvh_textures.wgsl`): this step
// writes them from `refit_nodes` for the copy over the node texture. It runs whatever the
// check found, so a refused refit copies the nodes as they were.
@group(0) @binding(7) var<storage, read_write> refit_node_texels: array<vec4<u32>>;

@compute @workgroup_size(256)
fn refit_node_texels_step(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = refit_invocation(gid);
    if (i >= refit_params.count) {
        return;
    }
    let n = refit_nodes[i];
    let lo = bitcast<vec3<u32>>(n.min);
    let hi = bitcast<vec3<u32>>(n.max);
    refit_node_texels[2u * i] = vec4<u32>(lo, hi.x);
    refit_node_texels[2u * i + 1u] = vec4<u32>(hi.y, hi.z, n.right_or_first, n.meta_bits);
}
