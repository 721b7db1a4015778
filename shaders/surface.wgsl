// Secondary rays: `bvhtrace_core::surface::offset_ray_origin` (Wächter and Binder, Ray
// Tracing Gems chapter 6), operation for operation, so a shadow or bounce ray traced from
// a hit point in a user's shader leaves its surface as the CPU's does.

const BVH_OFFSET_ORIGIN: f32 = 0.03125;
const BVH_OFFSET_FLOAT_SCALE: f32 = 1.52587890625e-5;
const BVH_OFFSET_INT_SCALE: f32 = 256.0;

// Moves the surface point `p` off the surface along `n` (the unit geometric normal, on the
// side the new ray leaves from): 256 n ulps per coordinate, or n / 65536 within 1/32 of 0.
fn bvh_offset_ray_origin(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let oi = vec3<i32>(BVH_OFFSET_INT_SCALE * n);
    let bits = bitcast<vec3<i32>>(p);
    let moved = bitcast<vec3<f32>>(select(bits + oi, bits - oi, p < vec3<f32>(0.0)));
    return select(moved, p + BVH_OFFSET_FLOAT_SCALE * n, abs(p) < vec3<f32>(BVH_OFFSET_ORIGIN));
}
