//! What the path tracer reads besides the BVH: the materials, each primitive's material
//! and light, the emissive triangles with their chances of being sampled, and the
//! per-frame parameters. Each GPU type is the WGSL struct of `shaders/path_trace.wgsl`
//! field for field (a naga test checks the offsets).

use bvhtrace_core::Triangle;
use bvhtrace_scene::{Camera, Scene};
use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::PathError;
use crate::environment::Environment;
use crate::material::PathMaterial;
use crate::textures::HEADER_WORDS;

/// An emissive triangle (WGSL `PathLight`, 64 bytes): `v0`, `v0 + e1`, `v0 + e2`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct PathLight {
    /// The first corner.
    pub v0: [f32; 3],
    /// The chance that this light or one before it is sampled (the last is 1).
    pub cdf: f32,
    /// The second corner less the first.
    pub e1: [f32; 3],
    /// The chance of sampling this light, over its area.
    pub pdf_area: f32,
    /// The third corner less the first.
    pub e2: [f32; 3],
    /// Its primitive id.
    pub prim: u32,
    /// Its emitted radiance.
    pub emission: [f32; 3],
    /// Padding to 16 bytes.
    pub pad: u32,
}

/// A primitive without a light (`PathScene::prims`' second word).
pub const NO_LIGHT: u32 = u32::MAX;

/// One frame's parameters (WGSL `PathParams`, 128 bytes): the camera, the lights that are
/// not triangles, the sample's index.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct PathParams {
    /// The camera's position.
    pub eye: [f32; 3],
    /// `tan(fov_y / 2)`.
    pub tan_half_fov: f32,
    /// The unit view direction.
    pub forward: [f32; 3],
    /// Width over height.
    pub aspect: f32,
    /// The unit right vector.
    pub right: [f32; 3],
    /// Image width in pixels.
    pub width: u32,
    /// The unit up vector.
    pub up: [f32; 3],
    /// Image height in pixels.
    pub height: u32,
    /// The unit direction toward the sun.
    pub sun_dir: [f32; 3],
    /// The most bounces a path takes.
    pub max_depth: u32,
    /// The sun's radiance times its solid angle (irradiance on a surface facing it).
    pub sun: [f32; 3],
    /// Emissive triangles ([`PathScene::lights`]).
    pub light_count: u32,
    /// The environment's radiance, the same from every direction; with an environment
    /// map, the scale of its radiance.
    pub env: [f32; 3],
    /// This frame's sample index (0 starts the sum over).
    pub sample: u32,
    /// The random numbers' seed.
    pub seed: u32,
    /// Materials ([`PathScene::materials`]).
    pub material_count: u32,
    /// Primitives ([`PathScene::prims`]).
    pub prim_count: u32,
    /// Padding to 16 bytes.
    pub pad: u32,
}

/// The light a scene is lit by besides its emissive triangles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lighting {
    /// The direction toward the sun (normalised when used; zero for no sun).
    pub sun_dir: Vec3,
    /// The sun's irradiance on a surface facing it (linear RGB; zero for none).
    pub sun: Vec3,
    /// The environment's constant radiance (linear RGB; zero for none); with an
    /// environment map ([`PathScene::set_environment`]), the scale of its radiance.
    pub env: Vec3,
}

impl Default for Lighting {
    /// A sky of radiance 0.5 and no sun: scenes without emissive triangles are lit, and
    /// a closed room (the Cornell box) is lit by its own light alone.
    fn default() -> Self {
        Lighting {
            sun_dir: Vec3::new(0.4, 1.0, 0.3),
            sun: Vec3::ZERO,
            env: Vec3::splat(0.5),
        }
    }
}

/// A scene's shading data, for the device and the CPU twin alike.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PathScene {
    /// The materials, and a last grey one for primitives without.
    pub materials: Vec<PathMaterial>,
    /// Per primitive id: its material and its light ([`NO_LIGHT`] for none).
    pub prims: Vec<[u32; 2]>,
    /// The emissive triangles of non-zero area, chances by power.
    pub lights: Vec<PathLight>,
    /// The material textures and what reads them, and the environment map's words.
    pub textures: crate::textures::TextureData,
    /// The environment map the sky's radiance comes from ([`Lighting::env`] scales it);
    /// `None` for a constant sky.
    pub environment: Option<Environment>,
}

impl PathScene {
    /// Lights the scene by `environment` (a map's radiance times [`Lighting::env`]) in
    /// place of a constant sky; `None`, or a map that is black everywhere, for the
    /// constant sky. Its words follow the textures' in [`PathScene::textures`].
    pub fn set_environment(&mut self, environment: Option<Environment>) {
        let words = &mut self.textures.words;
        words.resize(words.len().max(HEADER_WORDS), 0);
        if words[3] != 0 {
            words.truncate(words[3] as usize);
            words[3] = 0;
        }
        self.environment = environment.filter(|e| !e.is_black());
        if let Some(e) = &self.environment {
            words[3] = words.len() as u32;
            words.extend(e.words());
        }
    }

    /// The shading data of `scene` traced as one mesh whose primitive ids number
    /// `triangles` (`Scene::flattened_triangles`: instance after instance).
    pub fn new(scene: &Scene, triangles: &[Triangle]) -> Result<PathScene, PathError> {
        let mut materials: Vec<PathMaterial> = scene.materials.iter().map(material).collect();
        let default = materials.len() as u32;
        materials.push(material(&bvhtrace_scene::Material::opaque(
            "default",
            glam::Vec4::new(0.8, 0.8, 0.8, 1.0),
        )));
        let (mesh, attributes) = scene.flatten_with_attributes();
        if attributes.materials.len() != triangles.len() && !attributes.materials.is_empty() {
            return Err(PathError::Scene(format!(
                "{}: {} triangles but {} per-triangle materials",
                scene.name,
                triangles.len(),
                attributes.materials.len()
            )));
        }
        let mut prims: Vec<[u32; 2]> = (0..triangles.len())
            .map(|i| {
                let m = attributes.materials.get(i).copied().unwrap_or(default);
                [m.min(default), NO_LIGHT]
            })
            .collect();
        let n = scene.materials.len();
        let textures = crate::textures::TextureData::new(
            scene,
            (&mesh, &attributes),
            &mut materials[..n],
            triangles.len(),
        );
        let lights = lights(&materials, triangles, &mut prims);
        Ok(PathScene {
            materials,
            prims,
            lights,
            textures,
            environment: None,
        })
    }
}

/// The most radiance a material emits per channel: far above any real light, far enough
/// below `f32::MAX` that no path's sum overflows.
pub const MAX_EMISSION: f32 = 1.0e6;

/// The primitives a one-mesh tree numbers: one more than its largest primitive id (an
/// SBVH's leaves may hold a triangle more than once).
pub(crate) fn primitives(bvh: &bvhtrace_core::FlatBvh) -> usize {
    (bvh.triangles().iter())
        .map(|t| t.prim as usize + 1)
        .max()
        .unwrap_or(0)
}

/// A material's shading values, each finite and in range: factors clamped to `[0, 1]`
/// (NaN to the glTF default), emission to `[0, MAX_EMISSION]` (not finite: 0).
fn material(m: &bvhtrace_scene::Material) -> PathMaterial {
    let unit = |x: f32, nan: f32| if x.is_nan() { nan } else { x.clamp(0.0, 1.0) };
    let glow = |x: f32| {
        if x.is_finite() {
            x.clamp(0.0, MAX_EMISSION)
        } else {
            0.0
        }
    };
    let c = m.base_color;
    crate::sampling::lobes(
        Vec3::new(unit(c.x, 0.8), unit(c.y, 0.8), unit(c.z, 0.8)),
        unit(m.metallic, 0.0),
        unit(m.roughness, 1.0),
        m.emissive.map(glow),
        unit(c.w, 1.0),
    )
}

/// The emissive triangles of non-zero area, each sampled in proportion to its power
/// (luminance times area), and their ids in `prims`.
fn lights(
    materials: &[PathMaterial],
    triangles: &[Triangle],
    prims: &mut [[u32; 2]],
) -> Vec<PathLight> {
    let luminance =
        |c: [f32; 3]| 0.2126 * c[0] as f64 + 0.7152 * c[1] as f64 + 0.0722 * c[2] as f64;
    let mut found: Vec<(usize, f64, f64)> = Vec::new();
    for (i, (t, p)) in triangles.iter().zip(prims.iter()).enumerate() {
        let emission = materials[p[0] as usize].emissive;
        let [a, b, c] = t.map(|v| v.as_dvec3());
        let area = 0.5 * (b - a).cross(c - a).length();
        let power = luminance(emission) * area;
        if power > 0.0 && power.is_finite() && area > 0.0 {
            found.push((i, area, power));
        }
    }
    let total: f64 = found.iter().map(|f| f.2).sum();
    let mut before = 0.0;
    let mut lights = Vec::with_capacity(found.len());
    for (k, &(i, area, power)) in found.iter().enumerate() {
        before += power;
        let t = triangles[i];
        let cdf = if k + 1 == found.len() {
            1.0
        } else {
            (before / total) as f32
        };
        prims[i][1] = k as u32;
        lights.push(PathLight {
            v0: t[0].to_array(),
            cdf,
            e1: (t[1] - t[0]).to_array(),
            pdf_area: (power / total / area) as f32,
            e2: (t[2] - t[0]).to_array(),
            prim: i as u32,
            emission: materials[prims[i][0] as usize].emissive,
            pad: 0,
        });
    }
    lights
}

impl PathParams {
    /// The parameters of a `width` x `height` frame seen by `camera`, lit by `lighting`,
    /// for `scene`; sample 0.
    pub fn new(
        camera: &Camera,
        (width, height): (u32, u32),
        lighting: &Lighting,
        max_depth: u32,
        scene: &PathScene,
    ) -> PathParams {
        let (forward, right, up) = camera.basis();
        let sun_dir = lighting.sun_dir.normalize_or_zero();
        let sun = if sun_dir == Vec3::ZERO {
            Vec3::ZERO
        } else {
            lighting.sun
        };
        let finite = |v: Vec3| {
            v.to_array()
                .map(|c| if c.is_finite() { c.max(0.0) } else { 0.0 })
        };
        PathParams {
            eye: camera.eye.to_array(),
            tan_half_fov: (camera.fov_y_deg.to_radians() * 0.5).tan(),
            forward: forward.to_array(),
            aspect: width as f32 / height as f32,
            right: right.to_array(),
            width,
            up: up.to_array(),
            height,
            sun_dir: sun_dir.to_array(),
            max_depth,
            sun: finite(sun),
            light_count: scene.lights.len() as u32,
            env: finite(lighting.env),
            sample: 0,
            seed: 0,
            material_count: scene.materials.len() as u32,
            prim_count: scene.prims.len() as u32,
            pad: 0,
        }
    }
}
