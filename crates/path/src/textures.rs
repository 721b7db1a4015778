//! The material textures as the path tracer reads them: one array of words
//! (`path_data` in `shaders/path_trace.wgsl`) holding each primitive's texture
//! coordinates, the sRGB table, the textures' headers and texels, and each textured
//! material's table; and the twin of `path_textured`, the material at a hit.
//!
//! Sampling is the nearest texel (`bvhtrace_core::alpha::texel_index`, as the alpha masks
//! sample), exact in f32 on both sides. A texel's colour is decoded from sRGB by a table
//! the host computes, and each complement the lobes need (`1 - metallic`,
//! `1 - alpha^2`, ...) comes from the material's table, indexed by the texel's byte, so
//! the shader writes no `1 - x` for its compiler to fold into a lerp of its own rounding.

use bvhtrace_core::alpha::{Wrap, interpolate_uv, texel_index};
use bvhtrace_core::mesh::TriangleMesh;
use bvhtrace_scene::{FlatAttributes, Scene, TextureRef};
use glam::{Vec2, Vec3};

use crate::material::{NO_TEXTURE, PathMaterial};
use crate::sampling::{MIN_ROUGHNESS, luminance};

/// Words of a material's table: 256 roughness entries, then 256 metalness entries, four
/// words each.
const TABLE_WORDS: usize = 2048;

/// Words before the data: the offsets of the texture coordinates, the sRGB table, the
/// textures' headers and the environment map ([`crate::PathScene::set_environment`]), 0
/// for none; then those of the materials, primitives and lights, which the device's
/// upload appends (`GpuPathTracer`).
pub const HEADER_WORDS: usize = 7;

/// The texture data (`path_data`): see the module's documentation.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TextureData {
    /// The words.
    pub words: Vec<u32>,
}

fn wrap_code(w: Wrap) -> u32 {
    match w {
        Wrap::Repeat => 0,
        Wrap::ClampToEdge => 1,
        Wrap::MirroredRepeat => 2,
    }
}

/// sRGB-encoded byte to linear.
fn srgb_to_linear(c: u32) -> f32 {
    let x = c as f32 / 255.0;
    if x <= 0.04045 {
        x / 12.92
    } else {
        ((x + 0.055) / 1.055).powf(2.4)
    }
}

impl TextureData {
    /// The data of `scene`, whose `triangles` primitives number its flattened triangles
    /// (the mesh and attributes of `Scene::flatten_with_attributes`), for `materials`
    /// (their texture slots and tables filled in here). Empty words but the
    /// [`HEADER_WORDS`] offsets when no material has a texture.
    pub fn new(
        scene: &Scene,
        (mesh, attributes): (&TriangleMesh, &FlatAttributes),
        materials: &mut [PathMaterial],
        triangles: usize,
    ) -> TextureData {
        let textured = |m: &bvhtrace_scene::Material| {
            m.base_color_texture.is_some()
                || m.metallic_roughness_texture.is_some()
                || m.emissive_texture.is_some()
        };
        let mut words = vec![0u32; HEADER_WORDS];
        if !scene.materials.iter().any(textured) {
            return TextureData { words };
        }
        // Texture coordinates: three corners a primitive, flattened like the triangles.
        words[0] = words.len() as u32;
        for i in 0..triangles {
            let corners = mesh.indices.get(i).copied().unwrap_or([0; 3]);
            for c in corners {
                let uv = attributes
                    .texcoords
                    .get(c as usize)
                    .copied()
                    .unwrap_or(Vec2::ZERO);
                words.extend([uv.x.to_bits(), uv.y.to_bits()]);
            }
        }
        words[1] = words.len() as u32;
        words.extend((0..256).map(|c| srgb_to_linear(c).to_bits()));
        // Headers, then texels.
        words[2] = words.len() as u32;
        let headers = words.len();
        words.resize(headers + 4 * scene.textures.len(), 0);
        for (i, t) in scene.textures.iter().enumerate() {
            let h = headers + 4 * i;
            words[h] = words.len() as u32;
            words[h + 1] = t.width.max(1);
            words[h + 2] = t.height.max(1);
            let texels = (t.width as usize * t.height as usize).max(1);
            words.extend((0..texels).map(|k| {
                let p = t.rgba.get(4 * k..4 * k + 4).unwrap_or(&[255; 4]);
                u32::from_le_bytes([p[0], p[1], p[2], p[3]])
            }));
        }
        let slot = |r: &Option<TextureRef>, words: &mut Vec<u32>| match r {
            Some(r) if r.texture < scene.textures.len() => {
                let h = headers + 4 * r.texture;
                words[h + 3] = wrap_code(r.wrap[0]) | (wrap_code(r.wrap[1]) << 2);
                r.texture as u32
            }
            _ => NO_TEXTURE,
        };
        for (m, pm) in scene.materials.iter().zip(materials.iter_mut()) {
            if !textured(m) {
                continue;
            }
            pm.base_tex = slot(&m.base_color_texture, &mut words);
            pm.mr_tex = slot(&m.metallic_roughness_texture, &mut words);
            pm.emissive_tex = slot(&m.emissive_texture, &mut words);
            pm.table = words.len() as u32;
            words.extend(table(m.metallic, m.roughness));
        }
        TextureData { words }
    }
}

/// A material's table: for each byte `g` of a roughness texel and `b` of a metalness texel
/// (255 where there is no texture), the lobes' values, as `sampling::lobes` computes them.
fn table(metallic: f32, roughness: f32) -> Vec<u32> {
    let unit = |x: f32, nan: f32| if x.is_nan() { nan } else { x.clamp(0.0, 1.0) };
    let (metallic, roughness) = (unit(metallic, 0.0), unit(roughness, 1.0));
    let mut t = Vec::with_capacity(TABLE_WORDS);
    for g in 0..256 {
        let r = (roughness * (g as f32 / 255.0)).max(MIN_ROUGHNESS);
        let alpha2 = (r * r) * (r * r);
        t.extend([alpha2, alpha2 - 1.0, 1.0 - alpha2, 0.0].map(f32::to_bits));
    }
    for b in 0..256 {
        let m = metallic * (b as f32 / 255.0);
        let dielectric = 1.0 - m;
        let c1 = 0.04 * dielectric;
        t.extend([m, dielectric, c1, 1.0 - c1].map(f32::to_bits));
    }
    t
}

/// The twin of `path_texel`: the RGBA8 texel of texture `t` nearest `uv`.
fn texel(words: &[u32], t: u32, uv: Vec2) -> [u32; 4] {
    let h = words[2] as usize + 4 * t as usize;
    let (w, ht, wraps) = (words[h + 1], words[h + 2], words[h + 3]);
    let wrap = |c: u32| match c {
        1 => Wrap::ClampToEdge,
        2 => Wrap::MirroredRepeat,
        _ => Wrap::Repeat,
    };
    let x = texel_index(uv.x, w, wrap(wraps & 3));
    let y = texel_index(uv.y, ht, wrap(wraps >> 2));
    let c = words[words[h] as usize + (y * w + x) as usize];
    [c & 255, (c >> 8) & 255, (c >> 16) & 255, c >> 24]
}

fn srgb(words: &[u32], c: [u32; 4]) -> Vec3 {
    let t = words[1] as usize;
    let f = |i: u32| f32::from_bits(words[t + i as usize]);
    Vec3::new(f(c[0]), f(c[1]), f(c[2]))
}

/// The twin of `path_textured`: material `m` at barycentrics `u`, `v` of `prim`.
pub fn textured(m: &PathMaterial, data: &TextureData, prim: u32, u: f32, v: f32) -> PathMaterial {
    if m.base_tex == NO_TEXTURE && m.mr_tex == NO_TEXTURE && m.emissive_tex == NO_TEXTURE {
        return *m;
    }
    let w = &data.words;
    let b = w[0] as usize + 6 * prim as usize;
    let c = |k: usize| f32::from_bits(w[b + k]);
    let corners = [
        Vec2::new(c(0), c(1)),
        Vec2::new(c(2), c(3)),
        Vec2::new(c(4), c(5)),
    ];
    let uv = interpolate_uv(&corners, u, v);
    let mut base = Vec3::from(m.base_factor);
    if m.base_tex != NO_TEXTURE {
        let t = srgb(w, texel(w, m.base_tex, uv));
        base = Vec3::new(base.x * t.x, base.y * t.y, base.z * t.z);
    }
    let (mut g, mut bm) = (255, 255);
    if m.mr_tex != NO_TEXTURE {
        let t = texel(w, m.mr_tex, uv);
        (g, bm) = (t[1], t[2]);
    }
    let word = |i: usize| f32::from_bits(w[i]);
    let r = m.table as usize + 4 * g as usize;
    let k = m.table as usize + 1024 + 4 * bm as usize;
    let mut out = *m;
    out.alpha2 = word(r);
    out.alpha2_m1 = word(r + 1);
    out.one_m_alpha2 = word(r + 2);
    let (metallic, dielectric, c1, e1) = (word(k), word(k + 1), word(k + 2), word(k + 3));
    let diffuse = Vec3::new(
        base.x * dielectric,
        base.y * dielectric,
        base.z * dielectric,
    );
    let f0 = Vec3::new(
        c1 + base.x * metallic,
        c1 + base.y * metallic,
        c1 + base.z * metallic,
    );
    out.diffuse = diffuse.to_array();
    out.f0 = f0.to_array();
    out.f0c = [
        e1 - base.x * metallic,
        e1 - base.y * metallic,
        e1 - base.z * metallic,
    ];
    let (ls, ld) = (luminance(f0), luminance(diffuse));
    let p = if ld > 0.0 {
        (ls / (ls + ld)).clamp(0.1, 0.9)
    } else {
        1.0
    };
    out.p_spec = p;
    out.p_diffuse = 1.0 - p;
    if m.emissive_tex != NO_TEXTURE {
        let t = srgb(w, texel(w, m.emissive_tex, uv));
        let e = m.emissive_factor;
        out.emissive = [e[0] * t.x, e[1] * t.y, e[2] * t.z];
    }
    out
}
