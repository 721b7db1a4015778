//! The wide layout: 8-wide nodes with child boxes compressed to 8 bits per plane
//! (after Ylitie, Karras and Laine 2017, "Efficient Incoherent Ray Traversal on GPUs
//! Through Compressed Wide BVHs"), converted from the binary [`FlatBvh`].
//!
//! # Layout (the single place it is described, beside the binary one in [`crate::flat`])
//!
//! * `nodes: [WideNode]`, 80 bytes each; the root is node 0. A node holds up to eight
//!   children in *slots* `0..8`. WGSL twin: `BvhWideNode` in `shaders/types.wgsl`.
//!   - `origin`, `exponents`: a per-node grid. Child `s`'s box on axis `a` is
//!     `origin[a] + q * 2^(e[a] - 127)` for `q` its 8-bit `q_lo` and `q_hi` planes
//!     ([`WideNode::child_box`]). The scale is a power of two, so `q * scale` is exact and
//!     the one rounding is the addition, the same on every backend (fused or not).
//!   - `q_lo`, `q_hi`: the planes, one byte per slot (slot `s` in byte `s % 4` of word
//!     `s / 4`), rounded outwards *through that f32 addition*: the decoded box contains
//!     the child's exact box, so no ray misses a child it would hit in the binary tree.
//!   - `imask` (the top byte of `exponents`): bit `s` marks an interior child; interior
//!     children are stored contiguously from `child_base`, in slot order, so child `s` is
//!     node `child_base + popcount(imask & ((1 << s) - 1))`.
//!   - `counts`: byte `s` is leaf child `s`'s triangle count (1..=[`MAX_LEAF_TRIANGLES`]),
//!     0 for an interior or empty slot. Leaf children's triangles are stored contiguously
//!     from `triangle_base`, in slot order, so leaf `s` starts at `triangle_base` plus the
//!     counts of the slots before it ([`WideNode::leaf_range`]).
//!   - In a two-level BVH, a leaf child of a top-level node (`index < top_nodes`) holds one
//!     instance (count 1): its "triangle" index is an index into `instances`.
//! * **Slot order** (Ylitie et al., section 3.2): slot `s` holds the child that a ray of
//!   octant `s` ([`crate::flat::octant`]) should visit first, chosen greedily by the
//!   child's centroid against the node's centre. A walk in octant `o` visits the hit
//!   children of a node in the order of `s ^ o`, which needs no sort.
//! * `triangles: [FlatTriangle]`: the binary tree's triangles, reordered into the wide
//!   leaf order (`prim` unchanged).
//! * `instances: [FlatInstance]`: the binary tree's instances in the wide top level's leaf
//!   order, `root` the mesh's wide root. The meshes' nodes follow the top level's, the
//!   first instance's mesh first, so `instances[0].root == top_nodes`: the kernels find
//!   the end of the top level there (the uploads check it).
//!
//! # Collapse
//! Greedy, top down (documented instead of Ylitie's SAH-optimal dynamic programme): a wide
//! node starts from the two children of its binary node, and while it has fewer than
//! eight, the expandable child of largest surface area is replaced by its two children.
//! Expandable: an interior binary node holding more than [`MERGE_TRIANGLES`] triangles, or
//! a run of more than [`MAX_LEAF_TRIANGLES`] triangles (a big binary leaf, split in
//! halves). A binary subtree of at most [`MERGE_TRIANGLES`] triangles becomes one leaf
//! child. The top level of a two-level BVH is collapsed the same way without merging, so
//! every leaf child there is exactly one instance.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::flat::{FlatBvh, FlatInstance, FlatTriangle};
use crate::geometry::Aabb;
use crate::intersect::PreparedRay;

/// Children per wide node.
pub const WIDTH: usize = 8;

/// The most triangles in one leaf child (8 of them then sum to under 256, so the counts of
/// a node's slots add up within one byte).
pub const MAX_LEAF_TRIANGLES: u32 = 31;

/// A binary subtree with at most this many triangles becomes one leaf child.
pub const MERGE_TRIANGLES: u32 = 3;

/// One wide node (see the module docs for the encoding).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct WideNode {
    /// The grid's origin (the lower corner of the node's box).
    pub origin: [f32; 3],
    /// Biased exponents of the grid's scale per axis (bytes 0..3: `2^(e - 127)`), and
    /// `imask` in byte 3.
    pub exponents: u32,
    /// The first interior child's node index.
    pub child_base: u32,
    /// The first leaf child's first triangle (or instance, in a top-level node).
    pub triangle_base: u32,
    /// Byte `s`: leaf child `s`'s triangle count; 0 for interior and empty slots.
    pub counts: [u32; 2],
    /// Lower planes per axis, one byte per slot.
    pub q_lo: [[u32; 2]; 3],
    /// Upper planes per axis, one byte per slot.
    pub q_hi: [[u32; 2]; 3],
}

/// Byte `s` of an 8-byte field.
#[inline(always)]
fn byte(w: &[u32; 2], s: usize) -> u32 {
    (w[s >> 2] >> ((s & 3) * 8)) & 0xff
}

/// Sum of the bytes of `x` (their sum must be under 256).
#[inline(always)]
fn byte_sum(x: u32) -> u32 {
    x.wrapping_mul(0x0101_0101) >> 24
}

/// The bytes of `x` below byte `k` (0..=4).
#[inline(always)]
fn bytes_below(x: u32, k: usize) -> u32 {
    if k >= 4 {
        x
    } else {
        x & ((1u32 << (k * 8)) - 1)
    }
}

/// `2^(e - 127)` for a biased exponent byte `1..=254`.
#[inline(always)]
pub fn exponent_scale(e: u32) -> f32 {
    f32::from_bits(e << 23)
}

impl WideNode {
    /// Bit `s` set when slot `s` holds an interior child.
    #[inline(always)]
    pub fn imask(&self) -> u32 {
        self.exponents >> 24
    }

    /// The grid's scale per axis.
    #[inline(always)]
    pub fn scale(&self) -> Vec3 {
        Vec3::new(
            exponent_scale(self.exponents & 0xff),
            exponent_scale((self.exponents >> 8) & 0xff),
            exponent_scale((self.exponents >> 16) & 0xff),
        )
    }

    /// Leaf child `s`'s triangle count (0 for interior and empty slots).
    #[inline(always)]
    pub fn count(&self, s: usize) -> u32 {
        byte(&self.counts, s)
    }

    /// True when slot `s` holds a child.
    #[inline(always)]
    pub fn is_used(&self, s: usize) -> bool {
        (self.imask() >> s) & 1 != 0 || self.count(s) != 0
    }

    /// The slots that hold a child, as bits.
    #[inline(always)]
    pub fn used_mask(&self) -> u32 {
        // Bit 7 of each byte set when the byte is not zero, then gathered to bits 0..8.
        let x = u64::from(self.counts[0]) | u64::from(self.counts[1]) << 32;
        let low7 = 0x7f7f_7f7f_7f7f_7f7f_u64;
        let nonzero = (((x & low7) + low7) | x) & !low7;
        let leaves = ((nonzero >> 7).wrapping_mul(0x0102_0408_1020_4080) >> 56) as u32;
        leaves | self.imask()
    }

    /// Interior child `s`'s node index.
    #[inline(always)]
    pub fn child(&self, s: usize) -> u32 {
        self.child_base + (self.imask() & ((1u32 << s) - 1)).count_ones()
    }

    /// Leaf child `s`'s first triangle and count.
    #[inline(always)]
    pub fn leaf_range(&self, s: usize) -> (u32, u32) {
        let before = if s < 4 {
            byte_sum(bytes_below(self.counts[0], s))
        } else {
            byte_sum(self.counts[0]) + byte_sum(bytes_below(self.counts[1], s - 4))
        };
        (self.triangle_base + before, self.count(s))
    }

    /// Child `s`'s decoded box: `origin + q * scale`, one rounding per plane (what every
    /// walk tests).
    #[inline(always)]
    pub fn child_box(&self, s: usize) -> (Vec3, Vec3) {
        let e = self.scale();
        let plane = |q: &[[u32; 2]; 3], a: usize| self.origin[a] + byte(&q[a], s) as f32 * e[a];
        (
            Vec3::new(
                plane(&self.q_lo, 0),
                plane(&self.q_lo, 1),
                plane(&self.q_lo, 2),
            ),
            Vec3::new(
                plane(&self.q_hi, 0),
                plane(&self.q_hi, 1),
                plane(&self.q_hi, 2),
            ),
        )
    }
}

/// A BVH in the wide layout, converted from a binary one ([`WideBvh::collapse`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WideBvh {
    /// The nodes; the root is node 0.
    pub nodes: Vec<WideNode>,
    /// The triangles in wide leaf order.
    pub triangles: Vec<FlatTriangle>,
    /// The instances of a two-level BVH in the top level's leaf order; empty for one mesh.
    pub instances: Vec<FlatInstance>,
    /// For each of `instances`, its index in the binary BVH's ([`FlatBvh::instances`]): the
    /// instance a hit filter is told of.
    pub instance_order: Vec<u32>,
    /// Nodes of the top level (`nodes[..top_nodes]`); 0 for one mesh.
    pub top_nodes: u32,
    /// Longest root-to-leaf path in nodes, through an instance into its mesh for two
    /// levels: the most node groups a walk's stack holds.
    pub depth: u32,
}

/// One child being gathered for a wide node: a binary node, or a run of a big leaf.
#[derive(Clone, Copy, Debug)]
enum Item {
    Node(u32),
    Run {
        first: u32,
        count: u32,
        bounds: Aabb,
    },
}

/// What the collapse reads of one binary tree.
struct Source<'a> {
    bvh: &'a FlatBvh,
    /// Triangles under each binary node, and the first of them (the subtree's triangles
    /// are contiguous in binary leaf order).
    tri_count: Vec<u32>,
    tri_first: Vec<u32>,
    /// True while collapsing a top level (no merging; leaves are instances).
    top: bool,
}

impl<'a> Source<'a> {
    fn new(bvh: &'a FlatBvh) -> Self {
        let n = bvh.nodes.len();
        let (mut tri_count, mut tri_first) = (vec![0u32; n], vec![0u32; n]);
        // Children come after their parents: one pass from the end.
        for i in (0..n).rev() {
            let node = &bvh.nodes[i];
            if node.is_leaf() {
                tri_count[i] = node.count();
                tri_first[i] = node.right_or_first;
            } else {
                let (l, r) = (i + 1, node.right_or_first as usize);
                tri_count[i] = tri_count[l] + tri_count[r];
                tri_first[i] = tri_first[l].min(tri_first[r]);
            }
        }
        Source {
            bvh,
            tri_count,
            tri_first,
            top: false,
        }
    }

    fn bounds(&self, item: &Item) -> Aabb {
        match item {
            Item::Node(i) => self.bvh.nodes[*i as usize].aabb(),
            Item::Run { bounds, .. } => *bounds,
        }
    }

    /// The item as a leaf child: its triangle run, when it is one.
    fn as_leaf(&self, item: &Item) -> Option<(u32, u32)> {
        match *item {
            Item::Run { first, count, .. } => Some((first, count)),
            Item::Node(i) => {
                let n = &self.bvh.nodes[i as usize];
                if n.is_leaf() && n.count() <= MAX_LEAF_TRIANGLES {
                    Some((n.right_or_first, n.count()))
                } else if !self.top && !n.is_leaf() && self.tri_count[i as usize] <= MERGE_TRIANGLES
                {
                    Some((self.tri_first[i as usize], self.tri_count[i as usize]))
                } else {
                    None
                }
            }
        }
    }

    /// The two halves of an expandable item (one that is not a leaf child).
    fn expand(&self, item: &Item) -> [Item; 2] {
        let run = |first: u32, count: u32| {
            let h = count / 2;
            let half = |f: u32, c: u32| Item::Run {
                first: f,
                count: c,
                bounds: self.bvh.triangles[f as usize..(f + c) as usize]
                    .iter()
                    .fold(Aabb::EMPTY, |b, t| {
                        b.union(&Aabb::from_triangle(&t.corners()))
                    }),
            };
            [half(first, h), half(first + h, count - h)]
        };
        match *item {
            Item::Run { first, count, .. } => run(first, count),
            Item::Node(i) => {
                let n = &self.bvh.nodes[i as usize];
                if n.is_leaf() {
                    run(n.right_or_first, n.count())
                } else {
                    [Item::Node(i + 1), Item::Node(n.right_or_first)]
                }
            }
        }
    }

    /// The children of the wide node standing for `item` (an expandable one).
    fn gather(&self, item: Item) -> Vec<Item> {
        let mut kids: Vec<Item> = self.expand(&item).to_vec();
        while kids.len() < WIDTH {
            let best = kids
                .iter()
                .enumerate()
                .filter(|(_, k)| self.as_leaf(k).is_none())
                .max_by(|a, b| {
                    let (sa, sb) = (
                        self.bounds(a.1).surface_area(),
                        self.bounds(b.1).surface_area(),
                    );
                    sa.total_cmp(&sb)
                })
                .map(|(i, _)| i);
            let Some(i) = best else { break };
            let [a, b] = self.expand(&kids[i]);
            kids[i] = a;
            kids.push(b);
        }
        kids
    }
}

/// The slot of each child: greedily, the (child, slot) pair whose centroid lies furthest
/// against the direction of the slot's octant goes first (Ylitie et al.'s auction, greedy).
fn assign_slots(parent: &Aabb, boxes: &[Aabb]) -> [Option<usize>; WIDTH] {
    let c = (parent.min + parent.max) * 0.5;
    let mut cost = Vec::with_capacity(boxes.len() * WIDTH);
    for (i, b) in boxes.iter().enumerate() {
        let d = (b.min + b.max) * 0.5 - c;
        for s in 0..WIDTH {
            let sign = |a: usize| if (s >> a) & 1 == 0 { 1.0 } else { -1.0 };
            let v = d.x * sign(0) + d.y * sign(1) + d.z * sign(2);
            cost.push((v, i, s));
        }
    }
    cost.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut slots = [None; WIDTH];
    let mut placed = [false; WIDTH];
    for (_, i, s) in cost {
        if slots[s].is_none() && !placed[i] {
            slots[s] = Some(i);
            placed[i] = true;
        }
    }
    slots
}

/// The grid of one axis: the smallest power-of-two scale whose 255 steps from `lo` reach
/// `hi` in f32, as a biased exponent.
fn axis_exponent(lo: f32, hi: f32) -> u32 {
    let extent = f64::from(hi) - f64::from(lo);
    let mut k = if extent > 0.0 {
        (extent / 255.0).log2().ceil() as i32
    } else {
        -126
    };
    k = k.clamp(-126, 127);
    while k < 127 && !(lo + 255.0 * exponent_scale((k + 127) as u32) >= hi) {
        k += 1;
    }
    (k + 127) as u32
}

/// The byte `q` whose plane `lo + q * e` (rounded as the walks round it) is the largest
/// not above `v` (`up == false`), or the smallest not below it (`up == true`).
fn quantise(origin: f32, e: f32, v: f32, up: bool) -> u32 {
    let plane = |q: u32| origin + q as f32 * e;
    let guess = ((f64::from(v) - f64::from(origin)) / f64::from(e)).clamp(0.0, 255.0);
    if up {
        let mut q = guess.ceil() as u32;
        while q > 0 && plane(q - 1) >= v {
            q -= 1;
        }
        while q < 255 && plane(q) < v {
            q += 1;
        }
        q
    } else {
        let mut q = guess.floor() as u32;
        while q < 255 && plane(q + 1) <= v {
            q += 1;
        }
        while q > 0 && plane(q) > v {
            q -= 1;
        }
        q
    }
}

/// Writes byte `s` of an 8-byte field.
fn set_byte(w: &mut [u32; 2], s: usize, v: u32) {
    w[s >> 2] |= (v & 0xff) << ((s & 3) * 8);
}

/// Builds the wide tree of one binary tree (or of the top level of a two-level one).
struct Emitter<'a> {
    out: &'a mut WideBvh,
    /// Where each source triangle (or instance) went, for the caller.
    leaf_slots: Vec<u32>,
    /// For the top level: each leaf child's instance.
    instance_of_leaf: Vec<u32>,
}

impl Emitter<'_> {
    /// Emits the subtree of `item` at node index `at` (already reserved), with its
    /// triangles from `self.out.triangles.len()`. Returns the depth below it.
    fn emit(&mut self, src: &Source, item: Item, at: u32, triangles: &[FlatTriangle]) -> u32 {
        let kids = if src.as_leaf(&item).is_some() {
            vec![item] // a lone leaf root: one leaf child
        } else {
            src.gather(item)
        };
        let boxes: Vec<Aabb> = kids.iter().map(|k| src.bounds(k)).collect();
        let parent = boxes.iter().fold(Aabb::EMPTY, |b, c| b.union(c));
        let slots = assign_slots(&parent, &boxes);
        let lo = parent.min;
        let mut node = WideNode {
            origin: lo.to_array(),
            ..WideNode::zeroed()
        };
        let mut e = [0u32; 3];
        for a in 0..3 {
            e[a] = axis_exponent(lo[a], parent.max[a]);
            node.exponents |= e[a] << (8 * a);
        }
        node.child_base = self.out.nodes.len() as u32;
        node.triangle_base = if src.top {
            self.instance_of_leaf.len() as u32
        } else {
            self.out.triangles.len() as u32
        };
        let mut interior = Vec::new();
        let mut imask = 0u32;
        for (s, k) in slots.iter().enumerate() {
            let Some(k) = *k else { continue };
            let b = &boxes[k];
            for a in 0..3 {
                let scale = exponent_scale(e[a]);
                set_byte(
                    &mut node.q_lo[a],
                    s,
                    quantise(lo[a], scale, b.min[a], false),
                );
                set_byte(&mut node.q_hi[a], s, quantise(lo[a], scale, b.max[a], true));
            }
            match src.as_leaf(&kids[k]) {
                Some((first, count)) => {
                    set_byte(&mut node.counts, s, count);
                    for t in first..first + count {
                        if src.top {
                            self.instance_of_leaf.push(t);
                        } else {
                            self.leaf_slots[t as usize] = self.out.triangles.len() as u32;
                            self.out.triangles.push(triangles[t as usize]);
                        }
                    }
                }
                None => {
                    imask |= 1 << s;
                    interior.push(kids[k]);
                }
            }
        }
        node.exponents |= imask << 24;
        for _ in &interior {
            self.out.nodes.push(WideNode::zeroed());
        }
        self.out.nodes[at as usize] = node;
        let mut depth = 0;
        for (i, k) in interior.into_iter().enumerate() {
            depth = depth.max(1 + self.emit(src, k, node.child_base + i as u32, triangles));
        }
        depth
    }
}

impl WideBvh {
    /// Converts a binary BVH (one mesh or two levels) into the wide layout.
    pub fn collapse(bvh: &FlatBvh) -> WideBvh {
        let mut out = WideBvh::default();
        if bvh.nodes.is_empty() {
            return out;
        }
        if !bvh.is_instanced() {
            let src = Source::new(bvh);
            out.nodes.push(WideNode::zeroed());
            let mut em = Emitter {
                out: &mut out,
                leaf_slots: vec![0; bvh.triangles.len()],
                instance_of_leaf: Vec::new(),
            };
            let d = em.emit(&src, Item::Node(0), 0, &bvh.triangles);
            out.depth = d + 1;
            return out;
        }
        // The top level: a tree over the top nodes alone, whose leaves ("triangles") are
        // the top-level leaf nodes themselves.
        let top = top_level_view(bvh);
        let mut src = Source::new(&top);
        src.top = true;
        out.nodes.push(WideNode::zeroed());
        let mut em = Emitter {
            out: &mut out,
            leaf_slots: Vec::new(),
            instance_of_leaf: Vec::new(),
        };
        let top_depth = em.emit(&src, Item::Node(0), 0, &[]);
        let order = std::mem::take(&mut em.instance_of_leaf);
        out.top_nodes = out.nodes.len() as u32;
        // Each mesh once, in order of first use.
        let mut roots: Vec<(u32, u32, u32)> = Vec::new(); // (binary root, wide root, depth)
        let mut mesh_depth = 0;
        for &i in &order {
            let root = bvh.instances[i as usize].root;
            if roots.iter().any(|r| r.0 == root) {
                continue;
            }
            let mesh = bvh_subtree(bvh, root);
            let src = Source::new(&mesh);
            let wide_root = out.nodes.len() as u32;
            out.nodes.push(WideNode::zeroed());
            let mut em = Emitter {
                out: &mut out,
                leaf_slots: vec![0; mesh.triangles.len()],
                instance_of_leaf: Vec::new(),
            };
            let d = em.emit(&src, Item::Node(0), wide_root, &mesh.triangles);
            mesh_depth = mesh_depth.max(d + 1);
            roots.push((root, wide_root, d + 1));
        }
        out.instances = order
            .iter()
            .map(|&i| {
                let mut inst = bvh.instances[i as usize];
                inst.root = roots.iter().find(|r| r.0 == inst.root).map_or(0, |r| r.1);
                inst
            })
            .collect();
        out.instance_order = order;
        out.depth = top_depth + 1 + mesh_depth;
        out
    }

    /// Bytes of the nodes and triangles as uploaded (the instances, when there are any,
    /// are `size_of_val(instances)` more).
    pub fn byte_sizes(&self) -> (usize, usize) {
        (
            std::mem::size_of_val(self.nodes.as_slice()),
            std::mem::size_of_val(self.triangles.as_slice()),
        )
    }

    /// True for a two-level BVH.
    pub fn is_instanced(&self) -> bool {
        !self.instances.is_empty()
    }

    /// Checks the structure against the binary tree it came from: every child box
    /// contains its subtree's triangles (or instance leaf boxes; for an SBVH, whose leaves
    /// may hold part of a triangle, the boxes holding a triangle cover it together), every
    /// triangle slot is in exactly one leaf, the indices are in range. Returns the first
    /// violation.
    pub fn check_invariants(&self, binary: &FlatBvh) -> Result<(), String> {
        if self.nodes.is_empty() {
            return if binary.nodes.is_empty() {
                Ok(())
            } else {
                Err("no nodes".into())
            };
        }
        let mut seen_tri = vec![false; self.triangles.len()];
        let mut coverage = crate::flat::Coverage::default();
        let mut seen_node = vec![false; self.nodes.len()];
        // Each node with the decoded boxes of the children on its path: every one of them
        // must contain what is below it (a child's box need not lie in its parent's:
        // each is rounded outwards on its own grid).
        let mut stack = vec![(0u32, Vec::<Aabb>::new())];
        if self.is_instanced() {
            for inst in &self.instances {
                if inst.root < self.top_nodes || inst.root as usize >= self.nodes.len() {
                    return Err(format!("instance root {} out of range", inst.root));
                }
            }
        }
        let mut roots: Vec<u32> = self.instances.iter().map(|i| i.root).collect();
        roots.sort_unstable();
        roots.dedup();
        stack.extend(roots.iter().map(|&r| (r, Vec::new())));
        while let Some((i, path)) = stack.pop() {
            let Some(n) = self.nodes.get(i as usize) else {
                return Err(format!("node {i} out of range"));
            };
            if std::mem::replace(&mut seen_node[i as usize], true) {
                return Err(format!("node {i} reached twice"));
            }
            let top = i < self.top_nodes;
            for s in 0..WIDTH {
                if !n.is_used(s) {
                    continue;
                }
                let (lo, hi) = n.child_box(s);
                let b = Aabb { min: lo, max: hi };
                let mut path = path.clone();
                path.push(b);
                let covers = |x: &Aabb| path.iter().all(|p| p.contains(x));
                if (n.imask() >> s) & 1 != 0 {
                    if n.count(s) != 0 {
                        return Err(format!("node {i} slot {s} is interior with triangles"));
                    }
                    stack.push((n.child(s), path));
                    continue;
                }
                let (first, count) = n.leaf_range(s);
                if top {
                    let Some(inst) = self.instances.get(first as usize) else {
                        return Err(format!("node {i} slot {s}: instance {first} out of range"));
                    };
                    if count != 1 {
                        return Err(format!("node {i} slot {s}: {count} instances in a leaf"));
                    }
                    let world = binary
                        .instances
                        .iter()
                        .position(|x| x.user_id == inst.user_id && x.prim_base == inst.prim_base)
                        .and_then(|k| {
                            binary.nodes[..binary.top_nodes as usize]
                                .iter()
                                .find(|nd| nd.is_instance_leaf() && nd.right_or_first == k as u32)
                        });
                    match world {
                        Some(nd) if covers(&nd.aabb()) => {}
                        _ => return Err(format!("node {i} slot {s}: instance box not covered")),
                    }
                    continue;
                }
                for t in first..first + count {
                    let Some(tri) = self.triangles.get(t as usize) else {
                        return Err(format!("node {i} slot {s}: triangle {t} out of range"));
                    };
                    if std::mem::replace(&mut seen_tri[t as usize], true) {
                        return Err(format!("triangle slot {t} in two leaves"));
                    }
                    // What of the triangle the boxes above it hold (all of it, but for an
                    // SBVH's clipped references).
                    let held = path
                        .iter()
                        .fold(Aabb::from_triangle(&tri.corners()), |h, p| Aabb {
                            min: h.min.max(p.min),
                            max: h.max.min(p.max),
                        });
                    coverage
                        .add(&held, tri)
                        .map_err(|e| format!("a box above node {i} slot {s}: {e} (slot {t})"))?;
                }
            }
        }
        if let Some(t) = seen_tri.iter().position(|s| !s) {
            return Err(format!("triangle slot {t} is in no leaf"));
        }
        coverage.finish()?;
        if !binary.is_instanced() && self.triangles.len() != binary.triangles.len() {
            return Err("triangle count differs from the binary tree's".into());
        }
        Ok(())
    }
}

/// The top level of a two-level BVH as a tree of its own, each instance leaf a
/// one-"triangle" leaf whose triangle index is its instance.
fn top_level_view(bvh: &FlatBvh) -> FlatBvh {
    let nodes = bvh.nodes[..bvh.top_nodes as usize]
        .iter()
        .map(|n| {
            let mut n = *n;
            if n.is_leaf() {
                n.meta = 1 << 2;
            }
            n
        })
        .collect();
    FlatBvh {
        nodes,
        ..FlatBvh::default()
    }
}

/// One mesh of a two-level BVH as a tree of its own: the subtree at `root`, its node and
/// triangle indices made relative.
fn bvh_subtree(bvh: &FlatBvh, root: u32) -> FlatBvh {
    // A mesh's nodes are contiguous from its root; its subtree ends where the walk of
    // right children ends.
    let (mut last, mut i) = (root as usize, root as usize);
    loop {
        let n = &bvh.nodes[i];
        if n.is_leaf() {
            last = last.max(i);
            break;
        }
        i = n.right_or_first as usize;
        last = last.max(i);
    }
    let nodes = &bvh.nodes[root as usize..=last];
    let tri_first = nodes
        .iter()
        .filter(|n| n.is_leaf())
        .map(|n| n.right_or_first)
        .min()
        .unwrap_or(0);
    let tri_end = nodes
        .iter()
        .filter(|n| n.is_leaf())
        .map(|n| n.right_or_first + n.count())
        .max()
        .unwrap_or(0);
    FlatBvh {
        nodes: nodes
            .iter()
            .map(|n| {
                let mut n = *n;
                n.right_or_first -= if n.is_leaf() { tri_first } else { root };
                n
            })
            .collect(),
        triangles: bvh.triangles[tri_first as usize..tri_end as usize].to_vec(),
        ..FlatBvh::default()
    }
}

/// Bit `s ^ oct` of the result is bit `s` of `mask`: a node's hits in slot order turned
/// into the visit order of a ray in octant `oct` (three conditional swaps).
#[inline(always)]
pub fn visit_order(mut m: u32, oct: usize) -> u32 {
    if oct & 1 != 0 {
        m = ((m & 0x55) << 1) | ((m >> 1) & 0x55);
    }
    if oct & 2 != 0 {
        m = ((m & 0x33) << 2) | ((m >> 2) & 0x33);
    }
    if oct & 4 != 0 {
        m = ((m & 0x0f) << 4) | ((m >> 4) & 0x0f);
    }
    m
}

/// Tests the ray against node `n`'s used child boxes: each with
/// [`crate::intersect::intersect_box`] on its decoded box ([`WideNode::child_box`]), so the
/// answers are the binary walks' and the kernel's. Bit `s ^ oct` of the result's mask is
/// set when child `s` is hit: the visit order of a ray in octant `oct`. The second value is
/// where in that order the nearest hit child is (the least entry distance, the first in
/// visit order among equal ones; 32 when none is hit): the walk visits it first. The
/// portable path; [`hit_children_avx2`] tests the eight boxes at once.
#[inline(always)]
pub fn hit_children(n: &WideNode, r: &PreparedRay, t_best: f32, oct: usize) -> (u32, u32) {
    let (mut hits, mut nearest) = (0u32, None::<(f32, u32)>);
    for s in 0..WIDTH {
        if !n.is_used(s) {
            continue;
        }
        let (lo, hi) = n.child_box(s);
        if let Some(t) = crate::intersect::intersect_box(r, lo, hi, t_best) {
            let j = (s ^ oct) as u32;
            hits |= 1 << j;
            if nearest.is_none_or(|(tn, jn)| t < tn || (t == tn && j < jn)) {
                nearest = Some((t, j));
            }
        }
    }
    (hits, nearest.map_or(u32::BITS, |n| n.1))
}

/// [`hit_children`] out of line: keeps the AVX version's frame small for the rare rays
/// parallel to a slab.
#[cfg(target_arch = "x86_64")]
#[inline(never)]
fn hit_children_apart(n: &WideNode, r: &PreparedRay, t_best: f32, oct: usize) -> (u32, u32) {
    hit_children(n, r, t_best, oct)
}

/// [`hit_children`] with AVX: the same values lane by lane, so the same bits. Each axis's
/// entry and exit distances come from its near and far planes, picked by the sign of the
/// ray's direction (what `fmin`/`fmax` of the two distances give: the planes decode in
/// order, `lo <= hi`, and rounding keeps that order through the subtraction and the
/// product, with no NaN for a ray not parallel to a slab); the rest is the scalar test's
/// operations in its order (`vminps`/`vmaxps` are the walks' `a < b ? a : b` and
/// `a > b ? a : b`, no fused multiply-add). Rays parallel to a slab take the portable
/// path. Also returns the used slots' mask.
///
/// # Safety
/// The CPU must support AVX2 (`is_x86_feature_detected!("avx2")`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub unsafe fn hit_children_avx2(
    n: &WideNode,
    r: &PreparedRay,
    t_best: f32,
    oct: usize,
) -> (u32, u32, u32) {
    use crate::intersect::{BOX_CULL_SLACK, BOX_TFAR_SCALE, BOX_TFAR_SCALE_NEG};
    use std::arch::x86_64::*;
    // Bytes of eight slots widened to eight i32 lanes.
    // SAFETY: `q` is eight readable bytes.
    let widen = |q: &[u32; 2]| unsafe { _mm256_cvtepu8_epi32(_mm_loadl_epi64(q.as_ptr().cast())) };
    let used = n.used_mask();
    if r.parallel {
        let (hits, first) = hit_children_apart(n, r, t_best, oct);
        return (hits, first, used);
    }
    let e = n.scale();
    // Distances to axis `a`'s planes `q`: decoded (`origin + q * scale`), then
    // `(plane - org) * inv_dir`.
    let dist = |q: &[u32; 2], a: usize| {
        let plane = _mm256_add_ps(
            _mm256_set1_ps(n.origin[a]),
            _mm256_mul_ps(_mm256_cvtepi32_ps(widen(q)), _mm256_set1_ps(e[a])),
        );
        _mm256_mul_ps(
            _mm256_sub_ps(plane, _mm256_set1_ps(r.org[a])),
            _mm256_set1_ps(r.inv_dir[a]),
        )
    };
    let near_far = |a: usize| {
        if r.inv_dir[a] >= 0.0 {
            (dist(&n.q_lo[a], a), dist(&n.q_hi[a], a))
        } else {
            (dist(&n.q_hi[a], a), dist(&n.q_lo[a], a))
        }
    };
    let (n0, f0) = near_far(0);
    let (n1, f1) = near_far(1);
    let (n2, f2) = near_far(2);
    let tnear = _mm256_max_ps(
        _mm256_max_ps(n0, n1),
        _mm256_max_ps(n2, _mm256_set1_ps(r.t_min)),
    );
    let limit = if t_best == f32::INFINITY {
        // `inf + slack * m` is `inf` (`m` is never NaN), and `fmin(inf, t_max)` is `t_max`.
        _mm256_set1_ps(r.t_max)
    } else {
        let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
        // A branch the ray always takes the same way, where indexing would spill to memory.
        let (nk, fk) = match r.kz {
            0 => (n0, f0),
            1 => (n1, f1),
            _ => (n2, f2),
        };
        let m = _mm256_max_ps(_mm256_and_ps(nk, abs_mask), _mm256_and_ps(fk, abs_mask));
        let widened = _mm256_add_ps(
            _mm256_set1_ps(t_best),
            _mm256_mul_ps(_mm256_set1_ps(BOX_CULL_SLACK), m),
        );
        _mm256_min_ps(widened, _mm256_set1_ps(r.t_max))
    };
    let tfar = _mm256_min_ps(_mm256_min_ps(f0, f1), _mm256_min_ps(f2, limit));
    let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(tfar, _mm256_setzero_ps());
    let scale = _mm256_blendv_ps(
        _mm256_set1_ps(BOX_TFAR_SCALE),
        _mm256_set1_ps(BOX_TFAR_SCALE_NEG),
        negative,
    );
    let boxes = _mm256_cmp_ps::<_CMP_LE_OQ>(tnear, _mm256_mul_ps(tfar, scale));
    let hit = _mm256_movemask_ps(boxes) as u32 & used;
    if hit & (hit.wrapping_sub(1)) == 0 {
        // No hit, or one: nothing to choose between.
        let order = visit_order(hit, oct);
        return (order, order.trailing_zeros(), used);
    }
    // The nearest hit lane: the least `tnear` over the hit lanes (`vminps` as `fmin`).
    let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    let hitv = _mm256_cmpeq_epi32(
        _mm256_and_si256(_mm256_set1_epi32(hit as i32), lane_bits),
        lane_bits,
    );
    let near = _mm256_blendv_ps(
        _mm256_set1_ps(f32::INFINITY),
        tnear,
        _mm256_castsi256_ps(hitv),
    );
    let m1 = _mm256_min_ps(near, _mm256_permute2f128_ps::<1>(near, near));
    let m2 = _mm256_min_ps(m1, _mm256_permute_ps::<0b01_00_11_10>(m1));
    let m3 = _mm256_min_ps(m2, _mm256_permute_ps::<0b10_11_00_01>(m2));
    let ties = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(near, m3)) as u32 & hit;
    (
        visit_order(hit, oct),
        visit_order(ties, oct).trailing_zeros(),
        used,
    )
}
