//! Secondary rays from a hit: the hit point, the normal, the robust origin offset of
//! Wächter and Binder ("A Fast and Robust Method for Avoiding Self-Intersection", Ray
//! Tracing Gems, chapter 6, 2019), and repeatable cosine-weighted directions. Shared by
//! the renderer, the viewer and the stress cases, so all three leave a surface the same way.

use glam::Vec3;

use crate::mesh::Triangle;
use crate::ray::{Hit, Ray};

/// Below this magnitude a coordinate is offset by a fixed amount instead of in ulps
/// (`origin()` in the chapter).
pub const OFFSET_ORIGIN: f32 = 1.0 / 32.0;
/// Fixed offset per unit of normal, for coordinates near zero (`float_scale()`).
pub const OFFSET_FLOAT_SCALE: f32 = 1.0 / 65536.0;
/// Offset in ulps per unit of normal (`int_scale()`).
pub const OFFSET_INT_SCALE: f32 = 256.0;

/// Moves a surface point `p` off the surface along `n` (the geometric normal, unit length,
/// pointing to the side the new ray leaves on) far enough that a ray from the result does
/// not hit the surface it starts on, and no farther than needed: each coordinate moves
/// by `256 n[i]` ulps of itself, or by `n[i] / 65536` when it is within `1/32` of zero,
/// where ulps are too small to matter.
///
/// Exactly the chapter's code: the integer offset is truncated toward zero, and it is
/// added to the coordinate's bit pattern with the coordinate's sign (so it moves away
/// from or toward zero as `n` says, whatever the sign of the coordinate). The constants
/// assume scenes of roughly unit scale: for a scene far smaller than `1/32` around the
/// origin, the fixed `1/65536` offset can be larger than its features.
pub fn offset_ray_origin(p: Vec3, n: Vec3) -> Vec3 {
    let off = |c: f32, n: f32| {
        let oi = (OFFSET_INT_SCALE * n) as i32;
        let moved = f32::from_bits(
            (c.to_bits() as i32).wrapping_add(if c < 0.0 { -oi } else { oi }) as u32,
        );
        if c.abs() < OFFSET_ORIGIN {
            c + OFFSET_FLOAT_SCALE * n
        } else {
            moved
        }
    };
    Vec3::new(off(p.x, n.x), off(p.y, n.y), off(p.z, n.z))
}

/// The hit point from the hit's barycentrics, in f32: `(1 - u - v) v0 + u v1 + v v2`
/// (the chapter's recommendation: its error does not grow with the hit distance, unlike
/// `origin + t dir`).
pub fn hit_point(tri: &Triangle, hit: &Hit) -> Vec3 {
    tri[0] * (1.0 - hit.u - hit.v) + tri[1] * hit.u + tri[2] * hit.v
}

/// The triangle's unit geometric normal (`(v1 - v0) x (v2 - v0)`, computed in f64), or
/// zero for a zero-area triangle.
pub fn geometric_normal(tri: &Triangle) -> Vec3 {
    let [a, b, c] = tri.map(|p| p.as_dvec3());
    (b - a).cross(c - a).normalize_or_zero().as_vec3()
}

/// The geometric normal (in f32) flipped to face against `dir`; `-dir` for a zero-area
/// triangle.
pub fn facing_normal(tri: &Triangle, dir: Vec3) -> Vec3 {
    let n = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
    let n = if n.length_squared() > 0.0 {
        n.normalize()
    } else {
        -dir.normalize()
    };
    if n.dot(dir) > 0.0 { -n } else { n }
}

/// Where secondary rays leave a hit: the hit point moved off the surface (by
/// [`offset_ray_origin`]) to the side the incoming ray came from, and the unit normal facing
/// that side. Made by [`Hit::surface`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// The ray origin: off the surface, on the incoming ray's side.
    pub origin: Vec3,
    /// The geometric normal facing the incoming ray ([`facing_normal`]).
    pub normal: Vec3,
}

impl SurfacePoint {
    /// A ray from here in direction `dir` over `[0, t_max)`: a bounce or an
    /// ambient-occlusion ray. It cannot hit the triangle it leaves when `dir` points to the
    /// normal's side.
    pub fn spawn_ray(&self, dir: Vec3, t_max: f32) -> Ray {
        Ray::with_interval(self.origin, dir, 0.0, t_max)
    }

    /// A shadow ray from here to `target`: direction `target - origin`, interval `[0, 1)`,
    /// so any hit (`Query::Any`) means something lies between the surface and the target.
    pub fn ray_toward(&self, target: Vec3) -> Ray {
        Ray::with_interval(self.origin, target - self.origin, 0.0, 1.0)
    }
}

impl Hit {
    /// Where secondary rays leave this hit, found on `tri` (the triangle of index
    /// `self.prim` in the builder's input) by a ray going along `incoming`: the hit point
    /// from the barycentrics ([`hit_point`]) moved off the surface to the incoming ray's side.
    pub fn surface(&self, tri: &Triangle, incoming: Vec3) -> SurfacePoint {
        let normal = facing_normal(tri, incoming);
        SurfacePoint {
            origin: offset_ray_origin(hit_point(tri, self), normal),
            normal,
        }
    }
}

/// A small integer hash (PCG) for repeatable sampling.
pub fn hash(mut x: u32) -> u32 {
    x = x.wrapping_mul(747796405).wrapping_add(2891336453);
    let w = ((x >> ((x >> 28) + 4)) ^ x).wrapping_mul(277803737);
    (w >> 22) ^ w
}

/// The top 24 bits of `x` as a number in `[0, 1)`.
pub fn unit_float(x: u32) -> f32 {
    (x >> 8) as f32 / (1u32 << 24) as f32
}

/// Two uniform numbers in `[0, 1)` for sample `s` of pixel `p`, repeatable.
pub fn uniform2(p: u32, s: u32) -> (f32, f32) {
    let h1 = hash(p.wrapping_mul(9781).wrapping_add(s.wrapping_mul(6271)) ^ 0x9e37_79b9);
    (unit_float(h1), unit_float(hash(h1)))
}

/// Cosine-weighted unit direction around the unit normal `n` for sample `s` of pixel `p`.
pub fn cosine_dir(n: Vec3, p: u32, s: u32) -> Vec3 {
    let (u1, u2) = uniform2(p, s);
    let r = u1.sqrt();
    let phi = std::f32::consts::TAU * u2;
    let (t, b) = n.any_orthonormal_pair();
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u1).max(0.0).sqrt()).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offset_moves_along_the_normal_by_ulps_or_a_fixed_amount() {
        // Large coordinates: 256 ulps along n, sign-aware.
        let p = Vec3::new(1000.0, -1000.0, 0.0);
        let q = offset_ray_origin(p, Vec3::new(1.0, 1.0, 0.0).normalize());
        let ulp = 1000f32.to_bits();
        // 256 * 0.7071 = 181.02 -> 181 ulps.
        assert_eq!(q.x.to_bits(), ulp + 181);
        assert!(q.x > p.x);
        assert!(
            q.y > p.y,
            "moves toward zero for a negative coordinate with n > 0"
        );
        assert_eq!((-q.y).to_bits(), ulp - 181);
        // Near zero: a fixed offset.
        assert_eq!(q.z, 0.0);
        let q = offset_ray_origin(Vec3::new(0.01, 0.0, -0.02), Vec3::Z);
        assert_eq!(q, Vec3::new(0.01, 0.0, -0.02 + OFFSET_FLOAT_SCALE));
        let q = offset_ray_origin(Vec3::new(0.01, 0.0, -0.02), -Vec3::Z);
        assert_eq!(q.z, -0.02 - OFFSET_FLOAT_SCALE);
    }

    #[test]
    fn normals_face_the_ray_and_samples_stay_in_the_hemisphere() {
        let tri: Triangle = [Vec3::ZERO, Vec3::X, Vec3::Y];
        assert_eq!(facing_normal(&tri, -Vec3::Z), Vec3::Z);
        assert_eq!(facing_normal(&tri, Vec3::Z), -Vec3::Z);
        assert_eq!(geometric_normal(&tri), Vec3::Z);
        assert_eq!(
            geometric_normal(&[Vec3::ZERO, Vec3::X, Vec3::X]),
            Vec3::ZERO
        );
        let h = Hit {
            t: 1.0,
            prim: 0,
            u: 0.25,
            v: 0.5,
        };
        assert_eq!(hit_point(&tri, &h), Vec3::new(0.25, 0.5, 0.0));
        for s in 0..256 {
            let d = cosine_dir(Vec3::Z, 7, s);
            assert!(d.z >= 0.0 && (d.length() - 1.0).abs() < 1e-5, "{d}");
        }
        assert_ne!(cosine_dir(Vec3::Z, 7, 0), cosine_dir(Vec3::Z, 7, 1));
    }
}
