// traverse_common.wgsl: what every traversal shares, twin of the helpers in
// `bvhtrace_core::traverse`: the best hit so far, the leaf visit with the hit rule, and
// the start and end of a ray.
//
// Hit rule: a triangle hit at `t` replaces the best one when `t_min <= t` and either
// `t < best.t`, or `t == best.t` and its primitive index is lower. `best.t` starts at
// `t_max`, so the interval is `[t_min, t_max)`.

// The trip budget: loop trips (box tests, triangle tests) a ray may take before it gives
// up with `INCOMPLETE`. Unbounded by default. Some drivers end every loop of an invocation
// silently after a fixed number of trips in all (lavapipe: 65,535 per 8-lane batch, over
// all its loops), which would return a wrong answer without a sign; the host sets a budget
// that stays under such a limit (`bvhtrace_gpu::trip_limit_for`, the bound on
// `CPU_DRIVER_TRIP_LIMIT`) and finishes the rays that exhaust it.
override BVH_TRIP_LIMIT: u32 = 0xffffffffu;

// Trips left to the current ray (set by `start_best`).
var<private> bvh_trips_left: u32;

// The triangle slot and the instance of the last hit a walk accepted, for the library's
// `bvh_hit_surface` (`library.wgsl`). The kernels never read them, so their compiler
// drops the stores.
var<private> bvh_hit_slot: u32;
var<private> bvh_hit_instance: u32;

// Takes one trip; false when the budget is spent. The walks then break out of their
// loops and answer `incomplete` after them. Why no `return` from inside the loops, no
// branch here and no check in the triangle loop's condition (`visit_leaf`): on lavapipe,
// where every lane runs every branch under a mask, those cost 7-15% of the whole walk
// (`gpu_bench`, builds run interleaved on `bunny_69k` and `igea`).
fn bvh_take_trip() -> bool {
    let ok = bvh_trips_left != 0u;
    bvh_trips_left -= select(0u, 1u, ok);
    return ok;
}

// The answer of a ray that spent its budget: `INCOMPLETE`, with the best `t` so far.
fn bvh_incomplete(best: BvhBest, c: BvhCounters) -> BvhTraceResult {
    return BvhTraceResult(BvhHit(best.t, BVH_INCOMPLETE, 0.0, 0.0), c);
}

struct BvhBest {
    t: f32,
    prim: u32,
    u: f32,
    v: f32,
    found: bool,
}

// Tests the triangles `first .. first + count` of a leaf; true when an any-hit query can
// stop.
fn bvh_visit_leaf(
    r: BvhPreparedRay,
    first: u32,
    count: u32,
    best: ptr<function, BvhBest>,
    c: ptr<function, BvhCounters>,
    any_hit: bool,
) -> bool {
    // The leaf's trips are taken together (as many as are left): a per-triangle budget
    // check in the loop's condition costs every trip on a CPU driver.
    let taken = min(count, bvh_trips_left);
    bvh_trips_left -= taken;
    let end = first + taken;
    for (var i = first; i < end; i += 1u) {
        (*c).tris += 1u;
        let tri = bvh_load_triangle(i);
        let h = bvh_intersect_triangle(r, tri.v0, tri.v1, tri.v2);
        let prim = bvh_hit_prim(tri.prim);
        // A masked BVH's alpha test and a library's filter ask about the candidate here
        // (`ModuleSet::files` puts them in at the mark).
        if (h.hit && (h.t < (*best).t || (h.t == (*best).t && (*best).found && prim < (*best).prim))/*BVH_ACCEPT*/) {
            *best = BvhBest(h.t, prim, h.u, h.v, true);
            bvh_hit_slot = i;
            bvh_hit_instance = bvh_instance_index;
            if (any_hit) {
                return true;
            }
        }
    }
    return false;
}

// The answer for a ray that is not traversed: invalid (`t` = `t_max`, or 0 when that is
// NaN), or an empty interval (a miss at `t_max`).
fn bvh_untraced_result(ray: BvhRay) -> BvhTraceResult {
    var out: BvhTraceResult;
    out.counters = BvhCounters(0u, 0u);
    if (!bvh_ray_is_valid(ray)) {
        let t = select(ray.t_max, 0.0, bvh_is_nan_f32(ray.t_max));
        out.hit = BvhHit(t, BVH_INVALID_RAY, 0.0, 0.0);
    } else {
        out.hit = BvhHit(ray.t_max, BVH_MISS, 0.0, 0.0);
    }
    return out;
}

// True when the ray is walked through the tree (valid, and `t_min <= t_max`).
fn bvh_ray_is_traced(ray: BvhRay) -> bool {
    return bvh_ray_is_valid(ray) && ray.t_min <= ray.t_max;
}

fn bvh_start_best(ray: BvhRay) -> BvhBest {
    bvh_trips_left = BVH_TRIP_LIMIT;
    return BvhBest(ray.t_max, BVH_MISS, 0.0, 0.0, false);
}

fn bvh_finish(best: BvhBest, c: BvhCounters) -> BvhTraceResult {
    var out: BvhTraceResult;
    out.counters = c;
    if (best.found) {
        out.hit = BvhHit(best.t, best.prim, best.u, best.v);
    } else {
        out.hit = BvhHit(best.t, BVH_MISS, 0.0, 0.0);
    }
    return out;
}
