//! A glTF file's materials as the tracer uses them: the factors (base colour, metallic,
//! roughness, emission), the base colour, metallic-roughness, emissive and normal
//! textures, and for masked materials (`alphaMode` `MASK`, or `BLEND` taken as a mask at
//! 0.5) the cutoff and the base colour texture's alpha channel.
//!
//! Each image a material samples is decoded once (PNG or JPEG, through `image`) into a
//! [`Texture`]. A masked material's alpha texture is its base colour image's alpha
//! channel; a JPEG has none, so it cuts by the factor alone, as if its alpha were 1.
//!
//! A texture that cannot be used (a missing or unreadable image, another format, a second
//! texture coordinate set, too many texels) is not an error: the material keeps its
//! factors (a masked one is cut by the base colour factor's alpha alone), and one warning
//! names such materials and their images.

use std::path::Path;

use glam::{Vec3, Vec4};
use gltf::json;
use gltf::json::validation::Checked;

use crate::{AlphaMode, AlphaTexture, AlphaTextureRef, Material, Texture, TextureRef, Wrap};

/// The largest image file read for a texture.
const MAX_IMAGE_BYTES: u64 = 1 << 28;

/// The most texels a texture may have (8192 x 8192, 256 MiB decoded): larger ones are
/// left out rather than risking the memory of a whole scene on one image.
#[cfg(feature = "textures")]
const MAX_TEXELS: u64 = 1 << 26;

/// How many unusable textures the warning names one by one.
const NAMED: usize = 10;

/// Reads image bytes: a buffer view's (through `view`), a `data:` URI's, or a file's
/// relative to `base_dir`.
pub(crate) struct ImageSource<'a> {
    pub(crate) root: &'a json::Root,
    pub(crate) base_dir: Option<&'a Path>,
    pub(crate) view: &'a dyn Fn(usize) -> Result<Vec<u8>, String>,
}

/// What [`load`] gives: the file's materials, the alpha textures masked ones sample,
/// and the textures all of them sample.
pub(crate) struct Loaded {
    pub(crate) materials: Vec<Material>,
    pub(crate) alpha_textures: Vec<AlphaTexture>,
    pub(crate) textures: Vec<Texture>,
}

/// The file's materials and the textures they sample; warnings for what could not be
/// used.
pub(crate) fn load(src: &ImageSource<'_>, warnings: &mut Vec<String>) -> Loaded {
    let mut images = Images {
        src,
        images: vec![None; src.root.images.len()],
        textures: Vec::new(),
        alpha_textures: Vec::new(),
        unusable: Vec::new(),
        masked_fallbacks: 0,
    };
    let mut blend = 0;
    let materials = (src.root.materials.iter().enumerate())
        .map(|(i, m)| material(&mut images, i, m, &mut blend))
        .collect();
    let unusable = &images.unusable;
    if !unusable.is_empty() {
        let n = unusable.len();
        let masked = match images.masked_fallbacks {
            0 => String::new(),
            k => {
                format!(" ({k} masked material(s) are cut by the base colour factor's alpha alone)")
            }
        };
        let more = match n.saturating_sub(NAMED) {
            0 => String::new(),
            k => format!("; and {k} more"),
        };
        warnings.push(format!(
            "{n} material texture(s) are unusable, their materials keep their factors\
             {masked}: {}{more}",
            unusable[..n.min(NAMED)].join("; ")
        ));
    }
    if blend > 0 {
        warnings.push(format!(
            "{blend} material(s) with alphaMode BLEND are traced as MASK at alpha 0.5"
        ));
    }
    Loaded {
        materials,
        alpha_textures: images.alpha_textures,
        textures: images.textures,
    }
}

/// Material `i`, `m`, with its textures; counts it in `blend` when its `alphaMode` is
/// `BLEND`.
fn material(
    images: &mut Images<'_, '_>,
    i: usize,
    m: &json::Material,
    blend: &mut usize,
) -> Material {
    let name = m.name.clone().unwrap_or_else(|| format!("material {i}"));
    let pbr = &m.pbr_metallic_roughness;
    let c = Vec4::from(pbr.base_color_factor.0);
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
            *blend += 1;
            AlphaMode::Mask { cutoff: 0.5 }
        }
        _ => AlphaMode::Opaque,
    };
    let what = format!("material {i} ({name})");
    let mut slot = |label: &str, info: Option<&json::texture::Info>| {
        info.and_then(|t| images.texture(&format!("{what} {label}"), t.index.value(), t.tex_coord))
    };
    let base = slot("base colour", pbr.base_color_texture.as_ref());
    let metallic_roughness = slot(
        "metallic-roughness",
        pbr.metallic_roughness_texture.as_ref(),
    );
    let emissive = slot("emissive", m.emissive_texture.as_ref());
    let normal = (m.normal_texture.as_ref())
        .and_then(|t| images.texture(&format!("{what} normal"), t.index.value(), t.tex_coord));
    let alpha_texture = match (alpha_mode, base, &pbr.base_color_texture) {
        (AlphaMode::Mask { .. }, Some((image, r)), _) => {
            images.alpha(image).map(|texture| AlphaTextureRef {
                texture,
                wrap: r.wrap,
            })
        }
        (AlphaMode::Mask { .. }, None, Some(_)) => {
            images.masked_fallbacks += 1;
            None
        }
        _ => None,
    };
    let strength = (m.extensions.as_ref())
        .and_then(|e| e.emissive_strength.as_ref())
        .map_or(1.0, |s| s.emissive_strength.0);
    let normal_scale = m.normal_texture.as_ref().map_or(1.0, |t| t.scale);
    Material {
        name,
        base_color,
        metallic: unit_or(pbr.metallic_factor.0, 0.0),
        roughness: unit_or(pbr.roughness_factor.0, 1.0),
        emissive: (Vec3::from(m.emissive_factor.0) * strength)
            .map(|c| if c.is_finite() { c.max(0.0) } else { 0.0 }),
        alpha_mode,
        alpha_texture,
        base_color_texture: base.map(|(_, r)| r),
        metallic_roughness_texture: metallic_roughness.map(|(_, r)| r),
        emissive_texture: emissive.map(|(_, r)| r),
        normal_texture: normal.map(|(_, r)| r),
        normal_scale: if normal_scale.is_finite() {
            normal_scale
        } else {
            1.0
        },
    }
}

/// `x` clamped to `[0, 1]`, `nan` for NaN.
fn unit_or(x: f32, nan: f32) -> f32 {
    if x.is_nan() { nan } else { x.clamp(0.0, 1.0) }
}

/// A glTF image once decoded.
#[derive(Clone, Copy)]
struct Decoded {
    /// Index into [`Images::textures`].
    texture: usize,
    /// Whether its alpha can cut: false for a JPEG, which has no alpha channel.
    has_alpha: bool,
    /// Index into [`Images::alpha_textures`], once a masked material has sampled it.
    alpha: Option<usize>,
}

/// The images materials sample, each decoded at most once, and what could not be used.
struct Images<'a, 'b> {
    src: &'a ImageSource<'b>,
    /// Per glTF image: not read yet (`None`), decoded, or why it cannot be used.
    images: Vec<Option<Result<Decoded, String>>>,
    textures: Vec<Texture>,
    alpha_textures: Vec<AlphaTexture>,
    /// One line per unusable texture slot: the material, the slot and why.
    unusable: Vec<String>,
    /// Masked materials left to the base colour factor's alpha by an unusable texture.
    masked_fallbacks: usize,
}

impl Images<'_, '_> {
    /// Texture `index` read through `TEXCOORD_{tex_coord}` for `what` (a material's slot):
    /// its glTF image and reference, or `None` with the reason recorded.
    fn texture(&mut self, what: &str, index: usize, tex_coord: u32) -> Option<(usize, TextureRef)> {
        match self.image(index, tex_coord) {
            Ok((image, d)) => Some((
                image,
                TextureRef {
                    texture: d.texture,
                    wrap: wraps(self.src.root, index),
                },
            )),
            Err(why) => {
                self.unusable.push(format!("{what}: {why}"));
                None
            }
        }
    }

    /// The glTF image texture `index` samples, decoded on first use.
    fn image(&mut self, index: usize, tex_coord: u32) -> Result<(usize, Decoded), String> {
        if tex_coord != 0 {
            return Err(format!(
                "it reads TEXCOORD_{tex_coord}, only TEXCOORD_0 is kept"
            ));
        }
        let root = self.src.root;
        let tex =
            (root.textures.get(index)).ok_or_else(|| format!("texture {index} does not exist"))?;
        let ii = tex.source.value();
        let (Some(image), Some(slot)) = (root.images.get(ii), self.images.get(ii)) else {
            return Err(format!("texture {index}'s image {ii} does not exist"));
        };
        if let Some(done) = slot {
            return done.clone().map(|d| (ii, d));
        }
        let label =
            (image.name.clone()).or_else(|| image.uri.clone().filter(|u| !u.starts_with("data:")));
        let named = label.as_ref().map_or(String::new(), |l| format!(" ({l})"));
        let label = label.unwrap_or_else(|| format!("image {ii}"));
        let made = image_bytes(self.src, image)
            .and_then(|bytes| decode(&bytes, label))
            .map(|(texture, has_alpha)| {
                self.textures.push(texture);
                Decoded {
                    texture: self.textures.len() - 1,
                    has_alpha,
                    alpha: None,
                }
            })
            .map_err(|e| format!("image {ii}{named}: {}", e.trim_end()));
        self.images[ii] = Some(made.clone());
        made.map(|d| (ii, d))
    }

    /// The alpha texture of decoded glTF image `image`, for a masked material: made on
    /// first use; `None` for an image without alpha (a JPEG).
    fn alpha(&mut self, image: usize) -> Option<usize> {
        let Some(Some(Ok(d))) = self.images.get_mut(image) else {
            return None;
        };
        if d.alpha.is_some() || !d.has_alpha {
            return d.alpha;
        }
        let t = self.textures.get(d.texture)?;
        self.alpha_textures.push(AlphaTexture {
            name: t.name.clone(),
            width: t.width,
            height: t.height,
            alpha: t.rgba.chunks_exact(4).map(|p| p[3]).collect(),
        });
        d.alpha = Some(self.alpha_textures.len() - 1);
        d.alpha
    }
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
                // The warning names the URI already: no need for the whole path.
                match std::fs::metadata(&path) {
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                        Err("the file is missing".into())
                    }
                    Ok(m) if m.len() > MAX_IMAGE_BYTES => Err(format!(
                        "the file has {} bytes, more than the {MAX_IMAGE_BYTES} read for an image",
                        m.len()
                    )),
                    _ => crate::loader::read_buffer_file(&path, MAX_IMAGE_BYTES),
                }
            }
            None => Err("an external file, and the scene was given as bytes".into()),
        },
        None => Err("it has neither a buffer view nor a URI".into()),
    }
}

/// Without the `textures` feature no image is decoded: the texture is left out, with a
/// warning, as an unreadable one is.
#[cfg(not(feature = "textures"))]
fn decode(_bytes: &[u8], _name: String) -> Result<(Texture, bool), String> {
    Err("textures are left out of this build (bvhtrace-scene's `textures` feature)".into())
}

/// An encoded PNG or JPEG image as an 8-bit RGBA texture named `name`, and whether its
/// alpha can cut (false for a JPEG).
#[cfg(feature = "textures")]
fn decode(bytes: &[u8], name: String) -> Result<(Texture, bool), String> {
    use image::ImageFormat;
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| format!("not a readable PNG or JPEG: {e}"))
    };
    let format = reader()?.format();
    let kind = match format {
        Some(ImageFormat::Png) => "PNG",
        Some(ImageFormat::Jpeg) => "JPEG",
        Some(other) => return Err(format!("a {other:?} image: only PNG and JPEG are read")),
        None => return Err("not a readable PNG or JPEG (unknown format)".into()),
    };
    // The header first: a huge image is refused before its texels are allocated.
    let (width, height) =
        (reader()?.into_dimensions()).map_err(|e| format!("not a readable {kind}: {e}"))?;
    if width == 0 || height == 0 {
        return Err("it has no texels".into());
    }
    if u64::from(width) * u64::from(height) > MAX_TEXELS {
        return Err(format!(
            "{width} x {height} texels, more than the {MAX_TEXELS} a texture may have"
        ));
    }
    let img = image::load_from_memory(bytes).map_err(|e| format!("not a readable {kind}: {e}"))?;
    let rgba = img.into_rgba8();
    let texture = Texture {
        name,
        width: rgba.width(),
        height: rgba.height(),
        rgba: rgba.into_raw(),
    };
    Ok((texture, format == Some(ImageFormat::Png)))
}

/// Texture `index`'s sampler's wrap modes (`REPEAT` where it has none or an unknown one).
pub(crate) fn wraps(root: &json::Root, index: usize) -> [Wrap; 2] {
    let sampler = (root.textures.get(index))
        .and_then(|t| t.sampler)
        .and_then(|s| root.samplers.get(s.value()));
    let mode = |w: &Checked<json::texture::WrappingMode>| match w {
        Checked::Valid(m) => Wrap::from_gl(m.as_gl_enum()).unwrap_or_default(),
        Checked::Invalid => Wrap::Repeat,
    };
    sampler.map_or([Wrap::Repeat; 2], |s| [mode(&s.wrap_s), mode(&s.wrap_t)])
}
