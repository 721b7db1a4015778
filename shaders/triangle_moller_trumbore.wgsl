// triangle_moller_trumbore.wgsl: the Moller-Trumbore ray/triangle test in f32, not
// watertight, twin of `bvhtrace_core::precision::intersect_triangle_mt`
// operation for operation (glam's `cross` and `dot` written out in its order). Composed
// instead of `triangle.wgsl` for `Precision::MollerTrumboreF32`; same signature.

fn bvh_mt_cross(a: vec3<f32>, b: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(a.y * b.z - b.y * a.z, a.z * b.x - b.z * a.x, a.x * b.y - b.x * a.y);
}

fn bvh_mt_dot(a: vec3<f32>, b: vec3<f32>) -> f32 {
    return (a.x * b.x) + (a.y * b.y) + (a.z * b.z);
}

fn bvh_intersect_triangle(r: BvhPreparedRay, v0: vec3<f32>, v1: vec3<f32>, v2: vec3<f32>) -> BvhTriHit {
    var out = BvhTriHit(0.0, 0.0, 0.0, false);
    let e1 = v1 - v0;
    let e2 = v2 - v0;
    let p = bvh_mt_cross(r.dir, e2);
    let det = bvh_mt_dot(e1, p);
    if (det == 0.0) {
        return out;
    }
    let s = r.org - v0;
    let un = bvh_mt_dot(s, p);
    let q = bvh_mt_cross(s, e1);
    let vn = bvh_mt_dot(r.dir, q);
    // The division-free decision (see the CPU twin for why).
    var inside: bool;
    if (det > 0.0) {
        inside = un >= 0.0 && un <= det && vn >= 0.0 && un + vn <= det;
    } else {
        inside = un <= 0.0 && un >= det && vn <= 0.0 && un + vn >= det;
    }
    if (!inside) {
        return out;
    }
    let inv = 1.0 / det;
    let t = bvh_mt_dot(e2, q) * inv;
    // NaN fails this comparison and is rejected.
    if (!(t >= r.t_min)) {
        return out;
    }
    out.t = t;
    out.u = un * inv;
    out.v = vn * inv;
    out.hit = true;
    return out;
}
