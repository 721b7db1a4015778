//! The recursion the object-split builders share, writing the flat layout directly.
//!
//! A subtree over `n` primitives has at most `2n - 1` nodes, so every node gets a
//! range of that many slots in one preallocated array. Where the two children are built
//! in parallel, the second child's range starts after the first's `2 mid - 1` slots, so
//! neither waits on the other's size, and the first's unused slots are a gap. Built on
//! one thread, the second child starts right after the first child's last node: no gap.
//! [`compact`] then closes the forks' gaps, keeping the depth-first order. No tree of boxed nodes is ever allocated, which is what bounds the build's
//! memory to the flat layout's.

use super::small::{self, SMALL_NODE};
use super::{BuildOptions, BuilderKind, PrimRef, Split, binned, bounds_of, sweep};
use crate::flat::FlatNode;
use crate::geometry::Aabb;

/// The nodes of a build, in depth-first order.
pub(super) struct Slots {
    pub nodes: Vec<FlatNode>,
    /// Longest root-to-leaf path, in edges.
    pub depth: u32,
}

/// What building a subtree returns.
#[derive(Clone, Copy, Debug)]
pub(super) struct Built {
    /// Longest path from the subtree's root to a leaf, in edges.
    pub depth: u32,
    /// Slots from the subtree's root to one past its last node: its node count when no
    /// part of it was built in parallel.
    pub extent: usize,
}

/// A run of unused slots: (first, count).
type Gap = (usize, usize);

/// Builds the nodes over `refs` (their order becomes the leaf order), compacted.
pub(super) fn build_nodes(
    refs: &mut [PrimRef],
    opts: &BuildOptions,
    bounds: Aabb,
    cb: Aabb,
) -> Slots {
    let n = refs.len();
    // Zeroed memory comes from the allocator lazily; the gaps and the slots past the
    // last node are never touched.
    let mut nodes: Vec<FlatNode> = bytemuck::zeroed_vec(2 * n - 1);
    let mut gaps = Vec::new();
    let built = recurse(refs, 0, 0, opts, bounds, cb, &mut nodes, 0, &mut gaps);
    compact(&mut nodes, built.extent, &gaps);
    Slots {
        nodes,
        depth: built.depth,
    }
}

/// Writes a leaf of `count` primitives from `first` into the first of `slots`.
pub(super) fn write_leaf(slots: &mut [FlatNode], bounds: &Aabb, first: usize, count: usize) {
    slots[0] = FlatNode {
        min: bounds.min.to_array(),
        right_or_first: first as u32,
        max: bounds.max.to_array(),
        meta: (count as u32) << 2,
    };
}

/// Writes an interior node whose second child is at slot `right` (before compaction).
pub(super) fn write_interior(slots: &mut [FlatNode], bounds: &Aabb, axis: usize, right: usize) {
    slots[0] = FlatNode {
        min: bounds.min.to_array(),
        right_or_first: right as u32,
        max: bounds.max.to_array(),
        meta: axis as u32,
    };
}

/// Builds the subtree over `refs` (the first at `offset` in the final primitive order)
/// into `slots` (at least `2 n - 1`), whose first slot has index `base`, and appends the
/// gaps it leaves to `gaps`, in order.
#[allow(clippy::too_many_arguments)]
fn recurse(
    refs: &mut [PrimRef],
    offset: usize,
    depth: usize,
    opts: &BuildOptions,
    bounds: Aabb,
    cb: Aabb,
    slots: &mut [FlatNode],
    base: usize,
    gaps: &mut Vec<Gap>,
) -> Built {
    let n = refs.len();
    debug_assert!(slots.len() >= 2 * n - 1);
    let parallel = n >= opts.parallel_threshold;
    let make_leaf = |slots: &mut [FlatNode]| {
        write_leaf(slots, &bounds, offset, n);
        Built {
            depth: 0,
            extent: 1,
        }
    };
    if n == 1 {
        return make_leaf(slots);
    }
    let sweeps = matches!(
        opts.builder,
        BuilderKind::Sah | BuilderKind::SweepSah | BuilderKind::Sbvh
    );
    if sweeps && n <= SMALL_NODE {
        return small::subtree(refs, offset, depth, opts, bounds, cb, slots, base);
    }
    let degenerate = cb.extent().max_element() <= 0.0;
    let split = if degenerate || depth >= opts.max_depth {
        // Every centroid is the same point, or we are deep enough that only a balanced
        // split keeps the depth bounded.
        if n <= opts.max_leaf_size {
            Split::Leaf
        } else {
            super::median_split(refs, cb.longest_axis())
        }
    } else {
        match opts.builder {
            // Small nodes take the exact sweep above ([`small`]): it costs less than
            // initialising and sweeping the bins, and is at least as good.
            // Sbvh only gets here for boxes (`build_boxes`): binned SAH.
            BuilderKind::Sah | BuilderKind::Sbvh => {
                binned::split(refs, &bounds, &cb, opts, parallel)
            }
            BuilderKind::SweepSah => sweep::split(refs, &bounds, &cb, opts),
            BuilderKind::Median => super::median_builder_split(refs, &cb, opts, &bounds),
            BuilderKind::Midpoint => super::midpoint_split(refs, &cb, opts, &bounds),
        }
    };
    let split = match split {
        Split::Leaf if n <= opts.max_leaf_size => return make_leaf(slots),
        // The strategy found nothing that pays but the node is too big for a leaf.
        Split::Leaf => super::median_split(refs, cb.longest_axis()),
        s => s,
    };
    let (axis, mid, children) = match split {
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
    let (left_refs, right_refs) = refs.split_at_mut(mid);
    let [(lb, lc), (rb, rc)] = children;
    let mut first = |slots: &mut [FlatNode], gaps: &mut Vec<Gap>| {
        recurse(
            left_refs,
            offset,
            depth + 1,
            opts,
            lb,
            lc,
            slots,
            base + 1,
            gaps,
        )
    };
    // The second child, `at` slots after this node.
    let mut second = |at: usize, slots: &mut [FlatNode], gaps: &mut Vec<Gap>| {
        let o = offset + mid;
        recurse(
            right_refs,
            o,
            depth + 1,
            opts,
            rb,
            rc,
            slots,
            base + at,
            gaps,
        )
    };
    let (l, r, at) = if parallel {
        // The second child starts past the most the first can take, `2 mid - 1` slots.
        let at = 2 * mid;
        let (left_slots, right_slots) = slots[1..].split_at_mut(at - 1);
        let mut right_gaps = Vec::new();
        let (l, r) = rayon::join(
            || first(left_slots, gaps),
            || second(at, right_slots, &mut right_gaps),
        );
        if 1 + l.extent < at {
            gaps.push((base + 1 + l.extent, at - 1 - l.extent));
        }
        gaps.append(&mut right_gaps);
        (l, r, at)
    } else {
        let l = first(&mut slots[1..], gaps);
        let at = 1 + l.extent;
        let r = second(at, &mut slots[at..], gaps);
        (l, r, at)
    };
    write_interior(slots, &bounds, axis, base + at);
    Built {
        depth: 1 + l.depth.max(r.depth),
        extent: at + r.extent,
    }
}

/// Removes the gaps (in order) from the first `extent` slots, keeping depth-first order.
/// The slots between two gaps are a run, and every node of a run moves down by the same
/// shift (the gaps before it); a second child's new index is its old one less the shift
/// of the run it lies in. So the runs renumber their second children in parallel, then
/// move down in order, each move writing only over slots already moved or in a gap.
fn compact(nodes: &mut Vec<FlatNode>, extent: usize, gaps: &[Gap]) {
    use rayon::prelude::*;
    // (first slot, one past the last, shift) of each run.
    let mut runs = Vec::with_capacity(gaps.len() + 1);
    let (mut from, mut shift) = (0, 0);
    for &(at, len) in gaps.iter().chain(&[(extent, 0)]) {
        runs.push((from, at, shift));
        shift += len;
        from = at + len;
    }
    // The run that slot `x` (not in a gap) lies in: the last one starting at or before it.
    let shift_of = |x: usize| runs[runs.partition_point(|r| r.0 <= x) - 1].2;
    let mut parts = Vec::with_capacity(runs.len());
    let mut rest = &mut nodes[..extent];
    let mut at = 0;
    for &(from, end, shift) in &runs {
        let (run, tail) = std::mem::take(&mut rest)[from - at..].split_at_mut(end - from);
        parts.push((run, end, shift));
        (rest, at) = (tail, end);
    }
    parts.into_par_iter().for_each(|(run, end, shift)| {
        for n in run.iter_mut().filter(|n| !n.is_leaf()) {
            let right = n.right_or_first as usize;
            // Most second children lie in their parent's run; a forked parent's does not.
            n.right_or_first -= if right < end { shift } else { shift_of(right) } as u32;
        }
    });
    for &(from, end, shift) in &runs[1..] {
        nodes.copy_within(from..end, from - shift);
    }
    nodes.truncate(extent - shift);
    // Give the unused tail's memory back: a big allocation shrinks in place.
    nodes.shrink_to_fit();
}
