//! The upload plan every device backend follows: which arrays of a [`FlatBvh`] go to the
//! device, laid out as the kernels read them (buffers or texel textures), checked against
//! the device's limits, and what they cost ([`UploadStats`]).

use std::borrow::Cow;

use bvhtrace_core::{FlatBvh, FlatNode, MaskTables, Traversal, WideBvh};

use crate::error::TraceError;
use crate::plan::{DeviceLimits, check_buffer_in, check_texels};
use crate::storage::{BvhStorage, texel_extent};
use crate::walks::{Layout, check_depth, walk};

/// What to upload for.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UploadOptions {
    /// The traversals the BVH will be traced with: the arrays their walks read are
    /// uploaded ([`crate::walks::WALKS`]), the escape links only when one of them follows
    /// them; a tree deeper than a listed walk's stack is refused
    /// ([`crate::walks::DepthRule::Refuse`]). [`Traversal::Wide`] uploads the wide layout (`FlatBvh::wide`, or the tree
    /// collapsed into it when the BVH has none), in buffers or textures of its own; the
    /// binary layout is uploaded when a binary traversal is listed (or none at all).
    pub traversals: Vec<Traversal>,
    /// Buffers or textures for both layouts; `None` picks the context's
    /// [`DriverTuning::storage`](crate::DriverTuning::storage) (textures on CPU drivers
    /// such as lavapipe, buffers elsewhere) where the backend has textures. The rays of a
    /// trace follow this storage for every traversal.
    pub storage: Option<BvhStorage>,
}

impl UploadOptions {
    /// Upload for one traversal, default storage.
    pub fn for_traversal(traversal: Traversal) -> Self {
        UploadOptions {
            traversals: vec![traversal],
            storage: None,
        }
    }

    /// Upload for every traversal of the binary layout (escape links included; the depth
    /// check applies), default storage. The wide layout is a second copy of the tree: add
    /// [`Traversal::Wide`] ([`UploadOptions::with_traversal`]) to upload it too.
    pub fn all() -> Self {
        UploadOptions {
            traversals: (Traversal::ALL.into_iter())
                .filter(|&t| walk(t).layout == Layout::Binary)
                .collect(),
            storage: None,
        }
    }

    /// Every traversal `bvh` can take: [`UploadOptions::all`] without the full stack for a
    /// tree deeper than it, with [`Traversal::Wide`] when the tree has its wide layout.
    /// What an upload given no options takes.
    pub fn fitting(bvh: &FlatBvh) -> Self {
        let mut opts = UploadOptions::all();
        opts.traversals
            .retain(|&t| check_depth(t, bvh.depth()).is_ok());
        if bvh.wide().is_some() {
            opts = opts.with_traversal(Traversal::Wide);
        }
        opts
    }

    /// The same options with this storage.
    pub fn with_storage(mut self, storage: BvhStorage) -> Self {
        self.storage = Some(storage);
        self
    }

    /// The same options with `traversal` listed too.
    pub fn with_traversal(mut self, traversal: Traversal) -> Self {
        if !self.traversals.contains(&traversal) {
            self.traversals.push(traversal);
        }
        self
    }

    /// True when the wide layout is uploaded.
    pub fn wide(&self) -> bool {
        self.reads(Layout::Wide)
    }

    /// True when the binary layout is uploaded (a binary walk listed, or none at all).
    pub fn binary(&self) -> bool {
        !self.wide() || self.reads(Layout::Binary)
    }

    /// True when the escape links are uploaded.
    pub fn escapes(&self) -> bool {
        self.traversals.iter().any(|&t| walk(t).escapes)
    }

    /// True when a listed walk reads `layout`.
    fn reads(&self, layout: Layout) -> bool {
        self.traversals.iter().any(|&t| walk(t).layout == layout)
    }
}

impl Default for UploadOptions {
    /// [`UploadOptions::all`].
    fn default() -> Self {
        Self::all()
    }
}

/// What an upload holds, and what it cost.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct UploadStats {
    /// Where the tree was put.
    pub storage: BvhStorage,
    /// Bytes of the nodes as uploaded (texture row padding included).
    pub nodes_bytes: u64,
    /// Bytes of the triangles as uploaded.
    pub triangles_bytes: u64,
    /// Bytes of the escape links as uploaded (0 when not uploaded).
    pub escapes_bytes: u64,
    /// Bytes of the instances of a two-level BVH (0 for one mesh).
    pub instances_bytes: u64,
    /// Bytes of the alpha masks (0 for a BVH without them).
    pub masks_bytes: u64,
    /// Wall time to create and fill the device's copies and wait for the device,
    /// milliseconds.
    pub upload_ms: f64,
}

impl UploadStats {
    /// All bytes uploaded.
    pub fn total_bytes(&self) -> u64 {
        self.nodes_bytes
            + self.triangles_bytes
            + self.escapes_bytes
            + self.instances_bytes
            + self.masks_bytes
    }
}

/// Checks a wide tree for the kernels: the one property they rely on beyond the CPU
/// walk's, that the first instance's mesh starts right after the top level
/// (`bvh_instances.wgsl` takes `instances[0].root` for the top level's node count), as
/// `WideBvh::collapse` lays it out.
pub fn check_wide_top_level(w: &WideBvh) -> Result<(), TraceError> {
    match w.instances.first() {
        Some(first) if first.root != w.top_nodes => Err(TraceError::BadBuffer {
            buffer: "wide instances",
            problem: format!(
                "the first instance's mesh starts at node {}, not right after the {} top-level \
                 nodes: collapse the tree with WideBvh::collapse",
                first.root, w.top_nodes
            ),
        }),
        _ => Ok(()),
    }
}

/// One array of an upload: which binding of which layout it fills.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ArrayRole {
    /// The binary nodes (binding 0).
    Nodes,
    /// The binary layout's triangles (binding 1).
    Triangles,
    /// The escape links (binding 2).
    Escapes,
    /// The instances of a two-level tree (binding 4).
    Instances,
    /// The wide nodes (binding 0 of the wide layout).
    WideNodes,
    /// The wide layout's triangles (binding 1).
    WideTriangles,
    /// The instances in the wide top level's order (binding 4).
    WideInstances,
    /// The alpha masks with the binary layout's instance order (binding 5).
    Masks,
    /// The alpha masks with the wide layout's instance order (binding 5).
    WideMasks,
}

impl ArrayRole {
    /// True for the arrays of the wide layout.
    pub fn is_wide(self) -> bool {
        matches!(
            self,
            ArrayRole::WideNodes
                | ArrayRole::WideTriangles
                | ArrayRole::WideInstances
                | ArrayRole::WideMasks
        )
    }

    /// The binding the array fills in its layout's bind group.
    pub fn binding(self) -> u32 {
        match self {
            ArrayRole::Nodes | ArrayRole::WideNodes => 0,
            ArrayRole::Triangles | ArrayRole::WideTriangles => 1,
            ArrayRole::Escapes => 2,
            ArrayRole::Instances | ArrayRole::WideInstances => 4,
            ArrayRole::Masks | ArrayRole::WideMasks => 5,
        }
    }

    /// The name errors and labels give the array: as a buffer, or as a texel texture.
    pub fn name(self, texels: bool) -> &'static str {
        match (self, texels) {
            (ArrayRole::Nodes, false) => "nodes",
            (ArrayRole::Nodes, true) => "node texels",
            (ArrayRole::Triangles, false) => "triangles",
            (ArrayRole::Triangles, true) => "triangle texels",
            (ArrayRole::Escapes, false) => "escapes",
            (ArrayRole::Escapes, true) => "escape texels",
            (ArrayRole::Instances, _) => "instances",
            (ArrayRole::WideNodes, false) => "wide nodes",
            (ArrayRole::WideNodes, true) => "wide node texels",
            (ArrayRole::WideTriangles, false) => "wide triangles",
            (ArrayRole::WideTriangles, true) => "wide triangle texels",
            (ArrayRole::WideInstances, _) => "wide instances",
            (ArrayRole::Masks, _) => "alpha masks",
            (ArrayRole::WideMasks, _) => "wide alpha masks",
        }
    }
}

/// One array as the device holds it: its bytes, laid out as the kernels read them, in a
/// storage buffer or (`texel_bytes` set) a texel texture of [`texel_extent`].
#[derive(Clone, Debug)]
pub struct DeviceArray<'a> {
    /// Which array.
    pub role: ArrayRole,
    /// Its bytes (texels, row-major, for a texture; the last row not yet padded).
    pub bytes: Cow<'a, [u8]>,
    /// Bytes of one texel (16: four `u32`; 4: one) when the array is a texture; `None` for
    /// a storage buffer.
    pub texel_bytes: Option<u64>,
    /// Which page of its array this is (0 for an array not split: [`crate::pages`]).
    pub page: u8,
}

impl<'a> DeviceArray<'a> {
    /// The name errors and labels give it.
    pub fn name(&self) -> &'static str {
        self.role.name(self.texel_bytes.is_some())
    }

    /// The binding it fills in its layout's bind group: its role's, or for a further page
    /// of a split array, [`crate::pages::PAGE_BINDING_STRIDE`] on per page.
    pub fn binding(&self) -> u32 {
        self.role.binding() + crate::pages::PAGE_BINDING_STRIDE * u32::from(self.page)
    }

    /// This array (a buffer) cut into pages of `bytes` bytes, the last one shorter.
    pub(crate) fn pages(self, bytes: usize) -> Vec<DeviceArray<'a>> {
        let (role, texel_bytes) = (self.role, self.texel_bytes);
        let piece = |page: usize, bytes: Cow<'a, [u8]>| DeviceArray {
            role,
            bytes,
            texel_bytes,
            page: page as u8,
        };
        match self.bytes {
            Cow::Borrowed(all) => (all.chunks(bytes.max(1)).enumerate())
                .map(|(i, c)| piece(i, Cow::Borrowed(c)))
                .collect(),
            Cow::Owned(all) => (all.chunks(bytes.max(1)).enumerate())
                .map(|(i, c)| piece(i, Cow::Owned(c.to_vec())))
                .collect(),
        }
    }

    /// Texels of a texture's data (0 for a buffer).
    pub fn texels(&self) -> u64 {
        self.texel_bytes
            .map_or(0, |b| self.bytes.len() as u64 / b.max(1))
    }

    /// Bytes the device holds: the data, or the whole texture with its last row padded.
    pub fn device_bytes(&self) -> u64 {
        match self.texel_bytes {
            None => self.bytes.len() as u64,
            Some(b) => {
                let (w, h) = texel_extent(self.texels());
                u64::from(w) * u64::from(h) * b
            }
        }
    }

    /// Checks the array against the device's limits ([`TraceError::TooLarge`] names it).
    pub fn check(&self, limits: &DeviceLimits) -> Result<(), TraceError> {
        match self.texel_bytes {
            None => check_buffer_in(
                limits,
                self.name(),
                self.bytes.len() as u64,
                Some(BvhStorage::Buffers),
            ),
            Some(b) => check_texels(limits, self.name(), self.texels(), b),
        }
    }
}

/// Texels of one wide node in `bvh_textures_wide.wgsl` (`BVH_WIDE_NODE_TEXELS`).
pub const WIDE_NODE_TEXELS: u64 = (std::mem::size_of::<bvhtrace_core::WideNode>() / 16) as u64;

/// The node texels of `bvh_textures.wgsl`: `(min.xyz, max.x)`, `(max.yz, right, meta)`.
fn node_texels(nodes: &[FlatNode]) -> Vec<u8> {
    let mut v: Vec<u32> = Vec::with_capacity(nodes.len() * 8);
    for n in nodes {
        v.extend_from_slice(&[
            n.min[0].to_bits(),
            n.min[1].to_bits(),
            n.min[2].to_bits(),
            n.max[0].to_bits(),
            n.max[1].to_bits(),
            n.max[2].to_bits(),
            n.right_or_first,
            n.meta,
        ]);
    }
    bytemuck::cast_slice(&v).to_vec()
}

fn array<'a>(role: ArrayRole, bytes: Cow<'a, [u8]>, texel_bytes: Option<u64>) -> DeviceArray<'a> {
    DeviceArray {
        role,
        bytes,
        texel_bytes,
        page: 0,
    }
}

/// The binary layout's arrays of `bvh` in `storage`: nodes (`nodes` of them: all, or the
/// top level's for an update), triangles when `triangles`, escape links (`links` of them)
/// when `links` is set, instances of a two-level tree.
pub(crate) fn binary_arrays<'a>(
    bvh: &'a FlatBvh,
    storage: BvhStorage,
    nodes: usize,
    triangles: bool,
    links: Option<usize>,
) -> Vec<DeviceArray<'a>> {
    let textures = storage == BvhStorage::Textures;
    let texel = |b: u64| textures.then_some(b);
    let mut out = vec![array(
        ArrayRole::Nodes,
        if textures {
            Cow::Owned(node_texels(&bvh.nodes()[..nodes]))
        } else {
            Cow::Borrowed(bytemuck::cast_slice(&bvh.nodes()[..nodes]))
        },
        texel(16),
    )];
    if triangles {
        out.push(array(
            ArrayRole::Triangles,
            Cow::Borrowed(bytemuck::cast_slice(bvh.triangles())),
            texel(16),
        ));
    }
    if let Some(n) = links {
        out.push(array(
            ArrayRole::Escapes,
            Cow::Borrowed(bytemuck::cast_slice(&bvh.escapes()[..n])),
            texel(4),
        ));
    }
    if bvh.is_instanced() {
        out.push(array(
            ArrayRole::Instances,
            Cow::Borrowed(bytemuck::cast_slice(bvh.instances())),
            None,
        ));
    }
    if let Some(m) = bvh.masks() {
        out.push(masks_array(ArrayRole::Masks, m.words(&m.instance_bases)));
    }
    out
}

/// The alpha masks' words ([`MaskTables::words`]) as a buffer in `role`.
fn masks_array(role: ArrayRole, words: Vec<u32>) -> DeviceArray<'static> {
    array(
        role,
        Cow::Owned(bytemuck::cast_slice(&words).to_vec()),
        None,
    )
}

/// The wide layout's arrays in `storage`: nodes, triangles, the instances of a two-level
/// tree, and `masks` with the wide instance order (those two always buffers).
pub(crate) fn wide_arrays<'a>(
    w: &'a WideBvh,
    storage: BvhStorage,
    masks: Option<&MaskTables>,
) -> Vec<DeviceArray<'a>> {
    let texel = (storage == BvhStorage::Textures).then_some(16);
    let mut out = vec![
        array(
            ArrayRole::WideNodes,
            Cow::Borrowed(bytemuck::cast_slice(&w.nodes)),
            texel,
        ),
        array(
            ArrayRole::WideTriangles,
            Cow::Borrowed(bytemuck::cast_slice(&w.triangles)),
            texel,
        ),
    ];
    if w.is_instanced() {
        out.push(array(
            ArrayRole::WideInstances,
            Cow::Borrowed(bytemuck::cast_slice(&w.instances)),
            None,
        ));
    }
    if let Some(m) = masks {
        let bases = m.bases_in_order(&w.instance_order);
        out.push(masks_array(ArrayRole::WideMasks, m.words(&bases)));
    }
    out
}

/// [`UploadStats`] of these arrays (without the time).
pub(crate) fn stats_of(storage: BvhStorage, arrays: &[DeviceArray<'_>]) -> UploadStats {
    let mut s = UploadStats {
        storage,
        ..UploadStats::default()
    };
    for a in arrays {
        let b = a.device_bytes();
        match a.role {
            ArrayRole::Nodes | ArrayRole::WideNodes => s.nodes_bytes += b,
            ArrayRole::Triangles | ArrayRole::WideTriangles => s.triangles_bytes += b,
            ArrayRole::Escapes => s.escapes_bytes += b,
            ArrayRole::Instances | ArrayRole::WideInstances => s.instances_bytes += b,
            ArrayRole::Masks | ArrayRole::WideMasks => s.masks_bytes += b,
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::TEXEL_ROW;

    /// A texel texture fits while its rows do: the wide layout's five texels a node reach
    /// the limit at a fifth of the nodes the texels allow, and the error names the texture
    /// and the way out.
    #[test]
    fn texel_textures_are_checked_row_by_row() {
        let limits = |max| DeviceLimits {
            max_storage_buffer_binding_size: 1 << 30,
            max_buffer_size: 1 << 30,
            max_compute_workgroups_per_dimension: 65_535,
            min_storage_buffer_offset_alignment: 256,
            max_texture_dimension_2d: max,
            max_storage_buffers_per_shader_stage: 8,
        };
        let row = u64::from(TEXEL_ROW);
        let l = limits(TEXEL_ROW);
        let most = row * row;
        assert!(check_texels(&l, "wide node texels", most, 16).is_ok());
        let nodes = most / WIDE_NODE_TEXELS + 1;
        match check_texels(&l, "wide node texels", WIDE_NODE_TEXELS * nodes, 16) {
            Err(
                e @ TraceError::TooLarge {
                    buffer,
                    bytes,
                    limit,
                    ..
                },
            ) => {
                assert_eq!(buffer, "wide node texels");
                assert_eq!(bytes, nodes * 80);
                assert_eq!(limit, most * 16);
                let msg = e.to_string();
                assert!(
                    msg.contains("max_texture_dimension_2d") && msg.contains("BvhStorage::Buffers"),
                    "{msg}"
                );
            }
            other => panic!("{other:?}"),
        }
        // Rows narrower than `TEXEL_ROW`: no texture fits, however small.
        assert!(matches!(
            check_texels(&limits(TEXEL_ROW / 2), "wide node texels", 5, 16),
            Err(TraceError::TooLarge { .. })
        ));
    }

    /// A texture taller than a row pads its last row, and the stats count the padding.
    #[test]
    fn device_bytes_count_the_row_padding() {
        let row = u64::from(TEXEL_ROW);
        let a = array(
            ArrayRole::Escapes,
            Cow::Owned(vec![0u8; 4 * (row as usize + 1)]),
            Some(4),
        );
        assert_eq!(a.device_bytes(), 2 * row * 4);
        assert_eq!(a.name(), "escape texels");
    }
}
