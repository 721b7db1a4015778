//! Builders: from triangles to a [`BuildTree`] (a plain binary tree over a primitive
//! permutation). [`crate::flat`] then lays that tree out for traversal.
//!
//! All builders share one recursion and differ only in how they choose a split
//! ([`BuilderKind`]). The recursion forks with `rayon::join` above a size threshold;
//! every choice depends only on the primitives of the node, so the tree is the same
//! whatever the thread count.

mod binned;
mod recursion;
pub mod reinsert;
mod sbvh;
mod small;
mod sweep;

use std::fmt;
use std::str::FromStr;

use glam::{BVec4A, Mat3A, Vec3, Vec3A, Vec4};

use crate::flat::{FlatBvh, FlatNode};
use crate::geometry::Aabb;
use crate::mesh::{MeshError, Triangle, validate_triangles};

/// Which split strategy to build with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum BuilderKind {
    /// Binned SAH (the default).
    #[default]
    Sah,
    /// Full sweep SAH over sorted centroids: slower to build, the best SAH.
    SweepSah,
    /// Split at the median centroid of the widest centroid axis (`select_nth_unstable`).
    Median,
    /// Split at the middle of the widest centroid range.
    Midpoint,
    /// Spatial-split BVH (Stich et al. 2009): binned SAH over references that may be
    /// clipped at a split plane, so that a triangle can sit in several leaves (at most
    /// `split_budget` more references than triangles). The lowest SAH on scenes with large
    /// or long triangles; slower to build. Over boxes ([`build_boxes`]) it is binned SAH.
    Sbvh,
}

impl BuilderKind {
    /// Every builder, in the order reports list them.
    pub const ALL: [BuilderKind; 5] = [
        BuilderKind::Sah,
        BuilderKind::SweepSah,
        BuilderKind::Median,
        BuilderKind::Midpoint,
        BuilderKind::Sbvh,
    ];

    /// The name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            BuilderKind::Sah => "sah",
            BuilderKind::SweepSah => "sweep-sah",
            BuilderKind::Median => "median",
            BuilderKind::Midpoint => "midpoint",
            BuilderKind::Sbvh => "sbvh",
        }
    }
}

impl fmt::Display for BuilderKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for BuilderKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        BuilderKind::ALL
            .into_iter()
            .find(|b| b.name() == s)
            .ok_or_else(|| {
                format!("unknown builder '{s}' (expected sah, sweep-sah, median, midpoint or sbvh)")
            })
    }
}

/// Build settings. `Default` gives binned SAH with PBRT's costs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildOptions {
    /// Split strategy.
    pub builder: BuilderKind,
    /// Bins per axis for [`BuilderKind::Sah`] (2..=256).
    pub bins: usize,
    /// SAH cost of one traversal step, relative to `cost_intersection` (PBRT: 1/8).
    pub cost_traversal: f32,
    /// SAH cost of one triangle test (PBRT: 1).
    pub cost_intersection: f32,
    /// Nodes with more primitives than this are always split.
    pub max_leaf_size: usize,
    /// Below this depth the chosen strategy decides; at it and beyond, nodes are split at
    /// their object median, so depth stays under `max_depth + log2(n)` on any input.
    pub max_depth: usize,
    /// Nodes with at least this many primitives build their two children in parallel.
    pub parallel_threshold: usize,
    /// Optimise the built tree by reinsertion ([`reinsert`]: Bittner et al. 2013), which
    /// lowers its SAH cost at some build time; off by default.
    pub optimize: bool,
    /// [`BuilderKind::Sbvh`] only: how many references beyond one per triangle spatial
    /// splits may add, as a fraction of the triangle count (0..=16; 0.3 by default, as
    /// Embree and tinybvh allow about). The reference array is allocated once at
    /// `(1 + split_budget) n` and never grows.
    pub split_budget: f32,
}

impl Default for BuildOptions {
    fn default() -> Self {
        BuildOptions {
            builder: BuilderKind::Sah,
            bins: 32,
            cost_traversal: 0.125,
            cost_intersection: 1.0,
            max_leaf_size: 8,
            max_depth: 64,
            parallel_threshold: 4096,
            optimize: false,
            split_budget: 0.3,
        }
    }
}

impl BuildOptions {
    /// Checks that every option is in range (what [`build`] checks first).
    pub fn validate(&self) -> Result<(), BuildError> {
        if !(2..=256).contains(&self.bins) {
            return Err(BuildError::Options(format!(
                "bins must be in 2..=256, got {}",
                self.bins
            )));
        }
        if self.max_leaf_size == 0 {
            return Err(BuildError::Options(
                "max_leaf_size must be at least 1".into(),
            ));
        }
        if !(self.cost_traversal >= 0.0 && self.cost_intersection > 0.0) {
            return Err(BuildError::Options(
                "costs must be finite, traversal >= 0, intersection > 0".into(),
            ));
        }
        if !(0.0..=16.0).contains(&self.split_budget) {
            return Err(BuildError::Options(format!(
                "split_budget must be in 0..=16, got {}",
                self.split_budget
            )));
        }
        Ok(())
    }

    /// Default options with another builder.
    pub fn with_builder(builder: BuilderKind) -> Self {
        BuildOptions {
            builder,
            ..Default::default()
        }
    }
}

/// A node of the plain build tree.
#[derive(Clone, Debug, PartialEq)]
pub enum BuildNode {
    /// A leaf: `count` primitives starting at `first` in [`BuildTree::prim_order`].
    Leaf {
        /// The box around the leaf's primitives.
        bounds: Aabb,
        /// Index of the leaf's first primitive in [`BuildTree::prim_order`].
        first: u32,
        /// Number of primitives in the leaf.
        count: u32,
    },
    /// An interior node split along `axis` (0, 1, 2).
    Interior {
        /// The box around both children.
        bounds: Aabb,
        /// The split axis: 0 = x, 1 = y, 2 = z.
        axis: u8,
        /// The two children.
        children: Box<[BuildNode; 2]>,
    },
}

impl BuildNode {
    /// The node's box.
    pub fn bounds(&self) -> &Aabb {
        match self {
            BuildNode::Leaf { bounds, .. } | BuildNode::Interior { bounds, .. } => bounds,
        }
    }
}

/// The builder's output: a tree whose leaves index `prim_order`, the input primitives in
/// leaf order, every leaf a contiguous range.
#[derive(Clone, Debug)]
pub struct BuildTree {
    /// The root node.
    pub root: BuildNode,
    /// The input primitives' indices the leaves index into: a permutation, except for
    /// [`BuilderKind::Sbvh`], whose references may name a primitive several times (each
    /// at least once; a leaf's box then holds the part of the triangle in that leaf).
    pub prim_order: Vec<u32>,
    /// Number of nodes (at most `2 r - 1` for `r` references).
    pub node_count: usize,
}

/// Why a build failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BuildError {
    /// The input had a bad primitive.
    #[error(transparent)]
    Mesh(#[from] MeshError),
    /// There was nothing to build over.
    #[error("no triangles to build a BVH over")]
    Empty,
    /// Options out of range.
    #[error("invalid build options: {0}")]
    Options(String),
}

/// What the recursion keeps per primitive: its box and its original index, as two
/// 16-byte vectors (Embree's layout): a ref loads in two aligned moves and never
/// straddles a cache line.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
pub(crate) struct PrimRef {
    /// The box's min corner; the fourth lane holds the index's bits.
    lo: Vec4,
    /// The box's max corner; the fourth lane is 0.
    hi: Vec4,
}

impl PrimRef {
    /// The ref of primitive `index` with box `min`..`max`.
    #[inline(always)]
    pub fn new(min: Vec3, max: Vec3, index: u32) -> PrimRef {
        PrimRef {
            lo: min.extend(f32::from_bits(index)),
            hi: max.extend(0.0),
        }
    }
    /// The box's min corner (the index's lane cleared: as a float it is often subnormal,
    /// which arithmetic on some CPUs takes slow paths for).
    #[inline(always)]
    pub fn min(&self) -> Vec3A {
        Vec3A::from_vec4(Vec4::select(XYZ, self.lo, Vec4::ZERO))
    }
    /// The box's max corner.
    #[inline(always)]
    pub fn max(&self) -> Vec3A {
        Vec3A::from_vec4(self.hi)
    }
    /// The primitive's index in the input.
    #[inline(always)]
    pub fn index(&self) -> u32 {
        self.lo.w.to_bits()
    }
    #[inline(always)]
    pub fn centroid(&self) -> Vec3A {
        (self.min() + self.max()) * 0.5
    }
    #[inline(always)]
    pub fn bounds(&self) -> Aabb {
        Aabb {
            min: self.min().into(),
            max: self.max().into(),
        }
    }
    /// Replaces the box, keeping the index.
    pub fn set_bounds(&mut self, b: &Aabb) {
        *self = PrimRef::new(b.min, b.max, self.index());
    }
}

/// The lanes of a [`PrimRef`] vector that hold its box.
const XYZ: BVec4A = BVec4A::new(true, true, true, false);

/// A chosen split: primitives `[0, mid)` go left after the strategy's partition.
pub(crate) enum Split {
    /// Make this node a leaf.
    Leaf,
    /// The refs have been partitioned; the left child takes `[0, mid)`.
    At { axis: usize, mid: usize },
    /// As `At`, with each child's (bounds, centroid bounds) already known.
    Known {
        axis: usize,
        mid: usize,
        children: [(Aabb, Aabb); 2],
    },
}

/// Node bounds and centroid bounds of a set of refs (parallel for big sets).
pub(crate) fn bounds_of(refs: &[PrimRef], parallel: bool) -> (Aabb, Aabb) {
    let fold = |(mut b, mut c): (Aabb, Aabb), r: &PrimRef| {
        b = b.union(&r.bounds());
        c.grow(r.centroid().into());
        (b, c)
    };
    if parallel && refs.len() >= 32 * 1024 {
        use rayon::prelude::*;
        refs.par_chunks(8 * 1024)
            .map(|ch| ch.iter().fold((Aabb::EMPTY, Aabb::EMPTY), fold))
            .reduce(
                || (Aabb::EMPTY, Aabb::EMPTY),
                |a, b| (a.0.union(&b.0), a.1.union(&b.1)),
            )
    } else {
        refs.iter().fold((Aabb::EMPTY, Aabb::EMPTY), fold)
    }
}

/// Cost, relative to the node, of splitting into two sets (PBRT's SAH).
#[inline]
pub(crate) fn split_cost(
    opts: &BuildOptions,
    node_area: f32,
    n_l: usize,
    a_l: f32,
    n_r: usize,
    a_r: f32,
) -> f32 {
    opts.cost_traversal + opts.cost_intersection * split_weight(n_l, a_l, n_r, a_r) / node_area
}

/// The part of [`split_cost`] that differs between a node's candidate splits: the sweeps
/// compare it, which orders them as the cost does without a division per candidate.
#[inline(always)]
pub(crate) fn split_weight(n_l: usize, a_l: f32, n_r: usize, a_r: f32) -> f32 {
    n_l as f32 * a_l + n_r as f32 * a_r
}

/// A float's bits flipped as `f32::total_cmp` orders it, so that integer order is float
/// order: the sweeps sort centroids on integer keys made of it.
#[inline(always)]
pub(crate) fn ordered_bits(c: f32) -> u32 {
    let b = c.to_bits();
    if b >> 31 == 1 { !b } else { b | 0x8000_0000 }
}

/// Half the surface areas of three boxes, box `i` in lane `i` (`lo[i]` to `hi[i]`): the
/// sweeps grow one box per axis in lock step, and with the extents transposed one
/// multiply gives all three.
#[inline(always)]
pub(crate) fn half_areas(lo: &[Vec3A; 3], hi: &[Vec3A; 3]) -> Vec3A {
    let e = Mat3A::from_cols(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]).transpose();
    let (x, y, z) = (e.x_axis, e.y_axis, e.z_axis);
    x * y + y * z + z * x
}

/// Splits at the object median along `axis` (ties broken by primitive index, so the
/// result is deterministic).
pub(crate) fn median_split(refs: &mut [PrimRef], axis: usize) -> Split {
    let mid = refs.len() / 2;
    refs.select_nth_unstable_by(mid, |a, b| {
        a.centroid()[axis]
            .total_cmp(&b.centroid()[axis])
            .then(a.index().cmp(&b.index()))
    });
    Split::At { axis, mid }
}

/// Splits at the middle of the centroid range; falls back to the median when one side
/// would be empty.
fn midpoint_split(refs: &mut [PrimRef], cb: &Aabb, opts: &BuildOptions, node: &Aabb) -> Split {
    let axis = cb.longest_axis();
    let mid_pos = cb.centroid()[axis];
    let mid = partition(refs, |r| r.centroid()[axis] < mid_pos);
    if mid == 0 || mid == refs.len() {
        return median_split(refs, axis);
    }
    leaf_if_cheaper(refs, axis, mid, opts, node)
}

/// The median split, made a leaf when splitting does not pay.
fn median_builder_split(
    refs: &mut [PrimRef],
    cb: &Aabb,
    opts: &BuildOptions,
    node: &Aabb,
) -> Split {
    let axis = cb.longest_axis();
    match median_split(refs, axis) {
        Split::At { axis, mid } => leaf_if_cheaper(refs, axis, mid, opts, node),
        s => s,
    }
}

/// For the non-SAH builders: a node small enough to be a leaf becomes one when the SAH
/// says the split does not pay.
fn leaf_if_cheaper(
    refs: &[PrimRef],
    axis: usize,
    mid: usize,
    opts: &BuildOptions,
    node: &Aabb,
) -> Split {
    if refs.len() <= opts.max_leaf_size {
        let area_of = |s: &[PrimRef]| {
            s.iter()
                .fold(Aabb::EMPTY, |b, r| b.union(&r.bounds()))
                .surface_area()
        };
        let area = node.surface_area();
        if area > 0.0 {
            let cost = split_cost(
                opts,
                area,
                mid,
                area_of(&refs[..mid]),
                refs.len() - mid,
                area_of(&refs[mid..]),
            );
            if cost >= opts.cost_intersection * refs.len() as f32 {
                return Split::Leaf;
            }
        }
    }
    Split::At { axis, mid }
}

/// In-place partition: elements satisfying `pred` first. Returns the count of those.
pub(crate) fn partition(refs: &mut [PrimRef], pred: impl Fn(&PrimRef) -> bool) -> usize {
    let mut i = 0;
    let mut j = refs.len();
    while i < j {
        if pred(&refs[i]) {
            i += 1;
        } else {
            j -= 1;
            refs.swap(i, j);
        }
    }
    i
}

/// Builds a BVH over triangles (validated first: a NaN or infinite corner is an error
/// naming the triangle).
pub fn build(tris: &[Triangle], opts: &BuildOptions) -> Result<BuildTree, BuildError> {
    if opts.builder == BuilderKind::Sbvh {
        // References change during an SBVH build: it has its own recursion.
        validate_triangles(tris)?;
        return Ok(reinsert::finish(sbvh::build(tris, opts)?, opts));
    }
    let (nodes, prim_order) = build_refs(triangle_refs(tris)?, opts)?;
    Ok(reinsert::finish(tree_of(&nodes.nodes, prim_order), opts))
}

/// Builds a BVH over triangles straight into the flat layout: the tree [`build`] gives,
/// laid out as [`FlatBvh::flatten`] would, without the boxed tree in between.
pub(crate) fn build_flat(tris: &[Triangle], opts: &BuildOptions) -> Result<FlatBvh, BuildError> {
    if opts.optimize || opts.builder == BuilderKind::Sbvh {
        // The optimiser works on the boxed tree, and so does the SBVH.
        return Ok(FlatBvh::flatten(&build(tris, opts)?, tris));
    }
    let (slots, prim_order) = build_refs(triangle_refs(tris)?, opts)?;
    Ok(FlatBvh::from_nodes(
        slots.nodes,
        slots.depth,
        &prim_order,
        tris,
    ))
}

/// Each triangle's ref, the triangles checked on the way ([`validate_triangles`]'s
/// checks): with every corner finite, in one parallel pass; otherwise the sequential
/// check names the first bad triangle.
fn triangle_refs(tris: &[Triangle]) -> Result<Vec<PrimRef>, MeshError> {
    use rayon::prelude::*;
    use std::sync::atomic::{AtomicBool, Ordering};
    if tris.len() > crate::flat::MAX_PRIMITIVES {
        validate_triangles(tris)?;
    }
    // A flag rather than a fallible collect: rayon collects an `Option<Vec>` through
    // a list of pieces and a copy, a `Vec` in place.
    let bad = AtomicBool::new(false);
    let refs = tris
        .par_iter()
        .with_min_len(4096)
        .enumerate()
        .map(|(i, t)| {
            if !t.iter().all(|p| p.is_finite()) {
                bad.store(true, Ordering::Relaxed);
            }
            let b = Aabb::from_triangle(t);
            PrimRef::new(b.min, b.max, i as u32)
        })
        .collect();
    if bad.into_inner() {
        validate_triangles(tris)?;
    }
    Ok(refs)
}

/// Builds a BVH over boxes, as [`build`] does over triangles' boxes: the top level over
/// instances. The boxes must be finite (an instance's box is). [`BuilderKind::Sbvh`]
/// builds binned SAH here: there is no triangle to clip a box's reference to.
pub fn build_boxes(boxes: &[Aabb], opts: &BuildOptions) -> Result<BuildTree, BuildError> {
    let refs = boxes
        .iter()
        .enumerate()
        .map(|(i, b)| PrimRef::new(b.min, b.max, i as u32))
        .collect();
    let (nodes, prim_order) = build_refs(refs, opts)?;
    Ok(reinsert::finish(tree_of(&nodes.nodes, prim_order), opts))
}

/// Checks the options, then builds the flat nodes over `refs`; returns them with the
/// primitive order their leaves index.
fn build_refs(
    mut refs: Vec<PrimRef>,
    opts: &BuildOptions,
) -> Result<(recursion::Slots, Vec<u32>), BuildError> {
    if refs.is_empty() {
        return Err(BuildError::Empty);
    }
    opts.validate()?;
    let (bounds, cb) = bounds_of(&refs, true);
    let slots = recursion::build_nodes(&mut refs, opts, bounds, cb);
    let prim_order = {
        use rayon::prelude::*;
        refs.par_iter()
            .with_min_len(4096)
            .map(|r| r.index())
            .collect()
    };
    Ok((slots, prim_order))
}

/// The boxed tree of flat nodes (depth-first, first child next).
fn tree_of(nodes: &[FlatNode], prim_order: Vec<u32>) -> BuildTree {
    fn node(nodes: &[FlatNode], i: usize) -> BuildNode {
        let n = &nodes[i];
        if n.is_leaf() {
            BuildNode::Leaf {
                bounds: n.aabb(),
                first: n.right_or_first,
                count: n.count(),
            }
        } else {
            BuildNode::Interior {
                bounds: n.aabb(),
                axis: n.axis() as u8,
                children: Box::new([node(nodes, i + 1), node(nodes, n.right_or_first as usize)]),
            }
        }
    }
    BuildTree {
        root: node(nodes, 0),
        prim_order,
        node_count: nodes.len(),
    }
}
