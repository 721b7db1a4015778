//! Binned SAH (Wald 2007; PBRT-v4's `BVHAggregate`): bin centroids along each axis,
//! sweep the bin boundaries, partition at the cheapest. The children's boxes come out of
//! the bins and their centroid bounds out of the partition, so no other pass is needed.

use glam::{BVec3A, Vec3A};

use super::{BuildOptions, PrimRef, Split, half_areas};
use crate::geometry::Aabb;

const MAX_BINS: usize = 256;

/// A box in SIMD registers.
#[derive(Clone, Copy)]
struct BoxA {
    min: Vec3A,
    max: Vec3A,
}

impl BoxA {
    const EMPTY: BoxA = BoxA {
        min: Vec3A::splat(f32::INFINITY),
        max: Vec3A::splat(f32::NEG_INFINITY),
    };
    #[inline(always)]
    fn union(self, o: BoxA) -> BoxA {
        BoxA {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }
    fn aabb(self) -> Aabb {
        Aabb {
            min: self.min.into(),
            max: self.max.into(),
        }
    }
}

/// One bin: the box around its refs, and how many there are.
#[derive(Clone, Copy)]
struct Bin {
    min: Vec3A,
    max: Vec3A,
    count: u32,
}

/// The bins of all three axes, `bins[axis * count + k]`. Only boxes and counts are
/// binned; the children's centroid bounds come out of the partition pass.
#[derive(Clone)]
struct Bins(Vec<Bin>);

impl Bins {
    fn new(bins: usize) -> Bins {
        let empty = Bin {
            min: Vec3A::INFINITY,
            max: Vec3A::NEG_INFINITY,
            count: 0,
        };
        Bins(vec![empty; 3 * bins])
    }
    fn box_of(&self, range: std::ops::Range<usize>) -> BoxA {
        let mut b = BoxA::EMPTY;
        for x in &self.0[range] {
            b = b.union(BoxA {
                min: x.min,
                max: x.max,
            });
        }
        b
    }
}

/// Where centroids fall: bin `k` along an axis holds `(c - lo) * scale` in `[k, k + 1)`,
/// the last bin also everything beyond.
#[derive(Clone, Copy)]
struct Binning {
    lo: Vec3A,
    scale: Vec3A,
    last: Vec3A,
}

impl Binning {
    /// The bin of a ref along every axis. Binning and partitioning both call this, so
    /// they agree exactly.
    #[inline(always)]
    fn of(&self, min: Vec3A, max: Vec3A) -> [usize; 3] {
        let c = (min + max) * 0.5;
        // `max` then `min` put every lane in [0, bins - 1] and turn a NaN (a subnormal
        // extent's 0 * inf) into 0: SSE's max returns its second operand for a NaN.
        let k = ((c - self.lo) * self.scale).max(Vec3A::ZERO).min(self.last);
        [truncate(k.x), truncate(k.y), truncate(k.z)]
    }

    /// [`Binning::of`] along one axis only, with the same arithmetic lane by lane.
    #[inline(always)]
    fn of_axis(&self, min: f32, max: f32, axis: usize) -> usize {
        let c = (min + max) * 0.5;
        let k = Vec3A::splat((c - self.lo[axis]) * self.scale[axis]);
        truncate(k.max(Vec3A::ZERO).min(self.last).x)
    }
}

/// `k as usize` for a `k` known to be in `[0, 255]`, without the saturating cast's checks.
#[inline(always)]
fn truncate(k: f32) -> usize {
    debug_assert!((0.0..256.0).contains(&k));
    // SAFETY: `Binning` clamps every value to [0, bins - 1] (bins <= 256) and maps NaN to
    // 0, so the value is finite and fits an i32.
    unsafe { k.to_int_unchecked::<i32>() as usize }
}

/// Bins the refs of all three axes in one pass. Alternate refs go to two sets of bins,
/// merged at the end: neighbouring refs often fall in the same bin, and one set would
/// make each update wait for the previous one.
fn bin_refs(refs: &[PrimRef], at: &Binning, bins: usize) -> Bins {
    let mut out = [Bins::new(bins), Bins::new(bins)];
    let add = |out: &mut Bins, r: &PrimRef| {
        let (min, max) = (r.min(), r.max());
        let k = at.of(min, max);
        for (a, k) in k.into_iter().enumerate() {
            debug_assert!(k < bins);
            // SAFETY: `Binning::of` gives k <= bins - 1, so the index is below 3 * bins,
            // the length. This loop is the builder's hottest: no bounds checks here.
            let b = unsafe { out.0.get_unchecked_mut(a * bins + k) };
            b.min = b.min.min(min);
            b.max = b.max.max(max);
            b.count += 1;
        }
    };
    let mut pairs = refs.chunks_exact(2);
    for p in &mut pairs {
        add(&mut out[0], &p[0]);
        add(&mut out[1], &p[1]);
    }
    for r in pairs.remainder() {
        add(&mut out[0], r);
    }
    let [a, b] = out;
    merge(a, b)
}

fn merge(mut a: Bins, b: Bins) -> Bins {
    for (x, y) in a.0.iter_mut().zip(b.0) {
        x.min = x.min.min(y.min);
        x.max = x.max.max(y.max);
        x.count += y.count;
    }
    a
}

/// Bins per unit of centroid extent along each axis; 0 along an axis where every
/// centroid is the same (it is not split there).
pub(super) fn bin_scale(cb: &Aabb, bins: usize) -> [f32; 3] {
    let ext = cb.extent();
    [0, 1, 2].map(|a| {
        if ext[a] > 0.0 {
            bins as f32 / ext[a]
        } else {
            0.0
        }
    })
}

/// Chooses and applies the cheapest binned split, or says the node should be a leaf.
pub(super) fn split(
    refs: &mut [PrimRef],
    bounds: &Aabb,
    cb: &Aabb,
    opts: &BuildOptions,
    parallel: bool,
) -> Split {
    let bins = opts.bins.min(MAX_BINS);
    let n = refs.len();
    let scale = bin_scale(cb, bins);
    let at = Binning {
        lo: cb.min.into(),
        scale: Vec3A::from_array(scale),
        last: Vec3A::splat((bins - 1) as f32),
    };
    // Integer counts and min/max are exact under any reduction order: deterministic.
    let binned = if parallel && n >= 32 * 1024 {
        use rayon::prelude::*;
        refs.par_chunks(8 * 1024)
            .map(|ch| bin_refs(ch, &at, bins))
            .reduce(|| Bins::new(bins), merge)
    } else {
        bin_refs(refs, &at, bins)
    };

    let area = bounds.surface_area();
    let best = cheapest(&binned, bins, n, &scale);
    let (w, axis, k) = best;
    let cost = opts.cost_traversal + opts.cost_intersection * w / area;
    if !cost.is_finite() {
        return Split::Leaf;
    }
    if n <= opts.max_leaf_size && cost >= opts.cost_intersection * n as f32 {
        return Split::Leaf;
    }
    let o = axis * bins;
    let lefts = binned.0[o..=o + k].iter().map(|b| b.count as usize).sum();
    let left = |r: &PrimRef| at.of_axis(r.min()[axis], r.max()[axis], axis) <= k;
    let (mid, centroids) = partition_at(refs, lefts, left);
    if mid == 0 || mid == n {
        return super::median_split(refs, axis);
    }
    Split::Known {
        axis,
        mid,
        children: [
            (binned.box_of(o..o + k + 1).aabb(), centroids[0]),
            (binned.box_of(o + k + 1..o + bins).aabb(), centroids[1]),
        ],
    }
}

/// The cheapest split between bins over all three axes: (weight, axis, last bin on the
/// left). The axes are swept in lock step, one SIMD lane each ([`half_areas`]), with
/// each lane's arithmetic the scalar sweep's: the same weights, and ties to the lowest
/// axis, then the first bin.
fn cheapest(binned: &Bins, bins: usize, n: usize, scale: &[f32; 3]) -> (f32, usize, usize) {
    let b = &binned.0;
    // The three axes' boxes grown by bin `k` of each, and their areas in lanes.
    let grow = |lo: &mut [Vec3A; 3], hi: &mut [Vec3A; 3], k: usize| {
        for a in 0..3 {
            let bin = &b[a * bins + k];
            lo[a] = lo[a].min(bin.min);
            hi[a] = hi[a].max(bin.max);
        }
        2.0 * half_areas(lo, hi)
    };
    let empty = || ([Vec3A::INFINITY; 3], [Vec3A::NEG_INFINITY; 3]);
    let mut right_area = [Vec3A::ZERO; MAX_BINS];
    let (mut lo, mut hi) = empty();
    for k in (1..bins).rev() {
        right_area[k] = grow(&mut lo, &mut hi, k);
    }
    let (mut lo, mut hi) = empty();
    let mut n_l = [0u32; 3];
    let (mut best, mut at) = (Vec3A::INFINITY, [0usize; 3]);
    for k in 0..bins - 1 {
        let left = grow(&mut lo, &mut hi, k);
        for (a, c) in n_l.iter_mut().enumerate() {
            *c += b[a * bins + k].count;
        }
        let nl = Vec3A::new(n_l[0] as f32, n_l[1] as f32, n_l[2] as f32);
        let nr = Vec3A::new(
            (n - n_l[0] as usize) as f32,
            (n - n_l[1] as usize) as f32,
            (n - n_l[2] as usize) as f32,
        );
        // A side with no refs is no split.
        let [a, b2, c] = n_l.map(|c| c > 0 && (c as usize) < n);
        let both = BVec3A::new(a, b2, c);
        let w = nl * left + nr * right_area[k + 1];
        let better = both & w.cmplt(best);
        best = Vec3A::select(better, w, best);
        let mask = better.bitmask();
        for (a, at) in at.iter_mut().enumerate() {
            if mask & (1 << a) != 0 {
                *at = k;
            }
        }
    }
    let mut out = (f32::INFINITY, 0usize, 0usize);
    for (a, &s) in scale.iter().enumerate() {
        // An axis along which every centroid is the same is not split.
        if s != 0.0 && best[a] < out.0 {
            out = (best[a], a, at[a]);
        }
    }
    out
}

/// In-place partition of refs of which `lefts` satisfy `left` (the bins counted them):
/// those first. Returns their count and both sides' centroid bounds.
///
/// Knowing the count, the refs in `[0, lefts)` that belong right and those in
/// `[lefts, n)` that belong left are equally many, and are swapped pairwise. Each side is
/// scanned a block at a time, the misplaced refs' offsets recorded without a branch on
/// their side (after BlockQuicksort, Edelkamp and Weiß 2016): which side a ref falls is
/// close to a coin toss, and a branch on it mispredicts about every other ref. Should the
/// count be wrong, the refs are partitioned again by [`partition`].
fn partition_at(
    refs: &mut [PrimRef],
    lefts: usize,
    left: impl Fn(&PrimRef) -> bool,
) -> (usize, [Aabb; 2]) {
    const BLOCK: usize = 64;
    let n = refs.len();
    if lefts > n {
        return partition(refs, left);
    }
    let mut c = [BoxA::EMPTY; 2];
    // Scans `refs[from..to]` (at most BLOCK), growing each side's centroid bounds, and
    // records the offsets of the refs whose side is `misplaced` (left: true). Returns
    // how many.
    let scan = |refs: &[PrimRef],
                from: usize,
                misplaced: bool,
                off: &mut [u8; BLOCK],
                c: &mut [BoxA; 2]| {
        let mut k = 0;
        for (t, r) in refs[from..].iter().take(BLOCK).enumerate() {
            let (min, max) = (r.min(), r.max());
            let p = (min + max) * 0.5;
            let l = left(r);
            off[k] = t as u8;
            k += (l == misplaced) as usize;
            // -inf for a left ref, +inf for a right one: clamping the centroid by it
            // (or its negation) gives the centroid on its own side, an identity there.
            let side = Vec3A::splat(f32::from_bits(f32::INFINITY.to_bits() | (l as u32) << 31));
            c[0].min = c[0].min.min(p.max(side));
            c[0].max = c[0].max.max(p.min(-side));
            c[1].min = c[1].min.min(p.max(-side));
            c[1].max = c[1].max.max(p.min(side));
        }
        k
    };
    // Each side: the next ref to scan, the scanned block's start, its misplaced offsets,
    // how many there are and how many have been swapped.
    let (mut l_next, mut l_at, mut l_off, mut l_len, mut l_done) = (0, 0, [0u8; BLOCK], 0, 0);
    let (mut r_next, mut r_at, mut r_off, mut r_len, mut r_done) =
        (lefts, lefts, [0u8; BLOCK], 0, 0);
    loop {
        if l_done == l_len && l_next < lefts {
            let to = (l_next + BLOCK).min(lefts);
            l_len = scan(&refs[..to], l_next, false, &mut l_off, &mut c);
            (l_at, l_done, l_next) = (l_next, 0, to);
            continue;
        }
        if r_done == r_len && r_next < n {
            r_len = scan(refs, r_next, true, &mut r_off, &mut c);
            (r_at, r_done, r_next) = (r_next, 0, (r_next + BLOCK).min(n));
            continue;
        }
        if l_done == l_len || r_done == r_len {
            break;
        }
        let k = (l_len - l_done).min(r_len - r_done);
        for (&a, &b) in l_off[l_done..l_done + k]
            .iter()
            .zip(&r_off[r_done..r_done + k])
        {
            refs.swap(l_at + a as usize, r_at + b as usize);
        }
        l_done += k;
        r_done += k;
    }
    if l_done == l_len && r_done == r_len {
        (lefts, c.map(BoxA::aabb))
    } else {
        partition(refs, left)
    }
}

/// In-place partition (Hoare's: each misplaced pair swapped once): refs satisfying `left`
/// first. Returns their count and both sides' centroid bounds, gathered on the way.
fn partition(refs: &mut [PrimRef], left: impl Fn(&PrimRef) -> bool) -> (usize, [Aabb; 2]) {
    let mut c = [BoxA::EMPTY; 2];
    let centre = |r: &PrimRef| {
        let (min, max) = (r.min(), r.max());
        ((min + max) * 0.5, left(r))
    };
    let (mut i, mut j) = (0, refs.len());
    loop {
        // Skip what is already on its side.
        while i < j {
            let (p, l) = centre(&refs[i]);
            if !l {
                break;
            }
            c[0] = c[0].union(BoxA { min: p, max: p });
            i += 1;
        }
        while i < j {
            let (p, l) = centre(&refs[j - 1]);
            if l {
                break;
            }
            c[1] = c[1].union(BoxA { min: p, max: p });
            j -= 1;
        }
        if i + 1 >= j {
            break;
        }
        // refs[i] belongs right and refs[j - 1] left.
        refs.swap(i, j - 1);
    }
    (i, c.map(BoxA::aabb))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// Refs along x in a scrambled order, each a small box around its centre.
    fn refs(n: usize) -> Vec<PrimRef> {
        (0..n)
            .map(|i| {
                let x = ((i * 7919) % n) as f32;
                let c = Vec3::new(x, (i % 5) as f32, -(i as f32));
                PrimRef::new(c - 0.25, c + 0.25, i as u32)
            })
            .collect()
    }

    /// Checks a partition at `x < cut` against the refs it started from.
    fn check(before: &[PrimRef], after: &[PrimRef], mid: usize, bounds: [Aabb; 2], cut: f32) {
        let is_left = |r: &PrimRef| r.centroid().x < cut;
        assert_eq!(mid, before.iter().filter(|r| is_left(r)).count());
        assert!(after[..mid].iter().all(is_left));
        assert!(!after[mid..].iter().any(is_left));
        let mut ids: Vec<u32> = after.iter().map(PrimRef::index).collect();
        ids.sort_unstable();
        assert!(ids.iter().enumerate().all(|(i, &id)| id as usize == i));
        for (side, refs) in [&after[..mid], &after[mid..]].into_iter().enumerate() {
            let mut c = Aabb::EMPTY;
            for r in refs {
                c.grow(r.centroid().into());
            }
            assert_eq!(bounds[side], c, "side {side}");
        }
    }

    #[test]
    fn block_partition_matches_the_count_and_gathers_both_sides_centroid_bounds() {
        // Sizes around the block's, cuts that leave either side empty, small or large.
        for n in [1, 2, 63, 64, 65, 200, 1000] {
            for cut in [
                -1.0,
                0.5,
                3.5,
                n as f32 / 2.0,
                n as f32 - 1.5,
                n as f32 + 1.0,
            ] {
                let before = refs(n);
                let mut after = before.clone();
                let lefts = before.iter().filter(|r| r.centroid().x < cut).count();
                let (mid, bounds) = partition_at(&mut after, lefts, |r| r.centroid().x < cut);
                check(&before, &after, mid, bounds, cut);
            }
        }
    }

    #[test]
    fn block_partition_told_a_wrong_count_still_partitions() {
        let before = refs(300);
        let cut = 120.5;
        for lefts in [0, 100, 150, 300, 301] {
            let mut after = before.clone();
            let (mid, bounds) = partition_at(&mut after, lefts, |r| r.centroid().x < cut);
            check(&before, &after, mid, bounds, cut);
        }
    }
}
