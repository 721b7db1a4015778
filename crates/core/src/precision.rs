//! Intersection precision: which ray/triangle test the traversals use.
//!
//! The traversals in [`crate::traverse`] are generic over a [`TriangleTest`], monomorphised
//! per precision, so the default path ([`WatertightF32`]) is exactly the code it was
//! before the choice existed. Each test has a WGSL twin in `shaders/` that performs the
//! same operations in the same order (`triangle.wgsl`, `triangle_moller_trumbore.wgsl`,
//! `triangle_f64.wgsl`), so a GPU result equals its CPU twin bit for bit.
//!
//! # Box culling
//!
//! Every precision culls boxes with the same f32 slab test and the same slack
//! ([`crate::intersect::BOX_CULL_SLACK`], `64 u m`), which keeps closest hits independent
//! of the visit order:
//!
//! * watertight f32: the slack's own error analysis;
//! * watertight f64: `t` is computed in f64 (error about `1e-15 m`) and rounded to f32
//!   once (at most `u |t| <= u m`), and the f32 box's entry is within `γ_3 m` of the exact
//!   one: about `4 u m`, well inside `64 u m`. The f32 boxes are conservative for the f32
//!   corners, which f64 represents exactly;
//! * Möller–Trumbore f32: its `t = (e2 · q) / det` has an error proportional to
//!   `|e1| |e2| |s| / |det|`, not to `m`: bounded by the slack for well-conditioned hits
//!   and unbounded for grazing ones, the same cases where the f32 weights are
//!   indeterminate. It is the comparison variant, not the reference: measured, not
//!   relied on.

use std::fmt;
use std::str::FromStr;

use glam::{DVec3, Vec3};

use crate::intersect::{PreparedRay, Shear, TriHit, intersect_triangle};

/// Which ray/triangle test a traversal uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Precision {
    /// The watertight test in f32 (Woop, Benthin, Wald 2013): the default. A ray through
    /// a shared edge or vertex of a closed mesh never slips through.
    #[default]
    WatertightF32,
    /// Möller–Trumbore in f32, not watertight: kept to measure what watertightness buys.
    MollerTrumboreF32,
    /// The watertight test in f64 (corners and ray converted exactly, `t`, `u`, `v`
    /// rounded to f32 once at the end). On the GPU it needs `SHADER_F64`.
    WatertightF64,
}

impl Precision {
    /// Every precision, default first.
    pub const ALL: [Precision; 3] = [
        Precision::WatertightF32,
        Precision::MollerTrumboreF32,
        Precision::WatertightF64,
    ];

    /// The name used on the command line and in reports.
    pub fn name(&self) -> &'static str {
        match self {
            Precision::WatertightF32 => "watertight-f32",
            Precision::MollerTrumboreF32 => "moller-trumbore-f32",
            Precision::WatertightF64 => "watertight-f64",
        }
    }

    /// True when the test computes in f64 (a GPU needs `SHADER_F64`).
    pub fn needs_f64(&self) -> bool {
        *self == Precision::WatertightF64
    }

    /// True for the tests that never let a ray slip between triangles sharing an edge.
    pub fn is_watertight(&self) -> bool {
        *self != Precision::MollerTrumboreF32
    }

    /// The test itself, for one triangle (what the traversals call, monomorphised).
    pub fn intersect(&self, r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
        match self {
            Precision::WatertightF32 => WatertightF32::intersect(r, v0, v1, v2),
            Precision::MollerTrumboreF32 => MollerTrumboreF32::intersect(r, v0, v1, v2),
            Precision::WatertightF64 => WatertightF64::intersect(r, v0, v1, v2),
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Precision {
    type Err = String;
    /// `watertight-f32` (or `f32`), `moller-trumbore-f32` (or `mt`), `watertight-f64`
    /// (or `f64`).
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "watertight-f32" | "watertight" | "f32" => Ok(Precision::WatertightF32),
            "moller-trumbore-f32" | "moller-trumbore" | "mt" => Ok(Precision::MollerTrumboreF32),
            "watertight-f64" | "f64" => Ok(Precision::WatertightF64),
            _ => Err(format!(
                "unknown precision '{s}' (expected watertight-f32, moller-trumbore-f32 or watertight-f64)"
            )),
        }
    }
}

/// A ray/triangle test the traversals can be specialised for. Returns the hit whatever its
/// distance along the ray beyond `t_min`; the caller applies the hit rule.
pub trait TriangleTest {
    /// The precision this test implements.
    const PRECISION: Precision;
    /// Intersects the prepared ray with the triangle `v0 v1 v2`.
    fn intersect(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit>;
}

/// [`Precision::WatertightF32`]: [`intersect_triangle`].
pub struct WatertightF32;
/// [`Precision::MollerTrumboreF32`]: [`intersect_triangle_mt`].
pub struct MollerTrumboreF32;
/// [`Precision::WatertightF64`]: [`intersect_triangle_f64`].
pub struct WatertightF64;

impl TriangleTest for WatertightF32 {
    const PRECISION: Precision = Precision::WatertightF32;
    #[inline(always)]
    fn intersect(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
        intersect_triangle(r, v0, v1, v2)
    }
}

impl TriangleTest for MollerTrumboreF32 {
    const PRECISION: Precision = Precision::MollerTrumboreF32;
    #[inline(always)]
    fn intersect(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
        intersect_triangle_mt(r, v0, v1, v2)
    }
}

impl TriangleTest for WatertightF64 {
    const PRECISION: Precision = Precision::WatertightF64;
    #[inline(always)]
    fn intersect(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
        intersect_triangle_f64(r, v0, v1, v2)
    }
}

/// Möller–Trumbore (1997) in f32, twin of `shaders/triangle_moller_trumbore.wgsl`
/// operation for operation: not watertight (each triangle decides its own edges from its
/// own `e1`, `e2`, `s = org - v0`, so a ray through a shared edge can miss both).
///
/// The inside decision compares the unscaled numerators with `det` (the 1997 paper's
/// division-free form), then scales once by `1/det`; no exact-zero epsilon other than
/// `det == 0`. Dividing first (`u = (s · p) / det`, then `u + v > 1`) would put the sum of
/// two products with a common factor in the decision, which a GPU compiler may legally
/// refactor (Mesa's NIR does, for ops not marked exact) and decide differently from the
/// CPU. Products and sums are written out in the order of glam's `cross` and `dot`.
#[inline(always)]
pub fn intersect_triangle_mt(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
    let e1 = v1 - v0;
    let e2 = v2 - v0;
    let p = r.dir.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 {
        return None;
    }
    let s = r.org - v0;
    let un = s.dot(p);
    let q = s.cross(e1);
    let vn = r.dir.dot(q);
    let inside = if det > 0.0 {
        un >= 0.0 && un <= det && vn >= 0.0 && un + vn <= det
    } else {
        un <= 0.0 && un >= det && vn <= 0.0 && un + vn >= det
    };
    if !inside {
        return None;
    }
    let inv = 1.0 / det;
    let t = e2.dot(q) * inv;
    // NaN fails this comparison and is rejected.
    if !(t >= r.t_min) {
        return None;
    }
    Some(TriHit {
        t,
        u: un * inv,
        v: vn * inv,
    })
}

/// The watertight test in f64, twin of `shaders/triangle_f64.wgsl` operation for
/// operation. The ray's f32 origin and (flushed) direction and the corners are converted
/// to f64 exactly; the dominant axis and the winding are the f32 ray's (`r.kx`, `r.ky`,
/// `r.kz`: the same ones, as the conversion keeps the ordering of magnitudes); the shear is
/// recomputed in f64. `t = T / det`, `u = v / det`, `w / det` are rounded to f32 once, and
/// the f32 `t` is checked against `t_min` (a zero edge function counts as inside, as in
/// [`intersect_triangle`]).
#[inline(always)]
pub fn intersect_triangle_f64(r: &PreparedRay, v0: Vec3, v1: Vec3, v2: Vec3) -> Option<TriHit> {
    let org = r.org.as_dvec3();
    let d: DVec3 = r.dir.as_dvec3();
    let (kx, ky, kz) = (r.kx, r.ky, r.kz);
    let dz = d[kz];
    let sx = d[kx] / dz;
    let sy = d[ky] / dz;
    let sz = 1.0 / dz;
    let corners = [v0, v1, v2].map(|c| (c.as_dvec3() - org).to_array());
    let shear = Shear {
        k: (kx, ky, kz),
        s: [sx, sy, sz],
    };
    let (v, w, det, t_scaled) = shear.edges(corners)?;
    let t = (t_scaled / det) as f32;
    // NaN fails this comparison and is rejected.
    if !(t >= r.t_min) {
        return None;
    }
    Some(TriHit {
        t,
        u: (v / det) as f32,
        v: (w / det) as f32,
    })
}
