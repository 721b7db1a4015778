// ray.wgsl: ray validity and per-ray precomputation, twin of
// `bvhtrace_core::ray::Ray::is_valid` and `bvhtrace_core::intersect::PreparedRay::new`.
//
// Validity and zero tests look at the bits, so they hold even where the device flushes
// subnormals to zero.

struct BvhPreparedRay {
    org: vec3<f32>,
    // Direction, subnormal components flushed to signed zero.
    dir: vec3<f32>,
    inv_dir: vec3<f32>,
    // Some direction component is zero: `intersect_box` takes its general path.
    parallel: bool,
    t_min: f32,
    // The ray's own `t_max`: the cap of the widened culling bound (`box.wgsl`).
    t_max: f32,
    kx: u32,
    ky: u32,
    kz: u32,
    sx: f32,
    sy: f32,
    sz: f32,
}

// +infinity, made from a `let` so that it is computed at run time: a constant expression
// that evaluates to infinity is an error in WGSL (Chrome's compiler refuses the module;
// naga lets it through).
fn bvh_infinity() -> f32 {
    let bits = 0x7f800000u;
    return bitcast<f32>(bits);
}

fn bvh_is_finite_f32(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn bvh_is_nan_f32(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) > 0x7f800000u;
}

fn bvh_is_zero_f32(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) == 0u;
}

// `Ray::is_valid`: finite origin and direction, non-zero direction, no NaN interval end.
fn bvh_ray_is_valid(ray: BvhRay) -> bool {
    let o = ray.origin;
    let d = ray.dir;
    return bvh_is_finite_f32(o.x) && bvh_is_finite_f32(o.y) && bvh_is_finite_f32(o.z)
        && bvh_is_finite_f32(d.x) && bvh_is_finite_f32(d.y) && bvh_is_finite_f32(d.z)
        && !(bvh_is_zero_f32(d.x) && bvh_is_zero_f32(d.y) && bvh_is_zero_f32(d.z))
        && !bvh_is_nan_f32(ray.t_min) && !bvh_is_nan_f32(ray.t_max);
}

// `intersect::safe_inverse`: `1/d`, with a zero or subnormal `d` taken as
// `±f32::MIN_POSITIVE` (sign kept).
fn bvh_safe_inverse(d: f32) -> f32 {
    let bits = bitcast<u32>(d);
    var x = d;
    if ((bits & 0x7fffffffu) < 0x00800000u) {
        x = bitcast<f32>((bits & 0x80000000u) | 0x00800000u);
    }
    return 1.0 / x;
}

// `intersect::flush_subnormal`: `d`, or a zero of the same sign when `d` is subnormal.
fn bvh_flush_subnormal(d: f32) -> f32 {
    let bits = bitcast<u32>(d);
    if ((bits & 0x7fffffffu) < 0x00800000u) {
        return bitcast<f32>(bits & 0x80000000u);
    }
    return d;
}

// `PreparedRay::new` for a valid ray.
fn bvh_prepare_ray(ray: BvhRay) -> BvhPreparedRay {
    let d = vec3<f32>(
        bvh_flush_subnormal(ray.dir.x),
        bvh_flush_subnormal(ray.dir.y),
        bvh_flush_subnormal(ray.dir.z),
    );
    let a = abs(d);
    // Dominant axis; ties go to the lower axis.
    var kz = 2u;
    if (a.x >= a.y && a.x >= a.z) {
        kz = 0u;
    } else if (a.y >= a.z) {
        kz = 1u;
    }
    var kx = kz + 1u;
    if (kx == 3u) {
        kx = 0u;
    }
    var ky = kx + 1u;
    if (ky == 3u) {
        ky = 0u;
    }
    let dz = bvh_component(d, kz);
    // Keep the winding: swap when the dominant component is negative.
    if (dz < 0.0) {
        let s = kx;
        kx = ky;
        ky = s;
    }
    var p: BvhPreparedRay;
    p.org = ray.origin;
    p.dir = d;
    p.inv_dir = vec3<f32>(bvh_safe_inverse(d.x), bvh_safe_inverse(d.y), bvh_safe_inverse(d.z));
    p.parallel = d.x == 0.0 || d.y == 0.0 || d.z == 0.0;
    p.t_min = ray.t_min;
    p.t_max = ray.t_max;
    p.kx = kx;
    p.ky = ky;
    p.kz = kz;
    p.sx = bvh_component(d, kx) / dz;
    p.sy = bvh_component(d, ky) / dz;
    p.sz = 1.0 / dz;
    return p;
}

// The ray's octant (`bvhtrace_core::flat::octant`): bit `a` set when direction component
// `a` is not `>= 0`. It orders the walks: an interior node split along `a` is entered on
// its second child first when bit `a` is set (`traverse_short_stack.wgsl`), and a wide
// node's children are visited in the order of `slot ^ octant` (`traverse_wide.wgsl`).
fn bvh_octant(d: vec3<f32>) -> u32 {
    return select(0u, 1u, !(d.x >= 0.0)) | select(0u, 2u, !(d.y >= 0.0)) | select(0u, 4u, !(d.z >= 0.0));
}
