//! Curves: hair, fur and grass as strands of segments with a radius per control point,
//! in one BVH beside triangles (the node, its build and its walk together).
//!
//! The four kinds are Embree 3's: [`CurveKind::RoundLinear`] (cones between spheres),
//! [`CurveKind::FlatLinear`] (ribbons that face the ray), and round cubic curves, the
//! surface swept by a circle normal to a [`CurveKind::RoundBezier`] or
//! [`CurveKind::RoundBSpline`] curve. Each segment is a primitive of its own, with its own
//! box; [`CurveBvh`] builds one tree over a scene's triangles and segments, whose leaves
//! hold either, and answers with the hit's curve parameter in [`Hit::u`] and a normal
//! ([`CurveBvh::normal`]). The intersections follow Embree's in f32 (see `linear.rs` and
//! `cubic.rs`), so hits can be checked against Embree's on the same rays.

use bytemuck::{Pod, Zeroable};
use glam::{Vec3, Vec4};

use crate::build::{BuildError, BuildOptions};
use crate::flat::{FlatNode, FlatTriangle};
use crate::geometry::Aabb;
use crate::intersect::{PreparedRay, intersect_triangle};
use crate::mesh::{MeshError, Triangle, validate_triangles};
use crate::motion::TimeBounds;
use crate::motion::tree::{TimeTree, trace_all};
use crate::ray::{Counters, Hit, Ray};
use crate::traverse::{Best, Query, untraced};

mod cubic;
mod linear;

use cubic::Bezier;
use linear::RaySpace;

/// What a strand's segments are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CurveKind {
    /// Straight segments swept by a sphere: cones between spheres at the points
    /// (Embree's `RTC_GEOMETRY_TYPE_ROUND_LINEAR_CURVE`).
    RoundLinear,
    /// Straight ribbons of the points' width that turn to face the ray
    /// (`RTC_GEOMETRY_TYPE_FLAT_LINEAR_CURVE`).
    FlatLinear,
    /// Cubic Bezier segments of four control points, swept by a circle normal to the
    /// curve (`RTC_GEOMETRY_TYPE_ROUND_BEZIER_CURVE`).
    RoundBezier,
    /// Uniform cubic B-spline segments of four control points, swept likewise
    /// (`RTC_GEOMETRY_TYPE_ROUND_BSPLINE_CURVE`).
    RoundBSpline,
}

impl CurveKind {
    /// Every kind, in the order the dump format numbers them.
    pub const ALL: [CurveKind; 4] = [
        CurveKind::RoundLinear,
        CurveKind::FlatLinear,
        CurveKind::RoundBezier,
        CurveKind::RoundBSpline,
    ];

    /// Control points a segment takes after its first: 1 for linear, 3 for cubic.
    pub fn degree(self) -> usize {
        match self {
            CurveKind::RoundLinear | CurveKind::FlatLinear => 1,
            CurveKind::RoundBezier | CurveKind::RoundBSpline => 3,
        }
    }

    /// The kind's name on the command line (`round-linear`, ...).
    pub fn name(self) -> &'static str {
        match self {
            CurveKind::RoundLinear => "round-linear",
            CurveKind::FlatLinear => "flat-linear",
            CurveKind::RoundBezier => "round-bezier",
            CurveKind::RoundBSpline => "round-bspline",
        }
    }
}

/// Strands of one kind: control points with a radius each, and segments that name their
/// first control point (the rest follow it), as Embree's vertex and index buffers do.
///
/// A linear segment's neighbours are the segments listed just before and after it that
/// share its points (`segments[i - 1] + 1 == segments[i]`): a strand is its segments in
/// order. The round linear surface cuts a neighbour's cone out of a segment, and caps a
/// strand's first point with a sphere (Embree's `RTC_CURVE_FLAG_NEIGHBOR_LEFT/RIGHT`).
#[derive(Clone, Debug, PartialEq)]
pub struct Curves {
    /// What the segments are.
    pub kind: CurveKind,
    /// Control points: position in `xyz`, radius in `w`.
    pub points: Vec<Vec4>,
    /// Each segment's first control point.
    pub segments: Vec<u32>,
}

/// Why curves were refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CurveError {
    /// A control point has a NaN or infinite coordinate or radius, or a negative radius.
    #[error("curve point {point}: {value:?} is not a finite position with a radius of 0 or more")]
    BadPoint {
        /// The point at fault.
        point: usize,
        /// Its position and radius.
        value: [f32; 4],
    },
    /// A segment's control points run past the end of the points.
    #[error("curve segment {segment} starts at point {first}, but a {kind} segment needs points up to {last} and there are {points}", kind = kind.name(), last = first + kind.degree() as u64)]
    OutOfRange {
        /// The segment at fault.
        segment: usize,
        /// Its first point.
        first: u64,
        /// The kind of segment.
        kind: CurveKind,
        /// The number of points.
        points: usize,
    },
    /// The triangles beside the curves are bad, or the scene is too large or empty.
    #[error(transparent)]
    Build(#[from] BuildError),
}

impl Curves {
    /// Checks every point and segment.
    pub fn validate(&self) -> Result<(), CurveError> {
        for (i, p) in self.points.iter().enumerate() {
            if !p.is_finite() || !(p.w >= 0.0) {
                return Err(CurveError::BadPoint {
                    point: i,
                    value: p.to_array(),
                });
            }
        }
        for (s, &first) in self.segments.iter().enumerate() {
            let last = u64::from(first) + self.kind.degree() as u64;
            if last >= self.points.len() as u64 {
                return Err(CurveError::OutOfRange {
                    segment: s,
                    first: first.into(),
                    kind: self.kind,
                    points: self.points.len(),
                });
            }
        }
        Ok(())
    }

    /// Number of segments.
    pub fn len(&self) -> usize {
        self.segments.len()
    }

    /// True when there are no segments.
    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    /// Whether linear segment `s` continues one before it and one after it.
    pub fn neighbours(&self, s: usize) -> (bool, bool) {
        let first = self.segments[s];
        let left = s > 0 && self.segments[s - 1].wrapping_add(1) == first;
        let right = self
            .segments
            .get(s + 1)
            .is_some_and(|&n| n == first.wrapping_add(1));
        (left, right)
    }

    /// Segment `s`'s control points (two or four).
    fn control(&self, s: usize) -> &[Vec4] {
        let first = self.segments[s] as usize;
        &self.points[first..=first + self.kind.degree()]
    }

    /// Segment `s`'s control points relative to its first point, scaled by `k`; a cubic
    /// segment's in Bezier form. The intersections and the box both start from these.
    fn local(&self, s: usize, k: f32) -> [Vec4; 4] {
        let c = self.control(s);
        let base = c[0].truncate().extend(0.0);
        let p = |i: usize| (c[i.min(c.len() - 1)] - base) * k;
        let b = [p(0), p(1), p(2), p(3)];
        match self.kind {
            CurveKind::RoundBSpline => bspline_to_bezier(b),
            _ => b,
        }
    }

    /// The box around segment `s`'s surface, found relative to its first point and
    /// widened by a few units in the last place of the largest coordinate, so it holds
    /// the surface the intersection sees wherever the strand is.
    pub fn segment_box(&self, s: usize) -> Aabb {
        let base = self.control(s)[0].truncate();
        let c = self.local(s, 1.0);
        let (lo, hi) = match self.kind.degree() {
            1 => {
                let (a, b) = (c[0], c[1]);
                let lo = (a.truncate() - a.w).min(b.truncate() - b.w);
                let hi = (a.truncate() + a.w).max(b.truncate() + b.w);
                (lo, hi)
            }
            _ => Bezier(c).bounds(),
        };
        let scale = base.abs().max(lo.abs()).max(hi.abs()).max_element();
        let slack = scale * (1.0 / (1 << 21) as f32);
        Aabb {
            min: base + lo - slack,
            max: base + hi + slack,
        }
    }

    /// Segment `s` against a ray from `org` along `dir`: its first hit in
    /// `t_min..=t_max`. `space` is the ray's space (flat segments use it).
    fn intersect(
        &self,
        s: usize,
        (org, dir, space): (Vec3, Vec3, &RaySpace),
        range: (f32, f32),
    ) -> Option<CurveHit> {
        let c = self.control(s);
        // Relative to the segment's first point, so a strand far from the origin loses no
        // more than its own size's precision.
        let base = c[0].truncate();
        // Positions and the direction scaled by powers of two to about unit size: exact,
        // so the answers are those of the unscaled arithmetic wherever that neither
        // underflows nor overflows, and tiny or huge strands are solved as well as unit
        // ones. Distances along the ray scale by `k / m`.
        let (ek, em) = (
            unit_exponent(c, org - base),
            unit_exponent_of(dir.abs().max_element()),
        );
        let (k, m, f) = (pow2(ek), pow2(em), pow2((ek - em).clamp(-126, 126)));
        let (org, dir, space) = ((org - base) * k, dir * m, space.scaled(m));
        let range = (range.0 * f, range.1 * f);
        let p = |i: usize| (self.points[i] - base.extend(0.0)) * k;
        let first = self.segments[s] as usize;
        let hit = match self.kind {
            CurveKind::FlatLinear => {
                linear::flat_linear(org, &space, range, p(first), p(first + 1))
            }
            CurveKind::RoundLinear => {
                let (left, right) = self.neighbours(s);
                let vl = left.then(|| p(first - 1));
                let vr = right.then(|| p(first + 2));
                linear::round_linear(org, dir, range, [p(first), p(first + 1)], [vl, vr])
            }
            CurveKind::RoundBezier | CurveKind::RoundBSpline => {
                cubic::round_cubic(org, dir, range, &Bezier(self.local(s, k)))
            }
        };
        hit.map(|h| CurveHit { t: h.t / f, ..h })
    }
}

/// `2^e` for `e` in `[-126, 127]`, from its bits.
fn pow2(e: i32) -> f32 {
    f32::from_bits(((e + 127) as u32) << 23)
}

/// The exponent `e` for which `x 2^e` is in `[1, 2)`, clamped to `[-126, 126]`, from the
/// bits of `x` (0 for zero, subnormal and non-finite `x`).
fn unit_exponent_of(x: f32) -> i32 {
    let biased = ((x.to_bits() >> 23) & 0xff) as i32;
    if x > 0.0 && (1..255).contains(&biased) {
        (127 - biased).clamp(-126, 126)
    } else {
        0
    }
}

/// The exponent of the power of two that brings a segment's size (its control points'
/// spread and radii) to `[1, 2)`, lowered where the ray's origin or the points (all
/// relative to the first point) would pass `2^100`.
fn unit_exponent(control: &[Vec4], org: Vec3) -> i32 {
    let base = control[0].truncate();
    let (size, far) = control
        .iter()
        .fold((0.0f32, org.abs().max_element()), |(s, f), p| {
            let d = (p.truncate() - base).abs().max_element();
            (s.max(d).max(p.w), f.max(d))
        });
    // `far` is below `2^(1 - unit_exponent_of(far))`.
    let room = 100 - (1 - unit_exponent_of(far));
    unit_exponent_of(size).min(room.max(-126))
}

/// `|v|` as `sqrt(v.v)`, spelled out so the kernel's twin computes it alike.
pub(crate) fn length(v: Vec3) -> f32 {
    v.dot(v).sqrt()
}

/// `v / |v|` as `v (1 / |v|)`, or zero for a zero vector.
pub(crate) fn unit(v: Vec3) -> Vec3 {
    let l = length(v);
    if l > 0.0 { v * (1.0 / l) } else { Vec3::ZERO }
}

/// The Bezier control points of the uniform cubic B-spline segment with control points
/// `b`: the same curve (and radius), the form the round cubic intersection takes.
pub fn bspline_to_bezier(b: [Vec4; 4]) -> [Vec4; 4] {
    [
        (b[0] + 4.0 * b[1] + b[2]) * (1.0 / 6.0),
        (2.0 * b[1] + b[2]) * (1.0 / 3.0),
        (b[1] + 2.0 * b[2]) * (1.0 / 3.0),
        (b[1] + 4.0 * b[2] + b[3]) * (1.0 / 6.0),
    ]
}

/// A segment as the kernels read it (`bvh_curve_buffers.wgsl`): its first control point
/// and its neighbours (bit 0: one before it in the strand, bit 1: one after), 8 bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct CurveSegment {
    /// The segment's first control point.
    pub first: u32,
    /// Bit 0: a segment before it in the strand; bit 1: one after it.
    pub neighbours: u32,
}

/// A curve hit: distance, curve parameter, and a normal (not unit length; for flat
/// curves the side that faces the ray).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct CurveHit {
    pub t: f32,
    pub u: f32,
    pub normal: Vec3,
}

/// One tree over triangles and curve segments, their leaves holding either. Primitive
/// ids: the triangles' own index, then `triangle_count() + segment`.
#[derive(Clone, Debug)]
pub struct CurveBvh {
    tree: TimeTree,
    /// Primitive ids in leaf order.
    order: Vec<u32>,
    triangles: Vec<Triangle>,
    curves: Curves,
}

impl CurveBvh {
    /// Builds the tree over `triangles` (may be empty) and `curves` with any CPU builder's
    /// options; the two together must not be empty.
    pub fn build(
        triangles: &[Triangle],
        curves: Curves,
        opts: &BuildOptions,
    ) -> Result<CurveBvh, CurveError> {
        validate_triangles(triangles).map_err(BuildError::from)?;
        curves.validate()?;
        let total = triangles.len() + curves.len();
        if total > crate::flat::MAX_PRIMITIVES {
            return Err(BuildError::from(MeshError::TooMany(total)).into());
        }
        let boxes = CurveBvh::prim_boxes(triangles, &curves);
        let (tree, order) = TimeTree::build(&boxes, 1, opts, TimeBounds::Merged)?;
        Ok(CurveBvh {
            tree,
            order,
            triangles: triangles.to_vec(),
            curves,
        })
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// The curves.
    pub fn curves(&self) -> &Curves {
        &self.curves
    }

    /// The tree's depth (levels, the root's counted).
    pub fn depth(&self) -> u32 {
        self.tree.depth
    }

    /// The box around everything.
    pub fn bounds(&self) -> Aabb {
        self.tree.nodes[0].aabb()
    }

    /// Bytes the walk reads: nodes, leaf order, triangles, points and segments.
    pub fn byte_size(&self) -> usize {
        use std::mem::size_of;
        self.tree.byte_size()
            + self.order.len() * 4
            + self.triangles.len() * size_of::<Triangle>()
            + self.curves.points.len() * size_of::<Vec4>()
            + self.curves.segments.len() * 4
    }

    /// The nodes, depth first (a node's first child follows it).
    pub fn nodes(&self) -> &[FlatNode] {
        &self.tree.nodes
    }

    /// Each leaf slot's primitive id: a leaf's `first .. first + count` index this.
    pub fn leaf_prims(&self) -> &[u32] {
        &self.order
    }

    /// The triangles by primitive id, as the kernels read them.
    pub fn flat_triangles(&self) -> Vec<FlatTriangle> {
        (self.triangles.iter().enumerate())
            .map(|(i, t)| FlatTriangle::new(t, i as u32))
            .collect()
    }

    /// The segments as the kernels read them, with their neighbours.
    pub fn kernel_segments(&self) -> Vec<CurveSegment> {
        (0..self.curves.len())
            .map(|s| {
                let (left, right) = self.curves.neighbours(s);
                CurveSegment {
                    first: self.curves.segments[s],
                    neighbours: u32::from(left) | (u32::from(right) << 1),
                }
            })
            .collect()
    }

    /// The segment a primitive id names, `None` for a triangle.
    pub fn segment_of(&self, prim: u32) -> Option<usize> {
        (prim as usize).checked_sub(self.triangles.len())
    }

    /// Traces one ray: the closest hit (the walks' hit rule: the nearest, a lower id on a
    /// tie) or any hit, with the boxes and primitives tested. A curve hit's [`Hit::u`] is
    /// its curve parameter in `[0, 1]` and [`Hit::v`] is 0.
    pub fn trace(&self, ray: &Ray, query: Query) -> (Hit, Counters) {
        // The prepared ray's direction (subnormal components flushed, as the kernels do).
        let prepared = PreparedRay::new(ray);
        let (org, dir) = (prepared.org, prepared.dir);
        let space = RaySpace::new(dir);
        self.tree.trace(ray, 0.0, query, |r, _, n, best, c| {
            self.visit_leaf(r, (org, dir, &space), ray.t_min, n, best, c, query)
        })
    }

    /// Traces every ray in parallel (see [`CurveBvh::trace`]).
    pub fn trace_rays(&self, rays: &[Ray], query: Query) -> Vec<Hit> {
        let times = vec![0.0; rays.len()];
        trace_all(rays, &times, |r, _| self.trace(r, query).0)
    }

    /// The boxes the tree was built over, by primitive id.
    fn prim_boxes(triangles: &[Triangle], curves: &Curves) -> Vec<Aabb> {
        (triangles.iter().map(triangle_box))
            .chain((0..curves.len()).map(|s| curves.segment_box(s)))
            .collect()
    }

    /// The closest hit of testing every primitive in id order with the walk's tests and
    /// hit rule (each segment asked for its first hit up to the best so far): what every
    /// walk of this tree must return for a closest-hit query, and hit or miss alike for an
    /// any-hit one.
    pub fn brute_force(&self, ray: &Ray) -> Hit {
        if !ray.is_valid() {
            return untraced(ray);
        }
        let r = PreparedRay::new(ray);
        let space = RaySpace::new(r.dir);
        let mut best = Best::start(ray);
        for prim in 0..(self.triangles.len() + self.curves.len()) as u32 {
            self.test_prim(prim, &r, (r.org, r.dir, &space), ray.t_min, &mut best);
        }
        best.into_hit()
    }

    /// Primitive `prim`'s box (a triangle's corners, or [`Curves::segment_box`]): the
    /// box the tree was built over.
    pub fn prim_box(&self, prim: u32) -> Aabb {
        match self.segment_of(prim) {
            None => triangle_box(&self.triangles[prim as usize]),
            Some(s) => self.curves.segment_box(s),
        }
    }

    /// Tests primitive `prim` (a triangle or a segment; below
    /// `triangle_count() + curves().len()`) against `ray` with the walk's own test,
    /// offering its hit to `best` under the hit rule; true when it was taken. A walk over
    /// another layout of this tree (bvhtrace-cpu) that tests every primitive the tree's
    /// walk tests, each at its best so far, returns the same closest hit.
    #[inline]
    pub fn test(&self, prim: u32, ray: &CurveRay, best: &mut Best) -> bool {
        let r = &ray.prepared;
        match &ray.space {
            Some(space) => self.test_prim(prim, r, (r.org, r.dir, space), ray.t_min, best),
            // Made where it is read: only flat segments read it.
            None => {
                let space = RaySpace::new(r.dir);
                self.test_prim(prim, r, (r.org, r.dir, &space), ray.t_min, best)
            }
        }
    }

    /// Prepares `ray` for [`CurveBvh::test`] on this tree's primitives: as
    /// [`CurveRay::new`], less what they do not read.
    pub fn prepare(&self, ray: &Ray) -> CurveRay {
        let prepared = PreparedRay::new(ray);
        CurveRay {
            space: (self.curves.kind == CurveKind::FlatLinear).then(|| RaySpace::new(prepared.dir)),
            prepared,
            t_min: ray.t_min,
        }
    }

    /// Tests a leaf's primitives; true when one was taken (an any-hit walk stops at the
    /// first, as the kernels do).
    #[allow(clippy::too_many_arguments)]
    fn visit_leaf(
        &self,
        r: &PreparedRay,
        ray: (Vec3, Vec3, &RaySpace),
        t_min: f32,
        n: &FlatNode,
        best: &mut Best,
        c: &mut Counters,
        query: Query,
    ) -> bool {
        let first = n.right_or_first as usize;
        let mut taken = false;
        for &prim in &self.order[first..first + n.count() as usize] {
            c.tris += 1;
            taken |= self.test_prim(prim, r, ray, t_min, best);
            if taken && query == Query::Any {
                break;
            }
        }
        taken
    }

    /// Tests primitive `prim` (a triangle or a segment), offering its hit to `best`; true
    /// when it was taken.
    fn test_prim(
        &self,
        prim: u32,
        r: &PreparedRay,
        ray: (Vec3, Vec3, &RaySpace),
        t_min: f32,
        best: &mut Best,
    ) -> bool {
        match self.segment_of(prim) {
            None => {
                let t = &self.triangles[prim as usize];
                intersect_triangle(r, t[0], t[1], t[2])
                    .is_some_and(|h| best.offer(h.t, prim, h.u, h.v))
            }
            Some(s) => (self.curves.intersect(s, ray, (t_min, best.t)))
                .is_some_and(|h| best.offer(h.t, prim, h.u, 0.0)),
        }
    }

    /// The geometric normal at `hit` (a hit of `ray` this tree returned), unit length: a
    /// triangle's, a round curve's surface normal, or the side of a flat curve that
    /// faces the ray.
    pub fn normal(&self, hit: &Hit, ray: &Ray) -> Vec3 {
        let dir = Vec3::from(ray.dir);
        let n = match self.segment_of(hit.prim) {
            None => self
                .triangles
                .get(hit.prim as usize)
                .map_or(-dir, |t| (t[1] - t[0]).cross(t[2] - t[0])),
            // The segment's own first hit up to the tree's is the tree's hit.
            Some(s) => {
                let org = Vec3::from(ray.origin);
                let space = RaySpace::new(dir);
                let ray = (org, dir, &space);
                (self.curves.intersect(s, ray, (ray_t_min(hit), hit.t))).map_or(-dir, |h| h.normal)
            }
        };
        n.normalize_or(-dir.normalize_or_zero())
    }

    /// A triangle through the hit point in the surface's tangent plane, for shading code
    /// that takes triangles: its normal is [`CurveBvh::normal`]'s, and its point at the
    /// barycentric weights `(hit.u, hit.v)` is the hit point. A triangle's hit gives the
    /// triangle itself.
    pub fn shading_triangle(&self, hit: &Hit, ray: &Ray) -> Triangle {
        if self.segment_of(hit.prim).is_none() {
            return self.triangles[hit.prim as usize];
        }
        let n = self.normal(hit, ray);
        let p = Vec3::from(ray.origin) + hit.t * Vec3::from(ray.dir);
        let a = n.any_orthonormal_vector();
        let b = n.cross(a);
        let c0 = p - hit.u * a - hit.v * b;
        [c0, c0 + a, c0 + b]
    }
}

/// The box around a triangle's corners.
fn triangle_box(t: &Triangle) -> Aabb {
    t.iter()
        .fold(Aabb::EMPTY, |b, &p| b.union(&Aabb::from_point(p)))
}

/// A ray made ready for [`CurveBvh::test`]: what a walk computes once per ray (the
/// prepared ray, and the frame flat segments are seen in).
#[derive(Clone, Copy, Debug)]
pub struct CurveRay {
    prepared: PreparedRay,
    /// The frame flat segments are seen in; `None` where the tree has none.
    space: Option<RaySpace>,
    t_min: f32,
}

impl CurveRay {
    /// Prepares `ray` as [`CurveBvh::trace`] does.
    pub fn new(ray: &Ray) -> CurveRay {
        let prepared = PreparedRay::new(ray);
        CurveRay {
            space: Some(RaySpace::new(prepared.dir)),
            prepared,
            t_min: ray.t_min,
        }
    }

    /// The prepared ray, for box tests ([`crate::intersect::intersect_box`]).
    pub fn prepared(&self) -> &PreparedRay {
        &self.prepared
    }
}

/// The start of the interval to look again for a curve hit's normal: a little before it.
fn ray_t_min(hit: &Hit) -> f32 {
    hit.t - hit.t.abs() * 1e-3
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(origin: [f32; 3], dir: [f32; 3]) -> Ray {
        Ray {
            origin,
            t_min: 0.0,
            dir,
            t_max: f32::INFINITY,
        }
    }

    fn one(kind: CurveKind, points: Vec<Vec4>) -> CurveBvh {
        let curves = Curves {
            kind,
            segments: (0..(points.len() - kind.degree()) as u32)
                .step_by(kind.degree())
                .collect(),
            points,
        };
        CurveBvh::build(&[], curves, &BuildOptions::default()).unwrap()
    }

    #[test]
    fn a_round_segment_is_hit_at_its_radius() {
        // Along x from -1 to 1, radius 0.25; a ray down -z at x = 0.3 meets it at z = 0.25.
        let bvh = one(
            CurveKind::RoundLinear,
            vec![
                Vec4::new(-1.0, 0.0, 0.0, 0.25),
                Vec4::new(1.0, 0.0, 0.0, 0.25),
            ],
        );
        let r = ray([0.3, 0.0, 5.0], [0.0, 0.0, -1.0]);
        let (h, _) = bvh.trace(&r, Query::Closest);
        assert_eq!(h.prim, 0);
        assert!((h.t - 4.75).abs() < 1e-5, "{h:?}");
        assert!((h.u - 0.65).abs() < 1e-5, "{h:?}");
        assert!(bvh.normal(&h, &r).abs_diff_eq(Vec3::Z, 1e-5));
        // The end spheres: past x = 1 the ray meets the sphere at (1, 0, 0).
        let (h, _) = bvh.trace(&ray([1.2, 0.0, 5.0], [0.0, 0.0, -1.0]), Query::Closest);
        assert!(
            (h.t - (5.0 - (0.25f32 * 0.25 - 0.04).sqrt())).abs() < 1e-5,
            "{h:?}"
        );
        assert_eq!(h.u, 1.0);
        let (h, _) = bvh.trace(&ray([0.0, 0.3, 5.0], [0.0, 0.0, -1.0]), Query::Closest);
        assert!(!h.is_hit());
    }

    #[test]
    fn a_flat_segment_faces_the_ray() {
        let bvh = one(
            CurveKind::FlatLinear,
            vec![
                Vec4::new(-1.0, 0.0, 0.0, 0.25),
                Vec4::new(1.0, 0.0, 0.0, 0.25),
            ],
        );
        let r = ray([0.5, 0.2, 5.0], [0.0, 0.0, -2.0]);
        let (h, _) = bvh.trace(&r, Query::Closest);
        assert!((h.t - 2.5).abs() < 1e-6, "{h:?}");
        assert!((h.u - 0.75).abs() < 1e-6, "{h:?}");
        assert!(bvh.normal(&h, &r).abs_diff_eq(Vec3::Z, 1e-6));
        let (h, _) = bvh.trace(&ray([0.5, 0.3, 5.0], [0.0, 0.0, -1.0]), Query::Closest);
        assert!(!h.is_hit());
    }

    #[test]
    fn a_straight_cubic_is_a_tube() {
        // A Bezier along x with its control points evenly spaced: a cylinder of radius
        // 0.25, open at its ends.
        let pts = [-1.5f32, -0.5, 0.5, 1.5].map(|x| Vec4::new(x, 0.0, 0.0, 0.25));
        for kind in [CurveKind::RoundBezier, CurveKind::RoundBSpline] {
            let bvh = one(kind, pts.to_vec());
            let r = ray([0.1, 0.15, 5.0], [0.0, 0.0, -1.0]);
            let (h, _) = bvh.trace(&r, Query::Closest);
            let z = (0.25f32 * 0.25 - 0.15 * 0.15).sqrt();
            assert!((h.t - (5.0 - z)).abs() < 1e-4, "{kind:?} {h:?}");
            let n = bvh.normal(&h, &r);
            assert!(n.abs_diff_eq(Vec3::new(0.0, 0.15, z) / 0.25, 1e-3), "{n}");
            let (h, _) = bvh.trace(&ray([0.1, 0.26, 5.0], [0.0, 0.0, -1.0]), Query::Closest);
            assert!(!h.is_hit(), "{kind:?} {h:?}");
        }
    }

    #[test]
    fn bad_curves_are_refused_by_name() {
        let good = Vec4::new(0.0, 0.0, 0.0, 0.1);
        let bad = |points: Vec<Vec4>, segments: Vec<u32>| {
            let c = Curves {
                kind: CurveKind::RoundBezier,
                points,
                segments,
            };
            CurveBvh::build(&[], c, &BuildOptions::default()).unwrap_err()
        };
        let nan = Vec4::new(0.0, f32::NAN, 0.0, 0.1);
        assert!(matches!(
            bad(vec![good, nan, good, good], vec![0]),
            CurveError::BadPoint { point: 1, .. }
        ));
        let e = bad(vec![good; 4], vec![0, 1]);
        assert!(e.to_string().contains("segment 1 starts at point 1"), "{e}");
        let neg = Vec4::new(0.0, 0.0, 0.0, -1.0);
        assert!(matches!(
            bad(vec![good, good, good, neg], vec![0]),
            CurveError::BadPoint { point: 3, .. }
        ));
    }
}
