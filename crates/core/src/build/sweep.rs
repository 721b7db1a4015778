//! Full-sweep SAH: sort the centroids along each axis and evaluate every split between
//! consecutive primitives. O(n log n) per node; the reference for SAH quality.

use super::{BuildOptions, PrimRef, Split, split_cost};
use crate::geometry::Aabb;

fn key_cmp(a: &PrimRef, b: &PrimRef, axis: usize) -> std::cmp::Ordering {
    a.centroid()[axis]
        .total_cmp(&b.centroid()[axis])
        .then(a.index.cmp(&b.index))
}

/// Chooses and applies the cheapest split over all sorted positions.
pub(super) fn split(refs: &mut [PrimRef], bounds: &Aabb, cb: &Aabb, opts: &BuildOptions) -> Split {
    let n = refs.len();
    let area = bounds.surface_area();
    let mut small = [0f32; 32];
    let mut big = Vec::new();
    let right_area: &mut [f32] = if n <= small.len() {
        &mut small[..n]
    } else {
        big.resize(n, 0f32);
        &mut big
    };
    let mut best = (f32::INFINITY, 0usize, 0usize);
    let mut sorted_on = usize::MAX;
    for axis in 0..3 {
        if cb.extent()[axis] <= 0.0 {
            continue;
        }
        refs.sort_unstable_by(|a, b| key_cmp(a, b, axis));
        sorted_on = axis;
        let mut acc = Aabb::EMPTY;
        for i in (1..n).rev() {
            acc = acc.union(&refs[i].bounds());
            right_area[i] = acc.surface_area();
        }
        let mut left = Aabb::EMPTY;
        for i in 0..n - 1 {
            left = left.union(&refs[i].bounds());
            let cost = split_cost(
                opts,
                area,
                i + 1,
                left.surface_area(),
                n - i - 1,
                right_area[i + 1],
            );
            if cost < best.0 {
                best = (cost, axis, i + 1);
            }
        }
    }
    let (cost, axis, mid) = best;
    if !cost.is_finite() {
        return Split::Leaf;
    }
    if n <= opts.max_leaf_size && cost >= opts.cost_intersection * n as f32 {
        return Split::Leaf;
    }
    if sorted_on != axis {
        refs.sort_unstable_by(|a, b| key_cmp(a, b, axis));
    }
    Split::At { axis, mid }
}
