//! Tree quality: SAH cost in two conventions, depth, counts, leaf-size histogram.

use crate::flat::FlatBvh;

/// Quality figures of a flat BVH.
#[derive(Clone, Debug, PartialEq)]
pub struct BvhStats {
    /// Number of triangle slots (`FlatBvh::triangles`): the references, which for an SBVH
    /// ([`crate::BuilderKind::Sbvh`]) may name a triangle several times; the leaf costs
    /// below count these, since each is a test.
    pub triangles: usize,
    /// Number of distinct triangles (primitive ids) among them, summed over the meshes of
    /// a two-level BVH: `triangles / primitives` is an SBVH's duplication.
    pub primitives: usize,
    /// Number of nodes, interior and leaves.
    pub nodes: usize,
    /// Number of leaves.
    pub leaves: usize,
    /// Longest root-to-leaf path, in edges ([`FlatBvh::depth`]).
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
            primitives: distinct_primitives(bvh),
            nodes: bvh.nodes.len(),
            leaves,
            depth: bvh.depth,
            sah_cost: norm(a),
            sah_cost_pbrt: norm(b),
            leaf_sizes,
        }
    }
}

/// Distinct primitive ids in the triangle slots, per mesh tree (a two-level BVH numbers
/// each mesh's primitives from 0).
fn distinct_primitives(bvh: &FlatBvh) -> usize {
    let mut roots: Vec<u32> = bvh.instances.iter().map(|i| i.root).collect();
    if roots.is_empty() && !bvh.nodes.is_empty() {
        roots.push(0);
    }
    roots.sort_unstable();
    roots.dedup();
    roots
        .iter()
        .map(|&root| {
            // The mesh's triangles: the range its leaves span.
            let (mut lo, mut hi) = (usize::MAX, 0);
            let mut stack = vec![root as usize];
            while let Some(i) = stack.pop() {
                let Some(n) = bvh.nodes.get(i) else { continue };
                if n.is_leaf() {
                    let f = n.right_or_first as usize;
                    lo = lo.min(f);
                    hi = hi.max(f + n.count() as usize);
                } else {
                    stack.extend([i + 1, n.right_or_first as usize]);
                }
            }
            let tris = bvh.triangles.get(lo..hi).unwrap_or_default();
            let mut seen = vec![false; tris.len()];
            let mut other = std::collections::HashSet::new();
            tris.iter()
                .filter(|t| match seen.get_mut(t.prim as usize) {
                    Some(s) => !std::mem::replace(s, true),
                    None => other.insert(t.prim),
                })
                .count()
        })
        .sum()
}
