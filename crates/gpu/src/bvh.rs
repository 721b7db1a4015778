//! Uploading a [`FlatBvh`] to the device.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use bvhtrace_core::flat::{ESCAPE_BLOCK, OCTANTS};
use bvhtrace_core::{FlatBvh, FlatNode, Traversal, WideBvh};
use bvhtrace_kernels::{
    BvhStorage, DeviceLimits, TEXEL_ROW, UploadStats, check_buffer_size, check_depth,
    check_wide_top_level, texel_rows, wide_stack_may_overflow,
};
use wgpu::util::DeviceExt;

use crate::GpuError;
use crate::context::GpuContext;
use crate::trace::Scratch;

/// What to upload for.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UploadOptions {
    /// The traversals the BVH will be traced with. The escape links are uploaded only when
    /// one of them needs them ([`Traversal::needs_escapes`]); a tree deeper than
    /// [`FULL_STACK_SIZE`](bvhtrace_kernels::FULL_STACK_SIZE) is refused when [`Traversal::FullStack`] is listed.
    /// [`Traversal::Wide`] uploads the wide layout (`FlatBvh::wide`, or the tree collapsed
    /// into it when the BVH has none), in buffers or textures of its own; the binary layout
    /// is uploaded when a binary traversal is listed (or none at all).
    pub traversals: Vec<Traversal>,
    /// Buffers or textures for both layouts; `None` picks the context's
    /// [`DriverTuning::storage`](bvhtrace_kernels::DriverTuning::storage) (textures on CPU
    /// drivers such as lavapipe, buffers elsewhere). The rays of [`GpuBvh::trace`] follow
    /// this storage for every traversal.
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
            traversals: vec![
                Traversal::FullStack,
                Traversal::Stackless,
                Traversal::ShortStack(bvhtrace_core::traverse::DEFAULT_SHORT_STACK),
            ],
            storage: None,
        }
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
}

impl Default for UploadOptions {
    /// [`UploadOptions::all`].
    fn default() -> Self {
        Self::all()
    }
}

/// The device resources of one upload.
enum Resources {
    Buffers {
        nodes: wgpu::Buffer,
        triangles: wgpu::Buffer,
        escapes: Option<wgpu::Buffer>,
    },
    Textures {
        nodes: wgpu::Texture,
        triangles: wgpu::Texture,
        escapes: Option<wgpu::Texture>,
    },
}

/// Where the wide layout is missing, and the fix ([`GpuError::WideLayoutMissing`]).
const WIDE_NOT_UPLOADED: &str =
    "this upload left out: list Traversal::Wide in UploadOptions::traversals";

/// The wide layout's nodes and triangles on the device, in the upload's storage.
enum WideResources {
    /// `array<BvhWideNode>` and `array<BvhTriangle>` (`bvh_buffers_wide.wgsl`).
    Buffers {
        nodes: wgpu::Buffer,
        triangles: wgpu::Buffer,
    },
    /// Five texels per node, three per triangle (`bvh_textures_wide.wgsl`).
    Textures {
        nodes: wgpu::Texture,
        triangles: wgpu::Texture,
    },
}

/// Texels of one wide node in `bvh_textures_wide.wgsl` (`BVH_WIDE_NODE_TEXELS`).
const WIDE_NODE_TEXELS: u64 = (std::mem::size_of::<bvhtrace_core::WideNode>() / 16) as u64;

/// The wide layout on the device ([`Traversal::Wide`]): in the upload's storage, with its
/// own bind group.
struct WideUpload {
    resources: WideResources,
    /// The instances in the wide top level's order, for a two-level BVH (a buffer with
    /// either storage, as the binary layout's).
    instances: Option<wgpu::Buffer>,
    group: wgpu::BindGroup,
    /// Bytes of the nodes, triangles and instances (texture row padding included).
    bytes: (u64, u64, u64),
}

impl WideUpload {
    /// Checks `w` in `storage` against the device's limits, and the one property of the
    /// layout the kernel relies on beyond the Rust walk's: the first instance's mesh starts
    /// right after the top level (`bvh_instances.wgsl` finds the top level's end there).
    fn check(ctx: &GpuContext, w: &WideBvh, storage: BvhStorage) -> Result<(), GpuError> {
        let l = ctx.limits();
        match storage {
            BvhStorage::Buffers => {
                check_buffer_size(
                    l,
                    "wide nodes",
                    std::mem::size_of_val(w.nodes.as_slice()) as u64,
                )?;
                check_buffer_size(
                    l,
                    "wide triangles",
                    std::mem::size_of_val(w.triangles.as_slice()) as u64,
                )?;
            }
            BvhStorage::Textures => {
                let nodes = WIDE_NODE_TEXELS * w.nodes.len() as u64;
                check_texels(l, "wide node texels", nodes, 16)?;
                check_texels(l, "wide triangle texels", 3 * w.triangles.len() as u64, 16)?;
            }
        }
        check_buffer_size(
            l,
            "wide instances",
            std::mem::size_of_val(w.instances.as_slice()) as u64,
        )?;
        check_wide_top_level(w)
    }

    /// Creates and fills the buffers or textures and the bind group.
    fn new(ctx: &GpuContext, w: &WideBvh, storage: BvhStorage) -> WideUpload {
        let device = ctx.device();
        let make = |label: &str, contents: &[u8]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            })
        };
        let instances = w.is_instanced().then(|| {
            make(
                "bvhtrace wide instances",
                bytemuck::cast_slice(&w.instances),
            )
        });
        let size = |b: &wgpu::Buffer| b.size();
        let instances_bytes = instances.as_ref().map_or(0, size);
        // The layouts are the binary layout's: binding types say nothing of what the
        // elements or texels hold.
        let layout = ctx.bvh_layout(storage, false, w.is_instanced());
        let group = |entries: &[wgpu::BindGroupEntry<'_>]| {
            let mut entries = entries.to_vec();
            entries.extend(instances.as_ref().map(|b| buffer_entry(4, b)));
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("bvhtrace bvh (wide)"),
                layout,
                entries: &entries,
            })
        };
        let (resources, group, bytes) = match storage {
            BvhStorage::Buffers => {
                let nodes = make("bvhtrace wide nodes", bytemuck::cast_slice(&w.nodes));
                let triangles = make(
                    "bvhtrace wide triangles",
                    bytemuck::cast_slice(&w.triangles),
                );
                let group = group(&[buffer_entry(0, &nodes), buffer_entry(1, &triangles)]);
                let bytes = (size(&nodes), size(&triangles), instances_bytes);
                (WideResources::Buffers { nodes, triangles }, group, bytes)
            }
            BvhStorage::Textures => {
                let rgba = wgpu::TextureFormat::Rgba32Uint;
                // `WideNode`'s bytes as they are: texel `k` of a node is its bytes
                // `16k .. 16k + 16`.
                let (nodes, nodes_bytes) = texel_texture(
                    ctx,
                    "bvhtrace wide node texels",
                    rgba,
                    4,
                    bytemuck::cast_slice(&w.nodes).to_vec(),
                );
                let (triangles, triangles_bytes) = texel_texture(
                    ctx,
                    "bvhtrace wide triangle texels",
                    rgba,
                    4,
                    bytemuck::cast_slice(&w.triangles).to_vec(),
                );
                let nv = nodes.create_view(&Default::default());
                let tv = triangles.create_view(&Default::default());
                let group = group(&[view_entry(0, &nv), view_entry(1, &tv)]);
                let bytes = (nodes_bytes, triangles_bytes, instances_bytes);
                (WideResources::Textures { nodes, triangles }, group, bytes)
            }
        };
        WideUpload {
            resources,
            instances,
            group,
            bytes,
        }
    }

    /// Writes `w` over the buffers or textures when it has their sizes; false (nothing
    /// written) when not.
    fn write(&self, ctx: &GpuContext, w: &WideBvh) -> bool {
        let queue = ctx.queue();
        let fits = |b: &wgpu::Buffer, bytes: &[u8]| b.size() == bytes.len() as u64;
        let (nodes, tris, insts): (&[u8], &[u8], &[u8]) = (
            bytemuck::cast_slice(&w.nodes),
            bytemuck::cast_slice(&w.triangles),
            bytemuck::cast_slice(&w.instances),
        );
        let instances_fit = match &self.instances {
            Some(b) => fits(b, insts),
            None => insts.is_empty(),
        };
        // A texture fits when it has the extent `texel_texture` gives the new texels.
        let texels_fit = |t: &wgpu::Texture, bytes: &[u8]| {
            texel_extent(bytes.len() as u64 / 16) == (t.width(), t.height())
        };
        let layout_fits = match &self.resources {
            WideResources::Buffers {
                nodes: n,
                triangles,
            } => fits(n, nodes) && fits(triangles, tris),
            WideResources::Textures {
                nodes: n,
                triangles,
            } => texels_fit(n, nodes) && texels_fit(triangles, tris),
        };
        if !(layout_fits && instances_fit) {
            return false;
        }
        match &self.resources {
            WideResources::Buffers {
                nodes: n,
                triangles,
            } => {
                queue.write_buffer(n, 0, nodes);
                queue.write_buffer(triangles, 0, tris);
            }
            WideResources::Textures {
                nodes: n,
                triangles,
            } => {
                write_texels(ctx, n, 4, bytemuck::cast_slice(&w.nodes).to_vec());
                write_texels(
                    ctx,
                    triangles,
                    4,
                    bytemuck::cast_slice(&w.triangles).to_vec(),
                );
            }
        }
        if let Some(b) = &self.instances {
            queue.write_buffer(b, 0, insts);
        }
        true
    }
}

/// The tree [`GpuBvh::trace`] finishes incomplete rays on, with the wide layout uploaded
/// (`wide`): kept when the context's tuning sets a trip budget, or when the wide tree is
/// deep enough for a ray to overflow the wide walk's stack (on any device).
fn host_copy(ctx: &GpuContext, bvh: &FlatBvh, wide: Option<Arc<WideBvh>>) -> Option<Arc<FlatBvh>> {
    let deep = wide
        .as_ref()
        .is_some_and(|w| wide_stack_may_overflow(w.depth));
    (ctx.tuning().finishes_on_cpu() || deep).then(|| {
        let mut copy = bvh.clone();
        copy.wide = wide.or_else(|| bvh.wide.clone());
        Arc::new(copy)
    })
}

/// The wide layout of `bvh`: its own when it has one, else `bvh` collapsed.
fn wide_of(bvh: &FlatBvh) -> Arc<WideBvh> {
    bvh.wide
        .clone()
        .unwrap_or_else(|| Arc::new(WideBvh::collapse(bvh)))
}

/// What [`GpuBvh::update`] writes again.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Update {
    /// Every node, triangle and instance (after a refit: boxes and corners moved).
    Everything,
    /// The top level of a two-level BVH and its instances (after new transforms). An
    /// uploaded wide layout is collapsed again and written whole either way: its meshes'
    /// places follow the top level's order.
    TopLevel,
}

/// The BVH bind group of one upload, for group 0 of the kernels or any group of your own
/// shader ([`GpuBvh::bind_group_for`] of a [`GpuBvh::wgsl_library`]), with the layout
/// [`BvhBindGroup::layout`] names.
#[derive(Clone, Copy, Debug)]
pub struct BvhBindGroup<'a> {
    group: &'a wgpu::BindGroup,
    layout: &'a wgpu::BindGroupLayout,
}

impl<'a> BvhBindGroup<'a> {
    /// The bind group.
    pub fn group(&self) -> &'a wgpu::BindGroup {
        self.group
    }

    /// Its layout, for your pipeline layout.
    pub fn layout(&self) -> &'a wgpu::BindGroupLayout {
        self.layout
    }
}

/// A BVH on the device, ready to trace (see [`GpuBvh::trace`] and [`GpuBvh::record`]).
/// `Send + Sync`: trace it from several threads at once.
pub struct GpuBvh {
    pub(crate) ctx: GpuContext,
    storage: BvhStorage,
    /// The binary layout, unless only [`Traversal::Wide`] was listed.
    resources: Option<Resources>,
    /// The instances of a two-level BVH (binary layout).
    instances: Option<wgpu::Buffer>,
    /// A two-level BVH.
    instanced: bool,
    top_nodes: u32,
    instance_count: usize,
    /// The BVH group for the full-stack kernels (nodes, triangles).
    group_plain: Option<wgpu::BindGroup>,
    /// The BVH group for the escape-link kernels, when the escape links were uploaded.
    group_escapes: Option<wgpu::BindGroup>,
    /// The wide layout, when [`Traversal::Wide`] was listed.
    wide: Option<WideUpload>,
    depth: u32,
    node_count: usize,
    triangle_count: usize,
    stats: UploadStats,
    /// A host copy of the tree when the context's tuning bounds the kernels' loop trips
    /// ([`DriverTuning::finishes_on_cpu`](bvhtrace_kernels::DriverTuning::finishes_on_cpu)):
    /// [`GpuBvh::trace`] finishes the rays that spend the budget on it with the CPU walk,
    /// which gives the answer the kernel would have given.
    pub(crate) host_copy: Option<Arc<FlatBvh>>,
    pub(crate) scratch: Mutex<Option<Scratch>>,
    pub(crate) batch_groups: Mutex<crate::trace::BatchGroups>,
    /// [`bvhtrace_kernels::mesh_fingerprint`] of the uploaded tree.
    pub(crate) mesh_fingerprint: u64,
    /// The kernels traced so far, each once ([`Tracer::kernels_used`]).
    pub(crate) used: Mutex<Vec<bvhtrace_kernels::KernelKey>>,
    /// The instances' table every output carries, for a two-level BVH.
    pub(crate) instance_table: Option<Arc<bvhtrace_core::InstanceTable>>,
}

impl std::fmt::Debug for GpuBvh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuBvh")
            .field("storage", &self.storage)
            .field("nodes", &self.node_count)
            .field("triangles", &self.triangle_count)
            .field("depth", &self.depth)
            .field("escapes", &self.group_escapes.is_some())
            .field("binary", &self.resources.is_some())
            .field("wide", &self.wide.is_some())
            .field("stats", &self.stats)
            .finish()
    }
}

/// A `width` x `rows` storage texture, filled by copies and copied from: the BVH's texel
/// textures and [`crate::GpuBvh::trace`]'s ray texture (read-only in the kernels), and its
/// hit texture (write-only).
pub(crate) fn storage_texture(
    ctx: &GpuContext,
    label: &str,
    format: wgpu::TextureFormat,
    width: u32,
    rows: u32,
) -> wgpu::Texture {
    ctx.device().create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height: rows,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::STORAGE_BINDING
            | wgpu::TextureUsages::COPY_DST
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}

/// Checks one texel texture of `texels` texels against the device's limits: its rows are
/// [`TEXEL_ROW`] wide, and it has [`texel_rows`] of them.
fn check_texels(
    limits: &DeviceLimits,
    what: &'static str,
    texels: u64,
    texel_bytes: u64,
) -> Result<(), GpuError> {
    let max = u64::from(limits.max_texture_dimension_2d);
    if u64::from(TEXEL_ROW) > max || texel_rows(texels) > max {
        return Err(GpuError::TooLarge {
            buffer: what,
            bytes: texels * texel_bytes,
            limit: u64::from(TEXEL_ROW).min(max) * max * texel_bytes,
            limit_name: "max_texture_dimension_2d (squared, in bytes; use BvhStorage::Buffers)",
        });
    }
    Ok(())
}

/// Uploads `data` (`channels` u32 per texel) as a texture of [`TEXEL_ROW`]-texel rows,
/// the last row zero-padded. Returns the texture and the bytes uploaded.
fn texel_texture(
    ctx: &GpuContext,
    label: &str,
    format: wgpu::TextureFormat,
    channels: usize,
    data: Vec<u32>,
) -> (wgpu::Texture, u64) {
    let (width, rows) = texel_extent((data.len() / channels) as u64);
    let texture = storage_texture(ctx, label, format, width, rows);
    let bytes = write_texels(ctx, &texture, channels, data);
    (texture, bytes)
}

/// The `(width, rows)` of [`texel_texture`]'s texture for `texels` texels. One row is only
/// as wide as its texels (texel `t` is still at `(t, 0)`): no padding the kernel never
/// reads. Taller textures are [`TEXEL_ROW`] wide and pad their last row.
fn texel_extent(texels: u64) -> (u32, u32) {
    let rows = texel_rows(texels) as u32;
    if rows == 1 {
        ((texels as u32).max(1), 1)
    } else {
        (TEXEL_ROW, rows)
    }
}

/// Writes `data` over the whole of `texture` (as [`texel_texture`] laid it out). Returns
/// the bytes written.
fn write_texels(
    ctx: &GpuContext,
    texture: &wgpu::Texture,
    channels: usize,
    mut data: Vec<u32>,
) -> u64 {
    let (width, rows) = (texture.width(), texture.height());
    data.resize(width as usize * rows as usize * channels, 0);
    ctx.queue().write_texture(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        bytemuck::cast_slice(&data),
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(width * 4 * channels as u32),
            rows_per_image: Some(rows),
        },
        texture.size(),
    );
    (data.len() * 4) as u64
}

/// The node texels of `bvh_textures.wgsl`: `(min.xyz, max.x)`, `(max.yz, right, meta)`.
fn node_texels(nodes: &[FlatNode]) -> Vec<u32> {
    let mut v = Vec::with_capacity(nodes.len() * 8);
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
    v
}

fn buffer_entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

fn view_entry(binding: u32, view: &wgpu::TextureView) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: wgpu::BindingResource::TextureView(view),
    }
}

impl GpuBvh {
    /// Uploads `bvh`'s nodes and triangles, and its escape links when one of
    /// `opts.traversals` needs them (built then if they are not yet, before the upload's
    /// clock starts: [`FlatBvh::escapes`]), as buffers or textures (`opts.storage`); with
    /// [`Traversal::Wide`] listed, its wide layout too (`bvh.wide`, or `bvh` collapsed into
    /// it), in the same storage, and without a binary traversal listed only that. Everything is
    /// checked against the device's limits first ([`GpuError::TooLarge`] names the
    /// resource, its size and the limit), and a tree deeper than [`FULL_STACK_SIZE`](bvhtrace_kernels::FULL_STACK_SIZE) is
    /// refused ([`GpuError::TooDeep`]) when the full-stack traversal is listed. The
    /// [`UploadStats`] are those of both layouts together.
    pub fn upload(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        opts: &UploadOptions,
    ) -> Result<GpuBvh, GpuError> {
        if bvh.nodes.is_empty() || bvh.triangles.is_empty() {
            return Err(GpuError::EmptyBvh);
        }
        for &traversal in &opts.traversals {
            check_depth(traversal, bvh.depth)?;
        }
        let storage = opts.storage.unwrap_or(ctx.tuning().storage);
        let with_wide = opts.traversals.iter().any(|t| t.is_wide());
        let binary = !with_wide || opts.traversals.iter().any(|t| !t.is_wide());
        let with_escapes = opts.traversals.iter().any(|t| t.needs_escapes());
        if with_escapes {
            bvh.check_escape_links()?;
        }
        let wide = with_wide.then(|| wide_of(bvh));
        if let Some(w) = &wide {
            WideUpload::check(ctx, w, storage)?;
        }
        let (nb, eb, tb) = bvh.byte_sizes();
        let (n_nodes, n_tris) = (bvh.nodes.len() as u64, bvh.triangles.len() as u64);
        match storage {
            _ if !binary => {}
            BvhStorage::Buffers => {
                let l = ctx.limits();
                check_buffer_size(l, "nodes", nb as u64)?;
                check_buffer_size(l, "triangles", tb as u64)?;
                if with_escapes {
                    check_buffer_size(l, "escapes", eb as u64)?;
                }
            }
            BvhStorage::Textures => {
                let l = ctx.limits();
                check_texels(l, "node texels", 2 * n_nodes, 16)?;
                check_texels(l, "triangle texels", 3 * n_tris, 16)?;
                if with_escapes {
                    check_texels(l, "escape texels", eb as u64 / 4, 4)?;
                }
            }
        }

        let instanced = bvh.is_instanced();
        if instanced && binary {
            check_buffer_size(
                ctx.limits(),
                "instances",
                std::mem::size_of_val(bvh.instances.as_slice()) as u64,
            )?;
        }
        // Only the walks that read the links build them (once, kept in `bvh`).
        let escapes: &[u32] = if with_escapes && binary {
            bvh.escapes()
        } else {
            &[]
        };
        let start = Instant::now();
        let device = ctx.device();
        let layout_plain = ctx.bvh_layout(storage, false, instanced);
        let layout_escapes = ctx.bvh_layout(storage, true, instanced);
        let instances = (instanced && binary).then(|| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("bvhtrace instances"),
                contents: bytemuck::cast_slice(&bvh.instances),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            })
        });
        let instances_bytes = if binary {
            std::mem::size_of_val(bvh.instances.as_slice()) as u64
        } else {
            0
        };
        let group = |label: &str, layout, entries: &[wgpu::BindGroupEntry<'_>]| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(label),
                layout,
                entries,
            })
        };
        let (binary_upload, wide_upload) = ctx.scoped("uploading the BVH", || {
            let wide_upload = wide.as_deref().map(|w| WideUpload::new(ctx, w, storage));
            let binary_upload = binary.then(|| match storage {
                BvhStorage::Buffers => {
                    let make = |label: &str, contents: &[u8]| {
                        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                            label: Some(label),
                            contents,
                            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                        })
                    };
                    let nodes = make("bvhtrace nodes", bytemuck::cast_slice(&bvh.nodes));
                    let triangles =
                        make("bvhtrace triangles", bytemuck::cast_slice(&bvh.triangles));
                    let escapes = with_escapes
                        .then(|| make("bvhtrace escapes", bytemuck::cast_slice(escapes)));
                    let mut plain_entries =
                        vec![buffer_entry(0, &nodes), buffer_entry(1, &triangles)];
                    plain_entries.extend(instances.as_ref().map(|b| buffer_entry(4, b)));
                    let plain = group("bvhtrace bvh", layout_plain, &plain_entries);
                    let with = escapes.as_ref().map(|p| {
                        let mut entries = plain_entries.clone();
                        entries.push(buffer_entry(2, p));
                        group("bvhtrace bvh+escapes", layout_escapes, &entries)
                    });
                    let stats = UploadStats {
                        storage,
                        nodes_bytes: nb as u64,
                        triangles_bytes: tb as u64,
                        escapes_bytes: if with_escapes { eb as u64 } else { 0 },
                        instances_bytes,
                        upload_ms: 0.0,
                    };
                    (
                        Resources::Buffers {
                            nodes,
                            triangles,
                            escapes,
                        },
                        plain,
                        with,
                        stats,
                    )
                }
                BvhStorage::Textures => {
                    let rgba = wgpu::TextureFormat::Rgba32Uint;
                    let (nodes, nodes_bytes) = texel_texture(
                        ctx,
                        "bvhtrace node texels",
                        rgba,
                        4,
                        node_texels(&bvh.nodes),
                    );
                    let (triangles, triangles_bytes) = texel_texture(
                        ctx,
                        "bvhtrace triangle texels",
                        rgba,
                        4,
                        bytemuck::cast_slice(&bvh.triangles).to_vec(),
                    );
                    let escapes = with_escapes.then(|| {
                        texel_texture(
                            ctx,
                            "bvhtrace escape texels",
                            wgpu::TextureFormat::R32Uint,
                            1,
                            escapes.to_vec(),
                        )
                    });
                    let nv = nodes.create_view(&Default::default());
                    let tv = triangles.create_view(&Default::default());
                    let mut plain_entries = vec![view_entry(0, &nv), view_entry(1, &tv)];
                    plain_entries.extend(instances.as_ref().map(|b| buffer_entry(4, b)));
                    let plain = group("bvhtrace bvh", layout_plain, &plain_entries);
                    let with = escapes.as_ref().map(|(p, _)| {
                        let pv = p.create_view(&Default::default());
                        let mut entries = plain_entries.clone();
                        entries.push(view_entry(2, &pv));
                        group("bvhtrace bvh+escapes", layout_escapes, &entries)
                    });
                    let stats = UploadStats {
                        storage,
                        nodes_bytes,
                        triangles_bytes,
                        escapes_bytes: escapes.as_ref().map_or(0, |p| p.1),
                        instances_bytes,
                        upload_ms: 0.0,
                    };
                    (
                        Resources::Textures {
                            nodes,
                            triangles,
                            escapes: escapes.map(|p| p.0),
                        },
                        plain,
                        with,
                        stats,
                    )
                }
            });
            (binary_upload, wide_upload)
        })?;
        // Make the upload complete before timing stops.
        ctx.queue().submit([]);
        device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::device("uploading the BVH", e))?;
        let (resources, group_plain, group_escapes, stats) = match binary_upload {
            Some((r, plain, escapes, stats)) => (Some(r), Some(plain), escapes, stats),
            None => (
                None,
                None,
                None,
                UploadStats {
                    storage,
                    ..UploadStats::default()
                },
            ),
        };
        let (wn, wt, wi) = wide_upload.as_ref().map_or((0, 0, 0), |w| w.bytes);
        let stats = UploadStats {
            nodes_bytes: stats.nodes_bytes + wn,
            triangles_bytes: stats.triangles_bytes + wt,
            instances_bytes: stats.instances_bytes + wi,
            upload_ms: start.elapsed().as_secs_f64() * 1e3,
            ..stats
        };
        Ok(GpuBvh {
            ctx: ctx.clone(),
            storage,
            resources,
            instances,
            instanced,
            top_nodes: bvh.top_nodes,
            instance_count: bvh.instances.len(),
            group_plain,
            group_escapes,
            wide: wide_upload,
            depth: bvh.depth,
            node_count: bvh.nodes.len(),
            triangle_count: bvh.triangles.len(),
            stats,
            host_copy: host_copy(ctx, bvh, wide),
            scratch: Mutex::new(None),
            batch_groups: Mutex::new(Default::default()),
            mesh_fingerprint: bvhtrace_kernels::mesh_fingerprint(bvh),
            used: Mutex::new(Vec::new()),
            instance_table: bvhtrace_core::InstanceTable::of(bvh),
        })
    }

    /// Checks that this upload can run `traversal`.
    pub(crate) fn supports_traversal(&self, traversal: Traversal) -> Result<(), GpuError> {
        if traversal.is_wide() {
            return match self.wide {
                Some(_) => Ok(()),
                None => Err(GpuError::WideLayoutMissing {
                    missing: WIDE_NOT_UPLOADED,
                }),
            };
        }
        if self.resources.is_none() {
            return Err(GpuError::TraversalNotUploaded { traversal });
        }
        if traversal.needs_escapes() && self.group_escapes.is_none() {
            return Err(GpuError::EscapesNotUploaded { traversal });
        }
        check_depth(traversal, self.depth)
    }

    /// True when the wide layout was uploaded ([`Traversal::Wide`] listed).
    pub fn has_wide(&self) -> bool {
        self.wide.is_some()
    }

    /// The context this BVH lives in.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// Where both layouts live, buffers or textures; [`GpuBvh::trace`] puts the rays in
    /// textures when this is textures.
    pub fn storage(&self) -> BvhStorage {
        self.storage
    }

    /// What the upload cost.
    pub fn stats(&self) -> &UploadStats {
        &self.stats
    }

    /// The binary tree's depth (edges on its longest root-to-leaf path).
    pub fn depth(&self) -> u32 {
        self.depth
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.node_count
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangle_count
    }

    /// True when the escape links were uploaded.
    pub fn has_escapes(&self) -> bool {
        self.group_escapes.is_some()
    }

    /// The BVH bind group that `traversal`'s kernels read (nodes and triangles, the
    /// escape links for the walks that follow them, the instances for two levels; for
    /// [`Traversal::Wide`] the wide layout's), with its layout. For your own shader use
    /// [`GpuBvh::bind_group_for`], which checks the library against the upload.
    pub fn bind_group(&self, traversal: Traversal) -> Result<BvhBindGroup<'_>, GpuError> {
        let instanced = self.is_instanced();
        if traversal.is_wide() {
            let w = self.wide.as_ref().ok_or(GpuError::WideLayoutMissing {
                missing: WIDE_NOT_UPLOADED,
            })?;
            return Ok(BvhBindGroup {
                group: &w.group,
                layout: self.ctx.bvh_layout(self.storage, false, instanced),
            });
        }
        let with_escapes = traversal.needs_escapes();
        let group = match (&self.group_plain, &self.group_escapes, with_escapes) {
            (None, _, _) => return Err(GpuError::TraversalNotUploaded { traversal }),
            (_, Some(g), true) => g,
            (_, None, true) => return Err(GpuError::EscapesNotUploaded { traversal }),
            (Some(g), _, false) => g,
        };
        Ok(BvhBindGroup {
            group,
            layout: self.ctx.bvh_layout(self.storage, with_escapes, instanced),
        })
    }

    /// True for a two-level BVH (its bind group has the instances, binding 4).
    pub fn is_instanced(&self) -> bool {
        self.instanced
    }

    /// Writes `bvh` over this upload in place: `bvh` is the uploaded BVH after
    /// [`bvhtrace_core::InstancedBvh::refit_mesh`] ([`Update::Everything`]) or
    /// [`bvhtrace_core::InstancedBvh::set_transforms`] ([`Update::TopLevel`]: only the top
    /// level's nodes and links and the instances are written). Its sizes must be the
    /// upload's; a BVH of another shape is a new upload. An uploaded wide layout is
    /// collapsed again from `bvh` (its `wide`, which a refit leaves stale, is not read) and
    /// written whole, into new buffers only when the collapse came out with another number
    /// of nodes (the collapse follows the boxes' areas); nothing else is created.
    pub fn update(&mut self, bvh: &FlatBvh, what: Update) -> Result<(), GpuError> {
        let shape = (
            bvh.nodes.len(),
            bvh.triangles.len(),
            bvh.instances.len(),
            bvh.top_nodes,
        );
        let uploaded = (
            self.node_count,
            self.triangle_count,
            self.instance_count,
            self.top_nodes,
        );
        if shape != uploaded || (what == Update::TopLevel && !bvh.is_instanced()) {
            return Err(GpuError::BadBuffer {
                buffer: "nodes",
                problem: format!(
                    "an update needs the uploaded shape (nodes, triangles, instances, top-level \
                     nodes) {uploaded:?} with a top level for Update::TopLevel; got {shape:?}"
                ),
            });
        }
        let queue = self.ctx.queue();
        let top = self.top_nodes as usize;
        // Whole blocks of escape links hold the top level's (the last one may hold a
        // mesh's too: they are written with their current, unchanged values).
        let top_links = top.div_ceil(ESCAPE_BLOCK) * ESCAPE_BLOCK * OCTANTS;
        let nodes = match what {
            Update::Everything => bvh.nodes.as_slice(),
            Update::TopLevel => &bvh.nodes[..top],
        };
        // Read (and built, if they are not yet) only when the upload carries them.
        let links = || match what {
            Update::Everything => bvh.escapes(),
            Update::TopLevel => &bvh.escapes()[..top_links],
        };
        let wide = self
            .wide
            .is_some()
            .then(|| Arc::new(WideBvh::collapse(bvh)));
        if let Some(w) = &wide {
            WideUpload::check(&self.ctx, w, self.storage)?;
        }
        let remade = self.ctx.scoped("updating the BVH", || {
            match &self.resources {
                None => {}
                Some(Resources::Buffers {
                    nodes: nb,
                    triangles,
                    escapes,
                }) => {
                    queue.write_buffer(nb, 0, bytemuck::cast_slice(nodes));
                    if let Some(e) = escapes {
                        queue.write_buffer(e, 0, bytemuck::cast_slice(links()));
                    }
                    if what == Update::Everything {
                        queue.write_buffer(triangles, 0, bytemuck::cast_slice(&bvh.triangles));
                    }
                }
                Some(Resources::Textures {
                    nodes: nt,
                    triangles,
                    escapes,
                }) => {
                    write_texels(&self.ctx, nt, 4, node_texels(&bvh.nodes));
                    if let Some(e) = escapes {
                        write_texels(&self.ctx, e, 1, bvh.escapes().to_vec());
                    }
                    if what == Update::Everything {
                        let tris: &[u32] = bytemuck::cast_slice(&bvh.triangles);
                        write_texels(&self.ctx, triangles, 4, tris.to_vec());
                    }
                }
            }
            if let Some(b) = &self.instances {
                queue.write_buffer(b, 0, bytemuck::cast_slice(&bvh.instances));
            }
            match (&self.wide, &wide) {
                (Some(up), Some(w)) if !up.write(&self.ctx, w) => {
                    Some(WideUpload::new(&self.ctx, w, self.storage))
                }
                _ => None,
            }
        })?;
        if let Some(new) = remade {
            let (old_n, old_t, old_i) = self.wide.as_ref().map_or((0, 0, 0), |w| w.bytes);
            let (n, t, i) = new.bytes;
            self.stats.nodes_bytes = self.stats.nodes_bytes - old_n + n;
            self.stats.triangles_bytes = self.stats.triangles_bytes - old_t + t;
            self.stats.instances_bytes = self.stats.instances_bytes - old_i + i;
            self.wide = Some(new);
        }
        let keep = self.host_copy.is_some()
            || wide
                .as_ref()
                .is_some_and(|w| wide_stack_may_overflow(w.depth));
        self.host_copy = keep.then(|| {
            let mut copy = bvh.clone();
            copy.wide = wide;
            Arc::new(copy)
        });
        self.depth = bvh.depth;
        self.instance_table = bvhtrace_core::InstanceTable::of(bvh);
        if what == Update::Everything {
            self.mesh_fingerprint = bvhtrace_kernels::mesh_fingerprint(bvh);
        }
        Ok(())
    }

    /// The node buffer (`array<Node>`), for [`BvhStorage::Buffers`] uploads of the binary
    /// layout.
    pub fn nodes_buffer(&self) -> Option<&wgpu::Buffer> {
        match &self.resources {
            Some(Resources::Buffers { nodes, .. }) => Some(nodes),
            _ => None,
        }
    }

    /// The triangle buffer (`array<Triangle>`), for [`BvhStorage::Buffers`] uploads of the
    /// binary layout.
    pub fn triangles_buffer(&self) -> Option<&wgpu::Buffer> {
        match &self.resources {
            Some(Resources::Buffers { triangles, .. }) => Some(triangles),
            _ => None,
        }
    }

    /// The escape-link buffer (`array<u32>`, eight links per node), for
    /// [`BvhStorage::Buffers`] uploads with the escape links.
    pub fn escapes_buffer(&self) -> Option<&wgpu::Buffer> {
        match &self.resources {
            Some(Resources::Buffers { escapes, .. }) => escapes.as_ref(),
            _ => None,
        }
    }

    /// The wide layout's buffers (`array<BvhWideNode>`, its triangles), when it was
    /// uploaded in [`BvhStorage::Buffers`].
    pub fn wide_buffers(&self) -> Option<(&wgpu::Buffer, &wgpu::Buffer)> {
        match self.wide.as_ref().map(|w| &w.resources) {
            Some(WideResources::Buffers { nodes, triangles }) => Some((nodes, triangles)),
            _ => None,
        }
    }

    /// The wide layout's textures (five `Rgba32Uint` texels per node, three per triangle,
    /// [`TEXEL_ROW`] texels a row: `bvh_textures_wide.wgsl`), when it was uploaded in
    /// [`BvhStorage::Textures`].
    pub fn wide_textures(&self) -> Option<(&wgpu::Texture, &wgpu::Texture)> {
        match self.wide.as_ref().map(|w| &w.resources) {
            Some(WideResources::Textures { nodes, triangles }) => Some((nodes, triangles)),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        };
        let row = u64::from(TEXEL_ROW);
        let l = limits(TEXEL_ROW);
        let most = row * row;
        assert!(check_texels(&l, "wide node texels", most, 16).is_ok());
        let nodes = most / WIDE_NODE_TEXELS + 1;
        match check_texels(&l, "wide node texels", WIDE_NODE_TEXELS * nodes, 16) {
            Err(
                e @ GpuError::TooLarge {
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
            Err(GpuError::TooLarge { .. })
        ));
    }
}
