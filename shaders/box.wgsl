// box.wgsl: the conservative slab test, twin of `bvhtrace_core::intersect::intersect_box`.

// `intersect::BOX_TFAR_SCALE` = 1 + 16u (bits 0x3f800008), above 1 + 2 gamma(7): the
// reciprocal in each slab distance is counted at Vulkan's 2.5 ulp, since GPUs divide
// approximately.
const BVH_BOX_TFAR_SCALE: f32 = 1.000001f;
// `intersect::BOX_TFAR_SCALE_NEG` = 1 - 17u (bits 0x3f7fffef): scales a negative exit
// distance (hits behind the origin) towards +inf, as BOX_TFAR_SCALE does a positive one.
const BVH_BOX_TFAR_SCALE_NEG: f32 = 0.999999f;

// `intersect::BOX_CULL_SLACK` = 64 u = 2^-18: the running best `t` is widened by this
// times the larger magnitude of the box's slab distances along the dominant axis `kz`
// (the error analysis is on the Rust constant). The ray's own `t_max` is never widened.
const BVH_BOX_CULL_SLACK: f32 = 3.814697265625e-6f;

// False when no ray of the batch has a zero (or subnormal) direction component
// (`bvhtrace_core::intersect::is_parallel_to_a_slab`): the parallel path below is then
// compiled out, which on a CPU driver, where both sides of a branch run, saves a tenth of
// every box test. A shader that traces arbitrary rays leaves it true.
override BVH_PARALLEL_RAYS: bool = true;

// The CPU's `fmin`/`fmax`: `if a < b { a } else { b }` (and `>`), not IEEE minNum.
fn bvh_fmin(a: f32, b: f32) -> f32 {
    return select(b, a, a < b);
}

fn bvh_fmax(a: f32, b: f32) -> f32 {
    return select(b, a, a > b);
}

// Entry and exit distances of the ray's `[t_min, t_best]` through the box, the far end
// widened for culling to `min(t_best + BOX_CULL_SLACK * m, r.t_max)`; the box is hit when
// `x <= y` (see `box_hit`). `t_best` is the best hit's `t`, or `t_max` before any hit.
// The entry distance orders the full-stack walk.
fn bvh_intersect_box(r: BvhPreparedRay, bmin: vec3<f32>, bmax: vec3<f32>, t_best: f32) -> vec2<f32> {
    var t0 = (bmin - r.org) * r.inv_dir;
    var t1 = (bmax - r.org) * r.inv_dir;
    if (BVH_PARALLEL_RAYS && r.parallel) {
        // Along an axis the ray does not move, it is inside the slab for every t (its
        // boundary included) or for none.
        let inf = vec3<f32>(bvh_infinity());
        let zero = r.dir == vec3<f32>(0.0);
        let inside = (bmin <= r.org) & (r.org <= bmax);
        t0 = select(t0, select(inf, -inf, inside), zero);
        t1 = select(t1, inf, zero);
    }
    let tnear = bvh_fmax(
        bvh_fmax(bvh_fmin(t0.x, t1.x), bvh_fmin(t0.y, t1.y)),
        bvh_fmax(bvh_fmin(t0.z, t1.z), r.t_min),
    );
    // `fmin` returns its second operand when the first is NaN: a NaN never culls.
    let m = bvh_fmax(abs(bvh_component(t0, r.kz)), abs(bvh_component(t1, r.kz)));
    let limit = bvh_fmin(t_best + BVH_BOX_CULL_SLACK * m, r.t_max);
    let tfar = bvh_fmin(
        bvh_fmin(bvh_fmax(t0.x, t1.x), bvh_fmax(t0.y, t1.y)),
        bvh_fmin(bvh_fmax(t0.z, t1.z), limit),
    );
    return vec2<f32>(tnear, tfar * select(BVH_BOX_TFAR_SCALE, BVH_BOX_TFAR_SCALE_NEG, tfar < 0.0));
}

fn bvh_box_hit(t: vec2<f32>) -> bool {
    return t.x <= t.y;
}
