// traverse_short_stack.wgsl: twin of `bvhtrace_core::traverse::short_stack`: the stackless
// walk (`k == 0`) and the short stack of `k` entries.
//
// Both walk the tree depth first, one box test per loop trip: a node's box is tested when
// the walk arrives at it, and an interior node whose box is hit is entered on the child on
// the ray's side of its split axis (Hapala et al. 2011's order, fixed by the ray's octant).
// When the walk is done with a node's subtree (its box missed, or a leaf tested), it goes
// to the next node of that order:
// - the stackless walk follows the node's escape link for the octant (a skip link,
//   `FlatBvh::escapes`, `load_escape`): no stack, no parent climb, no box tested twice;
// - the short stack pushes the second child onto a ring of `k` entries when it enters the
//   first (overwriting the oldest entry when the ring is full) and pops it; only when the
//   ring runs dry after such an overflow does it follow the escape link of the node it is
//   done with, which leads to exactly the most recent dropped entry.
// The ring is two registers for `k <= REGISTER_RING`, else `lane`'s first `k` entries in
// `lane_stacks` (`traverse_stack.wgsl`). The register ring marks its empty entries with
// `NO_ESCAPE` instead of counting its live ones: the ring is full when entry `k - 1` is
// taken and dry when the popped entry is empty, so a push or pop is one shift with no
// count to keep. On lavapipe that is 10% fewer instructions for the whole short-stack(8)
// walk and 8-13% more rays a second (`bunny_69k`, `igea`); a counted ring ran at the full
// stack's speed.
//
// Why one box per trip, where the full stack tests both children of a node in one trip: on
// a driver that runs 8 lanes as SIMD and both sides of every branch (lavapipe), a trip that
// only tests one box and moves on is about half the cost of the two-box trip with its push,
// the walk leaves its inner loop only at leaves (a missed box is just the next trip), and
// no pop or climb runs per subtree. On `bunny_69k` and `igea` it tests 7% fewer boxes than
// the full stack too.
//
// There is no separate stackless kernel: it is this function specialised with k = 0 (the
// entry point passes the `SHORT_STACK_SIZE` override constant, so the compiler folds `k`).
// `k` is clamped to `1..=MAX_SHORT_STACK` by the host for `Traversal::ShortStack(k)`.
// Every box test and every triangle test takes one of the ray's `TRIP_LIMIT` trips.

// `bvhtrace_core::flat::NO_ESCAPE`: the walk is over; also an empty register-ring entry
// (no node has this index).
const BVH_NO_ESCAPE: u32 = 0xffffffffu;

// `bvhtrace_core::flat::ESCAPE_BLOCK` (a power of two, here as its log2) and `OCTANTS`.
const BVH_ESCAPE_BLOCK_LOG2: u32 = 4u;
const BVH_ESCAPE_BLOCK: u32 = 1u << BVH_ESCAPE_BLOCK_LOG2;
const BVH_OCTANTS: u32 = 8u;

// Where node `i`'s escape link for octant `oct` is (`bvhtrace_core::flat::escape_index`):
// blocks of `ESCAPE_BLOCK` nodes, octant by octant, so the links one walk reads share cache
// lines (on `igea`, 5-10% faster than eight links side by side per node).
fn bvh_escape_index(i: u32, oct: u32) -> u32 {
    return (i >> BVH_ESCAPE_BLOCK_LOG2) * (BVH_ESCAPE_BLOCK * BVH_OCTANTS) + oct * BVH_ESCAPE_BLOCK + (i & (BVH_ESCAPE_BLOCK - 1u));
}

// Rings of at most this many entries live in two `vec4<u32>` registers, pushed and popped
// by shifting, entries past `k` kept empty (on lavapipe a shift is a few vector selects,
// while a `lane_stacks` access is a loop over the 8 lanes); larger rings in `lane_stacks`.
// `k` is an override constant, so the driver keeps one of the two.
const BVH_REGISTER_RING: u32 = 8u;

fn bvh_trace_short_stack(ray: BvhRay, any_hit: bool, k: u32, lane: u32) -> BvhTraceResult {
    if (!bvh_ray_is_traced(ray)) {
        return bvh_untraced_result(ray);
    }
    var r = bvh_prepare_ray(ray);
    var best = bvh_start_best(ray);
    var c = BvhCounters(0u, 0u);
    var oct = bvh_octant(r.dir);
    bvh_start_space(ray, r, oct);
    // The ring: in two registers when it fits (`k <= REGISTER_RING`), else in `lane_stacks`.
    var newer = vec4<u32>(BVH_NO_ESCAPE); // entries 0..3, `newer.x` the top; `NO_ESCAPE`: empty
    var older = vec4<u32>(BVH_NO_ESCAPE); // entries 4..7
    var top = 0u; // next write slot in `lane_stacks`
    var count = 0u; // live entries in `lane_stacks`
    var overflow = false;
    var node = 0u;
    var escape_link = BVH_NO_ESCAPE; // the stackless walk's link of `node`
    var spent = false; // the trip budget ran out
    // For `k > 0` the escape link is followed in this loop, outside the walk's loops: a CPU
    // driver runs every loop body at least once for the whole SIMD batch, so the link's
    // load would cost every leaf, although only a ring that overflowed and ran dry needs
    // it. The stackless walk follows a link at the end of every subtree, in the inner loop.
    loop {
        var escape = false;
        // While-while (Aila and Laine 2009): the inner loop tests boxes until the ray
        // stands on a hit leaf or its walk (or ring) is done; the leaf is tested after it,
        // so SIMD lanes run box tests together and triangle tests together.
        loop {
            var leaf_first = 0u;
            var leaf_count = 0u;
            loop {
                if (!bvh_take_trip()) {
                    spent = true;
                    break;
                }
                c.nodes += 1u;
                let n = bvh_load_node(node);
                // The stackless walk loads the link before the box test, so that its
                // cache miss overlaps the node's instead of waiting for the box's result.
                if (k == 0u) {
                    escape_link = bvh_load_escape(node, oct);
                }
                let hit = bvh_box_hit(bvh_intersect_box(r, n.min, n.max, best.t));
                let count_here = n.meta_bits >> 2u;
                if (hit && count_here != 0u && bvh_is_instance_leaf(n.meta_bits)) {
                    let root = bvh_enter_instance(node, n.right_or_first, &r);
                    if (root != BVH_NOT_ENTERED) {
                        oct = bvh_octant(r.dir);
                        node = root;
                        continue;
                    }
                    // Passed through: the leaf is done (below, as a missed box).
                } else if (hit && count_here != 0u) {
                    leaf_first = n.right_or_first;
                    leaf_count = count_here;
                    break;
                } else if (hit) {
                    let second_first = ((oct >> (n.meta_bits & 3u)) & 1u) != 0u;
                    if (k > 0u) {
                        let far = select(n.right_or_first, node + 1u, second_first);
                        if (k <= BVH_REGISTER_RING) {
                            // A full ring (entry `k - 1` taken) drops its oldest entry.
                            let last = select(older[(k - 1u) & 3u], newer[(k - 1u) & 3u], k <= 4u);
                            overflow = overflow | (last != BVH_NO_ESCAPE);
                            older = vec4<u32>(newer.w, older.xyz);
                            newer = vec4<u32>(far, newer.xyz);
                            // Entry `k` (if there is one) got entry `k - 1`: empty it again.
                            if (k < 4u) {
                                newer[k & 3u] = BVH_NO_ESCAPE;
                            } else if (k < 8u) {
                                older[k & 3u] = BVH_NO_ESCAPE;
                            }
                        } else {
                            if (count == k) {
                                overflow = true; // the oldest entry is overwritten
                            } else {
                                count += 1u;
                            }
                            bvh_lane_stacks[bvh_stack_slot(lane, top)] = far;
                            top = select(top + 1u, 0u, top + 1u == k);
                        }
                    }
                    node = select(node + 1u, n.right_or_first, second_first);
                    continue;
                }
                // Missed: the subtree at `node` is done.
                let next = bvh_next_node(&node, escape_link, &newer, &older, &top, &count, overflow, k, lane, &r, &oct);
                if (next == BVH_NEXT_ON) {
                    continue;
                }
                escape = next == BVH_NEXT_ESCAPE;
                break;
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
            // The leaf's subtree is done (`escape_link` is still the leaf's, loaded on its trip).
            let next = bvh_next_node(&node, escape_link, &newer, &older, &top, &count, overflow, k, lane, &r, &oct);
            if (next == BVH_NEXT_ON) {
                continue;
            }
            escape = next == BVH_NEXT_ESCAPE;
            break;
        }
        if (!escape) {
            break;
        }
        // The ring ran dry after dropping entries: the most recent dropped one is where
        // `node`'s escape link leads.
        node = bvh_load_escape(node, oct);
        if (node == BVH_NO_ESCAPE && bvh_escape_instance(&node, &r, &oct) == BVH_NEXT_DONE) {
            break;
        }
    }
    if (spent) {
        return bvh_incomplete(best, c);
    }
    return bvh_finish(best, c);
}

// What the walk does when it is done with the subtree at `node`: go on at the new `node`
// (the escape link without a ring, else the ring's newest entry), end, or (a short stack
// whose ring ran dry after dropping entries) follow `node`'s escape link in the restart
// loop.
const BVH_NEXT_ON: u32 = 0u;
const BVH_NEXT_DONE: u32 = 1u;
const BVH_NEXT_ESCAPE: u32 = 2u;

fn bvh_next_node(
    node: ptr<function, u32>,
    escape_link: u32,
    newer: ptr<function, vec4<u32>>,
    older: ptr<function, vec4<u32>>,
    top: ptr<function, u32>,
    count: ptr<function, u32>,
    overflow: bool,
    k: u32,
    lane: u32,
    r: ptr<function, BvhPreparedRay>,
    oct: ptr<function, u32>,
) -> u32 {
    if (k == 0u) {
        *node = escape_link;
        if (*node == BVH_NO_ESCAPE) {
            return bvh_escape_instance(node, r, oct);
        }
        return BVH_NEXT_ON;
    }
    if (k <= BVH_REGISTER_RING) {
        // Shifting a dry ring leaves it dry.
        let popped = (*newer).x;
        *newer = vec4<u32>((*newer).yzw, (*older).x);
        *older = vec4<u32>((*older).yzw, BVH_NO_ESCAPE);
        if (popped == BVH_NO_ESCAPE) {
            return select(BVH_NEXT_DONE, BVH_NEXT_ESCAPE, overflow);
        }
        *node = popped;
        bvh_leave_popped(*node, r, oct);
        return BVH_NEXT_ON;
    }
    if (*count == 0u) {
        return select(BVH_NEXT_DONE, BVH_NEXT_ESCAPE, overflow);
    }
    *count -= 1u;
    *top = select(*top - 1u, k - 1u, *top == 0u);
    *node = bvh_lane_stacks[bvh_stack_slot(lane, *top)];
    bvh_leave_popped(*node, r, oct);
    return BVH_NEXT_ON;
}

// A popped top-level node: back in world space and its octant.
fn bvh_leave_popped(node: u32, r: ptr<function, BvhPreparedRay>, oct: ptr<function, u32>) {
    if (bvh_leave_if_top(node, r)) {
        *oct = bvh_world_oct;
    }
}

// The walk escaped to `NO_ESCAPE`: done, or (inside an instance) back in world space at
// the instance leaf's escape link.
fn bvh_escape_instance(node: ptr<function, u32>, r: ptr<function, BvhPreparedRay>, oct: ptr<function, u32>) -> u32 {
    if (!(BVH_INSTANCED && bvh_inside)) {
        return BVH_NEXT_DONE;
    }
    bvh_leave_instance(r);
    *oct = bvh_world_oct;
    *node = bvh_load_escape(bvh_instance_leaf, *oct);
    return select(BVH_NEXT_ON, BVH_NEXT_DONE, *node == BVH_NO_ESCAPE);
}
