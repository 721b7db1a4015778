// path_sampling.wgsl: the path tracer's numbers and its material, written so the CPU twin
// (`bvhtrace_path::sampling`) computes the same bits: only + - * /, sqrt, min and max,
// each product and sum in the order written (no `dot`, `normalize` or `mix` builtins,
// whose order is the driver's), and no transcendental function.

const PATH_PI: f32 = 3.14159265358979323846;

// `bvhtrace_core::surface::hash` (PCG).
fn path_hash(x0: u32) -> u32 {
    let x = x0 * 747796405u + 2891336453u;
    let w = ((x >> ((x >> 28u) + 4u)) ^ x) * 277803737u;
    return (w >> 22u) ^ w;
}

// A counter-based generator: number `n` of a path is a hash of its key (pixel, sample,
// seed) and `n`, so every number is known without any state carried between samples.
struct PathRng {
    key: u32,
    n: u32,
}

fn path_rng(pixel: u32, sample: u32, seed: u32) -> PathRng {
    return PathRng(path_hash(pixel ^ path_hash(sample ^ path_hash(seed))), 0u);
}

// The next number in [0, 1): 24 bits.
fn path_next(r: ptr<function, PathRng>) -> f32 {
    (*r).n += 1u;
    return f32(path_hash((*r).key ^ path_hash((*r).n)) >> 8u) / 16777216.0;
}

// A uniform point of the unit disk other than its centre, by rejection (no sine or
// cosine); after 32 rejections (odds 1e-21) a fixed point.
fn path_disk(r: ptr<function, PathRng>) -> vec2<f32> {
    for (var i = 0u; i < 32u; i += 1u) {
        let x = 2.0 * path_next(r) - 1.0;
        let y = 2.0 * path_next(r) - 1.0;
        let d = x * x + y * y;
        if (d < 1.0 && d > 0.0) {
            return vec2<f32>(x, y);
        }
    }
    return vec2<f32>(0.5, 0.0);
}

fn path_dot(a: vec3<f32>, b: vec3<f32>) -> f32 {
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

// `v` times `1 / sqrt(v . v)`, as glam's `normalize`.
fn path_normalize(v: vec3<f32>) -> vec3<f32> {
    let r = 1.0 / sqrt(path_dot(v, v));
    return vec3<f32>(v.x * r, v.y * r, v.z * r);
}

// An orthonormal basis around the unit `n` (Duff et al., "Building an Orthonormal Basis,
// Revisited", 2017): `x` and `y` of the local frame whose `z` is `n`.
struct PathFrame {
    x: vec3<f32>,
    y: vec3<f32>,
    z: vec3<f32>,
}

fn path_frame(n: vec3<f32>) -> PathFrame {
    let s = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    let x = vec3<f32>(1.0 + s * n.x * n.x * a, s * b, -s * n.x);
    let y = vec3<f32>(b, s + n.y * n.y * a, -n.y);
    return PathFrame(x, y, n);
}

fn path_to_world(f: PathFrame, l: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(
        f.x.x * l.x + f.y.x * l.y + f.z.x * l.z,
        f.x.y * l.x + f.y.y * l.y + f.z.y * l.z,
        f.x.z * l.x + f.y.z * l.y + f.z.z * l.z,
    );
}

// A cosine-weighted direction about the frame's `z` (Malley: the disk lifted to the
// hemisphere); its density is `z / pi`.
fn path_cosine(f: PathFrame, r: ptr<function, PathRng>) -> vec3<f32> {
    let d = path_disk(r);
    let z = sqrt(max(0.0, 1.0 - d.x * d.x - d.y * d.y));
    return path_to_world(f, vec3<f32>(d.x, d.y, z));
}

// The power heuristic (beta 2) of a strategy of density `a` against one of `b`.
fn path_mis(a: f32, b: f32) -> f32 {
    return a * a / (a * a + b * b);
}

// A material as sampled (`bvhtrace_path::PathMaterial`): computed once per material on
// the host (`bvhtrace_path::sampling::Lobes`), complements included (`1 - f0`,
// `alpha^2 - 1`, ...). A shader compiler may turn `a + c * (b - a)` into a lerp of its
// own rounding (Mesa's NIR does), so no expression here has that shape.
struct PathMaterial {
    diffuse: vec3<f32>,
    alpha2: f32,
    f0: vec3<f32>,
    p_spec: f32,
    f0c: vec3<f32>,
    alpha2_m1: f32,
    emissive: vec3<f32>,
    one_m_alpha2: f32,
    p_diffuse: f32,
    base_alpha: f32,
    // Textures (`PATH_NO_TEXTURE` for none): base colour, metallic-roughness, emissive,
    // and the offset of the material's table in `path_data` (`bvhtrace_path::textures`).
    base_tex: u32,
    mr_tex: u32,
    base_factor: vec3<f32>,
    emissive_tex: u32,
    emissive_factor: vec3<f32>,
    table: u32,
}

const PATH_NO_TEXTURE: u32 = 0xffffffffu;

// `f(wo, wi) cos(wi)` and the density of `path_sample_lobes` choosing `wi`, about the
// unit normal `n` on `wo`'s side.
struct PathEval {
    value: vec3<f32>,
    pdf: f32,
}

fn path_g1(m: PathMaterial, c: f32) -> f32 {
    return 2.0 * c / (c + sqrt(m.alpha2 + m.one_m_alpha2 * c * c));
}

fn path_eval(m: PathMaterial, n: vec3<f32>, wo: vec3<f32>, wi: vec3<f32>) -> PathEval {
    let cos_i = path_dot(n, wi);
    let cos_o = path_dot(n, wo);
    if (!(cos_i > 0.0 && cos_o > 0.0)) {
        return PathEval(vec3<f32>(0.0), 0.0);
    }
    let h = path_normalize(vec3<f32>(wo.x + wi.x, wo.y + wi.y, wo.z + wi.z));
    let nh = path_dot(n, h);
    let oh = max(path_dot(wo, h), 1e-8);
    let dd = nh * nh * m.alpha2_m1 + 1.0;
    let d = m.alpha2 / (PATH_PI * dd * dd);
    let g = path_g1(m, cos_o) * path_g1(m, cos_i);
    let fw = 1.0 - oh;
    let fw5 = fw * fw * fw * fw * fw;
    let spec = d * g / (4.0 * cos_o);
    let diff = cos_i / PATH_PI;
    let value = vec3<f32>(
        m.diffuse.x * diff + (m.f0.x + m.f0c.x * fw5) * spec,
        m.diffuse.y * diff + (m.f0.y + m.f0c.y * fw5) * spec,
        m.diffuse.z * diff + (m.f0.z + m.f0c.z * fw5) * spec,
    );
    let pdf = m.p_diffuse * cos_i / PATH_PI + m.p_spec * d * nh / (4.0 * oh);
    return PathEval(value, pdf);
}

// A direction from the lobes: the specular one with chance `p_spec` (a GGX normal, `wo`
// reflected about it), else cosine-weighted.
fn path_sample_lobes(m: PathMaterial, n: vec3<f32>, wo: vec3<f32>, r: ptr<function, PathRng>) -> vec3<f32> {
    let f = path_frame(n);
    if (path_next(r) >= m.p_spec) {
        return path_cosine(f, r);
    }
    let d = path_disk(r);
    let xi = path_next(r);
    let c2 = (1.0 - xi) / (1.0 + m.alpha2_m1 * xi);
    let cos_h = sqrt(c2);
    let sin_h = sqrt(max(0.0, 1.0 - c2));
    let len = sqrt(d.x * d.x + d.y * d.y);
    let h = path_to_world(f, vec3<f32>(sin_h * (d.x / len), sin_h * (d.y / len), cos_h));
    let oh2 = 2.0 * path_dot(wo, h);
    return vec3<f32>(h.x * oh2 - wo.x, h.y * oh2 - wo.y, h.z * oh2 - wo.z);
}
