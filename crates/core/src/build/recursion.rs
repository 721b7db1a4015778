//! The recursion the object-split builders share, writing the flat layout directly.
//!
//! A subtree over `n` primitives has at most `2n - 1` nodes, so every node gets a
//! range of that many slots in one preallocated array: the node itself, then its first
//! child's range (`2 mid - 1` slots), then its second child's. Both children can thus be
//! built in parallel without knowing each other's size, straight into their final
//! depth-first order. A leaf of `c` primitives leaves `2c - 2` slots unused; one
//! sequential pass ([`compact`]) closes those gaps. No tree of boxed nodes is ever
//! allocated, which is what bounds the build's memory to the flat layout's.

use super::small::{self, SMALL_NODE};
use super::{BuildOptions, BuilderKind, PrimRef, Split, binned, bounds_of, sweep};
use crate::flat::FlatNode;
use crate::geometry::Aabb;

/// `meta` of a slot no node was written to.
const UNUSED: u32 = u32::MAX;

/// The nodes of a build, in depth-first order with gaps marked [`UNUSED`].
pub(super) struct Slots {
    pub nodes: Vec<FlatNode>,
    /// Longest root-to-leaf path, in edges.
    pub depth: u32,
}

/// Builds the nodes over `refs` (their order becomes the leaf order), compacted.
pub(super) fn build_nodes(
    refs: &mut [PrimRef],
    opts: &BuildOptions,
    bounds: Aabb,
    cb: Aabb,
) -> Slots {
    let n = refs.len();
    // Zeroed memory comes from the allocator lazily; every slot is written once below.
    let mut nodes: Vec<FlatNode> = bytemuck::zeroed_vec(2 * n - 1);
    let depth = recurse(refs, 0, 0, opts, bounds, cb, &mut nodes, 0);
    compact(&mut nodes);
    Slots { nodes, depth }
}

/// Writes a leaf of `count` primitives from `first` into the first of its slots and marks
/// the rest unused.
pub(super) fn write_leaf(slots: &mut [FlatNode], bounds: &Aabb, first: usize, count: usize) {
    slots[0] = FlatNode {
        min: bounds.min.to_array(),
        right_or_first: first as u32,
        max: bounds.max.to_array(),
        meta: (count as u32) << 2,
    };
    for s in &mut slots[1..] {
        s.meta = UNUSED;
    }
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
/// into `slots`, whose first slot has index `base`. Returns the subtree's depth.
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
) -> u32 {
    let n = refs.len();
    debug_assert_eq!(slots.len(), 2 * n - 1);
    let parallel = n >= opts.parallel_threshold;
    let make_leaf = |slots: &mut [FlatNode]| {
        write_leaf(slots, &bounds, offset, n);
        0
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
    let right = base + 2 * mid;
    write_interior(slots, &bounds, axis, right);
    let (left_refs, right_refs) = refs.split_at_mut(mid);
    let (left_slots, right_slots) = slots[1..].split_at_mut(2 * mid - 1);
    let mut first = move || {
        let (b, c) = lb;
        recurse(
            left_refs,
            offset,
            depth + 1,
            opts,
            b,
            c,
            left_slots,
            base + 1,
        )
    };
    let mut second = move || {
        let (b, c) = rb;
        recurse(
            right_refs,
            offset + mid,
            depth + 1,
            opts,
            b,
            c,
            right_slots,
            right,
        )
    };
    let (dl, dr) = if parallel {
        rayon::join(first, second)
    } else {
        (first(), second())
    };
    1 + dl.max(dr)
}

/// Removes the unused slots, keeping depth-first order, and renumbers second children.
/// In depth-first order a second child comes right after its parent's first subtree, so
/// the parents still waiting for theirs form a stack, and its top is the one to fix.
fn compact(nodes: &mut Vec<FlatNode>) {
    let mut waiting: Vec<(usize, u32)> = Vec::new(); // (parent's new index, old second child)
    let mut next = 0;
    for i in 0..nodes.len() {
        let n = nodes[i];
        if n.meta == UNUSED {
            continue;
        }
        if let Some(&(parent, right)) = waiting.last()
            && right as usize == i
        {
            nodes[parent].right_or_first = next as u32;
            waiting.pop();
        }
        // `next <= i`: slots only move down, over ones already read.
        nodes[next] = n;
        if !n.is_leaf() {
            waiting.push((next, n.right_or_first));
        }
        next += 1;
    }
    debug_assert!(waiting.is_empty());
    nodes.truncate(next);
    // Give the gaps' memory back: a big allocation shrinks in place.
    nodes.shrink_to_fit();
}
