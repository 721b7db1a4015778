// bvh_ray_query_masks.wgsl: the alpha masks for `bvh_ray_query.wgsl`, composed after
// `bvh_alpha_masks.wgsl` (binding 5) only when the uploaded BVH has them. The masked
// meshes' BLASes are built without the opaque flag, so the driver hands each of their
// candidates to `bvh_ray_query_accept`, which puts it to the walks' own test,
// `bvh_alpha_accept`, at the driver's barycentrics. `bvh_ray_query_no_masks.wgsl` forces
// every candidate opaque instead.

const BVH_RAY_QUERY_OPAQUE: bool = false;

// The instance `bvh_alpha_accept` reads its instance base by: the walks' name for the
// instance being visited, set here from the candidate's TLAS instance (one per
// `FlatBvh::instances` entry, in that order).
var<private> bvh_instance_index: u32;

// Whether a candidate on mesh primitive `prim` of TLAS instance `instance`, at the
// driver's barycentrics `uv` (of corners 1 and 2), counts as a hit.
fn bvh_ray_query_accept(instance: u32, prim: u32, uv: vec2<f32>) -> bool {
    bvh_instance_index = instance;
    return bvh_alpha_accept(prim, uv.x, uv.y);
}
