//! Spatial-split BVH (SBVH): Stich, Friedrich and Dietrich 2009, "Spatial Splits in
//! Bounding Volume Hierarchies" (HPG 2009).
//!
//! The recursion works on *references*: a triangle's box, or the box of the part of it
//! that lies in a slab. At each node it takes the cheaper (SAH) of
//! * an **object split**: binned SAH over the references' centroids (an exact sweep for
//!   small nodes), as [`super::BuilderKind::Sah`] does, and
//! * a **spatial split** (section 4.2 of the paper), tried only when the best object
//!   split's children overlap by more than [`ALPHA`] of the root's surface area
//!   (section 4.3): the node's box is cut into bins along each axis, every reference is
//!   chopped at the bin planes it crosses (its triangle clipped, not its box), and a
//!   reference crossing the chosen plane goes to both children, each with the box of its
//!   part on that side;
//!
//! then, for a spatial split, *reference unsplitting* (section 4.4): a crossing reference
//! goes wholly to one side when that costs less than duplicating it.
//!
//! # Exact clipping
//! A piece's box is the box of the triangle's part in the closed half-space, intersected
//! with the reference's box; the plane coordinate is exact, and an edge's crossing point
//! is computed in f64 and rounded outwards to f32 ([`crossing`]), then clamped to the
//! edge's own range. So every point of a triangle lies in at least one of its references'
//! boxes, whatever the rounding. A piece that holds no part of the triangle is dropped
//! (the other side then holds all of it); nothing else is.
//!
//! # Bounded memory
//! All references live in one array of `n + floor(split_budget * n)` entries, allocated
//! once. A node owns a slice of it: its references first, then free room. A split hands
//! each child its references plus a share of the free room proportional to its reference
//! count; a spatial split whose references would not fit in the node's slice is not
//! considered. At the end the leaves' references are gathered into `prim_order`.
//!
//! # Determinism
//! Every choice depends only on the node's references and the size of its slice (itself
//! fixed by its ancestors' choices): the tree is the same whatever the thread count.
//! Parallel binning only takes minima, maxima and integer counts, which do not depend on
//! the reduction order.
//!
//! # Traversal
//! Several leaves may hold the same triangle. A ray tests it in each of them with the
//! same corners, so it gets the same `t`, `u`, `v` each time, and the hit rule (ties to
//! the lower primitive index) cannot change the answer. A leaf's box may be smaller than
//! its triangles' boxes, so the box test's culling slack (`intersect::BOX_CULL_SLACK`),
//! derived for boxes containing their triangles' corners, covers the error of the
//! triangle test's `t` only up to the triangle's extent along the ray: the closest hit
//! stays order-independent but for the documented f32 departures
//! ([`crate::oracle::f32_t_error_bound`] bounds that error).

use glam::{BVec3A, DVec3, Vec3, Vec3A};
use rayon::prelude::*;

use super::{
    BuildError, BuildNode, BuildOptions, BuildTree, PrimRef, Split, bounds_of, median_split,
    partition, split_cost,
};
// Nodes up to this size choose their object split by the exact sweep, as the binned SAH
// builder does.
use super::small::SMALL_NODE;
use crate::flat::MAX_PRIMITIVES;
use crate::geometry::Aabb;
use crate::mesh::Triangle;

/// The overlap threshold (the paper's alpha): spatial splits are tried at a node only when
/// its best object split's children overlap by more than this fraction of the root's
/// surface area. The paper finds 1e-5 close to the best SAH at little build cost.
const ALPHA: f32 = 1e-5;

/// At most this many spatial bins per axis (as Embree uses; fewer when `bins` is lower),
/// and no more than the node's references (at least 4): chopping references at every
/// plane is the bulk of an SBVH build, and a node of a few references gains nothing from
/// finer planes. Measured on the shared meshes against 32 bins: SAH cost within 1.5%
/// (bunny, drone, legocar, flight_helmet), a half to a third of the build time; the cap
/// by node size changed no cost and saved another third.
const SPATIAL_BINS: usize = 16;

/// Nodes at least this big are binned in parallel chunks of `PAR_CHUNK`.
const PAR_MIN: usize = 32 * 1024;
const PAR_CHUNK: usize = 8 * 1024;

/// Builds an SBVH over `tris` (already validated by [`super::build`]).
pub(super) fn build(tris: &[Triangle], opts: &BuildOptions) -> Result<BuildTree, BuildError> {
    opts.validate()?;
    let n = tris.len();
    if n == 0 {
        return Err(BuildError::Empty);
    }
    // The budget is validated to lie in 0..=16: the product is finite.
    let extra = (f64::from(opts.split_budget) * n as f64).floor() as usize;
    let cap = n.saturating_add(extra).min(MAX_PRIMITIVES).max(n);
    let mut buf: Vec<PrimRef> = Vec::with_capacity(cap);
    buf.extend(tris.iter().enumerate().map(|(i, t)| {
        let b = Aabb::from_triangle(t);
        PrimRef::new(b.min, b.max, i as u32)
    }));
    // The free room: placeholders, overwritten before they are read.
    buf.resize(cap, buf[0]);
    let (bounds, _) = bounds_of(&buf[..n], true);
    let ctx = Ctx {
        tris,
        opts,
        root_area: bounds.surface_area(),
    };
    let (mut root, node_count) = recurse(&ctx, &mut buf, n, 0, 0);
    let mut prim_order = Vec::with_capacity(cap);
    gather(&mut root, &buf, &mut prim_order);
    Ok(BuildTree {
        root,
        prim_order,
        node_count,
    })
}

/// What every node of one build shares.
struct Ctx<'a> {
    tris: &'a [Triangle],
    opts: &'a BuildOptions,
    /// The root's surface area, the denominator of the overlap test.
    root_area: f32,
}

/// Moves each leaf's references (at their place in the slack-spaced array) into
/// `out` in depth-first order, and renumbers the leaf's `first` to match.
fn gather(node: &mut BuildNode, buf: &[PrimRef], out: &mut Vec<u32>) {
    match node {
        BuildNode::Leaf { first, count, .. } => {
            let f = *first as usize;
            *first = out.len() as u32;
            out.extend(buf[f..f + *count as usize].iter().map(|r| r.index()));
        }
        BuildNode::Interior { children, .. } => {
            let [l, r] = &mut **children;
            gather(l, buf, out);
            gather(r, buf, out);
        }
    }
}

/// The common part of two boxes (empty when they are disjoint).
fn intersection(a: &Aabb, b: &Aabb) -> Aabb {
    Aabb {
        min: a.min.max(b.min),
        max: a.max.min(b.max),
    }
}

/// Builds the subtree over `buf[..count]`; `buf[count..]` is free room the subtree may
/// fill with duplicated references. `offset` is `buf`'s place in the whole array.
fn recurse(
    ctx: &Ctx,
    buf: &mut [PrimRef],
    count: usize,
    offset: usize,
    depth: usize,
) -> (BuildNode, usize) {
    let opts = ctx.opts;
    let parallel = count >= opts.parallel_threshold;
    let (bounds, cb) = bounds_of(&buf[..count], parallel);
    let leaf = BuildNode::Leaf {
        bounds,
        first: offset as u32,
        count: count as u32,
    };
    if count == 1 {
        return (leaf, 1);
    }
    let leaf_ok = count <= opts.max_leaf_size;
    let leaf_cost = opts.cost_intersection * count as f32;
    // Beyond max_depth only the object median splits, as in the shared recursion: the
    // depth stays bounded.
    let (object, spatial) = if depth < opts.max_depth {
        candidates(ctx, &buf[..count], buf.len(), &bounds, &cb, parallel)
    } else {
        (None, None)
    };
    let object_cost = object.as_ref().map_or(f32::INFINITY, |o| o.cost);
    let spatial = spatial.filter(|s| s.cost < object_cost);
    let best_cost = spatial.as_ref().map_or(object_cost, |s| s.cost);
    if leaf_ok && !(best_cost < leaf_cost) {
        return (leaf, 1);
    }
    let mut placed = spatial.and_then(|s| split_spatial(ctx, buf, count, &s, parallel));
    if placed.is_none()
        && let Some(o) = object.filter(|o| o.cost.is_finite())
    {
        placed = split_object(buf, count, &o);
    }
    // No split pays, or the chosen one left a side empty: the node is too big for a leaf.
    let (axis, n_l, left_cap, n_r) = match placed {
        Some(p) => p,
        None => {
            let axis = cb.longest_axis();
            let mid = match median_split(&mut buf[..count], axis) {
                Split::At { mid, .. } | Split::Known { mid, .. } => mid,
                Split::Leaf => count / 2,
            };
            (axis, mid, give_room(buf, count, mid), count - mid)
        }
    };
    debug_assert!(n_l > 0 && n_r > 0 && left_cap >= n_l && buf.len() - left_cap >= n_r);
    let (left, right) = buf.split_at_mut(left_cap);
    let ((l, nl), (r, nr)) = if parallel {
        rayon::join(
            || recurse(ctx, left, n_l, offset, depth + 1),
            || recurse(ctx, right, n_r, offset + left_cap, depth + 1),
        )
    } else {
        (
            recurse(ctx, left, n_l, offset, depth + 1),
            recurse(ctx, right, n_r, offset + left_cap, depth + 1),
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

/// After an object split (left `[0, mid)`, right `[mid, count)`): moves the right
/// references to make the left child's share of the free room, proportional to its
/// count. Returns where the right child's slice starts.
fn give_room(buf: &mut [PrimRef], count: usize, mid: usize) -> usize {
    let left_cap = mid + share(buf.len() - count, mid, count - mid);
    buf.copy_within(mid..count, left_cap);
    left_cap
}

/// The left child's part of `slack` free entries: proportional to its `n_l` references
/// of `n_l + n_r` (rounded down).
fn share(slack: usize, n_l: usize, n_r: usize) -> usize {
    (slack as u128 * n_l as u128 / (n_l + n_r) as u128) as usize
}

/// How an object split partitions the references.
#[derive(Clone, Copy, Debug)]
enum Rule {
    /// Centroid bin `<= k` along the axis (`bin_of` with these `lo`, `scale`) goes left.
    Bin { k: usize, lo: f32, scale: f32 },
    /// Sorted by (centroid, index) along the axis, the first `mid` go left.
    Sorted { mid: usize },
}

/// The best object split of a node.
#[derive(Clone, Copy, Debug)]
struct ObjectSplit {
    cost: f32,
    axis: usize,
    rule: Rule,
    bins: usize,
    /// The children's boxes (for the overlap test).
    left: Aabb,
    right: Aabb,
}

/// The best spatial split of a node.
#[derive(Clone, Copy, Debug)]
struct SpatialSplit {
    cost: f32,
    axis: usize,
    /// The plane `x[axis] = pos`.
    pos: f32,
    /// The children's boxes and reference counts with every crossing reference split.
    left: Aabb,
    right: Aabb,
    n_l: usize,
    n_r: usize,
}

/// The node's best object split and, when the overlap test asks for one and the node's
/// slice has room for duplicates, its best spatial split.
fn candidates(
    ctx: &Ctx,
    refs: &[PrimRef],
    cap: usize,
    bounds: &Aabb,
    cb: &Aabb,
    parallel: bool,
) -> (Option<ObjectSplit>, Option<SpatialSplit>) {
    let area = bounds.surface_area();
    if !(area > 0.0) {
        return (None, None);
    }
    let object = if cb.extent().max_element() <= 0.0 {
        None
    } else if refs.len() <= SMALL_NODE {
        sweep_object(refs, area, ctx.opts)
    } else {
        binned_object(refs, area, cb, ctx.opts, parallel)
    };
    let overlap = object.as_ref().map_or(f32::INFINITY, |o| {
        intersection(&o.left, &o.right).surface_area()
    });
    let spatial = if cap > refs.len() && ctx.root_area > 0.0 && overlap / ctx.root_area > ALPHA {
        binned_spatial(ctx, refs, cap, bounds, area, parallel)
    } else {
        None
    };
    (object, spatial)
}

/// Bin index of a centroid coordinate, for binning and partitioning alike.
#[inline(always)]
fn bin_of(c: f32, lo: f32, scale: f32, bins: usize) -> usize {
    (((c - lo) * scale) as usize).min(bins - 1)
}

/// Binned SAH over centroids (Wald 2007), evaluated without moving anything.
fn binned_object(
    refs: &[PrimRef],
    area: f32,
    cb: &Aabb,
    opts: &BuildOptions,
    parallel: bool,
) -> Option<ObjectSplit> {
    let bins = opts.bins;
    let scale = super::binned::bin_scale(cb, bins);
    let fill = |chunk: &[PrimRef]| {
        let mut out = vec![(Aabb::EMPTY, 0u32); 3 * bins];
        for r in chunk {
            let (b, c) = (r.bounds(), r.centroid());
            for a in 0..3 {
                if scale[a] > 0.0 {
                    let bin = &mut out[a * bins + bin_of(c[a], cb.min[a], scale[a], bins)];
                    bin.0 = bin.0.union(&b);
                    bin.1 += 1;
                }
            }
        }
        out
    };
    let binned = if parallel && refs.len() >= PAR_MIN {
        refs.par_chunks(PAR_CHUNK).map(fill).reduce(
            || vec![(Aabb::EMPTY, 0u32); 3 * bins],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x = (x.0.union(&y.0), x.1 + y.1);
                }
                a
            },
        )
    } else {
        fill(refs)
    };
    let n = refs.len();
    let mut best: Option<ObjectSplit> = None;
    let mut right = vec![Aabb::EMPTY; bins];
    for a in 0..3 {
        if scale[a] == 0.0 {
            continue;
        }
        let bin = &binned[a * bins..(a + 1) * bins];
        let mut acc = Aabb::EMPTY;
        for k in (1..bins).rev() {
            acc = acc.union(&bin[k].0);
            right[k] = acc;
        }
        let (mut left, mut n_l) = (Aabb::EMPTY, 0usize);
        for k in 0..bins - 1 {
            left = left.union(&bin[k].0);
            n_l += bin[k].1 as usize;
            let n_r = n - n_l;
            if n_l == 0 || n_r == 0 {
                continue;
            }
            let r = right[k + 1];
            let cost = split_cost(opts, area, n_l, left.surface_area(), n_r, r.surface_area());
            if best.as_ref().is_none_or(|b| cost < b.cost) {
                best = Some(ObjectSplit {
                    cost,
                    axis: a,
                    rule: Rule::Bin {
                        k,
                        lo: cb.min[a],
                        scale: scale[a],
                    },
                    bins,
                    left,
                    right: r,
                });
            }
        }
    }
    best
}

/// The sort key of the exact sweep: centroid along `axis`, then primitive index (a total
/// order: a node never holds two references of one triangle).
fn key_cmp(a: &PrimRef, b: &PrimRef, axis: usize) -> std::cmp::Ordering {
    a.centroid()[axis]
        .total_cmp(&b.centroid()[axis])
        .then(a.index().cmp(&b.index()))
}

/// [`key_cmp`]'s order as an integer: the centroid's bits made to sort as
/// `f32::total_cmp` does, then the primitive index.
#[inline]
fn sort_key(r: &PrimRef, axis: usize) -> u64 {
    (u64::from(super::ordered_bits(r.centroid()[axis])) << 32) | u64::from(r.index())
}

/// Full sweep SAH over sorted centroids, for small nodes (evaluated on a copy).
fn sweep_object(refs: &[PrimRef], area: f32, opts: &BuildOptions) -> Option<ObjectSplit> {
    let n = refs.len();
    // Sorting small integer keys is several times cheaper than sorting the references.
    let mut keys = [(0u64, 0u8); SMALL_NODE];
    let keys = &mut keys[..n];
    let mut right = [Aabb::EMPTY; SMALL_NODE];
    let mut best: Option<ObjectSplit> = None;
    for axis in 0..3 {
        for (i, (k, r)) in keys.iter_mut().zip(refs).enumerate() {
            *k = (sort_key(r, axis), i as u8);
        }
        keys.sort_unstable();
        let at = |i: usize| refs[keys[i].1 as usize].bounds();
        let mut acc = Aabb::EMPTY;
        for i in (1..n).rev() {
            acc = acc.union(&at(i));
            right[i] = acc;
        }
        let mut left = Aabb::EMPTY;
        for i in 0..n - 1 {
            left = left.union(&at(i));
            let r = right[i + 1];
            let (a_l, a_r) = (left.surface_area(), r.surface_area());
            let cost = split_cost(opts, area, i + 1, a_l, n - i - 1, a_r);
            if best.as_ref().is_none_or(|b| cost < b.cost) {
                best = Some(ObjectSplit {
                    cost,
                    axis,
                    rule: Rule::Sorted { mid: i + 1 },
                    bins: 0,
                    left,
                    right: r,
                });
            }
        }
    }
    best
}

/// Applies an object split and hands out the free room. `None` when a side would be
/// empty.
fn split_object(
    buf: &mut [PrimRef],
    count: usize,
    o: &ObjectSplit,
) -> Option<(usize, usize, usize, usize)> {
    let refs = &mut buf[..count];
    let axis = o.axis;
    let mid = match o.rule {
        Rule::Bin { k, lo, scale } => {
            partition(refs, |r| bin_of(r.centroid()[axis], lo, scale, o.bins) <= k)
        }
        Rule::Sorted { mid } => {
            refs.sort_unstable_by(|a, b| key_cmp(a, b, axis));
            mid
        }
    };
    if mid == 0 || mid >= count {
        return None;
    }
    Some((axis, mid, give_room(buf, count, mid), count - mid))
}

/// One spatial bin: the box of the reference pieces in it, how many references start
/// (`entry`) and end (`exit`) in it.
#[derive(Clone, Copy)]
struct SpatialBin {
    bounds: Aabb,
    entry: u32,
    exit: u32,
}

const EMPTY_SPATIAL_BIN: SpatialBin = SpatialBin {
    bounds: Aabb::EMPTY,
    entry: 0,
    exit: 0,
};

/// The bins a reference spans along an axis whose inner planes are `planes` (sorted):
/// bin `k` lies between `planes[k - 1]` and `planes[k]`. A reference goes to the left of
/// plane `k` when `min < planes[k]` or it lies flat on the plane (`max <= planes[k]`), and
/// to the right when `max > planes[k]`: exactly the rule of [`split_spatial`].
/// `guess` maps a coordinate to about its bin; the count is then corrected against the
/// planes themselves, so the result is exact whatever the guess's rounding.
#[inline]
fn span(planes: &[f32], guess: impl Fn(f32) -> usize, min: f32, max: f32) -> (usize, usize) {
    let n = planes.len();
    // The number of planes below `max`, then of planes at or below `min`.
    let mut last = guess(max).min(n);
    while last > 0 && !(planes[last - 1] < max) {
        last -= 1;
    }
    while last < n && planes[last] < max {
        last += 1;
    }
    let mut first = guess(min).min(n);
    while first > 0 && !(planes[first - 1] <= min) {
        first -= 1;
    }
    while first < n && planes[first] <= min {
        first += 1;
    }
    (first.min(last), last)
}

/// Stich et al.'s chopped binning along all three axes, then the sweep; only planes whose
/// children fit in the node's slice (`cap` references) are considered.
fn binned_spatial(
    ctx: &Ctx,
    refs: &[PrimRef],
    cap: usize,
    bounds: &Aabb,
    area: f32,
    parallel: bool,
) -> Option<SpatialSplit> {
    let bins = ctx.opts.bins.min(SPATIAL_BINS).min(refs.len().max(4));
    let planes: [Vec<f32>; 3] = [0, 1, 2].map(|a| {
        let (lo, hi) = (bounds.min[a], bounds.max[a]);
        if hi > lo {
            (1..bins)
                .map(|k| lo + (hi - lo) * (k as f32 / bins as f32))
                .collect()
        } else {
            Vec::new()
        }
    });
    let scale = [0, 1, 2].map(|a| bins as f32 / (bounds.max[a] - bounds.min[a]));
    let fill = |chunk: &[PrimRef]| {
        let mut out = vec![EMPTY_SPATIAL_BIN; 3 * bins];
        for r in chunk {
            for (a, planes) in planes.iter().enumerate() {
                if planes.is_empty() {
                    continue;
                }
                let bin = &mut out[a * bins..(a + 1) * bins];
                let (lo, scale) = (bounds.min[a], scale[a]);
                let guess = |x: f32| ((x - lo) * scale).max(0.0) as usize;
                let (first, last) = span(planes, guess, r.min()[a], r.max()[a]);
                bin[first].entry += 1;
                bin[last].exit += 1;
                if first == last {
                    bin[first].bounds = bin[first].bounds.union(&r.bounds());
                    continue;
                }
                chop(
                    &ctx.tris[r.index() as usize],
                    r,
                    a,
                    planes,
                    first,
                    last,
                    bin,
                );
            }
        }
        out
    };
    let binned = if parallel && refs.len() >= PAR_MIN {
        refs.par_chunks(PAR_CHUNK).map(fill).reduce(
            || vec![EMPTY_SPATIAL_BIN; 3 * bins],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    x.bounds = x.bounds.union(&y.bounds);
                    x.entry += y.entry;
                    x.exit += y.exit;
                }
                a
            },
        )
    } else {
        fill(refs)
    };
    let mut best: Option<SpatialSplit> = None;
    let mut right = vec![(Aabb::EMPTY, 0usize); bins];
    for (a, planes) in planes.iter().enumerate() {
        if planes.is_empty() {
            continue;
        }
        let bin = &binned[a * bins..(a + 1) * bins];
        let mut acc = (Aabb::EMPTY, 0usize);
        for k in (1..bins).rev() {
            acc = (acc.0.union(&bin[k].bounds), acc.1 + bin[k].exit as usize);
            right[k] = acc;
        }
        let (mut left, mut n_l) = (Aabb::EMPTY, 0usize);
        // The plane between bins k and k + 1 is planes[k].
        for k in 0..bins - 1 {
            left = left.union(&bin[k].bounds);
            n_l += bin[k].entry as usize;
            let (r, n_r) = right[k + 1];
            if n_l == 0 || n_r == 0 || n_l + n_r > cap {
                continue;
            }
            let cost = split_cost(
                ctx.opts,
                area,
                n_l,
                left.surface_area(),
                n_r,
                r.surface_area(),
            );
            if best.as_ref().is_none_or(|b| cost < b.cost) {
                best = Some(SpatialSplit {
                    cost,
                    axis: a,
                    pos: planes[k],
                    left,
                    right: r,
                    n_l,
                    n_r,
                });
            }
        }
    }
    best
}

/// Which side(s) a reference goes to in a spatial split.
const LEFT: u8 = 0;
const BOTH: u8 = 1;
const RIGHT: u8 = 2;

/// Where a reference that crosses the plane goes, after unsplitting (section 4.4 of the
/// paper: keeping it whole on one side, that child's box grown by it, costs less than
/// duplicating it). Also tightens a reference whose triangle lies on one side only.
fn side_of_crossing(ctx: &Ctx, r: &mut PrimRef, s: &SpatialSplit, whole: f32) -> u8 {
    let b = r.bounds();
    let (nl, nr) = (s.n_l as f32, s.n_r as f32);
    let (al, ar) = (s.left.surface_area(), s.right.surface_area());
    let to_left = s.left.union(&b).surface_area() * nl + ar * (nr - 1.0);
    let to_right = al * (nl - 1.0) + s.right.union(&b).surface_area() * nr;
    if to_left < whole && to_left <= to_right {
        return LEFT;
    }
    if to_right < whole {
        return RIGHT;
    }
    let (l, right) = split_box(&ctx.tris[r.index() as usize], &b, s.axis, s.pos);
    match (l.is_empty(), right.is_empty()) {
        (false, false) => BOTH,
        (true, false) => {
            r.set_bounds(&right);
            RIGHT
        }
        (false, true) => {
            r.set_bounds(&l);
            LEFT
        }
        // The box holds no point of the triangle (it can only come from outward rounding):
        // keep it whole all the same.
        (true, true) => LEFT,
    }
}

/// Applies a spatial split in place: the left child's references at `[0, n_l)`, its free
/// room after them up to `left_cap`, the right child's references from `left_cap`.
/// Returns `(axis, n_l, left_cap, n_r)`, or `None` when unsplitting left a side empty
/// (the references are then still valid, some of them tightened).
fn split_spatial(
    ctx: &Ctx,
    buf: &mut [PrimRef],
    count: usize,
    s: &SpatialSplit,
    parallel: bool,
) -> Option<(usize, usize, usize, usize)> {
    let (axis, pos) = (s.axis, s.pos);
    let whole = s.left.surface_area() * s.n_l as f32 + s.right.surface_area() * s.n_r as f32;
    let classify = |r: &mut PrimRef| {
        if r.max()[axis] <= pos {
            LEFT
        } else if r.min()[axis] >= pos {
            RIGHT
        } else {
            side_of_crossing(ctx, r, s, whole)
        }
    };
    let refs = &mut buf[..count];
    let mut class = vec![LEFT; count];
    if parallel && count >= PAR_MIN {
        refs.par_iter_mut()
            .zip(class.par_iter_mut())
            .for_each(|(r, c)| *c = classify(r));
    } else {
        for (r, c) in refs.iter_mut().zip(class.iter_mut()) {
            *c = classify(r);
        }
    }
    // Three-way partition: LEFT, then BOTH, then RIGHT.
    let (mut lo, mut i, mut hi) = (0, 0, count);
    while i < hi {
        match class[i] {
            LEFT => {
                refs.swap(lo, i);
                class.swap(lo, i);
                lo += 1;
                i += 1;
            }
            BOTH => i += 1,
            _ => {
                hi -= 1;
                refs.swap(i, hi);
                class.swap(i, hi);
            }
        }
    }
    let both = hi - lo;
    let (n_l, n_r) = (hi, count - lo);
    if n_l == 0 || n_r == 0 || n_l + n_r > buf.len() {
        return None;
    }
    let left_cap = n_l + share(buf.len() - n_l - n_r, n_l, n_r);
    // The right-only references to the end of the right child's pieces, then each
    // crossing reference split: its left piece in place, its right piece before them.
    buf.copy_within(hi..count, left_cap + both);
    for k in 0..both {
        let r = buf[lo + k];
        let (l, right) = split_box(&ctx.tris[r.index() as usize], &r.bounds(), axis, pos);
        buf[lo + k] = PrimRef::new(l.min, l.max, r.index());
        buf[left_cap + k] = PrimRef::new(right.min, right.max, r.index());
    }
    Some((axis, n_l, left_cap, n_r))
}

/// The boxes of the parts of triangle `tri` inside `b` on either side of the plane
/// `x[axis] = pos` (closed half-spaces), each conservative: the triangle clipped, its box
/// intersected with `b` and the half-space. Empty ([`Aabb::is_empty`]) where the
/// triangle has no point there.
fn split_box(tri: &Triangle, b: &Aabb, axis: usize, pos: f32) -> (Aabb, Aabb) {
    let (mut l, mut r) = (Aabb::EMPTY, Aabb::EMPTY);
    for i in 0..3 {
        let (p, q) = (tri[i], tri[(i + 1) % 3]);
        if p[axis] <= pos {
            l.grow(p);
        }
        if p[axis] >= pos {
            r.grow(p);
        }
        if (p[axis] < pos && pos < q[axis]) || (q[axis] < pos && pos < p[axis]) {
            let c = crossing(p, q, axis, pos);
            l = l.union(&c);
            r = r.union(&c);
        }
    }
    let mut l = intersection(&l, b);
    let mut r = intersection(&r, b);
    l.max[axis] = l.max[axis].min(pos);
    r.min[axis] = r.min[axis].max(pos);
    (l, r)
}

/// Stich et al.'s chopping, to estimate costs: grows `bin[k]` (`first <= k <= last`) by
/// the box of the part of reference `r` in bin `k`, cutting its triangle at each plane in
/// turn. Plain f32, not rounded outwards (the split itself uses [`split_box`]), and
/// in SIMD registers: this loop is most of an SBVH build.
fn chop(
    tri: &Triangle,
    r: &PrimRef,
    axis: usize,
    planes: &[f32],
    first: usize,
    last: usize,
    bin: &mut [SpatialBin],
) {
    let v = tri.map(Vec3A::from);
    let d = [v[1] - v[0], v[2] - v[1], v[0] - v[2]];
    let inv = d.map(|e| 1.0 / e[axis]);
    let grow_bin = |b: &mut SpatialBin, min: Vec3A, max: Vec3A| {
        if !min.cmpgt(max).any() {
            b.bounds = Aabb {
                min: b.bounds.min.min(min.into()),
                max: b.bounds.max.max(max.into()),
            };
        }
    };
    // Lane `axis` is clamped to the plane by a select, not a lane store (which would stall
    // the next vector load).
    let on_axis = BVec3A::new(axis == 0, axis == 1, axis == 2);
    // What is left of the reference right of the last plane cut.
    let (mut rest_min, mut rest_max) = (r.min(), r.max());
    for (k, &pos) in planes.iter().enumerate().take(last).skip(first) {
        let plane = Vec3A::splat(pos);
        let inf = Vec3A::splat(f32::INFINITY);
        let (mut lmin, mut lmax, mut rmin, mut rmax) = (inf, -inf, inf, -inf);
        for i in 0..3 {
            let (p, pa, qa) = (v[i], v[i][axis], v[(i + 1) % 3][axis]);
            if pa <= pos {
                (lmin, lmax) = (lmin.min(p), lmax.max(p));
            }
            if pa >= pos {
                (rmin, rmax) = (rmin.min(p), rmax.max(p));
            }
            if (pa < pos && pos < qa) || (qa < pos && pos < pa) {
                let c = p + d[i] * ((pos - pa) * inv[i]);
                (lmin, lmax) = (lmin.min(c), lmax.max(c));
                (rmin, rmax) = (rmin.min(c), rmax.max(c));
            }
        }
        let (lmin, lmax) = (lmin.max(rest_min), lmax.min(rest_max));
        let lmax = Vec3A::select(on_axis, lmax.min(plane), lmax);
        grow_bin(&mut bin[k], lmin, lmax);
        rest_min = rmin.max(rest_min);
        rest_max = rmax.min(rest_max);
        rest_min = Vec3A::select(on_axis, rest_min.max(plane), rest_min);
        if rest_min.cmpgt(rest_max).any() {
            return;
        }
    }
    grow_bin(&mut bin[last], rest_min, rest_max);
}

/// A box around the point where edge `p q` crosses the plane `x[axis] = pos` (`pos`
/// strictly between the ends): exactly `pos` on `axis`; on the other axes the f64 value,
/// widened by a bound on its rounding error and rounded outwards to f32, then clamped to
/// the edge's own range (which holds the exact point).
fn crossing(p: Vec3, q: Vec3, axis: usize, pos: f32) -> Aabb {
    let (a, b) = (p.as_dvec3(), q.as_dvec3());
    let t = (f64::from(pos) - a[axis]) / (b[axis] - a[axis]);
    let v: DVec3 = a + (b - a) * t;
    // Five roundings of values at most |a| + |b| in magnitude (two subtractions, the
    // quotient, the product, the sum): below 2^-50 (|a| + |b|); 2^-48 to spare.
    const U48: f64 = 1.0 / (1u64 << 48) as f64;
    let err = (a.abs() + b.abs()) * U48;
    let down = |x: f64| {
        let f = x as f32;
        if f64::from(f) > x { f.next_down() } else { f }
    };
    let up = |x: f64| {
        let f = x as f32;
        if f64::from(f) < x { f.next_up() } else { f }
    };
    let (mut min, mut max) = (Vec3::ZERO, Vec3::ZERO);
    for j in 0..3 {
        if j == axis {
            (min[j], max[j]) = (pos, pos);
        } else {
            min[j] = down(v[j] - err[j]).max(p[j].min(q[j]));
            max[j] = up(v[j] + err[j]).min(p[j].max(q[j]));
        }
    }
    Aabb { min, max }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crossing_points_are_rounded_outwards() {
        // An edge whose crossing is not representable: the box must hold the f64 point.
        let (p, q) = (
            Vec3::new(0.0, 0.1, -1e-3),
            Vec3::new(3.0, 1e7 + 1.0, 7.123_457),
        );
        for k in 1..200 {
            let pos = k as f32 * 0.015;
            let c = crossing(p, q, 0, pos);
            let t = (f64::from(pos) - 0.0) / 3.0;
            for j in 1..3 {
                let exact = f64::from(p[j]) + (f64::from(q[j]) - f64::from(p[j])) * t;
                assert!(f64::from(c.min[j]) <= exact && exact <= f64::from(c.max[j]));
            }
            assert_eq!((c.min.x, c.max.x), (pos, pos));
        }
    }

    #[test]
    fn pieces_cover_the_triangle_and_empty_sides_are_empty() {
        let tri = [
            Vec3::ZERO,
            Vec3::new(4.0, 0.0, 0.0),
            Vec3::new(0.0, 4.0, 1.0),
        ];
        let b = Aabb::from_triangle(&tri);
        let (l, r) = split_box(&tri, &b, 0, 1.0);
        assert_eq!(l.max.x, 1.0);
        assert_eq!(r.min.x, 1.0);
        assert!(l.max.y >= 4.0 && r.max.y >= 3.0 && r.max.y < 4.0);
        // Plane past the triangle: nothing on the right.
        let (l, r) = split_box(&tri, &b, 0, 5.0);
        assert!(r.is_empty() && l == b);
        // A triangle lying in the plane goes to both sides, flat.
        let flat = [Vec3::ZERO, Vec3::Y, Vec3::Z];
        let (l, r) = split_box(&flat, &Aabb::from_triangle(&flat), 0, 0.0);
        assert_eq!(l, r);
        assert_eq!(l, Aabb::from_triangle(&flat));
    }
}
