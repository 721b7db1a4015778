//! Binned SAH (Wald 2007; PBRT-v4's `BVHAggregate`): bin centroids along each axis,
//! sweep the bin boundaries, partition at the cheapest. The children's boxes come out of
//! the bins and their centroid bounds out of the partition, so no other pass is needed.

use glam::Vec3A;

use super::{BuildOptions, PrimRef, Split, split_weight};
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
    #[inline(always)]
    fn area(self) -> f32 {
        let e = self.max - self.min;
        if e.x < 0.0 {
            return 0.0;
        }
        2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
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
        let (min, max) = (Vec3A::from(r.min), Vec3A::from(r.max));
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
    let mut best = (f32::INFINITY, 0usize, 0usize); // cost, axis, last bin on the left
    let mut right_area = [0f32; MAX_BINS];
    for (a, &s) in scale.iter().enumerate() {
        if s == 0.0 {
            continue;
        }
        let o = a * bins;
        // Suffix areas, then a prefix sweep.
        let mut acc = BoxA::EMPTY;
        for k in (1..bins).rev() {
            let b = &binned.0[o + k];
            acc = acc.union(BoxA {
                min: b.min,
                max: b.max,
            });
            right_area[k] = acc.area();
        }
        let mut left = BoxA::EMPTY;
        let mut n_l = 0usize;
        for k in 0..bins - 1 {
            let b = &binned.0[o + k];
            left = left.union(BoxA {
                min: b.min,
                max: b.max,
            });
            n_l += b.count as usize;
            let n_r = n - n_l;
            if n_l == 0 || n_r == 0 {
                continue;
            }
            let w = split_weight(n_l, left.area(), n_r, right_area[k + 1]);
            if w < best.0 {
                best = (w, a, k);
            }
        }
    }
    let (w, axis, k) = best;
    let cost = opts.cost_traversal + opts.cost_intersection * w / area;
    if !cost.is_finite() {
        return Split::Leaf;
    }
    if n <= opts.max_leaf_size && cost >= opts.cost_intersection * n as f32 {
        return Split::Leaf;
    }
    let (mid, centroids) = partition(refs, |r| at.of_axis(r.min[axis], r.max[axis], axis) <= k);
    if mid == 0 || mid == n {
        return super::median_split(refs, axis);
    }
    let o = axis * bins;
    Split::Known {
        axis,
        mid,
        children: [
            (binned.box_of(o..o + k + 1).aabb(), centroids[0]),
            (binned.box_of(o + k + 1..o + bins).aabb(), centroids[1]),
        ],
    }
}

/// In-place partition (Hoare's: each misplaced pair swapped once): refs satisfying `left`
/// first. Returns their count and both sides' centroid bounds, gathered on the way.
fn partition(refs: &mut [PrimRef], left: impl Fn(&PrimRef) -> bool) -> (usize, [Aabb; 2]) {
    let mut c = [BoxA::EMPTY; 2];
    let centre = |r: &PrimRef| {
        let (min, max) = (Vec3A::from(r.min), Vec3A::from(r.max));
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
