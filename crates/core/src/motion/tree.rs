//! The tree both moving layouts share: a binary tree built over its primitives' boxes
//! merged over the shutter, each node's box at every time step, and its full-stack walk
//! with the leaves left to the layout (triangles, or moving instances).

use crate::build::{BuildError, BuildNode, BuildOptions, build_boxes};
use crate::flat::{FlatNode, MAX_PRIMITIVES};
use crate::geometry::Aabb;
use crate::intersect::{PreparedRay, intersect_box};
use crate::mesh::MeshError;
use crate::ray::{Counters, Hit, Ray};
use crate::traverse::{Best, Query, untraced};

use super::{MotionBox, TimeBounds, lerp_box, time_segment};

/// `trace(rays[i], times[i])` for every ray, in parallel.
///
/// # Panics
/// When the two slices differ in length.
pub(crate) fn trace_all(
    rays: &[Ray],
    times: &[f32],
    trace: impl Fn(&Ray, f32) -> Hit + Sync,
) -> Vec<Hit> {
    use rayon::prelude::*;
    assert_eq!(rays.len(), times.len(), "one time per ray");
    rays.par_iter()
        .zip(times)
        .with_min_len(64)
        .map(|(r, &t)| trace(r, t))
        .collect()
}

/// Nodes, and each node's box at every time step (see [`super::MotionBvh`]).
#[derive(Clone, Debug)]
pub(crate) struct TimeTree {
    pub nodes: Vec<FlatNode>,
    /// Node `i`'s box at step `k`: `step_boxes[i * steps + k]`; empty with
    /// [`TimeBounds::Merged`].
    pub step_boxes: Vec<MotionBox>,
    pub steps: usize,
    pub bounds: TimeBounds,
    pub depth: u32,
}

impl TimeTree {
    /// Builds the tree over primitives whose box at step `k` is `boxes[p * steps + k]`;
    /// returns it with the primitives in leaf order (its leaves index that order).
    /// With one step the tree is static, and its bounds must be [`TimeBounds::Merged`].
    pub fn build(
        boxes: &[Aabb],
        steps: usize,
        opts: &BuildOptions,
        bounds: TimeBounds,
    ) -> Result<(TimeTree, Vec<u32>), BuildError> {
        let n = boxes.len() / steps;
        if n > MAX_PRIMITIVES {
            return Err(MeshError::TooMany(n).into());
        }
        let merged: Vec<Aabb> = boxes
            .chunks(steps)
            .map(|b| b.iter().fold(Aabb::EMPTY, |m, x| m.union(x)))
            .collect();
        let built = build_boxes(&merged, opts)?;
        let mut tree = TimeTree {
            nodes: Vec::with_capacity(built.node_count),
            step_boxes: Vec::new(),
            steps,
            bounds,
            depth: 0,
        };
        let leaf_box = |first: u32, count: u32, k: usize| {
            let leaf = &built.prim_order[first as usize..(first + count) as usize];
            leaf.iter()
                .fold(Aabb::EMPTY, |b, &p| b.union(&boxes[p as usize * steps + k]))
        };
        let mut per_node = Vec::with_capacity(built.node_count);
        tree.depth = tree.lay_out(&built.root, 1, &leaf_box, &mut per_node);
        if bounds == TimeBounds::Linear {
            tree.step_boxes = per_node.iter().flatten().map(MotionBox::of).collect();
        }
        Ok((tree, built.prim_order))
    }

    /// Lays `node` out depth first (first child next), with its boxes at every step in
    /// `per_node`; returns the subtree's depth counted from `level`.
    fn lay_out(
        &mut self,
        node: &BuildNode,
        level: u32,
        leaf_box: &impl Fn(u32, u32, usize) -> Aabb,
        per_node: &mut Vec<Vec<Aabb>>,
    ) -> u32 {
        let index = self.nodes.len();
        self.nodes.push(FlatNode {
            min: node.bounds().min.to_array(),
            right_or_first: 0,
            max: node.bounds().max.to_array(),
            meta: 0,
        });
        per_node.push(Vec::new());
        let (meta, right_or_first, boxes, depth) = match node {
            BuildNode::Leaf { first, count, .. } => {
                let boxes = (0..self.steps).map(|k| leaf_box(*first, *count, k));
                (count << 2, *first, boxes.collect(), level)
            }
            BuildNode::Interior { axis, children, .. } => {
                let dl = self.lay_out(&children[0], level + 1, leaf_box, per_node);
                let right = self.nodes.len();
                let dr = self.lay_out(&children[1], level + 1, leaf_box, per_node);
                let (l, r) = (&per_node[index + 1], &per_node[right]);
                let boxes = l.iter().zip(r).map(|(a, b)| a.union(b)).collect();
                (*axis as u32, right as u32, boxes, dl.max(dr))
            }
        };
        let n = &mut self.nodes[index];
        (n.meta, n.right_or_first) = (meta, right_or_first);
        per_node[index] = boxes;
        depth
    }

    /// Bytes of the nodes and their step boxes.
    pub fn byte_size(&self) -> usize {
        use std::mem::size_of;
        self.nodes.len() * size_of::<FlatNode>() + self.step_boxes.len() * size_of::<MotionBox>()
    }

    /// Node `i`'s box at the time of `segment` (`(s, f)` from [`super::time_segment`]).
    #[inline(always)]
    pub fn node_box(&self, i: usize, (s, f): (usize, f32)) -> Aabb {
        match self.bounds {
            TimeBounds::Linear => {
                let b = &self.step_boxes[i * self.steps + s..];
                lerp_box(&b[0].aabb(), &b[1].aabb(), f)
            }
            TimeBounds::Merged => self.nodes[i].aabb(),
        }
    }

    /// Traces one ray at `time` (clamped to `[0, 1]`; a NaN time is an invalid ray): the
    /// closest hit (the walks' hit rule) or any hit of the primitives `leaf` tests (for the
    /// prepared ray at its time segment, offering hits to the best; true when it took
    /// one), with the boxes and primitives tested.
    pub fn trace(
        &self,
        ray: &Ray,
        time: f32,
        query: Query,
        leaf: impl Fn(&PreparedRay, (usize, f32), &FlatNode, &mut Best, &mut Counters) -> bool,
    ) -> (Hit, Counters) {
        if !ray.is_valid() || time.is_nan() {
            return (untraced(ray), Counters::default());
        }
        // One step is a static tree (curves): every time is its only step.
        let seg = match self.steps {
            1 => (0, 0.0),
            steps => time_segment(time, steps),
        };
        let r = PreparedRay::new(ray);
        let mut best = Best::start(ray);
        let mut c = Counters::default();
        self.walk(&r, seg, &mut best, &mut c, query, |n, best, c| {
            leaf(&r, seg, n, best, c)
        });
        (best.into_hit(), c)
    }

    /// The full-stack walk at the time of `seg`: the nearer child first (by entry
    /// distance), the other pushed; `leaf` tests a leaf's primitives and says whether it
    /// took a hit (an any-hit walk then stops).
    fn walk(
        &self,
        r: &PreparedRay,
        seg: (usize, f32),
        best: &mut Best,
        c: &mut Counters,
        query: Query,
        mut leaf: impl FnMut(&FlatNode, &mut Best, &mut Counters) -> bool,
    ) {
        // At most one entry per level: on the stack for the usual depths, no allocation.
        let mut small = [0u32; 64];
        let mut deep = Vec::new();
        let stack: &mut [u32] = match self.depth as usize {
            d if d <= small.len() => &mut small,
            d => {
                deep.resize(d, 0);
                &mut deep
            }
        };
        let mut sp = 0usize;
        let hit_box = |i: u32, t_best: f32| {
            let b = self.node_box(i as usize, seg);
            intersect_box(r, b.min, b.max, t_best)
        };
        c.nodes += 1;
        let mut node = hit_box(0, best.t).map(|_| 0u32);
        while let Some(i) = node.or_else(|| {
            sp = sp.checked_sub(1)?;
            Some(stack[sp])
        }) {
            let n = &self.nodes[i as usize];
            node = None;
            if n.is_leaf() {
                if leaf(n, best, c) && query == Query::Any {
                    break;
                }
                continue;
            }
            let (l, rt) = (i + 1, n.right_or_first);
            c.nodes += 2;
            match (hit_box(l, best.t), hit_box(rt, best.t)) {
                (Some(tl), Some(tr)) => {
                    let (near, far) = if tr < tl { (rt, l) } else { (l, rt) };
                    stack[sp] = far;
                    sp += 1;
                    node = Some(near);
                }
                (Some(_), None) => node = Some(l),
                (None, Some(_)) => node = Some(rt),
                (None, None) => {}
            }
        }
    }
}
