//! The f64 brute-force oracle: every triangle, in double precision, same hit rule.
//!
//! The rays and corners are converted to f64 exactly, so the oracle answers for the
//! geometry the f32 input represents; differences from the f32 traversals are the f32
//! arithmetic's own error.

use glam::DVec3;

use crate::mesh::Triangle;
use crate::ray::{INVALID_RAY, MISS, Ray};

/// An oracle hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OracleHit {
    /// Distance (`t_max` as given on a miss).
    pub t: f64,
    /// Primitive, [`MISS`] or [`INVALID_RAY`].
    pub prim: u32,
    pub u: f64,
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
        let org = DVec3::from(glam::Vec3::from(ray.origin).as_dvec3());
        let dir = glam::Vec3::from(ray.dir).as_dvec3();
        let a = dir.abs();
        let kz = if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        if dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
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
        let a = tri[0].as_dvec3() - self.org;
        let b = tri[1].as_dvec3() - self.org;
        let c = tri[2].as_dvec3() - self.org;
        let (kx, ky, kz) = (self.kx, self.ky, self.kz);
        let ax = a[kx] - self.sx * a[kz];
        let ay = a[ky] - self.sy * a[kz];
        let bx = b[kx] - self.sx * b[kz];
        let by = b[ky] - self.sy * b[kz];
        let cx = c[kx] - self.sx * c[kz];
        let cy = c[ky] - self.sy * c[kz];
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
        let t = (u * self.sz * a[kz] + v * self.sz * b[kz] + w * self.sz * c[kz]) / det;
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
