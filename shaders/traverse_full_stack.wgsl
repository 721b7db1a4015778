// traverse_full_stack.wgsl: twin of `bvhtrace_core::traverse::full_stack`.
//
// Both children are tested at their parent; when both are hit, the one with the nearer
// entry distance is visited first and the other pushed. The stack holds at most `depth`
// entries (one per level of the current path), so `GpuBvh::upload` refuses trees deeper
// than `FULL_STACK_SIZE` for this traversal: it never overflows. Every loop trip takes one
// of the ray's `TRIP_LIMIT` trips (`traverse_common.wgsl`). The stack is `lane`'s in
// `lane_stacks` (`traverse_stack.wgsl`).

const BVH_FULL_STACK_SIZE: u32 = BVH_STACK_ENTRIES;

fn bvh_trace_full_stack(ray: BvhRay, any_hit: bool, lane: u32) -> BvhTraceResult {
    if (!bvh_ray_is_traced(ray)) {
        return bvh_untraced_result(ray);
    }
    var r = bvh_prepare_ray(ray);
    bvh_start_space(ray, r, 0u);
    var best = bvh_start_best(ray);
    var c = BvhCounters(0u, 0u);
    var sp = 0u;
    var spent = false; // the trip budget ran out

    c.nodes += 1u;
    let root = bvh_load_node(0u);
    if (!bvh_box_hit(bvh_intersect_box(r, root.min, root.max, best.t))) {
        return bvh_finish(best, c);
    }
    var node = 0u;
    // `node`'s links, carried from where its box was loaded (at its parent, or the root);
    // a node popped from the stack loads them in the outer loop.
    var links = vec2<u32>(root.right_or_first, root.meta_bits);
    // While-while (Aila and Laine 2009): the inner loop walks interior nodes until this
    // ray stands on a leaf (or is done); the leaf is tested after it. On SIMD hardware the
    // lanes then run the box tests together and the triangle tests together, instead of
    // both paths in every trip whenever one lane is on a leaf. Same visit order and counts.
    loop {
        var on_leaf = false;
        var count = 0u;
        var first = 0u;
        loop {
            if (!bvh_take_trip()) {
                spent = true;
                break;
            }
            count = links.y >> 2u;
            if (count != 0u) {
                if (bvh_is_instance_leaf(links.y)) {
                    // The mesh's root is walked as the leaf was: its box is not tested again.
                    let root = bvh_enter_instance(node, links.x, &r);
                    if (root == BVH_NOT_ENTERED) {
                        break;
                    }
                    node = root;
                    links = bvh_load_node_links(root);
                    continue;
                }
                first = links.x;
                on_leaf = true;
                break;
            }
            let l = node + 1u;
            let rt = links.x;
            c.nodes += 2u;
            let nl = bvh_load_node(l);
            let nr = bvh_load_node(rt);
            let hl = bvh_intersect_box(r, nl.min, nl.max, best.t);
            let hr = bvh_intersect_box(r, nr.min, nr.max, best.t);
            let ok_l = bvh_box_hit(hl);
            let ok_r = bvh_box_hit(hr);
            let links_l = vec2<u32>(nl.right_or_first, nl.meta_bits);
            let links_r = vec2<u32>(nr.right_or_first, nr.meta_bits);
            if (ok_l && ok_r) {
                var near = l;
                var far = rt;
                links = links_l;
                if (hr.x < hl.x) {
                    near = rt;
                    far = l;
                    links = links_r;
                }
                bvh_lane_stacks[bvh_stack_slot(lane, sp)] = far;
                sp += 1u;
                node = near;
                continue;
            }
            if (ok_l) {
                node = l;
                links = links_l;
                continue;
            }
            if (ok_r) {
                node = rt;
                links = links_r;
                continue;
            }
            // Neither child: the subtree is done; the outer loop pops.
            break;
        }
        if (on_leaf) {
            if (bvh_visit_leaf(r, first, count, &best, &c, any_hit)) {
                break;
            }
            if (bvh_trips_left == 0u) {
                spent = true;
                break;
            }
        }
        if (spent || sp == 0u) {
            break;
        }
        sp -= 1u;
        node = bvh_lane_stacks[bvh_stack_slot(lane, sp)];
        bvh_leave_if_top(node, &r);
        links = bvh_load_node_links(node);
    }
    if (spent) {
        return bvh_incomplete(best, c);
    }
    return bvh_finish(best, c);
}
