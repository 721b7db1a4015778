//! The f64 brute-force oracle: every triangle, in double precision, same hit rule.
//!
//! The rays and corners are converted to f64 exactly, so the oracle answers for the
//! geometry the f32 input represents; differences from the f32 traversals are the f32
//! arithmetic's own error.

use glam::DVec3;

use crate::intersect::{Shear, shear_axes};
use crate::mesh::Triangle;
use crate::ray::{INVALID_RAY, MISS, Ray};

/// An oracle hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OracleHit {
    /// Distance (`t_max` as given on a miss).
    pub t: f64,
    /// Primitive, [`MISS`] or [`INVALID_RAY`].
    pub prim: u32,
    /// Barycentric weight of corner 1 (0 on a miss).
    pub u: f64,
    /// Barycentric weight of corner 2 (0 on a miss).
    pub v: f64,
}

impl OracleHit {
    /// True when a triangle was hit.
    pub fn is_hit(&self) -> bool {
        self.prim < INVALID_RAY
    }
}

/// A ray prepared in f64 (the watertight test's shear, as in `intersect.rs`).
pub struct PreparedRay64 {
    org: DVec3,
    kx: usize,
    ky: usize,
    kz: usize,
    sx: f64,
    sy: f64,
    sz: f64,
}

impl PreparedRay64 {
    /// Prepares a valid ray.
    pub fn new(ray: &Ray) -> Self {
        let org: DVec3 = glam::Vec3::from(ray.origin).as_dvec3();
        let dir = glam::Vec3::from(ray.dir).as_dvec3();
        let (kx, ky, kz) = shear_axes(dir.abs().to_array(), |k| dir[k] < 0.0);
        PreparedRay64 {
            org,
            kx,
            ky,
            kz,
            sx: dir[kx] / dir[kz],
            sy: dir[ky] / dir[kz],
            sz: 1.0 / dir[kz],
        }
    }

    /// Watertight test in f64: `(t, u, v)` or `None`.
    pub fn intersect(&self, tri: &Triangle) -> Option<(f64, f64, f64)> {
        let corners = tri.map(|c| (c.as_dvec3() - self.org).to_array());
        let shear = Shear {
            k: (self.kx, self.ky, self.kz),
            s: [self.sx, self.sy, self.sz],
        };
        let (v, w, det, t_scaled) = shear.edges(corners)?;
        let t = t_scaled / det;
        if !t.is_finite() {
            return None;
        }
        Some((t, v / det, w / det))
    }
}

/// Closest hit over all triangles in f64 (ties to the lower primitive index).
pub fn closest_hit(tris: &[Triangle], ray: &Ray) -> OracleHit {
    let t_max = ray.t_max as f64;
    if !ray.is_valid() {
        return OracleHit {
            t: if ray.t_max.is_nan() { 0.0 } else { t_max },
            prim: INVALID_RAY,
            u: 0.0,
            v: 0.0,
        };
    }
    let r = PreparedRay64::new(ray);
    let t_min = ray.t_min as f64;
    let mut best = OracleHit {
        t: t_max,
        prim: MISS,
        u: 0.0,
        v: 0.0,
    };
    if !(t_min <= t_max) {
        return best;
    }
    for (i, tri) in tris.iter().enumerate() {
        if let Some((t, u, v)) = r.intersect(tri)
            && t >= t_min
            && (t < best.t || (t == best.t && best.prim != MISS && (i as u32) < best.prim))
        {
            best = OracleHit {
                t,
                prim: i as u32,
                u,
                v,
            };
        }
    }
    best
}

/// Every triangle the ray hits in its interval, with its f64 distance, nearest first.
/// Used to recognise near-ties when comparing with f32 results.
pub fn all_hits(tris: &[Triangle], ray: &Ray) -> Vec<(f64, u32)> {
    if !ray.is_valid() {
        return Vec::new();
    }
    let r = PreparedRay64::new(ray);
    let (t_min, t_max) = (ray.t_min as f64, ray.t_max as f64);
    let mut hits: Vec<(f64, u32)> = tris
        .iter()
        .enumerate()
        .filter_map(|(i, t)| r.intersect(t).map(|h| (h.0, i as u32)))
        .filter(|&(t, _)| t >= t_min && t < t_max)
        .collect();
    hits.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    hits
}

impl PreparedRay64 {
    /// The three edge functions in f64 and a bound on the error the f32 test makes in each
    /// (from rounding the translation, the shear and the products: `16 u` times the sum of
    /// the magnitudes of the terms, `u = 2^-24`).
    pub fn edge_functions(&self, tri: &Triangle) -> ([f64; 3], [f64; 3]) {
        let (kx, ky, kz) = (self.kx, self.ky, self.kz);
        let proj = |p: glam::Vec3| {
            let a = p.as_dvec3() - self.org;
            (
                a[kx] - self.sx * a[kz],
                a[ky] - self.sy * a[kz],
                a[kx].abs() + (self.sx * a[kz]).abs(),
                a[ky].abs() + (self.sy * a[kz]).abs(),
            )
        };
        let (ax, ay, max_, may) = proj(tri[0]);
        let (bx, by, mbx, mby) = proj(tri[1]);
        let (cx, cy, mcx, mcy) = proj(tri[2]);
        let u = 2f64.powi(-24) * 16.0;
        (
            [cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax],
            [
                u * (mcx * mby + mcy * mbx),
                u * (max_ * mcy + may * mcx),
                u * (mbx * may + mby * max_),
            ],
        )
    }
}

/// True when f32 arithmetic cannot decide whether this ray hits this triangle: one of the
/// edge functions is within its f32 error bound (the ray passes, in the test's projected
/// space, within rounding of an edge line). Where the f32 input represents the geometry
/// exactly and this is false for every triangle involved, the f32 test must agree with
/// the oracle; where it is true, a difference is f32's, not the algorithm's.
pub fn f32_indeterminate(tri: &Triangle, ray: &Ray) -> bool {
    if !ray.is_valid() {
        return false;
    }
    let (e, bound) = PreparedRay64::new(ray).edge_functions(tri);
    e.iter().zip(&bound).any(|(e, b)| e.abs() <= *b)
}

/// A bound on the f32 test's error in `t` for this ray and triangle, from the edge
/// functions' error bounds: `t = T / det` is ill-conditioned when the triangle is seen
/// nearly edge-on (`det` small against its error). Infinite when the f32 `det` may be 0.
pub fn f32_t_error_bound(tri: &Triangle, ray: &Ray) -> f64 {
    if !ray.is_valid() {
        return 0.0;
    }
    let r = PreparedRay64::new(ray);
    let (e, b) = r.edge_functions(tri);
    let z = tri.map(|p| r.sz * (p.as_dvec3() - r.org)[r.kz]);
    let det: f64 = e.iter().sum();
    let det_err: f64 =
        b.iter().sum::<f64>() + 4.0 * f64::EPSILON * e.iter().map(|x| x.abs()).sum::<f64>();
    if det.abs() <= det_err {
        return f64::INFINITY;
    }
    let u = 2f64.powi(-24) * 8.0;
    let t_num: f64 = (0..3).map(|i| e[i] * z[i]).sum();
    let t_err: f64 = (0..3)
        .map(|i| b[i] * z[i].abs() + u * (e[i] * z[i]).abs())
        .sum();
    let t = t_num / det;
    (t_err + t.abs() * det_err) / (det.abs() - det_err) + u * t.abs()
}
