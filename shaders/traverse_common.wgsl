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
override TRIP_LIMIT: u32 = 0xffffffffu;

// Trips left to the current ray (set by `start_best`).
var<private> trips_left: u32;

// Takes one trip; false when the budget is spent. The walks then break out of their
// loops and answer `incomplete` after them. Why no `return` from inside the loops, no
// branch here and no check in the triangle loop's condition (`visit_leaf`): on lavapipe,
// where every lane runs every branch under a mask, those cost 7-15% of the whole walk
// (`gpu_bench`, builds run interleaved on `bunny_69k` and `igea`).
fn take_trip() -> bool {
    let ok = trips_left != 0u;
    trips_left -= select(0u, 1u, ok);
    return ok;
}

// The answer of a ray that spent its budget: `INCOMPLETE`, with the best `t` so far.
fn incomplete(best: Best, c: Counters) -> TraceResult {
    return TraceResult(Hit(best.t, INCOMPLETE, 0.0, 0.0), c);
}

struct Best {
    t: f32,
    prim: u32,
    u: f32,
    v: f32,
    found: bool,
}

// Tests the triangles `first .. first + count` of a leaf; true when an any-hit query can
// stop.
fn visit_leaf(
    r: PreparedRay,
    first: u32,
    count: u32,
    best: ptr<function, Best>,
    c: ptr<function, Counters>,
    any_hit: bool,
) -> bool {
    // The leaf's trips are taken together (as many as are left): a per-triangle budget
    // check in the loop's condition costs every trip on a CPU driver.
    let taken = min(count, trips_left);
    trips_left -= taken;
    let end = first + taken;
    for (var i = first; i < end; i += 1u) {
        (*c).tris += 1u;
        let tri = load_triangle(i);
        let h = intersect_triangle(r, tri.v0, tri.v1, tri.v2);
        if (h.hit && (h.t < (*best).t || (h.t == (*best).t && (*best).found && tri.prim < (*best).prim))) {
            *best = Best(h.t, tri.prim, h.u, h.v, true);
            if (any_hit) {
                return true;
            }
        }
    }
    return false;
}

// The answer for a ray that is not traversed: invalid (`t` = `t_max`, or 0 when that is
// NaN), or an empty interval (a miss at `t_max`).
fn untraced_result(ray: Ray) -> TraceResult {
    var out: TraceResult;
    out.counters = Counters(0u, 0u);
    if (!ray_is_valid(ray)) {
        let t = select(ray.t_max, 0.0, is_nan_f32(ray.t_max));
        out.hit = Hit(t, INVALID_RAY, 0.0, 0.0);
    } else {
        out.hit = Hit(ray.t_max, MISS, 0.0, 0.0);
    }
    return out;
}

// True when the ray is walked through the tree (valid, and `t_min <= t_max`).
fn ray_is_traced(ray: Ray) -> bool {
    return ray_is_valid(ray) && ray.t_min <= ray.t_max;
}

fn start_best(ray: Ray) -> Best {
    trips_left = TRIP_LIMIT;
    return Best(ray.t_max, MISS, 0.0, 0.0, false);
}

fn finish(best: Best, c: Counters) -> TraceResult {
    var out: TraceResult;
    out.counters = c;
    if (best.found) {
        out.hit = Hit(best.t, best.prim, best.u, best.v);
    } else {
        out.hit = Hit(best.t, MISS, 0.0, 0.0);
    }
    return out;
}
