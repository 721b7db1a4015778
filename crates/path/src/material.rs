//! A material as the kernel reads it: the GPU type shared by the scene's shading data, the
//! sampling twin and the textures (WGSL `PathMaterial` in `shaders/path_sampling.wgsl`).

use bytemuck::{Pod, Zeroable};

/// A material as the path tracer samples it (WGSL `PathMaterial`, 112 bytes): glTF's
/// metallic-roughness worked out into its lobes ([`crate::sampling::lobes`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct PathMaterial {
    /// The Lambert lobe's albedo: base colour times `1 - metallic`.
    pub diffuse: [f32; 3],
    /// GGX's `alpha^2` (`alpha` is roughness squared).
    pub alpha2: f32,
    /// Reflectance at normal incidence: 0.04 for a dielectric, the base colour for a metal.
    pub f0: [f32; 3],
    /// The chance of sampling the specular lobe.
    pub p_spec: f32,
    /// `1 - f0`.
    pub f0c: [f32; 3],
    /// `alpha^2 - 1`.
    pub alpha2_m1: f32,
    /// Emitted radiance.
    pub emissive: [f32; 3],
    /// `1 - alpha^2`.
    pub one_m_alpha2: f32,
    /// `1 - p_spec`.
    pub p_diffuse: f32,
    /// The base colour's alpha (masks cut in the walk; kept for reports).
    pub base_alpha: f32,
    /// The base colour texture's index in the textures ([`NO_TEXTURE`] for none).
    pub base_tex: u32,
    /// The metallic-roughness texture's ([`NO_TEXTURE`] for none).
    pub mr_tex: u32,
    /// The base colour factor, which a texture's linear colour multiplies.
    pub base_factor: [f32; 3],
    /// The emissive texture's ([`NO_TEXTURE`] for none).
    pub emissive_tex: u32,
    /// The emissive factor, which a texture's linear colour multiplies.
    pub emissive_factor: [f32; 3],
    /// The offset of a textured material's table in the texture data
    /// ([`crate::textures::TextureData`]).
    pub table: u32,
}

/// A material slot without a texture.
pub const NO_TEXTURE: u32 = u32::MAX;
