//! Binned SAH (Wald 2007; PBRT-v4's `BVHAggregate`): bin centroids along each axis,
//! sweep the bin boundaries, partition at the cheapest. The bins also carry centroid
//! bounds, so the children's boxes come out of the sweep without another pass.

use glam::Vec3A;

use super::{BuildOptions, PrimRef, Split, partition, split_cost};
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

#[derive(Clone, Copy)]
struct Bin {
    bounds: BoxA,
    centroids: BoxA,
    count: u32,
}

const EMPTY_BIN: Bin = Bin {
    bounds: BoxA::EMPTY,
    centroids: BoxA::EMPTY,
    count: 0,
};

/// Bin index of a centroid coordinate. Used for binning and for partitioning, so both
/// agree exactly.
#[inline(always)]
fn bin_of(c: f32, lo: f32, scale: f32, bins: usize) -> usize {
    (((c - lo) * scale) as usize).min(bins - 1)
}

/// Bins of all three axes in one pass (`out[axis * bins + k]`).
fn bin_refs(refs: &[PrimRef], cb: &Aabb, scale: [f32; 3], bins: usize) -> Vec<Bin> {
    let mut out = vec![EMPTY_BIN; 3 * bins];
    for r in refs {
        let b = BoxA {
            min: r.min.into(),
            max: r.max.into(),
        };
        let c = (b.min + b.max) * 0.5;
        let cbox = BoxA { min: c, max: c };
        for a in 0..3 {
            if scale[a] > 0.0 {
                let k = bin_of(c[a], cb.min[a], scale[a], bins);
                let bin = &mut out[a * bins + k];
                bin.bounds = bin.bounds.union(b);
                bin.centroids = bin.centroids.union(cbox);
                bin.count += 1;
            }
        }
    }
    out
}

fn merge(mut a: Vec<Bin>, b: Vec<Bin>) -> Vec<Bin> {
    for (x, y) in a.iter_mut().zip(b) {
        x.bounds = x.bounds.union(y.bounds);
        x.centroids = x.centroids.union(y.centroids);
        x.count += y.count;
    }
    a
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
    let ext = cb.extent();
    let scale = [0, 1, 2].map(|a| {
        if ext[a] > 0.0 {
            bins as f32 / ext[a]
        } else {
            0.0
        }
    });
    // Integer counts and min/max are exact under any reduction order: deterministic.
    let binned = if parallel && n >= 32 * 1024 {
        use rayon::prelude::*;
        refs.par_chunks(8 * 1024)
            .map(|ch| bin_refs(ch, cb, scale, bins))
            .reduce(|| vec![EMPTY_BIN; 3 * bins], merge)
    } else {
        bin_refs(refs, cb, scale, bins)
    };

    let area = bounds.surface_area();
    let mut best = (f32::INFINITY, 0usize, 0usize); // cost, axis, last bin on the left
    let mut right_area = [0f32; MAX_BINS];
    for a in 0..3 {
        if scale[a] == 0.0 {
            continue;
        }
        let bin = &binned[a * bins..(a + 1) * bins];
        // Suffix areas, then a prefix sweep.
        let mut acc = BoxA::EMPTY;
        for k in (1..bins).rev() {
            acc = acc.union(bin[k].bounds);
            right_area[k] = acc.area();
        }
        let mut left = BoxA::EMPTY;
        let mut n_l = 0usize;
        for k in 0..bins - 1 {
            left = left.union(bin[k].bounds);
            n_l += bin[k].count as usize;
            let n_r = n - n_l;
            if n_l == 0 || n_r == 0 {
                continue;
            }
            let cost = split_cost(opts, area, n_l, left.area(), n_r, right_area[k + 1]);
            if cost < best.0 {
                best = (cost, a, k);
            }
        }
    }
    let (cost, axis, k) = best;
    if !cost.is_finite() {
        return Split::Leaf;
    }
    if n <= opts.max_leaf_size && cost >= opts.cost_intersection * n as f32 {
        return Split::Leaf;
    }
    let (lo, s) = (cb.min[axis], scale[axis]);
    let mid = partition(refs, |r| bin_of(r.centroid()[axis], lo, s, bins) <= k);
    if mid == 0 || mid == n {
        return super::median_split(refs, axis);
    }
    let bin = &binned[axis * bins..(axis + 1) * bins];
    let side = |range: &[Bin]| {
        let (b, c) = range.iter().fold((BoxA::EMPTY, BoxA::EMPTY), |(b, c), x| {
            (b.union(x.bounds), c.union(x.centroids))
        });
        (b.aabb(), c.aabb())
    };
    Split::Known {
        axis,
        mid,
        children: [side(&bin[..=k]), side(&bin[k + 1..])],
    }
}
