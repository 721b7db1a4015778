//! The colours of the shading modes, shared by `bvhtrace render` and the viewer so that
//! their images match pixel for pixel.

use glam::Vec3;

use bvhtrace_core::Hit;

/// `v` in [0, 1] as an 8-bit channel, rounded.
pub fn to8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// The heatmap colour for `x` in [0, 1] (blue, cyan, green, yellow, red; NaN as 0): boxes
/// tested per pixel over the image's largest count.
pub fn heat_ramp(x: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [0.05, 0.05, 0.45],
        [0.0, 0.7, 0.9],
        [0.1, 0.8, 0.2],
        [0.95, 0.85, 0.1],
        [0.85, 0.1, 0.05],
    ];
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) } * 4.0;
    let i = (x as usize).min(3);
    let f = x - i as f32;
    let c = |k: usize| (STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f) * 255.0;
    [c(0) as u8, c(1) as u8, c(2) as u8]
}

/// `normal` mode: a unit normal's components mapped from [-1, 1] to [0, 1].
pub fn normal_colour(n: Vec3) -> [u8; 3] {
    let c = n * 0.5 + Vec3::splat(0.5);
    [to8(c.x), to8(c.y), to8(c.z)]
}

/// The nearest and farthest hit distances of an image, for [`depth_grey`]
/// (`(f32::MAX, 0)` when nothing is hit).
pub fn depth_range(hits: &[Hit]) -> (f32, f32) {
    hits.iter()
        .filter(|h| h.is_hit())
        .fold((f32::MAX, 0f32), |(a, b), h| (a.min(h.t), b.max(h.t)))
}

/// `depth` mode: nearer is lighter, over the image's [`depth_range`].
pub fn depth_grey(t: f32, (tmin, tmax): (f32, f32)) -> [u8; 3] {
    let g = 1.0 - (t - tmin) / (tmax - tmin).max(f32::MIN_POSITIVE);
    let v = to8(0.15 + 0.85 * g);
    [v, v, v]
}

/// `diffuse` mode: a warm white lit by `lit` in [0, 1] (cosine times visibility), over a
/// little ambient light.
pub fn diffuse_colour(lit: f32) -> [u8; 3] {
    let v = 0.08 + 0.85 * lit;
    [to8(v * 0.95), to8(v * 0.9), to8(v * 0.8)]
}

/// `ao` mode: the fraction of unoccluded samples as grey.
pub fn ao_grey(open: f32) -> [u8; 3] {
    let v = to8(open);
    [v, v, v]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colours_span_their_ranges() {
        assert_eq!(to8(-1.0), 0);
        assert_eq!(to8(0.5), 128);
        assert_eq!(to8(2.0), 255);
        assert_eq!(normal_colour(Vec3::Z), [128, 128, 255]);
        assert_eq!(normal_colour(-Vec3::X), [0, 128, 128]);
        // Nearest lightest, farthest darkest, a flat image not NaN.
        assert_eq!(depth_grey(1.0, (1.0, 3.0)), [255; 3]);
        assert_eq!(depth_grey(3.0, (1.0, 3.0)), [38; 3]);
        assert_eq!(depth_grey(2.0, (2.0, 2.0)), [255; 3]);
        assert_eq!(diffuse_colour(0.0), [19, 18, 16]);
        assert_eq!(ao_grey(1.0), [255; 3]);
        assert_eq!(heat_ramp(0.0), [12, 12, 114]);
        assert_eq!(heat_ramp(1.0), [216, 25, 12]);
        assert_eq!(heat_ramp(f32::NAN), heat_ramp(0.0));
    }
}
