//! Ray/box and ray/triangle tests shared by every traversal.
//!
//! Both are written so that the WGSL in `shaders/box.wgsl` and `shaders/triangle.wgsl`
//! performs the same f32 operations in the same order: the GPU kernels are checked
//! against these, ray by ray. Nothing here depends on the scene's absolute scale.

use glam::Vec3;

use crate::ray::Ray;

/// `1 + 16 u` (bits `0x3f800008`), `u = 2^-24`, above `1 + 2 gamma(7)` with
/// `gamma(n) = n u / (1 - n u)` (PBRT-v4, Ize 2013): scaling a box's exit distance by this
/// makes the slab test conservative under f32 rounding, whatever the scene's scale. Each
/// slab distance is a subtraction, a reciprocal and a product; the reciprocal is counted
/// at Vulkan's bound for a division (2.5 ulp, `5 u`), not as correctly rounded, because
/// GPUs (NVIDIA's among them) divide approximately: `7 u` at each end.
pub const BOX_TFAR_SCALE: f32 = 1.000_001;

/// The scale for a negative exit distance (hits behind the origin, with a negative
/// `t_min`): `1 - 17 u` (bits `0x3f7fffef`), below `1 / BOX_TFAR_SCALE`, so that the exit
/// moves away from zero, towards `+inf`, as [`BOX_TFAR_SCALE`] moves a positive one.
/// Multiplying a negative exit by [`BOX_TFAR_SCALE`] would move it the wrong way and cull
/// a box that is flat along the ray (a quad facing the ray) when it lies behind the
/// origin. A constant multiply, not a division, so the GPU rounds it the same way.
pub const BOX_TFAR_SCALE_NEG: f32 = 0.999_999;

/// `C u` with `C = 64`, `u = 2^-24` (exactly `2^-18`): when a box is culled against the
/// running best hit, the best `t` is widened by `BOX_CULL_SLACK * m`, where `m` is the
/// larger magnitude of the box's two slab distances along the ray's dominant axis `kz`.
/// The user's `t_max` is never widened.
///
/// # Why
///
/// The closest hit must not depend on the order in which boxes are visited: a box holding
/// a triangle whose f32 `t` would win must never be culled against a worse hit found
/// first. But [`intersect_triangle`]'s `t` can land before its own box's entry distance
/// by an error proportional to `m`, not to `t` (a large triangle hit close to the ray's
/// origin: tens of ulps of `t`), far beyond what [`BOX_TFAR_SCALE`] absorbs.
///
/// # Error analysis (`γ_n = n u / (1 - n u)`, first order in `u`)
///
/// Each rounding counts `u`, except a division or reciprocal, counted `5 u` (Vulkan's
/// 2.5 ulp: GPUs divide approximately); a fused multiply-add only drops roundings.
/// Let the f32 edge functions `u_i` (all of one sign, `det != 0`) define the exact weights
/// `β_i = u_i / (u_0 + u_1 + u_2)`: `β_i >= 0`, `Σ β_i = 1`. Let `Z_i = A_i[kz] / d[kz]`
/// (exact) be the corners' distances along the dominant axis. Then:
///
/// * `az = sz * a[kz]`: `a[kz]` (`u`), `sz = 1/d[kz]` (`5 u`), the product (`u`):
///   `az = Z_0 (1 + θ_7)`, and likewise `bz`, `cz`;
/// * `T = u az + v bz + w cz`: three products and two sums, `T = Σ u_i Z_i (1 + θ_10)`;
/// * `det = u + v + w` has no cancellation (one sign): `(Σ u_i)(1 + θ_2)`, so
///   `1/det = (1 + θ_7) / Σ u_i`, and `t = T * (1/det)` adds one rounding:
///   `t = Σ β_i Z_i (1 + θ_18)`, i.e. `|t - Σ β_i Z_i| <= γ_18 max |Z_i|`.
///
/// `Σ β_i Z_i` is a convex combination of the corners' `kz` distances, which lie in the
/// box's `kz` slab `[t0[kz], t1[kz]]`: so `max |Z_i| <= m` and, in exact arithmetic, the
/// `t` reported by a triangle inside the box is at most `γ_18 m` before the box's `kz`
/// slab. The box's own f32 entry distance is within `γ_7 |t_near| <= γ_7 m` of the exact
/// one (a hit box's entry lies in its `kz` slab, so `|t_near| <= m`). So a box holding
/// such a triangle is entered at most `(18 + 7) u m` after the triangle's `t`. Then the
/// slack itself: `m` and the product round (relative `θ_4`: second order), and the sum
/// `t_best + slack` rounds once (relative `u`). When the sum is non-negative,
/// [`BOX_TFAR_SCALE`] absorbs that; when it is negative (hits behind the origin with a
/// negative `t_min`; then `|t_best| <= m`), [`BOX_TFAR_SCALE_NEG`] moves it towards
/// `+inf` by `17 u |t|`, which absorbs it as well; count `17 u m` anyway. Worst case
/// `(25 + 17) u m = 42 u m`: `C = 64`, the next power of two (an exact f32), whose
/// remaining `22 u m` also absorbs moderate errors of the
/// weights (below). The box's other slabs agree with `Σ β_i Z_i` only up to the error of
/// the weights `β_i` themselves (the edge functions' rounding, amplified by `1/det`):
/// that part has no bound in terms of `m` (edge-on slivers), and it is exactly what
/// [`crate::oracle::f32_t_error_bound`] and [`crate::oracle::f32_indeterminate`] account
/// for. So two traversals can return different closest hits only when the f32 test is
/// indeterminate for one of them, or their `t` are within those bounds of each other.
///
/// Culling a box a little later costs nothing measurable (`64 u m` is below `4e-6 m`).
pub const BOX_CULL_SLACK: f32 = 3.814_697_3e-6; // 2^-18

/// A ray with everything the tests need precomputed once per ray.
#[derive(Clone, Copy, Debug)]
pub struct PreparedRay {
    /// Origin.
    pub org: Vec3,
    /// Direction, with subnormal components flushed to (signed) zero as GPUs do.
    pub dir: Vec3,
    /// `1/dir`, with zero components replaced by `±f32::MIN_POSITIVE` (sign kept) so the
    /// product is finite; such axes are handled apart (see `parallel`).
    pub inv_dir: Vec3,
    /// True when some direction component is zero: the ray is parallel to those slabs,
    /// and [`intersect_box`] takes its general path.
    pub parallel: bool,
    /// The interval start: hits closer than this are ignored.
    pub t_min: f32,
    /// The ray's own `t_max` (the user's interval end): what [`intersect_box`] culls
    /// against before any hit, and the cap of the widened best after one.
    pub t_max: f32,
    /// Watertight test (Woop et al. 2013): the axis after the dominant one `kz`
    /// (swapped with `ky` when `dir[kz] < 0`, keeping the winding).
    pub kx: usize,
    /// The remaining axis (see `kx`).
    pub ky: usize,
    /// The dominant axis: the direction's largest component in magnitude.
    pub kz: usize,
    /// Shear constant `dir[kx] / dir[kz]`.
    pub sx: f32,
    /// Shear constant `dir[ky] / dir[kz]`.
    pub sy: f32,
    /// Scale `1 / dir[kz]`.
    pub sz: f32,
}

/// True when the direction `d` has a zero (or subnormal) component: what
/// [`PreparedRay::parallel`] is for a ray along `d`, without the rest of the preparation.
/// The GPU crate asks it of every ray of a batch, and compiles the box test's parallel
/// path out when no ray needs it.
#[inline]
pub fn is_parallel_to_a_slab(d: Vec3) -> bool {
    flush_subnormal(d.x) == 0.0 || flush_subnormal(d.y) == 0.0 || flush_subnormal(d.z) == 0.0
}

/// `d`, or a zero of the same sign when `d` is subnormal.
#[inline]
pub fn flush_subnormal(d: f32) -> f32 {
    if d.abs() < f32::MIN_POSITIVE {
        0.0f32.copysign(d)
    } else {
        d
    }
}

/// `1/d`, where a zero or subnormal `d` is taken as `±f32::MIN_POSITIVE` (sign kept), so the
/// result is always finite and non-zero.
#[inline]
pub fn safe_inverse(d: f32) -> f32 {
    let d = if d.abs() < f32::MIN_POSITIVE {
        f32::MIN_POSITIVE.copysign(d)
    } else {
        d
    };
    1.0 / d
}

impl PreparedRay {
    /// Precomputes a valid ray (see [`Ray::is_valid`]). Inlined, so that the walks build
    /// it in registers instead of copying it through memory.
    #[inline(always)]
    pub fn new(ray: &Ray) -> Self {
        let org = Vec3::from(ray.origin);
        let d = Vec3::from(ray.dir);
        let dir = Vec3::new(
            flush_subnormal(d.x),
            flush_subnormal(d.y),
            flush_subnormal(d.z),
        );
        let inv_dir = Vec3::new(
            safe_inverse(dir.x),
            safe_inverse(dir.y),
            safe_inverse(dir.z),
        );
        let (kx, ky, kz) = shear_axes(dir.abs().to_array(), |k| dir[k] < 0.0);
        PreparedRay {
            org,
            dir,
            inv_dir,
            parallel: is_parallel_to_a_slab(dir),
            t_min: ray.t_min,
            t_max: ray.t_max,
            kx,
            ky,
            kz,
            sx: dir[kx] / dir[kz],
            sy: dir[ky] / dir[kz],
            sz: 1.0 / dir[kz],
        }
    }
}

/// The watertight test's axes `(kx, ky, kz)` for a direction with these magnitudes: `kz`
/// the dominant axis (ties to the lower axis, as the WGSL does), `kx` and `ky` swapped when
/// `negative(kz)` to keep the winding. Shared by the f32 test and the f64 oracle.
#[inline(always)]
pub(crate) fn shear_axes<T: PartialOrd>(
    a: [T; 3],
    negative: impl FnOnce(usize) -> bool,
) -> (usize, usize, usize) {
    let kz = if a[0] >= a[1] && a[0] >= a[2] {
        0
    } else if a[1] >= a[2] {
        1
    } else {
        2
    };
    let (kx, ky) = ((kz + 1) % 3, (kz + 2) % 3);
    if negative(kz) {
        (ky, kx, kz)
    } else {
        (kx, ky, kz)
    }
}

/// The arithmetic the watertight tests share (f32, f64 and the f64 oracle).
pub(crate) trait Real:
    Copy
    + PartialOrd
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Neg<Output = Self>
{
    /// Zero.
    const ZERO: Self;
    /// `a * b - c * d` as the device computes it: two products and a difference here; a
    /// device may fuse one product into the difference (the tests model that).
    #[inline(always)]
    fn product_difference(a: Self, b: Self, c: Self, d: Self) -> Self {
        a * b - c * d
    }
}
impl Real for f32 {
    const ZERO: f32 = 0.0;
}
impl Real for f64 {
    const ZERO: f64 = 0.0;
}

/// The edge function `p.x q.y - p.y q.x` of two sheared corners, with the corners taken
/// in one fixed order (the lexicographically smaller first) and the sign restored.
///
/// Two triangles sharing an edge then evaluate it with the same operations on the same
/// operands, so their functions are exact negatives even where the device fuses a product
/// into the subtraction (an FMA, which SPIR-V allows and NVIDIA's compiler does): the
/// test stays watertight. Without fusion the value is the plain formula's, bit for bit
/// (up to the sign of a zero).
#[inline(always)]
pub(crate) fn edge<T: Real>(px: T, py: T, qx: T, qy: T) -> T {
    if px > qx || (px == qx && py > qy) {
        -T::product_difference(qx, py, qy, px)
    } else {
        T::product_difference(px, qy, py, qx)
    }
}

/// A ray's shear for the watertight test: its axes and `(sx, sy, sz)`.
pub(crate) struct Shear<T> {
    /// `(kx, ky, kz)` from [`shear_axes`].
    pub k: (usize, usize, usize),
    /// `d[kx] / d[kz]`, `d[ky] / d[kz]`, `1 / d[kz]`.
    pub s: [T; 3],
}

impl<T: Real> Shear<T> {
    /// The edge functions `v` and `w` (the barycentric numerators of corners 1 and 2), the
    /// sum `det = u + v + w` and the scaled distance `T`, for the corners relative to the
    /// ray's origin; `None` outside (mixed signs) or for `det == 0`. A zero edge function
    /// counts as inside.
    #[inline(always)]
    pub fn edges(&self, [a, b, c]: [[T; 3]; 3]) -> Option<(T, T, T, T)> {
        let (kx, ky, kz) = self.k;
        let [sx, sy, sz] = self.s;
        let ax = a[kx] - sx * a[kz];
        let ay = a[ky] - sy * a[kz];
        let bx = b[kx] - sx * b[kz];
        let by = b[ky] - sy * b[kz];
        let cx = c[kx] - sx * c[kz];
        let cy = c[ky] - sy * c[kz];
        let u = edge(cx, cy, bx, by);
        let v = edge(ax, ay, cx, cy);
        let w = edge(bx, by, ax, ay);
        let zero = T::ZERO;
        if (u < zero || v < zero || w < zero) && (u > zero || v > zero || w > zero) {
            return None;
        }
        let det = u + v + w;
        if det == zero {
            return None;
        }
        let t_scaled = u * (sz * a[kz]) + v * (sz * b[kz]) + w * (sz * c[kz]);
        Some((v, w, det, t_scaled))
    }
}

#[inline(always)]
fn fmin(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}
#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// Conservative slab test against the ray's interval `[t_min, t_best]` widened for culling.
/// Returns the entry distance when the interval overlaps the box (boundaries included),
/// else `None`.
///
/// `t_best` is the `t` of the best hit so far, or the ray's `t_max` while there is none.
/// The far end is `min(t_best + BOX_CULL_SLACK * m, r.t_max)` (see [`BOX_CULL_SLACK`]):
/// so before any hit it is exactly the ray's `t_max`, and after one, a box that may hold a
/// triangle reporting a `t <= t_best` is kept whatever the order of the visit.
#[inline(always)]
pub fn intersect_box(r: &PreparedRay, bmin: Vec3, bmax: Vec3, t_best: f32) -> Option<f32> {
    let mut t0 = (bmin - r.org) * r.inv_dir;
    let mut t1 = (bmax - r.org) * r.inv_dir;
    if r.parallel {
        // Along an axis the ray does not move, it is inside the slab for every t (its
        // boundary included) or for none: no distance from a product with a fake inverse,
        // which would put a ray lying on a face just outside it.
        for a in 0..3 {
            if r.dir[a] == 0.0 {
                let inside = bmin[a] <= r.org[a] && r.org[a] <= bmax[a];
                t0[a] = if inside {
                    f32::NEG_INFINITY
                } else {
                    f32::INFINITY
                };
                t1[a] = f32::INFINITY;
            }
        }
    }
    let tnear = fmax(
        fmax(fmin(t0.x, t1.x), fmin(t0.y, t1.y)),
        fmax(fmin(t0.z, t1.z), r.t_min),
    );
    // The slack: `m` bounds `|Z_i|` of every corner inside the box. `fmin` returns its
    // second operand when the first is NaN (`-inf + inf`), so a NaN never culls.
    let m = fmax(t0[r.kz].abs(), t1[r.kz].abs());
    let limit = fmin(t_best + BOX_CULL_SLACK * m, r.t_max);
    let tfar = fmin(
        fmin(fmax(t0.x, t1.x), fmax(t0.y, t1.y)),
        fmin(fmax(t0.z, t1.z), limit),
    );
    // Away from zero towards +inf, whatever the sign (see `BOX_TFAR_SCALE_NEG`).
    let tfar = tfar
        * if tfar < 0.0 {
            BOX_TFAR_SCALE_NEG
        } else {
            BOX_TFAR_SCALE
        };
    if tnear <= tfar { Some(tnear) } else { None }
}

/// A triangle hit: distance and the barycentric weights of corners 1 and 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriHit {
    /// Distance along the ray.
    pub t: f32,
    /// Barycentric weight of corner 1.
    pub u: f32,
    /// Barycentric weight of corner 2.
    pub v: f32,
}

/// Watertight ray/triangle test (Woop, Benthin, Wald 2013, without the f64 fallback for
/// exactly-zero edge functions: a zero counts as inside, so a ray through a shared edge or
/// vertex hits at least one of the triangles that share it). Returns the hit whatever its
/// distance along the ray; the caller applies the interval.
#[inline(always)]
pub fn intersect_triangle(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
    let corners = [v0 - r.org, v1 - r.org, v2 - r.org].map(|c| c.to_array());
    let shear = Shear {
        k: (r.kx, r.ky, r.kz),
        s: [r.sx, r.sy, r.sz],
    };
    let (v, w, det, t_scaled) = shear.edges(corners)?;
    let inv_det = 1.0 / det;
    let t = t_scaled * inv_det;
    // NaN (from overflowing products) fails this comparison and is rejected.
    if !(t >= r.t_min) {
        return None;
    }
    Some(TriHit {
        t,
        u: v * inv_det,
        v: w * inv_det,
    })
}

#[cfg(test)]
mod tests {
    use super::{BOX_CULL_SLACK, BOX_TFAR_SCALE, BOX_TFAR_SCALE_NEG, Real, edge};

    /// The box test's constants are the f32 values their docs derive.
    #[test]
    fn box_constants_are_the_documented_f32s() {
        let u = f32::EPSILON / 2.0;
        assert_eq!(BOX_TFAR_SCALE, 1.0 + 16.0 * u);
        assert_eq!(BOX_TFAR_SCALE_NEG, 1.0 - 17.0 * u);
        assert_eq!(BOX_CULL_SLACK, 64.0 * u);
        const { assert!(BOX_TFAR_SCALE_NEG < 1.0 / BOX_TFAR_SCALE) };
    }

    /// f32 as a device that fuses the first product into the difference computes it.
    #[derive(Clone, Copy, Debug, PartialEq, PartialOrd)]
    struct Fused(f32);

    impl std::ops::Add for Fused {
        type Output = Fused;
        fn add(self, o: Fused) -> Fused {
            Fused(self.0 + o.0)
        }
    }
    impl std::ops::Sub for Fused {
        type Output = Fused;
        fn sub(self, o: Fused) -> Fused {
            Fused(self.0 - o.0)
        }
    }
    impl std::ops::Mul for Fused {
        type Output = Fused;
        fn mul(self, o: Fused) -> Fused {
            Fused(self.0 * o.0)
        }
    }
    impl std::ops::Neg for Fused {
        type Output = Fused;
        fn neg(self) -> Fused {
            Fused(-self.0)
        }
    }
    impl Real for Fused {
        const ZERO: Fused = Fused(0.0);
        fn product_difference(a: Fused, b: Fused, c: Fused, d: Fused) -> Fused {
            Fused(a.0.mul_add(b.0, -(c.0 * d.0)))
        }
    }

    /// A shared edge seen from its two triangles (its corners in opposite orders) gives
    /// exact negatives even when the device fuses a product, which the plain formula
    /// does not: the fused `p.x q.y - p.y q.x` and `q.x p.y - q.y p.x` round differently.
    #[test]
    fn shared_edges_are_exact_negatives_under_fusion() {
        let mut state = 0x2545_f491_u32;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            Fused(state as f32 / u32::MAX as f32 * 2.0 - 1.0)
        };
        let mut plain_asymmetric = 0;
        for _ in 0..10_000 {
            let (px, py, qx, qy) = (next(), next(), next(), next());
            let forward = edge(px, py, qx, qy);
            let backward = edge(qx, qy, px, py);
            assert_eq!(
                forward.0, -backward.0,
                "edge ({px:?}, {py:?}) ({qx:?}, {qy:?})"
            );
            let plain =
                |a: Fused, b: Fused, c: Fused, d: Fused| Fused::product_difference(a, b, c, d);
            if plain(px, qy, py, qx).0 != -plain(qx, py, qy, px).0 {
                plain_asymmetric += 1;
            }
        }
        // The model is real: the plain formula breaks under fusion on most inputs.
        assert!(plain_asymmetric > 1000, "{plain_asymmetric}");
    }
}
