//! Motion blur: triangles that move during the shutter, and the BVH that bounds them at
//! every time (the node, its build and its walk together).
//!
//! A [`MotionMesh`] holds the same triangles at two or more *time steps*, spread evenly
//! over the shutter `[0, 1]` as Embree's `rtcSetGeometryTimeStepCount` spreads them; between
//! two steps every corner moves in a straight line. A ray carries a time in `[0, 1]` and
//! meets the triangles where they are at that time.
//!
//! [`MotionBvh`] builds one tree over the triangles' boxes merged over the whole shutter,
//! and keeps, for every node, its box at each time step ([`TimeBounds::Linear`], the
//! *linear bounds* of Embree's motion-blur BVHs): a ray at time `t` between steps `s` and
//! `s + 1` tests the box interpolated between the node's boxes at those steps, which holds
//! every corner at `t` because each corner moves linearly within the segment. With
//! [`TimeBounds::Merged`] the walk tests the box over the whole shutter instead, which is
//! smaller in memory and looser for every ray.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::build::{BuildError, BuildOptions};
use crate::flat::{FlatNode, FlatTriangle};
use crate::geometry::Aabb;
use crate::intersect::{PreparedRay, intersect_triangle};
use crate::mesh::{MeshError, Triangle, validate_triangles};
use crate::ray::{Counters, Hit, Ray};
use crate::traverse::{Best, Query};

mod instances;
pub(crate) mod tree;

pub use instances::{
    InstanceMotionError, MotionInstancedBvh, MovingInstance, MovingInstanceRecord,
    MovingInstancesLayout, invert_rows, rows_of,
};
use tree::TimeTree;

/// Why a motion mesh was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MotionError {
    /// Fewer than two time steps (a mesh that does not move is a [`crate::TriangleMesh`]).
    #[error("a moving mesh needs at least 2 time steps, got {0}")]
    TooFewSteps(usize),
    /// More time steps than [`MAX_TIME_STEPS`] (Embree's limit too).
    #[error("{0} time steps is more than the {MAX_TIME_STEPS} a moving mesh may have")]
    TooManySteps(usize),
    /// A time step has a different number of triangles than the first.
    #[error("time step {step} has {len} triangles, time step 0 has {expected}")]
    StepLength {
        /// The step at fault.
        step: usize,
        /// Its triangle count.
        len: usize,
        /// Step 0's triangle count.
        expected: usize,
    },
    /// A triangle of a step is bad (a non-finite corner), or there are too many.
    #[error("time step {step}: {error}")]
    Step {
        /// The step at fault.
        step: usize,
        /// What is wrong with it.
        error: MeshError,
    },
}

/// The most time steps a moving mesh may have (Embree's `RTC_MAX_TIME_STEP_COUNT`).
pub const MAX_TIME_STEPS: usize = 129;

/// Where a time falls among `steps` evenly spaced time steps: the segment `s` (between
/// steps `s` and `s + 1`) and the fraction `f` of the way through it. Embree's
/// `getTimeSegment`: `t * (steps - 1)`, its floor clamped to a segment, the rest. The time
/// is clamped to `[0, 1]` first, so a time outside the shutter sees the mesh at its end.
#[inline(always)]
pub fn time_segment(time: f32, steps: usize) -> (usize, f32) {
    let segments = (steps - 1) as f32;
    let scaled = time.clamp(0.0, 1.0) * segments;
    let s = scaled.floor().clamp(0.0, segments - 1.0);
    (s as usize, scaled - s)
}

/// The point `f` of the way from `a` to `b` (`(1 - f) a + f b`), kept inside the box of the
/// two, so a corner between two steps never leaves the boxes that bound it there.
#[inline(always)]
pub fn lerp_point(a: Vec3, b: Vec3, f: f32) -> Vec3 {
    ((1.0 - f) * a + f * b).clamp(a.min(b), a.max(b))
}

/// A triangle `f` of the way from `a` to `b`, corner by corner ([`lerp_point`]).
#[inline(always)]
pub fn lerp_triangle(a: &Triangle, b: &Triangle, f: f32) -> Triangle {
    [0, 1, 2].map(|k| lerp_point(a[k], b[k], f))
}

/// The box `f` of the way from `a` to `b`, widened to hold every point [`lerp_point`] gives
/// for corners inside `a` and `b`: the rounding of both interpolations is below
/// `3 * 2^-24` of the largest coordinate involved, and the box grows by `2^-20` of it.
#[inline(always)]
pub fn lerp_box(a: &Aabb, b: &Aabb, f: f32) -> Aabb {
    let g = 1.0 - f;
    let scale = a
        .min
        .abs()
        .max(a.max.abs())
        .max(b.min.abs().max(b.max.abs()));
    let slack = scale * (1.0 / (1 << 20) as f32);
    Aabb {
        min: g * a.min + f * b.min - slack,
        max: g * a.max + f * b.max + slack,
    }
}

/// Triangles at two or more time steps, spread evenly over the shutter `[0, 1]`; the same
/// triangles in the same order at every step.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionMesh {
    steps: Vec<Vec<Triangle>>,
}

impl MotionMesh {
    /// The mesh whose triangles are `steps[k]` at time `k / (steps.len() - 1)`. Refuses
    /// fewer than two steps, steps of different lengths, and non-finite corners (naming
    /// the step and the triangle).
    pub fn new(steps: Vec<Vec<Triangle>>) -> Result<MotionMesh, MotionError> {
        if steps.len() < 2 {
            return Err(MotionError::TooFewSteps(steps.len()));
        }
        if steps.len() > MAX_TIME_STEPS {
            return Err(MotionError::TooManySteps(steps.len()));
        }
        let expected = steps[0].len();
        for (step, tris) in steps.iter().enumerate() {
            if tris.len() != expected {
                return Err(MotionError::StepLength {
                    step,
                    len: tris.len(),
                    expected,
                });
            }
            validate_triangles(tris).map_err(|error| MotionError::Step { step, error })?;
        }
        Ok(MotionMesh { steps })
    }

    /// Number of time steps (at least 2).
    pub fn time_steps(&self) -> usize {
        self.steps.len()
    }

    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.steps[0].len()
    }

    /// True when there are no triangles.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The triangles at time step `k`.
    pub fn step(&self, k: usize) -> &[Triangle] {
        &self.steps[k]
    }

    /// Triangle `prim` at `time`, as the walks see it.
    pub fn triangle_at(&self, prim: usize, time: f32) -> Triangle {
        let (s, f) = time_segment(time, self.steps.len());
        lerp_triangle(&self.steps[s][prim], &self.steps[s + 1][prim], f)
    }

    /// Every triangle at `time`, as the walks see them (what the f64 oracle judges a
    /// ray at that time against).
    pub fn at(&self, time: f32) -> Vec<Triangle> {
        (0..self.len()).map(|i| self.triangle_at(i, time)).collect()
    }
}

/// How a node of a [`MotionBvh`] bounds its triangles in time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum TimeBounds {
    /// A box per time step, interpolated at the ray's time (Embree's linear bounds).
    #[default]
    Linear,
    /// One box over the whole shutter.
    Merged,
}

/// A node's box at one time step. GPU layout: WGSL `BvhMotionBox` in
/// `shaders/bvh_motion_buffers.wgsl` (32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MotionBox {
    /// The lower corner.
    pub min: [f32; 3],
    /// Padding to 16 bytes (zero).
    pub _pad0: u32,
    /// The upper corner.
    pub max: [f32; 3],
    /// Padding to 16 bytes (zero).
    pub _pad1: u32,
}

impl MotionBox {
    pub(crate) fn of(b: &Aabb) -> MotionBox {
        MotionBox {
            min: b.min.to_array(),
            max: b.max.to_array(),
            ..MotionBox::default()
        }
    }

    /// The box as an [`Aabb`].
    #[inline(always)]
    pub fn aabb(&self) -> Aabb {
        Aabb {
            min: Vec3::from(self.min),
            max: Vec3::from(self.max),
        }
    }
}

/// A BVH over a [`MotionMesh`]: the binary layout's nodes ([`FlatNode`], each box over the
/// whole shutter), each node's box at every time step, and the triangles at every step in
/// leaf order. The kernels read these arrays as they are (`bvh_motion_buffers.wgsl`).
#[derive(Clone, Debug)]
pub struct MotionBvh {
    tree: TimeTree,
    /// Leaf order's triangle `j` at step `k`: `tris[k * n + j]`, each with its input id.
    tris: Vec<FlatTriangle>,
    /// Triangles per step.
    count: usize,
}

impl MotionBvh {
    /// Builds the tree over the triangles' boxes merged over the shutter with `opts`
    /// (the SBVH builds binned SAH here: its splits clip static triangles), and bounds
    /// each node in time as `bounds` says.
    pub fn build(
        mesh: &MotionMesh,
        opts: &BuildOptions,
        bounds: TimeBounds,
    ) -> Result<MotionBvh, BuildError> {
        let steps = mesh.time_steps();
        let boxes: Vec<Aabb> = (0..mesh.len())
            .flat_map(|p| (0..steps).map(move |k| Aabb::from_triangle(&mesh.step(k)[p])))
            .collect();
        let (tree, order) = TimeTree::build(&boxes, steps, opts, bounds)?;
        let mut tris = Vec::with_capacity(steps * order.len());
        for k in 0..steps {
            let step = mesh.step(k);
            tris.extend(order.iter().map(|&p| {
                let [v0, v1, v2] = step[p as usize].map(|v| v.to_array());
                FlatTriangle {
                    v0,
                    prim: p,
                    v1,
                    v2,
                    ..FlatTriangle::zeroed()
                }
            }));
        }
        Ok(MotionBvh {
            tree,
            tris,
            count: order.len(),
        })
    }

    /// Number of time steps.
    pub fn time_steps(&self) -> usize {
        self.tree.steps
    }

    /// How the nodes bound time.
    pub fn time_bounds(&self) -> TimeBounds {
        self.tree.bounds
    }

    /// The nodes (depth first; each box over the whole shutter).
    pub fn nodes(&self) -> &[FlatNode] {
        &self.tree.nodes
    }

    /// Levels from the root to the deepest leaf (a lone leaf is 1).
    pub fn depth(&self) -> u32 {
        self.tree.depth
    }

    /// The box around every triangle over the whole shutter.
    pub fn bounds(&self) -> Aabb {
        self.tree.nodes[0].aabb()
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.count
    }

    /// Each node's box at every time step: node `i`'s at step `k` is entry
    /// `i * time_steps() + k` (empty with [`TimeBounds::Merged`]).
    pub fn step_boxes(&self) -> &[MotionBox] {
        &self.tree.step_boxes
    }

    /// The triangles in leaf order at every time step: step `k`'s are entries
    /// `k * triangle_count()..(k + 1) * triangle_count()`.
    pub fn triangles(&self) -> &[FlatTriangle] {
        &self.tris
    }

    /// Bytes the walk reads: nodes, per-step boxes and triangles at every step.
    pub fn byte_size(&self) -> usize {
        self.tree.byte_size() + self.tris.len() * std::mem::size_of::<FlatTriangle>()
    }

    /// Traces one ray at `time` (clamped to `[0, 1]`; a NaN time is an invalid ray):
    /// the closest hit (the walks' hit rule) or any hit, with the boxes and triangles it
    /// tested.
    pub fn trace(&self, ray: &Ray, time: f32, query: Query) -> (Hit, Counters) {
        self.tree.trace(ray, time, query, |r, seg, n, best, c| {
            self.visit_leaf(r, n, seg, best, c, query == Query::Any)
        })
    }

    /// Traces `rays[i]` at `times[i]` in parallel (see [`MotionBvh::trace`]).
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace_rays(&self, rays: &[Ray], times: &[f32], query: Query) -> Vec<Hit> {
        tree::trace_all(rays, times, |r, t| self.trace(r, t, query).0)
    }

    /// Tests a leaf's triangles at the ray's time; true when one was taken (an any-hit
    /// walk, `any`, stops at the first, as the kernels do).
    fn visit_leaf(
        &self,
        r: &PreparedRay,
        n: &FlatNode,
        (s, f): (usize, f32),
        best: &mut Best,
        c: &mut Counters,
        any: bool,
    ) -> bool {
        let len = self.count;
        let first = n.right_or_first as usize;
        let mut taken = false;
        for j in first..first + n.count() as usize {
            c.tris += 1;
            let (a, b) = (&self.tris[s * len + j], &self.tris[(s + 1) * len + j]);
            let tri = lerp_triangle(&a.corners(), &b.corners(), f);
            // `offer` takes only hits nearer than the best, which starts at `t_max`.
            if let Some(h) = intersect_triangle(r, tri[0], tri[1], tri[2]) {
                taken |= best.offer(h.t, a.prim, h.u, h.v);
            }
            if taken && any {
                break;
            }
        }
        taken
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_segments_are_embrees() {
        assert_eq!(time_segment(0.0, 2), (0, 0.0));
        assert_eq!(time_segment(1.0, 2), (0, 1.0));
        assert_eq!(time_segment(0.5, 3), (1, 0.0));
        assert_eq!(time_segment(1.0, 3), (1, 1.0));
        assert_eq!(time_segment(0.75, 3), (1, 0.5));
        assert_eq!(time_segment(-1.0, 3), (0, 0.0));
        assert_eq!(time_segment(2.0, 5), (3, 1.0));
    }

    #[test]
    fn interpolated_boxes_hold_interpolated_points() {
        // Coordinates of mixed sign and magnitude, where the interpolation cancels.
        let pts = [
            (Vec3::new(-1.0e4, 3.0, 0.1), Vec3::new(1.0e4, -3.0, 7.0e-3)),
            (Vec3::new(0.3, 1.0e-6, -2.0), Vec3::new(-0.7, 5.0e5, 2.0)),
        ];
        let a = Aabb::from_point(pts[0].0).union(&Aabb::from_point(pts[1].0));
        let b = Aabb::from_point(pts[0].1).union(&Aabb::from_point(pts[1].1));
        for i in 0..=1000 {
            let f = i as f32 / 1000.0;
            let bx = lerp_box(&a, &b, f);
            for (p, q) in pts {
                let x = lerp_point(p, q, f);
                assert!(
                    bx.min.cmple(x).all() && x.cmple(bx.max).all(),
                    "{f}: {x} {bx:?}"
                );
            }
        }
    }
}
