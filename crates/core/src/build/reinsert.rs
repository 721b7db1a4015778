//! Tree optimisation by reinsertion: J. Bittner, M. Hapala, V. Havran, "Fast
//! insertion-based optimization of bounding volume hierarchies", Computer Graphics Forum
//! 32(1), 2013.
//!
//! The tree is copied into an array of nodes with parent links, optimised in rounds, and
//! converted back. Each **round** ranks the interior nodes by the paper's inefficiency
//! measure `M_sum · M_min · M_area` (with `A` the surface area and `C` the two children:
//! `M_sum = A(N) / mean A(C)`, `M_min = A(N) / min A(C)`, `M_area = A(N)`) and takes the
//! worst [`ReinsertOptions::batch_fraction`] of them. For each such node `N` it plans, in
//! this order:
//! * the paper's move: `N` and its parent `P` out of the tree (`N`'s sibling takes `P`'s
//!   place), then `N`'s two children reinserted one after the other, the larger box first,
//!   `P` and `N` reused as their new parents;
//! * each child of `N` moved alone: out of the tree (its sibling takes `N`'s place), then
//!   reinserted with `N` reused as its new parent. Staying where it was is one of its
//!   options, so this move finds an improvement wherever a single reinsertion can.
//!
//! A subtree is reinserted where it raises the cost least, found by the paper's
//! branch-and-bound search: a priority queue of positions ordered by their induced cost
//! (how much the position's ancestors grow), a position costing that plus its direct cost
//! (the new parent's area), a subtree pruned once its induced cost plus the reinserted
//! box's own area cannot beat the best position found. The node count never changes and
//! every leaf keeps its primitives.
//!
//! # The cost, and which moves are kept
//! The cost is the build's SAH (interior nodes `cost_traversal × area`, leaves
//! `cost_intersection × count × area`, over the root's area: [`crate::BvhStats`]'
//! convention). Leaves never change, so only the interior areas move: the optimiser lowers
//! both of `BvhStats`' figures at once, and the costs only weigh the stop rule (with
//! `cost_traversal == 0` nothing can improve, and the tree is returned as it is).
//! A move is kept only when it lowers the cost (the paper keeps every reinsertion); a
//! round whose recomputed cost ends higher than it started is undone. A move that found
//! nothing better is not planned again until another move writes its node.
//!
//! # Stop rule
//! The paper stops once several batches in a row fail to lower the cost. Here a round
//! that lowers the cost by less than [`ReinsertOptions::min_gain`] (0.1 % by default) of
//! its starting cost is the last, and there are at most [`ReinsertOptions::max_rounds`]
//! (100); the optimisation also ends when no move is left to plan.
//!
//! # Parallelism and determinism
//! The ranking and the planning are parallel: each move is planned (removal, searches,
//! insertions) on a private copy-on-write view of the tree as it stood at the start of
//! the round. The plans are then applied one by one in rank order, each checked on the
//! tree as it is by then: still well-formed (its targets in the tree, outside the subtree
//! being moved) and still lowering the cost, or dropped. Nothing depends on which thread
//! planned what, so the tree is the same whatever the thread count.
//!
//! # Depth
//! Reinsertion can deepen the tree. A position is taken only if the tree stays within
//! `max(depth before, ReinsertOptions::depth_limit)` levels (40 by default: a full-stack
//! walk holds 64, which leaves room for a top level over instances).
//!
//! # Back to a [`BuildTree`]
//! Leaves are emitted depth-first and `prim_order` is rebuilt so each leaf's primitives are
//! contiguous again (an SBVH tree's repeated references stay as they were). Interior boxes
//! are refitted (the union of the children). A node whose children changed gets the axis
//! along which its children's box centres lie farthest apart, its child with the lower
//! centre first: the stackless and short-stack walks enter the child on the ray's side of
//! that axis first. Untouched nodes keep the builder's axis and child order.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};
use std::hash::{BuildHasherDefault, Hasher};

use rayon::prelude::*;

use super::{BuildNode, BuildOptions, BuildTree};
use crate::geometry::Aabb;

/// No node (the root's parent).
const NONE: u32 = u32::MAX;

/// The root's index in the node array.
const ROOT: u32 = 0;

/// Settings of the optimiser ([`optimize_with`]); [`BuildOptions::optimize`] uses the
/// defaults.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReinsertOptions {
    /// Fraction of the interior nodes whose moves are planned in each round, the most
    /// inefficient first (default 0.05).
    pub batch_fraction: f64,
    /// A round that lowers the SAH cost by less than this fraction of its starting cost
    /// ends the optimisation (default 1e-3, 0.1 %).
    pub min_gain: f64,
    /// The most rounds (default 100).
    pub max_rounds: usize,
    /// The tree may grow to `max(its depth before, depth_limit)` levels, no deeper
    /// (default 40).
    pub depth_limit: u32,
}

impl Default for ReinsertOptions {
    fn default() -> Self {
        ReinsertOptions {
            batch_fraction: 0.05,
            min_gain: 1e-3,
            max_rounds: 100,
            depth_limit: 40,
        }
    }
}

/// What one round did.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundReport {
    /// Moves planned in the round.
    pub candidates: usize,
    /// Moves applied (each lowered the cost).
    pub moves: usize,
    /// Planned moves dropped because earlier moves of the round made them worthless (or
    /// ill-formed).
    pub rejected: usize,
    /// The SAH cost after the round (the starting cost when the round was undone).
    pub cost: f64,
    /// True when the round ended with a higher cost and was undone.
    pub undone: bool,
}

/// What the optimiser did ([`optimize_with`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReinsertReport {
    /// The SAH cost before (the build's costs, [`crate::BvhStats`]' convention).
    pub cost_before: f64,
    /// The SAH cost after; never above `cost_before`.
    pub cost_after: f64,
    /// One entry per round run, in order.
    pub rounds: Vec<RoundReport>,
}

/// Optimises `tree` by reinsertion with the default [`ReinsertOptions`], for the costs in
/// `opts` (see the module docs). The result has the same node count, the same leaves and
/// a SAH cost no higher.
pub fn optimize(tree: &BuildTree, opts: &BuildOptions) -> BuildTree {
    optimize_with(tree, opts, &ReinsertOptions::default()).0
}

/// [`optimize`] with explicit settings; also says what each round did.
pub fn optimize_with(
    tree: &BuildTree,
    opts: &BuildOptions,
    settings: &ReinsertOptions,
) -> (BuildTree, ReinsertReport) {
    let (out, report) = run(tree, opts, settings);
    (out.unwrap_or_else(|| tree.clone()), report)
}

/// Optimises an owned tree when `opts.optimize` says so (what the builders call last).
pub(crate) fn finish(tree: BuildTree, opts: &BuildOptions) -> BuildTree {
    if !opts.optimize {
        return tree;
    }
    run(&tree, opts, &ReinsertOptions::default())
        .0
        .unwrap_or(tree)
}

/// The optimisation; `None` when no move was kept (the tree is unchanged).
fn run(
    tree: &BuildTree,
    opts: &BuildOptions,
    settings: &ReinsertOptions,
) -> (Option<BuildTree>, ReinsertReport) {
    let mut nodes = Vec::with_capacity(tree.node_count);
    push_tree(&tree.root, NONE, &mut nodes);
    let before = sah(&nodes, opts);
    let mut report = ReinsertReport {
        cost_before: before,
        cost_after: before,
        rounds: Vec::new(),
    };
    let interior = nodes.iter().filter(|n| !n.leaf).count();
    // Nothing to gain: no node with a grandparent, interiors cost nothing, or a degenerate
    // (zero or overflowing) cost that the relative stop rule cannot read.
    if interior < 2 || !(opts.cost_traversal > 0.0) || !(before > 0.0 && before.is_finite()) {
        return (None, report);
    }
    let limit = nodes[ROOT as usize].height.max(settings.depth_limit);
    // Moves gaining less than this are rounding, not improvement (an area sum's last bits).
    let eps = area(&nodes[ROOT as usize].bounds) * 1e-10;
    let batch = ((interior as f64 * settings.batch_fraction).ceil() as usize).clamp(1, interior);
    let mut dirty = vec![false; nodes.len()];
    let mut settled = vec![Settled::default(); nodes.len()];
    let mut cost = before;
    let mut kept = 0;
    for _ in 0..settings.max_rounds {
        let cands = candidates(&nodes, batch, &settled);
        if cands.is_empty() {
            break;
        }
        // Planned on the round's starting tree, in parallel; applied below in rank order.
        let plans: Vec<Option<Move>> = cands
            .par_iter()
            .map(|&c| plan(&nodes, c, limit, eps))
            .collect();
        dirty.fill(false);
        let (mut moves, mut rejected) = (0, 0);
        let mut undo = Vec::new();
        for (c, p) in cands.iter().zip(plans) {
            let Some(mv) = p else {
                // Nothing better on the round's tree: not worth planning again until a
                // move changes the node (unless one already did).
                if !dirty[c.node as usize] {
                    let s = &mut settled[c.node as usize];
                    if c.pair {
                        s.pair = true;
                    } else {
                        s.alone = true;
                    }
                }
                continue;
            };
            match apply(&mut nodes, mv, limit, eps) {
                Some(written) => {
                    for &(w, _) in &written {
                        dirty[w as usize] = true;
                        settled[w as usize] = Settled::default();
                    }
                    undo.extend(written);
                    moves += 1;
                }
                None => rejected += 1,
            }
        }
        let after = sah(&nodes, opts);
        // Every move lowered the f64 sum it changed; a recomputed total that ends higher
        // (summation order) undoes the round rather than let the cost rise.
        let undone = !(after <= cost);
        if undone {
            for (i, old) in undo.into_iter().rev() {
                nodes[i as usize] = old;
            }
        }
        let gain = if undone { 0.0 } else { (cost - after) / cost };
        if !undone {
            cost = after;
            kept += moves;
        }
        report.rounds.push(RoundReport {
            candidates: cands.len(),
            moves: if undone { 0 } else { moves },
            rejected,
            cost,
            undone,
        });
        if undone || gain < settings.min_gain {
            break;
        }
    }
    report.cost_after = cost;
    if kept == 0 {
        return (None, report);
    }
    let mut prim_order = Vec::with_capacity(tree.prim_order.len());
    let root = emit(&nodes, ROOT, &tree.prim_order, &mut prim_order);
    (
        Some(BuildTree {
            root,
            prim_order,
            node_count: nodes.len(),
        }),
        report,
    )
}

/// One node of the working array.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Node {
    bounds: Aabb,
    /// [`NONE`] for the root.
    parent: u32,
    /// Interior: the two children. Leaf: `[first, count]` in the input's `prim_order`.
    kids: [u32; 2],
    /// Edges on the longest path down to a leaf (0 for a leaf).
    height: u32,
    leaf: bool,
    /// The builder's split axis (kept unless `changed`).
    axis: u8,
    /// The children changed: axis and child order are chosen again on the way out.
    changed: bool,
}

#[inline]
fn area(b: &Aabb) -> f64 {
    f64::from(b.surface_area())
}

/// Appends `node`'s subtree in depth-first order, interior boxes refitted; returns its
/// index.
fn push_tree(node: &BuildNode, parent: u32, out: &mut Vec<Node>) -> u32 {
    let i = out.len() as u32;
    match node {
        BuildNode::Leaf {
            bounds,
            first,
            count,
        } => out.push(Node {
            bounds: *bounds,
            parent,
            kids: [*first, *count],
            height: 0,
            leaf: true,
            axis: 0,
            changed: false,
        }),
        BuildNode::Interior { axis, children, .. } => {
            out.push(Node {
                bounds: Aabb::EMPTY,
                parent,
                kids: [NONE; 2],
                height: 0,
                leaf: false,
                axis: *axis,
                changed: false,
            });
            let a = push_tree(&children[0], i, out);
            let b = push_tree(&children[1], i, out);
            let (na, nb) = (out[a as usize], out[b as usize]);
            let n = &mut out[i as usize];
            n.kids = [a, b];
            n.bounds = na.bounds.union(&nb.bounds);
            n.height = 1 + na.height.max(nb.height);
        }
    }
    i
}

/// The SAH cost in [`crate::BvhStats`]' convention with the build's costs. Sequential, so
/// the sum (and the stop rule reading it) does not depend on the thread count.
fn sah(nodes: &[Node], opts: &BuildOptions) -> f64 {
    let (mut inner, mut leaves) = (0f64, 0f64);
    for n in nodes {
        if n.leaf {
            leaves += area(&n.bounds) * f64::from(n.kids[1]);
        } else {
            inner += area(&n.bounds);
        }
    }
    let root = area(&nodes[ROOT as usize].bounds);
    if root > 0.0 {
        (f64::from(opts.cost_traversal) * inner + f64::from(opts.cost_intersection) * leaves) / root
    } else {
        0.0
    }
}

/// Bittner's inefficiency measure `M_sum · M_min · M_area` of an interior node.
fn inefficiency(nodes: &[Node], n: &Node) -> f64 {
    let a = area(&n.bounds);
    let (l, r) = (
        area(&nodes[n.kids[0] as usize].bounds),
        area(&nodes[n.kids[1] as usize].bounds),
    );
    // Children without area under a parent with some: as inefficient as it gets.
    let ratio = |num: f64, den: f64| {
        if den > 0.0 {
            num / den
        } else if num > 0.0 {
            1e30
        } else {
            1.0
        }
    };
    ratio(a, 0.5 * (l + r)) * ratio(a, l.min(r)) * a
}

/// Moves already found not to pay, per node: planning them again is pointless until a
/// move writes the node.
#[derive(Clone, Copy, Default)]
struct Settled {
    /// The node moved alone.
    alone: bool,
    /// The node and its parent out, its children reinserted.
    pair: bool,
}

/// A move to plan: `node` alone, or (`pair`) `node` and its parent out and `node`'s
/// children reinserted.
#[derive(Clone, Copy, Debug)]
struct Candidate {
    node: u32,
    pair: bool,
}

/// The moves to plan for the `k` most inefficient interior nodes `N` (not the root),
/// worst first (ties to the lower index, so the order is total): the paper's (`N` and its
/// parent out, when the parent is not the root), then each child of `N` alone; moves
/// already settled are left out.
fn candidates(nodes: &[Node], k: usize, settled: &[Settled]) -> Vec<Candidate> {
    let mut c: Vec<(f64, u32)> = nodes
        .par_iter()
        .enumerate()
        .filter_map(|(i, n)| {
            let open = !n.leaf
                && n.parent != NONE
                && (n.kids.iter().any(|&k| !settled[k as usize].alone)
                    || (!settled[i].pair && nodes[n.parent as usize].parent != NONE));
            open.then(|| (inefficiency(nodes, n), i as u32))
        })
        .collect();
    let worst_first = |a: &(f64, u32), b: &(f64, u32)| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1));
    if c.len() > k {
        c.select_nth_unstable_by(k, worst_first);
        c.truncate(k);
    }
    c.par_sort_unstable_by(worst_first);
    let mut out = Vec::with_capacity(3 * c.len());
    for (_, i) in c {
        let n = &nodes[i as usize];
        if !settled[i as usize].pair && nodes[n.parent as usize].parent != NONE {
            out.push(Candidate {
                node: i,
                pair: true,
            });
        }
        for k in n.kids {
            if !settled[k as usize].alone {
                out.push(Candidate {
                    node: k,
                    pair: false,
                });
            }
        }
    }
    out
}

/// Where the tree operations read and write nodes: a private view for planning, or the
/// tree itself. Both sum the change of the interior areas as they write.
trait Store {
    fn get(&mut self, i: u32) -> Node;
    fn set(&mut self, i: u32, n: Node);
}

/// A multiplicative hash of a node index (the std SipHash is needlessly slow here).
#[derive(Default)]
struct SlotHasher(u64);

impl Hasher for SlotHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }
    fn write_u32(&mut self, i: u32) {
        self.0 = u64::from(i).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}

/// Copy-on-write view of the tree for planning a move: writes go to `changed`.
struct Overlay<'a> {
    base: &'a [Node],
    changed: HashMap<u32, Node, BuildHasherDefault<SlotHasher>>,
    /// One bit per `changed` key (of 64, by a hash of the index): most reads are of nodes
    /// the plan never wrote, and this answers them without a lookup.
    mask: u64,
    delta: f64,
}

impl<'a> Overlay<'a> {
    fn new(base: &'a [Node]) -> Self {
        Overlay {
            base,
            changed: HashMap::with_capacity_and_hasher(64, Default::default()),
            mask: 0,
            delta: 0.0,
        }
    }
    #[inline(always)]
    fn bit(i: u32) -> u64 {
        1 << (i.wrapping_mul(0x9E37_79B9) >> 26)
    }
}

impl Store for Overlay<'_> {
    #[inline(always)]
    fn get(&mut self, i: u32) -> Node {
        if self.mask & Self::bit(i) != 0
            && let Some(n) = self.changed.get(&i)
        {
            return *n;
        }
        self.base[i as usize]
    }
    fn set(&mut self, i: u32, n: Node) {
        let old = self.get(i);
        if !n.leaf {
            self.delta += area(&n.bounds) - area(&old.bounds);
        }
        self.mask |= Self::bit(i);
        self.changed.insert(i, n);
    }
}

/// The tree itself, with an undo log.
struct Live<'a> {
    nodes: &'a mut [Node],
    undo: Vec<(u32, Node)>,
    delta: f64,
}

impl Store for Live<'_> {
    fn get(&mut self, i: u32) -> Node {
        self.nodes[i as usize]
    }
    fn set(&mut self, i: u32, n: Node) {
        let old = std::mem::replace(&mut self.nodes[i as usize], n);
        if !n.leaf {
            self.delta += area(&n.bounds) - area(&old.bounds);
        }
        self.undo.push((i, old));
    }
}

/// Refits boxes and heights from `i` up; stops at the first node that does not change (its
/// ancestors do not either).
fn refit_up<S: Store>(s: &mut S, mut i: u32) {
    while i != NONE {
        let mut n = s.get(i);
        let (a, b) = (s.get(n.kids[0]), s.get(n.kids[1]));
        let bounds = a.bounds.union(&b.bounds);
        let height = 1 + a.height.max(b.height);
        if bounds == n.bounds && height == n.height {
            return;
        }
        n.bounds = bounds;
        n.height = height;
        s.set(i, n);
        i = n.parent;
    }
}

/// Replaces `child` by `by` among `parent`'s children.
fn relink<S: Store>(s: &mut S, parent: u32, child: u32, by: u32) {
    let mut p = s.get(parent);
    let k = usize::from(p.kids[1] == child);
    debug_assert_eq!(p.kids[k], child);
    p.kids[k] = by;
    p.changed = true;
    s.set(parent, p);
}

/// Takes node `x` out of the tree: its sibling takes its parent's place, and the boxes
/// above are refitted. Returns the freed parent and the sibling; `None` when `x` is the
/// root or a child of the root.
fn remove<S: Store>(s: &mut S, x: u32) -> Option<(u32, u32)> {
    let p = s.get(x).parent;
    if p == NONE {
        return None;
    }
    let pn = s.get(p);
    if pn.parent == NONE {
        return None;
    }
    let g = pn.parent;
    let sibling = pn.kids[usize::from(pn.kids[0] == x)];
    relink(s, g, p, sibling);
    let mut sn = s.get(sibling);
    sn.parent = g;
    s.set(sibling, sn);
    refit_up(s, g);
    Some((p, sibling))
}

/// Makes the freed `slot` the parent of `x` (any node but the root) and the detached
/// subtree `sub`, in `x`'s place, and refits.
fn insert<S: Store>(s: &mut S, sub: u32, x: u32, slot: u32) {
    let mut xn = s.get(x);
    let mut sn = s.get(sub);
    let xp = xn.parent;
    debug_assert!(xp != NONE, "never insert above the root");
    s.set(
        slot,
        Node {
            bounds: xn.bounds.union(&sn.bounds),
            parent: xp,
            kids: [x, sub],
            height: 1 + xn.height.max(sn.height),
            leaf: false,
            axis: 0,
            changed: true,
        },
    );
    xn.parent = slot;
    s.set(x, xn);
    sn.parent = slot;
    s.set(sub, sn);
    relink(s, xp, x, slot);
    refit_up(s, xp);
}

/// A search position: a node, the induced cost of inserting there (the growth of its
/// ancestors' areas) and its depth. Ordered so that `BinaryHeap` pops the lowest induced
/// cost first, ties to the lower index.
struct Entry {
    induced: f64,
    node: u32,
    depth: u32,
}

impl Ord for Entry {
    fn cmp(&self, o: &Self) -> Ordering {
        o.induced
            .total_cmp(&self.induced)
            .then(o.node.cmp(&self.node))
    }
}
impl PartialOrd for Entry {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl PartialEq for Entry {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o) == Ordering::Equal
    }
}
impl Eq for Entry {}

/// The paper's branch-and-bound search: the node (not the root) beside which inserting
/// `sub` costs least (its direct cost, the new parent's area, plus the induced cost, the
/// growth of the ancestors' areas), among those that keep the tree within `limit` levels.
/// `home` (where `sub` came from) is the position to beat: a strictly cheaper one or
/// `home` itself is returned. Inserting above the root is never better than beside one of
/// its children (the root's box already holds `sub`'s).
fn search<S: Store>(s: &mut S, sub: &Node, home: u32, limit: u32) -> Option<u32> {
    let own = area(&sub.bounds);
    // The cost of going back home bounds the search from the start.
    let h = s.get(home);
    let mut home_cost = area(&h.bounds.union(&sub.bounds));
    let (mut a, mut depth) = (h.parent, 0);
    while a != NONE {
        let an = s.get(a);
        home_cost += area(&an.bounds.union(&sub.bounds)) - area(&an.bounds);
        a = an.parent;
        depth += 1;
    }
    let (mut best, mut best_cost) = if depth + 1 + h.height.max(sub.height) <= limit {
        (Some(home), home_cost)
    } else {
        (None, f64::INFINITY)
    };
    let root = s.get(ROOT);
    let induced = area(&root.bounds.union(&sub.bounds)) - area(&root.bounds);
    let mut heap = BinaryHeap::new();
    for k in root.kids {
        heap.push(Entry {
            induced,
            node: k,
            depth: 1,
        });
    }
    while let Some(e) = heap.pop() {
        // Any position below costs at least its induced cost plus `sub`'s own area.
        if e.induced + own >= best_cost {
            break;
        }
        let x = s.get(e.node);
        let union = area(&x.bounds.union(&sub.bounds));
        let cost = e.induced + union;
        if cost < best_cost && e.depth + 1 + x.height.max(sub.height) <= limit {
            best = Some(e.node);
            best_cost = cost;
        }
        if !x.leaf {
            let induced = cost - area(&x.bounds);
            if induced + own < best_cost {
                for k in x.kids {
                    heap.push(Entry {
                        induced,
                        node: k,
                        depth: e.depth + 1,
                    });
                }
            }
        }
    }
    best
}

/// A planned move.
#[derive(Clone, Copy, Debug)]
enum Move {
    /// Node `x` out of the tree, then beside `target`.
    Alone { x: u32, target: u32 },
    /// Node `n` and its parent out; `n`'s child `first` beside `targets[0]`, then the
    /// other beside `targets[1]`.
    Pair {
        n: u32,
        first: u32,
        targets: [u32; 2],
    },
}

/// Plans candidate `c` on a private view of `nodes`: the move, when it lowers the cost
/// by more than `eps`.
fn plan(nodes: &[Node], c: Candidate, limit: u32, eps: f64) -> Option<Move> {
    let mut ov = Overlay::new(nodes);
    let (slot, sibling) = remove(&mut ov, c.node)?;
    let mv = if c.pair {
        let n = ov.get(c.node);
        let (a, b) = (ov.get(n.kids[0]), ov.get(n.kids[1]));
        // The larger first, as the paper does: it has the fewer good places.
        let order = if area(&b.bounds) > area(&a.bounds) {
            [n.kids[1], n.kids[0]]
        } else {
            n.kids
        };
        let free = [slot, c.node];
        let mut targets = [NONE; 2];
        for k in 0..2 {
            let sub = ov.get(order[k]);
            targets[k] = search(&mut ov, &sub, sibling, limit)?;
            insert(&mut ov, order[k], targets[k], free[k]);
        }
        Move::Pair {
            n: c.node,
            first: order[0],
            targets,
        }
    } else {
        let sub = ov.get(c.node);
        // Back beside its sibling is where it was: no move.
        let target = search(&mut ov, &sub, sibling, limit).filter(|&t| t != sibling)?;
        insert(&mut ov, c.node, target, slot);
        Move::Alone { x: c.node, target }
    };
    (ov.delta < -eps).then_some(mv)
}

/// True when `t` hangs from the root through consistent links without passing `avoid`:
/// a place in the tree outside the subtree being moved.
fn in_tree<S: Store>(s: &mut S, mut t: u32, avoid: u32) -> bool {
    loop {
        if t == avoid {
            return false;
        }
        if t == ROOT {
            return true;
        }
        let p = s.get(t).parent;
        if p == NONE {
            return false;
        }
        let pn = s.get(p);
        if pn.leaf || !pn.kids.contains(&t) {
            return false;
        }
        t = p;
    }
}

/// Applies a planned move to the tree (planned, perhaps, before other moves changed it).
/// Keeps it, returning the nodes written with their old values, only if it is still
/// well-formed, lowers the cost by more than `eps` and keeps the depth within `limit`;
/// otherwise leaves the tree as it was.
fn apply(nodes: &mut [Node], mv: Move, limit: u32, eps: f64) -> Option<Vec<(u32, Node)>> {
    let mut live = Live {
        nodes,
        undo: Vec::new(),
        delta: 0.0,
    };
    // Each target must still be in the tree, outside the subtree going beside it, and
    // not the root (a move never replaces the root).
    let done = (|| {
        match mv {
            Move::Alone { x, target } => {
                let (slot, sibling) = remove(&mut live, x)?;
                if target == sibling || target == ROOT || !in_tree(&mut live, target, x) {
                    return None;
                }
                insert(&mut live, x, target, slot);
            }
            Move::Pair { n, first, targets } => {
                let kids = live.get(n).kids;
                if !kids.contains(&first) {
                    return None;
                }
                let order = [first, kids[usize::from(kids[0] == first)]];
                let (slot, _) = remove(&mut live, n)?;
                let free = [slot, n];
                for k in 0..2 {
                    if targets[k] == ROOT || !in_tree(&mut live, targets[k], order[k]) {
                        return None;
                    }
                    insert(&mut live, order[k], targets[k], free[k]);
                }
            }
        }
        (live.delta < -eps && live.nodes[ROOT as usize].height <= limit).then_some(())
    })();
    if done.is_some() {
        return Some(live.undo);
    }
    for (i, old) in live.undo.into_iter().rev() {
        live.nodes[i as usize] = old;
    }
    None
}

/// The axis along which `a`'s and `b`'s box centres lie farthest apart (the lowest on
/// ties), and whether `b` comes first along it.
fn split_axis(a: &Aabb, b: &Aabb) -> (u8, bool) {
    let (ca, cb) = (a.centroid(), b.centroid());
    let d = (cb - ca).abs();
    let axis = if d.x >= d.y && d.x >= d.z {
        0
    } else if d.y >= d.z {
        1
    } else {
        2
    };
    (axis as u8, cb[axis] < ca[axis])
}

/// Emits the subtree at `i` as a [`BuildNode`], appending its leaves' primitives (taken
/// from the input's `old_order`) to `order` depth-first.
fn emit(nodes: &[Node], i: u32, old_order: &[u32], order: &mut Vec<u32>) -> BuildNode {
    let n = &nodes[i as usize];
    if n.leaf {
        let (first, count) = (n.kids[0] as usize, n.kids[1] as usize);
        let start = order.len() as u32;
        order.extend_from_slice(&old_order[first..first + count]);
        return BuildNode::Leaf {
            bounds: n.bounds,
            first: start,
            count: n.kids[1],
        };
    }
    let (axis, kids) = if n.changed {
        let (a, b) = (&nodes[n.kids[0] as usize], &nodes[n.kids[1] as usize]);
        let (axis, swap) = split_axis(&a.bounds, &b.bounds);
        (axis, if swap { [n.kids[1], n.kids[0]] } else { n.kids })
    } else {
        (n.axis, n.kids)
    };
    let a = emit(nodes, kids[0], old_order, order);
    let b = emit(nodes, kids[1], old_order, order);
    BuildNode::Interior {
        bounds: n.bounds,
        axis,
        children: Box::new([a, b]),
    }
}
