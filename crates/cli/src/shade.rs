//! Turning hits into pixels, and the secondary rays some modes need. Everything here runs
//! on the CPU for both backends, so the GPU and CPU images differ only where hits do.

use bvhtrace_core::palette;
use bvhtrace_core::{FlatBvh, Hit, Ray, Triangle};
use bvhtrace_scene::Camera;
use glam::Vec3;

/// Background colour.
pub const BACKGROUND: [u8; 3] = [24, 26, 32];

/// Shading modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Shade {
    /// Geometric normal, facing the camera, as colour.
    Normal,
    /// Distance, near bright, far dark.
    Depth,
    /// Diffuse light with a shadow ray (any-hit) to a point light.
    Diffuse,
    /// Ambient occlusion from `--ao-samples` any-hit rays per pixel.
    Ao,
    /// Nodes visited per pixel, with a colour legend.
    Heatmap,
}

// The repeatable sampling and the hit point are shared with the viewer and the stress
// cases; secondary rays leave a surface by `Hit::surface`.
pub use bvhtrace_core::surface::{cosine_dir, facing_normal, hit_point};

/// Secondary rays for the diffuse (one shadow ray) and AO (`samples` rays) modes: for each
/// primary hit, rays and the index of the pixel they belong to.
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
/// images made from disjoint ranges have independent samples (`bench --converge`).
#[allow(clippy::too_many_arguments)]
pub fn secondary_rays_from(
    mode: Shade,
    tri: &dyn Fn(u32) -> Triangle,
    primary: &[Ray],
    hits: &[Hit],
    light: Vec3,
    samples: std::ops::Range<u32>,
    ao_radius: f32,
) -> (Vec<Ray>, Vec<u32>) {
    let mut rays = Vec::new();
    let mut owner = Vec::new();
    for (i, (r, h)) in primary.iter().zip(hits).enumerate() {
        if !h.is_hit() {
            continue;
        }
        let p = h.surface(&tri(h.prim), Vec3::from(r.dir));
        match mode {
            Shade::Diffuse => {
                rays.push(p.ray_toward(light));
                owner.push(i as u32);
            }
            Shade::Ao => {
                for s in samples.clone() {
                    rays.push(p.spawn_ray(cosine_dir(p.normal, i as u32, s), ao_radius));
                    owner.push(i as u32);
                }
            }
            _ => {}
        }
    }
    (rays, owner)
}

/// The point light of the diffuse modes: up and to the right of the camera, so that it sees
/// what the camera sees (closed rooms as well as open scenes) and casts visible shadows.
pub fn point_light(cam: &Camera) -> Vec3 {
    let (_, right, up) = cam.basis();
    cam.eye + (right * 0.25 + up * 0.2) * (cam.target - cam.eye).length()
}

/// The length of ambient-occlusion rays: 15% of the diagonal of the scene's box.
pub fn ao_radius(bvh: &FlatBvh) -> f32 {
    let b = bvh.bounds();
    0.15 * (b.max - b.min).length().max(f32::MIN_POSITIVE)
}

/// Direct light at a hit from the point light `light`, before visibility: the cosine
/// between the facing normal and the direction to the light (0 facing away).
pub fn lambert(tri: &Triangle, hit: &Hit, ray_dir: Vec3, light: Vec3) -> f32 {
    let n = facing_normal(tri, ray_dir);
    let l = (light - hit_point(tri, hit)).normalize_or_zero();
    n.dot(l).max(0.0)
}

/// 3x5 digits for the legend.
const DIGITS: [[u8; 5]; 10] = [
    [7, 5, 5, 5, 7],
    [2, 6, 2, 2, 7],
    [7, 1, 7, 4, 7],
    [7, 1, 7, 1, 7],
    [5, 5, 7, 1, 1],
    [7, 4, 7, 1, 7],
    [7, 4, 7, 5, 7],
    [7, 1, 1, 1, 1],
    [7, 5, 7, 5, 7],
    [7, 5, 7, 1, 7],
];

/// Draws a number at (x, y) with `scale`-pixel dots.
pub fn draw_number(
    img: &mut [u8],
    w: u32,
    h: u32,
    (x, y): (u32, u32),
    n: u32,
    scale: u32,
    col: [u8; 3],
) {
    for (k, ch) in n.to_string().bytes().enumerate() {
        let g = DIGITS[(ch - b'0') as usize];
        for (row, bits) in g.iter().enumerate() {
            for c in 0..3 {
                if bits >> (2 - c) & 1 == 1 {
                    for dy in 0..scale {
                        for dx in 0..scale {
                            let px = x + (k as u32 * 4 + c) * scale + dx;
                            let py = y + row as u32 * scale + dy;
                            if px < w && py < h {
                                let o = ((py * w + px) * 3) as usize;
                                img[o..o + 3].copy_from_slice(&col);
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Adds the heatmap legend: a ramp bar along the bottom with its end values.
pub fn draw_legend(img: &mut [u8], w: u32, h: u32, max: u32) {
    let scale = (h / 200).max(1);
    let bar_h = 8 * scale;
    let y0 = h.saturating_sub(bar_h + 8 * scale);
    let (x0, x1) = (8 * scale, w.saturating_sub(8 * scale));
    for y in y0.saturating_sub(2 * scale)..h {
        for x in 0..w {
            let o = ((y * w + x) * 3) as usize;
            img[o..o + 3].copy_from_slice(&[0, 0, 0]);
        }
    }
    for x in x0..x1 {
        let c = palette::heat_ramp((x - x0) as f32 / (x1 - x0).max(1) as f32);
        for y in y0..y0 + bar_h {
            let o = ((y * w + x) * 3) as usize;
            img[o..o + 3].copy_from_slice(&c);
        }
    }
    let ty = y0 + bar_h + scale;
    draw_number(img, w, h, (x0, ty), 0, scale, [255; 3]);
    let digits = max.to_string().len() as u32;
    draw_number(
        img,
        w,
        h,
        (x1.saturating_sub(digits * 4 * scale), ty),
        max,
        scale,
        [255; 3],
    );
}
