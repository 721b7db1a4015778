//! The CPU layout: 8-wide nodes with their children's f32 boxes in SoA, and leaves as
//! runs of 4-triangle blocks in SoA, converted from a binary [`FlatBvh`].
//!
//! # Layout
//! * `nodes: [Node8]`, 256 bytes each (four cache lines, aligned); the root is node 0.
//!   `planes[2a][i]`/`planes[2a + 1][i]` is child `i`'s box on axis `a` (lower, upper),
//!   the binary node's own box to the bit, so each lane of the SIMD box test is the scalar test of the same box.
//!   `child[i]` is a [`ChildRef`]: [`EMPTY`], a node index, or a leaf
//!   ([`LEAF`]` | (blocks - 1) << 27 | first block`).
//! * `blocks: [Tri4]`, 160 bytes each: four triangles' corners, `v[corner][axis][lane]`,
//!   and their primitive ids. A leaf of `n` triangles takes `ceil(n / 4)` consecutive
//!   blocks; the last block's free lanes repeat its last triangle (same corners, same id),
//!   which finds nothing the triangle itself does not, so no lane mask is needed.
//!
//! # Collapse
//! A binary leaf, or a binary subtree of at most [`MERGE_TRIANGLES`] triangles, becomes
//! one leaf child. Which binary nodes above those become wide nodes is the least-cost
//! choice (`plan`: the sum of the wide nodes' surface areas, Ylitie et al.'s dynamic
//! programme), which fills the nodes near the leaves that a greedy collapse leaves with
//! two or three children. The top level over instances is collapsed greedily, top down:
//! a wide node starts from its binary node's two children, and while it has fewer than
//! eight, the interior child of largest surface area is replaced by its two children. A
//! leaf of more than [`MAX_LEAF_BLOCKS`]` * 4` triangles (only with a large
//! `max_leaf_size`) is split into a node over runs of the leaf's triangles, boxed by
//! their corners.
//!
//! # Two levels
//! A two-level tree (instances over meshes, `bvhtrace_core::flat`'s *Two levels*) is the
//! same arrays: the top level's nodes first (node 0 its root), collapsed alike but with
//! one instance per leaf child (`LEAF | instance index`, no blocks), then each mesh's
//! nodes, converted once however many instances place it, and every mesh's blocks (their
//! ids the mesh's own). Each instance keeps the core's `FlatInstance` (transform,
//! primitive base, visibility mask) and where its mesh's walk starts: the mesh's root
//! node, or its leaf when the mesh is one leaf.
//!
//! Skipping the binary boxes between a wide node and its children only removes culls:
//! every walk over this layout visits a superset of what the binary walk would with the
//! same running best hit, so the closest hit is the binary walk's (see the crate docs).

use std::sync::Arc;

use bvhtrace_core::masks::MaskTables;
use bvhtrace_core::{Aabb, FlatBvh, FlatInstance, FlatNode, FlatTriangle};
use glam::Vec3;
use rayon::prelude::*;

use crate::plan::Plan;

/// Children per node: one AVX register per plane of a node's boxes.
pub const WIDTH: usize = 8;

/// Triangles per block: one SSE register per coordinate of a block's corners.
pub const BLOCK: usize = 4;

/// A node's child slot: [`EMPTY`], a node index (below [`LEAF`]), or a leaf.
pub type ChildRef = u32;

/// The flag of a leaf child.
pub const LEAF: u32 = 1 << 31;

/// An unused child slot.
pub const EMPTY: u32 = u32::MAX;

/// The most 4-triangle blocks one leaf child holds.
pub const MAX_LEAF_BLOCKS: u32 = 16;

/// Bits of a leaf's first block (the rest hold the block count).
const FIRST_BITS: u32 = 27;

/// The leaf child over `count` blocks from `first`.
#[inline(always)]
pub fn leaf_ref(first: u32, count: u32) -> ChildRef {
    debug_assert!((1..=MAX_LEAF_BLOCKS).contains(&count) && first < 1 << FIRST_BITS);
    LEAF | (count - 1) << FIRST_BITS | first
}

/// A leaf child's first block and block count.
#[inline(always)]
pub fn leaf_range(r: ChildRef) -> (usize, usize) {
    let first = (r & ((1 << FIRST_BITS) - 1)) as usize;
    let count = ((r >> FIRST_BITS) & (MAX_LEAF_BLOCKS - 1)) as usize + 1;
    (first, count)
}

/// One 8-wide node (see the module docs).
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Node8 {
    /// The children's boxes, plane by plane: `planes[2 * axis][slot]` the lower corner's
    /// coordinate, `planes[2 * axis + 1][slot]` the upper one's.
    pub planes: [[f32; WIDTH]; 6],
    /// The children.
    pub child: [ChildRef; WIDTH],
    /// Bit `i` set when slot `i` is used.
    pub used: u32,
    /// Padding to 256 bytes (zero).
    pub pad: [u32; 7],
}

impl Node8 {
    /// A node with no children.
    pub const EMPTY: Node8 = Node8 {
        planes: [[0.0; WIDTH]; 6],
        child: [EMPTY; WIDTH],
        used: 0,
        pad: [0; 7],
    };

    /// Slot `i`'s box.
    pub fn child_box(&self, i: usize) -> Aabb {
        Aabb {
            min: Vec3::new(self.planes[0][i], self.planes[2][i], self.planes[4][i]),
            max: Vec3::new(self.planes[1][i], self.planes[3][i], self.planes[5][i]),
        }
    }

    fn set(&mut self, i: usize, b: &Aabb, child: ChildRef) {
        for a in 0..3 {
            self.planes[2 * a][i] = b.min[a];
            self.planes[2 * a + 1][i] = b.max[a];
        }
        self.child[i] = child;
        self.used |= 1 << i;
    }
}

/// Four triangles in SoA (see the module docs).
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Zeroable)]
pub struct Tri4 {
    /// `v[corner][axis][lane]`.
    pub v: [[[f32; BLOCK]; 3]; 3],
    /// Each lane's primitive id.
    pub prim: [u32; BLOCK],
}

impl Tri4 {
    /// Lane `i`'s triangle's box.
    pub fn corner_box(&self, i: usize) -> Aabb {
        let c = |k: usize| Vec3::new(self.v[k][0][i], self.v[k][1][i], self.v[k][2][i]);
        Aabb::from_triangle(&[c(0), c(1), c(2)])
    }

    /// The block of `tris` (one to four), its free lanes repeating the last triangle.
    pub(crate) fn of(tris: &[FlatTriangle]) -> Tri4 {
        let mut b = Tri4 {
            v: [[[0.0; BLOCK]; 3]; 3],
            prim: [0; BLOCK],
        };
        for lane in 0..BLOCK {
            let t = &tris[lane.min(tris.len() - 1)];
            for (c, corner) in [t.v0, t.v1, t.v2].iter().enumerate() {
                for (a, &x) in corner.iter().enumerate() {
                    b.v[c][a][lane] = x;
                }
            }
            b.prim[lane] = t.prim;
        }
        b
    }
}

/// A block whose every lane's binary leaf box is its triangle's own box (a leaf of one
/// triangle, boxed by its corners, as the builders box it): the walks make the box from
/// the corners, and no [`LeafBoxes`] are kept for it.
pub const CORNER_BOXES: u32 = u32::MAX;

/// The boxes of the binary leaves a block's four triangles come from, lane by lane. The
/// walks test a hit's own leaf box, as the binary walk does before it tests the triangle,
/// where the hit lies within f32 error of an end of the ray's interval: only there can a
/// triangle report a `t` inside the interval while the binary walk's box test rejects its
/// leaf (a triangle at or behind the ray's origin, its `t` rounded into the interval), and
/// the binary walk's answer is what the layout's must be.
#[repr(C, align(32))]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Zeroable)]
pub struct LeafBoxes {
    /// `planes[2 * axis][lane]` the lower corner, `planes[2 * axis + 1][lane]` the upper.
    pub planes: [[f32; BLOCK]; 6],
}

impl LeafBoxes {
    /// The boxes of one to four triangles, the free lanes repeating the last.
    fn of(boxes: &[Aabb]) -> LeafBoxes {
        let mut planes = [[0.0; BLOCK]; 6];
        for lane in 0..BLOCK {
            let b = &boxes[lane.min(boxes.len() - 1)];
            for axis in 0..3 {
                planes[2 * axis][lane] = b.min[axis];
                planes[2 * axis + 1][lane] = b.max[axis];
            }
        }
        LeafBoxes { planes }
    }

    /// Lane `i`'s box.
    pub fn lane(&self, i: usize) -> Aabb {
        let p = &self.planes;
        Aabb {
            min: Vec3::new(p[0][i], p[2][i], p[4][i]),
            max: Vec3::new(p[1][i], p[3][i], p[5][i]),
        }
    }
}

/// Why a tree cannot be converted.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ConvertError {
    /// The tree's instances or instance leaves point outside its arrays, or a box is out
    /// of order or NaN (a tree edited by hand): what is wrong.
    #[error("the BVH cannot be converted: {0}")]
    Malformed(String),
    /// More blocks than a leaf reference can address.
    #[error("{0} triangle blocks exceed the CPU layout's 2^27")]
    TooLarge(usize),
}

/// A tree in the CPU layout (see the module docs), converted by [`CpuBvh::from_flat`].
#[derive(Clone, Debug, Default)]
pub struct CpuBvh {
    pub(crate) nodes: Vec<Node8>,
    pub(crate) blocks: Vec<Tri4>,
    /// Per block, where its lanes' binary leaf boxes are (see [`LeafBoxes`]):
    /// [`CORNER_BOXES`], or an index into `leaf_boxes`.
    pub(crate) box_index: Vec<u32>,
    /// The leaf boxes of the blocks whose boxes are not their triangles' own.
    pub(crate) leaf_boxes: Vec<LeafBoxes>,
    /// Levels of nodes on the longest path (0 for an empty tree); for two levels, the top
    /// level's and the deepest mesh's together (what the shared stack holds at most).
    pub(crate) depth: u32,
    pub(crate) triangles: usize,
    /// Two levels: the instances, in `FlatBvh::instances`' order (a top-level node's leaf
    /// child is `LEAF | index`); empty for one mesh.
    pub(crate) instances: Vec<CpuInstance>,
    /// The alpha masks the walks cut candidates by (the tree's own tables, shared).
    pub(crate) masks: Option<Arc<MaskTables>>,
    /// The box around the root's children ([`crate::tests4::SceneBox::around`]), made once:
    /// rays that miss it take no walk.
    pub(crate) scene_box: Option<crate::tests4::SceneBox>,
}

/// One instance as the two-level walk reads it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct CpuInstance {
    /// The core's instance: the transform (applied by its own `ray_to_object`), the
    /// primitive base and the visibility mask.
    pub flat: FlatInstance,
    /// Where the walk starts in the mesh: its root node, or its one leaf.
    pub root: ChildRef,
    /// `MaskTables::base` of the instance (0 without masks).
    pub mask_base: u32,
}

/// Which level a collapse converts: a mesh (leaves of triangles), or the top level of a
/// two-level tree (leaves of one instance each, of this many instances).
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Level {
    Mesh,
    Top(u32),
}

/// What a wide node's slot is made from while converting.
#[derive(Clone, Copy)]
pub(crate) enum Src {
    /// A binary node.
    Node(u32),
    /// A run of the binary tree's triangles (`first`, `count`), too long for one leaf.
    Run(u32, u32),
}

/// A leaf child's triangles, before their blocks are written.
pub(crate) struct PendingLeaf {
    pub node: u32,
    pub slot: u8,
    pub first_tri: u32,
    pub tris: u32,
}

impl CpuBvh {
    /// Converts a [`FlatBvh`]: one mesh, or two levels (a top level over instances, each
    /// mesh's tree converted once however many instances place it), with or without alpha
    /// masks (the tables are shared with `flat`, the walks apply them as the core walks
    /// do). The blocks are written in parallel on the current rayon pool; the node
    /// collapse is one pass over the binary nodes. A tree whose instances or instance
    /// leaves point outside its arrays, or with a box whose lower corner is not at or
    /// below its upper one, is refused ([`ConvertError::Malformed`]).
    pub fn from_flat(flat: &FlatBvh) -> Result<CpuBvh, ConvertError> {
        let (fnodes, ftris) = (flat.nodes(), flat.triangles());
        if fnodes.is_empty() {
            return Ok(CpuBvh::default());
        }
        let masks = flat.masks().cloned();
        let spans = subtree_spans(fnodes);
        let leaf_box = LeafBoxOf::of(flat);
        let tri_box = |t: usize| leaf_box.get(t);
        let plan = Plan::new(fnodes, &spans);
        // Reserved ahead, so that the arrays are rarely copied as they grow: builders'
        // trees give a wide node per 8 to 12 binary leaves and a leaf child per 3 (a
        // margin of 2 to 3), and the reserve is given back after (an over-reserve in
        // wasm, where memory is committed when allocated, stays bounded by the margin).
        let binary_leaves = fnodes.len() / 2 + 1;
        let mut nodes = Vec::with_capacity(binary_leaves / 4 + 1);
        let mut leaves = Vec::with_capacity(binary_leaves / 2 + 1);
        if !flat.is_instanced() {
            let depth = collapse(
                fnodes,
                &spans,
                &tri_box,
                0,
                Level::Mesh,
                &mut nodes,
                &mut leaves,
                &mut |_, _, _| {},
                Some(&plan),
            )?;
            let (blocks, box_index, leaf_boxes) =
                write_blocks(&mut nodes, &leaves, ftris, &tri_box)?;
            // The reserve given back: a large allocation shrinks in place.
            nodes.shrink_to_fit();
            return Ok(CpuBvh {
                scene_box: nodes.first().and_then(crate::tests4::SceneBox::around),
                nodes,
                blocks,
                box_index,
                leaf_boxes,
                depth,
                triangles: ftris.len(),
                masks,
                ..CpuBvh::default()
            });
        }
        let finst = flat.instances();
        if finst.len() >= LEAF as usize {
            return Err(ConvertError::Malformed(format!(
                "{} instances exceed the CPU layout's 2^31",
                finst.len()
            )));
        }
        let top = Level::Top(finst.len() as u32);
        let top_depth = collapse(
            fnodes,
            &spans,
            &tri_box,
            0,
            top,
            &mut nodes,
            &mut leaves,
            &mut |_, _, _| {},
            None,
        )?;
        // Each mesh once: its root's start reference, by binary root.
        let mut meshes = std::collections::HashMap::new();
        let mut mesh_depth = 0;
        let mut instances = Vec::with_capacity(finst.len());
        for (index, fi) in finst.iter().enumerate() {
            if fi.root < flat.top_nodes() || fi.root as usize >= fnodes.len() {
                return Err(ConvertError::Malformed(format!(
                    "instance {index}'s mesh root {} is not a mesh node ({} top-level nodes of {})",
                    fi.root,
                    flat.top_nodes(),
                    fnodes.len()
                )));
            }
            let root = match meshes.get(&fi.root) {
                Some(&r) => r,
                None => {
                    let at = nodes.len();
                    let d = collapse(
                        fnodes,
                        &spans,
                        &tri_box,
                        fi.root,
                        Level::Mesh,
                        &mut nodes,
                        &mut leaves,
                        &mut |_, _, _| {},
                        Some(&plan),
                    )?;
                    mesh_depth = mesh_depth.max(d);
                    meshes.insert(fi.root, at as u32);
                    at as u32
                }
            };
            instances.push(CpuInstance {
                flat: *fi,
                root,
                mask_base: masks.as_ref().map_or(0, |m| m.base(Some(index as u32))),
            });
        }
        let (blocks, box_index, leaf_boxes) = write_blocks(&mut nodes, &leaves, ftris, &tri_box)?;
        nodes.shrink_to_fit();
        // A mesh whose root is one leaf starts at the leaf: the core walks test no box of
        // the mesh's root either (the instance leaf's box stood for it).
        for inst in &mut instances {
            let n = &nodes[inst.root as usize];
            if n.used == 1 && n.child[0] & LEAF != 0 {
                inst.root = n.child[0];
            }
        }
        Ok(CpuBvh {
            scene_box: nodes.first().and_then(crate::tests4::SceneBox::around),
            nodes,
            blocks,
            box_index,
            leaf_boxes,
            depth: top_depth + mesh_depth,
            triangles: ftris.len(),
            instances,
            masks,
        })
    }

    /// The nodes; the root is node 0.
    pub fn nodes(&self) -> &[Node8] {
        &self.nodes
    }

    /// The triangle blocks.
    pub fn blocks(&self) -> &[Tri4] {
        &self.blocks
    }

    /// Levels of nodes on the longest root-to-leaf path.
    pub fn depth(&self) -> u32 {
        self.depth
    }

    /// Triangles of the tree it was converted from (a triangle the builder put in two
    /// leaves, as spatial splits do, counts once per leaf there and here).
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// Bytes of nodes, and of triangle blocks with their leaf boxes.
    pub fn byte_sizes(&self) -> (usize, usize) {
        (
            std::mem::size_of_val(self.nodes.as_slice()),
            std::mem::size_of_val(self.blocks.as_slice())
                + std::mem::size_of_val(self.box_index.as_slice())
                + std::mem::size_of_val(self.leaf_boxes.as_slice()),
        )
    }

    /// Block `block`'s lane `i`'s binary leaf box (see [`LeafBoxes`]).
    pub fn leaf_box(&self, block: usize, i: usize) -> Aabb {
        match self.box_index[block] {
            CORNER_BOXES => self.blocks[block].corner_box(i),
            k => self.leaf_boxes[k as usize].lane(i),
        }
    }

    /// Blocks whose leaf boxes are kept (the others' are their triangles' own).
    pub fn kept_leaf_boxes(&self) -> usize {
        self.leaf_boxes.len()
    }

    /// Bytes of the whole layout (nodes and blocks) per triangle; for two levels, per
    /// triangle of the meshes (each mesh counted once), the instances left out
    /// ([`CpuBvh::instance_bytes`]).
    pub fn bytes_per_triangle(&self) -> f64 {
        let (n, b) = self.byte_sizes();
        (n + b) as f64 / self.triangles.max(1) as f64
    }

    /// True for a two-level tree (instances over meshes).
    pub fn is_instanced(&self) -> bool {
        !self.instances.is_empty()
    }

    /// Instances of a two-level tree (0 for one mesh).
    pub fn instance_count(&self) -> usize {
        self.instances.len()
    }

    /// Bytes of the instance table (0 for one mesh).
    pub fn instance_bytes(&self) -> usize {
        std::mem::size_of_val(self.instances.as_slice())
    }

    /// The alpha masks the walks apply (the converted tree's own tables), if any.
    pub fn masks(&self) -> Option<&Arc<MaskTables>> {
        self.masks.as_ref()
    }

    /// True for one mesh without alpha masks: the tree the packet walk and the walks in
    /// turns take (the others go ray by ray, alone).
    pub fn is_plain(&self) -> bool {
        !self.is_instanced() && self.masks.is_none()
    }
}

/// Collapses the binary tree at `root` (a whole mesh, or the top level) into wide nodes
/// appended to `nodes`, the mesh's leaves appended to `leaves` (their blocks written
/// later); its first node is the tree's root; `on_slot(node, slot, src)` hears what each
/// slot was made from. A mesh's nodes take their slots from its `plan` (the least-cost
/// collapse); without one (the top level over instances), [`expand`] fills each node
/// greedily. Returns its levels of nodes.
#[allow(clippy::too_many_arguments)]
pub(crate) fn collapse(
    fnodes: &[FlatNode],
    spans: &[(u32, u32)],
    tri_box: &impl Fn(usize) -> Aabb,
    root: u32,
    level: Level,
    nodes: &mut Vec<Node8>,
    leaves: &mut Vec<PendingLeaf>,
    on_slot: &mut impl FnMut(u32, usize, Src),
    plan: Option<&Plan>,
) -> Result<u32, ConvertError> {
    let slots_of = |i: u32| match plan {
        Some(p) => p.slots(fnodes, i),
        None => expand(fnodes, spans, level, children_of(fnodes, i)),
    };
    let at = nodes.len() as u32;
    nodes.push(Node8::EMPTY);
    let mut depth = 1;
    let root_src = if fnodes[root as usize].is_leaf() {
        SrcList::of(&[Src::Node(root)])
    } else {
        slots_of(root)
    };
    // Depth first: each work item fills its node's slots, appending child nodes.
    let mut work = vec![(at, root_src, 1u32)];
    while let Some((at, srcs, depth_here)) = work.pop() {
        depth = depth.max(depth_here);
        for (slot, &src) in srcs.as_slice().iter().enumerate() {
            let mut pending = |first: u32, count: u32| {
                leaves.push(PendingLeaf {
                    node: at,
                    slot: slot as u8,
                    first_tri: first,
                    tris: count,
                });
            };
            let (bounds, child) = match src {
                Src::Node(i) if is_leaf_child(fnodes, spans, level, i) => {
                    let n = &fnodes[i as usize];
                    if let Level::Top(instances) = level {
                        if !n.is_instance_leaf() || n.right_or_first >= instances {
                            return Err(ConvertError::Malformed(format!(
                                "top-level leaf {i} is not one of the {instances} instances"
                            )));
                        }
                        (n.aabb(), LEAF | n.right_or_first)
                    } else {
                        let (first, count) = spans[i as usize];
                        if count.div_ceil(BLOCK as u32) > MAX_LEAF_BLOCKS {
                            let next = nodes.len() as u32;
                            nodes.push(Node8::EMPTY);
                            work.push((next, split_run(first, count), depth_here + 1));
                            (n.aabb(), next)
                        } else {
                            pending(first, count);
                            (n.aabb(), LEAF)
                        }
                    }
                }
                Src::Node(i) => {
                    let next = nodes.len() as u32;
                    nodes.push(Node8::EMPTY);
                    work.push((next, slots_of(i), depth_here + 1));
                    (fnodes[i as usize].aabb(), next)
                }
                Src::Run(first, count) => {
                    // The binary leaf's own box: a tighter one would cull triangles the
                    // binary walk tests (see `LeafBoxes`).
                    let b = tri_box(first as usize);
                    if count.div_ceil(BLOCK as u32) > MAX_LEAF_BLOCKS {
                        let next = nodes.len() as u32;
                        nodes.push(Node8::EMPTY);
                        work.push((next, split_run(first, count), depth_here + 1));
                        (b, next)
                    } else {
                        pending(first, count);
                        (b, LEAF)
                    }
                }
            };
            // The box tests that take each slab's entry from the plane the direction's sign
            // picks (the packets' one-origin test, the any-hit walks by octant) give the
            // scalar test's `fmin` only when the planes are in order (a builder's boxes
            // always are).
            if let Some(a) = (0..3).find(|&a| !(bounds.min[a] <= bounds.max[a])) {
                let of = match src {
                    Src::Node(i) => format!("binary node {i}"),
                    Src::Run(first, _) => format!("the leaf run from triangle {first}"),
                };
                return Err(ConvertError::Malformed(format!(
                    "the box of {of} is inverted or NaN on axis {a}: {bounds:?}"
                )));
            }
            nodes[at as usize].set(slot, &bounds, child);
            on_slot(at, slot, src);
        }
    }
    Ok(depth)
}

/// A wide node's slots while converting: up to [`WIDTH`], in order, with no allocation
/// (the collapse makes one per wide node).
#[derive(Clone, Copy)]
pub(crate) struct SrcList {
    items: [Src; WIDTH],
    len: usize,
}

impl SrcList {
    pub(crate) fn of(srcs: &[Src]) -> SrcList {
        let mut items = [Src::Run(0, 0); WIDTH];
        items[..srcs.len()].copy_from_slice(srcs);
        SrcList {
            items,
            len: srcs.len(),
        }
    }

    fn as_slice(&self) -> &[Src] {
        &self.items[..self.len]
    }

    /// Appends a slot (at most [`WIDTH`] in all).
    pub(crate) fn push(&mut self, src: Src) {
        self.items[self.len] = src;
        self.len += 1;
    }
}

/// A binary interior node's two children.
fn child_nodes(fnodes: &[FlatNode], i: u32) -> [Src; 2] {
    [
        Src::Node(i + 1),
        Src::Node(fnodes[i as usize].right_or_first),
    ]
}

/// [`child_nodes`] as a wide node's slots.
fn children_of(fnodes: &[FlatNode], i: u32) -> SrcList {
    SrcList::of(&child_nodes(fnodes, i))
}

/// Grows a slot list to eight: the interior child of largest surface area is replaced by
/// its two children, in its place, while there is one (the first of equal areas, so the
/// result is deterministic).
fn expand(fnodes: &[FlatNode], spans: &[(u32, u32)], level: Level, mut srcs: SrcList) -> SrcList {
    // Each slot's area when it can be opened, else none: computed once per slot.
    let openable = |s: Src| match s {
        Src::Node(i) if !is_leaf_child(fnodes, spans, level, i) => {
            Some(fnodes[i as usize].aabb().surface_area())
        }
        _ => None,
    };
    let mut area = [None; WIDTH];
    for (a, &s) in area.iter_mut().zip(srcs.as_slice()) {
        *a = openable(s);
    }
    while srcs.len < WIDTH {
        let mut pick: Option<(usize, f32)> = None;
        for (k, a) in area[..srcs.len].iter().enumerate() {
            if let Some(a) = *a
                && pick.is_none_or(|(_, best)| a > best)
            {
                pick = Some((k, a));
            }
        }
        let Some((k, _)) = pick else { break };
        let Src::Node(i) = srcs.items[k] else { break };
        let [a, b] = child_nodes(fnodes, i);
        // The slots after `k` move up one; `k` and `k + 1` take the two children.
        srcs.items.copy_within(k + 1..srcs.len, k + 2);
        area.copy_within(k + 1..srcs.len, k + 2);
        srcs.items[k] = a;
        srcs.items[k + 1] = b;
        area[k] = openable(a);
        area[k + 1] = openable(b);
        srcs.len += 1;
    }
    srcs
}

/// Binary subtrees of at most this many triangles become one leaf child (one block):
/// fewer box tests and no half-empty blocks, at the price of testing a few triangles
/// whose own boxes a ray misses.
pub const MERGE_TRIANGLES: u32 = BLOCK as u32;

/// Each binary node's triangles as a run `(first, count)`, or `count == u32::MAX` when
/// they are not one contiguous run (a tree flattened by hand).
pub(crate) fn subtree_spans(fnodes: &[FlatNode]) -> Vec<(u32, u32)> {
    let mut spans = vec![(0u32, 0u32); fnodes.len()];
    // Children come after their parent in the depth-first order: one backward pass.
    for i in (0..fnodes.len()).rev() {
        let n = &fnodes[i];
        spans[i] = if n.is_leaf() {
            (n.right_or_first, n.count())
        } else {
            let (l, r) = (spans[i + 1], spans[n.right_or_first as usize]);
            if l.1 != u32::MAX && r.1 != u32::MAX && l.0.checked_add(l.1) == Some(r.0) {
                (l.0, l.1 + r.1)
            } else {
                (0, u32::MAX)
            }
        };
    }
    spans
}

/// True when binary node `i` becomes a leaf child: a leaf, or in a mesh a subtree of at
/// most [`MERGE_TRIANGLES`] contiguous triangles (the top level keeps one instance per
/// leaf).
pub(crate) fn is_leaf_child(
    fnodes: &[FlatNode],
    spans: &[(u32, u32)],
    level: Level,
    i: u32,
) -> bool {
    fnodes[i as usize].is_leaf() || (level == Level::Mesh && spans[i as usize].1 <= MERGE_TRIANGLES)
}

/// A long run of triangles as up to eight shorter runs.
fn split_run(first: u32, count: u32) -> SrcList {
    let per = count.div_ceil(WIDTH as u32);
    let mut out = SrcList::of(&[]);
    for k in 0..WIDTH as u32 {
        let c = per.min(count.saturating_sub(k * per));
        if c > 0 {
            out.items[out.len] = Src::Run(first + k * per, c);
            out.len += 1;
        }
    }
    out
}

/// Each triangle slot's binary leaf box: the box the binary walk tests before the
/// triangle, or an infinite one for a mesh whose root is a leaf (inside an instance, the
/// binary walk tests no box of the mesh's root: the instance leaf's box stood for it).
/// Kept as each slot's leaf index, a quarter of the memory of the boxes themselves.
pub(crate) struct LeafBoxOf<'a> {
    fnodes: &'a [FlatNode],
    leaf: Vec<u32>,
}

impl<'a> LeafBoxOf<'a> {
    /// A slot no leaf holds (a tree flattened by hand): the empty box.
    const NONE: u32 = u32::MAX;
    /// A slot of a mesh whose root is a leaf: the infinite box.
    const EVERYWHERE: u32 = u32::MAX - 1;

    /// The leaf boxes of a tree of one mesh over `triangles` slots.
    pub(crate) fn new(fnodes: &'a [FlatNode], triangles: usize) -> LeafBoxOf<'a> {
        let leaf = leaf_of_triangles(fnodes, triangles, |i, _| i, Self::NONE);
        LeafBoxOf { fnodes, leaf }
    }

    /// The leaf boxes of `flat`, its instances' meshes included.
    fn of(flat: &'a FlatBvh) -> LeafBoxOf<'a> {
        let (fnodes, triangles) = (flat.nodes(), flat.triangles().len());
        let LeafBoxOf { mut leaf, .. } = LeafBoxOf::new(fnodes, triangles);
        for fi in flat.instances() {
            match fnodes.get(fi.root as usize) {
                Some(n) if n.is_leaf() && !n.is_instance_leaf() => {
                    let first = (n.right_or_first as usize).min(triangles);
                    let end = (first + n.count() as usize).min(triangles);
                    leaf[first..end].fill(Self::EVERYWHERE);
                }
                _ => {}
            }
        }
        LeafBoxOf { fnodes, leaf }
    }

    /// Triangle slot `t`'s box.
    pub(crate) fn get(&self, t: usize) -> Aabb {
        match self.leaf[t] {
            Self::NONE => Aabb::EMPTY,
            Self::EVERYWHERE => Aabb {
                min: Vec3::splat(f32::NEG_INFINITY),
                max: Vec3::splat(f32::INFINITY),
            },
            i => self.fnodes[i as usize].aabb(),
        }
    }
}

/// `of(i, node)` for each triangle slot's binary leaf `i` (`none` for a slot no leaf
/// holds).
pub(crate) fn leaf_of_triangles<T: Clone>(
    fnodes: &[FlatNode],
    triangles: usize,
    of: impl Fn(u32, &FlatNode) -> T,
    none: T,
) -> Vec<T> {
    let mut out = vec![none; triangles];
    for (i, n) in fnodes.iter().enumerate() {
        if n.is_leaf() && !n.is_instance_leaf() {
            let first = (n.right_or_first as usize).min(triangles);
            let end = (first + n.count() as usize).min(triangles);
            out[first..end].fill(of(i as u32, n));
        }
    }
    out
}

/// The triangle blocks, each block's place in the kept leaf boxes, and those boxes.
type Blocks = (Vec<Tri4>, Vec<u32>, Vec<LeafBoxes>);

/// Gives every leaf its blocks, in leaf order, and sets its node's leaf reference; returns
/// the blocks in all, or the error when they exceed what a reference addresses.
pub(crate) fn place_leaves(
    nodes: &mut [Node8],
    leaves: &[PendingLeaf],
) -> Result<usize, ConvertError> {
    place_leaves_of(nodes, leaves, BLOCK as u32)
}

/// [`place_leaves`] with `per_block` primitives to a block.
pub(crate) fn place_leaves_of(
    nodes: &mut [Node8],
    leaves: &[PendingLeaf],
    per_block: u32,
) -> Result<usize, ConvertError> {
    let blocks = |l: &PendingLeaf| l.tris.div_ceil(per_block);
    let total: usize = leaves.iter().map(|l| blocks(l) as usize).sum();
    if total > 1 << FIRST_BITS {
        return Err(ConvertError::TooLarge(total));
    }
    let mut first = 0;
    for l in leaves {
        nodes[l.node as usize].child[l.slot as usize] = leaf_ref(first, blocks(l));
        first += blocks(l);
    }
    Ok(total)
}

/// Allocates every leaf's blocks in leaf order, sets the leaf references, and fills the
/// blocks in parallel; then keeps the leaf boxes of the blocks that need theirs.
fn write_blocks(
    nodes: &mut [Node8],
    leaves: &[PendingLeaf],
    ftris: &[FlatTriangle],
    tri_box: &(impl Fn(usize) -> Aabb + Sync),
) -> Result<Blocks, ConvertError> {
    let total = place_leaves(nodes, leaves)?;
    // Each block's triangles, (first, count), in leaf order: the blocks are then filled
    // in parallel, each on its own.
    let mut block_tris: Vec<(u32, u32)> = Vec::with_capacity(total);
    for l in leaves {
        for k in (0..l.tris).step_by(BLOCK) {
            block_tris.push((l.first_tri + k, (l.tris - k).min(BLOCK as u32)));
        }
    }
    let range = |&(first, count): &(u32, u32)| first as usize..(first + count) as usize;
    // Zeroed memory comes from the allocator lazily: the blocks are written once, in
    // parallel below, not first on one thread.
    let mut blocks: Vec<Tri4> = bytemuck::zeroed_vec(total);
    let mut corner: Vec<bool> = vec![false; total];
    blocks
        .par_iter_mut()
        .zip(corner.par_iter_mut())
        .zip(block_tris.par_iter())
        .with_min_len(1024)
        .for_each(|((b, c), t)| {
            *b = Tri4::of(&ftris[range(t)]);
            // A free lane repeats the last triangle and its box: the used lanes decide.
            *c = range(t)
                .enumerate()
                .all(|(i, t)| tri_box(t) == b.corner_box(i));
        });
    // Only the blocks whose boxes are not their triangles' own keep theirs, made here:
    // most blocks need none.
    let mut box_index = Vec::with_capacity(total);
    let mut kept = Vec::with_capacity(corner.iter().filter(|&&c| !c).count());
    for (t, &is_corner) in block_tris.iter().zip(&corner) {
        if is_corner {
            box_index.push(CORNER_BOXES);
        } else {
            box_index.push(kept.len() as u32);
            let mut boxes = [Aabb::EMPTY; BLOCK];
            for (b, t) in boxes.iter_mut().zip(range(t)) {
                *b = tri_box(t);
            }
            kept.push(LeafBoxes::of(&boxes[..t.1 as usize]));
        }
    }
    Ok((blocks, box_index, kept))
}
