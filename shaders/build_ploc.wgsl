// build_ploc.wgsl: a BVH built on the device by locally-ordered clustering (PLOC, Meister
// and Bittner 2018) over the sorted codes of `build_morton.wgsl`, with leaves collapsed by
// the SAH, written straight into the flat layout every walk reads (`types.wgsl`).
//
// The clusters start as the triangles in Morton order. Each iteration, every cluster finds
// its nearest neighbour within `radius` places (the smallest box around both), mutual
// nearest neighbours merge into a new node at the lower place, and the clusters are
// compacted; iterations run until one cluster, the root, is left. Equal distances prefer
// the nearer place, then a pair starting at an even place, then the lower place: that
// orders all pairs strictly, so the closest pair is always mutual and every iteration
// merges at least once, and equal boxes pair off. An iteration after one that merged fewer
// than a sixteenth of the clusters (nested boxes can chain one merge an iteration) pairs
// places 2k and 2k + 1 instead, so the iterations stay O(log n). After the sort, the host
// runs
// `ploc_leaves`, then iterations of `ploc_prepare`, `ploc_neighbours`, `ploc_merge`,
// `ploc_block_sums`, `ploc_scan` and `ploc_compact` (their sizes read from the state
// by indirect dispatch, so a batch of iterations is recorded without reading back), and
// then `ploc_flatten`.
//
// Node numbering: leaf `j` is the `j`-th triangle in Morton order, interior nodes are
// `n ..` in the order they merged.

struct PlocParams {
    // How many places each side a cluster looks for its nearest neighbour.
    radius: u32,
    // The most triangles a collapsed leaf may hold.
    max_leaf: u32,
    // SAH costs of a traversal step and a triangle test (`BuildOptions`).
    cost_traversal: f32,
    cost_intersection: f32,
}

// A node's measures for the leaf collapse: triangles under it, the flat leaves it becomes,
// whether it becomes one leaf, and its SAH cost (unnormalised areas).
struct PlocInfo {
    tris: u32,
    leaves: u32,
    collapsed: u32,
    cost: f32,
}

const PLOC_BLOCK: u32 = 1024u;
// Distances at or above this (overflowed, or NaN from an infinite extent times zero)
// compare equal, so the index order still decides.
const PLOC_FAR: f32 = 3.0e38;

@group(0) @binding(8) var<uniform> ploc: PlocParams;
// 0: clusters this iteration; 1: the next node number; 2: clusters after it; 3: the
// tree's depth; 4: blocks of `PLOC_BLOCK` clusters this iteration; 5: iterations that ran;
// 6: 1 when this iteration pairs places instead of neighbours.
@group(0) @binding(9) var<storage, read_write> ploc_state: array<atomic<u32>, 8>;
// Indirect dispatch sizes: per cluster (x, y, z), then per block.
@group(0) @binding(10) var<storage, read_write> ploc_args: array<u32, 6>;
@group(0) @binding(11) var<storage, read_write> ploc_clusters: array<u32>;
// Each place's cluster after merging, `MORTON_NONE` where it merged into a lower place.
@group(0) @binding(12) var<storage, read_write> ploc_merged: array<u32>;
@group(0) @binding(13) var<storage, read_write> ploc_nearest: array<u32>;
@group(0) @binding(14) var<storage, read_write> ploc_block_sum: array<u32>;
// Every node's box: min in `2k`, max in `2k + 1` (w unused).
@group(0) @binding(15) var<storage, read_write> ploc_boxes: array<vec4<f32>>;
@group(0) @binding(16) var<storage, read_write> ploc_info: array<PlocInfo>;
// Every node's left and right child (interior nodes) and parent (`MORTON_NONE` for the root).
@group(0) @binding(17) var<storage, read_write> ploc_links: array<vec4<u32>>;
@group(0) @binding(18) var<storage, read_write> ploc_nodes: array<BvhNode>;
@group(0) @binding(19) var<storage, read_write> ploc_triangles: array<BvhTriangle>;

fn ploc_half_area(lo: vec3<f32>, hi: vec3<f32>) -> f32 {
    let e = max(hi - lo, vec3<f32>(0.0));
    return e.x * e.y + e.y * e.z + e.z * e.x;
}

// One invocation per triangle in Morton order: its leaf, its cluster, no parent yet.
@compute @workgroup_size(MORTON_WG)
fn ploc_leaves(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = morton_index(gid);
    if (j >= morton.n) {
        return;
    }
    let b = morton_triangle_box(morton_input[morton_values[j]]);
    ploc_boxes[2u * j] = vec4<f32>(b[0], 0.0);
    ploc_boxes[2u * j + 1u] = vec4<f32>(b[1], 0.0);
    let cost = ploc.cost_intersection * ploc_half_area(b[0], b[1]);
    ploc_info[j] = PlocInfo(1u, 1u, 0u, cost);
    ploc_clusters[j] = j;
    ploc_links[j] = vec4<u32>(MORTON_NONE);
    if (j + 1u < morton.n) {
        ploc_links[morton.n + j] = vec4<u32>(MORTON_NONE);
    }
}

// The iteration's sizes from the cluster count the last one left.
@compute @workgroup_size(1)
fn ploc_prepare() {
    let count = atomicLoad(&ploc_state[2]);
    // The last iteration's clusters (`u32` max before the first).
    let last = atomicLoad(&ploc_state[0]);
    atomicStore(&ploc_state[6], select(0u, 1u, last - count < last / 16u));
    atomicStore(&ploc_state[0], count);
    let blocks = (count + PLOC_BLOCK - 1u) / PLOC_BLOCK;
    atomicStore(&ploc_state[4], blocks);
    let live = count > 1u;
    if (live) {
        atomicAdd(&ploc_state[5], 1u);
    }
    let groups = (count + MORTON_WG - 1u) / MORTON_WG;
    let gx = min(groups, 65535u);
    let bx = min(blocks, 65535u);
    ploc_args[0] = select(0u, gx, live);
    ploc_args[1] = select(1u, (groups + gx - 1u) / max(gx, 1u), live);
    ploc_args[2] = 1u;
    ploc_args[3] = select(0u, bx, live);
    ploc_args[4] = select(1u, (blocks + bx - 1u) / max(bx, 1u), live);
    ploc_args[5] = 1u;
}

fn ploc_item(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * MORTON_WG;
}

// Each cluster's nearest neighbour within `radius` places: the smallest box around both,
// ties broken as the file's header says.
@compute @workgroup_size(MORTON_WG)
fn ploc_neighbours(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let i = ploc_item(gid, groups);
    let count = atomicLoad(&ploc_state[0]);
    if (i >= count) {
        return;
    }
    let c = ploc_clusters[i];
    let lo = ploc_boxes[2u * c].xyz;
    let hi = ploc_boxes[2u * c + 1u].xyz;
    let first = i - min(i, ploc.radius);
    let last = min(i + ploc.radius, count - 1u);
    var best = MORTON_NONE;
    var best_area = PLOC_FAR;
    var best_tie = 0u;
    for (var j = first; j <= last; j += 1u) {
        if (j == i) {
            continue;
        }
        let o = ploc_clusters[j];
        let a = ploc_half_area(
            min(lo, ploc_boxes[2u * o].xyz),
            max(hi, ploc_boxes[2u * o + 1u].xyz),
        );
        let d = select(PLOC_FAR, a, a < PLOC_FAR);
        // Ties: the gap, then an odd first place; the lower place wins what is left, as
        // `j` rises.
        let tie = 2u * (max(i, j) - min(i, j)) + (min(i, j) & 1u);
        if (best == MORTON_NONE || d < best_area || (d == best_area && tie < best_tie)) {
            best = j;
            best_area = d;
            best_tie = tie;
        }
    }
    ploc_nearest[i] = best;
}

// Mutual nearest neighbours merge into a new node at the lower place; the higher place
// empties. The node is a leaf of all its triangles when that costs no more by the SAH.
@compute @workgroup_size(MORTON_WG)
fn ploc_merge(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let i = ploc_item(gid, groups);
    let count = atomicLoad(&ploc_state[0]);
    if (i >= count) {
        return;
    }
    var j = ploc_nearest[i];
    var mutual = ploc_nearest[j] == i;
    if (atomicLoad(&ploc_state[6]) != 0u) {
        j = i ^ 1u;
        mutual = j < count;
    }
    if (!mutual) {
        ploc_merged[i] = ploc_clusters[i];
        return;
    }
    if (j < i) {
        ploc_merged[i] = MORTON_NONE;
        return;
    }
    let l = ploc_clusters[i];
    let r = ploc_clusters[j];
    let p = atomicAdd(&ploc_state[1], 1u);
    let lo = min(ploc_boxes[2u * l], ploc_boxes[2u * r]);
    let hi = max(ploc_boxes[2u * l + 1u], ploc_boxes[2u * r + 1u]);
    ploc_boxes[2u * p] = lo;
    ploc_boxes[2u * p + 1u] = hi;
    let a = ploc_info[l];
    let b = ploc_info[r];
    let area = ploc_half_area(lo.xyz, hi.xyz);
    let tris = a.tris + b.tris;
    let split = ploc.cost_traversal * area + a.cost + b.cost;
    let whole = ploc.cost_intersection * area * f32(tris);
    if (tris <= ploc.max_leaf && whole <= split) {
        ploc_info[p] = PlocInfo(tris, 1u, 1u, whole);
    } else {
        ploc_info[p] = PlocInfo(tris, a.leaves + b.leaves, 0u, split);
    }
    ploc_links[p] = vec4<u32>(l, r, MORTON_NONE, 0u);
    ploc_links[l].z = p;
    ploc_links[r].z = p;
    ploc_merged[i] = p;
}

// The clusters kept among invocation `lid`'s four places of block `block`.
fn ploc_kept(block: u32, lid: u32, count: u32) -> u32 {
    var kept = 0u;
    for (var k = 0u; k < 4u; k += 1u) {
        let i = block * PLOC_BLOCK + 4u * lid + k;
        if (i < count && ploc_merged[i] != MORTON_NONE) {
            kept += 1u;
        }
    }
    return kept;
}

// Each block's count of kept clusters.
@compute @workgroup_size(MORTON_WG)
fn ploc_block_sums(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = morton_block(wid, groups);
    let count = atomicLoad(&ploc_state[0]);
    morton_wg_sums[lid] = ploc_kept(block, lid, count);
    morton_wg_scan(lid);
    if (lid == 0u && block < atomicLoad(&ploc_state[4])) {
        ploc_block_sum[block] = morton_wg_sums[MORTON_WG - 1u];
    }
}

// The blocks' exclusive prefix sums, in one workgroup, and the clusters left.
@compute @workgroup_size(MORTON_WG)
fn ploc_scan(@builtin(local_invocation_index) lid: u32) {
    let total = atomicLoad(&ploc_state[4]);
    let per = (total + MORTON_WG - 1u) / MORTON_WG;
    let start = min(lid * per, total);
    let end = min(start + per, total);
    var sum = 0u;
    for (var i = start; i < end; i += 1u) {
        sum += ploc_block_sum[i];
    }
    morton_wg_sums[lid] = sum;
    morton_wg_scan(lid);
    var running = morton_wg_sums[lid] - sum;
    for (var i = start; i < end; i += 1u) {
        let c = ploc_block_sum[i];
        ploc_block_sum[i] = running;
        running += c;
    }
    if (lid == MORTON_WG - 1u && total > 0u) {
        atomicStore(&ploc_state[2], morton_wg_sums[lid]);
    }
}

// The kept clusters moved down to their places, in order.
@compute @workgroup_size(MORTON_WG)
fn ploc_compact(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = morton_block(wid, groups);
    let count = atomicLoad(&ploc_state[0]);
    let kept = ploc_kept(block, lid, count);
    morton_wg_sums[lid] = kept;
    morton_wg_scan(lid);
    if (block >= atomicLoad(&ploc_state[4])) {
        return;
    }
    var to = ploc_block_sum[block] + morton_wg_sums[lid] - kept;
    for (var k = 0u; k < 4u; k += 1u) {
        let i = block * PLOC_BLOCK + 4u * lid + k;
        if (i < count) {
            let c = ploc_merged[i];
            if (c != MORTON_NONE) {
                ploc_clusters[to] = c;
                to += 1u;
            }
        }
    }
}

// One invocation per node: unless an ancestor became a leaf, its flat node at its
// depth-first index (a left child follows its parent; a right child follows its left
// sibling's `2 * leaves - 1` flat nodes), and for a leaf its triangles, left to right.
@compute @workgroup_size(MORTON_WG)
fn ploc_flatten(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = morton_index(gid);
    // Recorded after the iterations a build usually needs: while clusters are left the
    // host records more, then this again.
    if (k >= 2u * morton.n - 1u || atomicLoad(&ploc_state[2]) > 1u) {
        return;
    }
    var at = 0u;
    var first_tri = 0u;
    var depth = 0u;
    var c = k;
    loop {
        let p = ploc_links[c].z;
        if (p == MORTON_NONE) {
            break;
        }
        if (ploc_info[p].collapsed != 0u) {
            return;
        }
        let left = ploc_links[p].x;
        if (left == c) {
            at += 1u;
        } else {
            at += 2u * ploc_info[left].leaves;
            first_tri += ploc_info[left].tris;
        }
        depth += 1u;
        c = p;
    }
    let lo = ploc_boxes[2u * k].xyz;
    let hi = ploc_boxes[2u * k + 1u].xyz;
    let info = ploc_info[k];
    if (k < morton.n || info.collapsed != 0u) {
        atomicMax(&ploc_state[3], depth);
        ploc_nodes[at] = BvhNode(lo, first_tri, hi, info.tris << 2u);
        // The subtree's leaves, left to right (a collapsed node has at most `max_leaf`
        // triangles, so at most that many nodes wait on the stack).
        var stack: array<u32, 32>;
        var top = 1u;
        stack[0] = k;
        var slot = first_tri;
        while (top > 0u && top <= 32u) {
            top -= 1u;
            let node = stack[top];
            if (node < morton.n) {
                ploc_triangles[slot] = morton_sorted_triangle(node);
                slot += 1u;
            } else if (top + 2u <= 32u) {
                stack[top] = ploc_links[node].y;
                stack[top + 1u] = ploc_links[node].x;
                top += 2u;
            }
        }
        return;
    }
    let right = at + 2u * ploc_info[ploc_links[k].x].leaves;
    ploc_nodes[at] = BvhNode(lo, right, hi, morton_longest_axis(lo, hi));
}
