//! Alpha-tested geometry: the one rule every walk uses to decide whether a candidate hit on
//! a masked triangle counts (glTF `alphaMode: "MASK"`), written so that the CPU and the
//! kernels compute the same bits.
//!
//! A candidate at barycentrics `(u, v)` (the weights of corners 1 and 2) on a triangle with
//! texture coordinates `uv0, uv1, uv2` samples its material's alpha texture at
//!
//! ```text
//! uv = (uv0 + (uv1 - uv0) u) + (uv2 - uv0) v        (each coordinate, in this order)
//! ```
//!
//! with the **nearest texel**: along an axis of `n` texels, the coordinate is wrapped into
//! `[0, 1]` by the sampler's mode ([`Wrap`]: `x - floor(x)`, `clamp(x, 0, 1)`, or the
//! mirror of `x - 2 floor(x / 2)`), then `floor(f * n)`, at most `n - 1` (a coordinate
//! that is not finite samples texel 0). The texel's alpha (8 bits) passes when it is at
//! least the material's [`AlphaMask::min_texel`], precomputed on the host from the base
//! colour factor's alpha and the cutoff ([`min_passing_texel`]), so no kernel compares
//! floats for the decision. Every step is exactly rounded and leaves a driver nothing to
//! fuse, so a device with IEEE f32 arithmetic agrees with the CPU bit for bit.
//!
//! Most triangles never need the texture: [`triangle_state`] settles each triangle ahead
//! of time as opaque, transparent, or one to test per candidate.

use glam::Vec2;

/// How texture coordinates outside `0..1` wrap (glTF sampler `wrapS` / `wrapT`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Wrap {
    /// `REPEAT` (10497, glTF's default): the fractional part.
    #[default]
    Repeat,
    /// `CLAMP_TO_EDGE` (33071): clamped to `0..1`.
    ClampToEdge,
    /// `MIRRORED_REPEAT` (33648): repeated, every other period mirrored.
    MirroredRepeat,
}

impl Wrap {
    /// The glTF sampler constant's mode (`None` for an unknown constant).
    pub fn from_gl(constant: u32) -> Option<Wrap> {
        match constant {
            10497 => Some(Wrap::Repeat),
            33071 => Some(Wrap::ClampToEdge),
            33648 => Some(Wrap::MirroredRepeat),
            _ => None,
        }
    }

    /// The mode's index in the kernels' material records (0, 1, 2 in declaration order).
    pub fn index(self) -> u32 {
        self as u32
    }
}

/// The smallest 8-bit texel alpha `t` with `(t / 255) * factor_alpha >= cutoff`, computed in
/// f32 as written; 256 when none passes. What the walks compare texels with.
pub fn min_passing_texel(factor_alpha: f32, cutoff: f32) -> u32 {
    (0..=255u32)
        .find(|&t| (t as f32 / 255.0) * factor_alpha >= cutoff)
        .unwrap_or(256)
}

/// One masked material's texture as a walk samples it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlphaMask<'a> {
    /// The texels' alpha, row by row from the top (`v = 0`), `width * height` of them.
    pub alpha: &'a [u8],
    /// Texels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// How `u` (along a row) and `v` (down the rows) wrap.
    pub wrap: [Wrap; 2],
    /// The smallest texel alpha that passes ([`min_passing_texel`]).
    pub min_texel: u32,
}

/// The texture coordinate at barycentrics `(u, v)` of a triangle whose corners have
/// `uv`, in the rule's order of operations.
pub fn interpolate_uv(uv: &[Vec2; 3], u: f32, v: f32) -> Vec2 {
    let at = |k: usize| (uv[0][k] + (uv[1][k] - uv[0][k]) * u) + (uv[2][k] - uv[0][k]) * v;
    Vec2::new(at(0), at(1))
}

/// The texel index along an axis of `size` texels for coordinate `x` under `wrap`.
pub fn texel_index(x: f32, size: u32, wrap: Wrap) -> u32 {
    if !x.is_finite() || size == 0 {
        return 0;
    }
    let f = match wrap {
        Wrap::Repeat => x - x.floor(),
        Wrap::ClampToEdge => x.clamp(0.0, 1.0),
        Wrap::MirroredRepeat => {
            let g = x - 2.0 * (x * 0.5).floor();
            if g > 1.0 { 2.0 - g } else { g }
        }
    };
    ((f * size as f32).floor() as u32).min(size - 1)
}

impl AlphaMask<'_> {
    /// The alpha of the texel nearest `uv`.
    pub fn texel(&self, uv: Vec2) -> u32 {
        let x = texel_index(uv.x, self.width, self.wrap[0]);
        let y = texel_index(uv.y, self.height, self.wrap[1]);
        let i = y as usize * self.width as usize + x as usize;
        self.alpha.get(i).copied().map_or(255, u32::from)
    }

    /// Whether a candidate at barycentrics `(u, v)` on a triangle with corner coordinates
    /// `uv` counts as a hit.
    pub fn passes(&self, uv: &[Vec2; 3], u: f32, v: f32) -> bool {
        self.texel(interpolate_uv(uv, u, v)) >= self.min_texel
    }
}

/// What a masked triangle is, settled ahead of any ray.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TriangleState {
    /// Every texel it can sample passes: a hit like any other, no texture read.
    Opaque,
    /// No texel it can sample passes: never hit.
    Transparent,
    /// Some pass and some do not: each candidate samples the texture.
    Test,
}

/// The texel range `[lo, hi]` (inclusive) along one axis that coordinates in
/// `[min, max]` can sample, one texel of margin each side; `None` for the whole axis.
fn texel_span(min: f32, max: f32, size: u32, wrap: Wrap) -> Option<(u32, u32)> {
    if !(min.is_finite() && max.is_finite()) {
        return None;
    }
    // Within one period (one unmirrored half-period for the mirror) the index is monotone.
    // An interpolated coordinate may round a little past the corners' range: a range that
    // comes that close to a period's end counts as crossing it.
    let d = 1e-5 * (1.0 + min.abs() + max.abs());
    let same_period = match wrap {
        Wrap::ClampToEdge => true,
        Wrap::Repeat | Wrap::MirroredRepeat => (min - d).floor() == (max + d).floor(),
    };
    if !same_period {
        return None;
    }
    let (a, b) = (texel_index(min, size, wrap), texel_index(max, size, wrap));
    let (lo, hi) = (a.min(b), a.max(b));
    Some((lo.saturating_sub(1), (hi + 1).min(size - 1)))
}

/// The state of a triangle with corner coordinates `uv` under `mask`, conservatively:
/// the texels its coordinates can reach (with a texel of margin for rounding) all pass,
/// none pass, or both.
pub fn triangle_state(uv: &[Vec2; 3], mask: &AlphaMask<'_>) -> TriangleState {
    if mask.min_texel == 0 {
        return TriangleState::Opaque;
    }
    if mask.min_texel > 255 || mask.width == 0 || mask.height == 0 {
        return TriangleState::Transparent;
    }
    let lo = uv[0].min(uv[1]).min(uv[2]);
    let hi = uv[0].max(uv[1]).max(uv[2]);
    let whole = |size: u32| (0, size - 1);
    let xs = texel_span(lo.x, hi.x, mask.width, mask.wrap[0]).unwrap_or(whole(mask.width));
    let ys = texel_span(lo.y, hi.y, mask.height, mask.wrap[1]).unwrap_or(whole(mask.height));
    let (mut pass, mut fail) = (false, false);
    for y in ys.0..=ys.1 {
        let row = y as usize * mask.width as usize;
        for x in xs.0..=xs.1 {
            let t = mask
                .alpha
                .get(row + x as usize)
                .copied()
                .map_or(255, u32::from);
            if t >= mask.min_texel {
                pass = true;
            } else {
                fail = true;
            }
            if pass && fail {
                return TriangleState::Test;
            }
        }
    }
    if pass {
        TriangleState::Opaque
    } else {
        TriangleState::Transparent
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thresholds_are_inclusive_and_exact() {
        // Alpha exactly at the cutoff passes (glTF: alpha >= cutoff is opaque).
        assert_eq!(min_passing_texel(1.0, 0.5), 128);
        assert_eq!(min_passing_texel(1.0, 0.0), 0);
        assert_eq!(min_passing_texel(1.0, 1.0), 255);
        assert_eq!(
            min_passing_texel(0.5, 0.75),
            256,
            "the factor caps alpha at 0.5"
        );
        assert_eq!(min_passing_texel(0.0, 0.5), 256);
    }

    #[test]
    fn wrap_modes_pick_the_nearest_texel() {
        let n = 4;
        for (x, repeat, clamp, mirror) in [
            (0.0, 0, 0, 0),
            (0.3, 1, 1, 1),
            (0.999, 3, 3, 3),
            (1.0, 0, 3, 3),
            (1.3, 1, 3, 2),
            (-0.3, 2, 0, 1),
            (2.3, 1, 3, 1),
            (-1.3, 2, 0, 2),
        ] {
            assert_eq!(texel_index(x, n, Wrap::Repeat), repeat, "repeat {x}");
            assert_eq!(texel_index(x, n, Wrap::ClampToEdge), clamp, "clamp {x}");
            assert_eq!(
                texel_index(x, n, Wrap::MirroredRepeat),
                mirror,
                "mirror {x}"
            );
        }
        // A tiny negative coordinate rounds to the last texel, never past it.
        assert_eq!(texel_index(-1e-9, n, Wrap::Repeat), 3);
        assert_eq!(texel_index(f32::NAN, n, Wrap::Repeat), 0);
        assert_eq!(texel_index(0.7, 1, Wrap::MirroredRepeat), 0, "one texel");
    }

    #[test]
    fn triangle_states_are_conservative() {
        // 4x4: the left half opaque (255), the right half cut (0).
        let alpha: Vec<u8> = (0..16).map(|i| if i % 4 < 2 { 255 } else { 0 }).collect();
        let mask = AlphaMask {
            alpha: &alpha,
            width: 4,
            height: 4,
            wrap: [Wrap::ClampToEdge; 2],
            min_texel: 128,
        };
        let tri = |a: [f32; 2], b: [f32; 2], c: [f32; 2]| [a.into(), b.into(), c.into()];
        let left = tri([0.0, 0.0], [0.1, 0.0], [0.0, 1.0]);
        let right = tri([0.9, 0.0], [1.0, 0.0], [1.0, 1.0]);
        let across = tri([0.0, 0.0], [1.0, 0.0], [0.0, 1.0]);
        assert_eq!(triangle_state(&left, &mask), TriangleState::Opaque);
        assert_eq!(triangle_state(&right, &mask), TriangleState::Transparent);
        assert_eq!(triangle_state(&across, &mask), TriangleState::Test);
        // Every candidate on a settled triangle agrees with its state.
        for (t, state) in [(&left, true), (&right, false)] {
            for k in 0..=20 {
                let (u, v) = (k as f32 / 40.0, (20 - k) as f32 / 40.0);
                assert_eq!(mask.passes(t, u, v), state, "{t:?} at {u}, {v}");
            }
        }
        let all_pass = AlphaMask {
            min_texel: 0,
            ..mask
        };
        assert_eq!(triangle_state(&across, &all_pass), TriangleState::Opaque);
        let none = AlphaMask {
            min_texel: 256,
            ..mask
        };
        assert_eq!(triangle_state(&across, &none), TriangleState::Transparent);
        // Repeat past a period boundary: the whole texture, so both kinds of texel.
        let wrapped = AlphaMask {
            wrap: [Wrap::Repeat; 2],
            ..mask
        };
        let spans = tri([0.1, 0.0], [1.2, 0.0], [0.1, 0.1]);
        assert_eq!(triangle_state(&spans, &wrapped), TriangleState::Test);
        // Corners on a period's start: a coordinate rounded just below it samples the far
        // end (here the cut half), so the triangle is tested, not settled.
        let on_edge = tri([1.0, 0.0], [1.2, 0.0], [1.0, 0.2]);
        assert_eq!(texel_index(0.99999994, 4, Wrap::Repeat), 3);
        assert_eq!(triangle_state(&on_edge, &wrapped), TriangleState::Test);
    }

    #[test]
    fn the_interpolated_coordinate_follows_the_barycentrics() {
        let uv = [
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(0.0, 2.0),
        ];
        assert_eq!(interpolate_uv(&uv, 0.0, 0.0), uv[0]);
        assert_eq!(interpolate_uv(&uv, 1.0, 0.0), uv[1]);
        assert_eq!(interpolate_uv(&uv, 0.0, 1.0), uv[2]);
        assert_eq!(interpolate_uv(&uv, 0.25, 0.5), Vec2::new(0.25, 1.0));
    }
}
