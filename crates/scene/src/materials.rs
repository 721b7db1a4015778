//! A glTF file's materials as the tracer uses them: the base colour factor, and for
//! masked materials (`alphaMode` `MASK`, or `BLEND` taken as a mask at 0.5) the cutoff and
//! the base colour texture's alpha channel. Only masked materials' textures are read, and
//! only their alpha is kept.
//!
//! A texture that cannot be used (a missing or unreadable image, a format other than PNG,
//! a second texture coordinate set) is not an error: the material keeps its mask with the
//! base colour factor's alpha alone, and one warning names such materials and their images.
//! A JPEG image has no alpha, so it is read as alpha 1 everywhere without decoding it.

use std::path::Path;

use glam::{Vec3, Vec4};
use gltf::json;
use gltf::json::validation::Checked;

use crate::{AlphaMode, AlphaTexture, AlphaTextureRef, Material, Wrap};

/// The largest image file read for a mask.
const MAX_IMAGE_BYTES: u64 = 1 << 28;

/// Reads image bytes: a buffer view's (through `view`), a `data:` URI's, or a file's
/// relative to `base_dir`.
pub(crate) struct ImageSource<'a> {
    pub(crate) root: &'a json::Root,
    pub(crate) base_dir: Option<&'a Path>,
    pub(crate) view: &'a dyn Fn(usize) -> Result<Vec<u8>, String>,
}

/// The file's materials and the alpha textures the masked ones sample; warnings for what
/// could not be used.
pub(crate) fn load(
    src: &ImageSource<'_>,
    warnings: &mut Vec<String>,
) -> (Vec<Material>, Vec<AlphaTexture>) {
    let mut textures: Vec<AlphaTexture> = Vec::new();
    // glTF image index to index in `textures` (`None`: no alpha to keep).
    let mut decoded: Vec<Option<Option<usize>>> = vec![None; src.root.images.len()];
    let (mut blend, mut fallbacks) = (0, Vec::new());
    let materials = (src.root.materials.iter().enumerate())
        .map(|(i, m)| {
            let name = m.name.clone().unwrap_or_else(|| format!("material {i}"));
            let c = Vec4::from(m.pbr_metallic_roughness.base_color_factor.0);
            let base_color = if c.is_finite() { c } else { Vec4::ONE };
            let cutoff = m.alpha_cutoff.map_or(0.5, |c| c.0);
            let cutoff = if cutoff.is_finite() && cutoff >= 0.0 {
                cutoff
            } else {
                0.5
            };
            use json::material::AlphaMode as G;
            let alpha_mode = match m.alpha_mode {
                Checked::Valid(G::Mask) => AlphaMode::Mask { cutoff },
                Checked::Valid(G::Blend) => {
                    blend += 1;
                    AlphaMode::Mask { cutoff: 0.5 }
                }
                _ => AlphaMode::Opaque,
            };
            let alpha_texture = match (alpha_mode, &m.pbr_metallic_roughness.base_color_texture) {
                (AlphaMode::Mask { .. }, Some(info)) => {
                    let what = format!("material {i} ({name})");
                    texture(
                        src,
                        info,
                        &what,
                        &mut decoded,
                        &mut textures,
                        &mut fallbacks,
                    )
                    .map(|t| AlphaTextureRef::of(src.root, info, t))
                }
                _ => None,
            };
            let pbr = &m.pbr_metallic_roughness;
            let strength = (m.extensions.as_ref())
                .and_then(|e| e.emissive_strength.as_ref())
                .map_or(1.0, |s| s.emissive_strength.0);
            Material {
                name,
                base_color,
                metallic: unit_or(pbr.metallic_factor.0, 0.0),
                roughness: unit_or(pbr.roughness_factor.0, 1.0),
                emissive: (Vec3::from(m.emissive_factor.0) * strength)
                    .map(|c| if c.is_finite() { c.max(0.0) } else { 0.0 }),
                alpha_mode,
                alpha_texture,
            }
        })
        .collect();
    if let Some(first) = fallbacks.first() {
        let more = match fallbacks.len() {
            1 => String::new(),
            n => format!(" and {} more", n - 1),
        };
        warnings.push(format!(
            "{} masked material(s) are cut by the base colour factor's alpha alone, their \
             texture unusable: {first}{more}",
            fallbacks.len()
        ));
    }
    if blend > 0 {
        warnings.push(format!(
            "{blend} material(s) with alphaMode BLEND are traced as MASK at alpha 0.5"
        ));
    }
    (materials, textures)
}

/// `x` clamped to `[0, 1]`, `nan` for NaN.
fn unit_or(x: f32, nan: f32) -> f32 {
    if x.is_nan() { nan } else { x.clamp(0.0, 1.0) }
}

/// The alpha texture of a masked material's base colour texture `info`, decoded once per
/// image; `None` (with a warning naming `what`) when it cannot be used or has no alpha.
fn texture(
    src: &ImageSource<'_>,
    info: &json::texture::Info,
    what: &str,
    decoded: &mut [Option<Option<usize>>],
    textures: &mut Vec<AlphaTexture>,
    warnings: &mut Vec<String>,
) -> Option<usize> {
    let root = src.root;
    let mut warn = |why: String| warnings.push(format!("{what}: {why}"));
    if info.tex_coord != 0 {
        warn(format!(
            "it reads TEXCOORD_{}, only TEXCOORD_0 is kept",
            info.tex_coord
        ));
        return None;
    }
    let ti = info.index.value();
    let Some(tex) = root.textures.get(ti) else {
        warn(format!("texture {ti} does not exist"));
        return None;
    };
    let ii = tex.source.value();
    let Some(slot) = decoded.get_mut(ii) else {
        warn(format!("texture {ti}'s image {ii} does not exist"));
        return None;
    };
    if let Some(done) = *slot {
        return done;
    }
    let image = &root.images[ii];
    let label = image
        .name
        .clone()
        .or_else(|| image.uri.clone().filter(|u| !u.starts_with("data:")));
    let label = label.unwrap_or_else(|| format!("image {ii}"));
    let made = image_bytes(src, image)
        .and_then(|bytes| alpha_of(&bytes))
        .map(|alpha| {
            alpha.map(|(width, height, alpha)| {
                textures.push(AlphaTexture {
                    name: label.clone(),
                    width,
                    height,
                    alpha,
                });
                textures.len() - 1
            })
        });
    let got = made.unwrap_or_else(|e| {
        warn(format!("image {ii} ({label}): {e}"));
        None
    });
    *slot = Some(got);
    got
}

/// An image's encoded bytes.
fn image_bytes(src: &ImageSource<'_>, image: &json::Image) -> Result<Vec<u8>, String> {
    if let Some(v) = image.buffer_view {
        return (src.view)(v.value());
    }
    match image.uri.as_deref() {
        Some(u) if u.starts_with("data:") => crate::loader::decode_data_uri(u),
        Some(u) if crate::loader::is_remote(u) => Err("remote images are not fetched".into()),
        Some(u) => match src.base_dir {
            Some(dir) => {
                let path = dir.join(crate::loader::percent_decode(u));
                crate::loader::read_buffer_file(&path, MAX_IMAGE_BYTES)
            }
            None => Err("an external file, and the scene was given as bytes".into()),
        },
        None => Err("it has neither a buffer view nor a URI".into()),
    }
}

/// Width, height and alpha of an encoded image; `None` for a JPEG (no alpha channel).
fn alpha_of(bytes: &[u8]) -> Result<Option<(u32, u32, Vec<u8>)>, String> {
    if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
        return Ok(None);
    }
    let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| format!("not a readable PNG: {e}"))?;
    let (width, height) = (img.width(), img.height());
    if width == 0 || height == 0 {
        return Err("it has no texels".into());
    }
    let alpha = img.to_rgba8().pixels().map(|p| p.0[3]).collect();
    Ok(Some((width, height, alpha)))
}

/// A sampler's wrap modes (`REPEAT` where it has none or an unknown one).
pub(crate) fn wraps(root: &json::Root, info: &json::texture::Info) -> [Wrap; 2] {
    let sampler = (root.textures.get(info.index.value()))
        .and_then(|t| t.sampler)
        .and_then(|s| root.samplers.get(s.value()));
    let mode = |w: &Checked<json::texture::WrappingMode>| match w {
        Checked::Valid(m) => Wrap::from_gl(m.as_gl_enum()).unwrap_or_default(),
        Checked::Invalid => Wrap::Repeat,
    };
    sampler.map_or([Wrap::Repeat; 2], |s| [mode(&s.wrap_s), mode(&s.wrap_t)])
}

impl AlphaTextureRef {
    /// The reference to `texture` with `info`'s sampler's wrap modes.
    pub(crate) fn of(
        root: &json::Root,
        info: &json::texture::Info,
        texture: usize,
    ) -> AlphaTextureRef {
        AlphaTextureRef {
            texture,
            wrap: wraps(root, info),
        }
    }
}
