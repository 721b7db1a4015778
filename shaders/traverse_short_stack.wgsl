// traverse_short_stack.wgsl: twin of `bvhtrace_core::traverse::short_stack`.
//
// A ring buffer of `k` far-child entries (Hapala et al. 2011 with a short stack): two
// registers for `k <= REGISTER_RING`, else `lane`'s first `k` entries in `lane_stacks`
// (`traverse_stack.wgsl`). As in
// the full stack, an interior node's two children are tested at the node, but taken in a
// deterministic near/far order (the sign of the ray's direction along the split axis): the
// near child when it is hit, the far one pushed when both are (overwriting the oldest entry
// when the ring is full). A popped node is not tested again. When the ring runs dry after
// an overflow, the walk climbs the parent links to the first ancestor it entered from the
// near side while the far child was hit, re-tests that far child and continues there when
// it is still hit: exactly the dropped subtrees, in order.
//
// A 32-bit trail (bit `i`: the ancestor `i + 1` levels up left its far child pending) lets
// the climb skip the other ancestors without a box test and ends the walk as soon as it is
// empty. Bits more than 32 levels up are lost and shifted back in as set; after a pop from
// the ring, the trail above the popped node is unknown and taken as all set.
//
// `k == 0` is the stackless walk: nothing is ever pushed and every subtree ends in a climb.
// There is no separate stackless kernel: it is this function specialised with k = 0 (the
// entry point passes the `SHORT_STACK_SIZE` override constant, so the compiler folds `k`).
// `k` is clamped to `1..=MAX_SHORT_STACK` by the host for `Traversal::ShortStack(k)`.
// Every loop trip, climb step included, takes one of the ray's `TRIP_LIMIT` trips.

// Near and far child of interior node `index` with links `(right_or_first, meta)`:
// `vec2(near, far)`.
fn near_far(r: PreparedRay, index: u32, links: vec2<u32>) -> vec2<u32> {
    let l = index + 1u;
    let rt = links.x;
    if (component(r.dir, links.y & 3u) >= 0.0) {
        return vec2<u32>(l, rt);
    }
    return vec2<u32>(rt, l);
}

// Rings of at most this many entries live in two `vec4<u32>` registers, pushed and popped
// by shifting (on lavapipe a shift is a few vector selects, while a `lane_stacks` access is
// a loop over the 8 lanes); larger rings in `lane_stacks`. `k` is an override constant, so
// the driver keeps one of the two.
const REGISTER_RING: u32 = 8u;

// The depth after a pop from the ring, where the trail above the popped node is unknown:
// at least 32, so that every bit the climb shifts in is set.
const DEPTH_UNKNOWN: u32 = 0x7fffffffu;

// The trail after a climb of one level to depth `depth`: bits of ancestors more than 32
// levels up were lost and come back set.
fn trail_up(trail: u32, depth: u32) -> u32 {
    return (trail >> 1u) | select(0u, 0x80000000u, depth >= 32u);
}

// What a climb did: the walk goes on at `node` (after testing its box: `CLIMB_TESTED`,
// `visit` says whether it was hit), the walk is back at the root and over, or the ray ran
// out of trips.
const CLIMB_ON: u32 = 0u;
const CLIMB_TESTED: u32 = 1u;
const CLIMB_DONE: u32 = 2u;
const CLIMB_OUT_OF_TRIPS: u32 = 3u;

// Climbs from `node`, whose subtree is done, to the nearest ancestor whose trail bit is
// set, and goes to that ancestor's far child when `node` is on its near side and the far
// child is (still) hit; otherwise that ancestor is done too (`visit` false).
fn climb(
    r: PreparedRay,
    best_t: f32,
    node: ptr<function, u32>,
    links: ptr<function, vec2<u32>>,
    trail: ptr<function, u32>,
    depth: ptr<function, u32>,
    visit: ptr<function, bool>,
) -> u32 {
    while ((*trail & 1u) == 0u) {
        if (!take_trip()) {
            return CLIMB_OUT_OF_TRIPS;
        }
        *depth -= 1u;
        *node = load_parent(*node);
        *trail = trail_up(*trail, *depth);
    }
    if (*node == 0u) {
        return CLIMB_DONE;
    }
    let p = load_parent(*node);
    let pnf = near_far(r, p, load_node_links(p));
    *trail &= ~1u;
    if (*node == pnf.x) {
        let sib = load_node(pnf.y);
        *visit = box_hit(intersect_box(r, sib.min, sib.max, best_t));
        *node = pnf.y;
        *links = vec2<u32>(sib.right_or_first, sib.meta_bits);
        return CLIMB_TESTED;
    }
    *visit = false;
    *depth -= 1u;
    *node = p;
    *trail = trail_up(*trail, *depth);
    return CLIMB_ON;
}

fn trace_short_stack(ray: Ray, any_hit: bool, k: u32, lane: u32) -> TraceResult {
    if (!ray_is_traced(ray)) {
        return untraced_result(ray);
    }
    let r = prepare_ray(ray);
    var best = start_best(ray);
    var c = Counters(0u, 0u);
    // The ring: in two registers when it fits (`k <= REGISTER_RING`), else in `lane_stacks`.
    var newer = vec4<u32>(0u); // entries 0..3, `newer.x` the top
    var older = vec4<u32>(0u); // entries 4..7
    var top = 0u; // next write slot in `lane_stacks`
    var count = 0u; // live entries
    var overflow = false;

    c.nodes += 1u;
    let root = load_node(0u);
    if (!box_hit(intersect_box(r, root.min, root.max, best.t))) {
        return finish(best, c);
    }
    var node = 0u;
    // `node`'s links, carried from where its box was loaded (its parent's step, the root,
    // the climb), so the inner loop loads only the two children.
    var links = vec2<u32>(root.right_or_first, root.meta_bits);
    var trail = 0u;
    var depth = 0u; // `node`'s
    // `visit`: `node`'s box was hit (at its parent, at the root or by the climb), visit it.
    // Otherwise `node`'s subtree is done.
    var visit = true;
    // For `k > 0` the climb runs in this loop, outside the walk's loops: a CPU driver runs
    // every loop body at least once for the whole SIMD batch, so a climb inside the outer
    // loop cost the short stack a quarter of its time (lavapipe, `bunny_69k`), on every
    // leaf and pop, although only a ring that overflowed and ran dry needs it. The
    // stackless walk (`k == 0`) climbs at the end of every subtree and keeps it inside.
    // Same order, counts and trips either way.
    loop {
        var climbing = false;
        // While-while, as in the full stack: the inner loop walks interior nodes until the
        // ray stands on a leaf or its subtree is done; the leaf is tested after it, so SIMD
        // lanes run box tests together and triangle tests together.
        loop {
            var leaf_first = 0u;
            var leaf_count = 0u;
            loop {
                if (!take_trip()) {
                    return incomplete(best, c);
                }
                if (!visit) {
                    break;
                }
                leaf_count = links.y >> 2u;
                if (leaf_count != 0u) {
                    leaf_first = links.x;
                    break;
                }
                let nf = near_far(r, node, links);
                c.nodes += 2u;
                let near_node = load_node(nf.x);
                let far_node = load_node(nf.y);
                let hit_near = box_hit(intersect_box(r, near_node.min, near_node.max, best.t));
                let hit_far = box_hit(intersect_box(r, far_node.min, far_node.max, best.t));
                if (!(hit_near || hit_far)) {
                    break;
                }
                let both = hit_near && hit_far;
                trail = (trail << 1u) | select(0u, 1u, both);
                depth += 1u;
                if (both && k > 0u) {
                    if (count == k) {
                        overflow = true; // the oldest entry is overwritten
                    } else {
                        count += 1u;
                    }
                    if (k <= REGISTER_RING) {
                        // Shift down one entry; the one pushed out is the oldest, past `k`.
                        older = vec4<u32>(newer.w, older.xyz);
                        newer = vec4<u32>(nf.y, newer.xyz);
                    } else {
                        lane_stacks[stack_slot(lane, top)] = nf.y;
                        top = select(top + 1u, 0u, top + 1u == k);
                    }
                }
                node = select(nf.y, nf.x, hit_near);
                links = select(
                    vec2<u32>(far_node.right_or_first, far_node.meta_bits),
                    vec2<u32>(near_node.right_or_first, near_node.meta_bits),
                    hit_near,
                );
            }
            if (leaf_count != 0u) {
                if (visit_leaf(r, leaf_first, leaf_count, &best, &c, any_hit)) {
                    break;
                }
                if (trips_left == 0u) {
                    return incomplete(best, c);
                }
            }
            // The subtree at `node` is done: take the next pending node.
            if (k > 0u && count > 0u) {
                count -= 1u;
                if (k <= REGISTER_RING) {
                    node = newer.x;
                    newer = vec4<u32>(newer.yzw, older.x);
                    older = vec4<u32>(older.yzw, 0u);
                } else {
                    top = select(top - 1u, k - 1u, top == 0u);
                    node = lane_stacks[stack_slot(lane, top)];
                }
                links = load_node_links(node);
                trail = 0xffffffffu;
                depth = DEPTH_UNKNOWN;
                visit = true;
                continue;
            }
            if (trail == 0u || (k > 0u && !overflow)) {
                break;
            }
            if (k > 0u) {
                climbing = true;
                break;
            }
            let step = climb(r, best.t, &node, &links, &trail, &depth, &visit);
            if (step == CLIMB_OUT_OF_TRIPS) {
                return incomplete(best, c);
            }
            if (step == CLIMB_DONE) {
                break;
            }
            c.nodes += select(0u, 1u, step == CLIMB_TESTED);
        }
        if (!climbing) {
            break;
        }
        let step = climb(r, best.t, &node, &links, &trail, &depth, &visit);
        if (step == CLIMB_OUT_OF_TRIPS) {
            return incomplete(best, c);
        }
        if (step == CLIMB_DONE) {
            break;
        }
        c.nodes += select(0u, 1u, step == CLIMB_TESTED);
    }
    return finish(best, c);
}
