//! Builders: from triangles to a [`BuildTree`] (a plain binary tree over a primitive
//! permutation). [`crate::flat`] then lays that tree out for traversal.
//!
//! All builders share one recursion and differ only in how they choose a split
//! ([`BuilderKind`]). The recursion forks with `rayon::join` above a size threshold;
//! every choice depends only on the primitives of the node, so the tree is the same
//! whatever the thread count.

mod binned;
mod sweep;

use std::fmt;
use std::str::FromStr;

use glam::Vec3;

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
}

impl BuilderKind {
    /// Every builder, in the order reports list them.
    pub const ALL: [BuilderKind; 4] = [
        BuilderKind::Sah,
        BuilderKind::SweepSah,
        BuilderKind::Median,
        BuilderKind::Midpoint,
    ];

    /// The name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            BuilderKind::Sah => "sah",
            BuilderKind::SweepSah => "sweep-sah",
            BuilderKind::Median => "median",
            BuilderKind::Midpoint => "midpoint",
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
                format!("unknown builder '{s}' (expected sah, sweep-sah, median or midpoint)")
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
        }
    }
}

impl BuildOptions {
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

/// The builder's output: a tree whose leaves index `prim_order`, a permutation of the
/// input primitives in which every leaf is a contiguous range.
#[derive(Clone, Debug)]
pub struct BuildTree {
    /// The root node.
    pub root: BuildNode,
    /// The permutation of the input primitives the leaves index into.
    pub prim_order: Vec<u32>,
    /// Number of nodes (at most `2 n - 1`).
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

/// Nodes up to this size use the exact sweep in the binned builder.
const SMALL_NODE: usize = 24;

/// What the recursion keeps per primitive: its box and its original index.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PrimRef {
    pub min: Vec3,
    pub index: u32,
    pub max: Vec3,
}

impl PrimRef {
    #[inline(always)]
    pub fn centroid(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }
    #[inline(always)]
    pub fn bounds(&self) -> Aabb {
        Aabb {
            min: self.min,
            max: self.max,
        }
    }
}

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
        c.grow(r.centroid());
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
    opts.cost_traversal + opts.cost_intersection * (n_l as f32 * a_l + n_r as f32 * a_r) / node_area
}

/// Splits at the object median along `axis` (ties broken by primitive index, so the
/// result is deterministic).
pub(crate) fn median_split(refs: &mut [PrimRef], axis: usize) -> Split {
    let mid = refs.len() / 2;
    refs.select_nth_unstable_by(mid, |a, b| {
        a.centroid()[axis]
            .total_cmp(&b.centroid()[axis])
            .then(a.index.cmp(&b.index))
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
    validate_triangles(tris)?;
    build_refs(
        tris.iter()
            .enumerate()
            .map(|(i, t)| {
                let b = Aabb::from_triangle(t);
                PrimRef {
                    min: b.min,
                    index: i as u32,
                    max: b.max,
                }
            })
            .collect(),
        opts,
    )
}

/// Builds a BVH over boxes, as [`build`] does over triangles' boxes: the top level over
/// instances. The boxes must be finite (an instance's box is).
pub fn build_boxes(boxes: &[Aabb], opts: &BuildOptions) -> Result<BuildTree, BuildError> {
    build_refs(
        boxes
            .iter()
            .enumerate()
            .map(|(i, b)| PrimRef {
                min: b.min,
                index: i as u32,
                max: b.max,
            })
            .collect(),
        opts,
    )
}

fn build_refs(mut refs: Vec<PrimRef>, opts: &BuildOptions) -> Result<BuildTree, BuildError> {
    if refs.is_empty() {
        return Err(BuildError::Empty);
    }
    if !(2..=256).contains(&opts.bins) {
        return Err(BuildError::Options(format!(
            "bins must be in 2..=256, got {}",
            opts.bins
        )));
    }
    if opts.max_leaf_size == 0 {
        return Err(BuildError::Options(
            "max_leaf_size must be at least 1".into(),
        ));
    }
    if !(opts.cost_traversal >= 0.0 && opts.cost_intersection > 0.0) {
        return Err(BuildError::Options(
            "costs must be finite, traversal >= 0, intersection > 0".into(),
        ));
    }
    let (bounds, cb) = bounds_of(&refs, true);
    let (root, node_count) = recurse(&mut refs, 0, 0, opts, bounds, cb);
    let prim_order = refs.iter().map(|r| r.index).collect();
    Ok(BuildTree {
        root,
        prim_order,
        node_count,
    })
}

/// Builds the subtree over `refs`, whose first element sits at `offset` in the final
/// primitive order. Returns the subtree and its node count.
fn recurse(
    refs: &mut [PrimRef],
    offset: usize,
    depth: usize,
    opts: &BuildOptions,
    bounds: Aabb,
    cb: Aabb,
) -> (BuildNode, usize) {
    let n = refs.len();
    let parallel = n >= opts.parallel_threshold;
    let leaf = BuildNode::Leaf {
        bounds,
        first: offset as u32,
        count: n as u32,
    };
    if n == 1 {
        return (leaf, 1);
    }
    let degenerate = cb.extent().max_element() <= 0.0;
    let split = if degenerate || depth >= opts.max_depth {
        // Every centroid is the same point, or we are deep enough that only a balanced
        // split keeps the depth bounded.
        if n <= opts.max_leaf_size {
            Split::Leaf
        } else {
            median_split(refs, cb.longest_axis())
        }
    } else {
        match opts.builder {
            // Small nodes: the exact sweep costs less than initialising and sweeping the
            // bins, and is at least as good.
            BuilderKind::Sah if n <= SMALL_NODE => sweep::split(refs, &bounds, &cb, opts),
            BuilderKind::Sah => binned::split(refs, &bounds, &cb, opts, parallel),
            BuilderKind::SweepSah => sweep::split(refs, &bounds, &cb, opts),
            BuilderKind::Median => median_builder_split(refs, &cb, opts, &bounds),
            BuilderKind::Midpoint => midpoint_split(refs, &cb, opts, &bounds),
        }
    };
    let split = match split {
        Split::Leaf if n <= opts.max_leaf_size => return (leaf, 1),
        // The strategy found nothing that pays but the node is too big for a leaf.
        Split::Leaf => median_split(refs, cb.longest_axis()),
        s => s,
    };
    let (axis, mid, [lb, rb]) = match split {
        Split::Known {
            axis,
            mid,
            children,
        } => (axis, mid, children),
        Split::At { axis, mid } => (
            axis,
            mid,
            [
                bounds_of(&refs[..mid], parallel),
                bounds_of(&refs[mid..], parallel),
            ],
        ),
        Split::Leaf => unreachable!("median_split always splits"),
    };
    debug_assert!(mid > 0 && mid < n);
    let (left, right) = refs.split_at_mut(mid);
    let ((l, nl), (r, nr)) = if parallel {
        rayon::join(
            || recurse(left, offset, depth + 1, opts, lb.0, lb.1),
            || recurse(right, offset + mid, depth + 1, opts, rb.0, rb.1),
        )
    } else {
        (
            recurse(left, offset, depth + 1, opts, lb.0, lb.1),
            recurse(right, offset + mid, depth + 1, opts, rb.0, rb.1),
        )
    };
    (
        BuildNode::Interior {
            bounds,
            axis: axis as u8,
            children: Box::new([l, r]),
        },
        1 + nl + nr,
    )
}
