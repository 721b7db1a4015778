//! An image's rays in 8x8 tiles ([`tile_order`]), the order in which
//! [`crate::trace_packets`] walks one tile per packet, and the answers back in pixel order.

use bvhtrace_core::Ray;

use crate::packet::{PACKET, tile_order};

/// A `width` x `height` image's pixels in [`tile_order`], and the way back.
pub struct Tiles {
    /// The pixel at each place of the tiled order.
    order: Vec<u32>,
    /// Each pixel's place in it.
    rank: Vec<u32>,
    /// The pixels of each tile, in order (tiles at the right and bottom edges are cut).
    sizes: Vec<usize>,
}

impl Tiles {
    /// The tiles of a `width` x `height` image.
    pub fn new(width: u32, height: u32) -> Tiles {
        let order = tile_order(width, height);
        let mut rank = vec![0; order.len()];
        for (k, &p) in order.iter().enumerate() {
            rank[p as usize] = k as u32;
        }
        let mut sizes = Vec::new();
        for ty in (0..height).step_by(8) {
            for tx in (0..width).step_by(8) {
                sizes.push(((width - tx).min(8) * (height - ty).min(8)) as usize);
            }
        }
        Tiles { order, rank, sizes }
    }

    /// Per-pixel `v` (one per pixel) in tile order.
    pub fn gather<T: Copy>(&self, v: &[T]) -> Vec<T> {
        self.order.iter().map(|&p| v[p as usize]).collect()
    }

    /// Tile-ordered `v` (one per pixel) back in pixel order.
    pub fn scatter<T: Copy>(&self, v: &[T]) -> Vec<T> {
        self.rank.iter().map(|&k| v[k as usize]).collect()
    }

    /// Rays `rays` of pixels `owner` in tile order, and where each of them went. With at
    /// most one per pixel (shadow rays toward one light), each tile's rays make one packet
    /// of [`PACKET`]: a pixel without one holds the tile's first ray over an empty interval
    /// (`t_min` 1, `t_max` 0), which no tracer walks and every tracer answers with a miss,
    /// so that no packet spans two tiles; tiles without any are left out. With several
    /// per pixel (ambient occlusion), each pixel's rays stay together, in their order.
    pub fn packets(&self, rays: &[Ray], owner: &[u32]) -> (Vec<Ray>, Vec<usize>) {
        let mut of_place = vec![u32::MAX; self.order.len()];
        let mut one_each = true;
        for (i, &p) in owner.iter().enumerate() {
            let k = &mut of_place[self.rank[p as usize] as usize];
            one_each &= *k == u32::MAX;
            *k = i as u32;
        }
        let mut out = Vec::with_capacity(rays.len());
        let mut place = vec![0; rays.len()];
        if !one_each {
            let mut by_place: Vec<usize> = (0..rays.len()).collect();
            by_place.sort_by_key(|&i| self.rank[owner[i] as usize]);
            for i in by_place {
                place[i] = out.len();
                out.push(rays[i]);
            }
            return (out, place);
        }
        let mut at = 0;
        for &size in &self.sizes {
            let tile = &of_place[at..at + size];
            at += size;
            let Some(&first) = tile.iter().find(|&&i| i != u32::MAX) else {
                continue;
            };
            // A tracer that looks at the directions to choose its walk sees the tile's own.
            let idle = Ray {
                t_min: 1.0,
                t_max: 0.0,
                ..rays[first as usize]
            };
            for k in 0..PACKET {
                match tile.get(k).filter(|&&i| i != u32::MAX) {
                    Some(&i) => {
                        place[i as usize] = out.len();
                        out.push(rays[i as usize]);
                    }
                    None => out.push(idle),
                }
            }
        }
        (out, place)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// A ray told apart by its origin's `x`.
    fn ray(i: u32) -> Ray {
        Ray::new(Vec3::new(i as f32, 0.0, 0.0), Vec3::new(0.1, 0.2, 1.0))
    }

    #[test]
    fn tiles_put_answers_back_in_pixel_order() {
        // Cut tiles at the right and bottom edges.
        let tiles = Tiles::new(21, 13);
        let px: Vec<u32> = (0..21 * 13).collect();
        let tiled = tiles.gather(&px);
        assert_ne!(tiled, px);
        assert_eq!(tiled[..8], [0, 1, 2, 3, 4, 5, 6, 7]);
        assert_eq!(tiled[8], 21);
        assert_eq!(tiles.scatter(&tiled), px);
        assert_eq!(tiles.sizes.iter().sum::<usize>(), px.len());
    }

    #[test]
    fn one_ray_per_pixel_makes_one_packet_per_tile() {
        let (w, h) = (20, 10);
        let tiles = Tiles::new(w, h);
        // Every third pixel of the top band has a shadow ray; the tiles of the bottom band
        // (pixels from row 8 on) and the third tile of the top band have none.
        let owner: Vec<u32> = (0..w * 8).filter(|p| p % 3 == 0 && p % w < 16).collect();
        let rays: Vec<Ray> = owner.iter().map(|&p| ray(p)).collect();
        let (out, place) = tiles.packets(&rays, &owner);
        assert_eq!(out.len(), 2 * PACKET);
        for (i, &k) in place.iter().enumerate() {
            assert_eq!(out[k], rays[i]);
            // Its place in its tile's packet is its pixel's place in the tile.
            let p = owner[i];
            let (tile, at) = ((p % w) / 8, (p / w) * 8 + (p % w) % 8);
            assert_eq!(k as u32, tile * 64 + at);
        }
        let idle = out.iter().filter(|r| r.t_min > r.t_max).count();
        assert_eq!(idle, out.len() - rays.len());
    }

    #[test]
    fn several_rays_per_pixel_keep_each_pixels_rays_together() {
        let tiles = Tiles::new(16, 8);
        let owner: Vec<u32> = (0..16 * 8).flat_map(|p| [p, p, p]).collect();
        let rays: Vec<Ray> = (0..owner.len() as u32).map(ray).collect();
        let (out, place) = tiles.packets(&rays, &owner);
        assert_eq!(out.len(), rays.len());
        for (i, &k) in place.iter().enumerate() {
            assert_eq!(out[k], rays[i]);
        }
        // The first tile's pixels first, each pixel's three rays in their order.
        assert_eq!(out[3..6], rays[3..6]);
        assert_eq!(out[24..27], rays[48..51]);
    }
}
