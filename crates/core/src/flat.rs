//! The flat layout: the one representation traversed on the CPU and uploaded to the GPU.
//!
//! # Layout (the single place it is described)
//!
//! * `nodes: [FlatNode]`, 32 bytes each, in depth-first order: the root is node 0 and an
//!   interior node's **first child is the next node** (`i + 1`); its second child's index
//!   is stored. WGSL twin: `Node` in `shaders/types.wgsl`.
//!   - `min`, `max`: the node's box.
//!   - `right_or_first`: interior: index of the second child; leaf: index of its first
//!     triangle in `triangles`.
//!   - `meta`: `count << 2 | axis`. `count > 0` marks a leaf holding triangles
//!     `right_or_first .. right_or_first + count`; `count == 0` marks an interior node
//!     split along `axis` (0 = x, 1 = y, 2 = z). The stackless and short-stack traversals
//!     visit the child on the ray's side of `axis` first (Hapala et al. 2011), which
//!     depends only on the ray's [`octant`].
//! * `escapes: [u32]`, eight per node: `escapes[escape_index(i, o)]` is where a walk in
//!   octant `o` goes when it is done with node `i`'s subtree: its skip link, the next node
//!   of the octant's depth-first order ([`NO_ESCAPE`] after the last). In blocks of
//!   [`ESCAPE_BLOCK`] consecutive nodes, octant by octant, so that the links one walk reads
//!   (its octant's, of neighbouring nodes) share cache lines; the last block is padded.
//!   Only the stackless and short-stack traversals read them, so they are built from the
//!   nodes on first use ([`FlatBvh::escapes`]) and only those walks' uploads carry them: a
//!   BVH only walked otherwise never pays their bytes (as many as the nodes') or time.
//! * `triangles: [FlatTriangle]`, 48 bytes each, in leaf order (every leaf is a contiguous
//!   range); each carries its corners and its index in the builder's input (`prim`), so no
//!   indirection is needed to report hits. WGSL twin: `Triangle`.
//!
//! # Two levels (instances over meshes)
//! A BVH over instances ([`crate::instance::InstancedBvh`]) is the same arrays, concatenated:
//! * `nodes`: the top level first (`0 .. top_nodes`, built over the instances' world boxes,
//!   one instance per leaf), then each mesh's tree as above, its child and triangle
//!   indices offset to where it lands. A top-level leaf is marked by axis bits
//!   [`INSTANCE_LEAF`] (`meta = 1 << 2 | 3`) and its `right_or_first` is an index into
//!   `instances`;
//! * `escapes`: [`escape_links`] of the whole array, built on first use as well (no node
//!   links one level to the other: an instance leaf has no children, and a mesh's root
//!   escapes to [`NO_ESCAPE`]);
//! * `triangles`: each mesh's triangles once, `prim` the index within its mesh;
//! * `instances: [FlatInstance]`, 64 bytes each: the world-to-object transform, the mesh's
//!   root node, and `prim_base`, the instance's first primitive id. WGSL twin: `BvhInstance`.
//!
//! A walk standing on an instance leaf whose box it hits transforms the ray into the mesh's
//! space (the same `t` parametrisation: the direction is transformed, not normalised),
//! goes on at the mesh's root, and transforms back when it reaches a top-level node again
//! (popped, or the top-level leaf's escape link once the mesh's walk escapes to
//! `NO_ESCAPE`). A hit reports `prim_base + prim`: primitive ids are numbered instance by
//! instance, as the flattened scene numbers its triangles, and
//! [`crate::instance::InstancedBvh::locate`] splits one into (instance, primitive).

use std::ops::Range;
use std::sync::{Arc, OnceLock};

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::build::{BuildNode, BuildTree};
use crate::geometry::Aabb;
use crate::masks::MaskTables;
use crate::mesh::Triangle;
use crate::wide::WideBvh;

/// The most primitives one BVH may hold (30 bits of leaf offsets and counts, with room for
/// the miss codes in `Hit::prim`).
pub const MAX_PRIMITIVES: usize = (1 << 30) - 1;

/// The escape link after the last node of a walk: the walk is over.
pub const NO_ESCAPE: u32 = u32::MAX;

/// Escape links per node, one per ray octant.
pub const OCTANTS: usize = 8;

/// The ray's octant: bit `a` is set when the direction's component `a` is not `>= 0`
/// (negative or NaN). An interior node split along `a` is entered on its second child
/// first when bit `a` is set, else on its first (`i + 1`).
#[inline(always)]
pub fn octant(dir: Vec3) -> usize {
    usize::from(!(dir.x >= 0.0))
        | usize::from(!(dir.y >= 0.0)) << 1
        | usize::from(!(dir.z >= 0.0)) << 2
}

/// The child entered first and the one entered second, for octant `oct`, of interior node
/// `index`.
#[inline(always)]
pub fn near_far(oct: usize, index: u32, n: &FlatNode) -> (u32, u32) {
    let (l, r) = (index + 1, n.right_or_first);
    if (oct >> n.axis()) & 1 == 0 {
        (l, r)
    } else {
        (r, l)
    }
}

/// The axis bits of a top-level leaf holding one instance (`right_or_first` is its index
/// in `FlatBvh::instances`).
pub const INSTANCE_LEAF: u32 = 3;

/// Nodes per block of `FlatBvh::escapes`.
pub const ESCAPE_BLOCK: usize = 16;

/// Where node `i`'s escape link for octant `oct` is in `FlatBvh::escapes`.
#[inline(always)]
pub fn escape_index(i: u32, oct: usize) -> usize {
    let i = i as usize;
    (i / ESCAPE_BLOCK) * ESCAPE_BLOCK * OCTANTS + oct * ESCAPE_BLOCK + i % ESCAPE_BLOCK
}

/// The length of `FlatBvh::escapes` for `nodes` nodes: eight links per node, in whole
/// blocks.
pub fn escape_links_len(nodes: usize) -> usize {
    nodes.div_ceil(ESCAPE_BLOCK) * ESCAPE_BLOCK * OCTANTS
}

/// The escape links set by hand ([`FlatBvh::set_escapes`]) do not fit `FlatBvh::nodes`, or
/// the nodes were edited after the links were built: a walk reading them could leave the
/// tree. (Links built on first use always fit.)
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "the BVH has {found} escape links for {nodes} nodes, where the stackless and short-stack \
     walks need {expected} (FlatBvh::build_escapes sets them to \
     bvhtrace_core::flat::escape_links(&nodes))"
)]
pub struct EscapeLinksMismatch {
    /// Nodes in the BVH.
    pub nodes: usize,
    /// Links it has.
    pub found: usize,
    /// Links it needs ([`escape_links_len`]).
    pub expected: usize,
}

/// The escape links of `nodes` (see the module docs): the near child of a node escapes to
/// its far child, the far child to where the node escapes. Parents come before their
/// children in the layout, so one pass in index order sets every link.
pub fn escape_links(nodes: &[FlatNode]) -> Vec<u32> {
    let mut e = vec![NO_ESCAPE; escape_links_len(nodes.len())];
    link_children(nodes, &mut e, 0..nodes.len());
    e
}

/// Sets the escape links of `nodes[range]`, a whole tree (its first node the root) or a
/// run of whole trees, in `escapes`: what rebuilding one tree of a two-level BVH rewrites.
pub fn set_escape_links(nodes: &[FlatNode], escapes: &mut [u32], range: Range<usize>) {
    for i in range.clone() {
        for o in 0..OCTANTS {
            escapes[escape_index(i as u32, o)] = NO_ESCAPE;
        }
    }
    link_children(nodes, escapes, range);
}

/// Sets the links of every child of an interior node in `range`, parents first; a root's
/// links stay as they are ([`NO_ESCAPE`]).
fn link_children(nodes: &[FlatNode], escapes: &mut [u32], range: Range<usize>) {
    // Node `i`'s link for octant `o` is at `block(i) + o * ESCAPE_BLOCK`.
    let block = |i: u32| escape_index(i, 0);
    for i in range {
        let n = &nodes[i];
        if n.is_leaf() {
            continue;
        }
        let (l, r) = (i as u32 + 1, n.right_or_first);
        let (bi, bl, br) = (block(i as u32), block(l), block(r));
        for o in 0..OCTANTS {
            let up = escapes[bi + o * ESCAPE_BLOCK];
            // The near child escapes to the far one, the far one to where the node does.
            if (o >> n.axis()) & 1 == 0 {
                escapes[bl + o * ESCAPE_BLOCK] = r;
                escapes[br + o * ESCAPE_BLOCK] = up;
            } else {
                escapes[br + o * ESCAPE_BLOCK] = l;
                escapes[bl + o * ESCAPE_BLOCK] = up;
            }
        }
    }
}

/// Why [`FlatBvh::refit`] refused (the BVH is left as it was).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RefitError {
    /// Not as many triangles as the tree was built over.
    #[error(
        "{given} triangles given for a tree over {built} (a refit keeps the triangles; rebuild instead)"
    )]
    Count {
        /// Triangles given.
        given: usize,
        /// Triangles in the tree.
        built: usize,
    },
    /// A two-level tree, refitted a mesh at a time.
    #[error("a two-level BVH is refitted a mesh at a time (InstancedBvh::refit_mesh)")]
    TwoLevels,
    /// A corner is NaN or infinite (the error names it).
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshError),
}

/// Refits the boxes of `nodes[range]` (whole trees, with absolute child and triangle
/// indices) bottom up from `triangles`: children come after their parents, so one pass
/// backwards refits every box.
pub(crate) fn refit_boxes(nodes: &mut [FlatNode], triangles: &[FlatTriangle], range: Range<usize>) {
    for i in range.rev() {
        let n = nodes[i];
        let b = if n.is_leaf() {
            let f = n.right_or_first as usize;
            triangles[f..f + n.count() as usize]
                .iter()
                .fold(Aabb::EMPTY, |b, t| {
                    b.union(&Aabb::from_triangle(&t.corners()))
                })
        } else {
            nodes[i + 1]
                .aabb()
                .union(&nodes[n.right_or_first as usize].aabb())
        };
        let n = &mut nodes[i];
        (n.min, n.max) = (b.min.to_array(), b.max.to_array());
    }
}

/// One BVH node (see the module docs for the encoding).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct FlatNode {
    /// The box's lower corner.
    pub min: [f32; 3],
    /// Interior: index of the second child; leaf: index of its first triangle.
    pub right_or_first: u32,
    /// The box's upper corner.
    pub max: [f32; 3],
    /// `count << 2 | axis`: a leaf's triangle count, or 0 and an interior node's split axis.
    pub meta: u32,
}

impl FlatNode {
    /// Number of triangles in a leaf; 0 for an interior node.
    #[inline(always)]
    pub fn count(&self) -> u32 {
        self.meta >> 2
    }
    /// True for a leaf.
    #[inline(always)]
    pub fn is_leaf(&self) -> bool {
        self.meta >> 2 != 0
    }
    /// Split axis of an interior node.
    #[inline(always)]
    pub fn axis(&self) -> usize {
        (self.meta & 3) as usize
    }
    /// True for a top-level leaf holding an instance ([`INSTANCE_LEAF`]).
    #[inline(always)]
    pub fn is_instance_leaf(&self) -> bool {
        self.meta & 3 == INSTANCE_LEAF && self.is_leaf()
    }
    /// The node's box.
    pub fn aabb(&self) -> Aabb {
        Aabb {
            min: Vec3::from(self.min),
            max: Vec3::from(self.max),
        }
    }
}

/// One triangle in leaf order.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct FlatTriangle {
    /// The first corner.
    pub v0: [f32; 3],
    /// Index of this triangle in the builder's input.
    pub prim: u32,
    /// The second corner.
    pub v1: [f32; 3],
    /// Padding to 16 bytes (zero).
    pub _pad1: u32,
    /// The third corner.
    pub v2: [f32; 3],
    /// Padding to 16 bytes (zero).
    pub _pad2: u32,
}

impl FlatTriangle {
    /// Triangle `t`, the builder's input number `prim`, as the layouts store it.
    pub fn new(t: &Triangle, prim: u32) -> FlatTriangle {
        FlatTriangle {
            v0: t[0].to_array(),
            prim,
            v1: t[1].to_array(),
            _pad1: 0,
            v2: t[2].to_array(),
            _pad2: 0,
        }
    }

    /// The three corners.
    #[inline(always)]
    pub fn corners(&self) -> [Vec3; 3] {
        [
            Vec3::from(self.v0),
            Vec3::from(self.v1),
            Vec3::from(self.v2),
        ]
    }
}

/// One instance as the walks read it (see the module docs).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct FlatInstance {
    /// The world-to-object transform, three rows of a 3x4 matrix: an object-space point is
    /// `row[k] . (x, y, z, 1)`, a direction `row[k] . (x, y, z, 0)`
    /// ([`FlatInstance::ray_to_object`]).
    pub world_to_object: [[f32; 4]; 3],
    /// The mesh's root in `FlatBvh::nodes`.
    pub root: u32,
    /// The instance's first primitive id: a hit on the mesh's primitive `p` reports
    /// `prim_base + p`.
    pub prim_base: u32,
    /// Visibility mask (8 bits): a ray whose mask ([`crate::TraceOptions::mask`]) shares no
    /// bit with it passes through the instance.
    pub mask: u32,
    /// The caller's id for the instance.
    pub user_id: u32,
}

impl FlatInstance {
    /// The ray in the mesh's space: origin and direction transformed, the interval kept
    /// (so `t` is comparable across instances). The arithmetic of the kernels'
    /// `bvh_ray_to_object`, product by product, left to right.
    #[inline(always)]
    pub fn ray_to_object(&self, ray: &crate::Ray) -> crate::Ray {
        let m = &self.world_to_object;
        let (o, d) = (ray.origin, ray.dir);
        let point = |r: &[f32; 4]| r[0] * o[0] + r[1] * o[1] + r[2] * o[2] + r[3];
        let vector = |r: &[f32; 4]| r[0] * d[0] + r[1] * d[1] + r[2] * d[2];
        crate::Ray {
            origin: [point(&m[0]), point(&m[1]), point(&m[2])],
            t_min: ray.t_min,
            dir: [vector(&m[0]), vector(&m[1]), vector(&m[2])],
            t_max: ray.t_max,
        }
    }
}

/// A BVH ready to traverse or upload.
///
/// Equality compares the escape links as [`FlatBvh::escapes`] returns them: links not built
/// yet stand for `escape_links(&nodes)`, what they will be, so building them changes no
/// comparison (links built on one side only are compared with the other's computed for
/// the occasion, not kept).
///
/// The fields are read through accessors named after them ([`FlatBvh::nodes`],
/// [`FlatBvh::triangles`], ...): the escape links and the wide layout are kept with the
/// tree and follow from it, so the tree is changed only through methods that keep them
/// (or drop them) with it. The fields are crate-visible for the builders, refits and
/// instancing code that fill them in.
#[derive(Clone, Debug, Default)]
pub struct FlatBvh {
    /// The nodes, depth-first; the root is node 0.
    pub(crate) nodes: Vec<FlatNode>,
    /// [`escape_links`] of `nodes`, eight per node, built on first use
    /// ([`FlatBvh::escapes`]) or set by hand ([`FlatBvh::set_escapes`]): only two walks
    /// read them, and they weigh as much as the nodes.
    pub(crate) escapes: OnceLock<Vec<u32>>,
    /// The triangles in leaf order.
    pub(crate) triangles: Vec<FlatTriangle>,
    /// Longest root-to-leaf path, in edges (a single leaf has depth 0); for two levels,
    /// through an instance leaf into its mesh (what a full stack holds at most).
    pub(crate) depth: u32,
    /// The instances of a two-level BVH; empty for one mesh.
    pub(crate) instances: Vec<FlatInstance>,
    /// Nodes of the top level (`nodes[..top_nodes]`); 0 for one mesh.
    pub(crate) top_nodes: u32,
    /// The same tree in the wide layout, for [`crate::Traversal::Wide`]: `None` until
    /// [`FlatBvh::build_wide`] (the GPU uploads convert it themselves when it is missing).
    pub(crate) wide: Option<Arc<WideBvh>>,
    /// The alpha-tested triangles every walk cuts candidates by; `None` when no triangle
    /// is masked ([`FlatBvh::set_masks`]).
    pub(crate) masks: Option<Arc<MaskTables>>,
}

/// The editable fields of a [`FlatBvh`] ([`FlatBvh::parts_mut`]), for tests and tools that
/// build or corrupt trees by hand. The cached escape links and wide layout are cleared
/// when this is taken; each field is documented on its accessor.
#[doc(hidden)]
#[derive(Debug)]
pub struct FlatParts<'a> {
    /// [`FlatBvh::nodes`].
    pub nodes: &'a mut Vec<FlatNode>,
    /// [`FlatBvh::triangles`].
    pub triangles: &'a mut Vec<FlatTriangle>,
    /// [`FlatBvh::depth`].
    pub depth: &'a mut u32,
    /// [`FlatBvh::instances`].
    pub instances: &'a mut Vec<FlatInstance>,
    /// [`FlatBvh::top_nodes`].
    pub top_nodes: &'a mut u32,
}

impl PartialEq for FlatBvh {
    fn eq(&self, other: &FlatBvh) -> bool {
        // Destructured so that a new field cannot be left out of the comparison.
        let FlatBvh {
            nodes,
            escapes: _,
            triangles,
            depth,
            instances,
            top_nodes,
            wide,
            masks,
        } = self;
        *nodes == other.nodes
            && *triangles == other.triangles
            && *depth == other.depth
            && *instances == other.instances
            && *top_nodes == other.top_nodes
            && *wide == other.wide
            && *masks == other.masks
            && match (self.escapes.get(), other.escapes.get()) {
                // Same nodes: the same links once built.
                (None, None) => true,
                (Some(a), Some(b)) => a == b,
                (Some(a), None) | (None, Some(a)) => *a == escape_links(nodes),
            }
    }
}

impl FlatBvh {
    /// Lays out a build tree depth-first over the given triangles (the builder's input).
    pub fn flatten(tree: &BuildTree, tris: &[Triangle]) -> FlatBvh {
        let mut bvh = FlatBvh {
            nodes: Vec::with_capacity(tree.node_count),
            triangles: tree
                .prim_order
                .iter()
                .map(|&p| FlatTriangle::new(&tris[p as usize], p))
                .collect(),
            ..FlatBvh::default()
        };
        bvh.emit(&tree.root, 0);
        bvh
    }

    fn emit(&mut self, node: &BuildNode, depth: u32) -> u32 {
        let index = self.nodes.len() as u32;
        self.depth = self.depth.max(depth);
        let b = node.bounds();
        self.nodes.push(FlatNode {
            min: b.min.to_array(),
            right_or_first: 0,
            max: b.max.to_array(),
            meta: 0,
        });
        match node {
            BuildNode::Leaf { first, count, .. } => {
                let n = &mut self.nodes[index as usize];
                n.right_or_first = *first;
                n.meta = count << 2;
            }
            BuildNode::Interior { axis, children, .. } => {
                self.emit(&children[0], depth + 1);
                let right = self.emit(&children[1], depth + 1);
                let n = &mut self.nodes[index as usize];
                n.right_or_first = right;
                n.meta = *axis as u32;
            }
        }
        index
    }

    /// Builds and flattens in one call.
    pub fn build(
        tris: &[Triangle],
        opts: &crate::build::BuildOptions,
    ) -> Result<FlatBvh, crate::build::BuildError> {
        crate::build::build_flat(tris, opts)
    }

    /// A BVH of `nodes` (already in the flat layout) over `tris` taken in `prim_order`.
    pub(crate) fn from_nodes(
        nodes: Vec<FlatNode>,
        depth: u32,
        prim_order: &[u32],
        tris: &[Triangle],
    ) -> FlatBvh {
        use rayon::prelude::*;
        let triangles = prim_order
            .par_iter()
            .with_min_len(4096)
            .map(|&p| FlatTriangle::new(&tris[p as usize], p))
            .collect();
        FlatBvh {
            nodes,
            triangles,
            depth,
            ..FlatBvh::default()
        }
    }

    /// The nodes, depth-first; the root is node 0.
    pub fn nodes(&self) -> &[FlatNode] {
        &self.nodes
    }

    /// The triangles in leaf order.
    pub fn triangles(&self) -> &[FlatTriangle] {
        &self.triangles
    }

    /// Longest root-to-leaf path, in edges (a single leaf has depth 0); for two levels,
    /// through an instance leaf into its mesh (what a full stack holds at most).
    pub fn depth(&self) -> u32 {
        self.depth
    }

    /// The instances of a two-level BVH; empty for one mesh.
    pub fn instances(&self) -> &[FlatInstance] {
        &self.instances
    }

    /// Nodes of the top level (`nodes()[..top_nodes]`); 0 for one mesh.
    pub fn top_nodes(&self) -> u32 {
        self.top_nodes
    }

    /// The same tree in the wide layout, for [`crate::Traversal::Wide`]: `None` until
    /// [`FlatBvh::build_wide`] (the GPU uploads convert it themselves when it is missing).
    pub fn wide(&self) -> Option<&Arc<WideBvh>> {
        self.wide.as_ref()
    }

    /// Sets the wide layout to one already collapsed from this same tree
    /// ([`WideBvh::collapse`] of it, as it is now), sparing a second collapse; `None` drops
    /// it. A layout collapsed from another tree would be walked as this one's: pass only
    /// this tree's.
    pub fn set_wide(&mut self, wide: Option<Arc<WideBvh>>) {
        self.wide = wide;
    }

    /// The alpha-tested triangles every walk (CPU and device) cuts candidates by
    /// ([`crate::masks`]); `None` when no triangle is masked.
    pub fn masks(&self) -> Option<&Arc<MaskTables>> {
        self.masks.as_ref()
    }

    /// Attaches the masked triangles' tables (`bvhtrace_scene::Scene::alpha_masks` makes
    /// them from a scene's materials), or drops them with `None` (every triangle opaque
    /// again). They must cover this tree: one state per primitive id for one mesh, one
    /// base per instance for two levels. They follow refits and moved instances (the
    /// primitive ids and the instance list stay); new instances drop them.
    pub fn set_masks(&mut self, masks: Option<Arc<MaskTables>>) -> Result<(), String> {
        if let Some(m) = &masks {
            if self.is_instanced() {
                if m.instance_bases.len() != self.instances.len() {
                    return Err(format!(
                        "the masks have {} instance bases for {} instances",
                        m.instance_bases.len(),
                        self.instances.len()
                    ));
                }
            } else if let Some(t) = self
                .triangles
                .iter()
                .find(|t| t.prim as usize >= m.states.len())
            {
                return Err(format!(
                    "the masks have {} states, but the tree has primitive {}",
                    m.states.len(),
                    t.prim
                ));
            }
        }
        self.masks = masks;
        Ok(())
    }

    /// The fields to edit by hand, for tests and tools that build or corrupt trees by hand
    /// (a depth that is not the tree's, triangles past a device's limits, children out of
    /// range). Clears the cached escape links and wide layout first, so that neither
    /// outlives the edit: build them again ([`FlatBvh::build_escapes`],
    /// [`FlatBvh::build_wide`]) or set them ([`FlatBvh::set_escapes`]) afterwards when
    /// needed. Nothing checks the edited tree; [`FlatBvh::check_invariants`] can.
    #[doc(hidden)]
    pub fn parts_mut(&mut self) -> FlatParts<'_> {
        self.clear_escapes();
        self.wide = None;
        FlatParts {
            nodes: &mut self.nodes,
            triangles: &mut self.triangles,
            depth: &mut self.depth,
            instances: &mut self.instances,
            top_nodes: &mut self.top_nodes,
        }
    }

    /// A one-mesh tree from its arrays, as a device builder reads them back (depth-first
    /// nodes with the left child next, triangles in leaf order, the longest root-to-leaf
    /// path in edges). Nothing is checked here: [`FlatBvh::check_invariants`] does.
    pub fn from_parts(nodes: Vec<FlatNode>, triangles: Vec<FlatTriangle>, depth: u32) -> FlatBvh {
        FlatBvh {
            nodes,
            triangles,
            depth,
            ..FlatBvh::default()
        }
    }

    /// Converts the tree into the wide layout as well ([`crate::wide::WideBvh::collapse`]),
    /// so that [`crate::Traversal::Wide`] can walk it. Editing the tree by hand
    /// ([`FlatBvh::parts_mut`]) drops it: call this again afterwards to have it back.
    pub fn build_wide(&mut self) {
        self.wide = None;
        self.wide = Some(Arc::new(WideBvh::collapse(self)));
    }

    /// The same tree with its wide layout built ([`FlatBvh::build_wide`]).
    pub fn with_wide(mut self) -> FlatBvh {
        self.build_wide();
        self
    }

    /// The escape links (see the module docs), eight per node: built from `nodes`
    /// ([`escape_links`]) on the first call, by whichever thread makes it (the others
    /// wait), and kept; or as set by hand ([`FlatBvh::set_escapes`]). Only the stackless
    /// and short-stack walks read them, so a BVH walked only otherwise never builds them.
    /// Kept links do not follow edits of the tree's shape (children, axes): call
    /// [`FlatBvh::build_escapes`] or [`FlatBvh::clear_escapes`] after one.
    pub fn escapes(&self) -> &[u32] {
        self.escapes.get_or_init(|| escape_links(&self.nodes))
    }

    /// True when the escape links are there (built, or set by hand); false while they
    /// are still to be built on first use.
    pub fn has_escapes(&self) -> bool {
        self.escapes.get().is_some()
    }

    /// Builds the escape links now, replacing any there were: ahead of the walks that
    /// read them (so that no trace or upload pays for it), or after editing the tree's
    /// shape. A refit (boxes moved) leaves them valid.
    pub fn build_escapes(&mut self) {
        self.escapes = OnceLock::from(escape_links(&self.nodes));
    }

    /// The same tree with its escape links built ([`FlatBvh::build_escapes`]).
    pub fn with_escapes(mut self) -> FlatBvh {
        self.build_escapes();
        self
    }

    /// The escape links to edit in place, built first when they are not there: for
    /// partial updates ([`set_escape_links`] over the trees that changed) and for tests.
    pub fn escapes_mut(&mut self) -> &mut Vec<u32> {
        if self.escapes.get().is_none() {
            self.build_escapes();
        }
        match self.escapes.get_mut() {
            Some(e) => e,
            None => unreachable!("the escape links were just built"),
        }
    }

    /// Sets the escape links by hand (a BVH assembled by hand, or a test of links that
    /// do not fit: [`FlatBvh::check_escape_links`] is what catches those).
    pub fn set_escapes(&mut self, links: Vec<u32>) {
        self.escapes = OnceLock::from(links);
    }

    /// Drops the escape links (their memory goes back); the next [`FlatBvh::escapes`]
    /// builds them again from the nodes as they are then.
    pub fn clear_escapes(&mut self) {
        self.escapes = OnceLock::new();
    }

    /// After `nodes[range]` (whole trees, as [`set_escape_links`] takes) changed shape:
    /// rewrites their escape links when the links are there, and leaves links not built
    /// yet to be built on first use. Links that do not fit the nodes are built anew.
    pub fn relink_escapes(&mut self, range: Range<usize>) {
        let expected = escape_links_len(self.nodes.len());
        match self.escapes.get_mut() {
            None => {}
            Some(e) if e.len() == expected => set_escape_links(&self.nodes, e, range),
            Some(_) => self.build_escapes(),
        }
    }

    /// The escape links, built for the occasion (and not kept) when they are not there:
    /// for checks, which should not leave a BVH heavier than they found it.
    pub(crate) fn escapes_or_computed(&self) -> std::borrow::Cow<'_, [u32]> {
        match self.escapes.get() {
            Some(e) => std::borrow::Cow::Borrowed(e),
            None => std::borrow::Cow::Owned(escape_links(&self.nodes)),
        }
    }

    /// The vertices moved (same triangles, `tris` in the builder's input order): the
    /// corners are replaced and every box refitted bottom up, the tree kept; the wide
    /// layout, when there is one, is collapsed again. A one-level tree only (a two-level
    /// one is refitted a mesh at a time, [`crate::InstancedBvh::refit_mesh`]). An error
    /// leaves the BVH as it was. `GpuRefit` in bvhtrace-gpu is its twin on the device.
    pub fn refit(&mut self, tris: &[Triangle]) -> Result<(), RefitError> {
        if self.is_instanced() {
            return Err(RefitError::TwoLevels);
        }
        if tris.len() != self.triangles.len() {
            return Err(RefitError::Count {
                given: tris.len(),
                built: self.triangles.len(),
            });
        }
        crate::mesh::validate_triangles(tris)?;
        for t in &mut self.triangles {
            let [a, b, c] = tris[t.prim as usize];
            (t.v0, t.v1, t.v2) = (a.to_array(), b.to_array(), c.to_array());
        }
        let n = self.nodes.len();
        refit_boxes(&mut self.nodes, &self.triangles, 0..n);
        if self.wide.is_some() {
            self.build_wide();
        }
        Ok(())
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// The scene's box.
    pub fn bounds(&self) -> Aabb {
        self.nodes[0].aabb()
    }

    /// True for a two-level BVH (instances over meshes).
    pub fn is_instanced(&self) -> bool {
        !self.instances.is_empty()
    }

    /// Bytes of the nodes, escape links and triangles as uploaded (the instances,
    /// when there are any, are `size_of_val(instances)` more). The escape links count
    /// whether built yet or not ([`escape_links_len`]), as the uploads that carry them do.
    pub fn byte_sizes(&self) -> (usize, usize, usize) {
        (
            std::mem::size_of_val(self.nodes.as_slice()),
            escape_links_len(self.nodes.len()) * std::mem::size_of::<u32>(),
            std::mem::size_of_val(self.triangles.as_slice()),
        )
    }

    /// Checks that there are as many escape links as the nodes need (what a GPU upload
    /// checks before the stackless and short-stack kernels may follow them;
    /// [`FlatBvh::check_invariants`] checks where they lead). Links not built yet pass
    /// (they will be built to fit) and stay unbuilt.
    pub fn check_escape_links(&self) -> Result<(), EscapeLinksMismatch> {
        let expected = escape_links_len(self.nodes.len());
        match self.escapes.get() {
            Some(e) if e.len() != expected => Err(EscapeLinksMismatch {
                nodes: self.nodes.len(),
                found: e.len(),
                expected,
            }),
            _ => Ok(()),
        }
    }

    /// Checks every structural invariant; returns a description of the first violation.
    /// Used by the tests; cheap enough to run on any tree. Every primitive id from 0 to
    /// the largest is in a leaf, and the leaf boxes holding a triangle cover its box: one
    /// box contains it, or (an SBVH's references, [`crate::BuilderKind::Sbvh`]) several
    /// leaves hold it, each box meeting it.
    pub fn check_invariants(&self) -> Result<(), String> {
        if self.is_instanced() {
            return crate::instance::check_two_level(self);
        }
        let n_nodes = self.nodes.len();
        let n_tris = self.triangles.len();
        if n_nodes == 0 || n_nodes > 2 * n_tris.max(1) - 1 {
            return Err(format!("{n_nodes} nodes for {n_tris} triangles"));
        }
        let mut seen = vec![false; n_tris];
        let mut covered = vec![false; n_tris];
        let mut coverage = Coverage::default();
        // Children in range first: the escape links are computed from them. Parents come
        // before their children, so one pass also measures the depth the walks size by.
        let mut depth = vec![0u32; n_nodes];
        for (i, n) in self.nodes.iter().enumerate() {
            let r = n.right_or_first as usize;
            if n.is_leaf() {
                continue;
            }
            if r <= i + 1 || r >= n_nodes || n.axis() > 2 {
                return Err(format!("node {i}: bad children {}, {r}", i + 1));
            }
            (depth[i + 1], depth[r]) = (depth[i] + 1, depth[i] + 1);
        }
        let longest = depth.into_iter().max().unwrap_or(0);
        if longest != self.depth {
            return Err(format!("depth {} stated, {longest} found", self.depth));
        }
        self.check_escape_links().map_err(|e| e.to_string())?;
        let escapes = self.escapes_or_computed();
        if (0..OCTANTS).any(|o| escapes[escape_index(0, o)] != NO_ESCAPE) {
            return Err("the root escapes somewhere".into());
        }
        for (i, n) in self.nodes.iter().enumerate() {
            let b = n.aabb();
            if n.is_leaf() {
                let (f, c) = (n.right_or_first as usize, n.count() as usize);
                if f + c > n_tris {
                    return Err(format!("leaf {i} range {f}+{c} past {n_tris}"));
                }
                for (k, t) in self.triangles[f..f + c].iter().enumerate() {
                    if covered[f + k] {
                        return Err(format!("triangle slot {} in two leaves", f + k));
                    }
                    covered[f + k] = true;
                    let p = t.prim as usize;
                    if p >= n_tris {
                        return Err(format!("primitive {p} out of range"));
                    }
                    seen[p] = true;
                    coverage.add(&b, t).map_err(|e| format!("leaf {i}: {e}"))?;
                }
            } else {
                let l = i + 1;
                let r = n.right_or_first as usize;
                if r <= l || r >= n_nodes || n.axis() > 2 {
                    return Err(format!("node {i}: bad children {l}, {r}"));
                }
                for o in 0..OCTANTS {
                    let (near, far) = near_far(o, i as u32, n);
                    let (en, ef) = (
                        escapes[escape_index(near, o)],
                        escapes[escape_index(far, o)],
                    );
                    if en != far || ef != escapes[escape_index(i as u32, o)] {
                        return Err(format!(
                            "node {i}, octant {o}: children escape to {en} and {ef}"
                        ));
                    }
                }
                for c in [l, r] {
                    if !b.contains(&self.nodes[c].aabb()) {
                        return Err(format!("node {i} box does not contain child {c}"));
                    }
                }
            }
        }
        // Primitive ids run from 0 to the largest present (with no repeat, that is every
        // slot's; an SBVH's references may repeat one).
        let n_prims = seen.iter().rposition(|s| *s).map_or(0, |p| p + 1);
        if let Some(p) = seen[..n_prims].iter().position(|s| !s) {
            return Err(format!("primitive {p} is in no leaf"));
        }
        coverage.finish()
    }
}

/// Checks that the leaf boxes holding a triangle cover it: each one meets the
/// triangle's box, and together they cover that box. With one reference per triangle
/// that is "the leaf's box contains the triangle's"; an SBVH leaf may hold only the part
/// of a triangle on its side of a split plane ([`crate::BuilderKind::Sbvh`]). A triangle
/// is known by its stored bytes (corners and primitive id), so the meshes of a two-level
/// layout need no separating.
#[derive(Default)]
pub(crate) struct Coverage {
    parts: std::collections::HashMap<[u32; 12], Aabb>,
}

impl Coverage {
    /// Records that a leaf (or wide child) with box `b` holds `t`.
    pub(crate) fn add(&mut self, b: &Aabb, t: &FlatTriangle) -> Result<(), String> {
        let tb = Aabb::from_triangle(&t.corners());
        let part = Aabb {
            min: b.min.max(tb.min),
            max: b.max.min(tb.max),
        };
        if part.is_empty() {
            return Err(format!("box misses triangle {}", t.prim));
        }
        let key: [u32; 12] = bytemuck::cast(*t);
        let e = self.parts.entry(key).or_insert(Aabb::EMPTY);
        *e = e.union(&part);
        Ok(())
    }

    /// Checks that every triangle's parts cover its box.
    pub(crate) fn finish(&self) -> Result<(), String> {
        for (key, part) in &self.parts {
            let t: FlatTriangle = bytemuck::cast(*key);
            if !part.contains(&Aabb::from_triangle(&t.corners())) {
                return Err(format!(
                    "the leaves holding primitive {} do not cover its box",
                    t.prim
                ));
            }
        }
        Ok(())
    }
}
