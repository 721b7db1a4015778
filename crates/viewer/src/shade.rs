//! Progressive accumulation over the shared shading (`bvhtrace_shade`: the modes, the
//! light, the secondary rays and the colours of `bvhtrace render`): the diffuse and AO
//! modes add more secondary samples every frame while the camera is still and show their
//! running average. Also the comparison of two backends' hits.
//!
//! Everything here runs on the CPU from the traced hits, for both backends, so the GPU and
//! CPU images differ only where the hits do.

use bvhtrace_core::surface::SurfacePoint;
use bvhtrace_core::{Counters, Hit, Ray, Triangle};
use bvhtrace_shade::{hit_colour, palette};
use glam::Vec3;

// The modes, the light, the AO radius, the secondary rays and the colours are the shared
// shading crate's, so the viewer's images match `bvhtrace render`.
pub use bvhtrace_shade::{BACKGROUND, Shade, View};

/// One primary pass and the secondary samples accumulated on top of it.
#[derive(Clone, Debug, Default)]
pub struct Accumulation {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// The primary rays, row-major (`Camera::rays`).
    pub rays: Vec<Ray>,
    /// Their closest hits.
    pub hits: Vec<Hit>,
    /// Their counters (empty unless the heatmap asked for them).
    pub counters: Vec<Counters>,
    /// Secondary samples per hit pixel accumulated so far.
    pub samples: u32,
    /// Pixels with a hit, in order: the owners of the secondary rays.
    hit_pixels: Vec<u32>,
    /// Where each hit pixel's secondary rays leave its surface.
    surfaces: Vec<SurfacePoint>,
    /// Per hit pixel: the sum of the samples' values.
    sums: Vec<f32>,
}

impl Accumulation {
    /// A fresh accumulation over a primary pass; `triangle` gives the world-space corners
    /// of the primitive a hit names (`None` for an id it does not know: the pixel then
    /// counts as a miss).
    pub fn new(
        width: u32,
        height: u32,
        rays: Vec<Ray>,
        hits: Vec<Hit>,
        counters: Vec<Counters>,
        triangle: impl Fn(u32) -> Option<Triangle>,
    ) -> Accumulation {
        let mut hit_pixels = Vec::new();
        let mut surfaces = Vec::new();
        for (i, (r, h)) in rays.iter().zip(&hits).enumerate() {
            let Some(tri) = h.is_hit().then(|| triangle(h.prim)).flatten() else {
                continue;
            };
            hit_pixels.push(i as u32);
            surfaces.push(h.surface(&tri, Vec3::from(r.dir)));
        }
        let sums = vec![0.0; hit_pixels.len()];
        Accumulation {
            width,
            height,
            rays,
            hits,
            counters,
            samples: 0,
            hit_pixels,
            surfaces,
            sums,
        }
    }

    /// Number of pixels whose primary ray hit something.
    pub fn hit_count(&self) -> usize {
        self.hit_pixels.len()
    }

    /// The secondary rays of samples `samples .. samples + count` for every hit pixel,
    /// pixel after pixel (`count` consecutive rays each). Empty for modes that do not
    /// accumulate.
    pub fn secondary_rays(&self, view: &View, count: u32) -> Vec<Ray> {
        if !view.accumulates() || count == 0 {
            return Vec::new();
        }
        let mut out = Vec::with_capacity(self.hit_pixels.len() * count as usize);
        for (&p, surface) in self.hit_pixels.iter().zip(&self.surfaces) {
            for k in 0..count {
                let s = self.samples.wrapping_add(k);
                out.extend(view.secondary_ray(surface, p, s));
            }
        }
        out
    }

    /// Adds the answers to [`Accumulation::secondary_rays`]`(view, count)`.
    pub fn accumulate(&mut self, view: &View, rays: &[Ray], hits: &[Hit], count: u32) {
        if count == 0 || hits.len() != self.hit_pixels.len() * count as usize {
            return;
        }
        for (i, sum) in self.sums.iter_mut().enumerate() {
            let n = self.surfaces[i].normal;
            let range = i * count as usize..(i + 1) * count as usize;
            for (r, h) in rays[range.clone()].iter().zip(&hits[range]) {
                if h.is_hit() {
                    continue;
                }
                *sum += match view.shade {
                    Shade::Ao => 1.0,
                    _ => n.dot(Vec3::from(r.dir).normalize_or_zero()).max(0.0),
                };
            }
        }
        self.samples += count;
    }

    /// The most nodes any primary ray visited (the heatmap's scale), at least 1.
    pub fn max_nodes(&self) -> u32 {
        bvhtrace_shade::max_nodes(&self.counters)
    }

    /// The image as RGBA8, row-major, top row first.
    pub fn compose(&self, view: &View) -> Vec<u8> {
        let n_px = self.width as usize * self.height as usize;
        let mut img = vec![255u8; n_px * 4];
        let mut put = |i: usize, c: [u8; 3]| img[i * 4..i * 4 + 3].copy_from_slice(&c);
        if view.heatmap() {
            let max = self.max_nodes() as f32;
            for i in 0..n_px {
                let n = self.counters.get(i).map_or(0, |c| c.nodes);
                put(i, palette::heat_ramp(n as f32 / max));
            }
            return img;
        }
        for i in 0..n_px {
            put(i, BACKGROUND);
        }
        let range = palette::depth_range(&self.hits);
        for (k, &p) in self.hit_pixels.iter().enumerate() {
            let p = p as usize;
            let SurfacePoint {
                normal: n,
                origin: o,
            } = self.surfaces[k];
            let mean = |sum: f32| sum / self.samples as f32;
            let value = match view.shade {
                // No shadow samples yet: unshadowed light as a preview.
                Shade::Diffuse if self.samples == 0 => {
                    n.dot((view.light - o).normalize_or_zero()).max(0.0)
                }
                Shade::Ao if self.samples == 0 => 1.0,
                Shade::Diffuse | Shade::Ao => mean(self.sums[k]),
                _ => 0.0,
            };
            put(p, hit_colour(view.shade, n, self.hits[p].t, range, value));
        }
        img
    }
}

/// The result of comparing GPU hits with the CPU twin's on the same rays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Comparison {
    /// Rays compared.
    pub rays: usize,
    /// Rays whose hit triangle differs (including hit against miss).
    pub prim_mismatches: usize,
    /// Rays with the same triangle but a different `t` (bitwise).
    pub t_mismatches: usize,
    /// The largest relative `t` difference among same-triangle hits.
    pub max_rel_t: f32,
}

/// Compares two hit lists ray by ray and draws the difference image (RGBA8): matching pixels
/// dimmed grey from `base` (an RGBA8 image of the same size), a different triangle in red,
/// the same triangle at a different `t` in yellow.
pub fn compare_hits(a: &[Hit], b: &[Hit], base: &[u8]) -> (Comparison, Vec<u8>) {
    let mut c = Comparison {
        rays: a.len().min(b.len()),
        ..Default::default()
    };
    let mut img = vec![255u8; c.rays * 4];
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        let px = &mut img[i * 4..i * 4 + 3];
        let same_prim = x.prim == y.prim || (!x.is_hit() && !y.is_hit());
        if !same_prim {
            c.prim_mismatches += 1;
            px.copy_from_slice(&[255, 40, 40]);
        } else if x.is_hit() && x.t.to_bits() != y.t.to_bits() {
            c.t_mismatches += 1;
            let rel = (x.t - y.t).abs() / x.t.abs().max(y.t.abs()).max(f32::MIN_POSITIVE);
            c.max_rel_t = c.max_rel_t.max(rel);
            px.copy_from_slice(&[255, 220, 40]);
        } else {
            let g = base
                .get(i * 4..i * 4 + 3)
                .map_or(0, |s| ((s[0] as u32 + s[1] as u32 + s[2] as u32) / 9) as u8);
            px.copy_from_slice(&[g, g, g]);
        }
    }
    (c, img)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bvhtrace_core::{BuildOptions, FlatBvh, Query, TraceOptions, Traversal, trace_rays};
    use bvhtrace_scene::Camera;

    fn quad() -> Vec<Triangle> {
        let (a, b, c, d) = (
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(-1.0, 1.0, 0.0),
        );
        vec![[a, b, c], [a, c, d]]
    }

    #[test]
    fn ao_accumulates_towards_open_sky() {
        let tris = quad();
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
        let cam = Camera {
            eye: Vec3::new(0.0, 0.0, 3.0),
            target: Vec3::ZERO,
            fov_y_deg: 30.0,
        };
        let (w, h) = (8, 6);
        let rays = cam.rays(w, h);
        let hits = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::Stackless)).hits;
        let mut acc = Accumulation::new(w, h, rays, hits, Vec::new(), |p| {
            tris.get(p as usize).copied()
        });
        assert!(acc.hit_count() > 0);
        let view = View::for_camera(Shade::Ao, &cam, 2.0);
        for _ in 0..3 {
            let sec = acc.secondary_rays(&view, 4);
            assert_eq!(sec.len(), acc.hit_count() * 4);
            let any = TraceOptions::new(Traversal::Stackless, Query::Any);
            let sh = trace_rays(&bvh, &sec, &any).hits;
            acc.accumulate(&view, &sec, &sh, 4);
        }
        assert_eq!(acc.samples, 12);
        // A lone quad occludes nothing in front of itself: AO is fully open.
        let img = acc.compose(&view);
        assert_eq!(img.len(), (w * h * 4) as usize);
        let centre = ((h / 2 * w + w / 2) * 4) as usize;
        assert_eq!(img[centre..centre + 3], [255, 255, 255]);
        // Non-accumulating views trace no secondary rays.
        let normal = View::for_camera(Shade::Normal, &cam, 2.0);
        assert!(acc.secondary_rays(&normal, 4).is_empty());
    }

    #[test]
    fn compare_counts_mismatches() {
        let hit = |prim, t| Hit {
            t,
            prim,
            u: 0.0,
            v: 0.0,
        };
        let a = [
            hit(1, 1.0),
            hit(2, 2.0),
            Hit::miss(f32::INFINITY),
            hit(3, 1.0),
        ];
        let b = [
            hit(1, 1.0),
            hit(5, 2.0),
            Hit::miss(f32::INFINITY),
            hit(3, 1.5),
        ];
        let (c, img) = compare_hits(&a, &b, &[100; 16]);
        assert_eq!((c.rays, c.prim_mismatches, c.t_mismatches), (4, 1, 1));
        assert_eq!(&img[4..7], &[255, 40, 40]);
        assert_eq!(&img[12..15], &[255, 220, 40]);
        assert!((c.max_rel_t - 1.0 / 3.0).abs() < 1e-6);
    }
}
