// library.wgsl: the traversal library's calls for your own shader, the same for every
// upload (one mesh or two levels, binary or wide layout, buffers or textures). Composed
// after the library's files by `BvhLibrary` (`bvhtrace_engine::wgsl`), which replaces
// `BVH_LIBRARY_CLOSEST` and `BVH_LIBRARY_ANY` with the call of the walk it was composed
// for (`ray`, `lane` and the query passed on, `k` for the short stack).

// The closest hit of `ray` (`prim` is `BVH_MISS` for none); `lane` is the invocation's
// `local_invocation_index` (the walks' stacks live in workgroup memory).
fn bvh_trace_closest(ray: BvhRay, lane: u32) -> BvhTraceResult {
    return BVH_LIBRARY_CLOSEST;
}

// Some hit of `ray` in its interval, found by the first triangle that answers: for shadow
// and occlusion rays.
fn bvh_trace_any(ray: BvhRay, lane: u32) -> BvhTraceResult {
    return BVH_LIBRARY_ANY;
}

// Where secondary rays leave a hit (`bvhtrace_core::surface::SurfacePoint`): the origin
// moved off the surface to the incoming ray's side, and the unit geometric normal facing
// that side, both in world space.
struct BvhSurface {
    origin: vec3<f32>,
    normal: vec3<f32>,
}

// The instance (its index in `FlatBvh::instances`) of the hit the invocation's last
// `bvh_trace_*` call returned; 0 for one mesh. Read it before the next trace. The wide
// layout holds the instances in its top level's leaf order, so there the index is found
// by counting the instances numbered before it (primitive ids are numbered instance by
// instance, and every instance has primitives): a loop over the instances.
fn bvh_hit_instance_index() -> u32 {
    if (!BVH_INSTANCED) {
        return 0u;
    }
    if (!BVH_WIDE_LAYOUT) {
        return bvh_hit_instance;
    }
    let base = bvh_load_instance(bvh_hit_instance).prim_base;
    var before = 0u;
    for (var j = 0u; j < bvh_instance_count(); j += 1u) {
        before += select(0u, 1u, bvh_load_instance(j).prim_base < base);
    }
    return before;
}

// That instance's user id (`Instance::user_id`); 0 for one mesh.
fn bvh_hit_user_id() -> u32 {
    if (BVH_INSTANCED) {
        return bvh_load_instance(bvh_hit_instance).user_id;
    }
    return 0u;
}

// The primitive of `hit` (the last call's) within its instance's mesh: `hit.prim` less
// the instance's first id; `hit.prim` for one mesh.
fn bvh_hit_mesh_prim(hit: BvhHit) -> u32 {
    if (BVH_INSTANCED) {
        return hit.prim - bvh_load_instance(bvh_hit_instance).prim_base;
    }
    return hit.prim;
}

// `FlatInstance::normal_to_world`: the transpose of `world_to_object` times `n`, product
// by product, left to right.
fn bvh_normal_to_world(inst: BvhInstance, n: vec3<f32>) -> vec3<f32> {
    let m = inst.world_to_object;
    return vec3<f32>(
        m[0].x * n.x + m[1].x * n.y + m[2].x * n.z,
        m[0].y * n.x + m[1].y * n.y + m[2].y * n.z,
        m[0].z * n.x + m[1].z * n.y + m[2].z * n.z,
    );
}

// `a x b` as glam's `Vec3::cross` computes it.
fn bvh_cross(a: vec3<f32>, b: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(a.y * b.z - b.y * a.z, a.z * b.x - b.z * a.x, a.x * b.y - b.x * a.y);
}

// `v . v` as glam's `Vec3::length_squared`.
fn bvh_length_squared(v: vec3<f32>) -> f32 {
    return v.x * v.x + v.y * v.y + v.z * v.z;
}

// `v` normalised as glam's `Vec3::normalize`: times `1 / sqrt(v . v)`.
fn bvh_normalize(v: vec3<f32>) -> vec3<f32> {
    let r = 1.0 / sqrt(bvh_length_squared(v));
    return vec3<f32>(v.x * r, v.y * r, v.z * r);
}

// The tail of `surface::facing_normal`: `n` normalised and turned against `dir`; `-dir`
// normalised for a zero `n`.
fn bvh_face_against(n: vec3<f32>, dir: vec3<f32>) -> vec3<f32> {
    var f = -bvh_normalize(dir);
    if (bvh_length_squared(n) > 0.0) {
        f = bvh_normalize(n);
    }
    let d = f.x * dir.x + f.y * dir.y + f.z * dir.z;
    return select(f, -f, d > 0.0);
}

// Where secondary rays leave `hit`, the answer of the invocation's last `bvh_trace_*`
// call for `ray` (world space). One mesh: `Hit::surface`, operation for operation (the
// point from the barycentrics). Two levels: `bvhtrace_core::hits::instance_surface` (the
// object-space normal taken to world space, the point `origin + t dir`). Only for a hit
// (`hit.prim` not a miss code).
fn bvh_hit_surface(ray: BvhRay, hit: BvhHit) -> BvhSurface {
    let tri = bvh_load_triangle(bvh_hit_slot);
    let e1 = tri.v1 - tri.v0;
    let e2 = tri.v2 - tri.v0;
    var n: vec3<f32>;
    var p: vec3<f32>;
    if (BVH_INSTANCED) {
        n = bvh_face_against(bvh_normal_to_world(bvh_load_instance(bvh_hit_instance), bvh_cross(e1, e2)), ray.dir);
        p = vec3<f32>(ray.origin.x + ray.dir.x * hit.t, ray.origin.y + ray.dir.y * hit.t, ray.origin.z + ray.dir.z * hit.t);
    } else {
        n = bvh_face_against(bvh_cross(e1, e2), ray.dir);
        let w = 1.0 - hit.u - hit.v;
        p = tri.v0 * w + tri.v1 * hit.u + tri.v2 * hit.v;
    }
    return BvhSurface(bvh_offset_ray_origin(p, n), n);
}
