// traverse_wide.wgsl: twin of `bvhtrace_core::traverse::wide`, the walk of the wide layout
// (`bvhtrace_core::wide`, nodes from `bvh_buffers_wide.wgsl` or `bvh_textures_wide.wgsl`).
//
// At each node the eight child boxes are tested together (`bvh_wide_group`: each one is
// `bvh_intersect_box` of `box.wgsl` on the decoded box, as `wide::hit_children` does on the
// CPU), giving the node's *group*: its hit children as a mask in visit order, bit `s ^ oct`
// for slot `s` (the slots are laid out so that the ray's octant `oct` visits them roughly
// nearest first without a sort), and the nearest hit child (least entry distance, the
// first in visit order among equal ones). The walk takes that one first, then the others
// in mask order: a leaf's triangles are tested (or, in a top-level node, its instance
// entered), an interior child is descended into, the rest of the group pushed. When the
// group runs out the next one is popped and taken in mask order. A group is two stack
// entries (node, mask) of `lane`'s stack in `lane_stacks` (`traverse_stack.wgsl`), so the
// stack holds `WIDE_STACK_GROUPS` groups.
//
// Correct at any depth: the stack holds at most one group per level above the current
// node, so a tree of at most `WIDE_STACK_GROUPS + 1` levels never fills it. On a deeper one
// a push that would overflow gives the ray up as incomplete, as a spent trip budget does
// (`bvh_incomplete`), and the host finishes it with the CPU twin
// (`bvhtrace_engine::finish_incomplete`), keeping a host copy for that whenever the
// uploaded wide tree is that deep. A wide tree is about a third as deep as a balanced
// binary one (a seventh of a chain), so the trees that can overflow are ones the full stack
// (64 entries) refuses outright, and no per-lane storage is spent on them.
//
// Loops as in the full stack (while-while, Aila and Laine 2009): the inner loop tests
// groups, pops and enters instances until the ray stands on a leaf child or is done; the
// leaf is tested after it. Every inner trip takes one of the ray's `TRIP_LIMIT` trips, and
// every triangle one.

// Groups `lane_stacks` holds per lane: a node and its mask each.
const BVH_WIDE_STACK_GROUPS: u32 = BVH_STACK_ENTRIES / 2u;

// What the walk keeps of the node whose group it is taking: where its children are.
// `imask` bit `s` marks an interior child in slot `s`.
struct BvhWideLinks {
    imask: u32,
    child_base: u32,
    triangle_base: u32,
    counts: vec2<u32>,
}

fn bvh_wide_links(n: BvhWideNode) -> BvhWideLinks {
    return BvhWideLinks(n.exponents >> 24u, n.child_base, n.triangle_base, n.counts);
}

// Byte `s` (0..8) of an 8-byte field: slot `s`'s plane or count.
fn bvh_wide_byte(w: vec2<u32>, s: u32) -> u32 {
    return (select(w.x, w.y, s >= 4u) >> ((s & 3u) * 8u)) & 0xffu;
}

// The sum of the bytes of `x` (under 256 for counts, `wide::MAX_LEAF_TRIANGLES`).
fn bvh_wide_byte_sum(x: u32) -> u32 {
    return (x * 0x01010101u) >> 24u;
}

// Bit `k` set when byte `k` of `x` is not zero (`WideNode::used_mask`'s bit trick).
fn bvh_wide_nonzero_bytes(x: u32) -> u32 {
    let low7 = 0x7f7f7f7fu;
    let high = (((x & low7) + low7) | x) & 0x80808080u;
    return (((high >> 7u) * 0x00204081u) >> 21u) & 0xfu;
}

// Leaf child `s`'s first triangle (or instance, in a top-level node) and count
// (`WideNode::leaf_range`).
fn bvh_wide_leaf_range(l: BvhWideLinks, s: u32) -> vec2<u32> {
    let below = (1u << ((s & 3u) * 8u)) - 1u;
    let before = select(
        bvh_wide_byte_sum(l.counts.x & below),
        bvh_wide_byte_sum(l.counts.x) + bvh_wide_byte_sum(l.counts.y & below),
        s >= 4u,
    );
    return vec2<u32>(l.triangle_base + before, bvh_wide_byte(l.counts, s));
}

// Interior child `s`'s node (`WideNode::child`).
fn bvh_wide_child(l: BvhWideLinks, s: u32) -> u32 {
    return l.child_base + countOneBits(l.imask & ((1u << s) - 1u));
}

// A node's group as its children's boxes are tested (`wide::hit_children`): the hit
// children in visit order, and the nearest of them so far, its entry distance and its
// place in the visit order (`BVH_WIDE_NONE` while none is hit).
struct BvhWideGroup {
    mask: u32,
    nearest: f32,
    first: u32,
}

const BVH_WIDE_NONE: u32 = 32u;

// Tests slot `s` into `g` when it is used: the box is decoded as `WideNode::child_box` does
// (`origin + q * scale`; `q * scale` is exact, so a fused multiply-add rounds the same),
// tested by `bvh_intersect_box`, and a hit is bit `s ^ oct`. The nearest is the least
// entry distance, the first in visit order among equal ones, as the CPU's minimum over
// the hit slots and its lowest tie are (a NaN distance never wins either way).
fn bvh_wide_slot(g: ptr<function, BvhWideGroup>, n: BvhWideNode, scale: vec3<f32>, used: u32, s: u32, oct: u32, r: BvhPreparedRay, t_best: f32) {
    let lo = vec3<u32>(bvh_wide_byte(n.q_lo[0], s), bvh_wide_byte(n.q_lo[1], s), bvh_wide_byte(n.q_lo[2], s));
    let hi = vec3<u32>(bvh_wide_byte(n.q_hi[0], s), bvh_wide_byte(n.q_hi[1], s), bvh_wide_byte(n.q_hi[2], s));
    let t = bvh_intersect_box(r, n.origin + vec3<f32>(lo) * scale, n.origin + vec3<f32>(hi) * scale, t_best);
    let j = s ^ oct;
    let hit = ((used >> s) & 1u) != 0u && bvh_box_hit(t);
    let nearer = t.x < (*g).nearest || (t.x == (*g).nearest && j < (*g).first);
    (*g).mask |= select(0u, 1u << j, hit);
    (*g).first = select((*g).first, j, hit && nearer);
    (*g).nearest = select((*g).nearest, t.x, hit && nearer);
}

// Node `n`'s group (`traverse::group`): its hit children in visit order, and where the
// nearest is in it; every used slot's box test is counted. The eight slots are written
// out rather than looped over: a CPU driver counts every loop trip against its
// per-invocation limit (`traverse_common.wgsl`).
fn bvh_wide_group(n: BvhWideNode, r: BvhPreparedRay, t_best: f32, oct: u32, c: ptr<function, BvhCounters>) -> BvhWideGroup {
    let used = bvh_wide_nonzero_bytes(n.counts.x) | (bvh_wide_nonzero_bytes(n.counts.y) << 4u) | (n.exponents >> 24u);
    (*c).nodes += countOneBits(used);
    // `2^(e - 127)` per axis: the biased exponent moved into place.
    let e = (vec3<u32>(n.exponents) >> vec3<u32>(0u, 8u, 16u)) & vec3<u32>(0xffu);
    let scale = bitcast<vec3<f32>>(e << vec3<u32>(23u));
    var g = BvhWideGroup(0u, bvh_infinity(), BVH_WIDE_NONE);
    bvh_wide_slot(&g, n, scale, used, 0u, oct, r, t_best);
    bvh_wide_slot(&g, n, scale, used, 1u, oct, r, t_best);
    bvh_wide_slot(&g, n, scale, used, 2u, oct, r, t_best);
    bvh_wide_slot(&g, n, scale, used, 3u, oct, r, t_best);
    bvh_wide_slot(&g, n, scale, used, 4u, oct, r, t_best);
    bvh_wide_slot(&g, n, scale, used, 5u, oct, r, t_best);
    bvh_wide_slot(&g, n, scale, used, 6u, oct, r, t_best);
    bvh_wide_slot(&g, n, scale, used, 7u, oct, r, t_best);
    return g;
}

fn bvh_trace_wide(ray: BvhRay, any_hit: bool, lane: u32) -> BvhTraceResult {
    if (!bvh_ray_is_traced(ray)) {
        return bvh_untraced_result(ray);
    }
    var r = bvh_prepare_ray(ray);
    var best = bvh_start_best(ray);
    var c = BvhCounters(0u, 0u);
    var oct = bvh_octant(r.dir);
    bvh_start_space(ray, r, oct);
    var sp = 0u; // groups on the stack
    var spent = false; // the trip budget ran out, or the stack would have overflowed
    // The group being taken: its node, the children left (visit order), the one to take
    // next when it is a fresh group's nearest (`BVH_WIDE_NONE`: the mask's lowest), where
    // they are.
    var node = 0u;
    let root = bvh_load_wide_node(0u);
    let g = bvh_wide_group(root, r, best.t, oct, &c);
    var mask = g.mask;
    var first = g.first;
    var links = bvh_wide_links(root);
    loop {
        // The leaf child the inner loop stops at; a count of 0: none (done or given up).
        var leaf_first = 0u;
        var leaf_count = 0u;
        loop {
            if (!bvh_take_trip()) {
                spent = true;
                break;
            }
            if (mask == 0u) {
                if (sp == 0u) {
                    break;
                }
                sp -= 1u;
                node = bvh_lane_stacks[bvh_stack_slot(lane, 2u * sp)];
                mask = bvh_lane_stacks[bvh_stack_slot(lane, 2u * sp + 1u)];
                first = BVH_WIDE_NONE;
                if (bvh_leave_if_top(node, &r)) {
                    oct = bvh_world_oct;
                }
                links = bvh_load_wide_links(node);
                continue;
            }
            let j = select(firstTrailingBit(mask), first, first != BVH_WIDE_NONE);
            first = BVH_WIDE_NONE;
            mask &= ~(1u << j);
            let slot = j ^ oct;
            var next: u32;
            if (((links.imask >> slot) & 1u) != 0u) {
                next = bvh_wide_child(links, slot);
            } else {
                let range = bvh_wide_leaf_range(links, slot);
                if (!(BVH_INSTANCED && node < bvh_top_nodes())) {
                    leaf_first = range.x;
                    leaf_count = range.y;
                    break;
                }
                // A top-level leaf child is one instance: the walk goes on at its mesh's
                // root, whose own box is not tested (the leaf's was).
                next = bvh_enter_instance(node, range.x, &r);
                if (next == BVH_NOT_ENTERED) {
                    continue;
                }
                oct = bvh_octant(r.dir);
            }
            // Down to `next`, the rest of this group pushed.
            if (mask != 0u) {
                if (sp == BVH_WIDE_STACK_GROUPS) {
                    spent = true;
                    break;
                }
                bvh_lane_stacks[bvh_stack_slot(lane, 2u * sp)] = node;
                bvh_lane_stacks[bvh_stack_slot(lane, 2u * sp + 1u)] = mask;
                sp += 1u;
            }
            node = next;
            let n = bvh_load_wide_node(node);
            let g = bvh_wide_group(n, r, best.t, oct, &c);
            mask = g.mask;
            first = g.first;
            links = bvh_wide_links(n);
        }
        if (leaf_count == 0u) {
            break;
        }
        if (bvh_visit_leaf(r, leaf_first, leaf_count, &best, &c, any_hit)) {
            break;
        }
        if (bvh_trips_left == 0u) {
            spent = true;
            break;
        }
    }
    if (spent) {
        return bvh_incomplete(best, c);
    }
    return bvh_finish(best, c);
}
