//! Two levels: a top-level BVH over instances, each instance a mesh (with its own BVH), a
//! transform, a user id and a visibility mask.
//!
//! [`InstancedBvh`] keeps one bottom-level BVH per mesh however many instances use it, and
//! lays everything out as one [`FlatBvh`] (the two-level layout is described in
//! [`crate::flat`]), so every walk and every backend traces it as it traces one mesh.
//!
//! # What a hit reports
//! `Hit::prim` is the instance's `prim_base` plus the primitive's index in its mesh:
//! instance by instance, in instance order, as [`crate::FlatBvh`] of the flattened scene
//! numbers them. [`InstancedBvh::locate`] splits it into (instance, primitive). `t` is in
//! the world ray's parametrisation (the direction is transformed, not normalised), so it
//! compares across instances; it is computed in the mesh's space, from the ray rounded
//! to f32 there, so it equals the flattened scene's `t` within the f32 error of the
//! transform (`docs/design.md`, *Two levels*). For a mirroring instance, `u` and `v` are
//! the mesh's corners' (the flattened scene swaps corners 1 and 2 to keep the winding).
//!
//! # Moving things
//! * [`InstancedBvh::set_transforms`]: the instances moved; the top level is rebuilt (it
//!   has `2n - 1` nodes for `n` instances whatever their placement, so the upload keeps
//!   its buffers and only the top level and the instances are written again).
//! * [`InstancedBvh::refit_mesh`]: a mesh's vertices moved (same triangles); its boxes are
//!   refitted bottom up, the tree kept, and the top level rebuilt.
//!   [`InstancedBvh::refit_quality`] says how much the SAH cost has grown since the build;
//!   past [`REFIT_REBUILD_ADVISED`] a rebuild ([`InstancedBvh::rebuild_mesh`]) pays.

use bytemuck::Zeroable;
use glam::{Affine3A, DAffine3, DVec3, Vec3};
use rayon::prelude::*;

use crate::build::{BuildError, BuildNode, BuildOptions, build_boxes};
use crate::flat::{
    FlatBvh, FlatInstance, FlatNode, INSTANCE_LEAF, OCTANTS, escape_index, set_escape_links,
};
use crate::geometry::Aabb;
use crate::mesh::Triangle;
use crate::ray::INCOMPLETE;

/// The SAH cost growth (refitted over built, [`InstancedBvh::refit_quality`]) past which
/// rebuilding the mesh's tree is advised: the rays traced through it cost about this much
/// more. Measured on `igea` with every vertex moved (`docs/design.md`, *Refit*).
pub const REFIT_REBUILD_ADVISED: f64 = 1.5;

/// The relative padding of an instance's world box: its eight transformed corners
/// (in f64) are rounded outwards and pushed out by this times the box's largest
/// coordinate, which covers the f32 rounding of the ray transform for rays whose origins
/// are within a few times that distance (rays starting inside the box never depend on
/// it: their origin is in the box).
const WORLD_BOX_PAD: f64 = 1.0 / (1 << 17) as f64;

/// One placement of a mesh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Instance {
    /// Index of the mesh.
    pub mesh: u32,
    /// Object-to-world transform (finite and invertible).
    pub transform: Affine3A,
    /// The caller's id, kept with the instance (`FlatInstance::user_id`).
    pub user_id: u32,
    /// Visibility mask: rays whose mask ([`crate::TraceOptions::mask`]) shares no bit
    /// with it pass through.
    pub mask: u8,
}

impl Instance {
    /// Mesh `mesh` placed by `transform`, user id 0, visible to every ray.
    pub fn new(mesh: u32, transform: Affine3A) -> Self {
        Instance {
            mesh,
            transform,
            user_id: 0,
            mask: 0xff,
        }
    }
}

/// Why a two-level BVH could not be made or changed. Each names the instance or mesh.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InstanceError {
    /// An instance is not usable: a mesh index out of range, or a transform that is not
    /// finite or not invertible.
    #[error("instance {index}: {problem}")]
    BadInstance {
        /// The instance's index.
        index: usize,
        /// What is wrong.
        problem: String,
    },
    /// A mesh's BVH could not be built (or its new vertices are unusable).
    #[error("mesh {mesh}: {problem}")]
    BadMesh {
        /// The mesh's index.
        mesh: usize,
        /// What is wrong.
        problem: String,
    },
    /// No instances: there is nothing to trace.
    #[error("a two-level BVH needs at least one instance")]
    NoInstances,
    /// More primitives over all instances than 32-bit primitive ids can number (the top
    /// three values are the miss codes).
    #[error(
        "{0} primitives over all instances: hit primitive ids are 32-bit (at most {max})",
        max = INCOMPLETE as u64
    )]
    TooManyPrimitives(u64),
}

/// Where one mesh's tree lies in the two-level layout.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshSlot {
    /// Its root in `FlatBvh::nodes`.
    pub node_base: u32,
    /// Its node count.
    pub nodes: u32,
    /// Its first triangle in `FlatBvh::triangles`.
    pub tri_base: u32,
    /// Its triangle slots in `FlatBvh::triangles` (more than `primitives` when its tree
    /// is an SBVH, whose leaves may share a triangle).
    pub triangles: u32,
    /// Its primitives: the mesh's triangle count, ids `0..primitives`.
    pub primitives: u32,
    /// Its depth.
    pub depth: u32,
    /// SAH cost (traversal 1, intersection 1, root-normalised) when it was built.
    pub built_sah: f64,
}

/// A top-level BVH over instances of meshes, laid out as one [`FlatBvh`].
#[derive(Clone, Debug, PartialEq)]
pub struct InstancedBvh {
    bvh: FlatBvh,
    meshes: Vec<MeshSlot>,
    instances: Vec<Instance>,
    /// Each mesh's primitive `p` is in triangle slot `tri_base + slots[tri_base + p]`.
    slots: Vec<u32>,
    top_depth: u32,
}

/// Top level: one instance per leaf, SAH over the world boxes.
fn top_options() -> BuildOptions {
    BuildOptions {
        max_leaf_size: 1,
        ..BuildOptions::default()
    }
}

/// `m` in f64 and its world-to-object rows, or why `m` cannot place an instance.
pub(crate) fn check_transform(
    index: usize,
    m: &Affine3A,
) -> Result<(DAffine3, [[f32; 4]; 3]), InstanceError> {
    let bad = |problem: &str| InstanceError::BadInstance {
        index,
        problem: problem.into(),
    };
    if !m.is_finite() {
        return Err(bad("the transform has a NaN or infinite entry"));
    }
    let d = DAffine3::from_mat4(glam::Mat4::from(*m).as_dmat4());
    let det = d.matrix3.determinant();
    if det == 0.0 || !det.is_finite() {
        return Err(bad(
            "the transform is singular (determinant 0): it has no inverse",
        ));
    }
    let inv = d.inverse();
    let ok = inv.matrix3.is_finite() && inv.translation.is_finite();
    let f32_ok = inv.to_cols_array().iter().all(|x| (*x as f32).is_finite());
    if !ok || !f32_ok {
        return Err(bad("the transform's inverse overflows f32"));
    }
    // The inverse's rows, rounded to f32 once.
    let rows = std::array::from_fn(|r| {
        let row = inv.matrix3.row(r);
        let t = inv.translation[r];
        [row.x as f32, row.y as f32, row.z as f32, t as f32]
    });
    Ok((d, rows))
}

/// The world box of object box `b` under `d`, conservative (see [`WORLD_BOX_PAD`]).
pub(crate) fn world_box(d: &DAffine3, b: &Aabb) -> Aabb {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for k in 0..8 {
        let c = DVec3::new(
            if k & 1 == 0 { b.min.x } else { b.max.x } as f64,
            if k & 2 == 0 { b.min.y } else { b.max.y } as f64,
            if k & 4 == 0 { b.min.z } else { b.max.z } as f64,
        );
        let w = d.transform_point3(c);
        lo = lo.min(w);
        hi = hi.max(w);
    }
    let pad = lo.abs().max(hi.abs()).max_element() * WORLD_BOX_PAD;
    let down = |x: f64| {
        let f = (x - pad) as f32;
        if f as f64 > x - pad { f.next_down() } else { f }
    };
    let up = |x: f64| {
        let f = (x + pad) as f32;
        if (f as f64) < x + pad { f.next_up() } else { f }
    };
    Aabb {
        min: Vec3::new(down(lo.x), down(lo.y), down(lo.z)),
        max: Vec3::new(up(hi.x), up(hi.y), up(hi.z)),
    }
}

/// A triangle standing for box `b` in a builder over triangles: `[min, max, centre]`, whose
/// bounding box is `b` exactly and whose centroid is `b`'s centre (halves first, so huge
/// boxes do not overflow). What a top level built by such a builder takes
/// ([`InstancedBvh::set_transforms_with`]).
pub fn box_triangle(b: &Aabb) -> Triangle {
    [b.min, b.max, b.min * 0.5 + b.max * 0.5]
}

/// Where the top level comes from: our CPU builder, or a caller's builder over the world
/// boxes ([`InstancedBvh::set_transforms_with`]).
enum TopLevel<'a> {
    Cpu,
    Given(&'a mut dyn FnMut(&[Aabb]) -> Result<FlatBvh, String>),
}

/// Checks a caller's top-level tree over `boxes`: `2n - 1` nodes, each reached once from
/// the root (left child next, right child later), each leaf one box (every box once), each
/// leaf's box containing its box and each interior node's its children's. Returns its
/// depth.
fn check_top_tree(tree: &FlatBvh, boxes: &[Aabb]) -> Result<u32, String> {
    let n = boxes.len();
    let nodes = &tree.nodes;
    if nodes.len() != 2 * n - 1 || tree.triangles.len() != n {
        return Err(format!(
            "{} nodes and {} leaf slots for {n} instances (want {} and {n})",
            nodes.len(),
            tree.triangles.len(),
            2 * n - 1
        ));
    }
    let (mut reached, mut seen) = (vec![false; nodes.len()], vec![false; n]);
    let contains = |a: &Aabb, b: &Aabb| a.min.cmple(b.min).all() && a.max.cmpge(b.max).all();
    let (mut stack, mut depth) = (vec![(0usize, 0u32)], 0);
    while let Some((i, d)) = stack.pop() {
        depth = depth.max(d);
        if std::mem::replace(&mut reached[i], true) {
            return Err(format!("node {i} is reached twice"));
        }
        let (node, b) = (&nodes[i], nodes[i].aabb());
        if node.is_leaf() {
            let prim = (tree.triangles.get(node.right_or_first as usize)).map(|t| t.prim as usize);
            match prim {
                Some(p) if node.count() == 1 && p < n && !seen[p] && contains(&b, &boxes[p]) => {
                    seen[p] = true;
                }
                _ => {
                    return Err(format!(
                        "leaf {i} is not one instance's box, once, contained"
                    ));
                }
            }
        } else {
            let (l, r) = (i + 1, node.right_or_first as usize);
            if r <= l || r >= nodes.len() {
                return Err(format!("node {i}'s children {l} and {r} are out of order"));
            }
            if !contains(&b, &nodes[l].aabb()) || !contains(&b, &nodes[r].aabb()) {
                return Err(format!("node {i} does not contain its children"));
            }
            stack.extend([(r, d + 1), (l, d + 1)]);
        }
    }
    match reached.iter().position(|r| !r) {
        Some(i) => Err(format!("node {i} is not reached from the root")),
        None => Ok(depth),
    }
}

/// SAH cost of `nodes` (one tree, its root first), traversal 1 and intersection 1,
/// normalised by the root's area ([`crate::BvhStats::sah_cost`]'s convention).
fn sah_cost(nodes: &[FlatNode]) -> f64 {
    let root = nodes[0].aabb().surface_area() as f64;
    let sum: f64 = nodes
        .iter()
        .map(|n| n.aabb().surface_area() as f64 * n.count().max(1) as f64)
        .sum();
    if root > 0.0 { sum / root } else { 0.0 }
}

impl InstancedBvh {
    /// Builds one BVH per mesh (in parallel, with `opts`) and the top level over
    /// `instances`. `meshes[i]` is mesh `i`'s triangles.
    pub fn build(
        meshes: &[Vec<Triangle>],
        instances: Vec<Instance>,
        opts: &BuildOptions,
    ) -> Result<InstancedBvh, InstanceError> {
        let trees = meshes
            .par_iter()
            .enumerate()
            .map(|(i, tris)| {
                FlatBvh::build(tris, opts).map_err(|e: BuildError| InstanceError::BadMesh {
                    mesh: i,
                    problem: e.to_string(),
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        InstancedBvh::new(trees, instances)
    }

    /// Lays out `meshes` (one-mesh BVHs, as [`FlatBvh::flatten`] makes them) under a top
    /// level over `instances`.
    pub fn new(
        meshes: Vec<FlatBvh>,
        instances: Vec<Instance>,
    ) -> Result<InstancedBvh, InstanceError> {
        if instances.is_empty() {
            return Err(InstanceError::NoInstances);
        }
        for (i, m) in meshes.iter().enumerate() {
            if m.is_instanced() || m.nodes.is_empty() {
                return Err(InstanceError::BadMesh {
                    mesh: i,
                    problem: "expected a one-mesh BVH with at least one triangle".into(),
                });
            }
        }
        let top_nodes = 2 * instances.len() - 1;
        let mut bvh = FlatBvh {
            top_nodes: top_nodes as u32,
            ..FlatBvh::default()
        };
        bvh.nodes.resize(top_nodes, FlatNode::zeroed());
        let mut slots = Vec::new();
        let mut slot_list = Vec::with_capacity(meshes.len());
        for m in &meshes {
            let (node_base, tri_base) = (bvh.nodes.len() as u32, bvh.triangles.len() as u32);
            bvh.nodes.extend(m.nodes.iter().map(|n| {
                let mut n = *n;
                n.right_or_first += if n.is_leaf() { tri_base } else { node_base };
                n
            }));
            bvh.triangles.extend_from_slice(&m.triangles);
            slots.resize(bvh.triangles.len(), 0);
            for (slot, t) in m.triangles.iter().enumerate() {
                slots[(tri_base + t.prim) as usize] = slot as u32;
            }
            slot_list.push(MeshSlot {
                node_base,
                nodes: m.nodes.len() as u32,
                tri_base,
                triangles: m.triangles.len() as u32,
                // Every primitive is in some leaf: the largest id names the count.
                primitives: m.triangles.iter().map(|t| t.prim + 1).max().unwrap_or(0),
                depth: m.depth,
                built_sah: sah_cost(&m.nodes),
            });
        }
        if bvh.nodes.len() > u32::MAX as usize / 2 || bvh.triangles.len() > u32::MAX as usize / 2 {
            return Err(InstanceError::TooManyPrimitives(bvh.triangles.len() as u64));
        }
        // The escape links are left to be built on first use, over both levels at once.
        let mut out = InstancedBvh {
            bvh,
            meshes: slot_list,
            instances: Vec::new(),
            slots,
            top_depth: 0,
        };
        out.set_instances(instances)?;
        Ok(out)
    }

    /// Replaces the instances (same count: the layout keeps its size) and rebuilds the
    /// top level with our binned SAH builder.
    fn set_instances(&mut self, instances: Vec<Instance>) -> Result<(), InstanceError> {
        self.set_instances_with(instances, TopLevel::Cpu)
    }

    /// The instances' records and world boxes, or why one cannot be placed.
    fn place(
        &self,
        instances: &[Instance],
    ) -> Result<(Vec<FlatInstance>, Vec<Aabb>), InstanceError> {
        let mut flat = Vec::with_capacity(instances.len());
        let mut boxes = Vec::with_capacity(instances.len());
        let mut prim_base = 0u64;
        for (i, inst) in instances.iter().enumerate() {
            let Some(mesh) = self.meshes.get(inst.mesh as usize) else {
                return Err(InstanceError::BadInstance {
                    index: i,
                    problem: format!(
                        "mesh {} does not exist ({} meshes)",
                        inst.mesh,
                        self.meshes.len()
                    ),
                });
            };
            let (d, world_to_object) = check_transform(i, &inst.transform)?;
            boxes.push(world_box(
                &d,
                &self.bvh.nodes[mesh.node_base as usize].aabb(),
            ));
            flat.push(FlatInstance {
                world_to_object,
                root: mesh.node_base,
                prim_base: prim_base as u32,
                mask: u32::from(inst.mask),
                user_id: inst.user_id,
            });
            prim_base += u64::from(mesh.primitives);
        }
        if prim_base >= u64::from(INCOMPLETE) {
            return Err(InstanceError::TooManyPrimitives(prim_base));
        }
        Ok((flat, boxes))
    }

    /// [`InstancedBvh::set_instances`] with the top level from `top`.
    fn set_instances_with(
        &mut self,
        instances: Vec<Instance>,
        top: TopLevel<'_>,
    ) -> Result<(), InstanceError> {
        let (flat, boxes) = self.place(&instances)?;
        let bad = |problem: String| InstanceError::BadInstance { index: 0, problem };
        let mut next = 0u32;
        self.top_depth = 0;
        match top {
            TopLevel::Cpu => {
                let tree = build_boxes(&boxes, &top_options()).map_err(|e| bad(e.to_string()))?;
                self.emit_top(&tree.root, &tree.prim_order, &mut next, 0);
            }
            TopLevel::Given(build) => {
                let tree =
                    build(&boxes).map_err(|e| bad(format!("the top level's builder: {e}")))?;
                let depth = check_top_tree(&tree, &boxes)
                    .map_err(|e| bad(format!("the top level given: {e}")))?;
                self.copy_top(&tree);
                self.top_depth = depth;
                next = tree.nodes.len() as u32;
            }
        }
        debug_assert_eq!(next, self.bvh.top_nodes);
        let top = self.bvh.top_nodes as usize;
        // Built links: the top level's rewritten (the meshes' stay); unbuilt: left so.
        self.bvh.relink_escapes(0..top);
        let deepest_mesh = instances
            .iter()
            .map(|i| self.meshes[i.mesh as usize].depth)
            .max()
            .unwrap_or(0);
        self.bvh.depth = self.top_depth + deepest_mesh;
        self.bvh.instances = flat;
        // Masks follow moved instances; other instances (other meshes) drop them.
        let same_meshes = self.instances.len() == instances.len()
            && (self.instances.iter().zip(&instances)).all(|(a, b)| a.mesh == b.mesh);
        if !same_meshes {
            self.bvh.masks = None;
        }
        self.instances = instances;
        // New transforms or refitted meshes: the wide layout, when there is one, follows.
        if self.bvh.wide.is_some() {
            self.bvh.build_wide();
        }
        Ok(())
    }

    /// Attaches alpha masks to the two-level BVH ([`FlatBvh::set_masks`]: one instance
    /// base per instance), or drops them with `None`.
    pub fn set_masks(
        &mut self,
        masks: Option<std::sync::Arc<crate::MaskTables>>,
    ) -> Result<(), String> {
        self.bvh.set_masks(masks)
    }

    /// Moves the instances as [`InstancedBvh::set_transforms`] does, with the top level
    /// built by `build` instead of our CPU builder: given the instances' world boxes (in
    /// instance order, conservative), it returns a BVH over them in the [`FlatBvh`]
    /// layout with one box per leaf, the box's index as the leaf triangle's `prim` (as a
    /// builder over triangles `[min, max, centre]` of each box gives it; the device builder
    /// in bvhtrace-gpu does, `GpuContext::set_transforms_on_device`). A tree that is not
    /// such a tree (a box missing or twice, a leaf of several, a box not contained) is an
    /// error, and like any error leaves the BVH as it was.
    pub fn set_transforms_with(
        &mut self,
        transforms: &[Affine3A],
        build: &mut dyn FnMut(&[Aabb]) -> Result<FlatBvh, String>,
    ) -> Result<(), InstanceError> {
        let moved = self.moved(transforms)?;
        let mut copy = self.clone();
        copy.set_instances_with(moved, TopLevel::Given(build))?;
        *self = copy;
        Ok(())
    }

    /// The instances' world boxes (conservative, in instance order) were they moved to
    /// `transforms`: what [`InstancedBvh::set_transforms_with`]'s builder is given. An
    /// unusable transform is an error naming the instance.
    pub fn world_boxes(&self, transforms: &[Affine3A]) -> Result<Vec<Aabb>, InstanceError> {
        Ok(self.place(&self.moved(transforms)?)?.1)
    }

    /// The instances with `transforms`, one per instance.
    fn moved(&self, transforms: &[Affine3A]) -> Result<Vec<Instance>, InstanceError> {
        if transforms.len() != self.instances.len() {
            return Err(InstanceError::BadInstance {
                index: transforms.len().min(self.instances.len()),
                problem: format!(
                    "{} transforms for {} instances",
                    transforms.len(),
                    self.instances.len()
                ),
            });
        }
        Ok(self
            .instances
            .iter()
            .zip(transforms)
            .map(|(i, t)| Instance {
                transform: *t,
                ..*i
            })
            .collect())
    }

    /// Copies a checked top-level tree ([`check_top_tree`]) over the top nodes: leaves
    /// name their instance.
    fn copy_top(&mut self, tree: &FlatBvh) {
        for (i, n) in tree.nodes.iter().enumerate() {
            let mut n = *n;
            if n.is_leaf() {
                n.right_or_first = tree.triangles[n.right_or_first as usize].prim;
                n.meta = 1 << 2 | INSTANCE_LEAF;
            }
            self.bvh.nodes[i] = n;
        }
    }

    fn emit_top(&mut self, node: &BuildNode, order: &[u32], next: &mut u32, depth: u32) -> u32 {
        let index = *next;
        *next += 1;
        self.top_depth = self.top_depth.max(depth);
        let b = node.bounds();
        let (right_or_first, meta) = match node {
            BuildNode::Leaf { first, .. } => (order[*first as usize], 1 << 2 | INSTANCE_LEAF),
            BuildNode::Interior { axis, children, .. } => {
                self.emit_top(&children[0], order, next, depth + 1);
                let right = self.emit_top(&children[1], order, next, depth + 1);
                (right, u32::from(*axis))
            }
        };
        self.bvh.nodes[index as usize] = FlatNode {
            min: b.min.to_array(),
            right_or_first,
            max: b.max.to_array(),
            meta,
        };
        index
    }

    /// The layout every walk and backend traces.
    pub fn bvh(&self) -> &FlatBvh {
        &self.bvh
    }

    /// The instances, as given.
    pub fn instances(&self) -> &[Instance] {
        &self.instances
    }

    /// Where each mesh's tree lies.
    pub fn meshes(&self) -> &[MeshSlot] {
        &self.meshes
    }

    /// Primitives over all instances (the flattened scene's triangle count).
    pub fn instanced_primitives(&self) -> u64 {
        match (self.bvh.instances.last(), self.instances.last()) {
            (Some(f), Some(i)) => {
                u64::from(f.prim_base) + u64::from(self.meshes[i.mesh as usize].primitives)
            }
            _ => 0,
        }
    }

    /// The (instance, primitive in its mesh) of a hit's primitive id; `None` for a miss
    /// code or an id past the last instance.
    pub fn locate(&self, prim: u32) -> Option<(u32, u32)> {
        let inst = &self.bvh.instances;
        let i = inst
            .partition_point(|f| f.prim_base <= prim)
            .checked_sub(1)?;
        let mesh = &self.meshes[self.instances[i].mesh as usize];
        let local = prim - inst[i].prim_base;
        (local < mesh.primitives).then_some((i as u32, local))
    }

    /// The world-space corners of the primitive a hit reports (the instance's transform
    /// applied in f32, as the flattened scene applies it); `None` as for
    /// [`InstancedBvh::locate`].
    pub fn world_triangle(&self, prim: u32) -> Option<Triangle> {
        let (i, local) = self.locate(prim)?;
        let inst = &self.instances[i as usize];
        let mesh = &self.meshes[inst.mesh as usize];
        let slot = mesh.tri_base + self.slots[(mesh.tri_base + local) as usize];
        let corners = self.bvh.triangles[slot as usize].corners();
        Some(corners.map(|c| inst.transform.transform_point3(c)))
    }

    /// The object-space corners of the primitive a hit reports, with its instance as
    /// traced (what `hits::instance_surface` takes); `None` as for
    /// [`InstancedBvh::locate`].
    pub fn object_triangle(&self, prim: u32) -> Option<(Triangle, &FlatInstance)> {
        let (i, local) = self.locate(prim)?;
        let mesh = &self.meshes[self.instances[i as usize].mesh as usize];
        let slot = mesh.tri_base + self.slots[(mesh.tri_base + local) as usize];
        let corners = self.bvh.triangles[slot as usize].corners();
        Some((corners, &self.bvh.instances[i as usize]))
    }

    /// Bytes of the top level (nodes, their escape links, the instances) and of the
    /// meshes (nodes, escape links, triangles), as uploaded with escape links.
    pub fn level_bytes(&self) -> (usize, usize) {
        let top = self.bvh.top_nodes as usize;
        let node = std::mem::size_of::<FlatNode>();
        let link = OCTANTS * 4;
        let top_bytes =
            top * (node + link) + self.bvh.instances.len() * std::mem::size_of::<FlatInstance>();
        let (n, e, t) = self.bvh.byte_sizes();
        (top_bytes, n + e + t - top * (node + link))
    }

    /// Moves the instances: new object-to-world transforms, one per instance, and the top
    /// level rebuilt. An unusable transform is an error naming the instance, and leaves
    /// the BVH as it was.
    pub fn set_transforms(&mut self, transforms: &[Affine3A]) -> Result<(), InstanceError> {
        let moved = self.moved(transforms)?;
        self.set_instances(moved)
    }

    /// A mesh's vertices moved: `tris` are its triangles in their original order (same
    /// count). Its tree is kept and its boxes refitted bottom up; the top level is
    /// rebuilt. A NaN or infinite corner is an error naming the triangle, and leaves the
    /// BVH as it was.
    pub fn refit_mesh(&mut self, mesh: usize, tris: &[Triangle]) -> Result<(), InstanceError> {
        let bad = |problem: String| InstanceError::BadMesh { mesh, problem };
        let slot = *self
            .meshes
            .get(mesh)
            .ok_or_else(|| bad(format!("no such mesh ({} meshes)", self.meshes.len())))?;
        if tris.len() != slot.primitives as usize {
            return Err(bad(format!(
                "{} triangles given for a mesh of {} (a refit keeps the triangles; rebuild instead)",
                tris.len(),
                slot.primitives
            )));
        }
        crate::mesh::validate_triangles(tris).map_err(|e| bad(e.to_string()))?;
        let (t0, nt) = (slot.tri_base as usize, slot.triangles as usize);
        for t in &mut self.bvh.triangles[t0..t0 + nt] {
            let [a, b, c] = tris[t.prim as usize];
            (t.v0, t.v1, t.v2) = (a.to_array(), b.to_array(), c.to_array());
        }
        let (n0, nn) = (slot.node_base as usize, slot.nodes as usize);
        crate::flat::refit_boxes(&mut self.bvh.nodes, &self.bvh.triangles, n0..n0 + nn);
        self.set_instances(self.instances.clone())
    }

    /// A mesh's SAH cost now over its cost when built: 1 after a build, growing with
    /// refits that move vertices far from where the tree was built for.
    pub fn refit_quality(&self, mesh: usize) -> f64 {
        let Some(s) = self.meshes.get(mesh) else {
            return 1.0;
        };
        let (n0, nn) = (s.node_base as usize, s.nodes as usize);
        let now = sah_cost(&self.bvh.nodes[n0..n0 + nn]);
        if s.built_sah > 0.0 {
            now / s.built_sah
        } else {
            1.0
        }
    }

    /// A new layout in which mesh `mesh`'s tree is built anew over `tris` with `opts` (what
    /// [`REFIT_REBUILD_ADVISED`] advises; the node count may change, so the whole layout is
    /// made again and an upload of it is a new upload, not an update).
    pub fn rebuild_mesh(
        &self,
        mesh: usize,
        tris: &[Triangle],
        opts: &BuildOptions,
    ) -> Result<InstancedBvh, InstanceError> {
        let mut trees: Vec<FlatBvh> = (0..self.meshes.len()).map(|m| self.mesh_bvh(m)).collect();
        let slot = trees.get_mut(mesh).ok_or_else(|| InstanceError::BadMesh {
            mesh,
            problem: format!("no such mesh ({} meshes)", self.meshes.len()),
        })?;
        *slot = FlatBvh::build(tris, opts).map_err(|e| InstanceError::BadMesh {
            mesh,
            problem: e.to_string(),
        })?;
        let mut out = InstancedBvh::new(trees, self.instances.clone())?;
        if self.bvh.wide.is_some() {
            out.build_wide();
        }
        Ok(out)
    }

    /// Converts the layout into the wide one as well ([`FlatBvh::build_wide`]), so that
    /// [`crate::Traversal::Wide`] can walk it; kept up to date by
    /// [`InstancedBvh::set_transforms`], [`InstancedBvh::refit_mesh`] and
    /// [`InstancedBvh::rebuild_mesh`] from then on.
    pub fn build_wide(&mut self) {
        self.bvh.build_wide();
    }

    /// Mesh `mesh`'s tree as a one-mesh BVH.
    pub fn mesh_bvh(&self, mesh: usize) -> FlatBvh {
        let s = &self.meshes[mesh];
        let (n0, nn) = (s.node_base as usize, s.nodes as usize);
        let (t0, nt) = (s.tri_base as usize, s.triangles as usize);
        let nodes: Vec<FlatNode> = self.bvh.nodes[n0..n0 + nn]
            .iter()
            .map(|n| {
                let mut n = *n;
                n.right_or_first -= if n.is_leaf() { s.tri_base } else { s.node_base };
                n
            })
            .collect();
        FlatBvh {
            nodes,
            triangles: self.bvh.triangles[t0..t0 + nt].to_vec(),
            depth: s.depth,
            ..FlatBvh::default()
        }
    }
}

/// [`FlatBvh::check_invariants`] for a two-level layout: the top level has `2n - 1` nodes
/// over `n` instances, each instance in one leaf whose box contains its mesh's root box
/// transformed; each mesh's tree holds within its own node and triangle ranges; boxes
/// contain their children, and the leaves holding a triangle cover it (as in one mesh);
/// every escape link is its tree's.
pub(crate) fn check_two_level(bvh: &FlatBvh) -> Result<(), String> {
    let top = bvh.top_nodes as usize;
    let (n_nodes, n_tris) = (bvh.nodes.len(), bvh.triangles.len());
    if top != 2 * bvh.instances.len() - 1 || top > n_nodes {
        return Err(format!(
            "{top} top-level nodes for {} instances",
            bvh.instances.len()
        ));
    }
    bvh.check_escape_links().map_err(|e| e.to_string())?;
    let mut seen = vec![false; bvh.instances.len()];
    let mut coverage = crate::flat::Coverage::default();
    for inst in &bvh.instances {
        if (inst.root as usize) < top || inst.root as usize >= n_nodes {
            return Err(format!(
                "an instance's root {} is not a mesh node",
                inst.root
            ));
        }
    }
    for (i, n) in bvh.nodes.iter().enumerate() {
        let in_top = i < top;
        let b = n.aabb();
        if n.is_instance_leaf() {
            let k = n.right_or_first as usize;
            if !in_top || k >= seen.len() || seen[k] {
                return Err(format!("node {i}: instance {k} misplaced or repeated"));
            }
            seen[k] = true;
        } else if n.is_leaf() {
            let (f, c) = (n.right_or_first as usize, n.count() as usize);
            if in_top || f + c > n_tris {
                return Err(format!("node {i}: triangle leaf {f}+{c} misplaced"));
            }
            for t in &bvh.triangles[f..f + c] {
                coverage.add(&b, t).map_err(|e| format!("leaf {i}: {e}"))?;
            }
        } else {
            let (l, r) = (i + 1, n.right_or_first as usize);
            let same_level = |c: usize| (c < top) == in_top && c < n_nodes;
            if r <= l || !same_level(l) || !same_level(r) || n.axis() > 2 {
                return Err(format!("node {i}: bad children {l}, {r}"));
            }
            for c in [l, r] {
                if !b.contains(&bvh.nodes[c].aabb()) {
                    return Err(format!("node {i} box does not contain child {c}"));
                }
            }
        }
    }
    if let Some(k) = seen.iter().position(|s| !s) {
        return Err(format!("instance {k} is in no top-level leaf"));
    }
    coverage.finish()?;
    let escapes = bvh.escapes_or_computed();
    let mut expected = escapes.to_vec();
    set_escape_links(&bvh.nodes, &mut expected, 0..n_nodes);
    if let Some(i) = (0..n_nodes).find(|&i| {
        (0..OCTANTS)
            .any(|o| expected[escape_index(i as u32, o)] != escapes[escape_index(i as u32, o)])
    }) {
        return Err(format!("node {i}: an escape link is not its tree's"));
    }
    Ok(())
}
