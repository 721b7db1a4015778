// curve.wgsl: a ray against one curve segment, twin of `bvhtrace_core::curves`
// (`Curves::intersect`, `linear.rs`, `cubic.rs`): Embree 3's round and flat linear
// segments and round cubic (Bezier, B-spline) curves, solved relative to the segment's
// first point and scaled by powers of two, step for step as the CPU solves them.
//
// The kind is `BVH_CURVE_KIND` (0 round linear, 1 flat linear, 2 round Bezier, 3 round
// B-spline: `CurveKind::ALL`'s order). Composed with `bvh_curve_buffers.wgsl`, whose
// `bvh_curve_point` and `bvh_curve_segment` it reads.

override BVH_CURVE_KIND: u32 = 0u;

const BVH_F32_EPSILON: f32 = 1.1920929e-7;
// Embree's factor for flat curves (`linear::SELF_INTERSECTION_AVOIDANCE`).
const BVH_SELF_INTERSECTION_AVOIDANCE: f32 = 2.0;
// The cubic cut: pieces per level, levels, Newton steps (`cubic.rs`).
const BVH_CURVE_PIECES: u32 = 7u;
const BVH_CURVE_LEVELS: u32 = 2u;
const BVH_NEWTON_STEPS: u32 = 5u;

fn bvh_length(v: vec3<f32>) -> f32 {
    return sqrt(dot(v, v));
}

fn bvh_unit(v: vec3<f32>) -> vec3<f32> {
    let l = bvh_length(v);
    if (l > 0.0) {
        return v * (1.0 / l);
    }
    return vec3<f32>(0.0);
}

fn bvh_max3(v: vec3<f32>) -> f32 {
    return max(max(v.x, v.y), v.z);
}

// `2^e` from its bits (`curves::pow2`).
fn bvh_pow2(e: i32) -> f32 {
    return bitcast<f32>(u32(e + 127) << 23u);
}

// Twin of `curves::unit_exponent_of`.
fn bvh_unit_exponent_of(x: f32) -> i32 {
    let biased = i32((bitcast<u32>(x) >> 23u) & 0xffu);
    if (x > 0.0 && biased >= 1 && biased < 255) {
        return clamp(127 - biased, -126, 126);
    }
    return 0;
}

// ---- Flat linear: `linear::flat_linear` in the ray space of `linear::RaySpace`. ----

struct BvhRaySpace {
    x: vec3<f32>,
    y: vec3<f32>,
    z: vec3<f32>,
    depth_scale: f32,
}

fn bvh_ray_space(dir: vec3<f32>) -> BvhRaySpace {
    let depth_scale = 1.0 / sqrt(dot(dir, dir));
    let n = dir * depth_scale;
    let a = vec3<f32>(0.0, n.z, -n.y);
    let b = vec3<f32>(-n.z, 0.0, n.x);
    let x = bvh_unit(select(b, a, dot(a, a) > dot(b, b)));
    let y = bvh_unit(cross(n, x));
    return BvhRaySpace(x, y, n * depth_scale, depth_scale);
}

fn bvh_apply_space(s: BvhRaySpace, p: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(dot(s.x, p), dot(s.y, p), dot(s.z, p));
}

fn bvh_flat_linear(org: vec3<f32>, s: BvhRaySpace, range: vec2<f32>, v0: vec4<f32>, v1: vec4<f32>) -> BvhTriHit {
    var out = BvhTriHit(0.0, 0.0, 0.0, false);
    let p0 = vec4<f32>(bvh_apply_space(s, v0.xyz - org), v0.w);
    let p1 = vec4<f32>(bvh_apply_space(s, v1.xyz - org), v1.w);
    let v = p1 - p0;
    let d0 = -p0.x * v.x - p0.y * v.y;
    let d1 = v.x * v.x + v.y * v.y;
    var u = 0.0;
    if (d1 > 0.0) {
        u = clamp(d0 / d1, 0.0, 1.0);
    }
    let p = p0 + u * v;
    let t = p.z;
    let r = p.w;
    let near_enough = p.x * p.x + p.y * p.y <= r * r;
    let inside = range.x <= t && t <= range.y;
    let not_self = t > BVH_SELF_INTERSECTION_AVOIDANCE * r * s.depth_scale;
    let tangent = (v1 - v0).xyz;
    if (near_enough && inside && not_self && any(tangent != vec3<f32>(0.0))) {
        out = BvhTriHit(t, u, 0.0, true);
    }
    return out;
}

// ---- Round linear: `linear::round_linear`, Embree's cone between spheres. ----

struct BvhCone {
    p0: vec3<f32>,
    p1: vec3<f32>,
    dp: vec3<f32>,
    dpdp: f32,
    r0: f32,
    r1: f32,
    r0dr: f32,
    g: f32,
}

fn bvh_cone(a: vec4<f32>, b: vec4<f32>) -> BvhCone {
    let dp = b.xyz - a.xyz;
    let dr = b.w - a.w;
    let dpdp = dot(dp, dp);
    return BvhCone(a.xyz, b.xyz, dp, dpdp, a.w, b.w, a.w * dr, dpdp - dr * dr);
}

// A cone to an absent neighbour (its far point is infinite) holds and clips nothing.
fn bvh_cone_exists(c: BvhCone) -> bool {
    return !bvh_is_inf_f32(c.p0.x) && !bvh_is_inf_f32(c.p1.x) && c.p0.x == c.p0.x && c.p1.x == c.p1.x;
}

fn bvh_is_inf_f32(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) == 0x7f800000u;
}

fn bvh_cone_clips(c: BvhCone, p: vec3<f32>) -> bool {
    return bvh_cone_exists(c) && dot(p - c.p0, c.dp) > -c.r0dr;
}

fn bvh_cone_holds(c: BvhCone, p: vec3<f32>) -> bool {
    let p0p = p - c.p0;
    let y = dot(p0p, c.dp);
    let dr = c.r1 - c.r0;
    return bvh_cone_exists(c) && y > -c.r0dr + BVH_F32_EPSILON && y < -c.r1 * dr + c.dpdp
        && dot(p0p, p0p) * c.g - y * y < c.dpdp * c.r0 * c.r0 + 2.0 * c.r0dr * y;
}

// A sphere's two crossings (near, far), or an empty pair (+inf, -inf).
fn bvh_sphere(org: vec3<f32>, dir: vec3<f32>, rcp_dd: f32, c: vec3<f32>, r: f32) -> vec3<f32> {
    let o = org - c;
    let od = dot(o, dir);
    let h2 = od * od - dot(dir, dir) * (dot(o, o) - r * r);
    if (h2 >= 0.0) {
        let q = sqrt(h2);
        return vec3<f32>((-od - q) * rcp_dd, (-od + q) * rcp_dd, 1.0);
    }
    return vec3<f32>(0.0, 0.0, 0.0);
}

fn bvh_round_linear(
    org_in: vec3<f32>,
    dir: vec3<f32>,
    range: vec2<f32>,
    v0: vec4<f32>,
    v1: vec4<f32>,
    vl: vec4<f32>,
    vr: vec4<f32>,
    has_left: bool,
) -> BvhTriHit {
    let none = BvhTriHit(0.0, 0.0, 0.0, false);
    let inf = bvh_infinity();
    let dd = dot(dir, dir);
    let rcp_dd = 1.0 / dd;
    let center = 0.5 * (v0.xyz + v1.xyz);
    let dt = dot(center - org_in, dir) * rcp_dd;
    let org = org_in + dt * dir;
    let cone = bvh_cone(v0, v1);
    let o = org - cone.p0;
    let odp = dot(cone.dp, o);
    let ddp = dot(cone.dp, dir);
    let yp = odp + cone.r0dr;
    let left = bvh_cone(v0, vl);
    let right = bvh_cone(v1, vr);
    var cone_x = vec2<f32>(inf, -inf);
    var start_x = vec2<f32>(inf, -inf);
    var end_x = vec2<f32>(inf, -inf);
    let g = cone.g;
    let a = g * dd - ddp * ddp;
    let b = 2.0 * (g * dot(dir, o) - ddp * yp);
    let c = g * dot(o, o) - odp * odp - cone.r0 * cone.r0 * cone.dpdp - 2.0 * cone.r0dr * odp;
    let disc = b * b - 4.0 * a * c;
    let parallel = abs(a) <= 16.0 * BVH_F32_EPSILON * max(g * dd, ddp * ddp);
    let cone_valid = disc >= 0.0 && g > 0.0 && !parallel;
    if (!cone_valid && g > 0.0 && !parallel) {
        return none;
    }
    var cone_y = vec2<f32>(0.0, 0.0);
    if (cone_valid) {
        let q = sqrt(disc);
        let rcp_2a = 1.0 / (2.0 * a);
        let tf = (-b - q) * rcp_2a;
        let tb = (-b + q) * rcp_2a;
        cone_y = vec2<f32>(yp + tf * ddp, yp + tb * ddp);
        let pf = org + tf * dir;
        let pb = org + tb * dir;
        if (cone_y.x > -BVH_F32_EPSILON && cone_y.x <= g && !bvh_cone_holds(left, pf) && !bvh_cone_holds(right, pf)) {
            cone_x.x = tf;
        }
        if (cone_y.y > -BVH_F32_EPSILON && cone_y.y <= g && !bvh_cone_holds(left, pb) && !bvh_cone_holds(right, pb)) {
            cone_x.y = tb;
        }
    }
    let s1 = bvh_sphere(org, dir, rcp_dd, cone.p1, cone.r1);
    if (s1.z != 0.0) {
        if (yp + s1.x * ddp > g && !bvh_cone_clips(right, org + s1.x * dir)) {
            end_x.x = s1.x;
        }
        if (yp + s1.y * ddp > g && !bvh_cone_clips(right, org + s1.y * dir)) {
            end_x.y = s1.y;
        }
    }
    if (!has_left) {
        let s0 = bvh_sphere(org, dir, rcp_dd, cone.p0, cone.r0);
        if (s0.z != 0.0) {
            if (yp + s0.x * ddp < 0.0) {
                start_x.x = s0.x;
            }
            if (yp + s0.y * ddp < 0.0) {
                start_x.y = s0.y;
            }
        }
    }
    let lower = min(cone_x.x, min(start_x.x, end_x.x));
    let upper = max(cone_x.y, max(start_x.y, end_x.y));
    var t = 0.0;
    var front = true;
    if (lower != inf && range.x <= dt + lower && dt + lower <= range.y) {
        t = lower;
    } else if (upper != -inf && range.x <= dt + upper && dt + upper <= range.y) {
        t = upper;
        front = false;
    } else {
        return none;
    }
    var u = 1.0;
    if (t == cone_x.x || t == cone_x.y) {
        let y = select(cone_y.y, cone_y.x, front);
        u = clamp(y / g, 0.0, 1.0);
    } else if (t == start_x.x || t == start_x.y) {
        u = 0.0;
    }
    return BvhTriHit(dt + t, u, 0.0, true);
}

// ---- Round cubic: `cubic::round_cubic`, Embree's sweep with Newton's method. ----

// The curve (moved to the ray), the ray, and the best hit so far, of the segment being
// tested: `cubic::Sweep`.
var<private> bvh_cv: array<vec4<f32>, 4>;
var<private> bvh_sw_dir: vec3<f32>;
var<private> bvh_sw_dt: f32;
var<private> bvh_sw_range: vec2<f32>;
var<private> bvh_sw_found: bool;
var<private> bvh_sw_t: f32;
var<private> bvh_sw_u: f32;

struct BvhCurvePoint {
    p: vec4<f32>,
    d: vec4<f32>,
    dd: vec4<f32>,
}

// Twin of `Bezier::eval`.
fn bvh_bezier_eval(u: f32) -> BvhCurvePoint {
    let p0 = bvh_cv[0];
    let p1 = bvh_cv[1];
    let p2 = bvh_cv[2];
    let p3 = bvh_cv[3];
    let s = 1.0 - u;
    let p = s * s * s * p0 + 3.0 * s * s * u * p1 + 3.0 * s * u * u * p2 + u * u * u * p3;
    let d = 3.0 * (s * s * (p1 - p0) + 2.0 * s * u * (p2 - p1) + u * u * (p3 - p2));
    let dd = 6.0 * (s * (p2 - 2.0 * p1 + p0) + u * (p3 - 2.0 * p2 + p1));
    return BvhCurvePoint(p, d, dd);
}

fn bvh_sw_t_far() -> f32 {
    return select(bvh_sw_range.y, bvh_sw_t, bvh_sw_found);
}

// Twin of `cubic::cylinder`: (t0, t1, f0, f1) and whether it is crossed.
struct BvhCylinder {
    lo: f32,
    hi: f32,
    f0: f32,
    f1: f32,
    hit: bool,
}

fn bvh_cylinder(dir: vec3<f32>, p0: vec3<f32>, p1: vec3<f32>, r: f32) -> BvhCylinder {
    let inf = bvh_infinity();
    let axis = p1 - p0;
    let len = bvh_length(axis);
    let dp = axis / len;
    let o = -p0;
    let dd = dot(dir, dir);
    let od = dot(dir, o);
    let oo = dot(o, o);
    let doz = dot(dp, dir);
    let oz = dot(dp, o);
    let a = dd - doz * doz;
    let b = 2.0 * (od - doz * oz);
    let c = oo - oz * oz - r * r;
    let disc = b * b - 4.0 * a * c;
    if (!(disc >= 0.0)) {
        return BvhCylinder(0.0, 0.0, 0.0, 0.0, false);
    }
    if (abs(a) < 16.0 * BVH_F32_EPSILON * max(abs(dd), doz * doz)) {
        return BvhCylinder(-inf, inf, 0.0, 1.0, c <= 0.0);
    }
    let q = sqrt(disc);
    let rcp_2a = 1.0 / (2.0 * a);
    let t0 = (-b - q) * rcp_2a;
    let t1 = (-b + q) * rcp_2a;
    return BvhCylinder(t0, t1, (t0 * doz + oz) / len, (t1 * doz + oz) / len, true);
}

// Twin of `cubic::half_space`: (lo, hi).
fn bvh_half_space(dir: vec3<f32>, p: vec3<f32>, n: vec3<f32>) -> vec2<f32> {
    let inf = bvh_infinity();
    let a = -dot(p, n);
    let b = dot(dir, n);
    let t = -a / b;
    if (b > 0.0) {
        return vec2<f32>(t, inf);
    }
    if (b < 0.0) {
        return vec2<f32>(-inf, t);
    }
    if (a >= 0.0) {
        return vec2<f32>(-inf, inf);
    }
    return vec2<f32>(inf, -inf);
}

fn bvh_span_and(a: vec2<f32>, b: vec2<f32>) -> vec2<f32> {
    return vec2<f32>(max(a.x, b.x), min(a.y, b.y));
}

fn bvh_span_empty(s: vec2<f32>) -> bool {
    return !(s.x <= s.y);
}

fn bvh_off_chord(d: vec3<f32>, chord: vec3<f32>) -> f32 {
    let l = dot(chord, chord);
    if (l > 0.0) {
        return bvh_length(d - chord * (dot(d, chord) / l));
    }
    return bvh_length(d);
}

fn bvh_grazes(t: f32, f: f32, a: vec3<f32>, b: vec3<f32>) -> bool {
    let across = t * bvh_sw_dir - (a + f * (b - a));
    return abs(dot(bvh_unit(bvh_sw_dir), bvh_unit(across))) < 0.3;
}

// Twin of `Sweep::piece`: the piece's interval (x, y) and true in z when it is to be cut
// again.
fn bvh_piece(u0: f32, u1: f32, k: u32, depth: u32) -> vec3<f32> {
    let no = vec3<f32>(0.0, 0.0, 0.0);
    let dscale = (u1 - u0) * (1.0 / (3.0 * f32(BVH_CURVE_PIECES)));
    let ua = u0 + (u1 - u0) * (f32(k) * (1.0 / f32(BVH_CURVE_PIECES)));
    let ub = u0 + (u1 - u0) * (f32(k + 1u) * (1.0 / f32(BVH_CURVE_PIECES)));
    let ea = bvh_bezier_eval(ua);
    let eb = bvh_bezier_eval(ub);
    let p0 = ea.p;
    let d0 = ea.d * dscale;
    let p3 = eb.p;
    let d3 = eb.d * dscale;
    let p1 = p0 + d0;
    let p2 = p3 - d3;
    let chord = (p3 - p0).xyz;
    let bend = max(bvh_off_chord(d0.xyz, chord), bvh_off_chord(d3.xyz, chord));
    let rmax = max(max(max(max(p0.w, p1.w), p2.w), p3.w), 0.0);
    let rmin = min(min(min(p0.w, p1.w), p2.w), p3.w);
    let r_outer = (rmax + bend) * (1.0 + 2.0 * BVH_F32_EPSILON);
    let r_inner = max((rmin - bend) * (1.0 - 2.0 * BVH_F32_EPSILON), 0.0);
    let a = p0.xyz;
    let b = p3.xyz;
    let outer = bvh_cylinder(bvh_sw_dir, a, b, r_outer);
    if (!outer.hit) {
        return no;
    }
    var span = vec2<f32>(bvh_sw_range.x - bvh_sw_dt, bvh_sw_t_far() - bvh_sw_dt);
    span = bvh_span_and(span, vec2<f32>(outer.lo, outer.hi));
    span = bvh_span_and(span, bvh_half_space(bvh_sw_dir, a, d0.xyz));
    span = bvh_span_and(span, bvh_half_space(bvh_sw_dir, b, -d3.xyz));
    if (bvh_span_empty(span)) {
        return no;
    }
    let inner = bvh_cylinder(bvh_sw_dir, a, b, r_inner);
    var front = span;
    var back = span;
    var edge_on = true;
    if (inner.hit) {
        front = vec2<f32>(span.x, min(span.y, inner.lo));
        back = vec2<f32>(max(span.x, inner.hi), span.y);
        edge_on = bvh_grazes(inner.lo, inner.f0, a, b) || bvh_grazes(inner.hi, inner.f1, a, b);
    }
    let last = select(BVH_CURVE_LEVELS, BVH_CURVE_LEVELS + 1u, edge_on);
    if (depth < last) {
        let cut = !bvh_span_empty(front) || !bvh_span_empty(back);
        return vec3<f32>(ua, ub, select(0.0, 1.0, cut));
    }
    if (!bvh_span_empty(front)) {
        bvh_newton(ua + (ub - ua) * clamp(outer.f0, 0.0, 1.0), front.x);
    }
    if (!bvh_span_empty(back) && back.x + bvh_sw_dt <= bvh_sw_t_far()) {
        bvh_newton(ua + (ub - ua) * clamp(outer.f1, 0.0, 1.0), back.y);
    }
    return no;
}

// Twin of `Sweep::newton`.
fn bvh_newton(u_start: f32, t_start: f32) {
    var u = u_start;
    var t = t_start;
    let dir = bvh_sw_dir;
    let len_dir = bvh_length(dir);
    var lo = bvh_cv[0];
    var hi = bvh_cv[0];
    for (var i = 1u; i < 4u; i += 1u) {
        lo = min(lo, bvh_cv[i]);
        hi = max(hi, bvh_cv[i]);
    }
    let p_err = 16.0 * BVH_F32_EPSILON * bvh_max3(max(abs(lo), abs(hi)).xyz);
    let w_err = 16.0 * BVH_F32_EPSILON * hi.w;
    for (var step = 0u; step < BVH_NEWTON_STEPS; step += 1u) {
        let q = t * dir;
        let e = bvh_bezier_eval(u);
        let p3 = e.p.xyz;
        let dp3 = e.d.xyz;
        let ddp3 = e.dd.xyz;
        let r = q - p3;
        let len_r = bvh_length(r);
        let r_err = max(16.0 * BVH_F32_EPSILON * len_dir * t, p_err);
        let len_dp = bvh_length(dp3);
        let tan = dp3 / len_dp;
        let dtan = (ddp3 * dot(dp3, dp3) - dp3 * dot(dp3, ddp3)) / (len_dp * len_dp * len_dp);
        let cos_err = p_err / len_dp;
        let f = dot(r, tan);
        let f_err = len_r * p_err + r_err + cos_err * (1.0 + len_r);
        let dfdu = dot(-dp3, tan) + dot(r, dtan);
        let dfdt = dot(dir, tan);
        let k = dot(r, r) - f * f;
        let dkdu = dot(r, -dp3) - f * dfdu;
        let dkdt = dot(r, dir) - f * dfdt;
        let sqrt_k = sqrt(k);
        let g = sqrt_k - e.p.w;
        let g_err = r_err + f_err + w_err;
        let dgdu = dkdu / sqrt_k - e.d.w;
        let dgdt = dkdt / sqrt_k;
        let det = dfdu * dgdt - dfdt * dgdu;
        let du = (dgdt * f - dfdt * g) / det;
        let dtt = (dfdu * g - dgdu * f) / det;
        u -= du;
        t -= dtt;
        if (abs(f) < f_err && abs(g) < g_err) {
            let t_hit = t + bvh_sw_dt;
            let ok = bvh_sw_range.x <= t_hit && t_hit <= bvh_sw_t_far() && u >= 0.0 && u <= 1.0;
            if (ok && (!bvh_sw_found || t_hit < bvh_sw_t)) {
                bvh_sw_found = true;
                bvh_sw_t = t_hit;
                bvh_sw_u = u;
            }
            return;
        }
    }
}

fn bvh_round_cubic(org: vec3<f32>, dir: vec3<f32>, range: vec2<f32>, c: array<vec4<f32>, 4>) -> BvhTriHit {
    let center = 0.5 * (c[0].xyz + c[3].xyz);
    let dt = dot(center - org, dir) / dot(dir, dir);
    let moved = vec4<f32>(org + dt * dir, 0.0);
    for (var i = 0u; i < 4u; i += 1u) {
        bvh_cv[i] = c[i] - moved;
    }
    bvh_sw_dir = dir;
    bvh_sw_dt = dt;
    bvh_sw_range = range;
    bvh_sw_found = false;
    // (u0, u1, depth, next piece) per level: `Sweep::pieces`.
    var stack: array<vec4<f32>, 3>;
    stack[0] = vec4<f32>(0.0, 1.0, 1.0, 0.0);
    var sp = 1u;
    while (sp > 0u) {
        let top = stack[sp - 1u];
        let k = u32(top.w);
        if (k == BVH_CURVE_PIECES) {
            sp -= 1u;
            continue;
        }
        stack[sp - 1u].w = f32(k + 1u);
        let cut = bvh_piece(top.x, top.y, k, u32(top.z));
        if (cut.z != 0.0) {
            stack[sp] = vec4<f32>(cut.x, cut.y, top.z + 1.0, 0.0);
            sp += 1u;
        }
    }
    return BvhTriHit(bvh_sw_t, bvh_sw_u, 0.0, bvh_sw_found);
}

// ---- One segment: `Curves::intersect`. ----

// Segment `s` against the prepared ray `r` in `range`: the hit's t and curve parameter.
fn bvh_curve_hit(r: BvhPreparedRay, s: u32, range_in: vec2<f32>) -> BvhTriHit {
    let seg = bvh_curve_segment(s);
    let first = seg.first;
    let degree = select(3u, 1u, BVH_CURVE_KIND < 2u);
    let base = bvh_curve_point(first).xyz;
    let org_rel = r.org - base;
    // `unit_exponent`: the size and reach of the points relative to the first.
    var size = 0.0;
    var far = bvh_max3(abs(org_rel));
    for (var i = 0u; i <= degree; i += 1u) {
        let p = bvh_curve_point(first + i);
        let d = bvh_max3(abs(p.xyz - base));
        size = max(max(size, d), p.w);
        far = max(far, d);
    }
    let room = 100 - (1 - bvh_unit_exponent_of(far));
    let ek = min(bvh_unit_exponent_of(size), max(room, -126));
    let em = bvh_unit_exponent_of(bvh_max3(abs(r.dir)));
    let k = bvh_pow2(ek);
    let m = bvh_pow2(em);
    let f = bvh_pow2(clamp(ek - em, -126, 126));
    let org = org_rel * k;
    let dir = r.dir * m;
    let range = range_in * f;
    var h: BvhTriHit;
    if (BVH_CURVE_KIND == 1u) {
        let sp = bvh_ray_space(r.dir);
        let space = BvhRaySpace(sp.x, sp.y, sp.z / m, sp.depth_scale / m);
        let v0 = (bvh_curve_point(first) - vec4<f32>(base, 0.0)) * k;
        let v1 = (bvh_curve_point(first + 1u) - vec4<f32>(base, 0.0)) * k;
        h = bvh_flat_linear(org, space, range, v0, v1);
    } else if (BVH_CURVE_KIND == 0u) {
        let v0 = (bvh_curve_point(first) - vec4<f32>(base, 0.0)) * k;
        let v1 = (bvh_curve_point(first + 1u) - vec4<f32>(base, 0.0)) * k;
        let has_left = (seg.neighbours & 1u) != 0u;
        let has_right = (seg.neighbours & 2u) != 0u;
        let absent = vec4<f32>(bvh_infinity());
        var vl = absent;
        var vr = absent;
        if (has_left) {
            vl = (bvh_curve_point(first - 1u) - vec4<f32>(base, 0.0)) * k;
        }
        if (has_right) {
            vr = (bvh_curve_point(first + 2u) - vec4<f32>(base, 0.0)) * k;
        }
        h = bvh_round_linear(org, dir, range, v0, v1, vl, vr, has_left);
    } else {
        var c: array<vec4<f32>, 4>;
        for (var i = 0u; i < 4u; i += 1u) {
            c[i] = (bvh_curve_point(first + i) - vec4<f32>(base, 0.0)) * k;
        }
        if (BVH_CURVE_KIND == 3u) {
            // `bspline_to_bezier`.
            let b = c;
            c[0] = (b[0] + 4.0 * b[1] + b[2]) * (1.0 / 6.0);
            c[1] = (2.0 * b[1] + b[2]) * (1.0 / 3.0);
            c[2] = (b[1] + 2.0 * b[2]) * (1.0 / 3.0);
            c[3] = (b[1] + 4.0 * b[2] + b[3]) * (1.0 / 6.0);
        }
        h = bvh_round_cubic(org, dir, range, c);
    }
    h.t = h.t / f;
    return h;
}
