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
//! Greedy, top down: a wide node starts from its binary node's two children, and while it
//! has fewer than eight, the interior child of largest surface area is replaced by its two
//! children. A binary leaf, or a binary subtree of at most
//! [`MERGE_TRIANGLES`] triangles, becomes one leaf child. A leaf of more than
//! [`MAX_LEAF_BLOCKS`]` * 4` triangles (only with a large `max_leaf_size`) is split into a
//! node over runs of the leaf's triangles, boxed by their corners.
//!
//! Skipping the binary boxes between a wide node and its children only removes culls:
//! every walk over this layout visits a superset of what the binary walk would with the
//! same running best hit, so the closest hit is the binary walk's (see the crate docs).

use bvhtrace_core::{Aabb, FlatBvh, FlatNode, FlatTriangle};
use glam::Vec3;
use rayon::prelude::*;

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
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tri4 {
    /// `v[corner][axis][lane]`.
    pub v: [[[f32; BLOCK]; 3]; 3],
    /// Each lane's primitive id.
    pub prim: [u32; BLOCK],
}

impl Tri4 {
    /// The block of `tris` (one to four), its free lanes repeating the last triangle.
    fn of(tris: &[FlatTriangle]) -> Tri4 {
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

/// Why a tree cannot be converted.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ConvertError {
    /// Two-level trees are traced by the core walks, not by this layout.
    #[error("the CPU layout holds one mesh; this BVH has instances (trace it with bvhtrace_core)")]
    Instanced,
    /// Alpha-masked triangles (`FlatBvh::masks`): the layout's walks do not apply the masks,
    /// so they would return hits the core walks cut.
    #[error(
        "the CPU layout does not apply alpha masks; this BVH has masked triangles (trace it with bvhtrace_core)"
    )]
    Masked,
    /// More blocks than a leaf reference can address.
    #[error("{0} triangle blocks exceed the CPU layout's 2^27")]
    TooLarge(usize),
}

/// A tree in the CPU layout (see the module docs), converted by [`CpuBvh::from_flat`].
#[derive(Clone, Debug, Default)]
pub struct CpuBvh {
    pub(crate) nodes: Vec<Node8>,
    pub(crate) blocks: Vec<Tri4>,
    /// Levels of nodes on the longest path (0 for an empty tree).
    pub(crate) depth: u32,
    pub(crate) triangles: usize,
}

/// What a wide node's slot is made from while converting.
#[derive(Clone, Copy)]
enum Src {
    /// A binary node.
    Node(u32),
    /// A run of the binary tree's triangles (`first`, `count`), too long for one leaf.
    Run(u32, u32),
}

/// A leaf child's triangles, before their blocks are written.
struct PendingLeaf {
    node: u32,
    slot: u8,
    first_tri: u32,
    tris: u32,
}

impl CpuBvh {
    /// Converts a one-mesh [`FlatBvh`] without alpha masks ([`ConvertError::Instanced`],
    /// [`ConvertError::Masked`] otherwise). The blocks are written in parallel on the current
    /// rayon pool; the node collapse is one pass over the binary nodes.
    pub fn from_flat(flat: &FlatBvh) -> Result<CpuBvh, ConvertError> {
        if flat.is_instanced() {
            return Err(ConvertError::Instanced);
        }
        if flat.masks().is_some() {
            return Err(ConvertError::Masked);
        }
        let (fnodes, ftris) = (flat.nodes(), flat.triangles());
        if fnodes.is_empty() {
            return Ok(CpuBvh::default());
        }
        let spans = subtree_spans(fnodes);
        let mut nodes = vec![Node8::EMPTY];
        let mut leaves = Vec::new();
        let mut depth = 1;
        let root_src = if fnodes[0].is_leaf() {
            vec![Src::Node(0)]
        } else {
            children_of(fnodes, 0)
        };
        // Depth first: each work item fills its node's slots, appending child nodes.
        let mut work = vec![(0u32, root_src, 1u32)];
        while let Some((at, srcs, level)) = work.pop() {
            depth = depth.max(level);
            let srcs = expand(fnodes, &spans, srcs);
            for (slot, src) in srcs.into_iter().enumerate() {
                let (bounds, child) = match src {
                    Src::Node(i) if is_leaf_child(fnodes, &spans, i) => {
                        let n = &fnodes[i as usize];
                        let (first, count) = spans[i as usize];
                        if count.div_ceil(BLOCK as u32) > MAX_LEAF_BLOCKS {
                            let next = nodes.len() as u32;
                            nodes.push(Node8::EMPTY);
                            work.push((next, split_run(first, count), level + 1));
                            (n.aabb(), next)
                        } else {
                            leaves.push(PendingLeaf {
                                node: at,
                                slot: slot as u8,
                                first_tri: first,
                                tris: count,
                            });
                            (n.aabb(), LEAF)
                        }
                    }
                    Src::Node(i) => {
                        let next = nodes.len() as u32;
                        nodes.push(Node8::EMPTY);
                        work.push((next, children_of(fnodes, i), level + 1));
                        (fnodes[i as usize].aabb(), next)
                    }
                    Src::Run(first, count) => {
                        let b = run_bounds(&ftris[first as usize..(first + count) as usize]);
                        if count.div_ceil(BLOCK as u32) > MAX_LEAF_BLOCKS {
                            let next = nodes.len() as u32;
                            nodes.push(Node8::EMPTY);
                            work.push((next, split_run(first, count), level + 1));
                            (b, next)
                        } else {
                            leaves.push(PendingLeaf {
                                node: at,
                                slot: slot as u8,
                                first_tri: first,
                                tris: count,
                            });
                            (b, LEAF)
                        }
                    }
                };
                nodes[at as usize].set(slot, &bounds, child);
            }
        }
        let blocks = write_blocks(&mut nodes, &leaves, ftris)?;
        Ok(CpuBvh {
            nodes,
            blocks,
            depth,
            triangles: ftris.len(),
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

    /// Bytes of nodes and of triangle blocks.
    pub fn byte_sizes(&self) -> (usize, usize) {
        (
            std::mem::size_of_val(self.nodes.as_slice()),
            std::mem::size_of_val(self.blocks.as_slice()),
        )
    }

    /// Bytes of the whole layout per triangle.
    pub fn bytes_per_triangle(&self) -> f64 {
        let (n, b) = self.byte_sizes();
        (n + b) as f64 / self.triangles.max(1) as f64
    }
}

/// A binary interior node's two children.
fn children_of(fnodes: &[FlatNode], i: u32) -> Vec<Src> {
    vec![
        Src::Node(i + 1),
        Src::Node(fnodes[i as usize].right_or_first),
    ]
}

/// Grows a slot list to eight: the interior child of largest surface area is replaced by
/// its two children while there is one (the first of equal areas, so the result is
/// deterministic).
fn expand(fnodes: &[FlatNode], spans: &[(u32, u32)], mut srcs: Vec<Src>) -> Vec<Src> {
    while srcs.len() < WIDTH {
        let mut pick: Option<(usize, f32)> = None;
        for (k, s) in srcs.iter().enumerate() {
            if let Src::Node(i) = *s {
                let n = &fnodes[i as usize];
                let area = n.aabb().surface_area();
                if !is_leaf_child(fnodes, spans, i) && pick.is_none_or(|(_, a)| area > a) {
                    pick = Some((k, area));
                }
            }
        }
        let Some((k, _)) = pick else { break };
        let Src::Node(i) = srcs[k] else { break };
        srcs.splice(k..=k, children_of(fnodes, i));
    }
    srcs
}

/// Binary subtrees of at most this many triangles become one leaf child (one block):
/// fewer box tests and no half-empty blocks, at the price of testing a few triangles
/// whose own boxes a ray misses.
pub const MERGE_TRIANGLES: u32 = BLOCK as u32;

/// Each binary node's triangles as a run `(first, count)`, or `count == u32::MAX` when
/// they are not one contiguous run (a tree flattened by hand).
fn subtree_spans(fnodes: &[FlatNode]) -> Vec<(u32, u32)> {
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

/// True when binary node `i` becomes a leaf child: a leaf, or a subtree of at most
/// [`MERGE_TRIANGLES`] contiguous triangles.
fn is_leaf_child(fnodes: &[FlatNode], spans: &[(u32, u32)], i: u32) -> bool {
    fnodes[i as usize].is_leaf() || spans[i as usize].1 <= MERGE_TRIANGLES
}

/// A long run of triangles as up to eight shorter runs.
fn split_run(first: u32, count: u32) -> Vec<Src> {
    let per = count.div_ceil(WIDTH as u32);
    (0..WIDTH as u32)
        .map(|k| (first + k * per, per.min(count.saturating_sub(k * per))))
        .filter(|&(_, c)| c > 0)
        .map(|(f, c)| Src::Run(f, c))
        .collect()
}

/// The box of a run's corners.
fn run_bounds(tris: &[FlatTriangle]) -> Aabb {
    tris.iter()
        .map(|t| Aabb::from_triangle(&t.corners()))
        .fold(Aabb::EMPTY, |a, b| a.union(&b))
}

/// Allocates every leaf's blocks in leaf order, sets the leaf references, and fills the
/// blocks in parallel.
fn write_blocks(
    nodes: &mut [Node8],
    leaves: &[PendingLeaf],
    ftris: &[FlatTriangle],
) -> Result<Vec<Tri4>, ConvertError> {
    let mut starts = Vec::with_capacity(leaves.len());
    let mut total = 0usize;
    for l in leaves {
        starts.push(total);
        total += l.tris.div_ceil(BLOCK as u32) as usize;
    }
    if total > 1 << FIRST_BITS {
        return Err(ConvertError::TooLarge(total));
    }
    for (l, &s) in leaves.iter().zip(&starts) {
        let count = l.tris.div_ceil(BLOCK as u32);
        nodes[l.node as usize].child[l.slot as usize] = leaf_ref(s as u32, count);
    }
    let mut blocks = vec![
        Tri4 {
            v: [[[0.0; BLOCK]; 3]; 3],
            prim: [0; BLOCK],
        };
        total
    ];
    // Each leaf's blocks are a disjoint run: split the output by leaf and fill in parallel.
    let mut runs = Vec::with_capacity(leaves.len());
    let mut rest = blocks.as_mut_slice();
    for l in leaves {
        let (head, tail) = rest.split_at_mut(l.tris.div_ceil(BLOCK as u32) as usize);
        runs.push((head, l));
        rest = tail;
    }
    runs.into_par_iter()
        .with_min_len(1024)
        .for_each(|(out, l)| {
            let tris = &ftris[l.first_tri as usize..(l.first_tri + l.tris) as usize];
            for (b, chunk) in out.iter_mut().zip(tris.chunks(BLOCK)) {
                *b = Tri4::of(chunk);
            }
        });
    Ok(blocks)
}
