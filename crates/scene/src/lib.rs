//! Scenes for bvhtrace: glTF 2.0 loading, procedural (`builtin:`) scenes, the shared
//! camera and ray convention, and a small glTF exporter.
//!
//! # Scene specs
//!
//! [`load`] takes a *spec*:
//!
//! - a path to a `.gltf` (JSON, with external `.bin` files or `data:` URIs) or `.glb` file;
//! - `builtin:NAME`, one of [`builtin_names`] (for example [`DEFAULT_SCENE`],
//!   `builtin:icosphere:4`, `builtin:grid:igea:3x3`);
//! - either of the above followed by any number of transform suffixes, applied to the
//!   whole scene (its instances and its camera) from left to right:
//!   - `#scale=S`: uniform scale by `S` about the origin (finite, non-zero);
//!   - `#offset=X,Y,Z`: translation by `(X, Y, Z)`.
//!
//!   For example `builtin:cornell#scale=1e-3#offset=1e6,0,0` is the Cornell box one
//!   thousand times smaller, a million units along +x: for tiny-scale and huge-offset
//!   precision tests. A `#` that is not followed by `scale=` or `offset=` is part of the
//!   path.
//!
//! # What a scene holds
//!
//! A [`Scene`] is a list of [`Mesh`]es in their own (object) space and a list of
//! [`Instance`]s placing them in the world: a glTF mesh used by several nodes is loaded
//! once. [`Scene::flatten`] gives the world-space [`TriangleMesh`] the BVH builders take.
//! [`Attributes`] says which optional per-vertex data (normals, texture coordinates,
//! colours) and per-triangle materials the scene has: when a flag is set, *every* mesh has
//! that array, filled with defaults where the source had none. [`Material`]s hold glTF's
//! metallic-roughness factors and their base colour, metallic-roughness, emissive and
//! normal textures, decoded once each (PNG and JPEG) into [`Scene::textures`].
//!
//! # Animation
//!
//! A glTF file's node animations (translation, rotation, scale and morph target weights
//! channels; LINEAR, STEP and CUBICSPLINE), skins and morph targets are kept in
//! [`Scene::animation`]: [`Scene::instances`] holds the nodes' static transforms as
//! loaded, and the skinned or morphed meshes their static pose; [`Scene::set_time`] moves
//! them to any time and [`Scene::instance_transforms_at`] computes the transforms without
//! changing the scene (see the [`animation`] module).
//!
//! The library prints nothing: anything worth telling the user that is not an error
//! lands in [`Scene::warnings`].
#![warn(missing_docs)]

pub mod animation;
mod builtin;
pub mod camera;
mod error;
mod export;
mod glb;
mod hair;
mod loader;
mod masks;
mod materials;
mod shutter;
mod two_level;

use std::path::{Path, PathBuf};

use bvhtrace_core::alpha::AlphaMask;
pub use bvhtrace_core::alpha::Wrap;
use bvhtrace_core::curves::Curves;
use bvhtrace_core::mesh::TriangleMesh;
use glam::{Mat4, Vec2, Vec3, Vec4};

pub use animation::{
    Animation, AnimationNode, Channel, Deformed, Interpolation, Morph, NodeTransform, Property,
    Skin, morph_vertex, skin_vertex,
};
pub use builtin::{builtin_names, icosphere};
pub use camera::Camera;
pub use error::{ErrorKind, SceneError};
pub use export::{glb_bytes, gltf_embedded_string, write_glb, write_gltf_embedded};
pub use hair::{DEFAULT_STRANDS, hair_file_bytes, has_curves, load_hair_file};
pub use loader::{load_gltf_file, load_gltf_slice};
pub use shutter::SHUTTER_TOLERANCE;
pub use two_level::{SceneBvh, TracingBvhError};

/// The scene tools load when given none: the Cornell box.
pub const DEFAULT_SCENE: &str = "builtin:cornell";

/// The most triangles a scene may have over all its instances (the BVH's limit).
pub const MAX_TRIANGLES: usize = (1 << 30) - 1;

/// The most triangles over all instances a scene may place: a two-level BVH numbers them
/// with 32-bit primitive ids below the miss codes. Scenes past [`MAX_TRIANGLES`] can only
/// be traced in two levels ([`Scene::instanced_bvh`]), not flattened.
pub const MAX_INSTANCED_TRIANGLES: usize = bvhtrace_core::INCOMPLETE as usize - 1;

/// Which optional arrays the scene has. When a flag is set, every [`Mesh`] of the scene
/// has that array (filled with defaults where its source had none); when it is clear,
/// every mesh's array is empty. Later stages upload only what exists.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Attributes {
    /// [`Mesh::normals`]: one unit normal per vertex (glTF `NORMAL`; computed,
    /// area-weighted, where a mesh had none).
    pub normals: bool,
    /// [`Mesh::texcoords`]: one per vertex (glTF `TEXCOORD_0`; zero where absent).
    pub texcoords: bool,
    /// [`Mesh::colors`]: one linear RGBA colour per vertex (glTF `COLOR_0`; white where absent).
    pub colors: bool,
    /// [`Mesh::materials`]: one index into [`Scene::materials`] per triangle.
    pub materials: bool,
}

/// A material: only what the tracer shades with, and what cuts its surface. Each
/// texture, where there is one, multiplies its factor.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// The material's name (may be empty).
    pub name: String,
    /// Linear RGBA base colour factor (glTF `pbrMetallicRoughness.baseColorFactor`).
    pub base_color: Vec4,
    /// Metalness in `[0, 1]` (glTF `metallicFactor`; NaN or out of range is clamped, NaN
    /// to 0).
    pub metallic: f32,
    /// Perceptual roughness in `[0, 1]` (glTF `roughnessFactor`; clamped as `metallic`,
    /// NaN to 1).
    pub roughness: f32,
    /// Linear emitted radiance (glTF `emissiveFactor`): zero for a surface that does not
    /// glow; negative or non-finite components read as 0.
    pub emissive: Vec3,
    /// Whether its alpha cuts the surface (glTF `alphaMode`, `alphaCutoff`).
    pub alpha_mode: AlphaMode,
    /// The base colour texture's alpha, for a masked material that has one.
    pub alpha_texture: Option<AlphaTextureRef>,
    /// The base colour texture (glTF `baseColorTexture`): sRGB-encoded RGB, linear
    /// alpha; the surface's colour is [`Material::base_color`] times the texel decoded to
    /// linear.
    pub base_color_texture: Option<TextureRef>,
    /// The metallic-roughness texture (glTF `metallicRoughnessTexture`): linear;
    /// roughness is [`Material::roughness`] times G, metalness [`Material::metallic`]
    /// times B.
    pub metallic_roughness_texture: Option<TextureRef>,
    /// The emissive texture (glTF `emissiveTexture`): sRGB-encoded RGB; the emission is
    /// [`Material::emissive`] times the texel decoded to linear.
    pub emissive_texture: Option<TextureRef>,
    /// The normal map (glTF `normalTexture`): linear RGB `c` holds the tangent-space
    /// normal `2 c - 1`, its x and y scaled by [`Material::normal_scale`]. The scene keeps
    /// no tangents (glTF `TANGENT` is not loaded): derive them as glTF asks where a file
    /// has none, MikkTSpace over the positions, normals and texture coordinates.
    pub normal_texture: Option<TextureRef>,
    /// glTF `normalTexture.scale` (1 when absent or not finite).
    pub normal_scale: f32,
}

impl Material {
    /// An opaque dielectric (metallic 0, roughness 1, not emissive) of base colour
    /// `base_color`.
    pub fn opaque(name: impl Into<String>, base_color: Vec4) -> Material {
        Material {
            name: name.into(),
            base_color,
            metallic: 0.0,
            roughness: 1.0,
            emissive: Vec3::ZERO,
            alpha_mode: AlphaMode::Opaque,
            alpha_texture: None,
            base_color_texture: None,
            metallic_roughness_texture: None,
            emissive_texture: None,
            normal_texture: None,
            normal_scale: 1.0,
        }
    }

    /// The same material emitting `radiance` (linear RGB; what glTF's `emissiveFactor`
    /// holds).
    pub fn with_emissive(self, radiance: Vec3) -> Material {
        Material {
            emissive: radiance,
            ..self
        }
    }

    /// How a walk tests this material's candidates ([`bvhtrace_core::alpha`]): `None` for
    /// an opaque material; without a texture the mask is one texel of alpha 255, so the
    /// base colour factor's alpha alone decides.
    pub fn alpha_mask<'a>(&self, textures: &'a [AlphaTexture]) -> Option<AlphaMask<'a>> {
        let AlphaMode::Mask { cutoff } = self.alpha_mode else {
            return None;
        };
        let min_texel = bvhtrace_core::alpha::min_passing_texel(self.base_color.w, cutoff);
        let one: &'static [u8] = &[255];
        let (alpha, width, height, wrap) = match self.alpha_texture {
            Some(r) => match textures.get(r.texture) {
                Some(t) => (&t.alpha[..], t.width, t.height, r.wrap),
                None => (one, 1, 1, r.wrap),
            },
            None => (one, 1, 1, [Wrap::Repeat; 2]),
        };
        Some(AlphaMask {
            alpha,
            width,
            height,
            wrap,
            min_texel,
        })
    }
}

/// How a material's alpha cuts its surface (glTF `alphaMode`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum AlphaMode {
    /// `OPAQUE` (glTF's default): alpha is ignored.
    #[default]
    Opaque,
    /// `MASK`: a candidate hit whose alpha is below `cutoff` is skipped (glTF
    /// `alphaCutoff`, default 0.5). `BLEND` loads as a mask at 0.5: a tracer has no
    /// blending, and half-transparent surfaces then cast the shadows they mostly would.
    Mask {
        /// The smallest alpha that is a hit.
        cutoff: f32,
    },
}

/// A masked material's base colour texture: which [`Scene::alpha_textures`] entry, and how
/// coordinates outside `0..1` wrap along `u` and `v`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AlphaTextureRef {
    /// Index into [`Scene::alpha_textures`].
    pub texture: usize,
    /// The sampler's `wrapS` and `wrapT`.
    pub wrap: [Wrap; 2],
}

/// The alpha channel of a texture a masked material samples (the colour channels are not
/// kept: the tracer needs only the cut).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct AlphaTexture {
    /// The image's name or URI, for messages.
    pub name: String,
    /// Texels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Alpha, 8 bits per texel, row by row from the top (`v = 0`).
    pub alpha: Vec<u8>,
}

/// A material's texture: which [`Scene::textures`] entry, and how coordinates outside
/// `0..1` wrap along `u` and `v`. It is sampled at the vertices' [`Mesh::texcoords`]
/// (glTF `TEXCOORD_0`; textures on other sets are not loaded).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TextureRef {
    /// Index into [`Scene::textures`].
    pub texture: usize,
    /// The sampler's `wrapS` and `wrapT`.
    pub wrap: [Wrap; 2],
}

/// A decoded texture image, shared by every material slot that samples it.
#[derive(Clone, Default, PartialEq, Eq)]
pub struct Texture {
    /// The image's name or URI, for messages.
    pub name: String,
    /// Texels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// 8-bit RGBA, 4 bytes per texel, row by row from the top (`v = 0`), as the file
    /// stores them: not converted from sRGB (whether a channel is sRGB depends on the slot
    /// that samples it).
    pub rgba: Vec<u8>,
}

// By hand: the derived Debug would print megabytes of texels.
impl std::fmt::Debug for Texture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Texture")
            .field("name", &self.name)
            .field("width", &self.width)
            .field("height", &self.height)
            .field("rgba", &format_args!("[{} bytes]", self.rgba.len()))
            .finish()
    }
}

/// A triangle mesh in its own (object) space, with optional attributes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// The mesh's name (may be empty).
    pub name: String,
    /// Vertex positions (all finite).
    pub positions: Vec<Vec3>,
    /// Triangles: three indices into `positions` each (all in range).
    pub indices: Vec<[u32; 3]>,
    /// Per-vertex unit normals, or empty (see [`Attributes::normals`]).
    pub normals: Vec<Vec3>,
    /// Per-vertex texture coordinates, or empty (see [`Attributes::texcoords`]).
    pub texcoords: Vec<Vec2>,
    /// Per-vertex linear RGBA colours, or empty (see [`Attributes::colors`]).
    pub colors: Vec<Vec4>,
    /// Per-triangle indices into [`Scene::materials`], or empty (see [`Attributes::materials`]).
    pub materials: Vec<u32>,
}

impl Mesh {
    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// True when the mesh has no triangle.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// The mesh in its own space, positions and indices only.
    pub fn triangle_mesh(&self) -> TriangleMesh {
        TriangleMesh {
            positions: self.positions.clone(),
            indices: self.indices.clone(),
        }
    }

    /// Area-weighted vertex normals of the mesh's triangles (`+Y` for a vertex that only
    /// touches zero-area triangles or none).
    pub fn computed_normals(&self) -> Vec<Vec3> {
        vertex_normals(&self.positions, &self.indices)
    }
}

/// Area-weighted vertex normals (`+Y` for a vertex that only touches zero-area triangles
/// or none); out-of-range indices are skipped.
pub(crate) fn vertex_normals(positions: &[Vec3], indices: &[[u32; 3]]) -> Vec<Vec3> {
    let mut acc = vec![Vec3::ZERO; positions.len()];
    for t in indices {
        let [a, b, c] = t.map(|i| i as usize);
        let (Some(&pa), Some(&pb), Some(&pc)) =
            (positions.get(a), positions.get(b), positions.get(c))
        else {
            continue;
        };
        let n = (pb - pa).cross(pc - pa);
        if n.is_finite() {
            acc[a] += n;
            acc[b] += n;
            acc[c] += n;
        }
    }
    for n in &mut acc {
        let u = n.normalize_or_zero();
        *n = if u == Vec3::ZERO { Vec3::Y } else { u };
    }
    acc
}

/// One placement of a mesh in the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Instance {
    /// Index into [`Scene::meshes`].
    pub mesh: usize,
    /// Object-to-world transform (affine, finite).
    pub transform: Mat4,
}

impl Instance {
    /// True when the transform mirrors (negative determinant): [`Scene::flatten`] then
    /// swaps two corners of each triangle so that front faces stay front faces.
    pub fn flips_winding(&self) -> bool {
        self.transform.determinant() < 0.0
    }
}

/// World-space per-vertex and per-triangle data matching [`Scene::flatten`]'s mesh,
/// each array empty when the scene lacks it (see [`Attributes`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FlatAttributes {
    /// World-space unit normals (transformed by the inverse transpose), per vertex.
    pub normals: Vec<Vec3>,
    /// Texture coordinates, per vertex.
    pub texcoords: Vec<Vec2>,
    /// Linear RGBA colours, per vertex.
    pub colors: Vec<Vec4>,
    /// Indices into [`Scene::materials`], per triangle.
    pub materials: Vec<u32>,
}

/// A loaded scene: meshes, their instances, materials, an optional camera.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scene {
    /// A short name: the file's stem or the builtin's name.
    pub name: String,
    /// What the scene is, in words (for benchmark output).
    pub description: String,
    /// True for scenes this project made up (procedural, or a grid of copies of a real
    /// mesh) rather than published ones; benchmarks say so.
    pub synthetic: bool,
    /// The distinct meshes, in object space.
    pub meshes: Vec<Mesh>,
    /// Where the meshes are placed; a mesh may be placed many times.
    pub instances: Vec<Instance>,
    /// Materials that [`Mesh::materials`] index.
    pub materials: Vec<Material>,
    /// The alpha channels of the textures masked materials sample
    /// ([`Material::alpha_texture`]); empty when no material is masked with a texture.
    pub alpha_textures: Vec<AlphaTexture>,
    /// The images materials' textures sample ([`TextureRef::texture`]), each decoded
    /// once; empty when no material has a usable texture.
    pub textures: Vec<Texture>,
    /// Which optional arrays the meshes have.
    pub attributes: Attributes,
    /// The file's camera (the first perspective camera on a node, in world space), or a
    /// builtin's chosen view; `None` when the caller should frame [`Scene::bounds`].
    pub camera: Option<Camera>,
    /// Non-fatal problems met while loading (missing images, skipped primitives...).
    pub warnings: Vec<String>,
    /// The file's node animations, with what is needed to recompute [`Scene::instances`]
    /// at any time ([`Scene::set_time`]); `None` for scenes without animation (builtins,
    /// files without `animations`, or whose channels drive nothing that is loaded).
    ///
    /// It matches the instances as loaded: a scene whose instances are added or removed
    /// afterwards is no longer animated by [`Scene::set_time`].
    pub animation: Option<Animation>,
    /// Strands of curves (hair, fur, grass) in world space beside the triangles, traced
    /// by [`bvhtrace_core::CurveBvh`]; `None` for scenes without them.
    pub curves: Option<Curves>,
}

impl Scene {
    /// Number of instances.
    pub fn instance_count(&self) -> usize {
        self.instances.len()
    }

    /// Number of triangles over all instances (what [`Scene::flatten`] returns).
    pub fn triangle_count(&self) -> usize {
        self.instances
            .iter()
            .map(|i| self.meshes.get(i.mesh).map_or(0, Mesh::len))
            .sum()
    }

    /// Number of vertices over all instances (what [`Scene::flatten`] returns).
    pub fn vertex_count(&self) -> usize {
        self.instances
            .iter()
            .map(|i| self.meshes.get(i.mesh).map_or(0, |m| m.positions.len()))
            .sum()
    }

    /// World-space bounds `(min, max)` of every vertex of every instance. A scene without
    /// vertices gives the empty box `(+inf, -inf)`.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::INFINITY;
        let mut hi = Vec3::NEG_INFINITY;
        for inst in &self.instances {
            let Some(mesh) = self.meshes.get(inst.mesh) else {
                continue;
            };
            let m = inst.transform;
            for &p in &mesh.positions {
                let w = m.transform_point3(p);
                lo = lo.min(w);
                hi = hi.max(w);
            }
        }
        for p in self.curves.iter().flat_map(|c| &c.points) {
            lo = lo.min(p.truncate() - p.w);
            hi = hi.max(p.truncate() + p.w);
        }
        (lo, hi)
    }

    /// The scene's own camera, or one that frames its bounds for this aspect ratio.
    pub fn camera_or_frame(&self, aspect: f32) -> Camera {
        self.camera.unwrap_or_else(|| {
            let (lo, hi) = self.bounds();
            Camera::frame(lo, hi, aspect)
        })
    }

    /// All instances in world space, as one mesh: instance after instance, in
    /// [`Scene::instances`] order, each mesh's vertices and triangles in order. Triangles
    /// of mirroring instances ([`Instance::flips_winding`]) have corners 1 and 2 swapped.
    ///
    /// Loaded scenes always fit 32-bit indices (the loader refuses larger ones); a scene
    /// edited past that panics here.
    pub fn flatten(&self) -> TriangleMesh {
        let mut positions = Vec::with_capacity(self.vertex_count());
        let mut indices = Vec::with_capacity(self.triangle_count());
        for inst in &self.instances {
            let Some(mesh) = self.meshes.get(inst.mesh) else {
                continue;
            };
            let base = u32::try_from(positions.len()).expect("scene exceeds 32-bit vertex indices");
            let m = inst.transform;
            positions.extend(mesh.positions.iter().map(|&p| m.transform_point3(p)));
            if inst.flips_winding() {
                indices.extend(
                    mesh.indices
                        .iter()
                        .map(|t| [t[0] + base, t[2] + base, t[1] + base]),
                );
            } else {
                indices.extend(mesh.indices.iter().map(|t| t.map(|i| i + base)));
            }
        }
        TriangleMesh { positions, indices }
    }

    /// [`Scene::flatten`]'s triangles, refused (an error naming the scene and its size)
    /// when the scene places more than [`MAX_TRIANGLES`]: such a scene can only be traced
    /// in two levels ([`Scene::instanced_bvh`]).
    pub fn flattened_triangles(&self) -> Result<Vec<bvhtrace_core::Triangle>, SceneError> {
        let n = self.triangle_count();
        if n > MAX_TRIANGLES {
            return Err(SceneError::new(
                self.name.clone(),
                ErrorKind::TooLarge(format!(
                    "{n} triangles over all instances do not fit one flattened BVH (at most \
                     {MAX_TRIANGLES}); trace the scene in two levels"
                )),
            ));
        }
        self.flatten().triangles().map_err(|e| {
            SceneError::new(
                self.name.clone(),
                ErrorKind::Invalid(format!("bad geometry: {e}")),
            )
        })
    }

    /// [`Scene::flatten`] plus the matching world-space attributes.
    pub fn flatten_with_attributes(&self) -> (TriangleMesh, FlatAttributes) {
        let mesh = self.flatten();
        let a = self.attributes;
        let mut out = FlatAttributes::default();
        for inst in &self.instances {
            let Some(m) = self.meshes.get(inst.mesh) else {
                continue;
            };
            if a.normals {
                let nm = inst.transform.inverse().transpose();
                out.normals.extend(m.normals.iter().map(|&n| {
                    let w = nm.transform_vector3(n).normalize_or_zero();
                    if w == Vec3::ZERO { n } else { w }
                }));
            }
            if a.texcoords {
                out.texcoords.extend_from_slice(&m.texcoords);
            }
            if a.colors {
                out.colors.extend_from_slice(&m.colors);
            }
            if a.materials {
                out.materials.extend_from_slice(&m.materials);
            }
        }
        (mesh, out)
    }

    /// Applies an affine transform to the whole scene: every instance (`m * transform`)
    /// and the camera. Meshes are untouched, so instancing is kept. The animation keeps
    /// it too: [`Scene::set_time`] places the instances with `m` applied.
    pub fn transform(&mut self, m: Mat4) {
        for inst in &mut self.instances {
            inst.transform = m * inst.transform;
        }
        if let Some(a) = &mut self.animation {
            a.globals.push(m);
        }
        if let Some(c) = &mut self.camera {
            *c = c.transformed(m);
        }
        if let Some(curves) = &mut self.curves {
            // Radii scale as lengths do: by the cube root of the volume's scale.
            let r = m.determinant().abs().cbrt();
            for p in &mut curves.points {
                *p = m.transform_point3(p.truncate()).extend(p.w * r);
            }
        }
    }

    /// The length of the scene's animation in seconds ([`Animation::duration`]); 0 without
    /// animation.
    pub fn duration(&self) -> f32 {
        self.animation.as_ref().map_or(0.0, Animation::duration)
    }

    /// The animation when it still matches the instances (one node per instance).
    fn live_animation(&self) -> Option<&Animation> {
        self.animation
            .as_ref()
            .filter(|a| a.instance_nodes.len() == self.instances.len())
    }

    /// Every instance's object-to-world transform at time `t` (seconds), in
    /// [`Scene::instances`] order, with the transforms applied by [`Scene::transform`]:
    /// the animated pose (before a channel's first key its first value holds, after its
    /// last key the last value; a NaN time is the start). Without animation
    /// (or when the instances no longer match it, see [`Scene::animation`]) these are
    /// the current transforms.
    ///
    /// The loaded [`Scene::instances`] hold the nodes' static transforms, which is the
    /// pose at time 0 when the animation starts there (as exporters write it).
    pub fn instance_transforms_at(&self, t: f32) -> Vec<Mat4> {
        match self.live_animation() {
            Some(a) => a.instance_transforms_at(t),
            None => self.instances.iter().map(|i| i.transform).collect(),
        }
    }

    /// Moves every instance to its pose at time `t` (seconds): rewrites each
    /// [`Instance::transform`] with [`Scene::instance_transforms_at`], and the positions
    /// and normals of skinned and morphed meshes with [`Animation::deformed_at`]. Other
    /// meshes, the camera and materials are unchanged (the camera is not animated). Extreme keys may place an
    /// instance out of `f32` range: [`Scene::check_invariants`] says so.
    pub fn set_time(&mut self, t: f32) {
        if self.live_animation().is_none() {
            return;
        }
        let transforms = self.instance_transforms_at(t);
        for (inst, m) in self.instances.iter_mut().zip(transforms) {
            inst.transform = m;
        }
        self.apply_deformations(Some(t));
    }

    /// Writes each deformed instance's mesh (skins and morph targets,
    /// [`Animation::deformed_at`]) at time `t` (`None`: the static pose, as loaded).
    pub(crate) fn apply_deformations(&mut self, t: Option<f32>) {
        let Some(a) = self.live_animation() else {
            return;
        };
        for d in a.deformed_at(t) {
            let m = self
                .instances
                .get(d.instance)
                .map_or(usize::MAX, |i| i.mesh);
            if let Some(mesh) = self.meshes.get_mut(m) {
                mesh.positions = d.positions;
                if !mesh.normals.is_empty() {
                    // The file's normals deformed, or (when it had none) made again.
                    mesh.normals = if d.normals.len() == mesh.positions.len() {
                        d.normals
                    } else {
                        vertex_normals(&mesh.positions, &mesh.indices)
                    };
                }
            }
        }
    }

    /// Checks the invariants every loaded scene keeps: instance mesh indices in range,
    /// triangle indices in range, finite positions and transforms, attribute arrays
    /// present exactly when [`Scene::attributes`] says so and of the right length,
    /// material indices in range. Returns the first violation.
    pub fn check_invariants(&self) -> Result<(), String> {
        let a = self.attributes;
        for (mi, m) in self.meshes.iter().enumerate() {
            let nv = m.positions.len();
            if let Some(p) = m.positions.iter().position(|p| !p.is_finite()) {
                return Err(format!("mesh {mi}: position {p} is not finite"));
            }
            if let Some((t, _)) = m
                .indices
                .iter()
                .enumerate()
                .find(|(_, t)| t.iter().any(|&i| i as usize >= nv))
            {
                return Err(format!("mesh {mi}: triangle {t} has an index out of range"));
            }
            let check = |name: &str, on: bool, len: usize, want: usize| {
                let expect = if on { want } else { 0 };
                if len == expect {
                    Ok(())
                } else {
                    Err(format!(
                        "mesh {mi}: {name} has {len} entries, expected {expect}"
                    ))
                }
            };
            check("normals", a.normals, m.normals.len(), nv)?;
            check("texcoords", a.texcoords, m.texcoords.len(), nv)?;
            check("colors", a.colors, m.colors.len(), nv)?;
            check("materials", a.materials, m.materials.len(), m.indices.len())?;
            if let Some(&bad) = m
                .materials
                .iter()
                .find(|&&x| x as usize >= self.materials.len())
            {
                return Err(format!("mesh {mi}: material {bad} does not exist"));
            }
        }
        for (ii, inst) in self.instances.iter().enumerate() {
            if inst.mesh >= self.meshes.len() {
                return Err(format!("instance {ii}: mesh {} does not exist", inst.mesh));
            }
            if !inst.transform.is_finite() {
                return Err(format!("instance {ii}: transform is not finite"));
            }
        }
        Ok(())
    }

    /// Makes the attribute arrays agree with the union of what the meshes have (filling
    /// missing arrays with defaults) and sets [`Scene::attributes`] accordingly.
    pub(crate) fn unify_attributes(&mut self) {
        let any = |f: &dyn Fn(&Mesh) -> bool| self.meshes.iter().any(f);
        let a = Attributes {
            normals: any(&|m| !m.normals.is_empty()),
            texcoords: any(&|m| !m.texcoords.is_empty()),
            colors: any(&|m| !m.colors.is_empty()),
            materials: any(&|m| !m.materials.is_empty()),
        };
        let mut default_material = None;
        for m in &mut self.meshes {
            let nv = m.positions.len();
            if a.normals && m.normals.len() != nv {
                m.normals = m.computed_normals();
            }
            if a.texcoords && m.texcoords.len() != nv {
                m.texcoords = vec![Vec2::ZERO; nv];
            }
            if a.colors && m.colors.len() != nv {
                m.colors = vec![Vec4::ONE; nv];
            }
            if a.materials && m.materials.len() != m.indices.len() {
                let id = *default_material.get_or_insert_with(|| {
                    self.materials.push(Material::opaque("default", Vec4::ONE));
                    (self.materials.len() - 1) as u32
                });
                m.materials = vec![id; m.indices.len()];
            }
        }
        self.attributes = a;
    }

    /// The final checks every loaded scene passes: at least one triangle, within the
    /// size limits, finite in world space.
    pub(crate) fn finish(mut self, label: &str) -> Result<Scene, SceneError> {
        let err = |kind| SceneError::new(label, kind);
        // Drop instances of empty meshes: they add nothing.
        let meshes = &self.meshes;
        let keep: Vec<bool> = self
            .instances
            .iter()
            .map(|i| meshes.get(i.mesh).is_some_and(|m| !m.is_empty()))
            .collect();
        if let Some(a) = &mut self.animation
            && a.instance_nodes.len() == keep.len()
        {
            let mut k = keep.iter();
            a.instance_nodes
                .retain(|_| k.next().copied().unwrap_or(false));
        }
        let mut k = keep.iter();
        self.instances
            .retain(|_| k.next().copied().unwrap_or(false));
        let tris = self.triangle_count();
        if tris == 0 && self.curves.as_ref().is_none_or(|c| c.is_empty()) {
            return Err(err(ErrorKind::NoTriangles(String::new())));
        }
        if tris > MAX_INSTANCED_TRIANGLES {
            return Err(err(ErrorKind::TooLarge(format!(
                "{tris} triangles over all instances (at most {MAX_INSTANCED_TRIANGLES}, the \
                 32-bit primitive ids of a two-level BVH)"
            ))));
        }
        let verts = self.vertex_count();
        if verts > u32::MAX as usize {
            return Err(err(ErrorKind::TooLarge(format!(
                "{verts} vertices over all instances (at most {})",
                u32::MAX
            ))));
        }
        if let Some(c) = &self.curves {
            c.validate()
                .map_err(|e| err(ErrorKind::Invalid(format!("curves: {e}"))))?;
        }
        let (lo, hi) = self.bounds();
        if !lo.is_finite() || !hi.is_finite() {
            return Err(err(ErrorKind::NonFiniteWorld(format!(
                "the scene's world-space bounds are not finite ({lo} .. {hi}): a transform overflows f32"
            ))));
        }
        if let Some(c) = self.camera
            && !(c.eye.is_finite() && c.target.is_finite() && c.fov_y_deg.is_finite())
        {
            self.camera = None;
            self.warnings
                .push("the camera is not finite and was dropped".into());
        }
        Ok(self)
    }
}

/// How [`load_with`] loads.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LoadOptions {
    /// A folder holding `glb/MESH.glb` (the shared scenes folder, [`shared_scenes_dir`]):
    /// where `builtin:grid:MESH:AxB` looks for its mesh first, before the repository's own
    /// `scenes/MESH.glb`. The library looks in no other folder, and at no working
    /// directory.
    pub meshes: Option<PathBuf>,
}

impl LoadOptions {
    /// `builtin:grid` meshes from `dir` (its `glb/` folder), when given.
    pub fn with_meshes(dir: Option<PathBuf>) -> LoadOptions {
        LoadOptions { meshes: dir }
    }
}

/// Loads a scene from a spec: a `.gltf`/`.glb` path or a `builtin:` name, with optional
/// `#scale=S` / `#offset=X,Y,Z` suffixes (see the crate docs), `builtin:grid`'s meshes
/// from this repository's `scenes/` only ([`load_with`] names another folder).
///
/// Every error names the file (or spec) and the cause; nothing panics on bad input.
pub fn load(spec: &str) -> Result<Scene, SceneError> {
    load_with(spec, &LoadOptions::default())
}

/// [`load`] as `opts` says.
pub fn load_with(spec: &str, opts: &LoadOptions) -> Result<Scene, SceneError> {
    let (base, transforms) = split_suffixes(spec)?;
    let mut scene = if let Some(name) = base.strip_prefix("builtin:") {
        builtin::load_builtin(name, base, opts)?
    } else if base.to_ascii_lowercase().ends_with(".hair") {
        load_hair_file(Path::new(base))?
    } else {
        load_gltf_file(Path::new(base))?
    };
    if !transforms.is_empty() {
        for m in transforms {
            scene.transform(m);
        }
        scene = scene.finish(spec)?;
    }
    Ok(scene)
}

/// Splits `SPEC#scale=S#offset=X,Y,Z` into the spec and its transforms, in order.
fn split_suffixes(spec: &str) -> Result<(&str, Vec<Mat4>), SceneError> {
    let mut base = spec;
    let mut transforms = Vec::new();
    let bad = |msg: String| SceneError::new(spec, ErrorKind::Spec(msg));
    while let Some(hash) = base.rfind('#') {
        let tail = &base[hash + 1..];
        if let Some(v) = tail.strip_prefix("scale=") {
            let s: f32 = v
                .trim()
                .parse()
                .map_err(|_| bad(format!("#scale={v}: not a number")))?;
            if !s.is_finite() || s == 0.0 {
                return Err(bad(format!(
                    "#scale={v}: the scale must be finite and non-zero"
                )));
            }
            transforms.push(Mat4::from_scale(Vec3::splat(s)));
        } else if let Some(v) = tail.strip_prefix("offset=") {
            let parts: Vec<&str> = v.split(',').collect();
            let nums: Result<Vec<f32>, _> = parts.iter().map(|p| p.trim().parse::<f32>()).collect();
            match nums {
                Ok(n) if n.len() == 3 && n.iter().all(|x| x.is_finite()) => {
                    transforms.push(Mat4::from_translation(Vec3::new(n[0], n[1], n[2])));
                }
                _ => {
                    return Err(bad(format!(
                        "#offset={v}: expected three finite numbers X,Y,Z"
                    )));
                }
            }
        } else {
            break;
        }
        base = &base[..hash];
    }
    transforms.reverse();
    Ok((base, transforms))
}

/// The shared scenes folder (`shared/scenes`, holding `glb/`, `gltf/` and `SOURCES.md`):
/// the first `shared/scenes` folder found walking up from the current directory, then from
/// this crate's source directory; `None` when there is none (tests then skip with a
/// message). For front ends, benchmarks and tests to pass on ([`LoadOptions::meshes`]):
/// nothing in the library calls it. A front end that lets its user name another folder
/// (the CLI's `$BVHTRACE_SCENES`) checks that first.
pub fn shared_scenes_dir() -> Option<PathBuf> {
    let starts = [
        std::env::current_dir().ok(),
        Some(PathBuf::from(env!("CARGO_MANIFEST_DIR"))),
    ];
    for start in starts.into_iter().flatten() {
        for dir in start.ancestors() {
            let c = dir.join("shared").join("scenes");
            if c.is_dir() {
                return Some(c);
            }
        }
    }
    None
}

/// The repository's own `scenes/` folder (small scenes this project made), found from
/// this crate's source directory, or `None` when the crate was moved out of the repo.
pub fn repo_scenes_dir() -> Option<PathBuf> {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .canonicalize()
        .ok()
        .filter(|d| d.is_dir())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn suffixes_parse_in_order() {
        let (b, t) = split_suffixes("a#b.glb#scale=2#offset=1,2,3").expect("parses");
        assert_eq!(b, "a#b.glb");
        assert_eq!(t.len(), 2);
        let p = t.iter().fold(Vec3::ONE, |p, m| m.transform_point3(p));
        assert_eq!(p, Vec3::new(3.0, 4.0, 5.0));
        assert!(split_suffixes("x#scale=0").is_err());
        assert!(split_suffixes("x#scale=nan").is_err());
        assert!(split_suffixes("x#offset=1,2").is_err());
        assert_eq!(split_suffixes("x#y").expect("parses").0, "x#y");
    }
}
