// build_lbvh.wgsl: a linear BVH (Karras 2012) built on the device from the sorted codes
// of `build_morton.wgsl`, written straight into the flat layout every walk reads
// (`FlatNode`, `FlatTriangle`: `types.wgsl`). After the sort, the host runs:
//
// 1. `lbvh_hierarchy`: each interior node's range and split from the longest common prefix
//    of neighbouring codes (index order breaking ties), and every node's parent;
// 2. `lbvh_boxes`: boxes bottom up, each interior node finished by the second child to
//    arrive (an atomic counter per node);
// 3. `lbvh_flatten`: every node written at its depth-first index (`2 * first leaf + left
//    steps from the root`, so the left child follows its parent), one triangle per leaf, the
//    triangles in leaf order with their input index as `prim`, and the tree's depth.
//
// Node numbering before `lbvh_flatten`: interior nodes `0 .. n - 1` (0 is the root), leaf
// `j` is `n - 1 + j`.

// Every node's links: an interior node's children (node numbers as above) in x and y, its
// first leaf in z; every node's parent in w (`MORTON_NONE` for the root).
@group(0) @binding(8) var<storage, read_write> lbvh_links: array<vec4<u32>>;
// Every node's box: min in `2k`, max in `2k + 1` (w unused).
@group(0) @binding(9) var<storage, read_write> lbvh_boxes_out: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> lbvh_arrivals: array<atomic<u32>>;
@group(0) @binding(11) var<storage, read_write> lbvh_nodes: array<BvhNode>;
@group(0) @binding(12) var<storage, read_write> lbvh_triangles: array<BvhTriangle>;
// The longest root-to-leaf path, in edges.
@group(0) @binding(13) var<storage, read_write> lbvh_depth: atomic<u32>;

// The common prefix length of sorted keys `i` and `j` (-1 outside `0..n`); equal keys
// compare their indices, so every key is distinct.
fn lbvh_delta(i: u32, j: i32) -> i32 {
    if (j < 0 || j >= i32(morton.n)) {
        return -1;
    }
    let a = morton_keys[i];
    let b = morton_keys[u32(j)];
    if (a == b) {
        return 32 + i32(countLeadingZeros(i ^ u32(j)));
    }
    return i32(countLeadingZeros(a ^ b));
}

@compute @workgroup_size(MORTON_WG)
fn lbvh_hierarchy(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = morton_index(gid);
    if (i + 1u >= morton.n) {
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
    let leaf0 = morton.n - 1u;
    let left = select(u32(gamma), leaf0 + u32(gamma), first == u32(gamma));
    let right = select(u32(gamma) + 1u, leaf0 + u32(gamma) + 1u, last == u32(gamma) + 1u);
    lbvh_links[i].x = left;
    lbvh_links[i].y = right;
    lbvh_links[i].z = first;
    lbvh_links[left].w = i;
    lbvh_links[right].w = i;
    if (i == 0u) {
        lbvh_links[0].w = MORTON_NONE;
    }
}

// One invocation per leaf: its box, then up the tree while it is the second child to
// arrive at a node (the first stops), each node's box the union of its children's.
@compute @workgroup_size(MORTON_WG)
fn lbvh_boxes(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = morton_index(gid);
    if (j >= morton.n) {
        return;
    }
    let leaf = morton.n - 1u + j;
    let b = morton_triangle_box(morton_input[morton_values[j]]);
    lbvh_boxes_out[2u * leaf] = vec4<f32>(b[0], 0.0);
    lbvh_boxes_out[2u * leaf + 1u] = vec4<f32>(b[1], 0.0);
    var node = leaf;
    loop {
        let p = lbvh_links[node].w;
        if (p == MORTON_NONE || node == 0u) {
            break;
        }
        if (atomicAdd(&lbvh_arrivals[p], 1u) == 0u) {
            return;
        }
        let c = lbvh_links[p].xy;
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
    let leaf0 = morton.n - 1u;
    var first: u32;
    if (node >= leaf0) {
        first = node - leaf0;
    } else {
        first = lbvh_links[node].z;
    }
    var lefts = 0u;
    var depth = 0u;
    var k = node;
    loop {
        let p = lbvh_links[k].w;
        if (p == MORTON_NONE || k == 0u) {
            break;
        }
        lefts += select(0u, 1u, lbvh_links[p].x == k);
        depth += 1u;
        k = p;
    }
    return vec2<u32>(2u * first + lefts, depth);
}

// One invocation per node (interior `0 .. n - 1`, then the leaves): its flat node, and for
// a leaf its triangle.
@compute @workgroup_size(MORTON_WG)
fn lbvh_flatten(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = morton_index(gid);
    if (k >= 2u * morton.n - 1u) {
        return;
    }
    let leaf0 = morton.n - 1u;
    let lo = lbvh_boxes_out[2u * k].xyz;
    let hi = lbvh_boxes_out[2u * k + 1u].xyz;
    let place = lbvh_preorder(k);
    let at = place.x;
    if (k >= leaf0) {
        atomicMax(&lbvh_depth, place.y);
        let j = k - leaf0;
        lbvh_triangles[j] = morton_sorted_triangle(j);
        lbvh_nodes[at] = BvhNode(lo, j, hi, 1u << 2u);
        return;
    }
    let right = lbvh_preorder(lbvh_links[k].y).x;
    lbvh_nodes[at] = BvhNode(lo, right, hi, morton_longest_axis(lo, hi));
}
