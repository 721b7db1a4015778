//! Small subtrees, built with the exact sweep ([`super::sweep`]) but sorted only once.
//!
//! Below [`SMALL_NODE`] primitives the binned builder switches to the full sweep, which
//! needs each node's primitives sorted along the three axes. Sorting them once for the
//! whole subtree and handing each child its part of the three sorted lists (a stable
//! filter keeps them sorted) makes every level linear, and all of it stays on the stack.
//! The decisions are the sweep's: the same keys, the same areas, the same costs.

use glam::Vec3A;

use super::recursion::Built;
use super::{BuildOptions, PrimRef};
use crate::flat::FlatNode;
use crate::geometry::Aabb;

/// Subtrees of at most this many primitives are built here.
pub(super) const SMALL_NODE: usize = 48;
const _: () = assert!(SMALL_NODE <= 64, "ids and counts are masked to 64");

/// One subtree's primitives, copied out of the shared array.
struct Subtree<'a> {
    opts: &'a BuildOptions,
    min: [Vec3A; SMALL_NODE],
    max: [Vec3A; SMALL_NODE],
    centre: [Vec3A; SMALL_NODE],
    refs: [PrimRef; SMALL_NODE],
    /// Where the subtree's first primitive sits in the final order.
    offset: usize,
    /// The sweep's areas of the boxes right of each position, reused by every node.
    right_area: [Vec3A; SMALL_NODE],
}

/// Indices below this fit a packed key beside a position.
const PACKED_INDEX: u32 = 1 << 26;

/// Each axis's positions ordered as `(centroid, primitive index, position)`, the sweep's
/// order (the position makes it total even for a primitive referenced twice). With
/// indices below [`PACKED_INDEX`] the three fit one `u64`, which sorts faster than a pair.
fn sorted_lists(s: &Subtree, n: usize) -> [[u8; SMALL_NODE]; 3] {
    let mut lists = [[0u8; SMALL_NODE]; 3];
    if s.refs[..n].iter().all(|r| r.index() < PACKED_INDEX) {
        for (a, l) in lists.iter_mut().enumerate() {
            let mut keys = [0u64; SMALL_NODE];
            for (i, (k, r)) in keys.iter_mut().zip(&s.refs[..n]).enumerate() {
                let c = u64::from(super::ordered_bits(s.centre[i][a]));
                *k = (c << 32) | u64::from(r.index()) << 6 | i as u64;
            }
            keys[..n].sort_unstable();
            for (l, k) in l.iter_mut().zip(&keys[..n]) {
                *l = (k & 63) as u8;
            }
        }
    } else {
        for (a, l) in lists.iter_mut().enumerate() {
            // The exact sweep's own key ([`super::sweep`]).
            let mut keys = [(0u64, 0u32); SMALL_NODE];
            for (i, (k, r)) in keys.iter_mut().zip(&s.refs[..n]).enumerate() {
                *k = super::sweep::key(s.centre[i][a], r.index(), i);
            }
            keys[..n].sort_unstable();
            for (l, k) in l.iter_mut().zip(&keys[..n]) {
                *l = k.1 as u8;
            }
        }
    }
    lists
}

/// Builds the subtree over `refs` (at most [`SMALL_NODE`]; the first at `offset` in the
/// final order) into `slots` (first slot index `base`), rearranging `refs` into leaf
/// order.
#[allow(clippy::too_many_arguments)]
pub(super) fn subtree(
    refs: &mut [PrimRef],
    offset: usize,
    depth: usize,
    opts: &BuildOptions,
    bounds: Aabb,
    cb: Aabb,
    slots: &mut [FlatNode],
    base: usize,
) -> Built {
    let n = refs.len();
    debug_assert!((1..=SMALL_NODE).contains(&n));
    let mut s = Subtree::new(refs, opts, offset);
    let mut lists = sorted_lists(&s, n);
    let [l0, l1, l2] = &mut lists;
    s.node(
        [&mut l0[..n], &mut l1[..n], &mut l2[..n]],
        refs,
        offset,
        depth,
        bounds,
        cb,
        slots,
        base,
    )
}

impl<'a> Subtree<'a> {
    /// A copy of `refs` (at most [`SMALL_NODE`]) with their corners and centroids.
    fn new(refs: &[PrimRef], opts: &'a BuildOptions, offset: usize) -> Subtree<'a> {
        let mut s = Subtree {
            opts,
            min: [Vec3A::ZERO; SMALL_NODE],
            max: [Vec3A::ZERO; SMALL_NODE],
            centre: [Vec3A::ZERO; SMALL_NODE],
            refs: [refs[0]; SMALL_NODE],
            offset,
            right_area: [Vec3A::ZERO; SMALL_NODE],
        };
        for (i, r) in refs.iter().enumerate() {
            s.refs[i] = *r;
            s.min[i] = r.min();
            s.max[i] = r.max();
            s.centre[i] = r.centroid();
        }
        s
    }

    /// [`Subtree::bounds_and_mask`] without the mask.
    fn bounds_of(&self, ids: &[u8]) -> (Aabb, Aabb) {
        let (b, c, _) = self.bounds_and_mask(ids);
        (b, c)
    }

    /// The box and the centroid bounds of the primitives `ids`, and their mask (bit `id`
    /// set for each).
    fn bounds_and_mask(&self, ids: &[u8]) -> (Aabb, Aabb, u64) {
        let (mut lo, mut hi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        let (mut clo, mut chi) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        let mut mask = 0u64;
        for &i in ids {
            mask |= 1 << (i & 63);
            let i = i as usize;
            lo = lo.min(self.min[i]);
            hi = hi.max(self.max[i]);
            clo = clo.min(self.centre[i]);
            chi = chi.max(self.centre[i]);
        }
        let aabb = |min: Vec3A, max: Vec3A| Aabb {
            min: min.into(),
            max: max.into(),
        };
        (aabb(lo, hi), aabb(clo, chi), mask)
    }

    /// The cheapest split over the three sorted lists: (cost, axis, left count).
    ///
    /// The three axes are swept in lock step, one SIMD lane each ([`super::half_areas`]).
    fn sweep(&mut self, lists: &[&mut [u8]; 3], bounds: &Aabb, cb: &Aabb) -> (f32, usize, usize) {
        let n = lists[0].len();
        let [l0, l1, l2] = lists;
        let grow = |lo: &mut [Vec3A; 3], hi: &mut [Vec3A; 3], i: usize| {
            let ids = [l0[i] as usize, l1[i] as usize, l2[i] as usize];
            lo[0] = lo[0].min(self.min[ids[0]]);
            lo[1] = lo[1].min(self.min[ids[1]]);
            lo[2] = lo[2].min(self.min[ids[2]]);
            hi[0] = hi[0].max(self.max[ids[0]]);
            hi[1] = hi[1].max(self.max[ids[1]]);
            hi[2] = hi[2].max(self.max[ids[2]]);
            // Half areas: the factor 2 cancels in every comparison and in the cost.
            super::half_areas(lo, hi)
        };
        let empty = || ([Vec3A::INFINITY; 3], [Vec3A::NEG_INFINITY; 3]);
        let (mut lo, mut hi) = empty();
        for i in (1..n).rev() {
            self.right_area[i] = grow(&mut lo, &mut hi, i);
        }
        let (mut lo, mut hi) = empty();
        let (mut best, mut at) = (Vec3A::INFINITY, Vec3A::ZERO);
        for i in 0..n - 1 {
            let left = grow(&mut lo, &mut hi, i);
            let (nl, nr) = ((i + 1) as f32, (n - i - 1) as f32);
            let w = Vec3A::splat(nl) * left + Vec3A::splat(nr) * self.right_area[i + 1];
            let better = w.cmplt(best);
            best = Vec3A::select(better, w, best);
            at = Vec3A::select(better, Vec3A::splat(nl), at);
        }
        // Axes along which every centroid is the same cannot be split; ties go to the
        // lower axis, then (strict `<` above) to the first position.
        let ext = cb.extent();
        let (mut w, mut axis) = (f32::INFINITY, 0);
        for a in 0..3 {
            if ext[a] > 0.0 && best[a] < w {
                (w, axis) = (best[a], a);
            }
        }
        let half_area = bounds.surface_area() * 0.5;
        let cost = self.opts.cost_traversal + self.opts.cost_intersection * w / half_area;
        (cost, axis, at[axis] as usize)
    }

    /// A node of two primitives split into two leaves, `ids` in the sweep's order: what
    /// [`Subtree::node`] would write, without splitting lists or recursing (on igea, two
    /// in five of the interior nodes).
    #[allow(clippy::too_many_arguments)]
    fn two_leaves(
        &self,
        ids: &[u8],
        out: &mut [PrimRef],
        offset: usize,
        bounds: Aabb,
        axis: usize,
        slots: &mut [FlatNode],
        base: usize,
    ) -> Built {
        let at = offset - self.offset;
        for (k, &id) in ids[..2].iter().enumerate() {
            out[at + k] = self.refs[id as usize];
            let (b, _) = self.bounds_of(&ids[k..k + 1]);
            super::recursion::write_leaf(&mut slots[1 + k..], &b, offset + k, 1);
        }
        super::recursion::write_interior(slots, &bounds, axis, base + 2);
        Built {
            depth: 1,
            extent: 3,
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn node(
        &mut self,
        lists: [&mut [u8]; 3],
        out: &mut [PrimRef],
        offset: usize,
        depth: usize,
        bounds: Aabb,
        cb: Aabb,
        slots: &mut [FlatNode],
        base: usize,
    ) -> Built {
        let n = lists[0].len();
        let opts = self.opts;
        let leaf =
            |s: &Self, lists: &[&mut [u8]; 3], out: &mut [PrimRef], slots: &mut [FlatNode]| {
                let at = offset - s.offset;
                for (o, &id) in out[at..at + n].iter_mut().zip(lists[0].iter()) {
                    *o = s.refs[id as usize];
                }
                super::recursion::write_leaf(slots, &bounds, offset, n);
                Built {
                    depth: 0,
                    extent: 1,
                }
            };
        if n == 1 {
            return leaf(self, &lists, out, slots);
        }
        let degenerate = cb.extent().max_element() <= 0.0;
        let (axis, mid) = if degenerate || depth >= opts.max_depth {
            if n <= opts.max_leaf_size {
                return leaf(self, &lists, out, slots);
            }
            // The object median, as `median_split` takes it.
            (cb.longest_axis(), n / 2)
        } else {
            let (cost, axis, mid) = self.sweep(&lists, &bounds, &cb);
            if n <= opts.max_leaf_size && !(cost < opts.cost_intersection * n as f32) {
                return leaf(self, &lists, out, slots);
            }
            if cost.is_finite() {
                (axis, mid)
            } else {
                (cb.longest_axis(), n / 2)
            }
        };
        if n == 2 {
            debug_assert_eq!(mid, 1);
            return self.two_leaves(lists[axis], out, offset, bounds, axis, slots, base);
        }
        // Each side's bounds, and the left side as a mask of ids, from the split axis's
        // list; then the other two lists split in one loop. Short loops of unpredictable
        // length each cost a mispredicted exit, so there are few of them.
        let (lb, lc, left) = self.bounds_and_mask(&lists[axis][..mid]);
        let (rb, rc) = self.bounds_of(&lists[axis][mid..]);
        let [mut a0, mut a1, mut a2] = lists;
        let (p, q) = match axis {
            0 => (&mut a1, &mut a2),
            1 => (&mut a0, &mut a2),
            _ => (&mut a0, &mut a1),
        };
        // Without a branch on the side (it is as likely either way): each id is written
        // to both sides, and only its own side's count moves on. The left ids move down in
        // place (never past the one being read); ids and counts are below 64, so the mask
        // only spares the bounds check.
        let (mut p_right, mut q_right) = ([0u8; 64], [0u8; 64]);
        let (mut pi, mut pj, mut qi, mut qj) = (0, 0, 0, 0);
        for t in 0..n {
            let (x, y) = (p[t], q[t]);
            let x_left = (left >> (x & 63)) as usize & 1;
            let y_left = (left >> (y & 63)) as usize & 1;
            p[pi] = x;
            p_right[pj & 63] = x;
            pi += x_left;
            pj += 1 - x_left;
            q[qi] = y;
            q_right[qj & 63] = y;
            qi += y_left;
            qj += 1 - y_left;
        }
        // Byte by byte: a call to `memcpy` costs more at these lengths.
        for (t, (&x, &y)) in p_right[..n - mid].iter().zip(&q_right).enumerate() {
            p[mid + t] = x;
            q[mid + t] = y;
        }
        let (l0, r0) = a0.split_at_mut(mid);
        let (l1, r1) = a1.split_at_mut(mid);
        let (l2, r2) = a2.split_at_mut(mid);
        let l = self.node(
            [l0, l1, l2],
            out,
            offset,
            depth + 1,
            lb,
            lc,
            &mut slots[1..],
            base + 1,
        );
        // Built on one thread: the second child right after the first's last node.
        let at = 1 + l.extent;
        let r = self.node(
            [r0, r1, r2],
            out,
            offset + mid,
            depth + 1,
            rb,
            rc,
            &mut slots[at..],
            base + at,
        );
        super::recursion::write_interior(slots, &bounds, axis, base + at);
        Built {
            depth: 1 + l.depth.max(r.depth),
            extent: at + r.extent,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn packed_and_paired_keys_order_alike() {
        // Centroids with many ties on every axis, so that the index decides often.
        let refs = |base: u32| -> Vec<PrimRef> {
            (0..SMALL_NODE as u32)
                .map(|i| {
                    let c = Vec3::new((i % 3) as f32, -((i % 4) as f32), (i * 37 % 11) as f32);
                    // Indices in an order of their own, not the positions'.
                    PrimRef::new(c - 0.5, c + 0.5, base + (i * 29) % 97)
                })
                .collect()
        };
        let opts = BuildOptions::default();
        let (small, large) = (refs(0), refs(PACKED_INDEX));
        for n in [1, 2, 7, SMALL_NODE] {
            let packed = sorted_lists(&Subtree::new(&small[..n], &opts, 0), n);
            let paired = sorted_lists(&Subtree::new(&large[..n], &opts, 0), n);
            assert_eq!(packed, paired, "n = {n}");
            // And both follow (centroid, index), axis by axis.
            for (a, list) in packed.iter().enumerate() {
                for w in list[..n].windows(2) {
                    let (p, q) = (&small[w[0] as usize], &small[w[1] as usize]);
                    let key = |r: &PrimRef| (r.centroid()[a], r.index());
                    assert!(
                        key(p) < key(q),
                        "axis {a}: {:?} before {:?}",
                        key(p),
                        key(q)
                    );
                }
            }
        }
    }
}
