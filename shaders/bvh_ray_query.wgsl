// bvh_ray_query.wgsl: the device's own acceleration structure walked by its ray queries
// (`enable wgpu_ray_query;`, composed first), in place of our walks. Binding 0 is the TLAS
// (`bvhtrace_gpu::RayQueryBvh`: one instance per `FlatBvh` instance, or one identity
// instance for one mesh); each BLAS is a mesh's triangles, read straight from the triangle
// buffer (binding 1, 16-byte vertex stride over `FlatTriangle`), so a BLAS primitive index
// is a slot in that buffer after the mesh's first (binding 2, by the TLAS instance's custom
// data; absent for one mesh, whose first slot is 0).
//
// The same answer as our walks under a stated rule, not bit for bit: the driver's triangle
// test is its own, and its interval is closed, `[t_min, t_max]`. Rays our walks call invalid
// are answered `BVH_INVALID_RAY` without a query, and `t_min` below 0 is taken as 0 (the
// queries' interval cannot start behind the origin).
//
// Alpha masks: `bvh_ray_query_masks.wgsl` or `bvh_ray_query_no_masks.wgsl` (composed with
// this file) says whether every candidate is opaque (`BVH_RAY_QUERY_OPAQUE`) and which
// candidates count (`bvh_ray_query_accept`). A masked candidate is decided at the driver's
// barycentrics, so it may be decided otherwise than on our walks where it lies on a texel
// border.

const BVH_WIDE_LAYOUT: bool = false;

@group(0) @binding(0) var bvh_tlas: acceleration_structure;

// The visibility mask of two-level rays (`TraceOptions::mask`); one mesh ignores it, as
// our walks do.
override BVH_RAY_MASK: u32 = 0xffu;
// The walks' other overrides, declared so that a host sets the same constants for either
// library; the driver's walk has no trip budget and no parallel-ray path to leave out.
override BVH_TRIP_LIMIT: u32 = 0xffffffffu;
override BVH_PARALLEL_RAYS: bool = true;

// The triangle slot and the instance of the last hit, for the library's `bvh_hit_surface`.
var<private> bvh_hit_slot: u32;
var<private> bvh_hit_instance: u32;

// The largest finite f32: the queries' `t_max` must be finite on some drivers.
const BVH_MAX_F32: f32 = 3.40282347e38;

// Closest (`any_hit` false) or any hit of `ray`, as our walks' `BvhTraceResult` (counters
// zero: the driver's walk is not counted).
fn bvh_trace_ray_query(ray: BvhRay, any_hit: bool) -> BvhTraceResult {
    let none = BvhCounters(0u, 0u);
    if (!bvh_ray_is_valid(ray)) {
        return BvhTraceResult(BvhHit(ray.t_max, BVH_INVALID_RAY, 0.0, 0.0), none);
    }
    let t_min = max(ray.t_min, 0.0);
    let t_max = min(ray.t_max, BVH_MAX_F32);
    if (!(t_min < t_max)) {
        return BvhTraceResult(BvhHit(ray.t_max, BVH_MISS, 0.0, 0.0), none);
    }
    // Without masks every triangle is forced opaque: the driver commits its hits itself.
    var flags = RAY_FLAG_NONE;
    if (BVH_RAY_QUERY_OPAQUE) {
        flags = RAY_FLAG_FORCE_OPAQUE;
    }
    // For any hit the first confirmed candidate ends the query, as the first opaque one does.
    if (any_hit) {
        flags |= RAY_FLAG_TERMINATE_ON_FIRST_HIT;
    }
    let mask = select(0xffu, BVH_RAY_MASK & 0xffu, BVH_INSTANCED);
    var rq: ray_query;
    rayQueryInitialize(&rq, bvh_tlas, RayDesc(flags, mask, t_min, t_max, ray.origin, ray.dir));
    // Only the masked meshes' triangles (not opaque) stop here as candidates; the driver
    // hands over those within the interval left by the hits confirmed so far.
    while (rayQueryProceed(&rq)) {
        let c = rayQueryGetCandidateIntersection(&rq);
        if (c.kind != RAY_QUERY_INTERSECTION_TRIANGLE) {
            continue;
        }
        let at = bvh_mesh_first(c.instance_custom_data) + c.primitive_index;
        if (bvh_ray_query_accept(c.instance_index, bvh_load_triangle(at).prim, c.barycentrics)) {
            rayQueryConfirmIntersection(&rq);
        }
    }
    let x = rayQueryGetCommittedIntersection(&rq);
    if (x.kind == RAY_QUERY_INTERSECTION_NONE) {
        return BvhTraceResult(BvhHit(ray.t_max, BVH_MISS, 0.0, 0.0), none);
    }
    let slot = bvh_mesh_first(x.instance_custom_data) + x.primitive_index;
    bvh_hit_slot = slot;
    bvh_hit_instance = x.instance_index;
    var prim = bvh_load_triangle(slot).prim;
    if (BVH_INSTANCED) {
        prim += bvh_load_instance(x.instance_index).prim_base;
    }
    return BvhTraceResult(BvhHit(x.t, prim, x.barycentrics.x, x.barycentrics.y), none);
}
