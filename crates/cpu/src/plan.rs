//! Which binary nodes of a mesh become the layout's wide nodes: the core's least-cost
//! collapse ([`CollapsePlan`]) over the leaf children [`is_leaf_child`] fixes.

use bvhtrace_core::FlatNode;
use bvhtrace_core::collapse::CollapsePlan;

use crate::layout::{Level, Src, SrcList, is_leaf_child};

// The plan hands out up to the core's wide width of slots, which `SrcList` holds.
const _: () = assert!(bvhtrace_core::wide::WIDTH == crate::layout::WIDTH);

/// The planned slots of a mesh's wide nodes.
pub(crate) struct Plan(CollapsePlan);

impl Plan {
    /// Plans every mesh node of `fnodes`.
    pub(crate) fn new(fnodes: &[FlatNode], spans: &[(u32, u32)]) -> Plan {
        // The AVX box test takes a node's eight slots at once: used slots cost nothing.
        let leaf_child = |i| is_leaf_child(fnodes, spans, Level::Mesh, i);
        Plan(CollapsePlan::new(fnodes, leaf_child, 0.0))
    }

    /// The slots of the wide node made from binary interior node `i`.
    pub(crate) fn slots(&self, fnodes: &[FlatNode], i: u32) -> SrcList {
        let (slots, len) = self.0.slots(fnodes, i);
        let mut out = SrcList::of(&[]);
        for &s in &slots[..len] {
            out.push(Src::Node(s));
        }
        out
    }
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
                    let predicted = plan.0.cost(fnodes, 0) as f64;
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
