//! Hits to pixels: one colour rule per mode ([`hit_colour`]), a whole RGB image from a
//! traced frame ([`compose_rgb`]), and the heatmap's legend.

use bvhtrace_core::{Counters, Hit, Ray, Triangle};
use glam::Vec3;

use crate::{BACKGROUND, Shade, View, facing_normal, lambert, palette};

/// The colour of a pixel whose primary ray hit, in mode `shade`: `normal` is the facing
/// geometric normal, `t` the hit distance and `depth_range` the image's
/// ([`palette::depth_range`]); `value` is the light in [0, 1] for [`Shade::Diffuse`], the
/// unoccluded fraction for [`Shade::Ao`] and the nodes visited over the image's most for
/// [`Shade::Heatmap`] (unused by the other modes).
pub fn hit_colour(
    shade: Shade,
    normal: Vec3,
    t: f32,
    depth_range: (f32, f32),
    value: f32,
) -> [u8; 3] {
    match shade {
        Shade::Normal | Shade::Path => palette::normal_colour(normal),
        Shade::Depth => palette::depth_grey(t, depth_range),
        Shade::Diffuse => palette::diffuse_colour(value),
        Shade::Ao => palette::ao_grey(value),
        Shade::Heatmap => palette::heat_ramp(value),
    }
}

/// The most nodes any ray visited (the heatmap's scale), at least 1.
pub fn max_nodes(counters: &[Counters]) -> u32 {
    counters.iter().map(|c| c.nodes).max().unwrap_or(1).max(1)
}

/// A traced frame, as [`compose_rgb`] reads it.
#[derive(Clone, Copy, Debug)]
pub struct Pixels<'a> {
    /// Image width and height, pixels.
    pub size: (u32, u32),
    /// The primary rays, row-major.
    pub rays: &'a [Ray],
    /// Their closest hits.
    pub hits: &'a [Hit],
    /// Their counters (read by the heatmap only; may be empty otherwise).
    pub counters: &'a [Counters],
    /// For each secondary ray, the pixel it belongs to ([`crate::secondary_rays`]).
    pub owner: &'a [u32],
    /// The secondary rays' any hits.
    pub secondary: &'a [Hit],
    /// AO rays per pixel (the AO mode's denominator).
    pub ao_samples: u32,
}

/// The frame shaded into RGB8 pixels, row-major, top row first, as `bvhtrace render` writes
/// them: a point light's shadow ray decides the diffuse light, the AO mode counts the
/// occluded rays, and the heatmap gets a legend along the bottom. `triangle` gives the
/// world-space corners of a hit's primitive.
pub fn compose_rgb(view: &View, px: &Pixels, triangle: &dyn Fn(u32) -> Triangle) -> Vec<u8> {
    let (w, h) = px.size;
    let mut img = vec![0u8; (w * h * 3) as usize];
    let put = |img: &mut Vec<u8>, i: usize, c: [u8; 3]| img[i * 3..i * 3 + 3].copy_from_slice(&c);
    let mut occluded = vec![0u32; px.rays.len()];
    for (o, sh) in px.owner.iter().zip(px.secondary) {
        if sh.is_hit() {
            occluded[*o as usize] += 1;
        }
    }
    let range = palette::depth_range(px.hits);
    let max = max_nodes(px.counters);
    for (i, (r, hit)) in px.rays.iter().zip(px.hits).enumerate() {
        if view.heatmap() {
            let n = px.counters.get(i).map_or(0, |c| c.nodes);
            put(&mut img, i, palette::heat_ramp(n as f32 / max as f32));
            continue;
        }
        if !hit.is_hit() {
            put(&mut img, i, BACKGROUND);
            continue;
        }
        let tri = &triangle(hit.prim);
        let d = Vec3::from(r.dir);
        let value = match view.shade {
            Shade::Diffuse if occluded[i] == 0 => lambert(tri, hit, d, view.light),
            Shade::Ao => 1.0 - occluded[i] as f32 / px.ao_samples as f32,
            _ => 0.0,
        };
        let c = hit_colour(view.shade, facing_normal(tri, d), hit.t, range, value);
        put(&mut img, i, c);
    }
    if view.heatmap() {
        draw_legend(&mut img, w, h, max);
    }
    img
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

/// Draws a number at (x, y) with `scale`-pixel dots into an RGB8 image `w` by `h`.
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

/// Adds the heatmap legend to an RGB8 image: a ramp bar along the bottom with its end
/// values (0 and `max`).
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

#[cfg(test)]
mod tests {
    use super::*;

    fn hit(prim: u32, t: f32) -> Hit {
        Hit {
            t,
            prim,
            u: 0.25,
            v: 0.25,
        }
    }

    #[test]
    fn each_mode_has_its_colour() {
        let n = Vec3::Z;
        assert_eq!(
            hit_colour(Shade::Normal, n, 1.0, (1.0, 2.0), 0.0),
            [128, 128, 255]
        );
        assert_eq!(hit_colour(Shade::Depth, n, 2.0, (1.0, 2.0), 0.0), [38; 3]);
        assert_eq!(hit_colour(Shade::Ao, n, 1.0, (1.0, 2.0), 0.5), [128; 3]);
        assert_eq!(
            hit_colour(Shade::Diffuse, n, 1.0, (1.0, 2.0), 0.0),
            palette::diffuse_colour(0.0)
        );
        assert_eq!(
            hit_colour(Shade::Heatmap, n, 1.0, (1.0, 2.0), 1.0),
            [216, 25, 12]
        );
    }

    #[test]
    fn ao_counts_occluded_rays_and_misses_show_the_background() {
        let tri = [
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ];
        let down = Ray::new(Vec3::new(0.0, 0.0, 1.0), Vec3::NEG_Z);
        let rays = [down, down];
        let hits = [hit(0, 1.0), Hit::miss(f32::INFINITY)];
        // Pixel 0: three of four AO rays blocked.
        let owner = [0, 0, 0, 0];
        let secondary = [hit(0, 0.1), hit(0, 0.1), hit(0, 0.1), Hit::miss(1.0)];
        let view = View {
            shade: Shade::Ao,
            ao_radius: 1.0,
            light: Vec3::ONE,
            light_radius: 0.0,
        };
        let px = Pixels {
            size: (2, 1),
            rays: &rays,
            hits: &hits,
            counters: &[],
            owner: &owner,
            secondary: &secondary,
            ao_samples: 4,
        };
        let img = compose_rgb(&view, &px, &|_| tri);
        assert_eq!(img[..3], palette::ao_grey(0.25));
        assert_eq!(img[3..], BACKGROUND);
    }

    #[test]
    fn heatmap_scales_by_the_most_nodes_and_draws_a_legend() {
        let counters: Vec<Counters> = (0..400u32)
            .map(|i| Counters {
                nodes: i % 10,
                ..Default::default()
            })
            .collect();
        assert_eq!(max_nodes(&counters), 9);
        assert_eq!(max_nodes(&[]), 1);
        let mut img = vec![7u8; 20 * 20 * 3];
        draw_legend(&mut img, 20, 20, 9);
        // The bottom rows are the legend's (black, the ramp, white digits).
        assert!(img[(19 * 20) * 3..].iter().all(|&b| b == 0 || b == 255));
        assert_eq!(img[..3], [7, 7, 7]);
    }
}
