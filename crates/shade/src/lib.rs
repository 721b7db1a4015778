//! Shading for bvhtrace's front ends (`bvhtrace render`, the viewer, the benchmarks and the
//! examples): the modes ([`Shade`]), where the light sits and how long ambient-occlusion
//! rays are ([`View`]), the secondary rays some modes trace, and turning hits into pixels
//! ([`compose_rgb`], [`hit_colour`], [`palette`]).
//!
//! Everything here runs on the CPU from traced hits, whichever backend traced them, so two
//! backends' images differ only where their hits do.
//!
//! ```
//! use bvhtrace_core::{BuildOptions, FlatBvh, Query, TraceOptions, Traversal, trace_rays};
//! use bvhtrace_shade::{Pixels, Shade, View};
//!
//! let scene = bvhtrace_scene::load("builtin:cornell")?;
//! let tris = scene.flattened_triangles()?;
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let cam = scene.camera_or_frame(4.0 / 3.0);
//! let (w, h) = (32, 24);
//! let rays = cam.rays(w, h);
//! let walk = Traversal::Stackless;
//! let hits = trace_rays(&bvh, &rays, &TraceOptions::closest(walk)).hits;
//! // Diffuse light from the front ends' point light, with one shadow ray per hit.
//! let view = View::hard_shadows(Shade::Diffuse, &cam, &bvh);
//! let tri = |p: u32| tris[p as usize];
//! let (shadow, owner) = bvhtrace_shade::secondary_rays(
//!     view.shade, &tri, &rays, &hits, view.light, 1, view.ao_radius,
//! );
//! let secondary = trace_rays(&bvh, &shadow, &TraceOptions::new(walk, Query::Any)).hits;
//! let pixels = Pixels {
//!     size: (w, h),
//!     rays: &rays,
//!     hits: &hits,
//!     counters: &[],
//!     owner: &owner,
//!     secondary: &secondary,
//!     ao_samples: 1,
//! };
//! let rgb = bvhtrace_shade::compose_rgb(&view, &pixels, &tri);
//! assert_eq!(rgb.len(), (w * h * 3) as usize);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

#[cfg(feature = "cli")]
pub mod args;
mod compose;
pub mod palette;

use std::ops::Range;

use bvhtrace_core::{FlatBvh, Hit, Ray, Triangle};
use bvhtrace_scene::Camera;
use glam::Vec3;

pub use bvhtrace_core::surface::{SurfacePoint, cosine_dir, facing_normal, hit_point, uniform2};
pub use compose::{Pixels, compose_rgb, draw_legend, draw_number, hit_colour, max_nodes};

/// Background colour: what a pixel whose primary ray misses shows.
pub const BACKGROUND: [u8; 3] = [24, 26, 32];

/// Shading modes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize),
    serde(rename_all = "kebab-case")
)]
pub enum Shade {
    /// Geometric normal, facing the camera, as colour.
    #[default]
    Normal,
    /// Distance: near bright, far dark.
    Depth,
    /// Diffuse light from a point light near the camera, with shadow rays (any hit) to it:
    /// one per pixel, or samples of a small spherical light that converge to soft shadows.
    Diffuse,
    /// Ambient occlusion: cosine-weighted any-hit rays of a limited length.
    Ao,
    /// Nodes visited per pixel, with a colour legend.
    Heatmap,
    /// Path traced on the device (`bvhtrace-path`): camera rays, bounces, lights and the
    /// progressive sum all in WGSL, or on the CPU twin with the CPU backend. Not shaded
    /// from hits here: [`compose_rgb`] draws it as [`Shade::Normal`].
    Path,
}

impl Shade {
    /// Every mode.
    pub const ALL: [Shade; 6] = [
        Shade::Normal,
        Shade::Depth,
        Shade::Diffuse,
        Shade::Ao,
        Shade::Heatmap,
        Shade::Path,
    ];

    /// The modes that draw the surfaces hit, in the order a UI lists them (the viewer
    /// shows the heatmap with a switch of its own, over whichever of these is chosen).
    pub const SURFACE: [Shade; 4] = [Shade::Normal, Shade::Depth, Shade::Diffuse, Shade::Ao];

    /// A short name for a UI.
    pub fn label(self) -> &'static str {
        match self {
            Shade::Normal => "normals",
            Shade::Depth => "depth",
            Shade::Diffuse => "diffuse (soft shadows)",
            Shade::Ao => "ambient occlusion",
            Shade::Heatmap => "heatmap",
            Shade::Path => "path traced",
        }
    }

    /// True when the mode traces secondary rays (and a viewer may accumulate them).
    pub fn accumulates(self) -> bool {
        matches!(self, Shade::Diffuse | Shade::Ao)
    }
}

/// The point light of the diffuse modes: up and to the right of the camera, so that it sees
/// what the camera sees (closed rooms as well as open scenes) and casts visible shadows.
pub fn point_light(cam: &Camera) -> Vec3 {
    let (_, right, up) = cam.basis();
    cam.eye + (right * 0.25 + up * 0.2) * (cam.target - cam.eye).length()
}

/// The length of ambient-occlusion rays for a scene whose box has this diagonal: 15% of it.
pub fn ao_radius_of(diagonal: f32) -> f32 {
    0.15 * diagonal
}

/// The length of ambient-occlusion rays for a BVH: [`ao_radius_of`] its box's diagonal.
pub fn ao_radius(bvh: &FlatBvh) -> f32 {
    let b = bvh.bounds();
    ao_radius_of((b.max - b.min).length().max(f32::MIN_POSITIVE))
}

/// The radius of the spherical light that gives soft shadows, for a scene whose box has
/// this diagonal: 4% of it.
pub fn light_radius_of(diagonal: f32) -> f32 {
    0.04 * diagonal
}

/// How to shade: the mode and the sizes its secondary rays need.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// The shading mode.
    pub shade: Shade,
    /// Length of the AO rays, world units.
    pub ao_radius: f32,
    /// Where the light is, world space ([`point_light`]).
    pub light: Vec3,
    /// Radius of the light, world units; 0 for a point light (hard shadows).
    pub light_radius: f32,
}

impl View {
    /// A spherical light at [`point_light`] ([`light_radius_of`] the scene's diagonal, for
    /// soft shadows as samples accumulate) and AO rays [`ao_radius_of`] it: the viewer's.
    pub fn for_camera(shade: Shade, cam: &Camera, scene_diag: f32) -> View {
        View {
            shade,
            ao_radius: ao_radius_of(scene_diag),
            light: point_light(cam),
            light_radius: light_radius_of(scene_diag),
        }
    }

    /// A point light at [`point_light`] and AO rays [`ao_radius`] of the BVH: `bvhtrace
    /// render`'s.
    pub fn hard_shadows(shade: Shade, cam: &Camera, bvh: &FlatBvh) -> View {
        View {
            shade,
            ao_radius: ao_radius(bvh),
            light: point_light(cam),
            light_radius: 0.0,
        }
    }

    /// True for the node-visit heatmap.
    pub fn heatmap(&self) -> bool {
        self.shade == Shade::Heatmap
    }

    /// True when more samples add to this view (the diffuse and AO modes).
    pub fn accumulates(&self) -> bool {
        self.shade.accumulates()
    }

    /// Sample `sample` of pixel `pixel`'s secondary ray leaving `surface`: a shadow ray to
    /// the light (a point on it, for a light with a radius) in the diffuse mode, an AO ray
    /// in the AO mode, `None` in the others. Repeatable: the same pixel and sample give the
    /// same ray.
    pub fn secondary_ray(&self, surface: &SurfacePoint, pixel: u32, sample: u32) -> Option<Ray> {
        match self.shade {
            Shade::Ao => {
                Some(surface.spawn_ray(cosine_dir(surface.normal, pixel, sample), self.ao_radius))
            }
            Shade::Diffuse => {
                let target = if self.light_radius > 0.0 {
                    self.light + sphere_point(pixel, sample) * self.light_radius
                } else {
                    self.light
                };
                Some(surface.ray_toward(target))
            }
            _ => None,
        }
    }
}

/// A uniformly distributed point on the unit sphere for sample `s` of pixel `p`.
pub fn sphere_point(p: u32, s: u32) -> Vec3 {
    let (u1, u2) = uniform2(p ^ 0x5bd1_e995, s);
    let z = 1.0 - 2.0 * u1;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = std::f32::consts::TAU * u2;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Secondary rays for the diffuse (one shadow ray to the point light `light`) and AO
/// (`samples` rays of length `ao_radius`) modes: for each primary hit, rays and the index of
/// the pixel they belong to. `tri` gives the world-space corners of a hit's primitive.
#[allow(clippy::too_many_arguments)]
pub fn secondary_rays(
    mode: Shade,
    tri: &dyn Fn(u32) -> Triangle,
    primary: &[Ray],
    hits: &[Hit],
    light: Vec3,
    samples: u32,
    ao_radius: f32,
) -> (Vec<Ray>, Vec<u32>) {
    secondary_rays_from(mode, tri, primary, hits, light, 0..samples, ao_radius)
}

/// [`secondary_rays`] with the AO samples numbered `samples` instead of `0..samples`:
/// images made from disjoint ranges have independent samples (`bench --converge`). The
/// diffuse mode traces one shadow ray per hit whatever the range.
#[allow(clippy::too_many_arguments)]
pub fn secondary_rays_from(
    mode: Shade,
    tri: &dyn Fn(u32) -> Triangle,
    primary: &[Ray],
    hits: &[Hit],
    light: Vec3,
    samples: Range<u32>,
    ao_radius: f32,
) -> (Vec<Ray>, Vec<u32>) {
    let view = View {
        shade: mode,
        ao_radius,
        light,
        light_radius: 0.0,
    };
    let samples = if mode == Shade::Diffuse {
        0..1
    } else {
        samples
    };
    let mut rays = Vec::new();
    let mut owner = Vec::new();
    for (i, (r, h)) in primary.iter().zip(hits).enumerate() {
        if !h.is_hit() {
            continue;
        }
        let p = h.surface(&tri(h.prim), Vec3::from(r.dir));
        for s in samples.clone() {
            if let Some(ray) = view.secondary_ray(&p, i as u32, s) {
                rays.push(ray);
                owner.push(i as u32);
            }
        }
    }
    (rays, owner)
}

/// Direct light at a hit from the point light `light`, before visibility: the cosine
/// between the facing normal and the direction to the light (0 facing away).
pub fn lambert(tri: &Triangle, hit: &Hit, ray_dir: Vec3, light: Vec3) -> f32 {
    let n = facing_normal(tri, ray_dir);
    let l = (light - hit_point(tri, hit)).normalize_or_zero();
    n.dot(l).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad() -> Vec<Triangle> {
        let (a, b, c, d) = (
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(-1.0, 1.0, 0.0),
        );
        vec![[a, b, c], [a, c, d]]
    }

    fn camera() -> Camera {
        Camera {
            eye: Vec3::new(0.0, 0.0, 3.0),
            target: Vec3::ZERO,
            fov_y_deg: 60.0,
        }
    }

    #[test]
    fn light_sits_up_and_right_of_the_camera() {
        let cam = camera();
        let l = point_light(&cam);
        let (_, right, up) = cam.basis();
        assert!((l - cam.eye).dot(right) > 0.0 && (l - cam.eye).dot(up) > 0.0);
        assert!(((l - cam.eye).length() - 3.0 * 0.1025f32.sqrt()).abs() < 1e-5);
    }

    #[test]
    fn secondary_rays_per_mode() {
        use bvhtrace_core::{BuildOptions, TraceOptions, Traversal, trace_rays};
        let tris = quad();
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
        let cam = camera();
        let rays = cam.rays(8, 6);
        let hits = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::Stackless)).hits;
        let n_hit = hits.iter().filter(|h| h.is_hit()).count();
        assert!(n_hit > 0 && n_hit < rays.len());
        let tri = |p: u32| tris[p as usize];
        let light = point_light(&cam);
        let r = ao_radius(&bvh);
        let (ao, owner) = secondary_rays(Shade::Ao, &tri, &rays, &hits, light, 3, r);
        assert_eq!((ao.len(), owner.len()), (3 * n_hit, 3 * n_hit));
        assert!(ao.iter().all(|a| a.t_max == r && a.dir[2] > 0.0));
        // A later range of samples gives different rays from the same pixels.
        let (later, _) = secondary_rays_from(Shade::Ao, &tri, &rays, &hits, light, 3..6, r);
        assert_ne!(ao[0].dir, later[0].dir);
        let (shadow, _) = secondary_rays_from(Shade::Diffuse, &tri, &rays, &hits, light, 0..9, r);
        assert_eq!(shadow.len(), n_hit);
        let (none, _) = secondary_rays(Shade::Depth, &tri, &rays, &hits, light, 3, r);
        assert!(none.is_empty());
    }

    #[test]
    fn soft_lights_aim_at_points_of_the_sphere() {
        let cam = camera();
        let soft = View::for_camera(Shade::Diffuse, &cam, 2.0);
        assert_eq!(soft.ao_radius, 0.3);
        assert_eq!(soft.light_radius, 0.08);
        let surface = SurfacePoint {
            normal: Vec3::Z,
            origin: Vec3::ZERO,
        };
        for s in 0..16 {
            let r = soft.secondary_ray(&surface, 7, s).expect("diffuse traces");
            let end = Vec3::from(r.origin) + Vec3::from(r.dir) * r.t_max;
            let off = (end - soft.light).length();
            assert!(off <= soft.light_radius * 1.001, "sample {s}: {off}");
        }
        assert!(
            View::for_camera(Shade::Heatmap, &cam, 2.0)
                .secondary_ray(&surface, 0, 0)
                .is_none()
        );
    }
}
