//! Secondary-ray origins: the hit point from barycentrics and the robust origin offset of
//! Wächter and Binder, "A Fast and Robust Method for Avoiding Self-Intersection" (Ray
//! Tracing Gems, chapter 6, 2019).

use bvhtrace_core::{Hit, Triangle};
use glam::Vec3;

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
    let of_i = [
        (OFFSET_INT_SCALE * n.x) as i32,
        (OFFSET_INT_SCALE * n.y) as i32,
        (OFFSET_INT_SCALE * n.z) as i32,
    ];
    let mut out = [0.0f32; 3];
    for a in 0..3 {
        let c = p[a];
        let bits = c.to_bits() as i32;
        let moved =
            f32::from_bits(bits.wrapping_add(if c < 0.0 { -of_i[a] } else { of_i[a] }) as u32);
        out[a] = if c.abs() < OFFSET_ORIGIN {
            c + OFFSET_FLOAT_SCALE * n[a]
        } else {
            moved
        };
    }
    Vec3::from(out)
}

/// The hit point from the hit's barycentrics, in f32: `(1 - u - v) v0 + u v1 + v v2`
/// (the chapter's recommendation: its error does not grow with the hit distance, unlike
/// `origin + t dir`).
pub fn hit_point(tri: &Triangle, hit: &Hit) -> Vec3 {
    let w = 1.0 - hit.u - hit.v;
    tri[0] * w + tri[1] * hit.u + tri[2] * hit.v
}

/// The triangle's unit geometric normal (`(v1 - v0) x (v2 - v0)`, computed in f64), or
/// zero for a zero-area triangle.
pub fn geometric_normal(tri: &Triangle) -> Vec3 {
    let [a, b, c] = tri.map(|p| p.as_dvec3());
    (b - a).cross(c - a).normalize_or_zero().as_vec3()
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
}
