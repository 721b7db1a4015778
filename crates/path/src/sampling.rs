//! The CPU twin of `shaders/path_sampling.wgsl`, operation for operation: the random
//! numbers, the disk and hemisphere, the frame about a normal, the metallic-roughness
//! material. Only `+ - * /`, `sqrt`, `min` and `max` in the order the shader writes them,
//! so the two compute the same bits wherever the device rounds as IEEE 754 says.

use glam::{Vec2, Vec3};

use crate::material::{NO_TEXTURE, PathMaterial};

/// `PATH_PI`.
pub const PI: f32 = std::f32::consts::PI;
/// The least roughness shaded (no perfect mirrors).
pub const MIN_ROUGHNESS: f32 = 0.05;

/// `path_hash`: `bvhtrace_core::surface::hash`.
pub fn hash(x: u32) -> u32 {
    bvhtrace_core::surface::hash(x)
}

/// `PathRng`: number `n` of a path is a hash of its key and `n`.
#[derive(Clone, Copy, Debug)]
pub struct Rng {
    key: u32,
    n: u32,
}

impl Rng {
    /// The numbers of `sample` of `pixel` under `seed`.
    pub fn new(pixel: u32, sample: u32, seed: u32) -> Rng {
        Rng {
            key: hash(pixel ^ hash(sample ^ hash(seed))),
            n: 0,
        }
    }

    /// The next number in `[0, 1)` (`path_next`).
    pub fn uniform(&mut self) -> f32 {
        self.n = self.n.wrapping_add(1);
        (hash(self.key ^ hash(self.n)) >> 8) as f32 / 16777216.0
    }

    /// `path_disk`: a uniform point of the unit disk but its centre, by rejection.
    pub fn disk(&mut self) -> Vec2 {
        for _ in 0..32 {
            let x = 2.0 * self.uniform() - 1.0;
            let y = 2.0 * self.uniform() - 1.0;
            let d = x * x + y * y;
            if d < 1.0 && d > 0.0 {
                return Vec2::new(x, y);
            }
        }
        Vec2::new(0.5, 0.0)
    }
}

/// `path_dot`.
pub fn dot(a: Vec3, b: Vec3) -> f32 {
    a.x * b.x + a.y * b.y + a.z * b.z
}

/// `path_normalize`: times `1 / sqrt(v . v)`.
pub fn normalize(v: Vec3) -> Vec3 {
    let r = 1.0 / dot(v, v).sqrt();
    Vec3::new(v.x * r, v.y * r, v.z * r)
}

/// `bvh_cross`: glam's `cross`.
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    Vec3::new(
        a.y * b.z - b.y * a.z,
        a.z * b.x - b.z * a.x,
        a.x * b.y - b.x * a.y,
    )
}

/// `PathFrame`: the local frame whose `z` is the unit normal (Duff et al. 2017).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    x: Vec3,
    y: Vec3,
    z: Vec3,
}

impl Frame {
    /// `path_frame`.
    pub fn new(n: Vec3) -> Frame {
        let s = if n.z >= 0.0 { 1.0 } else { -1.0 };
        let a = -1.0 / (s + n.z);
        let b = n.x * n.y * a;
        let x = Vec3::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x);
        let y = Vec3::new(b, s + n.y * n.y * a, -n.y);
        Frame { x, y, z: n }
    }

    /// `path_to_world`.
    pub fn to_world(&self, l: Vec3) -> Vec3 {
        let (x, y, z) = (self.x, self.y, self.z);
        Vec3::new(
            x.x * l.x + y.x * l.y + z.x * l.z,
            x.y * l.x + y.y * l.y + z.y * l.z,
            x.z * l.x + y.z * l.y + z.z * l.z,
        )
    }

    /// `path_cosine`: a cosine-weighted direction about `z` (density `z / pi`).
    pub fn cosine(&self, r: &mut Rng) -> Vec3 {
        let d = r.disk();
        let z = (1.0 - d.x * d.x - d.y * d.y).max(0.0).sqrt();
        self.to_world(Vec3::new(d.x, d.y, z))
    }
}

/// `path_mis`: the power heuristic.
pub fn mis(a: f32, b: f32) -> f32 {
    a * a / (a * a + b * b)
}

/// `path_luminance`.
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// `PathEval`: `f(wo, wi) cos(wi)` and the density of [`sample`] choosing `wi`.
#[derive(Clone, Copy, Debug)]
pub struct Eval {
    /// `f cos`.
    pub value: Vec3,
    /// The density.
    pub pdf: f32,
}

/// glTF's metallic-roughness model as sampled (Lambert under GGX, the metal tinting the
/// reflection), worked out once per material on the host, complements included, so the
/// shader has no `a + c * (b - a)` for its compiler to turn into a lerp of other rounding.
/// Roughness is clamped to at least [`MIN_ROUGHNESS`]; `emissive` is kept as given.
pub fn lobes(
    base: Vec3,
    metallic: f32,
    roughness: f32,
    emissive: Vec3,
    alpha: f32,
) -> PathMaterial {
    let dielectric = 1.0 - metallic;
    let diffuse = base * dielectric;
    let f0 = Vec3::splat(0.04 * dielectric) + base * metallic;
    let r = roughness.max(MIN_ROUGHNESS);
    let alpha2 = (r * r) * (r * r);
    let (ls, ld) = (luminance(f0), luminance(diffuse));
    let p_spec = if ld > 0.0 {
        (ls / (ls + ld)).clamp(0.1, 0.9)
    } else {
        1.0
    };
    PathMaterial {
        base_tex: NO_TEXTURE,
        mr_tex: NO_TEXTURE,
        base_factor: base.to_array(),
        emissive_tex: NO_TEXTURE,
        emissive_factor: emissive.to_array(),
        table: 0,
        diffuse: diffuse.to_array(),
        alpha2,
        f0: f0.to_array(),
        p_spec,
        f0c: (Vec3::ONE - f0).to_array(),
        alpha2_m1: alpha2 - 1.0,
        emissive: emissive.to_array(),
        one_m_alpha2: 1.0 - alpha2,
        p_diffuse: 1.0 - p_spec,
        base_alpha: alpha,
    }
}

fn g1(m: &PathMaterial, c: f32) -> f32 {
    2.0 * c / (c + (m.alpha2 + m.one_m_alpha2 * c * c).sqrt())
}

/// `path_eval` about the unit normal `n` on `wo`'s side.
pub fn eval(m: &PathMaterial, n: Vec3, wo: Vec3, wi: Vec3) -> Eval {
    let cos_i = dot(n, wi);
    let cos_o = dot(n, wo);
    if !(cos_i > 0.0 && cos_o > 0.0) {
        return Eval {
            value: Vec3::ZERO,
            pdf: 0.0,
        };
    }
    let h = normalize(Vec3::new(wo.x + wi.x, wo.y + wi.y, wo.z + wi.z));
    let nh = dot(n, h);
    let oh = dot(wo, h).max(1e-8);
    let dd = nh * nh * m.alpha2_m1 + 1.0;
    let d = m.alpha2 / (PI * dd * dd);
    let g = g1(m, cos_o) * g1(m, cos_i);
    let fw = 1.0 - oh;
    let fw5 = fw * fw * fw * fw * fw;
    let spec = d * g / (4.0 * cos_o);
    let diff = cos_i / PI;
    let (kd, f0, f0c) = (m.diffuse, m.f0, m.f0c);
    let value = Vec3::new(
        kd[0] * diff + (f0[0] + f0c[0] * fw5) * spec,
        kd[1] * diff + (f0[1] + f0c[1] * fw5) * spec,
        kd[2] * diff + (f0[2] + f0c[2] * fw5) * spec,
    );
    let pdf = m.p_diffuse * cos_i / PI + m.p_spec * d * nh / (4.0 * oh);
    Eval { value, pdf }
}

/// `path_sample_lobes`: a GGX normal's reflection with chance `p_spec`, else a
/// cosine-weighted direction.
pub fn sample(m: &PathMaterial, n: Vec3, wo: Vec3, r: &mut Rng) -> Vec3 {
    let f = Frame::new(n);
    if r.uniform() >= m.p_spec {
        return f.cosine(r);
    }
    let d = r.disk();
    let xi = r.uniform();
    let c2 = (1.0 - xi) / (1.0 + m.alpha2_m1 * xi);
    let cos_h = c2.sqrt();
    let sin_h = (1.0 - c2).max(0.0).sqrt();
    let len = (d.x * d.x + d.y * d.y).sqrt();
    let h = f.to_world(Vec3::new(sin_h * (d.x / len), sin_h * (d.y / len), cos_h));
    let oh2 = 2.0 * dot(wo, h);
    Vec3::new(h.x * oh2 - wo.x, h.y * oh2 - wo.y, h.z * oh2 - wo.z)
}
