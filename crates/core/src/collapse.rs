//! Which binary nodes become wide nodes: the collapse of least SAH cost (Ylitie, Karras
//! and Laine 2017, "Efficient incoherent ray traversal on GPUs through compressed wide
//! BVHs", section 3.1), over leaf children a layout fixes.
//!
//! When the leaf children are the same whatever the nodes above them, the cost left to
//! choose is the wide nodes': each costs its box's surface area (the chance that a ray
//! enters it). A greedy collapse (open the child of largest area until eight) fills the
//! top well but leaves many nodes near the leaves with two or three children; the plan
//! pulls those children up into their parents. The CPU layout (`bvhtrace-cpu`) takes it;
//! the GPU's wide layout ([`crate::wide`]) is still collapsed greedily.

use crate::flat::FlatNode;
use crate::wide::WIDTH;

/// A node's least cost as exactly `j` slots, `j` = 1 to [`WIDTH`] (index `j - 1`;
/// infinite where its subtree cannot make `j`).
type Costs = [f32; WIDTH];

/// The least-cost slot distribution of every binary interior node that is not a leaf
/// child (a leaf child's cost is its own area, computed when asked).
#[derive(Clone, Debug, Default)]
pub struct CollapsePlan {
    /// Index + 1 into `costs` per binary node; 0 where the node was not planned.
    at: Vec<u32>,
    costs: Vec<Costs>,
    /// What a wide node's used slot costs per visit, against 1 for the visit itself.
    slot_cost: f32,
}

impl CollapsePlan {
    /// Plans the binary tree `nodes` (depth first, first child next), where
    /// `leaf_child(i)` says which binary nodes the layout makes leaf children (binary
    /// leaves among them): one backward pass, children before their parent. A wide node
    /// costs its surface area times `1 + slot_cost * slots` (0 where a node's boxes are
    /// tested together whatever their number, as in SIMD lanes).
    pub fn new(nodes: &[FlatNode], leaf_child: impl Fn(u32) -> bool, slot_cost: f32) -> Self {
        let mut plan = CollapsePlan {
            // Zeroed memory: only the planned nodes' entries are written.
            at: bytemuck::zeroed_vec(nodes.len()),
            // A leaf child per binary leaf or per few: rarely outgrown.
            costs: Vec::with_capacity(nodes.len() / 4),
            slot_cost,
        };
        for i in (0..nodes.len() as u32).rev() {
            if !leaf_child(i) && !nodes[i as usize].is_leaf() {
                let [l, r] = children(nodes, i).map(|c| plan.costs_of(nodes, c));
                // As `j >= 2` slots: the best split of `j` between its children. As one
                // (a wide node of its own): its visit and its best number of slots.
                let mut c = splits(&l, &r);
                c[0] = plan.node_cost(nodes, i, &c).0;
                plan.costs.push(c);
                plan.at[i as usize] = plan.costs.len() as u32;
            }
        }
        plan
    }

    /// Interior node `i` as a wide node over `splits` (its exact-slot costs): the cost,
    /// and the number of slots (the fewest among equal costs).
    #[inline(always)]
    fn node_cost(&self, nodes: &[FlatNode], i: u32, splits: &Costs) -> (f32, usize) {
        let area = nodes[i as usize].aabb().surface_area();
        let mut best = (f32::INFINITY, 2);
        for j in 2..=WIDTH {
            let c = area * self.slot_cost * j as f32 + splits[j - 1];
            if c < best.0 {
                best = (c, j);
            }
        }
        (area + best.0, best.1)
    }

    /// The least cost of binary node `i`'s subtree as one wide node (or leaf child): what
    /// the wide nodes and leaf children the plan makes of it cost, summed.
    pub fn cost(&self, nodes: &[FlatNode], i: u32) -> f32 {
        self.costs_of(nodes, i)[0]
    }

    /// Binary node `i`'s costs. A leaf child's is its area as one slot (the nodes above
    /// it do not change how often it is entered). A node not planned yet (out of the
    /// depth-first order: a tree flattened by hand) is taken as a leaf child.
    #[inline(always)]
    fn costs_of(&self, nodes: &[FlatNode], i: u32) -> Costs {
        match self.at.get(i as usize) {
            Some(&k) if k > 0 => self.costs[k as usize - 1],
            _ => {
                let mut c = [f32::INFINITY; WIDTH];
                c[0] = nodes
                    .get(i as usize)
                    .map_or(0.0, |n| n.aabb().surface_area());
                c
            }
        }
    }

    /// The slots of the wide node made from binary interior node `i`: binary nodes, in
    /// depth-first order, `len` of them (2 to [`WIDTH`]).
    pub fn slots(&self, nodes: &[FlatNode], i: u32) -> ([u32; WIDTH], usize) {
        let [l, r] = children(nodes, i).map(|c| self.costs_of(nodes, c));
        let (_, j) = self.node_cost(nodes, i, &splits(&l, &r));
        let mut out = ([0; WIDTH], 0);
        self.split_into(nodes, i, j, &mut out);
        out
    }

    /// Node `i`'s subtree as exactly `j` slots, appended to `out`. A node not planned is
    /// one slot whatever `j` (its costs never ask for more: a guard, not a case).
    fn distribute(&self, nodes: &[FlatNode], i: u32, j: usize, out: &mut ([u32; WIDTH], usize)) {
        let planned = self.at.get(i as usize).is_some_and(|&k| k > 0);
        if j == 1 || !planned {
            out.0[out.1] = i;
            out.1 += 1;
        } else {
            self.split_into(nodes, i, j, out);
        }
    }

    /// Node `i`'s two children, sharing `j >= 2` slots as cheaply as they can.
    fn split_into(&self, nodes: &[FlatNode], i: u32, j: usize, out: &mut ([u32; WIDTH], usize)) {
        let [a, b] = children(nodes, i);
        let [l, r] = [a, b].map(|c| self.costs_of(nodes, c));
        let (_, k) = split(&l, &r, j);
        self.distribute(nodes, a, k, out);
        self.distribute(nodes, b, j - k, out);
    }
}

/// A binary interior node's two children.
fn children(nodes: &[FlatNode], i: u32) -> [u32; 2] {
    [i + 1, nodes[i as usize].right_or_first]
}

/// The cheapest split of exactly `j` slots between two children for every `j` (index
/// `j - 1`; infinite for `j = 1`), without branches: the same sums and minima as
/// [`split`].
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

/// The cheapest way for two children to share exactly `j >= 2` slots: (cost, the first
/// child's slots); the fewest slots to the first child among equal costs, so the plan
/// is deterministic.
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
    use crate::{BuildOptions, FlatBvh, Triangle};
    use glam::Vec3;

    /// Small triangles scattered with a xorshift.
    fn soup(n: usize, mut s: u32) -> Vec<Triangle> {
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            (s >> 8) as f32 / (1u32 << 24) as f32
        };
        (0..n)
            .map(|_| {
                let a = Vec3::new(next(), next(), next()) * 50.0;
                let size = 0.1 + next() * next() * 4.0;
                [a, a + Vec3::X * size, a + Vec3::new(0.0, size, next())]
            })
            .collect()
    }

    /// The plan's wide nodes and leaf children under `i`, their costs summed as the plan
    /// counts them; every wide node with 2 to 8 slots.
    fn realised(
        plan: &CollapsePlan,
        nodes: &[FlatNode],
        leaf: &dyn Fn(u32) -> bool,
        i: u32,
    ) -> f64 {
        let (slots, len) = plan.slots(nodes, i);
        assert!((2..=WIDTH).contains(&len));
        let area = nodes[i as usize].aabb().surface_area() as f64;
        let mut cost = area * (1.0 + plan.slot_cost as f64 * len as f64);
        for &s in &slots[..len] {
            cost += if leaf(s) || nodes[s as usize].is_leaf() {
                nodes[s as usize].aabb().surface_area() as f64
            } else {
                realised(plan, nodes, leaf, s)
            };
        }
        cost
    }

    /// With and without a cost per slot, the slots the plan hands out cost exactly what it
    /// predicted, and a cost per slot gives nodes fewer slots.
    #[test]
    fn the_slots_cost_what_the_plan_predicts() {
        for (n, seed) in [(300, 7), (3000, 11)] {
            let tris = soup(n, seed);
            let flat = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
            let nodes = flat.nodes();
            // Leaf children: binary leaves, and nothing merged.
            let leaf = |i: u32| nodes[i as usize].is_leaf();
            let mut slots_used = Vec::new();
            for slot_cost in [0.0, 0.65, 4.0] {
                let plan = CollapsePlan::new(nodes, leaf, slot_cost);
                let predicted = plan.cost(nodes, 0) as f64;
                let got = realised(&plan, nodes, &leaf, 0);
                assert!(
                    (got - predicted).abs() <= 1e-5 * predicted,
                    "{n} triangles, slot cost {slot_cost}: {got} against {predicted}"
                );
                slots_used.push(plan.slots(nodes, 0).1);
            }
            assert!(
                slots_used[2] < slots_used[0],
                "slots at the root: {slots_used:?}"
            );
        }
    }

    /// A NaN box (a tree edited by hand; the layouts refuse it afterwards) makes no plan
    /// panic or recurse without end: every wide node still gets two to eight slots.
    #[test]
    fn nan_boxes_are_planned_without_panic() {
        let tris = soup(500, 3);
        let flat = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
        for bad in [0, 1, 5, 40] {
            let mut nodes = flat.nodes().to_vec();
            nodes[bad].min[1] = f32::NAN;
            let leaf = |i: u32| nodes[i as usize].is_leaf();
            for slot_cost in [0.0, 0.65] {
                let plan = CollapsePlan::new(&nodes, leaf, slot_cost);
                for i in 0..nodes.len() as u32 {
                    if !nodes[i as usize].is_leaf() {
                        let (_, len) = plan.slots(&nodes, i);
                        assert!((2..=WIDTH).contains(&len), "node {i}: {len} slots");
                    }
                }
            }
        }
    }
}
