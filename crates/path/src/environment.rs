//! An HDR environment map, resampled on the host from an equirectangular image into an
//! octahedral map that the device (`shaders/path_environment.wgsl`) and its CPU twin
//! ([`Environment::lookup`], [`Environment::sample`]) read with the same operations in the
//! same order: only `+ - * /`, `sqrt`, `abs`, `floor`, `min`, `max`, selections and
//! integer operations, no transcendental function, so both compute the same bits.
//!
//! # Octahedral map (+Y up)
//!
//! A direction `d` (finite, not zero, not necessarily unit) goes to the point
//! `p = d / (|d.x| + |d.y| + |d.z|)` of the octahedron, then to the square `[-1, 1]^2`:
//! if `p.y >= 0`, `(u, v) = (p.x, p.z)` (the upper hemisphere fills the middle diamond
//! `|u| + |v| <= 1`, +Y at its centre, +X toward `u = 1`, +Z toward `v = 1`); otherwise
//! the lower face folds out to the corners: `u = ±(1 - |p.z|)` with the sign of `p.x`,
//! `v = ±(1 - |p.x|)` with the sign of `p.z` (`-0.0` counts as positive, so -Y itself goes
//! to the corner `(1, 1)`; the square's outer edges are seams, `(1, v)` and `(1, -v)` being
//! the same direction). Texel column `ix = min(floor((u + 1) * (N/2)), N - 1)`, row `iy`
//! the same from `v`, index `iy * N + ix`. Back from the square:
//! `p = (u, 1 - |u| - |v|, v)`, and where that `y < 0`, `p.x = ±(1 - |v|)` with the sign
//! of `u` and `p.z = ±(1 - |u|)` with the sign of `v`; the direction is `p / |p|`.
//!
//! # Densities
//!
//! On each face the square maps linearly to the octahedron (`dA_face = sqrt(3) dA_uv`) and
//! the face's element at `p` (L1 norm 1) subtends `dA_face cos / |p|^2` with
//! `cos = 1 / (sqrt(3) |p|)`, so `dω = dA_uv / |p|^3`. A texel is chosen with probability
//! `P_i`, then a point uniformly in it, so the density over the square is
//! `pdf_uv = P_i / (2/N)^2` and over directions `pdf_ω = pdf_uv |p|^3`.
//!
//! `P_i` follows the texel's luminance (`0.2126 r + 0.7152 g + 0.0722 b`) times its solid
//! angle (`(2/N)^2` times the mean of `|p|^-3` over the texel's 8 x 8 sub-samples): 99 %
//! of the probability is spread that way, the rest (1 %, or more where `N` is large, so
//! that each such texel has at least `2^-22`) evenly over the texels whose radiance is not
//! zero, so that every texel with radiance may be sampled; a black texel has probability
//! 0. The stored `pdf_uv` is the difference of the stored (f32) cumulative distribution,
//! so it is the exact probability with which the search picks the texel. A map black
//! everywhere ([`Environment::is_black`]) is to be treated as no environment: its
//! cumulative distribution is 1 everywhere and every density 0, so [`Environment::sample`]
//! and [`Environment::lookup`] answer black with density 0 (and never NaN).
//!
//! # Resampling
//!
//! Each octahedral texel averages 4 x 4 sub-samples (the centres of a 4 x 4 grid of the
//! texel), weighted by their solid angle, each read bilinearly from the equirectangular
//! image (wrapping around horizontally, clamped at the top and bottom rows). The image is
//! +Y up, its column `u = 0.5 + atan2(d.x, -d.z) / 2π` (its centre column looks toward
//! -Z, `u = 0.75` toward +X) and its row `v = acos(d.y) / π` (row 0 straight up), pixel
//! `(c, r)` at `((c + 0.5) / width, (r + 0.5) / height)`. A channel that is not finite or
//! is negative reads as 0, and a texel's channel is at most [`crate::MAX_EMISSION`].
//!
//! # Words
//!
//! [`Environment::words`], read from offset `e` of the shader's `path_data`:
//!
//! | word | value |
//! |---|---|
//! | `e` | `N` |
//! | `e + 1` | `N / 2` (f32 bits) |
//! | `e + 2` | `2 / N` (f32 bits) |
//! | `e + 3 + 5 i ..` | texel `i = iy * N + ix`: red, green, blue, the inclusive cumulative distribution (the last exactly 1), `pdf_uv` (f32 bits each) |

use std::io::BufReader;
use std::path::Path;

use glam::Vec3;

use crate::PathError;

/// The octahedral map's default side, in texels.
pub const DEFAULT_SIZE: u32 = 512;
/// The largest side accepted (`2048^2 = 2^22` texels).
pub const MAX_SIZE: u32 = 2048;
/// Words before the texels in [`Environment::words`].
pub const HEADER_WORDS: usize = 3;
/// Words a texel in [`Environment::words`].
pub const TEXEL_WORDS: usize = 5;

/// Sub-samples a texel along each axis when resampling.
const SUB: u32 = 4;
/// Sub-samples a texel along each axis when working out its solid angle.
const OMEGA_SUB: u32 = 8;
/// The least share of the probability spread evenly over the texels with radiance.
const FLOOR: f64 = 0.01;
/// The least probability of a texel with radiance (4 f32 ulps below 1).
const FLOOR_TEXEL: f64 = 1.0 / 4_194_304.0;

/// An environment map as the path tracer samples it: see the module's documentation.
#[derive(Clone, Debug, PartialEq)]
pub struct Environment {
    size: u32,
    half: f32,
    step: f32,
    radiance: Vec<Vec3>,
    cdf: Vec<f32>,
    pdf: Vec<f32>,
}

/// An equirectangular image (row 0 straight up).
struct Equirect<'a> {
    width: usize,
    height: usize,
    texels: &'a [[f32; 3]],
}

impl Equirect<'_> {
    /// Pixel (`x`, `y`), each channel 0 where it is not finite or is negative.
    fn texel(&self, x: usize, y: usize) -> [f64; 3] {
        let t = self.texels[y * self.width + x];
        t.map(|c| {
            if c.is_finite() && c > 0.0 {
                c as f64
            } else {
                0.0
            }
        })
    }

    /// The image toward the unit `d`, bilinearly (wrapping around horizontally, clamped
    /// at the top and bottom rows).
    fn at(&self, d: [f64; 3]) -> [f64; 3] {
        let (w, h) = (self.width as f64, self.height as f64);
        let u = 0.5 + d[0].atan2(-d[2]) / std::f64::consts::TAU;
        let v = d[1].clamp(-1.0, 1.0).acos() / std::f64::consts::PI;
        let (x, y) = (u * w - 0.5, v * h - 0.5);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let col = |i: f64| (i as i64).rem_euclid(self.width as i64) as usize;
        let row = |i: f64| (i.max(0.0) as usize).min(self.height - 1);
        let (c0, c1, r0, r1) = (col(x0), col(x0 + 1.0), row(y0), row(y0 + 1.0));
        let (a, b) = (self.texel(c0, r0), self.texel(c1, r0));
        let (c, e) = (self.texel(c0, r1), self.texel(c1, r1));
        std::array::from_fn(|k| {
            let top = a[k] * (1.0 - fx) + b[k] * fx;
            let bottom = c[k] * (1.0 - fx) + e[k] * fx;
            top * (1.0 - fy) + bottom * fy
        })
    }
}

/// The octahedron's point (L1 norm 1) of the square's (`u`, `v`), in f64.
fn fold64(u: f64, v: f64) -> [f64; 3] {
    let (au, av) = (u.abs(), v.abs());
    let y = 1.0 - au - av;
    if y < 0.0 {
        let (x, z) = (1.0 - av, 1.0 - au);
        [
            if u >= 0.0 { x } else { -x },
            y,
            if v >= 0.0 { z } else { -z },
        ]
    } else {
        [u, y, v]
    }
}

/// The square's coordinate of sub-sample `k` of `sub` of texel column `i`.
fn sub_coord(i: u32, k: u32, sub: u32, size: u32) -> f64 {
    -1.0 + (i as f64 + (k as f64 + 0.5) / sub as f64) * (2.0 / size as f64)
}

/// Each texel's mean radiance (over [`SUB`] x [`SUB`] sub-samples, weighted by their solid
/// angle), from `f` of a unit direction.
fn resample(size: u32, f: impl Fn([f64; 3]) -> [f64; 3]) -> Vec<Vec3> {
    let mut radiance = Vec::with_capacity(size as usize * size as usize);
    for iy in 0..size {
        for ix in 0..size {
            let (mut sum, mut jac) = ([0.0f64; 3], 0.0);
            for k in 0..SUB * SUB {
                let u = sub_coord(ix, k % SUB, SUB, size);
                let p = fold64(u, sub_coord(iy, k / SUB, SUB, size));
                let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                let j = 1.0 / (l * l * l);
                let c = f(p.map(|x| x / l));
                for (s, c) in sum.iter_mut().zip(c) {
                    *s += if c.is_finite() && c > 0.0 { c * j } else { 0.0 };
                }
                jac += j;
            }
            // As bright as an emissive material at most: no path's sum overflows.
            let [r, g, b] = sum.map(|s| ((s / jac) as f32).min(crate::MAX_EMISSION));
            radiance.push(Vec3::new(r, g, b));
        }
    }
    radiance
}

/// Each texel's solid angle: its area times the mean of `|p|^-3` over [`OMEGA_SUB`] x
/// [`OMEGA_SUB`] sub-samples.
fn solid_angles(size: u32) -> Vec<f64> {
    let area = (2.0 / size as f64).powi(2) / (OMEGA_SUB * OMEGA_SUB) as f64;
    let mut omega = Vec::with_capacity(size as usize * size as usize);
    for iy in 0..size {
        for ix in 0..size {
            let mut jac = 0.0;
            for k in 0..OMEGA_SUB * OMEGA_SUB {
                let u = sub_coord(ix, k % OMEGA_SUB, OMEGA_SUB, size);
                let p = fold64(u, sub_coord(iy, k / OMEGA_SUB, OMEGA_SUB, size));
                let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                jac += 1.0 / (l * l * l);
            }
            omega.push(area * jac);
        }
    }
    omega
}

/// The inclusive cumulative distribution and the densities over the square of texels of
/// `weights` (see the module's documentation), or 1 and 0 everywhere where all are 0.
fn distribution(weights: &[f64], area: f64) -> (Vec<f32>, Vec<f32>) {
    let total: f64 = weights.iter().sum();
    let lit = weights.iter().filter(|&&w| w > 0.0).count();
    if lit == 0 || total <= 0.0 || !total.is_finite() {
        return (vec![1.0; weights.len()], vec![0.0; weights.len()]);
    }
    let floor = FLOOR.max(lit as f64 * FLOOR_TEXEL).min(1.0);
    let mut cdf = Vec::with_capacity(weights.len());
    let mut sum = 0.0f64;
    for &w in weights {
        if w > 0.0 {
            sum += (1.0 - floor) * (w / total) + floor / lit as f64;
        }
        cdf.push(sum);
    }
    let mut cdf: Vec<f32> = cdf.iter().map(|&c| (c / sum) as f32).collect();
    if let Some(last) = cdf.last_mut() {
        *last = 1.0;
    }
    let mut before = 0.0f32;
    let pdf = cdf
        .iter()
        .map(|&c| {
            let p = (c as f64 - before as f64) / area;
            before = c;
            p as f32
        })
        .collect();
    (cdf, pdf)
}

/// The octahedron's point of `d`: `d` over its L1 norm (`path_env_lookup`).
fn octahedron(d: Vec3) -> Vec3 {
    let s = d.x.abs() + d.y.abs() + d.z.abs();
    Vec3::new(d.x / s, d.y / s, d.z / s)
}

/// The square's point of the octahedron's `p` (`path_env_lookup`).
fn unfold(p: Vec3) -> (f32, f32) {
    if p.y < 0.0 {
        let fu = 1.0 - p.z.abs();
        let fv = 1.0 - p.x.abs();
        (
            if p.x >= 0.0 { fu } else { -fu },
            if p.z >= 0.0 { fv } else { -fv },
        )
    } else {
        (p.x, p.z)
    }
}

/// The octahedron's point of the square's (`u`, `v`) (`path_env_sample`).
fn fold(u: f32, v: f32) -> Vec3 {
    let au = u.abs();
    let av = v.abs();
    let y = 1.0 - au - av;
    if y < 0.0 {
        let fx = 1.0 - av;
        let fz = 1.0 - au;
        Vec3::new(
            if u >= 0.0 { fx } else { -fx },
            y,
            if v >= 0.0 { fz } else { -fz },
        )
    } else {
        Vec3::new(u, y, v)
    }
}

/// `path_env_cell`.
fn cell(c: f32, half: f32, n: u32) -> u32 {
    (((c + 1.0) * half).floor().max(0.0) as u32).min(n - 1)
}

fn check_size(size: u32) -> Result<(), PathError> {
    if (1..=MAX_SIZE).contains(&size) {
        Ok(())
    } else {
        Err(PathError::Setting(format!(
            "environment map size {size}: must be 1 to {MAX_SIZE} texels"
        )))
    }
}

impl Environment {
    /// Reads the Radiance `.hdr` image at `path` (equirectangular, see the module's
    /// documentation) and resamples it into an octahedral map of `size` x `size` texels.
    ///
    /// # Errors
    ///
    /// [`PathError::Setting`], naming the path and the cause, if the file cannot be read
    /// or is not a Radiance HDR image, or if `size` is not 1 to [`MAX_SIZE`].
    pub fn load(path: &Path, size: u32) -> Result<Environment, PathError> {
        check_size(size)?;
        let fail = |e: &dyn std::fmt::Display| {
            PathError::Setting(format!("environment map {}: {e}", path.display()))
        };
        let file = std::fs::File::open(path).map_err(|e| fail(&e))?;
        let decoder =
            image::codecs::hdr::HdrDecoder::new(BufReader::new(file)).map_err(|e| fail(&e))?;
        let image = image::DynamicImage::from_decoder(decoder)
            .map_err(|e| fail(&e))?
            .into_rgb32f();
        let (width, height) = image.dimensions();
        if width == 0 || height == 0 {
            return Err(fail(&"the image is empty"));
        }
        let texels: &[[f32; 3]] = bytemuck::cast_slice(image.as_raw());
        Ok(Self::from_equirect(width, height, texels, size))
    }

    /// Resamples the equirectangular image of `width` x `height` texels (row by row, row 0
    /// straight up) into an octahedral map of `size` x `size` texels.
    ///
    /// # Panics
    ///
    /// If `texels` does not hold `width * height` texels, if either is 0, or if `size` is
    /// not 1 to [`MAX_SIZE`].
    pub fn from_equirect(width: u32, height: u32, texels: &[[f32; 3]], size: u32) -> Environment {
        assert!(width > 0 && height > 0, "an empty equirectangular image");
        assert_eq!(texels.len(), width as usize * height as usize, "texels");
        let image = Equirect {
            width: width as usize,
            height: height as usize,
            texels,
        };
        Self::build(size, |d| image.at(d))
    }

    /// The octahedral map of `size` x `size` texels of the radiance `f` gives toward each
    /// unit direction (a procedural sky), each texel averaging 4 x 4 directions. A channel
    /// that is not finite or is negative counts as 0.
    ///
    /// # Panics
    ///
    /// If `size` is not 1 to [`MAX_SIZE`].
    pub fn from_fn(size: u32, f: impl Fn(Vec3) -> Vec3) -> Environment {
        Self::build(size, |d| {
            let c = f(Vec3::new(d[0] as f32, d[1] as f32, d[2] as f32));
            [c.x as f64, c.y as f64, c.z as f64]
        })
    }

    fn build(size: u32, f: impl Fn([f64; 3]) -> [f64; 3]) -> Environment {
        if let Err(e) = check_size(size) {
            panic!("{e}");
        }
        let radiance = resample(size, f);
        let omega = solid_angles(size);
        let weights: Vec<f64> = radiance
            .iter()
            .zip(&omega)
            .map(|(c, o)| {
                let (r, g, b) = (c.x as f64, c.y as f64, c.z as f64);
                (0.2126 * r + 0.7152 * g + 0.0722 * b) * o
            })
            .collect();
        let (cdf, pdf) = distribution(&weights, (2.0 / size as f64).powi(2));
        Environment {
            size,
            half: size as f32 / 2.0,
            step: 2.0 / size as f32,
            radiance,
            cdf,
            pdf,
        }
    }

    /// The map's side `N`, in texels.
    pub fn size(&self) -> u32 {
        self.size
    }

    /// Whether the map is black everywhere: then it is to be treated as no environment
    /// ([`Environment::sample`] and [`Environment::lookup`] answer black, density 0).
    pub fn is_black(&self) -> bool {
        self.pdf.iter().all(|&p| p == 0.0)
    }

    /// The radiance of texel (`ix`, `iy`) (column, row; see the module's documentation).
    ///
    /// # Panics
    ///
    /// If either is not below [`Environment::size`].
    pub fn radiance(&self, ix: u32, iy: u32) -> Vec3 {
        assert!(ix < self.size && iy < self.size, "texel ({ix}, {iy})");
        self.radiance[(iy * self.size + ix) as usize]
    }

    /// The words the shader reads from its offset `e` in `path_data` (see the module's
    /// documentation): `3 + 5 N^2` of them.
    pub fn words(&self) -> Vec<u32> {
        let mut words = Vec::with_capacity(HEADER_WORDS + TEXEL_WORDS * self.cdf.len());
        words.extend([self.size, self.half.to_bits(), self.step.to_bits()]);
        for ((c, &cdf), &pdf) in self.radiance.iter().zip(&self.cdf).zip(&self.pdf) {
            words.extend([c.x, c.y, c.z, cdf, pdf].map(f32::to_bits));
        }
        words
    }

    /// `path_env_texel`: texel `i`'s radiance and its density over directions at the point
    /// of squared length `l2` on the octahedron.
    fn texel(&self, i: u32, l2: f32) -> (Vec3, f32) {
        let i = i as usize;
        (self.radiance[i], self.pdf[i] * (l2 * l2.sqrt()))
    }

    /// The texel toward `d` (`path_env_lookup`), and the octahedron's point of `d`.
    fn texel_of(&self, d: Vec3) -> (u32, Vec3) {
        let n = self.size;
        let p = octahedron(d);
        let (u, v) = unfold(p);
        (cell(v, self.half, n) * n + cell(u, self.half, n), p)
    }

    /// `path_env_lookup`: the radiance toward `d` (finite, not zero, not necessarily unit)
    /// and the density over directions with which [`Environment::sample`] picks it, bit
    /// for bit as the shader computes them.
    pub fn lookup(&self, d: Vec3) -> (Vec3, f32) {
        let (i, p) = self.texel_of(d);
        self.texel(i, p.x * p.x + p.y * p.y + p.z * p.z)
    }

    /// The first texel whose inclusive cumulative distribution exceeds `u0`.
    fn pick(&self, u0: f32) -> u32 {
        let (mut lo, mut hi) = (0u32, self.size * self.size - 1);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if self.cdf[mid as usize] > u0 {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        lo
    }

    /// `path_env_sample`: a unit direction drawn with density proportional to the map's
    /// luminance (the texel by `u0`, the point in it by `u1` and `u2`, each in `[0, 1)`),
    /// its radiance and that density over directions, bit for bit as the shader computes
    /// them. A point on a texel's far edge (where `ix + u1` rounds up) is given the
    /// density of the texel drawn, which [`Environment::lookup`] may read from its
    /// neighbour.
    pub fn sample(&self, u0: f32, u1: f32, u2: f32) -> (Vec3, Vec3, f32) {
        let n = self.size;
        let lo = self.pick(u0);
        let u = -1.0 + ((lo % n) as f32 + u1) * self.step;
        let v = -1.0 + ((lo / n) as f32 + u2) * self.step;
        let p = fold(u, v);
        let l2 = p.x * p.x + p.y * p.y + p.z * p.z;
        let r = 1.0 / l2.sqrt();
        let (radiance, pdf) = self.texel(lo, l2);
        (Vec3::new(p.x * r, p.y * r, p.z * r), radiance, pdf)
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::{PI, TAU};

    use super::*;
    use crate::sampling::Rng;

    const SUN: Vec3 = Vec3::new(0.3, 0.8, -0.52);

    /// A sky with radiance everywhere and a small bright sun.
    fn sky(d: Vec3) -> Vec3 {
        let sun = if d.dot(SUN.normalize()) > 0.995 {
            40.0
        } else {
            0.0
        };
        Vec3::new(0.3, 0.5, 0.9) * (0.2 + d.y.max(0.0)) + Vec3::splat(sun)
    }

    fn uniform_sphere(r: &mut Rng) -> Vec3 {
        let z = 1.0 - 2.0 * r.uniform() as f64;
        let phi = TAU * r.uniform() as f64;
        let s = (1.0 - z * z).max(0.0).sqrt();
        Vec3::new((s * phi.cos()) as f32, (s * phi.sin()) as f32, z as f32)
    }

    fn dir64(u: f64, v: f64) -> [f64; 3] {
        let p = fold64(u, v);
        let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        p.map(|x| x / l)
    }

    fn to_vec(d: [f64; 3]) -> Vec3 {
        Vec3::new(d[0] as f32, d[1] as f32, d[2] as f32)
    }

    /// The direction of texel (`ix`, `iy`)'s centre.
    fn centre(size: u32, ix: u32, iy: u32) -> Vec3 {
        let c = |i: u32| -1.0 + (i as f64 + 0.5) * (2.0 / size as f64);
        to_vec(dir64(c(ix), c(iy)))
    }

    fn angle(a: Vec3, b: Vec3) -> f32 {
        a.normalize()
            .dot(b.normalize())
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    }

    #[test]
    fn octahedral_round_trip() {
        let mut worst = 0.0f32;
        for j in 0..400 {
            for k in 0..400 {
                // Off the square's outer edges, which are seams.
                let u = -0.9975 + j as f32 * 0.005;
                let v = -0.9975 + k as f32 * 0.005 + 1e-4;
                let p = fold(u, v);
                let r = 1.0 / (p.x * p.x + p.y * p.y + p.z * p.z).sqrt();
                let d = Vec3::new(p.x * r, p.y * r, p.z * r);
                let (u2, v2) = unfold(octahedron(d));
                worst = worst.max((u2 - u).abs()).max((v2 - v).abs());
            }
        }
        assert!(worst < 2e-6, "round trip off by {worst}");
    }

    #[test]
    fn every_direction_maps_to_a_texel_in_range() {
        let n = 256;
        let env = Environment::from_fn(n, |_| Vec3::ONE);
        let (h, m) = (n / 2, n - 1);
        let known = [
            (Vec3::Y, (h, h)),
            (Vec3::NEG_Y, (m, m)),
            (Vec3::new(-0.0, -1.0, -0.0), (m, m)),
            (Vec3::X, (m, h)),
            (Vec3::NEG_X, (0, h)),
            (Vec3::Z, (h, m)),
            (Vec3::NEG_Z, (h, 0)),
            (Vec3::new(-0.0, 1.0, -0.0), (h, h)),
        ];
        for (d, (ix, iy)) in known {
            assert_eq!(env.texel_of(d).0, iy * n + ix, "{d:?}");
        }
        let mut dirs = vec![
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(1.0, -0.0, -1.0),
            Vec3::new(-1.0, -1e-30, 1.0),
            Vec3::new(-1.0, 1e-30, -1.0),
            Vec3::new(1e-30, 1e-30, -1e-30),
            Vec3::new(1e-40, 0.0, -0.0),
            Vec3::new(1e30, -1e30, 2e30),
            Vec3::new(-0.0, -0.0, 1.0),
            Vec3::new(0.5, -0.5, 0.0),
        ];
        let mut r = Rng::new(1, 2, 3);
        dirs.extend((0..100_000).map(|_| uniform_sphere(&mut r)));
        for d in dirs {
            let (i, _) = env.texel_of(d);
            assert!(i < n * n, "{d:?}: texel {i}");
            let (c, pdf) = env.lookup(d);
            assert!((c - Vec3::ONE).abs().max_element() < 1e-6, "{d:?}: {c}");
            assert!(pdf.is_finite() && pdf > 0.0, "{d:?}: pdf {pdf}");
        }
    }

    #[test]
    fn texel_centres_map_back_to_their_texels() {
        for n in [1, 2, 3, 16, 33] {
            let env = Environment::from_fn(n, |_| Vec3::ONE);
            for iy in 0..n {
                for ix in 0..n {
                    let d = centre(n, ix, iy);
                    assert_eq!(env.texel_of(d).0, iy * n + ix, "N {n} ({ix}, {iy}) {d}");
                }
            }
        }
    }

    #[test]
    fn pdf_integrates_to_one_over_the_sphere() {
        let env = Environment::from_fn(128, sky);
        let area = (2.0f64 / 128.0).powi(2);
        let total: f64 = env.pdf.iter().map(|&p| p as f64 * area).sum();
        assert!((total - 1.0).abs() < 1e-6, "sum of pdf_uv * area {total}");
        let mut r = Rng::new(7, 0, 0);
        let count = 200_000;
        let mean = (0..count)
            .map(|_| env.lookup(uniform_sphere(&mut r)).1 as f64)
            .sum::<f64>()
            / count as f64;
        let integral = mean * 4.0 * PI;
        assert!(
            (integral - 1.0).abs() < 0.03,
            "integral of pdf_ω {integral}"
        );
        // Every texel is lit, so E[1 / pdf] over the samples is the sphere's 4π.
        let inverse = (0..count)
            .map(|_| 1.0 / env.sample(r.uniform(), r.uniform(), r.uniform()).2 as f64)
            .sum::<f64>()
            / count as f64;
        assert!(
            (inverse / (4.0 * PI) - 1.0).abs() < 0.03,
            "E[1/pdf] {inverse}"
        );
    }

    #[test]
    fn sampled_pdf_equals_lookup_pdf() {
        let env = Environment::from_fn(64, sky);
        let mut r = Rng::new(11, 0, 0);
        let mut edges = 0;
        let count = 100_000;
        for k in 0..count {
            let (u0, mut u1, u2) = (r.uniform(), r.uniform(), r.uniform());
            if k % 1000 == 0 {
                u1 = 1.0 - 1.0 / 16_777_216.0; // the far edge
            }
            let (d, c, pdf) = env.sample(u0, u1, u2);
            assert!((d.length() - 1.0).abs() < 1e-6, "{d}");
            assert!(pdf > 0.0 && pdf.is_finite(), "{pdf}");
            let (j, _) = env.texel_of(d);
            if j != env.pick(u0) {
                let near = [u1, 1.0 - u1, u2, 1.0 - u2].into_iter().fold(1.0, f32::min);
                assert!(near < 1e-3, "{d} left its texel ({u1}, {u2})");
                edges += 1;
                continue;
            }
            let (c2, pdf2) = env.lookup(d);
            assert_eq!(c, c2);
            assert!((pdf - pdf2).abs() <= 1e-5 * pdf, "{pdf} {pdf2}");
        }
        assert!(edges < count / 500, "{edges} samples on texel edges");
    }

    /// The solid angle of the spherical triangle (unit vertices).
    fn triangle(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
        let dot = |x: [f64; 3], y: [f64; 3]| x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
        let cross = [
            b[1] * c[2] - b[2] * c[1],
            b[2] * c[0] - b[0] * c[2],
            b[0] * c[1] - b[1] * c[0],
        ];
        let den = 1.0 + dot(a, b) + dot(b, c) + dot(c, a);
        2.0 * dot(a, cross).abs().atan2(den)
    }

    /// The solid angle of the square's rectangle from (`u`, `v`) of side `s`, cut in
    /// `k` x `k` cells.
    fn square(u: f64, v: f64, s: f64, k: u32) -> f64 {
        let h = s / k as f64;
        let mut sum = 0.0;
        for i in 0..k {
            for j in 0..k {
                let (a, b) = (u + i as f64 * h, v + j as f64 * h);
                let (p00, p10) = (dir64(a, b), dir64(a + h, b));
                let (p01, p11) = (dir64(a, b + h), dir64(a + h, b + h));
                sum += triangle(p00, p10, p11) + triangle(p00, p11, p01);
            }
        }
        sum
    }

    #[test]
    fn jacobian_is_the_inverse_cube_of_the_octahedron_point() {
        let delta = 1e-3;
        for (u, v) in [
            (0.3, 0.2),
            (-0.5, 0.1),
            (0.1, -0.6),
            (0.7, 0.6),
            (-0.8, -0.5),
        ] {
            let exact = square(u - delta / 2.0, v - delta / 2.0, delta, 1);
            let p = fold64(u, v);
            let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            let predicted = delta * delta / (l * l * l);
            assert!(
                (exact / predicted - 1.0).abs() < 1e-4,
                "({u}, {v}): {exact} against {predicted}"
            );
        }
        let n = 16;
        let omega = solid_angles(n);
        let total: f64 = omega.iter().sum();
        assert!(
            (total / (4.0 * PI) - 1.0).abs() < 1e-3,
            "texels cover {total}"
        );
        let side = 2.0 / n as f64;
        let mut worst = 0.0f64;
        for iy in 0..n {
            for ix in 0..n {
                let (u, v) = (-1.0 + ix as f64 * side, -1.0 + iy as f64 * side);
                let exact = square(u, v, side, 64);
                let o = omega[(iy * n + ix) as usize];
                worst = worst.max((o / exact - 1.0).abs());
            }
        }
        assert!(worst < 3e-3, "texel solid angles off by {worst}");
    }

    /// An equirectangular image of `width` x `height`, `background` everywhere but within
    /// `radius` degrees of `toward`, where it is `spot`.
    fn spot_image(width: u32, height: u32, toward: Vec3, radius: f32) -> Vec<[f32; 3]> {
        let mut texels = Vec::new();
        for r in 0..height {
            for c in 0..width {
                let phi = ((c as f64 + 0.5) / width as f64 - 0.5) * TAU;
                let theta = (r as f64 + 0.5) / height as f64 * PI;
                let d = [
                    theta.sin() * phi.sin(),
                    theta.cos(),
                    -theta.sin() * phi.cos(),
                ];
                let lit = angle(to_vec(d), toward) < radius;
                texels.push(if lit { [100.0, 80.0, 60.0] } else { [0.01; 3] });
            }
        }
        texels
    }

    /// The direction of the brightest texel's centre.
    fn brightest(env: &Environment) -> Vec3 {
        let n = env.size();
        let i = (0..n * n)
            .max_by(|&a, &b| {
                let l = |i: u32| crate::sampling::luminance(env.radiance(i % n, i / n));
                l(a).total_cmp(&l(b))
            })
            .unwrap_or(0);
        centre(n, i % n, i / n)
    }

    #[test]
    fn equirect_convention() {
        let (w, h) = (64u32, 32u32);
        // A block of pixels: the centre column and row, 3/4 of the way across, row 0.
        let block = |c0: u32, r0: u32| -> Vec<[f32; 3]> {
            let mut t = vec![[0.01f32; 3]; (w * h) as usize];
            for r in r0.saturating_sub(1)..(r0 + 2).min(h) {
                for c in c0 - 1..c0 + 2 {
                    t[(r * w + c) as usize] = [50.0; 3];
                }
            }
            t
        };
        let cases = [
            (w / 2, h / 2, Vec3::NEG_Z),
            (3 * w / 4, h / 2, Vec3::X),
            (w / 4, h / 2, Vec3::NEG_X),
            (w / 2, 0, Vec3::Y),
            (w / 2, h - 1, Vec3::NEG_Y),
        ];
        for (c, r, toward) in cases {
            let env = Environment::from_equirect(w, h, &block(c, r), 32);
            let b = brightest(&env);
            assert!(
                angle(b, toward) < 12.0,
                "column {c} row {r}: {b}, not {toward}"
            );
        }
    }

    #[test]
    fn bright_spot_is_found_and_sampled() {
        let toward = Vec3::new(0.4, 0.5, -0.75).normalize();
        let (w, h) = (256, 128);
        let env = Environment::from_equirect(w, h, &spot_image(w, h, toward, 5.0), 64);
        let b = brightest(&env);
        assert!(
            angle(b, toward) < 4.0,
            "brightest texel toward {b}, not {toward}"
        );
        let mut r = Rng::new(5, 0, 0);
        let count = 10_000;
        let near = (0..count)
            .filter(|_| {
                let (d, c, pdf) = env.sample(r.uniform(), r.uniform(), r.uniform());
                assert!(pdf > 0.0 && c.is_finite(), "{d} {c} {pdf}");
                angle(d, toward) < 8.0
            })
            .count();
        // The spot holds about 95 % of the power (1 % spread over every texel).
        assert!(
            near > count * 85 / 100,
            "{near} of {count} samples near the spot"
        );
    }

    /// A unique file name in the temporary directory.
    fn temp_path(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "bvhtrace-environment-{}-{name}",
            std::process::id()
        ));
        std::fs::create_dir_all(&dir).expect("a temporary directory");
        dir.join(name)
    }

    #[test]
    fn load_reads_a_radiance_file() {
        let path = temp_path("sky.hdr");
        let (w, h) = (32usize, 16usize);
        let pixels = vec![image::Rgb([1.5f32, 0.75, 0.25]); w * h];
        let file = std::fs::File::create(&path).expect("create");
        image::codecs::hdr::HdrEncoder::new(std::io::BufWriter::new(file))
            .encode(&pixels, w, h)
            .expect("encode");
        let env = Environment::load(&path, 16);
        let _ = std::fs::remove_dir_all(path.parent().expect("a directory"));
        let env = env.expect("loads");
        assert_eq!(env.size(), 16);
        assert!(!env.is_black());
        let expected = Vec3::new(1.5, 0.75, 0.25);
        for iy in 0..16 {
            for ix in 0..16 {
                let c = env.radiance(ix, iy);
                assert!(
                    (c - expected).abs().max_element() < 0.02,
                    "({ix}, {iy}): {c}"
                );
            }
        }
    }

    #[test]
    fn load_errors_name_the_path() {
        let missing = temp_path("missing.hdr").with_file_name("no-such-file.hdr");
        let png = temp_path("not-really.hdr");
        image::RgbImage::new(4, 4)
            .save_with_format(&png, image::ImageFormat::Png)
            .expect("a PNG");
        let results = [
            (missing.clone(), Environment::load(&missing, 16)),
            (png.clone(), Environment::load(&png, 16)),
        ];
        let size = Environment::load(&png, 0);
        let _ = std::fs::remove_dir_all(png.parent().expect("a directory"));
        for (path, result) in results {
            let Err(PathError::Setting(message)) = result else {
                panic!("{}: {result:?}", path.display());
            };
            let name = path.display().to_string();
            assert!(message.contains(&name), "{message:?} does not name {name}");
        }
        assert!(matches!(size, Err(PathError::Setting(m)) if m.contains("size 0")));
    }

    fn all_finite(env: &Environment) {
        assert!(env.words().iter().all(|&w| f32::from_bits(w).is_finite()));
        let mut r = Rng::new(9, 0, 0);
        for _ in 0..10_000 {
            let (c, pdf) = env.lookup(uniform_sphere(&mut r));
            assert!(c.is_finite() && pdf.is_finite(), "{c} {pdf}");
            let (d, c, pdf) = env.sample(r.uniform(), r.uniform(), r.uniform());
            assert!(
                d.is_finite() && c.is_finite() && pdf.is_finite(),
                "{d} {c} {pdf}"
            );
        }
    }

    #[test]
    fn bad_texels_read_as_black() {
        let (w, h) = (16u32, 8u32);
        let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1.0, -0.0];
        let texels: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                let b = bad[i as usize % bad.len()];
                if i % 2 == 0 { [b, 0.5, b] } else { [b; 3] }
            })
            .collect();
        let env = Environment::from_equirect(w, h, &texels, 16);
        assert!(!env.is_black());
        all_finite(&env);
        for iy in 0..16 {
            for ix in 0..16 {
                let c = env.radiance(ix, iy);
                assert!(c.x == 0.0 && c.z == 0.0 && c.y >= 0.0 && c.y <= 0.5, "{c}");
            }
        }
        let all_bad: Vec<[f32; 3]> = (0..w * h).map(|i| [bad[i as usize % 5]; 3]).collect();
        let black = Environment::from_equirect(w, h, &all_bad, 16);
        assert!(black.is_black());
        all_finite(&black);
        assert_eq!(black.sample(0.5, 0.5, 0.5).2, 0.0);
        assert_eq!(black.lookup(Vec3::Y), (Vec3::ZERO, 0.0));
    }

    #[test]
    fn distribution_is_inclusive_and_every_lit_texel_has_a_chance() {
        // Black below the horizon, dim above, and a sun a billion times brighter.
        let env = Environment::from_fn(32, |d| {
            let sun = if d.dot(SUN.normalize()) > 0.999 {
                1e9
            } else {
                0.0
            };
            Vec3::splat(if d.y > 0.0 { 1e-9 + sun } else { 0.0 })
        });
        assert_eq!(env.cdf.last(), Some(&1.0));
        assert!(env.cdf.windows(2).all(|c| c[0] <= c[1]), "not monotone");
        let mut before = 0.0;
        for (i, (&c, &pdf)) in env.cdf.iter().zip(&env.pdf).enumerate() {
            let lit = env.radiance[i] != Vec3::ZERO;
            assert_eq!(
                pdf > 0.0,
                lit,
                "texel {i}: pdf {pdf}, radiance {}",
                env.radiance[i]
            );
            assert_eq!(c > before, lit, "texel {i}: cdf {before} to {c}");
            before = c;
        }
        let dark = env.radiance.iter().filter(|&&c| c == Vec3::ZERO).count();
        assert!(dark > 300 && dark < 32 * 32 - 300, "{dark} black texels");
        // The first texel whose inclusive cumulative distribution exceeds u0.
        let first = |u0: f32| env.cdf.iter().position(|&c| c > u0);
        for &c in &env.cdf {
            let below = f32::from_bits(c.to_bits().saturating_sub(1));
            for u0 in [c, below].into_iter().filter(|&u| u < 1.0) {
                assert_eq!(Some(env.pick(u0) as usize), first(u0), "u0 {u0}");
            }
        }
        assert_eq!(Some(env.pick(0.0) as usize), first(0.0));
        let mut r = Rng::new(19, 0, 0);
        for _ in 0..10_000 {
            let (d, c, pdf) = env.sample(r.uniform(), r.uniform(), r.uniform());
            assert!(
                c != Vec3::ZERO && pdf > 0.0,
                "a black texel sampled toward {d}"
            );
        }
    }

    #[test]
    fn texels_are_sampled_as_often_as_their_probability() {
        let n = 4;
        let env = Environment::from_fn(n, sky);
        let area = (2.0f64 / n as f64).powi(2);
        let mut counts = vec![0u32; (n * n) as usize];
        let mut r = Rng::new(13, 0, 0);
        let count = 160_000;
        for _ in 0..count {
            let (d, _, _) = env.sample(r.uniform(), 0.25 + 0.5 * r.uniform(), 0.5);
            counts[env.texel_of(d).0 as usize] += 1;
        }
        for (i, &k) in counts.iter().enumerate() {
            let p = env.pdf[i] as f64 * area;
            let sigma = (count as f64 * p * (1.0 - p)).sqrt();
            let off = (k as f64 - count as f64 * p).abs();
            assert!(off < 5.0 * sigma + 1.0, "texel {i}: {k} of {count}, p {p}");
        }
    }

    /// `path_env_lookup` and `path_env_sample` over the words, as the shader reads them.
    fn from_words(w: &[u32], d: Option<Vec3>, u: [f32; 3]) -> (Vec3, Vec3, f32) {
        let f = |i: u32| f32::from_bits(w[i as usize]);
        let (n, half, step) = (w[0], f(1), f(2));
        let (i, dir, l2) = if let Some(d) = d {
            let p = octahedron(d);
            let (u, v) = unfold(p);
            let i = cell(v, half, n) * n + cell(u, half, n);
            (i, d, p.x * p.x + p.y * p.y + p.z * p.z)
        } else {
            let i = (0..n * n)
                .find(|&i| f(6 + 5 * i) > u[0])
                .unwrap_or(n * n - 1);
            let x = -1.0 + ((i % n) as f32 + u[1]) * step;
            let p = fold(x, -1.0 + ((i / n) as f32 + u[2]) * step);
            let l2 = p.x * p.x + p.y * p.y + p.z * p.z;
            let r = 1.0 / l2.sqrt();
            (i, Vec3::new(p.x * r, p.y * r, p.z * r), l2)
        };
        let t = 3 + 5 * i;
        let c = Vec3::new(f(t), f(t + 1), f(t + 2));
        (dir, c, f(t + 4) * (l2 * l2.sqrt()))
    }

    #[test]
    fn words_hold_what_the_twin_reads() {
        let env = Environment::from_fn(16, sky);
        let w = env.words();
        assert_eq!(w.len(), HEADER_WORDS + TEXEL_WORDS * 256);
        assert_eq!(w[..3], [16, 8.0f32.to_bits(), 0.125f32.to_bits()]);
        let mut r = Rng::new(17, 0, 0);
        for _ in 0..20_000 {
            let d = uniform_sphere(&mut r);
            let (_, c, pdf) = from_words(&w, Some(d), [0.0; 3]);
            let (c2, pdf2) = env.lookup(d);
            assert_eq!(
                (c.to_array().map(f32::to_bits), pdf.to_bits()),
                (c2.to_array().map(f32::to_bits), pdf2.to_bits())
            );
            let u = [r.uniform(), r.uniform(), r.uniform()];
            let (d, c, pdf) = from_words(&w, None, u);
            let (d2, c2, pdf2) = env.sample(u[0], u[1], u[2]);
            assert_eq!((d, c, pdf.to_bits()), (d2, c2, pdf2.to_bits()), "{u:?}");
        }
    }

    #[test]
    fn wgsl_validates_and_has_no_transcendental() {
        let file = include_str!("../../../shaders/path_environment.wgsl");
        let source =
            format!("@group(1) @binding(6) var<storage, read> path_data: array<u32>;\n{file}");
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("parse: {}", e.emit_to_string(&source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::all(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("validate: {}", e.emit_to_string(&source)));
        for (_, f) in module.functions.iter() {
            let name = f.name.as_deref().unwrap_or("");
            assert!(name.starts_with("path_env"), "{name}");
        }
        let code: String = file
            .lines()
            .map(|l| l.split("//").next().unwrap_or(""))
            .collect::<Vec<_>>()
            .join("\n");
        let banned = [
            "sin(",
            "cos(",
            "tan(",
            "atan",
            "acos",
            "asin",
            "pow(",
            "exp",
            "log",
            "mix(",
            "fma(",
            "dot(",
            "normalize(",
            "sign(",
            "length(",
            "inverseSqrt(",
        ];
        for b in banned {
            assert!(!code.contains(b), "the shader calls {b}");
        }
    }

    /// `path_env_lookup` and `path_env_sample` of each case (direction and `u0`, then
    /// `u1`, `u2`), run by the device from word 5 of `path_data`: 11 words a case.
    const DEVICE_KERNEL: &str = "
@group(0) @binding(0) var<storage, read> path_data: array<u32>;
@group(0) @binding(1) var<storage, read> env_in: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> env_out: array<u32>;

@compute @workgroup_size(64)
fn env_main(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x;
    if (i >= arrayLength(&env_in) / 2u) {
        return;
    }
    let a = env_in[2u * i];
    let b = env_in[2u * i + 1u];
    let l = path_env_lookup(5u, a.xyz);
    let s = path_env_sample(5u, a.w, b.x, b.y);
    let o = 11u * i;
    env_out[o] = bitcast<u32>(l.radiance.x);
    env_out[o + 1u] = bitcast<u32>(l.radiance.y);
    env_out[o + 2u] = bitcast<u32>(l.radiance.z);
    env_out[o + 3u] = bitcast<u32>(l.pdf);
    env_out[o + 4u] = bitcast<u32>(s.dir.x);
    env_out[o + 5u] = bitcast<u32>(s.dir.y);
    env_out[o + 6u] = bitcast<u32>(s.dir.z);
    env_out[o + 7u] = bitcast<u32>(s.radiance.x);
    env_out[o + 8u] = bitcast<u32>(s.radiance.y);
    env_out[o + 9u] = bitcast<u32>(s.radiance.z);
    env_out[o + 10u] = bitcast<u32>(s.pdf);
}
";

    /// The device's answers to `cases` over `env`'s words, or `None` without a device.
    fn on_device(env: &Environment, cases: &[[f32; 8]]) -> Option<Vec<u32>> {
        use bvhtrace_gpu::wgpu::{self, util::DeviceExt};
        let ctx = match bvhtrace_gpu::GpuContext::new(bvhtrace_gpu::AdapterChoice::Auto) {
            Ok(ctx) => ctx,
            Err(e @ bvhtrace_gpu::GpuError::NoAdapter { .. }) => {
                eprintln!("SKIP the environment map on a device: {e}");
                return None;
            }
            Err(e) => panic!("cannot open a GPU: {e}"),
        };
        let device = ctx.device();
        let file = include_str!("../../../shaders/path_environment.wgsl");
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("environment"),
            source: wgpu::ShaderSource::Wgsl(format!("{DEVICE_KERNEL}\n{file}").into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("environment"),
            layout: None,
            module: &module,
            entry_point: Some("env_main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let mut words = vec![0xdead_beef_u32; 5];
        words.extend(env.words());
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let init = |contents: &[u8]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: None,
                contents,
                usage: storage,
            })
        };
        let data = init(bytemuck::cast_slice(&words));
        let input = init(bytemuck::cast_slice(cases));
        let output = init(&vec![0u8; cases.len() * 44]);
        let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[&data, &input, &output]
                .iter()
                .enumerate()
                .map(|(i, b)| wgpu::BindGroupEntry {
                    binding: i as u32,
                    resource: b.as_entire_binding(),
                })
                .collect::<Vec<_>>(),
        });
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups((cases.len() as u32).div_ceil(64), 1, 1);
        }
        ctx.queue().submit([encoder.finish()]);
        let out = ctx
            .read_buffers("environment", &[&output])
            .expect("read back");
        Some(bytemuck::pod_collect_to_vec(&out[0]))
    }

    #[test]
    fn device_computes_the_twin_bits() {
        let env = Environment::from_fn(64, sky);
        let mut r = Rng::new(23, 0, 0);
        let special = [
            Vec3::Y,
            Vec3::NEG_Y,
            Vec3::new(-0.0, -1.0, -0.0),
            Vec3::X,
            Vec3::NEG_Z,
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(-1.0, -1e-30, 1.0),
            Vec3::new(1e30, -1e30, 2e30),
            Vec3::new(0.5, -0.5, 0.0),
        ];
        let edge = 1.0 - 1.0 / 16_777_216.0;
        let cases: Vec<[f32; 8]> = (0..20_000)
            .map(|k| {
                let d = special
                    .get(k)
                    .copied()
                    .unwrap_or_else(|| uniform_sphere(&mut r));
                let mut u = [r.uniform(), r.uniform(), r.uniform()];
                if k % 100 < 3 {
                    u[k % 100] = if k % 200 < 100 { 0.0 } else { edge };
                }
                [d.x, d.y, d.z, u[0], u[1], u[2], 0.0, 0.0]
            })
            .collect();
        let Some(device) = on_device(&env, &cases) else {
            return;
        };
        let mut wrong = 0;
        for (c, got) in cases.iter().zip(device.chunks(11)) {
            let (l, pdf) = env.lookup(Vec3::new(c[0], c[1], c[2]));
            let (d, s, spdf) = env.sample(c[3], c[4], c[5]);
            let twin: Vec<u32> = [l.x, l.y, l.z, pdf, d.x, d.y, d.z, s.x, s.y, s.z, spdf]
                .map(f32::to_bits)
                .to_vec();
            if twin != got {
                wrong += 1;
                if wrong < 5 {
                    eprintln!("{c:?}: twin {twin:x?}, device {got:x?}");
                }
            }
        }
        assert_eq!(wrong, 0, "{wrong} of {} cases differ", cases.len());
    }
}
