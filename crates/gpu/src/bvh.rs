//! Uploading a [`FlatBvh`] to the device.

use std::sync::Mutex;
use std::time::Instant;

use bvhtrace_core::{FlatBvh, Traversal};
use wgpu::util::DeviceExt;

use crate::context::GpuContext;
use crate::error::GpuError;
use crate::shaders::FULL_STACK_SIZE;
use crate::trace::Scratch;

/// What to upload for: the traversals the BVH will be traced with.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UploadOptions {
    /// The parent links are uploaded only when one of these needs them
    /// ([`Traversal::needs_parents`]); a tree deeper than [`FULL_STACK_SIZE`] is refused
    /// when [`Traversal::FullStack`] is listed.
    pub traversals: Vec<Traversal>,
}

impl UploadOptions {
    /// Upload for one traversal.
    pub fn for_traversal(traversal: Traversal) -> Self {
        UploadOptions {
            traversals: vec![traversal],
        }
    }

    /// Upload for every traversal (parents included; the depth check applies).
    pub fn all() -> Self {
        UploadOptions {
            traversals: vec![
                Traversal::FullStack,
                Traversal::Stackless,
                Traversal::ShortStack(bvhtrace_core::traverse::DEFAULT_SHORT_STACK),
            ],
        }
    }
}

impl Default for UploadOptions {
    /// [`UploadOptions::all`].
    fn default() -> Self {
        Self::all()
    }
}

/// What an upload cost.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct UploadStats {
    /// Bytes of the node buffer.
    pub nodes_bytes: u64,
    /// Bytes of the triangle buffer.
    pub triangles_bytes: u64,
    /// Bytes of the parent buffer (0 when not uploaded).
    pub parents_bytes: u64,
    /// Wall time to create and fill the buffers and wait for the device, milliseconds.
    pub upload_ms: f64,
}

impl UploadStats {
    /// All bytes uploaded.
    pub fn total_bytes(&self) -> u64 {
        self.nodes_bytes + self.triangles_bytes + self.parents_bytes
    }
}

/// A BVH on the device, ready to trace (see [`GpuBvh::trace`] and [`GpuBvh::record`]).
pub struct GpuBvh {
    pub(crate) ctx: GpuContext,
    nodes: wgpu::Buffer,
    triangles: wgpu::Buffer,
    parents: Option<wgpu::Buffer>,
    /// Group 0 for the full-stack kernels (nodes, triangles).
    pub(crate) group_plain: wgpu::BindGroup,
    /// Group 0 for the parent-link kernels, when parents were uploaded.
    pub(crate) group_parents: Option<wgpu::BindGroup>,
    depth: u32,
    node_count: usize,
    triangle_count: usize,
    stats: UploadStats,
    pub(crate) scratch: Mutex<Option<Scratch>>,
}

impl std::fmt::Debug for GpuBvh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuBvh")
            .field("nodes", &self.node_count)
            .field("triangles", &self.triangle_count)
            .field("depth", &self.depth)
            .field("parents", &self.parents.is_some())
            .field("stats", &self.stats)
            .finish()
    }
}

/// Checks one buffer against the device's limits.
pub(crate) fn check_size(
    ctx: &GpuContext,
    buffer: &'static str,
    bytes: u64,
) -> Result<(), GpuError> {
    let l = ctx.limits();
    if bytes > l.max_storage_buffer_binding_size {
        return Err(GpuError::TooLarge {
            buffer,
            bytes,
            limit: l.max_storage_buffer_binding_size,
            limit_name: "max_storage_buffer_binding_size",
        });
    }
    if bytes > l.max_buffer_size {
        return Err(GpuError::TooLarge {
            buffer,
            bytes,
            limit: l.max_buffer_size,
            limit_name: "max_buffer_size",
        });
    }
    Ok(())
}

impl GpuBvh {
    /// Uploads `bvh`'s nodes and triangles, and its parent links when one of
    /// `opts.traversals` needs them. Every buffer is checked against the device's limits
    /// first ([`GpuError::TooLarge`] names the buffer, its size and the limit), and a tree
    /// deeper than [`FULL_STACK_SIZE`] is refused ([`GpuError::TooDeep`]) when the full-stack
    /// traversal is listed.
    pub fn upload(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        opts: &UploadOptions,
    ) -> Result<GpuBvh, GpuError> {
        if bvh.nodes.is_empty() || bvh.triangles.is_empty() {
            return Err(GpuError::EmptyBvh);
        }
        if opts.traversals.contains(&Traversal::FullStack) && bvh.depth > FULL_STACK_SIZE {
            return Err(GpuError::TooDeep {
                depth: bvh.depth,
                max: FULL_STACK_SIZE,
            });
        }
        let with_parents = opts.traversals.iter().any(|t| t.needs_parents());
        let (nb, pb, tb) = bvh.byte_sizes();
        check_size(ctx, "nodes", nb as u64)?;
        check_size(ctx, "triangles", tb as u64)?;
        if with_parents {
            check_size(ctx, "parents", pb as u64)?;
        }

        let start = Instant::now();
        let device = ctx.device();
        let make = |label: &str, contents: &[u8]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            })
        };
        let (nodes, triangles, parents) = ctx.scoped("uploading the BVH", || {
            (
                make("bvhtrace nodes", bytemuck::cast_slice(&bvh.nodes)),
                make("bvhtrace triangles", bytemuck::cast_slice(&bvh.triangles)),
                with_parents.then(|| make("bvhtrace parents", bytemuck::cast_slice(&bvh.parents))),
            )
        })?;
        fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding,
                resource: buffer.as_entire_binding(),
            }
        }
        let group_plain = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("bvhtrace bvh"),
            layout: ctx.bvh_layout(false),
            entries: &[entry(0, &nodes), entry(1, &triangles)],
        });
        let group_parents = parents.as_ref().map(|p| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("bvhtrace bvh+parents"),
                layout: ctx.bvh_layout(true),
                entries: &[entry(0, &nodes), entry(1, &triangles), entry(2, p)],
            })
        });
        // Make the upload complete before timing stops.
        ctx.queue().submit([]);
        device.poll(wgpu::PollType::wait_indefinitely())?;
        let stats = UploadStats {
            nodes_bytes: nb as u64,
            triangles_bytes: tb as u64,
            parents_bytes: if with_parents { pb as u64 } else { 0 },
            upload_ms: start.elapsed().as_secs_f64() * 1e3,
        };
        Ok(GpuBvh {
            ctx: ctx.clone(),
            nodes,
            triangles,
            parents,
            group_plain,
            group_parents,
            depth: bvh.depth,
            node_count: bvh.nodes.len(),
            triangle_count: bvh.triangles.len(),
            stats,
            scratch: Mutex::new(None),
        })
    }

    /// Checks that this upload can run `traversal`.
    pub fn supports(&self, traversal: Traversal) -> Result<(), GpuError> {
        if traversal.needs_parents() && self.parents.is_none() {
            return Err(GpuError::ParentsNotUploaded { traversal });
        }
        if traversal == Traversal::FullStack && self.depth > FULL_STACK_SIZE {
            return Err(GpuError::TooDeep {
                depth: self.depth,
                max: FULL_STACK_SIZE,
            });
        }
        Ok(())
    }

    /// The context this BVH lives in.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// What the upload cost.
    pub fn stats(&self) -> &UploadStats {
        &self.stats
    }

    /// The tree's depth (edges on its longest root-to-leaf path).
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

    /// The node buffer (`array<Node>`, binding 0 of the BVH group).
    pub fn nodes_buffer(&self) -> &wgpu::Buffer {
        &self.nodes
    }

    /// The triangle buffer (`array<Triangle>`, binding 1 of the BVH group).
    pub fn triangles_buffer(&self) -> &wgpu::Buffer {
        &self.triangles
    }

    /// The parent buffer (`array<u32>`, binding 2 of the BVH group), when uploaded.
    pub fn parents_buffer(&self) -> Option<&wgpu::Buffer> {
        self.parents.as_ref()
    }
}
