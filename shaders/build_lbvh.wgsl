// build_lbvh.wgsl: a linear BVH (Karras 2012) built on the device, written straight into
// the flat layout every walk reads (`FlatNode`, `FlatTriangle`: `types.wgsl`, composed
// before this file). The host (`bvhtrace_gpu::build`) runs the entry points in order:
//
// 1. `lbvh_bounds`: the centroids' bounds, as order-preserving u32 in atomics;
// 2. `lbvh_morton`: a 30-bit Morton code per triangle centroid, and its index;
// 3. `lbvh_radix_count`, `lbvh_radix_scan`, `lbvh_radix_scatter`, four times (8 bits a
//    pass): a stable radix sort of (code, index), so equal codes keep input order and the
//    same input always gives the same tree;
// 4. `lbvh_hierarchy`: each interior node's range and split from the longest common prefix
//    of neighbouring codes (index order breaking ties), and every node's parent;
// 5. `lbvh_boxes`: boxes bottom up, each interior node finished by the second child to
//    arrive (an atomic counter per node);
// 6. `lbvh_flatten`: every node written at its depth-first index (`2 * first leaf + left
//    steps from the root`, so the left child follows its parent), one triangle per leaf, the
//    triangles in leaf order with their input index as `prim`, and the tree's depth.
//
// Node numbering before `lbvh_flatten`: interior nodes `0 .. n - 1` (0 is the root), leaf
// `j` is `n - 1 + j`. One invocation per element; the grid is 2D past 65,535 workgroups.

struct LbvhParams {
    // Triangles.
    n: u32,
    // The radix pass's first bit (0, 8, 16, 24).
    shift: u32,
    // Workgroups (blocks of `LBVH_BLOCK` keys) of the radix passes.
    blocks: u32,
    // Invocations per row of the 2D grid (`groups_x * LBVH_WG`).
    row: u32,
}

const LBVH_WG: u32 = 256u;
// Keys per radix block: four rounds of one key per invocation.
const LBVH_BLOCK: u32 = 1024u;
const LBVH_NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> lbvh: LbvhParams;
@group(0) @binding(1) var<storage, read> lbvh_input: array<BvhTriangle>;
// min x, y, z then max x, y, z of the centroids, order-preserving u32.
@group(0) @binding(2) var<storage, read_write> lbvh_bounds_bits: array<atomic<u32>, 6>;
@group(0) @binding(3) var<storage, read_write> lbvh_keys: array<u32>;
@group(0) @binding(4) var<storage, read_write> lbvh_values: array<u32>;
@group(0) @binding(5) var<storage, read_write> lbvh_keys_out: array<u32>;
@group(0) @binding(6) var<storage, read_write> lbvh_values_out: array<u32>;
// Digit-major histograms: `digit * blocks + block`.
@group(0) @binding(7) var<storage, read_write> lbvh_hist: array<u32>;
// Interior nodes' children (`LBVH_NONE`-free: node numbers as above) and first leaves.
@group(0) @binding(8) var<storage, read_write> lbvh_children: array<vec2<u32>>;
@group(0) @binding(9) var<storage, read_write> lbvh_first: array<u32>;
// Every node's parent (`LBVH_NONE` for the root).
@group(0) @binding(10) var<storage, read_write> lbvh_parent: array<u32>;
// Every node's box: min in `2k`, max in `2k + 1` (w unused).
@group(0) @binding(11) var<storage, read_write> lbvh_boxes_out: array<vec4<f32>>;
@group(0) @binding(12) var<storage, read_write> lbvh_arrivals: array<atomic<u32>>;
@group(0) @binding(13) var<storage, read_write> lbvh_nodes: array<BvhNode>;
@group(0) @binding(14) var<storage, read_write> lbvh_triangles: array<BvhTriangle>;
// The longest root-to-leaf path, in edges.
@group(0) @binding(15) var<storage, read_write> lbvh_depth: atomic<u32>;

fn lbvh_index(gid: vec3<u32>) -> u32 {
    return gid.x + gid.y * lbvh.row;
}

// f32 to u32 in the same order (negative values flipped, positive ones signed).
fn lbvh_order_bits(x: f32) -> u32 {
    let b = bitcast<u32>(x);
    return select(b | 0x80000000u, ~b, (b >> 31u) == 1u);
}

fn lbvh_from_order_bits(u: u32) -> f32 {
    return bitcast<f32>(select(~u, u & 0x7fffffffu, (u >> 31u) == 1u));
}

fn lbvh_centroid(t: BvhTriangle) -> vec3<f32> {
    return (t.v0 + t.v1 + t.v2) * (1.0 / 3.0);
}

var<workgroup> lbvh_wg_bounds: array<atomic<u32>, 6>;

// The workgroup's bounds first, then one update of the device's per workgroup.
@compute @workgroup_size(LBVH_WG)
fn lbvh_bounds(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    if (lid < 6u) {
        atomicStore(&lbvh_wg_bounds[lid], select(0u, 0xffffffffu, lid < 3u));
    }
    workgroupBarrier();
    let i = lbvh_index(gid);
    if (i < lbvh.n) {
        let c = lbvh_centroid(lbvh_input[i]);
        for (var a = 0u; a < 3u; a += 1u) {
            let u = lbvh_order_bits(c[a]);
            atomicMin(&lbvh_wg_bounds[a], u);
            atomicMax(&lbvh_wg_bounds[3u + a], u);
        }
    }
    workgroupBarrier();
    if (lid < 3u) {
        atomicMin(&lbvh_bounds_bits[lid], atomicLoad(&lbvh_wg_bounds[lid]));
    } else if (lid < 6u) {
        atomicMax(&lbvh_bounds_bits[lid], atomicLoad(&lbvh_wg_bounds[lid]));
    }
}

// 10 bits spread to every third bit.
fn lbvh_spread(v: u32) -> u32 {
    var x = v & 0x3ffu;
    x = (x | (x << 16u)) & 0x030000ffu;
    x = (x | (x << 8u)) & 0x0300f00fu;
    x = (x | (x << 4u)) & 0x030c30c3u;
    x = (x | (x << 2u)) & 0x09249249u;
    return x;
}

@compute @workgroup_size(LBVH_WG)
fn lbvh_morton(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lbvh_index(gid);
    if (i >= lbvh.n) {
        return;
    }
    let c = lbvh_centroid(lbvh_input[i]);
    var code = 0u;
    for (var a = 0u; a < 3u; a += 1u) {
        let lo = lbvh_from_order_bits(atomicLoad(&lbvh_bounds_bits[a]));
        let hi = lbvh_from_order_bits(atomicLoad(&lbvh_bounds_bits[3u + a]));
        let extent = hi - lo;
        var q = 0u;
        if (extent > 0.0) {
            q = u32(clamp((c[a] - lo) / extent * 1024.0, 0.0, 1023.0));
        }
        code |= lbvh_spread(q) << (2u - a);
    }
    lbvh_keys[i] = code;
    lbvh_values[i] = i;
}

var<workgroup> lbvh_wg_counts: array<atomic<u32>, 256>;
var<workgroup> lbvh_wg_offsets: array<u32, 256>;
// Which invocations of a round hold each digit: eight 32-bit words per digit, bit `l % 32`
// of word `l / 32` for invocation `l` (a ballot per digit).
var<workgroup> lbvh_wg_masks: array<atomic<u32>, 2048>;

fn lbvh_digit(key: u32) -> u32 {
    return (key >> lbvh.shift) & 0xffu;
}

// Block `wid`'s digit counts.
@compute @workgroup_size(LBVH_WG)
fn lbvh_radix_count(
    @builtin(workgroup_id) wid3: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = wid3.x + wid3.y * groups.x;
    atomicStore(&lbvh_wg_counts[lid], 0u);
    workgroupBarrier();
    if (block < lbvh.blocks) {
        for (var r = 0u; r < LBVH_BLOCK / LBVH_WG; r += 1u) {
            let i = block * LBVH_BLOCK + r * LBVH_WG + lid;
            if (i < lbvh.n) {
                atomicAdd(&lbvh_wg_counts[lbvh_digit(lbvh_keys[i])], 1u);
            }
        }
    }
    workgroupBarrier();
    if (block < lbvh.blocks) {
        lbvh_hist[lid * lbvh.blocks + block] = atomicLoad(&lbvh_wg_counts[lid]);
    }
}

var<workgroup> lbvh_wg_sums: array<u32, 256>;

// The exclusive prefix sum of the histograms, in one workgroup: each invocation sums a
// contiguous run, the runs' sums are scanned, then each run is written.
@compute @workgroup_size(LBVH_WG)
fn lbvh_radix_scan(@builtin(local_invocation_index) lid: u32) {
    let total = 256u * lbvh.blocks;
    let per = (total + LBVH_WG - 1u) / LBVH_WG;
    let start = min(lid * per, total);
    let end = min(start + per, total);
    var sum = 0u;
    for (var i = start; i < end; i += 1u) {
        sum += lbvh_hist[i];
    }
    lbvh_wg_sums[lid] = sum;
    workgroupBarrier();
    // Hillis-Steele over the 256 run sums.
    for (var d = 1u; d < LBVH_WG; d <<= 1u) {
        var add = 0u;
        if (lid >= d) {
            add = lbvh_wg_sums[lid - d];
        }
        workgroupBarrier();
        lbvh_wg_sums[lid] += add;
        workgroupBarrier();
    }
    var running = lbvh_wg_sums[lid] - sum;
    for (var i = start; i < end; i += 1u) {
        let c = lbvh_hist[i];
        lbvh_hist[i] = running;
        running += c;
    }
}

// Block `wid`'s keys to their places, in order: a key goes after every key of a smaller
// digit, every earlier block's keys of its digit, and the earlier keys of its block with
// its digit.
@compute @workgroup_size(LBVH_WG)
fn lbvh_radix_scatter(
    @builtin(workgroup_id) wid3: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = wid3.x + wid3.y * groups.x;
    if (block < lbvh.blocks) {
        lbvh_wg_offsets[lid] = lbvh_hist[lid * lbvh.blocks + block];
    }
    let word = lid / 32u;
    let bit = 1u << (lid % 32u);
    for (var r = 0u; r < LBVH_BLOCK / LBVH_WG; r += 1u) {
        let i = block * LBVH_BLOCK + r * LBVH_WG + lid;
        let live = block < lbvh.blocks && i < lbvh.n;
        for (var w = 0u; w < 8u; w += 1u) {
            atomicStore(&lbvh_wg_masks[lid * 8u + w], 0u);
        }
        workgroupBarrier();
        var key = 0u;
        var digit = 0u;
        if (live) {
            key = lbvh_keys[i];
            digit = lbvh_digit(key);
            atomicOr(&lbvh_wg_masks[digit * 8u + word], bit);
        }
        workgroupBarrier();
        if (live) {
            // The earlier invocations of this round with the same digit.
            var before = countOneBits(atomicLoad(&lbvh_wg_masks[digit * 8u + word]) & (bit - 1u));
            for (var w = 0u; w < word; w += 1u) {
                before += countOneBits(atomicLoad(&lbvh_wg_masks[digit * 8u + w]));
            }
            let to = lbvh_wg_offsets[digit] + before;
            lbvh_keys_out[to] = key;
            lbvh_values_out[to] = lbvh_values[i];
        }
        workgroupBarrier();
        var round = 0u;
        for (var w = 0u; w < 8u; w += 1u) {
            round += countOneBits(atomicLoad(&lbvh_wg_masks[lid * 8u + w]));
        }
        lbvh_wg_offsets[lid] += round;
        workgroupBarrier();
    }
}

// The common prefix length of sorted keys `i` and `j` (-1 outside `0..n`); equal keys
// compare their indices, so every key is distinct.
fn lbvh_delta(i: u32, j: i32) -> i32 {
    if (j < 0 || j >= i32(lbvh.n)) {
        return -1;
    }
    let a = lbvh_keys[i];
    let b = lbvh_keys[u32(j)];
    if (a == b) {
        return 32 + i32(countLeadingZeros(i ^ u32(j)));
    }
    return i32(countLeadingZeros(a ^ b));
}

@compute @workgroup_size(LBVH_WG)
fn lbvh_hierarchy(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lbvh_index(gid);
    if (i + 1u >= lbvh.n) {
        return;
    }
    let ii = i32(i);
    let d = select(-1, 1, lbvh_delta(i, ii + 1) > lbvh_delta(i, ii - 1));
    let delta_min = lbvh_delta(i, ii - d);
    // The range's other end: grow a bound, then binary search.
    var l_max = 2;
    while (lbvh_delta(i, ii + l_max * d) > delta_min) {
        l_max *= 2;
    }
    var l = 0;
    for (var t = l_max / 2; t >= 1; t /= 2) {
        if (lbvh_delta(i, ii + (l + t) * d) > delta_min) {
            l += t;
        }
    }
    let j = ii + l * d;
    let delta_node = lbvh_delta(i, j);
    // The split: the last key sharing more than `delta_node` bits with key `i`.
    var s = 0;
    var t = l;
    loop {
        t = (t + 1) / 2;
        if (lbvh_delta(i, ii + (s + t) * d) > delta_node) {
            s += t;
        }
        if (t <= 1) {
            break;
        }
    }
    let gamma = ii + s * d + min(d, 0);
    let first = u32(min(ii, j));
    let last = u32(max(ii, j));
    let leaf0 = lbvh.n - 1u;
    let left = select(u32(gamma), leaf0 + u32(gamma), first == u32(gamma));
    let right = select(u32(gamma) + 1u, leaf0 + u32(gamma) + 1u, last == u32(gamma) + 1u);
    lbvh_children[i] = vec2<u32>(left, right);
    lbvh_first[i] = first;
    lbvh_parent[left] = i;
    lbvh_parent[right] = i;
    if (i == 0u) {
        lbvh_parent[0] = LBVH_NONE;
    }
}

fn lbvh_triangle_box(t: BvhTriangle) -> array<vec3<f32>, 2> {
    return array<vec3<f32>, 2>(min(min(t.v0, t.v1), t.v2), max(max(t.v0, t.v1), t.v2));
}

// One invocation per leaf: its box, then up the tree while it is the second child to
// arrive at a node (the first stops), each node's box the union of its children's.
@compute @workgroup_size(LBVH_WG)
fn lbvh_boxes(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = lbvh_index(gid);
    if (j >= lbvh.n) {
        return;
    }
    let leaf = lbvh.n - 1u + j;
    let b = lbvh_triangle_box(lbvh_input[lbvh_values[j]]);
    lbvh_boxes_out[2u * leaf] = vec4<f32>(b[0], 0.0);
    lbvh_boxes_out[2u * leaf + 1u] = vec4<f32>(b[1], 0.0);
    var node = leaf;
    loop {
        let p = lbvh_parent[node];
        if (p == LBVH_NONE || node == 0u) {
            break;
        }
        if (atomicAdd(&lbvh_arrivals[p], 1u) == 0u) {
            return;
        }
        let c = lbvh_children[p];
        let lo = min(lbvh_boxes_out[2u * c.x], lbvh_boxes_out[2u * c.y]);
        let hi = max(lbvh_boxes_out[2u * c.x + 1u], lbvh_boxes_out[2u * c.y + 1u]);
        lbvh_boxes_out[2u * p] = lo;
        lbvh_boxes_out[2u * p + 1u] = hi;
        node = p;
    }
}

// The depth-first index of `node`: twice its first leaf, plus the left steps from the
// root to it (the nodes before it are its ancestors and the whole subtrees left of it);
// and its depth.
fn lbvh_preorder(node: u32) -> vec2<u32> {
    let leaf0 = lbvh.n - 1u;
    var first: u32;
    if (node >= leaf0) {
        first = node - leaf0;
    } else {
        first = lbvh_first[node];
    }
    var lefts = 0u;
    var depth = 0u;
    var k = node;
    loop {
        let p = lbvh_parent[k];
        if (p == LBVH_NONE || k == 0u) {
            break;
        }
        lefts += select(0u, 1u, lbvh_children[p].x == k);
        depth += 1u;
        k = p;
    }
    return vec2<u32>(2u * first + lefts, depth);
}

// One invocation per node (interior `0 .. n - 1`, then the leaves): its flat node, and for
// a leaf its triangle.
@compute @workgroup_size(LBVH_WG)
fn lbvh_flatten(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = lbvh_index(gid);
    if (k >= 2u * lbvh.n - 1u) {
        return;
    }
    let leaf0 = lbvh.n - 1u;
    let lo = lbvh_boxes_out[2u * k].xyz;
    let hi = lbvh_boxes_out[2u * k + 1u].xyz;
    let place = lbvh_preorder(k);
    let at = place.x;
    if (k >= leaf0) {
        atomicMax(&lbvh_depth, place.y);
        let j = k - leaf0;
        let src = lbvh_values[j];
        var t = lbvh_input[src];
        t.prim = src;
        t.pad1 = 0u;
        t.pad2 = 0u;
        lbvh_triangles[j] = t;
        lbvh_nodes[at] = BvhNode(lo, j, hi, 1u << 2u);
        return;
    }
    // The split axis: the box's longest (the walks read it for their near-far order).
    let e = hi - lo;
    var axis = 0u;
    if (e.y > e.x && e.y >= e.z) {
        axis = 1u;
    } else if (e.z > e.x && e.z > e.y) {
        axis = 2u;
    }
    let right = lbvh_preorder(lbvh_children[k].y).x;
    lbvh_nodes[at] = BvhNode(lo, right, hi, axis);
}
