//! Ray/box and ray/triangle tests shared by every traversal.
//!
//! Both are written so that the WGSL in `shaders/box.wgsl` and `shaders/triangle.wgsl`
//! performs the same f32 operations in the same order: the GPU kernels are checked
//! against these, ray by ray. Nothing here depends on the scene's absolute scale.

use glam::Vec3;

use crate::ray::Ray;

/// `1 + 2 * gamma(3)` with `gamma(n) = n u / (1 - n u)`, `u = 2^-24` (PBRT-v4, Ize 2013):
/// scaling a box's exit distance by this makes the slab test conservative under f32
/// rounding, whatever the scene's scale.
pub const BOX_TFAR_SCALE: f32 = 1.000_000_4;

/// A ray with everything the tests need precomputed once per ray.
#[derive(Clone, Copy, Debug)]
pub struct PreparedRay {
    pub org: Vec3,
    /// Direction, with subnormal components flushed to (signed) zero as GPUs do.
    pub dir: Vec3,
    /// `1/dir`, with zero components replaced by `±f32::MIN_POSITIVE` (sign kept) so the
    /// product is finite; such axes are handled apart (see `parallel`).
    pub inv_dir: Vec3,
    /// True when some direction component is zero: the ray is parallel to those slabs,
    /// and [`intersect_box`] takes its general path.
    pub parallel: bool,
    pub t_min: f32,
    /// Watertight test: the dominant axis and the two others (Woop et al. 2013).
    pub kx: usize,
    pub ky: usize,
    pub kz: usize,
    /// Shear constants.
    pub sx: f32,
    pub sy: f32,
    pub sz: f32,
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
    /// Precomputes a valid ray (see [`Ray::is_valid`]).
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
        let a = dir.abs();
        // Dominant axis; ties go to the lower axis (the WGSL does the same).
        let kz = if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        // Keep the winding: swap when the dominant component is negative.
        if dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        PreparedRay {
            org,
            dir,
            inv_dir,
            parallel: dir.x == 0.0 || dir.y == 0.0 || dir.z == 0.0,
            t_min: ray.t_min,
            kx,
            ky,
            kz,
            sx: dir[kx] / dir[kz],
            sy: dir[ky] / dir[kz],
            sz: 1.0 / dir[kz],
        }
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

/// Conservative slab test. Returns the entry distance when the ray's interval
/// `[t_min, t_max]` overlaps the box (boundaries included), else `None`.
#[inline(always)]
pub fn intersect_box(r: &PreparedRay, bmin: Vec3, bmax: Vec3, t_max: f32) -> Option<f32> {
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
    let tfar = fmin(
        fmin(fmax(t0.x, t1.x), fmax(t0.y, t1.y)),
        fmin(fmax(t0.z, t1.z), t_max),
    ) * BOX_TFAR_SCALE;
    if tnear <= tfar { Some(tnear) } else { None }
}

/// A triangle hit: distance and the barycentric weights of corners 1 and 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriHit {
    pub t: f32,
    pub u: f32,
    pub v: f32,
}

/// Watertight ray/triangle test (Woop, Benthin, Wald 2013, without the f64 fallback for
/// exactly-zero edge functions: a zero counts as inside, so a ray through a shared edge or
/// vertex hits at least one of the triangles that share it). Returns the hit whatever its
/// distance along the ray; the caller applies the interval.
#[inline(always)]
pub fn intersect_triangle(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
    let a = v0 - r.org;
    let b = v1 - r.org;
    let c = v2 - r.org;
    let (kx, ky, kz) = (r.kx, r.ky, r.kz);
    let ax = a[kx] - r.sx * a[kz];
    let ay = a[ky] - r.sy * a[kz];
    let bx = b[kx] - r.sx * b[kz];
    let by = b[ky] - r.sy * b[kz];
    let cx = c[kx] - r.sx * c[kz];
    let cy = c[ky] - r.sy * c[kz];
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let az = r.sz * a[kz];
    let bz = r.sz * b[kz];
    let cz = r.sz * c[kz];
    let t_scaled = u * az + v * bz + w * cz;
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

/// The classic Moller-Trumbore test (no epsilon on the determinant other than exact zero),
/// kept to measure what watertightness buys. Not used by the traversals by default.
#[inline(always)]
pub fn intersect_triangle_moller_trumbore(
    r: &PreparedRay,
    v0: Vec3,
    v1: Vec3,
    v2: Vec3,
) -> Option<TriHit> {
    let e1 = v1 - v0;
    let e2 = v2 - v0;
    let p = r.dir.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 {
        return None;
    }
    let inv = 1.0 / det;
    let s = r.org - v0;
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = r.dir.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(q) * inv;
    if !(t >= r.t_min) {
        return None;
    }
    Some(TriHit { t, u, v })
}
