//! Full-sweep SAH: sort the centroids along each axis and evaluate every split between
//! consecutive primitives. O(n log n) per node; the reference for SAH quality, and what the
//! binned builder uses for small nodes.
//!
//! The sort orders `(centroid, primitive index)` packed into one integer key, so it
//! compares integers instead of recomputing centroids, and all three axes' orders are kept
//! so the chosen one is applied without sorting again.

use glam::Vec3A;

use super::{BuildOptions, PrimRef, Split, split_weight};
use crate::geometry::Aabb;

/// Nodes up to this size sort on the stack.
const STACK: usize = 32;

/// A key ordered as `(c.total_cmp, index)`, then the ref's position (for duplicated
/// primitives), so every order is total and deterministic.
type Key = (u64, u32);

#[inline(always)]
pub(super) fn key(c: f32, index: u32, pos: usize) -> Key {
    (
        (u64::from(super::ordered_bits(c)) << 32) | u64::from(index),
        pos as u32,
    )
}

#[inline(always)]
fn area(min: Vec3A, max: Vec3A) -> f32 {
    let e = max - min;
    if e.x < 0.0 {
        return 0.0;
    }
    2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
}

/// Chooses and applies the cheapest split over all sorted positions.
pub(super) fn split(refs: &mut [PrimRef], bounds: &Aabb, cb: &Aabb, opts: &BuildOptions) -> Split {
    let n = refs.len();
    if n <= STACK {
        let mut keys = [[(0u64, 0u32); STACK]; 3];
        let mut right = [0f32; STACK];
        let mut tmp = [refs[0]; STACK];
        let [k0, k1, k2] = &mut keys;
        sweep(
            refs,
            bounds,
            cb,
            opts,
            [&mut k0[..n], &mut k1[..n], &mut k2[..n]],
            &mut right[..n],
            &mut tmp[..n],
        )
    } else {
        let mut keys = vec![(0u64, 0u32); 3 * n];
        let mut right = vec![0f32; n];
        let mut tmp = refs.to_vec();
        let (k0, rest) = keys.split_at_mut(n);
        let (k1, k2) = rest.split_at_mut(n);
        sweep(refs, bounds, cb, opts, [k0, k1, k2], &mut right, &mut tmp)
    }
}

fn sweep(
    refs: &mut [PrimRef],
    bounds: &Aabb,
    cb: &Aabb,
    opts: &BuildOptions,
    keys: [&mut [Key]; 3],
    right_area: &mut [f32],
    tmp: &mut [PrimRef],
) -> Split {
    let n = refs.len();
    let area_node = bounds.surface_area();
    let boxes = |i: u32| {
        let r = &refs[i as usize];
        (r.min(), r.max())
    };
    let mut best = (f32::INFINITY, 0usize, 0usize);
    let ext = cb.extent();
    let [k0, k1, k2] = keys;
    let mut keys = [k0, k1, k2];
    for (axis, ks) in keys.iter_mut().enumerate() {
        if ext[axis] <= 0.0 {
            continue;
        }
        for (i, (k, r)) in ks.iter_mut().zip(refs.iter()).enumerate() {
            *k = key(r.centroid()[axis], r.index(), i);
        }
        ks.sort_unstable();
        let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        for i in (1..n).rev() {
            let (a, b) = boxes(ks[i].1);
            lo = lo.min(a);
            hi = hi.max(b);
            right_area[i] = area(lo, hi);
        }
        let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        for i in 0..n - 1 {
            let (a, b) = boxes(ks[i].1);
            lo = lo.min(a);
            hi = hi.max(b);
            let w = split_weight(i + 1, area(lo, hi), n - i - 1, right_area[i + 1]);
            if w < best.0 {
                best = (w, axis, i + 1);
            }
        }
    }
    let (w, axis, mid) = best;
    let cost = opts.cost_traversal + opts.cost_intersection * w / area_node;
    if !cost.is_finite() {
        return Split::Leaf;
    }
    if n <= opts.max_leaf_size && cost >= opts.cost_intersection * n as f32 {
        return Split::Leaf;
    }
    for (t, k) in tmp.iter_mut().zip(keys[axis].iter()) {
        *t = refs[k.1 as usize];
    }
    refs.copy_from_slice(tmp);
    let side = |s: &[PrimRef]| {
        let (mut b, mut c) = (Aabb::EMPTY, Aabb::EMPTY);
        for r in s {
            b = b.union(&r.bounds());
            c.grow(r.centroid().into());
        }
        (b, c)
    };
    Split::Known {
        axis,
        mid,
        children: [side(&refs[..mid]), side(&refs[mid..])],
    }
}
