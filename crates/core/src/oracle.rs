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

/// Barycentric distance, below which a ray is said to pass along a triangle's edge in
/// [`agreement`]'s rule: 2^-16 of the triangle, about 500 f32 ulps of a barycentric.
pub const EDGE_TOLERANCE: f64 = 1.0 / 65536.0;

/// How close `ray` passes to an edge of `tri`: the smallest of its three barycentric
/// coordinates' magnitudes in f64 (edge function over their sum), 0 for a triangle seen
/// edge-on; for a ray that misses, the distance to the nearest edge line.
pub fn edge_distance(tri: &Triangle, ray: &Ray) -> f64 {
    if !ray.is_valid() {
        return f64::INFINITY;
    }
    let (e, _) = PreparedRay64::new(ray).edge_functions(tri);
    let det: f64 = e.iter().sum();
    if det == 0.0 {
        return 0.0;
    }
    e.iter()
        .map(|x| (x / det).abs())
        .fold(f64::INFINITY, f64::min)
}

/// How a hit from a tracer that is not watertight by contract (a device's ray queries)
/// stands against the CPU walks' hit for the same ray ([`agreement`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Agreement {
    /// The same bits.
    Same,
    /// The same primitive (or the same miss code), another `t` or barycentrics.
    SamePrimitive,
    /// Two primitives whose distances f32 cannot tell apart: `t`s within the sum of their
    /// f32 error bounds ([`f32_t_error_bound`]), or either indeterminate in f32.
    WithinF32,
    /// A hit against a miss (or, for any hit, a miss against a hit) where the ray passes
    /// along an edge of the triangle hit ([`edge_distance`] at most [`EDGE_TOLERANCE`], or
    /// [`f32_indeterminate`]): a silhouette, where a test that is not watertight may
    /// answer either way.
    Silhouette,
    /// Anything else: a wrong answer.
    Differs,
}

impl Agreement {
    /// True unless [`Agreement::Differs`].
    pub fn agrees(self) -> bool {
        self != Agreement::Differs
    }
}

/// The rule a tracer that is not watertight by contract is held to against the CPU
/// walks (`reference`), for one ray; `tris` by primitive id in world space. Closest hits
/// agree on the primitive, or on a distance f32 cannot resolve, or differ only at a
/// silhouette edge; any-hit answers (`any_hit`) agree on hit or miss, or differ only at
/// a silhouette edge.
pub fn agreement(
    tris: &[Triangle],
    ray: &Ray,
    reference: &crate::Hit,
    other: &crate::Hit,
    any_hit: bool,
) -> Agreement {
    if bytemuck::bytes_of(reference) == bytemuck::bytes_of(other) {
        return Agreement::Same;
    }
    let tri = |p: u32| tris.get(p as usize);
    let silhouette = |p: u32| {
        tri(p).is_some_and(|t| f32_indeterminate(t, ray) || edge_distance(t, ray) <= EDGE_TOLERANCE)
    };
    match (reference.is_hit(), other.is_hit()) {
        (true, true) if any_hit || reference.prim == other.prim => Agreement::SamePrimitive,
        (true, true) => {
            let terr = |p: u32| tri(p).map_or(f64::INFINITY, |t| f32_t_error_bound(t, ray));
            let close = (f64::from(reference.t) - f64::from(other.t)).abs()
                <= terr(reference.prim) + terr(other.prim);
            let undecided = [reference.prim, other.prim]
                .iter()
                .any(|&p| tri(p).is_some_and(|t| f32_indeterminate(t, ray)));
            if close || undecided {
                Agreement::WithinF32
            } else if silhouette(reference.prim) || silhouette(other.prim) {
                // The nearer triangle's edge: one side saw it, the other saw past it.
                Agreement::Silhouette
            } else {
                Agreement::Differs
            }
        }
        (true, false) if silhouette(reference.prim) => Agreement::Silhouette,
        (false, true) if silhouette(other.prim) => Agreement::Silhouette,
        (false, false) if reference.prim == other.prim => Agreement::SamePrimitive,
        _ => Agreement::Differs,
    }
}
