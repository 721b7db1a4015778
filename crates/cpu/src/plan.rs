//! Which binary nodes become wide nodes: the collapse of least SAH cost (Ylitie, Karras
//! and Laine 2017, "Efficient incoherent ray traversal on GPUs through compressed wide
//! BVHs", section 3.1), over the leaf children the layout fixes ([`is_leaf_child`]).
//!
//! The leaf children are the same whatever the nodes above them, so the cost left to
//! choose is the nodes': each wide node costs its box's surface area (the chance that a
//! ray enters it). A greedy collapse (open the child of largest area until eight) fills
//! the top well but leaves many nodes at the bottom with two or three leaf children; the
//! plan pulls those leaves up into their parents: igea's layout goes from 30,408 nodes to
//! 16,125 for the same 82,375 leaf children.

use bvhtrace_core::FlatNode;

use crate::layout::{Level, Src, SrcList, WIDTH, is_leaf_child};

/// Each planned binary node's least cost as at most `j` slots, `j` = 1 to [`WIDTH`].
type Costs = [f32; WIDTH];

/// The least-cost slot distribution of every binary interior node that is not a leaf
/// child (the others' cost is their own area, computed when asked).
pub(crate) struct Plan {
    /// Index + 1 into `costs` per binary node; 0 where the node was not planned.
    at: Vec<u32>,
    /// `costs[k][j - 1]`: the least cost of the node's subtree as at most `j` slots.
    costs: Vec<Costs>,
}

impl Plan {
    /// Plans every mesh node of `fnodes` (one backward pass: children come after their
    /// parent in the depth-first order).
    pub(crate) fn new(fnodes: &[FlatNode], spans: &[(u32, u32)]) -> Plan {
        // Zeroed memory: only the planned nodes' entries are written.
        let mut plan = Plan {
            at: bytemuck::zeroed_vec(fnodes.len()),
            // A wide tree has a node per two to three leaf children and a binary tree a
            // node per leaf: this is rarely outgrown.
            costs: Vec::with_capacity(fnodes.len() / 4),
        };
        for i in (0..fnodes.len() as u32).rev() {
            if !is_leaf_child(fnodes, spans, Level::Mesh, i) {
                let [l, r] = children(fnodes, i).map(|c| plan.costs_of(fnodes, c));
                // As a wide node of its own: its area and its best eight slots. As `j`
                // slots: the cheaper of that and the best split of `j` between its
                // children.
                let splits = splits(&l, &r);
                let whole = fnodes[i as usize].aabb().surface_area() + splits[WIDTH - 1];
                plan.costs.push(splits.map(|c| whole.min(c)));
                plan.at[i as usize] = plan.costs.len() as u32;
            }
        }
        plan
    }

    /// Binary node `i`'s costs. A leaf child's are its area for any number of slots: the
    /// nodes above it do not change how often it is entered, so that is only a constant.
    /// A node not planned yet (out of the depth-first order: a tree flattened by hand) is
    /// taken as one slot too.
    #[inline(always)]
    fn costs_of(&self, fnodes: &[FlatNode], i: u32) -> Costs {
        match self.at.get(i as usize) {
            Some(&k) if k > 0 => self.costs[k as usize - 1],
            _ => {
                [fnodes
                    .get(i as usize)
                    .map_or(0.0, |n| n.aabb().surface_area()); WIDTH]
            }
        }
    }

    /// The slots of the wide node made from binary interior node `i`.
    pub(crate) fn slots(&self, fnodes: &[FlatNode], i: u32) -> SrcList {
        let mut out = SrcList::of(&[]);
        self.split_into(fnodes, i, WIDTH, &mut out);
        out
    }

    /// Node `i`'s subtree as at most `j` slots, appended to `out` in depth-first order.
    fn distribute(&self, fnodes: &[FlatNode], i: u32, j: usize, out: &mut SrcList) {
        let planned = self.at.get(i as usize).is_some_and(|&k| k > 0);
        if j > 1 && planned {
            let whole = self.costs_of(fnodes, i)[0];
            let [l, r] = children(fnodes, i).map(|c| self.costs_of(fnodes, c));
            if split(&l, &r, j).0 < whole {
                self.split_into(fnodes, i, j, out);
                return;
            }
        }
        out.push(Src::Node(i));
    }

    /// Node `i`'s two children, sharing `j` slots as cheaply as they can.
    fn split_into(&self, fnodes: &[FlatNode], i: u32, j: usize, out: &mut SrcList) {
        let [a, b] = children(fnodes, i);
        let [l, r] = [a, b].map(|c| self.costs_of(fnodes, c));
        let (_, k) = split(&l, &r, j);
        self.distribute(fnodes, a, k, out);
        self.distribute(fnodes, b, j - k, out);
    }
}

/// A binary interior node's two children.
fn children(fnodes: &[FlatNode], i: u32) -> [u32; 2] {
    [i + 1, fnodes[i as usize].right_or_first]
}

/// The cheapest split of `j` slots between two children for every `j` (index `j - 1`;
/// infinite for `j = 1`), without branches: the same sums and minima as [`split`].
#[inline(always)]
fn splits(l: &Costs, r: &Costs) -> Costs {
    let mut out = [f32::INFINITY; WIDTH];
    for k in 1..WIDTH {
        for j in k + 1..=WIDTH {
            out[j - 1] = out[j - 1].min(l[k - 1] + r[j - k - 1]);
        }
    }
    out
}

/// The cheapest way for two children to share `j >= 2` slots: (cost, the first child's
/// slots); the fewest slots to the first child among equal costs, so the plan is
/// deterministic.
#[inline(always)]
fn split(l: &Costs, r: &Costs, j: usize) -> (f32, usize) {
    let mut best = (f32::INFINITY, 1);
    for k in 1..j {
        let c = l[k - 1] + r[j - k - 1];
        if c < best.0 {
            best = (c, k);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::{PendingLeaf, collapse, subtree_spans};
    use bvhtrace_core::{Aabb, BuildOptions, BuilderKind, FlatBvh, Triangle};
    use glam::Vec3;

    /// Clusters of small triangles at random places and sizes.
    fn soup(seed: u64, n: usize) -> Vec<Triangle> {
        let mut s = seed | 1;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut centre = Vec3::ZERO;
        (0..n)
            .map(|i| {
                if i % 23 == 0 {
                    centre = Vec3::new(next(), next(), next()) * 100.0;
                }
                let size = 0.05 + 3.0 * next() * next();
                let mut p = || centre + (Vec3::new(next(), next(), next()) - 0.5) * size * 8.0;
                let a = p();
                [
                    a,
                    a + Vec3::X * size * next(),
                    a + Vec3::Y * size * next() + Vec3::Z,
                ]
            })
            .collect()
    }

    /// The collapse of `flat` with the plan or greedily: the areas of its nodes' boxes
    /// and leaf children's boxes summed, and its leaf children's triangle runs.
    fn collapsed(flat: &FlatBvh, plan: Option<&Plan>) -> (f64, Vec<(u32, u32)>) {
        let fnodes = flat.nodes();
        let spans = subtree_spans(fnodes);
        let (mut nodes, mut leaves) = (Vec::new(), Vec::<PendingLeaf>::new());
        let mut area = fnodes[0].aabb().surface_area() as f64;
        let mut on_slot = |_, _, src| {
            if let Src::Node(i) = src {
                area += fnodes[i as usize].aabb().surface_area() as f64;
            }
        };
        let tri_box = |_| Aabb::EMPTY;
        collapse(
            fnodes,
            &spans,
            &tri_box,
            0,
            Level::Mesh,
            &mut nodes,
            &mut leaves,
            &mut on_slot,
            plan,
        )
        .expect("collapses");
        let mut runs: Vec<_> = leaves.iter().map(|l| (l.first_tri, l.tris)).collect();
        runs.sort_unstable();
        (area, runs)
    }

    /// On trees of every builder and leaf size, the planned collapse makes the same leaf
    /// children as the greedy one, at a cost (the nodes' and leaf children's areas) no
    /// higher, and exactly the cost its plan predicts: the slots are the plan's optimum.
    #[test]
    fn the_plan_realises_its_optimum_and_beats_the_greedy_collapse() {
        let builders = [
            BuilderKind::Sah,
            BuilderKind::SweepSah,
            BuilderKind::Median,
            BuilderKind::Midpoint,
            BuilderKind::Sbvh,
        ];
        let (mut fewer, mut trees) = (0, 0);
        for seed in 1..=6u64 {
            let tris = soup(seed, [40, 300, 2000][seed as usize % 3]);
            for builder in builders {
                for max_leaf_size in [1, 3, 8] {
                    let opts = BuildOptions {
                        builder,
                        max_leaf_size,
                        ..BuildOptions::with_builder(builder)
                    };
                    let flat = FlatBvh::build(&tris, &opts).expect("builds");
                    let fnodes = flat.nodes();
                    let spans = subtree_spans(fnodes);
                    let plan = Plan::new(fnodes, &spans);
                    let (planned, runs) = collapsed(&flat, Some(&plan));
                    let (greedy, greedy_runs) = collapsed(&flat, None);
                    assert_eq!(runs, greedy_runs, "{builder:?} {max_leaf_size}");
                    let predicted = plan.costs_of(fnodes, 0)[0] as f64;
                    let case = format!("seed {seed} {builder:?} leaves of {max_leaf_size}");
                    assert!(
                        (planned - predicted).abs() <= 1e-5 * predicted,
                        "{case}: the collapse costs {planned}, the plan said {predicted}"
                    );
                    assert!(
                        planned <= greedy * (1.0 + 1e-6),
                        "{case}: planned {planned} against greedy {greedy}"
                    );
                    fewer += usize::from(planned < greedy * 0.999);
                    trees += 1;
                }
            }
        }
        assert!(
            fewer * 2 > trees,
            "the plan gained on {fewer} of {trees} trees"
        );
    }
}
