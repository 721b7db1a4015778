//! Linear curve segments, as Embree 3 defines them.
//!
//! A *round* segment from `p0` (radius `r0`) to `p1` (radius `r1`) is the cone that touches
//! the spheres at both ends, plus the sphere at `p1` (and the one at `p0` where the strand
//! starts); the cones of the neighbouring segments are cut away, so the inside of a bend
//! is not hit twice. A *flat* segment is a ribbon that faces the ray: hit where the ray
//! passes within the interpolated radius of the segment, at the depth of the segment's
//! nearest point. Both follow Embree's arithmetic (`roundline_intersector.h`,
//! `line_intersector.h`) in f32, so a hit differs from Embree's by rounding only.

use glam::{Vec3, Vec4};

use super::{CurveHit, unit};

/// Ray space for a flat segment: two axes across the ray and the depth axis
/// `dir / |dir|^2`, so a point's third coordinate is its distance in ray units.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RaySpace {
    x: Vec3,
    y: Vec3,
    z: Vec3,
    /// `1 / |dir|`.
    depth_scale: f32,
}

impl RaySpace {
    pub fn new(dir: Vec3) -> RaySpace {
        let depth_scale = 1.0 / dir.dot(dir).sqrt();
        let n = dir * depth_scale;
        // Embree's `frame`: the longer of two vectors perpendicular to n.
        let (a, b) = (Vec3::new(0.0, n.z, -n.y), Vec3::new(-n.z, 0.0, n.x));
        let x = unit(if a.dot(a) > b.dot(b) { a } else { b });
        let y = unit(n.cross(x));
        RaySpace {
            x,
            y,
            z: n * depth_scale,
            depth_scale,
        }
    }

    /// The space of the direction scaled by `k` (a power of two: exact).
    pub fn scaled(&self, k: f32) -> RaySpace {
        RaySpace {
            z: self.z / k,
            depth_scale: self.depth_scale / k,
            ..*self
        }
    }

    fn apply(&self, p: Vec3) -> Vec3 {
        Vec3::new(self.x.dot(p), self.y.dot(p), self.z.dot(p))
    }
}

/// Embree's factor for flat curves: hits nearer than twice the radius (in ray units) are
/// taken for the curve a secondary ray leaves, and ignored.
const SELF_INTERSECTION_AVOIDANCE: f32 = 2.0;

/// The flat segment `v0`..`v1` (xyz and radius) against the ray from `org` in ray space
/// `space`: the hit in `[t_min, t_max]`, its `u` along the segment and, for a normal, the
/// side of the ribbon that faces the ray.
pub(crate) fn flat_linear(
    org: Vec3,
    space: &RaySpace,
    (t_min, t_max): (f32, f32),
    v0: Vec4,
    v1: Vec4,
) -> Option<CurveHit> {
    let p0 = space.apply(v0.truncate() - org).extend(v0.w);
    let p1 = space.apply(v1.truncate() - org).extend(v1.w);
    let v = p1 - p0;
    let d0 = -p0.x * v.x - p0.y * v.y;
    let d1 = v.x * v.x + v.y * v.y;
    // A segment seen end on (d1 = 0) is nearest the ray at its start.
    let u = if d1 > 0.0 {
        (d0 / d1).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let p = p0 + u * v;
    let (t, r) = (p.z, p.w);
    let near_enough = p.x * p.x + p.y * p.y <= r * r;
    let inside = t_min <= t && t <= t_max;
    let not_self = t > SELF_INTERSECTION_AVOIDANCE * r * space.depth_scale;
    let tangent = (v1 - v0).truncate();
    if !(near_enough && inside && not_self) || tangent == Vec3::ZERO {
        return None;
    }
    // The ribbon turns about its tangent to face the ray: its normal is the ray's
    // direction against, less its part along the tangent.
    let back = -space.z;
    let normal = back - tangent * (back.dot(tangent) / tangent.length_squared());
    Some(CurveHit { t, u, normal })
}

/// The cone between two spheres, relative to `p0` (Embree's `ConeGeometry`).
#[derive(Clone, Copy)]
struct Cone {
    p0: Vec3,
    p1: Vec3,
    dp: Vec3,
    dpdp: f32,
    r0: f32,
    r1: f32,
    r0dr: f32,
    /// `|dp|^2 - dr^2`: not positive when one sphere holds the other.
    g: f32,
}

impl Cone {
    fn new(a: Vec4, b: Vec4) -> Cone {
        let (p0, p1) = (a.truncate(), b.truncate());
        let dp = p1 - p0;
        let dr = b.w - a.w;
        let dpdp = dp.dot(dp);
        Cone {
            p0,
            p1,
            dp,
            dpdp,
            r0: a.w,
            r1: b.w,
            r0dr: a.w * dr,
            g: dpdp - dr * dr,
        }
    }

    /// A cone to an absent neighbour: holds nothing, clips nothing.
    fn exists(&self) -> bool {
        self.p0.x.is_finite() && self.p1.x.is_finite()
    }

    /// True when `p` is past the cone's start plane (inside the neighbour that starts at
    /// this segment's end).
    fn clips(&self, p: Vec3) -> bool {
        self.exists() && (p - self.p0).dot(self.dp) > -self.r0dr
    }

    /// True when `p` is inside the cone between its two clipping planes.
    fn holds(&self, p: Vec3) -> bool {
        let p0p = p - self.p0;
        let y = p0p.dot(self.dp);
        let dr = self.r1 - self.r0;
        self.exists()
            && y > -self.r0dr + f32::EPSILON
            && y < -self.r1 * dr + self.dpdp
            && p0p.dot(p0p) * self.g - y * y < self.dpdp * self.r0 * self.r0 + 2.0 * self.r0dr * y
    }
}

/// A sphere's two crossings `(near, far)` by the ray `org + t dir` (`None` when it misses).
fn sphere(org: Vec3, dir: Vec3, rcp_dd: f32, c: Vec3, r: f32) -> Option<(f32, f32)> {
    let o = org - c;
    let od = o.dot(dir);
    let h2 = od * od - dir.dot(dir) * (o.dot(o) - r * r);
    let q = (h2 >= 0.0).then(|| h2.sqrt())?;
    Some(((-od - q) * rcp_dd, (-od + q) * rcp_dd))
}

/// Where a round segment's surface is crossed: its cone, its end sphere and (at a strand's
/// start) its start sphere, near and far, relative to the moved origin; `±inf` where none.
#[derive(Clone, Copy, Debug)]
struct Crossings {
    cone: (f32, f32),
    start: (f32, f32),
    end: (f32, f32),
}

/// The round segment `v0`..`v1` (xyz and radius), with its strand's previous point `vl`
/// and next point `vr` where the strand goes on, against the ray `org + t dir`: the first
/// hit in `[t_min, t_max]`.
pub(crate) fn round_linear(
    org: Vec3,
    dir: Vec3,
    (t_min, t_max): (f32, f32),
    [v0, v1]: [Vec4; 2],
    [vl, vr]: [Option<Vec4>; 2],
) -> Option<CurveHit> {
    // Solve near the segment, where the quadratics are well conditioned.
    let dd = dir.dot(dir);
    let rcp_dd = dd.recip();
    let center = 0.5 * (v0.truncate() + v1.truncate());
    let dt = (center - org).dot(dir) * rcp_dd;
    let org = org + dt * dir;
    let cone = Cone::new(v0, v1);
    let o = org - cone.p0;
    let (odp, ddp) = (cone.dp.dot(o), cone.dp.dot(dir));
    let yp = odp + cone.r0dr;
    let absent = Vec4::splat(f32::INFINITY);
    let left = Cone::new(v0, vl.unwrap_or(absent));
    let right = Cone::new(v1, vr.unwrap_or(absent));
    let mut x = Crossings {
        cone: (f32::INFINITY, f32::NEG_INFINITY),
        start: (f32::INFINITY, f32::NEG_INFINITY),
        end: (f32::INFINITY, f32::NEG_INFINITY),
    };
    // The cone: (|dp|^2 - dr^2) |h|^2 - (h.dp)^2 - r0^2 |dp|^2 - 2 r0 dr (h.dp) = 0 for
    // h = o + t dir, between the planes that cut it where it touches the spheres.
    let g = cone.g;
    let a = g * dd - ddp * ddp;
    let b = 2.0 * (g * dir.dot(o) - ddp * yp);
    let c = g * o.dot(o) - odp * odp - cone.r0 * cone.r0 * cone.dpdp - 2.0 * cone.r0dr * odp;
    let disc = b * b - 4.0 * a * c;
    // A ray along the cone's axis (a = 0) cannot cross its side, but can its end spheres;
    // Embree gives it up, which leaves a hole in a strand seen end on.
    let parallel = a.abs() <= 16.0 * f32::EPSILON * (g * dd).max(ddp * ddp);
    let cone_valid = disc >= 0.0 && g > 0.0 && !parallel;
    if !cone_valid && g > 0.0 && !parallel {
        // The spheres lie inside the cone's infinite extension: a ray that misses it
        // misses them.
        return None;
    }
    let y_at = |t: f32| yp + t * ddp;
    let mut cone_y = (0.0, 0.0);
    if cone_valid {
        let q = disc.sqrt();
        let rcp_2a = (2.0 * a).recip();
        let (tf, tb) = ((-b - q) * rcp_2a, (-b + q) * rcp_2a);
        cone_y = (y_at(tf), y_at(tb));
        let on = |y: f32| y > -f32::EPSILON && y <= g;
        // A crossing inside a neighbour's cone is inside the strand.
        let outside = |t: f32| {
            let p = org + t * dir;
            !left.holds(p) && !right.holds(p)
        };
        if on(cone_y.0) && outside(tf) {
            x.cone.0 = tf;
        }
        if on(cone_y.1) && outside(tb) {
            x.cone.1 = tb;
        }
    }
    if let Some((tf, tb)) = sphere(org, dir, rcp_dd, cone.p1, cone.r1) {
        let keep = |t: f32| y_at(t) > g && !right.clips(org + t * dir);
        x.end = (
            if keep(tf) { tf } else { f32::INFINITY },
            if keep(tb) { tb } else { f32::NEG_INFINITY },
        );
    }
    if vl.is_none()
        && let Some((tf, tb)) = sphere(org, dir, rcp_dd, cone.p0, cone.r0)
    {
        let keep = |t: f32| y_at(t) < 0.0;
        x.start = (
            if keep(tf) { tf } else { f32::INFINITY },
            if keep(tb) { tb } else { f32::NEG_INFINITY },
        );
    }
    let lower = x.cone.0.min(x.start.0.min(x.end.0));
    let upper = x.cone.1.max(x.start.1.max(x.end.1));
    let within = |t: f32| t_min <= dt + t && dt + t <= t_max;
    let (t, front) = if lower != f32::INFINITY && within(lower) {
        (lower, true)
    } else if upper != f32::NEG_INFINITY && within(upper) {
        (upper, false)
    } else {
        return None;
    };
    let pick = |(f, b): (f32, f32)| if front { f } else { b };
    let (normal, u) = if t == x.cone.0 || t == x.cone.1 {
        // Embree's cone normal: (|dp|^2 - dr^2) h - dp (h.dp + r0 dr).
        let y = pick(cone_y);
        ((o + t * dir) * g - cone.dp * y, (y / g).clamp(0.0, 1.0))
    } else if t == x.start.0 || t == x.start.1 {
        (org + t * dir - cone.p0, 0.0)
    } else {
        (org + t * dir - cone.p1, 1.0)
    };
    Some(CurveHit {
        t: dt + t,
        u,
        normal,
    })
}
