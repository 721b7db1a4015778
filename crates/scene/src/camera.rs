//! A pinhole camera and the primary rays every tool in the project shares.
//!
//! # The ray convention
//!
//! Other tools (the CPU traversal, the GPU kernels, the benchmarks) are compared on the
//! same rays, so [`Camera::ray`] follows one convention exactly, in `f32`, in this order:
//!
//! ```text
//! forward = normalize(target - eye)
//! right   = normalize(cross(forward, +Y))
//! up      = cross(right, forward)
//! t       = tan(to_radians(fov_y_deg) * 0.5)          // f32::to_radians, f32::tan
//! aspect  = W / H                                      // W, H as f32
//! px      = (2 * (x + 0.5) / W - 1) * t * aspect       // left to right: ((2*(x+0.5))/W - 1) * t, then * aspect
//! py      = (1 - 2 * (y + 0.5) / H) * t                // y = 0 is the top row
//! dir     = normalize(forward + px * right + py * up)  // (forward + right*px) + up*py
//! ray     = { origin: eye, dir, t_min: 0, t_max: +inf }
//! ```
//!
//! `normalize` is glam's `Vec3::normalize` (multiplication by the reciprocal length).
//!
//! Degenerate cameras never give NaN: when `forward` is parallel to +Y (looking straight
//! up or down, `|cross(forward, Y)|² <= 1e-12`) `right` is `+X` (so `up` is `-Z` looking
//! down and `+Z` looking up: continuous with a camera slightly on the +z side); when
//! `eye == target` (or the difference is not finite) `forward` is `-Z`.

use bvhtrace_core::ray::Ray;
use glam::Vec3;

/// A pinhole camera: where it sits, what it looks at, and its vertical field of view.
///
/// The camera has no roll: its "up" always comes from world +Y (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// The pinhole: every primary ray starts here.
    pub eye: Vec3,
    /// A point the camera looks at (only the direction `target - eye` matters for rays).
    pub target: Vec3,
    /// Vertical field of view in degrees.
    pub fov_y_deg: f32,
}

/// The field of view [`Camera::frame`] uses, in degrees.
pub const FRAME_FOV_Y_DEG: f32 = 45.0;

impl Camera {
    /// A camera that sees all of the box `[min, max]` in an image of this aspect ratio
    /// (width / height), looking at its centre from the +z side and slightly above
    /// (direction `(0, 0.3, 1)`), with a [`FRAME_FOV_Y_DEG`] vertical field of view.
    ///
    /// The bounding sphere of the box fits inside both the vertical and the horizontal
    /// field of view, with a 5% margin. An empty or non-finite box (for instance
    /// `(+inf, -inf)`) is framed as the unit box around the origin; a single point gets a
    /// tiny radius relative to its distance from the origin. Very small boxes far from the
    /// origin cannot be framed better than `f32` allows; the rays stay finite regardless.
    pub fn frame(min: Vec3, max: Vec3, aspect: f32) -> Camera {
        let (min, max) = if min.is_finite() && max.is_finite() && min.cmple(max).all() {
            (min, max)
        } else {
            (Vec3::splat(-1.0), Vec3::splat(1.0))
        };
        let center = (min + max) * 0.5;
        let mut radius = ((max - min) * 0.5).length();
        let floor = (center.abs().max_element() * 1e-6).max(1e-30);
        if radius.is_nan() || radius < floor {
            radius = floor;
        }
        let aspect = if aspect.is_finite() && aspect > 0.0 {
            aspect
        } else {
            1.0
        };
        let half_y = (FRAME_FOV_Y_DEG * 0.5).to_radians();
        let half_x = (half_y.tan() * aspect).atan();
        let half = half_y.min(half_x);
        let dist = radius / half.sin() * 1.05;
        let dir = Vec3::new(0.0, 0.3, 1.0).normalize();
        Camera {
            eye: center + dir * dist,
            target: center,
            fov_y_deg: FRAME_FOV_Y_DEG,
        }
    }

    /// The camera's orthonormal basis `(forward, right, up)` as the module docs define it.
    pub fn basis(&self) -> (Vec3, Vec3, Vec3) {
        let d = self.target - self.eye;
        let forward = if d.is_finite() && d != Vec3::ZERO {
            let f = d.normalize();
            if f.is_finite() { f } else { Vec3::NEG_Z }
        } else {
            Vec3::NEG_Z
        };
        let c = forward.cross(Vec3::Y);
        let right = if c.length_squared() > 1e-12 {
            c.normalize()
        } else {
            Vec3::X
        };
        let up = right.cross(forward);
        (forward, right, up)
    }

    /// The primary ray through the centre of pixel `(x, y)` of a `w` × `h` image
    /// (`y = 0` is the top row), following the module's convention exactly.
    pub fn ray(&self, x: u32, y: u32, w: u32, h: u32) -> Ray {
        let (forward, right, up) = self.basis();
        self.ray_in_basis(forward, right, up, x, y, w, h)
    }

    /// All primary rays of a `w` × `h` image, row-major (`rays[y * w + x]`), top row first.
    /// Each is exactly [`Camera::ray`]`(x, y, w, h)`.
    pub fn rays(&self, w: u32, h: u32) -> Vec<Ray> {
        let (forward, right, up) = self.basis();
        let mut out = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            for x in 0..w {
                out.push(self.ray_in_basis(forward, right, up, x, y, w, h));
            }
        }
        out
    }

    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn ray_in_basis(
        &self,
        forward: Vec3,
        right: Vec3,
        up: Vec3,
        x: u32,
        y: u32,
        w: u32,
        h: u32,
    ) -> Ray {
        let wf = w as f32;
        let hf = h as f32;
        let t = (self.fov_y_deg.to_radians() * 0.5).tan();
        let aspect = wf / hf;
        let px = (2.0 * (x as f32 + 0.5) / wf - 1.0) * t * aspect;
        let py = (1.0 - 2.0 * (y as f32 + 0.5) / hf) * t;
        let dir = (forward + right * px + up * py).normalize();
        Ray {
            origin: self.eye.to_array(),
            t_min: 0.0,
            dir: dir.to_array(),
            t_max: f32::INFINITY,
        }
    }

    /// The camera moved by an affine transform: `eye` and `target` are transformed as
    /// points, the field of view is kept.
    pub fn transformed(&self, m: glam::Mat4) -> Camera {
        Camera {
            eye: m.transform_point3(self.eye),
            target: m.transform_point3(self.target),
            fov_y_deg: self.fov_y_deg,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn looking_straight_down_or_up_is_finite() {
        for target in [Vec3::new(0.0, -5.0, 0.0), Vec3::new(0.0, 5.0, 0.0)] {
            let cam = Camera {
                eye: Vec3::ZERO,
                target,
                fov_y_deg: 60.0,
            };
            for r in cam.rays(5, 3) {
                assert!(Vec3::from(r.dir).is_finite() && Vec3::from(r.dir) != Vec3::ZERO);
            }
        }
        let cam = Camera {
            eye: Vec3::ONE,
            target: Vec3::ONE,
            fov_y_deg: 60.0,
        };
        let r = cam.ray(1, 1, 3, 3);
        assert_eq!(Vec3::from(r.dir), Vec3::NEG_Z);
    }

    #[test]
    fn frame_sees_the_box() {
        let cam = Camera::frame(Vec3::splat(-1.0), Vec3::splat(1.0), 16.0 / 9.0);
        assert!(cam.eye.z > 1.0 && cam.eye.y > 0.0);
        assert_eq!(cam.target, Vec3::ZERO);
        let empty = Camera::frame(Vec3::INFINITY, Vec3::NEG_INFINITY, 1.0);
        assert!(empty.eye.is_finite());
        let point = Camera::frame(Vec3::ONE, Vec3::ONE, 1.0);
        assert!(point.eye.is_finite() && point.eye != point.target);
    }
}
