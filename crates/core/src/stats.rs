//! Tree quality: SAH cost in two conventions, depth, counts, leaf-size histogram; and the
//! colour ramp that shows per-ray counters as a heatmap.

use crate::flat::FlatBvh;

/// Quality figures of a flat BVH.
#[derive(Clone, Debug, PartialEq)]
pub struct BvhStats {
    pub triangles: usize,
    pub nodes: usize,
    pub leaves: usize,
    pub depth: u32,
    /// SAH cost with traversal 1 and intersection 1, summed over nodes (interior: area;
    /// leaf: area x triangles) and divided by the root's area: tinybvh's `SAHCost`
    /// convention, so the figures compare.
    pub sah_cost: f64,
    /// The same with PBRT's costs (traversal 1/8, intersection 1).
    pub sah_cost_pbrt: f64,
    /// `leaf_sizes[k]` = number of leaves holding `k` triangles.
    pub leaf_sizes: Vec<usize>,
}

impl BvhStats {
    /// Computes the figures.
    pub fn of(bvh: &FlatBvh) -> Self {
        let root_area = bvh.nodes[0].aabb().surface_area() as f64;
        let (mut a, mut b) = (0f64, 0f64);
        let mut leaves = 0;
        let mut leaf_sizes = Vec::new();
        for n in &bvh.nodes {
            let area = n.aabb().surface_area() as f64;
            if n.is_leaf() {
                let c = n.count() as usize;
                leaves += 1;
                a += area * c as f64;
                b += area * c as f64;
                if leaf_sizes.len() <= c {
                    leaf_sizes.resize(c + 1, 0);
                }
                leaf_sizes[c] += 1;
            } else {
                a += area;
                b += area * 0.125;
            }
        }
        let norm = |x: f64| if root_area > 0.0 { x / root_area } else { 0.0 };
        BvhStats {
            triangles: bvh.triangles.len(),
            nodes: bvh.nodes.len(),
            leaves,
            depth: bvh.depth,
            sah_cost: norm(a),
            sah_cost_pbrt: norm(b),
            leaf_sizes,
        }
    }
}

/// The heatmap colour for `x` in [0, 1] (blue, cyan, green, yellow, red; NaN as 0): how
/// `bvhtrace render --shade heatmap` and the viewer show boxes tested per pixel, so their
/// images match.
pub fn heat_ramp(x: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [0.05, 0.05, 0.45],
        [0.0, 0.7, 0.9],
        [0.1, 0.8, 0.2],
        [0.95, 0.85, 0.1],
        [0.85, 0.1, 0.05],
    ];
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) } * 4.0;
    let i = (x as usize).min(3);
    let f = x - i as f32;
    let c = |k: usize| (STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f) * 255.0;
    [c(0) as u8, c(1) as u8, c(2) as u8]
}
