// build_morton.wgsl: triangles in Morton order on the device, the first steps of every
// device builder (`build_lbvh.wgsl`, `build_ploc.wgsl`, composed after this file and
// `types.wgsl`). The host (`bvhtrace_gpu::build`) runs the entry points in order:
//
// 1. `morton_bounds`: the centroids' bounds, as order-preserving u32 in atomics;
// 2. `morton_codes`: a 30-bit Morton code per triangle centroid, and its index;
// 3. `morton_radix_count`, `morton_radix_scan`, `morton_radix_scatter`, four times (8 bits
//    a pass): a stable radix sort of (code, index), so equal codes keep input order and the
//    same input always gives the same tree.
//
// One invocation per element; the grid is 2D past 65,535 workgroups. Bindings 0 to 7 are
// this file's; the builders' start at 8.

struct MortonParams {
    // Triangles.
    n: u32,
    // The radix pass's first bit (0, 8, 16, 24).
    shift: u32,
    // Workgroups (blocks of `MORTON_BLOCK` keys) of the radix passes.
    blocks: u32,
    // Invocations per row of the 2D grid (`groups_x * MORTON_WG`).
    row: u32,
}

const MORTON_WG: u32 = 256u;
// Keys per radix block: four rounds of one key per invocation.
const MORTON_BLOCK: u32 = 1024u;
const MORTON_NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> morton: MortonParams;
@group(0) @binding(1) var<storage, read> morton_input: array<BvhTriangle>;
// min x, y, z then max x, y, z of the centroids, order-preserving u32.
@group(0) @binding(2) var<storage, read_write> morton_bounds_bits: array<atomic<u32>, 6>;
@group(0) @binding(3) var<storage, read_write> morton_keys: array<u32>;
@group(0) @binding(4) var<storage, read_write> morton_values: array<u32>;
@group(0) @binding(5) var<storage, read_write> morton_keys_out: array<u32>;
@group(0) @binding(6) var<storage, read_write> morton_values_out: array<u32>;
// Digit-major histograms: `digit * blocks + block`.
@group(0) @binding(7) var<storage, read_write> morton_hist: array<u32>;

fn morton_index(gid: vec3<u32>) -> u32 {
    return gid.x + gid.y * morton.row;
}

// The workgroup's index in a 2D grid of workgroups.
fn morton_block(wid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return wid.x + wid.y * groups.x;
}

// f32 to u32 in the same order (negative values flipped, positive ones signed).
fn morton_order_bits(x: f32) -> u32 {
    let b = bitcast<u32>(x);
    return select(b | 0x80000000u, ~b, (b >> 31u) == 1u);
}

fn morton_from_order_bits(u: u32) -> f32 {
    return bitcast<f32>(select(~u, u & 0x7fffffffu, (u >> 31u) == 1u));
}

fn morton_centroid(t: BvhTriangle) -> vec3<f32> {
    return (t.v0 + t.v1 + t.v2) * (1.0 / 3.0);
}

var<workgroup> morton_wg_bounds: array<atomic<u32>, 6>;

// The workgroup's bounds first, then one update of the device's per workgroup.
@compute @workgroup_size(MORTON_WG)
fn morton_bounds(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    if (lid < 6u) {
        atomicStore(&morton_wg_bounds[lid], select(0u, 0xffffffffu, lid < 3u));
    }
    workgroupBarrier();
    let i = morton_index(gid);
    if (i < morton.n) {
        let c = morton_centroid(morton_input[i]);
        for (var a = 0u; a < 3u; a += 1u) {
            let u = morton_order_bits(c[a]);
            atomicMin(&morton_wg_bounds[a], u);
            atomicMax(&morton_wg_bounds[3u + a], u);
        }
    }
    workgroupBarrier();
    if (lid < 3u) {
        atomicMin(&morton_bounds_bits[lid], atomicLoad(&morton_wg_bounds[lid]));
    } else if (lid < 6u) {
        atomicMax(&morton_bounds_bits[lid], atomicLoad(&morton_wg_bounds[lid]));
    }
}

// 10 bits spread to every third bit.
fn morton_spread(v: u32) -> u32 {
    var x = v & 0x3ffu;
    x = (x | (x << 16u)) & 0x030000ffu;
    x = (x | (x << 8u)) & 0x0300f00fu;
    x = (x | (x << 4u)) & 0x030c30c3u;
    x = (x | (x << 2u)) & 0x09249249u;
    return x;
}

@compute @workgroup_size(MORTON_WG)
fn morton_codes(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = morton_index(gid);
    if (i >= morton.n) {
        return;
    }
    let c = morton_centroid(morton_input[i]);
    var code = 0u;
    for (var a = 0u; a < 3u; a += 1u) {
        let lo = morton_from_order_bits(atomicLoad(&morton_bounds_bits[a]));
        let hi = morton_from_order_bits(atomicLoad(&morton_bounds_bits[3u + a]));
        let extent = hi - lo;
        var q = 0u;
        if (extent > 0.0) {
            q = u32(clamp((c[a] - lo) / extent * 1024.0, 0.0, 1023.0));
        }
        code |= morton_spread(q) << (2u - a);
    }
    morton_keys[i] = code;
    morton_values[i] = i;
}

var<workgroup> morton_wg_counts: array<atomic<u32>, 256>;
var<workgroup> morton_wg_offsets: array<u32, 256>;
// Which invocations of a round hold each digit: eight 32-bit words per digit, bit `l % 32`
// of word `l / 32` for invocation `l` (a ballot per digit).
var<workgroup> morton_wg_masks: array<atomic<u32>, 2048>;

fn morton_digit(key: u32) -> u32 {
    return (key >> morton.shift) & 0xffu;
}

// Block `wid`'s digit counts.
@compute @workgroup_size(MORTON_WG)
fn morton_radix_count(
    @builtin(workgroup_id) wid3: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = morton_block(wid3, groups);
    atomicStore(&morton_wg_counts[lid], 0u);
    workgroupBarrier();
    if (block < morton.blocks) {
        for (var r = 0u; r < MORTON_BLOCK / MORTON_WG; r += 1u) {
            let i = block * MORTON_BLOCK + r * MORTON_WG + lid;
            if (i < morton.n) {
                atomicAdd(&morton_wg_counts[morton_digit(morton_keys[i])], 1u);
            }
        }
    }
    workgroupBarrier();
    if (block < morton.blocks) {
        morton_hist[lid * morton.blocks + block] = atomicLoad(&morton_wg_counts[lid]);
    }
}

var<workgroup> morton_wg_sums: array<u32, 256>;

// The inclusive prefix sum of `morton_wg_sums` over the workgroup (Hillis-Steele). Every
// invocation calls it after writing its own entry; the first barrier makes those writes
// visible before any is read.
fn morton_wg_scan(lid: u32) {
    workgroupBarrier();
    for (var d = 1u; d < MORTON_WG; d <<= 1u) {
        var add = 0u;
        if (lid >= d) {
            add = morton_wg_sums[lid - d];
        }
        workgroupBarrier();
        morton_wg_sums[lid] += add;
        workgroupBarrier();
    }
}

// The exclusive prefix sum of the histograms, in one workgroup: each invocation sums a
// contiguous run, the runs' sums are scanned, then each run is written.
@compute @workgroup_size(MORTON_WG)
fn morton_radix_scan(@builtin(local_invocation_index) lid: u32) {
    let total = 256u * morton.blocks;
    let per = (total + MORTON_WG - 1u) / MORTON_WG;
    let start = min(lid * per, total);
    let end = min(start + per, total);
    var sum = 0u;
    for (var i = start; i < end; i += 1u) {
        sum += morton_hist[i];
    }
    morton_wg_sums[lid] = sum;
    morton_wg_scan(lid);
    var running = morton_wg_sums[lid] - sum;
    for (var i = start; i < end; i += 1u) {
        let c = morton_hist[i];
        morton_hist[i] = running;
        running += c;
    }
}

// Block `wid`'s keys to their places, in order: a key goes after every key of a smaller
// digit, every earlier block's keys of its digit, and the earlier keys of its block with
// its digit.
@compute @workgroup_size(MORTON_WG)
fn morton_radix_scatter(
    @builtin(workgroup_id) wid3: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = morton_block(wid3, groups);
    if (block < morton.blocks) {
        morton_wg_offsets[lid] = morton_hist[lid * morton.blocks + block];
    }
    let word = lid / 32u;
    let bit = 1u << (lid % 32u);
    for (var r = 0u; r < MORTON_BLOCK / MORTON_WG; r += 1u) {
        let i = block * MORTON_BLOCK + r * MORTON_WG + lid;
        let live = block < morton.blocks && i < morton.n;
        for (var w = 0u; w < 8u; w += 1u) {
            atomicStore(&morton_wg_masks[lid * 8u + w], 0u);
        }
        workgroupBarrier();
        var key = 0u;
        var digit = 0u;
        if (live) {
            key = morton_keys[i];
            digit = morton_digit(key);
            atomicOr(&morton_wg_masks[digit * 8u + word], bit);
        }
        workgroupBarrier();
        if (live) {
            // The earlier invocations of this round with the same digit.
            var before = countOneBits(atomicLoad(&morton_wg_masks[digit * 8u + word]) & (bit - 1u));
            for (var w = 0u; w < word; w += 1u) {
                before += countOneBits(atomicLoad(&morton_wg_masks[digit * 8u + w]));
            }
            let to = morton_wg_offsets[digit] + before;
            morton_keys_out[to] = key;
            morton_values_out[to] = morton_values[i];
        }
        workgroupBarrier();
        var round = 0u;
        for (var w = 0u; w < 8u; w += 1u) {
            round += countOneBits(atomicLoad(&morton_wg_masks[lid * 8u + w]));
        }
        morton_wg_offsets[lid] += round;
        workgroupBarrier();
    }
}

fn morton_triangle_box(t: BvhTriangle) -> array<vec3<f32>, 2> {
    return array<vec3<f32>, 2>(min(min(t.v0, t.v1), t.v2), max(max(t.v0, t.v1), t.v2));
}

// Sorted triangle `j` as the flat layout stores it: its input index as `prim`.
fn morton_sorted_triangle(j: u32) -> BvhTriangle {
    let src = morton_values[j];
    var t = morton_input[src];
    t.prim = src;
    t.pad1 = 0u;
    t.pad2 = 0u;
    return t;
}

// A flat interior node's split axis: its box's longest (the walks read it for their
// near-far order).
fn morton_longest_axis(lo: vec3<f32>, hi: vec3<f32>) -> u32 {
    let e = hi - lo;
    if (e.y > e.x && e.y >= e.z) {
        return 1u;
    }
    if (e.z > e.x && e.z > e.y) {
        return 2u;
    }
    return 0u;
}
