// bvh_ray_query_no_masks.wgsl: a BVH without alpha masks (`bvh_ray_query_masks.wgsl`'s
// names): every candidate is forced opaque, so the driver commits hits without asking.

const BVH_RAY_QUERY_OPAQUE: bool = true;

fn bvh_ray_query_accept(instance: u32, prim: u32, uv: vec2<f32>) -> bool {
    return true;
}
