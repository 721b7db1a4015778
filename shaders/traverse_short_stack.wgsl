// traverse_short_stack.wgsl: twin of `bvhtrace_core::traverse::short_stack`.
//
// A ring buffer of `k` far-child entries (Hapala et al. 2011 with a short stack). Each node
// is tested when it is visited; an interior node sends the walk to its near child (by the
// sign of the ray's direction along the split axis) and pushes the far one, overwriting the
// oldest entry when the ring is full. When the ring runs dry after an overflow, the walk
// climbs the parent links from the last node to the first ancestor entered from its near
// side and continues with that ancestor's far child: exactly the dropped subtrees, in order.
//
// `k == 0` is the stackless walk: nothing is ever pushed and every subtree ends in a climb.
// There is no separate stackless kernel: it is this function specialised with k = 0 (the
// entry point passes the `SHORT_STACK_SIZE` override constant, so the compiler folds `k`).
// `k` is clamped to `1..=MAX_SHORT_STACK` by the host for `Traversal::ShortStack(k)`.

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

fn trace_short_stack(ray: Ray, any_hit: bool, k: u32) -> TraceResult {
    if (!ray_is_traced(ray)) {
        return untraced_result(ray);
    }
    let r = prepare_ray(ray);
    var best = start_best(ray);
    var c = Counters(0u, 0u);
    var ring: array<u32, MAX_SHORT_STACK>;
    var top = 0u; // next write slot
    var count = 0u; // live entries
    var overflow = false;
    var node = 0u;
    loop {
        let n = load_node(node);
        c.nodes += 1u;
        if (box_hit(intersect_box(r, n.min, n.max, best.t))) {
            if (node_count(n) == 0u) {
                let nf = near_far(r, node, vec2<u32>(n.right_or_first, n.meta_bits));
                if (k == 0u) {
                    overflow = true;
                } else {
                    if (count == k) {
                        overflow = true; // the oldest entry is overwritten
                    } else {
                        count += 1u;
                    }
                    ring[top] = nf.y;
                    top = select(top + 1u, 0u, top + 1u == k);
                }
                node = nf.x;
                continue;
            }
            if (visit_leaf(r, n.right_or_first, node_count(n), &best, &c, any_hit)) {
                break;
            }
        }
        // The subtree at `node` is done: take the next pending node.
        if (count > 0u) {
            top = select(top - 1u, k - 1u, top == 0u);
            count -= 1u;
            node = ring[top];
            continue;
        }
        if (!overflow) {
            break;
        }
        // Climb: the first ancestor entered from its near side has its far child pending.
        var resumed = false;
        loop {
            if (node == 0u) {
                break;
            }
            let p = load_parent(node);
            let nf = near_far(r, p, load_node_links(p));
            if (node == nf.x) {
                node = nf.y;
                resumed = true;
                break;
            }
            node = p;
        }
        if (!resumed) {
            break;
        }
    }
    return finish(best, c);
}
