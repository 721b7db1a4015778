// traverse_instances.wgsl: entering and leaving instances, twin of `Space` in
// `bvhtrace_core::traverse` (the two-level layout is described in `bvhtrace_core::flat`).
//
// A walk standing on a top-level leaf whose box it hits enters the leaf's instance: the
// ray is transformed into the mesh's space (`t` keeps its parametrisation) and the walk
// goes on at the mesh's root. It leaves when its next node is a top-level one again
// (popped), or, for the walks with escape links, when the mesh's walk escapes to
// `NO_ESCAPE` (it goes on at the instance leaf's link). Hits report `prim_base + prim`.
// The state is per invocation (`var<private>`), so the walks keep their signatures.
// With `bvh_no_instances.wgsl`, `BVH_INSTANCED` is false and all of it folds away.

// The rays' visibility mask (`TraceOptions::mask`): an instance whose mask shares no bit
// with it is passed through.
override BVH_RAY_MASK: u32 = 0xffu;

// An instance not entered (masked out, or its transformed ray not valid).
const BVH_NOT_ENTERED: u32 = 0xffffffffu;

var<private> bvh_world_ray: BvhRay;
var<private> bvh_world: BvhPreparedRay;
var<private> bvh_world_oct: u32;
var<private> bvh_inside: bool;
var<private> bvh_prim_base: u32;
// The top-level leaf of the instance the walk is in.
var<private> bvh_instance_leaf: u32;
// The index (in `bvh_instances`) of the instance the walk is in.
var<private> bvh_instance_index: u32;

// Called once per ray, before the walk, with the ray and its preparation.
fn bvh_start_space(ray: BvhRay, r: BvhPreparedRay, oct: u32) {
    if (BVH_INSTANCED) {
        bvh_world_ray = ray;
        bvh_world = r;
        bvh_world_oct = oct;
        bvh_inside = false;
        bvh_prim_base = 0u;
    }
}

// True for a top-level leaf (called on leaves: `meta_bits >> 2 != 0`).
fn bvh_is_instance_leaf(meta_bits: u32) -> bool {
    return BVH_INSTANCED && (meta_bits & 3u) == 3u;
}

// `FlatInstance::ray_to_object`, product by product, left to right.
fn bvh_row_point(m: vec4<f32>, p: vec3<f32>) -> f32 {
    return m.x * p.x + m.y * p.y + m.z * p.z + m.w;
}

fn bvh_row_vector(m: vec4<f32>, d: vec3<f32>) -> f32 {
    return m.x * d.x + m.y * d.y + m.z * d.z;
}

fn bvh_ray_to_object(inst: BvhInstance, ray: BvhRay) -> BvhRay {
    let m = inst.world_to_object;
    let o = vec3<f32>(bvh_row_point(m[0], ray.origin), bvh_row_point(m[1], ray.origin), bvh_row_point(m[2], ray.origin));
    let d = vec3<f32>(bvh_row_vector(m[0], ray.dir), bvh_row_vector(m[1], ray.dir), bvh_row_vector(m[2], ray.dir));
    return BvhRay(o, ray.t_min, d, ray.t_max);
}

// Enters instance `index` of top-level leaf `leaf`: `*r` becomes the ray in the mesh's
// space and the mesh's root is returned; `BVH_NOT_ENTERED` when it is passed through.
fn bvh_enter_instance(leaf: u32, index: u32, r: ptr<function, BvhPreparedRay>) -> u32 {
    let inst = bvh_load_instance(index);
    if ((inst.mask & BVH_RAY_MASK) == 0u) {
        return BVH_NOT_ENTERED;
    }
    let object = bvh_ray_to_object(inst, bvh_world_ray);
    if (!bvh_ray_is_valid(object)) {
        return BVH_NOT_ENTERED;
    }
    *r = bvh_prepare_ray(object);
    bvh_inside = true;
    bvh_prim_base = inst.prim_base;
    bvh_instance_leaf = leaf;
    bvh_instance_index = index;
    return inst.root;
}

fn bvh_leave_instance(r: ptr<function, BvhPreparedRay>) {
    *r = bvh_world;
    bvh_inside = false;
    bvh_prim_base = 0u;
}

// Back in world space when the walk's next node is a top-level one; true when it left.
fn bvh_leave_if_top(node: u32, r: ptr<function, BvhPreparedRay>) -> bool {
    if (BVH_INSTANCED && bvh_inside && node < bvh_top_nodes()) {
        bvh_leave_instance(r);
        return true;
    }
    return false;
}

// The id a hit on a mesh's primitive `p` reports.
fn bvh_hit_prim(p: u32) -> u32 {
    if (BVH_INSTANCED) {
        return bvh_prim_base + p;
    }
    return p;
}
