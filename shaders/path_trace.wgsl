// path_trace.wgsl: a progressive path tracer over the traversal library's public calls
// (`bvh_trace_closest`, `bvh_trace_any`, `bvh_hit_surface`), composed after the library
// and path_sampling.wgsl. One invocation per pixel adds one sample to the pixel's sum in
// `path_accum`; the CPU twin (`bvhtrace_path::twin`) traces the same paths.
//
// Per vertex: the emission met (weighted by multiple importance sampling against the light
// sampling that could have found it), then next-event estimation toward the sun, the
// environment (cosine-weighted) and one emissive triangle (by power), each with a shadow
// ray (`bvh_trace_any`), then a bounce sampled from the material; Russian roulette from
// the third bounce, at most `max_depth` bounces.

// `bvhtrace_path::PathParams`.
struct PathParams {
    eye: vec3<f32>,
    tan_half_fov: f32,
    forward: vec3<f32>,
    aspect: f32,
    right: vec3<f32>,
    width: u32,
    up: vec3<f32>,
    height: u32,
    sun_dir: vec3<f32>,
    max_depth: u32,
    sun: vec3<f32>,
    light_count: u32,
    env: vec3<f32>,
    sample: u32,
    seed: u32,
    material_count: u32,
    prim_count: u32,
    pad: u32,
}

// `bvhtrace_path::PathLight`: an emissive triangle `v0`, `v0 + e1`, `v0 + e2`, chosen with
// probability `cdf[i] - cdf[i - 1]`; `pdf_area` is that over its area.
struct PathLight {
    v0: vec3<f32>,
    cdf: f32,
    e1: vec3<f32>,
    pdf_area: f32,
    e2: vec3<f32>,
    prim: u32,
    emission: vec3<f32>,
    pad: u32,
}

// Per primitive (the hit's `prim`): its material, and its light (`PATH_NO_LIGHT` for none).
const PATH_NO_LIGHT: u32 = 0xffffffffu;
// Longer than any scene: the interval of rays toward the sun and the environment.
const PATH_FAR: f32 = 1e30;

@group(1) @binding(0) var<uniform> path_params: PathParams;
// Per pixel: the sum of its samples' radiance, and their count in `w`.
@group(1) @binding(1) var<storage, read_write> path_accum: array<vec4<f32>>;
// The scene's shading data, one array (`bvhtrace_path::textures`), so that the kernel
// binds three storage buffers besides the BVH's: word 0 the texture coordinates' offset,
// word 1 the sRGB table's, word 2 the texture headers' (4 words a texture: texels'
// offset, width, height, wraps), word 3 the environment map's (path_environment.wgsl; 0
// for a constant sky), words 4, 5 and 6 the materials' (`path_material`), the
// primitives' (`path_prim`) and the lights' (`path_light`); then those, the texels and
// each textured material's table.
@group(1) @binding(3) var<storage, read> path_data: array<u32>;
// Rays the walk gave up on (a CPU driver's trip budget), samples dropped as not finite,
// rays traced (closest and any hit; wraps past 2^32), one unused; then the wavefront's
// control words (path_wavefront.wgsl), here so that the waves bind no storage more.
@group(1) @binding(2) var<storage, read_write> path_stats: array<atomic<u32>, 8>;

// The invocation's rays, added to `path_stats[2]` once at its end.
var<private> path_rays: u32;

fn path_scale(v: vec3<f32>, s: f32) -> vec3<f32> {
    return vec3<f32>(v.x * s, v.y * s, v.z * s);
}

fn path_mul(a: vec3<f32>, b: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(a.x * b.x, a.y * b.y, a.z * b.z);
}

fn path_add(a: vec3<f32>, b: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(a.x + b.x, a.y + b.y, a.z + b.z);
}

fn path_is_black(v: vec3<f32>) -> bool {
    return !(v.x > 0.0 || v.y > 0.0 || v.z > 0.0);
}

// Whether anything lies on `ray` in its interval; a ray the walk gave up on counts as
// blocked (and is counted).
fn path_blocked(ray: BvhRay, lane: u32) -> bool {
    path_rays += 1u;
    let prim = bvh_trace_any(ray, lane).hit.prim;
    if (prim == BVH_INCOMPLETE) {
        atomicAdd(&path_stats[0], 1u);
    }
    return prim != BVH_MISS && prim != BVH_INVALID_RAY;
}

// The RGBA8 texel of texture `t` nearest `uv`.
fn path_texel(t: u32, uv: vec2<f32>) -> vec4<u32> {
    let h = path_data[2] + 4u * t;
    let w = path_data[h + 1u];
    let x = bvh_texel_index(uv.x, w, path_data[h + 3u] & 3u);
    let y = bvh_texel_index(uv.y, path_data[h + 2u], path_data[h + 3u] >> 2u);
    let c = path_data[path_data[h] + y * w + x];
    return vec4<u32>(c & 255u, (c >> 8u) & 255u, (c >> 16u) & 255u, c >> 24u);
}

// An sRGB-encoded texel's colour, linear (the table of `bvhtrace_path::textures`).
fn path_srgb(c: vec4<u32>) -> vec3<f32> {
    let t = path_data[1];
    return vec3<f32>(
        bitcast<f32>(path_data[t + c.x]),
        bitcast<f32>(path_data[t + c.y]),
        bitcast<f32>(path_data[t + c.z]),
    );
}

// `bvhtrace_core::alpha::interpolate_uv` of primitive `prim` at barycentrics `u`, `v`.
fn path_uv(prim: u32, u: f32, v: f32) -> vec2<f32> {
    let b = path_data[0] + 6u * prim;
    let c = array<f32, 6>(
        bitcast<f32>(path_data[b]), bitcast<f32>(path_data[b + 1u]),
        bitcast<f32>(path_data[b + 2u]), bitcast<f32>(path_data[b + 3u]),
        bitcast<f32>(path_data[b + 4u]), bitcast<f32>(path_data[b + 5u]),
    );
    return vec2<f32>(
        (c[0] + (c[2] - c[0]) * u) + (c[4] - c[0]) * v,
        (c[1] + (c[3] - c[1]) * u) + (c[5] - c[1]) * v,
    );
}

fn path_word(i: u32) -> f32 {
    return bitcast<f32>(path_data[i]);
}

fn path_vec3(i: u32) -> vec3<f32> {
    return vec3<f32>(path_word(i), path_word(i + 1u), path_word(i + 2u));
}

// Material `i`: 28 words, `PathMaterial`'s members in order (its vec3s padded to 16 bytes).
fn path_material(i: u32) -> PathMaterial {
    let b = path_data[4] + 28u * i;
    return PathMaterial(
        path_vec3(b), path_word(b + 3u),
        path_vec3(b + 4u), path_word(b + 7u),
        path_vec3(b + 8u), path_word(b + 11u),
        path_vec3(b + 12u), path_word(b + 15u),
        path_word(b + 16u), path_word(b + 17u), path_data[b + 18u], path_data[b + 19u],
        path_vec3(b + 20u), path_data[b + 23u],
        path_vec3(b + 24u), path_data[b + 27u],
    );
}

// Primitive `i`'s material and light (`PATH_NO_LIGHT` for none).
fn path_prim(i: u32) -> vec2<u32> {
    let b = path_data[5] + 2u * i;
    return vec2<u32>(path_data[b], path_data[b + 1u]);
}

// Light `i`: 16 words, `PathLight`'s members in order.
fn path_light(i: u32) -> PathLight {
    let b = path_data[6] + 16u * i;
    return PathLight(
        path_vec3(b), path_word(b + 3u),
        path_vec3(b + 4u), path_word(b + 7u),
        path_vec3(b + 8u), path_data[b + 11u],
        path_vec3(b + 12u), 0u,
    );
}

// Material `m` at barycentrics `u`, `v` of `prim`: its textures read and its lobes worked
// out (`bvhtrace_path::sampling::textured`), with each complement from the material's
// table rather than `1 - x` here (see path_sampling.wgsl).
fn path_textured(m: PathMaterial, prim: u32, u: f32, v: f32) -> PathMaterial {
    if (m.base_tex == PATH_NO_TEXTURE && m.mr_tex == PATH_NO_TEXTURE && m.emissive_tex == PATH_NO_TEXTURE) {
        return m;
    }
    let uv = path_uv(prim, u, v);
    var base = m.base_factor;
    if (m.base_tex != PATH_NO_TEXTURE) {
        let c = path_srgb(path_texel(m.base_tex, uv));
        base = vec3<f32>(base.x * c.x, base.y * c.y, base.z * c.z);
    }
    var g = 255u;
    var b = 255u;
    if (m.mr_tex != PATH_NO_TEXTURE) {
        let c = path_texel(m.mr_tex, uv);
        g = c.y;
        b = c.z;
    }
    var out = m;
    // Roughness from G: alpha^2, alpha^2 - 1, 1 - alpha^2; metalness from B: metallic,
    // 1 - metallic, 0.04 (1 - metallic), 1 - 0.04 (1 - metallic).
    let r = m.table + 4u * g;
    let k = m.table + 1024u + 4u * b;
    out.alpha2 = path_word(r);
    out.alpha2_m1 = path_word(r + 1u);
    out.one_m_alpha2 = path_word(r + 2u);
    let metallic = path_word(k);
    let dielectric = path_word(k + 1u);
    let c1 = path_word(k + 2u);
    let e1 = path_word(k + 3u);
    out.diffuse = vec3<f32>(base.x * dielectric, base.y * dielectric, base.z * dielectric);
    out.f0 = vec3<f32>(c1 + base.x * metallic, c1 + base.y * metallic, c1 + base.z * metallic);
    out.f0c = vec3<f32>(e1 - base.x * metallic, e1 - base.y * metallic, e1 - base.z * metallic);
    let ls = 0.2126 * out.f0.x + 0.7152 * out.f0.y + 0.0722 * out.f0.z;
    let ld = 0.2126 * out.diffuse.x + 0.7152 * out.diffuse.y + 0.0722 * out.diffuse.z;
    var p = 1.0;
    if (ld > 0.0) {
        p = min(max(ls / (ls + ld), 0.1), 0.9);
    }
    out.p_spec = p;
    out.p_diffuse = 1.0 - p;
    if (m.emissive_tex != PATH_NO_TEXTURE) {
        let c = path_srgb(path_texel(m.emissive_tex, uv));
        let e = m.emissive_factor;
        out.emissive = vec3<f32>(e.x * c.x, e.y * c.y, e.z * c.z);
    }
    return out;
}

// The light whose cdf first exceeds `u` (binary search).
fn path_pick_light(u: f32) -> u32 {
    var lo = 0u;
    var hi = path_params.light_count - 1u;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        if (u < path_word(path_data[6] + 16u * mid + 3u)) {
            hi = mid;
        } else {
            lo = mid + 1u;
        }
    }
    return lo;
}

// A path between its vertices: the ray it goes on along, its random numbers' key and
// count, the bounces taken, the throughput, the last bounce's density and normal (for the
// weights of what the next vertex finds) and the radiance gathered so far. The
// wavefront kernels keep it in a buffer between waves (`path_wavefront.wgsl`).
struct PathState {
    origin: vec3<f32>,
    depth: u32,
    dir: vec3<f32>,
    last_pdf: f32,
    throughput: vec3<f32>,
    key: u32,
    last_n: vec3<f32>,
    count: u32,
    radiance: vec3<f32>,
    pad: u32,
}

// The path of a sample through pixel (`x`, `y`), before its first vertex.
fn path_camera(x: u32, y: u32) -> PathState {
    let p = path_params;
    var r = path_rng(y * p.width + x, p.sample, p.seed);
    let jx = path_next(&r);
    let jy = path_next(&r);
    let px = (2.0 * (f32(x) + jx) / f32(p.width) - 1.0) * p.tan_half_fov * p.aspect;
    let py = (1.0 - 2.0 * (f32(y) + jy) / f32(p.height)) * p.tan_half_fov;
    let dir = path_normalize(vec3<f32>(
        p.forward.x + p.right.x * px + p.up.x * py,
        p.forward.y + p.right.y * px + p.up.y * py,
        p.forward.z + p.right.z * px + p.up.z * py,
    ));
    let zero = vec3<f32>(0.0);
    return PathState(p.eye, 0u, dir, 0.0, vec3<f32>(1.0), r.key, zero, r.n, zero, 0u);
}

// The next vertex of path `st`: the ray traced, the emission met, the lights sampled and
// the bounce taken. Whether the path goes on.
fn path_vertex(st: ptr<function, PathState>, lane: u32) -> bool {
    var r = PathRng((*st).key, (*st).count);
    let more = path_step(st, &r, lane);
    (*st).count = r.n;
    return more;
}

fn path_step(st: ptr<function, PathState>, r: ptr<function, PathRng>, lane: u32) -> bool {
    let p = path_params;
    let depth = (*st).depth;
    let ray = BvhRay((*st).origin, 0.0, (*st).dir, PATH_FAR);
    let throughput = (*st).throughput;
    let has_env = !path_is_black(p.env);
    let hit = bvh_trace_closest(ray, lane).hit;
    path_rays += 1u;
    if (hit.prim == BVH_INCOMPLETE) {
        atomicAdd(&path_stats[0], 1u);
        return false;
    }
    if (hit.prim >= BVH_INVALID_RAY) {
        let map = path_data[3];
        if (has_env && map != 0u) {
            let l = path_env_lookup(map, ray.dir);
            var w = 1.0;
            if (depth > 0u) {
                w = path_mis((*st).last_pdf, l.pdf);
            }
            let le = path_mul(l.radiance, p.env);
            (*st).radiance = path_add((*st).radiance, path_scale(path_mul(throughput, le), w));
            return false;
        }
        var w = 1.0;
        if (depth > 0u && has_env) {
            w = path_mis((*st).last_pdf, max(path_dot((*st).last_n, ray.dir), 0.0) / PATH_PI);
        }
        (*st).radiance = path_add((*st).radiance, path_scale(path_mul(throughput, p.env), w));
        return false;
    }
    let s = bvh_hit_surface(ray, hit);
    let n = s.normal;
    let prim = path_prim(hit.prim);
    let m = path_textured(path_material(prim.x), hit.prim, hit.u, hit.v);
    // An emissive triangle lights its front only (the side its corners wind about, as
    // light sampling assumes); one that is no light (of no area) both sides.
    var front = true;
    if (prim.y != PATH_NO_LIGHT) {
        let lt = path_light(prim.y);
        front = path_dot(bvh_cross(lt.e1, lt.e2), ray.dir) < 0.0;
    }
    if (!path_is_black(m.emissive) && front) {
        var w = 1.0;
        if (depth > 0u && prim.y != PATH_NO_LIGHT) {
            let cos_l = abs(path_dot(n, ray.dir));
            let light_pdf = path_word(path_data[6] + 16u * prim.y + 7u) * (hit.t * hit.t) / cos_l;
            w = path_mis((*st).last_pdf, light_pdf);
        }
        (*st).radiance = path_add((*st).radiance, path_scale(path_mul(throughput, m.emissive), w));
    }
    let wo = vec3<f32>(-ray.dir.x, -ray.dir.y, -ray.dir.z);
    path_direct(st, m, s, wo, r, lane);
    // The bounce.
    let wi = path_sample_lobes(m, n, wo, r);
    let e = path_eval(m, n, wo, wi);
    if (!(e.pdf > 0.0) || path_is_black(e.value)) {
        return false;
    }
    var t = path_mul(throughput, vec3<f32>(e.value.x / e.pdf, e.value.y / e.pdf, e.value.z / e.pdf));
    (*st).last_pdf = e.pdf;
    (*st).last_n = n;
    if (depth >= 2u) {
        let survive = min(max(t.x, max(t.y, t.z)), 0.95);
        if (path_next(r) >= survive) {
            return false;
        }
        t = path_scale(t, 1.0 / survive);
    }
    (*st).throughput = t;
    (*st).origin = s.origin;
    (*st).dir = wi;
    (*st).depth = depth + 1u;
    return depth + 1u < p.max_depth;
}

// Next-event estimation at surface point `s` of material `m` seen from `wo`: the light
// reaching it from the sun, the environment and one emissive triangle, each through a
// shadow ray, added to path `st`'s radiance through its throughput.
fn path_direct(st: ptr<function, PathState>, m: PathMaterial, s: BvhSurface, wo: vec3<f32>, r: ptr<function, PathRng>, lane: u32) {
    let p = path_params;
    let n = s.normal;
    let throughput = (*st).throughput;
    var radiance = (*st).radiance;
    // The sun: a direction, found only by a shadow ray.
    if (!path_is_black(p.sun)) {
        let e = path_eval(m, n, wo, p.sun_dir);
        if (e.pdf > 0.0 && !path_blocked(BvhRay(s.origin, 0.0, p.sun_dir, PATH_FAR), lane)) {
            radiance = path_add(radiance, path_mul(throughput, path_mul(e.value, p.sun)));
        }
    }
    // The environment map, by its luminance.
    let map = path_data[3];
    if (!path_is_black(p.env) && map != 0u) {
        let u0 = path_next(r);
        let u1 = path_next(r);
        let u2 = path_next(r);
        let l = path_env_sample(map, u0, u1, u2);
        let e = path_eval(m, n, wo, l.dir);
        if (e.pdf > 0.0 && l.pdf > 0.0 && !path_blocked(BvhRay(s.origin, 0.0, l.dir, PATH_FAR), lane)) {
            let w = path_mis(l.pdf, e.pdf) / l.pdf;
            let le = path_mul(l.radiance, p.env);
            radiance = path_add(radiance, path_scale(path_mul(throughput, path_mul(e.value, le)), w));
        }
    }
    // A constant environment, cosine-weighted about the normal.
    if (!path_is_black(p.env) && map == 0u) {
        let wi = path_cosine(path_frame(n), r);
        let env_pdf = path_dot(n, wi) / PATH_PI;
        let e = path_eval(m, n, wo, wi);
        if (e.pdf > 0.0 && env_pdf > 0.0 && !path_blocked(BvhRay(s.origin, 0.0, wi, PATH_FAR), lane)) {
            let w = path_mis(env_pdf, e.pdf) / env_pdf;
            radiance = path_add(radiance, path_scale(path_mul(throughput, path_mul(e.value, p.env)), w));
        }
    }
    // One emissive triangle, chosen by power, a uniform point on it.
    if (p.light_count > 0u) {
        radiance = path_add(radiance, path_triangle_light(throughput, m, s, wo, r, lane));
    }
    (*st).radiance = radiance;
}

fn path_triangle_light(throughput: vec3<f32>, m: PathMaterial, s: BvhSurface, wo: vec3<f32>, r: ptr<function, PathRng>, lane: u32) -> vec3<f32> {
    let light = path_light(path_pick_light(path_next(r)));
    let su = sqrt(path_next(r));
    let b1 = 1.0 - su;
    let b2 = path_next(r) * su;
    let q = vec3<f32>(
        light.v0.x + light.e1.x * b1 + light.e2.x * b2,
        light.v0.y + light.e1.y * b1 + light.e2.y * b2,
        light.v0.z + light.e1.z * b1 + light.e2.z * b2,
    );
    let d = vec3<f32>(q.x - s.origin.x, q.y - s.origin.y, q.z - s.origin.z);
    let dist2 = path_dot(d, d);
    let dist = sqrt(dist2);
    let wi = vec3<f32>(d.x / dist, d.y / dist, d.z / dist);
    let nl = path_normalize(bvh_cross(light.e1, light.e2));
    let cos_l = abs(path_dot(nl, wi));
    let e = path_eval(m, s.normal, wo, wi);
    // Emission leaves a triangle's front only (the side its corners wind about).
    if (!(e.pdf > 0.0 && cos_l > 0.0) || path_dot(nl, wi) > 0.0) {
        return vec3<f32>(0.0);
    }
    // The point moved off the light toward the surface, so the light itself does not
    // block the shadow ray.
    let toward = select(nl, -nl, path_dot(nl, wi) > 0.0);
    let target_point = bvh_offset_ray_origin(q, toward);
    let dt = vec3<f32>(target_point.x - s.origin.x, target_point.y - s.origin.y, target_point.z - s.origin.z);
    if (path_blocked(BvhRay(s.origin, 0.0, dt, 1.0), lane)) {
        return vec3<f32>(0.0);
    }
    let light_pdf = light.pdf_area * dist2 / cos_l;
    let w = path_mis(light_pdf, e.pdf) / light_pdf;
    let lm = path_material(path_prim(light.prim).x);
    var emission = light.emission;
    if (lm.emissive_tex != PATH_NO_TEXTURE) {
        emission = path_textured(lm, light.prim, b1, b2).emissive;
    }
    return path_scale(path_mul(throughput, path_mul(e.value, emission)), w);
}

// One sample of the radiance reaching the camera through pixel (`x`, `y`).
fn path_radiance(x: u32, y: u32, lane: u32) -> vec3<f32> {
    var st = path_camera(x, y);
    if (path_params.max_depth > 0u) {
        loop {
            if (!path_vertex(&st, lane)) {
                break;
            }
        }
    }
    return st.radiance;
}

// Adds sample `c` to pixel `i`'s sum (the first sample replaces it). Never a NaN pixel: a
// sample that is not finite is dropped (and counted).
fn path_accumulate(i: u32, sample: vec3<f32>) {
    var c = sample;
    let big = 3.0e38;
    if (!(abs(c.x) <= big && abs(c.y) <= big && abs(c.z) <= big)) {
        atomicAdd(&path_stats[1], 1u);
        c = vec3<f32>(0.0);
    }
    var sum = vec4<f32>(0.0);
    if (path_params.sample > 0u) {
        sum = path_accum[i];
    }
    path_accum[i] = vec4<f32>(sum.x + c.x, sum.y + c.y, sum.z + c.z, sum.w + 1.0);
}

// 8 x 8 invocations: the walks' stacks are laid out for at most 64 lanes a workgroup.
@compute @workgroup_size(8, 8)
fn path_main(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let p = path_params;
    if (id.x >= p.width || id.y >= p.height) {
        return;
    }
    path_rays = 0u;
    let c = path_radiance(id.x, id.y, lane);
    atomicAdd(&path_stats[2], path_rays);
    path_accumulate(id.y * p.width + id.x, c);
}
