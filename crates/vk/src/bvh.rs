//! The BVH in storage buffers and the ray-batch API.

use bytemuck::Zeroable;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use ash::vk;
use bvhtrace_core::{FlatBvh, Ray, TraceOptions, TraceOutput, Traversal, WideBvh};
use bvhtrace_kernels::{
    BvhStorage, COUNTERS_BYTES, HIT_BYTES, KernelKey, RAY_BYTES, TraceError, Tracer, UploadStats,
    check_buffer_size, check_depth, check_wide_top_level, finish_incomplete, plan_dispatches,
    plan_submissions, wide_stack_may_overflow,
};

use crate::context::{Buffer, VkContext};
use crate::error::vkerr;

/// Host-visible ray, hit and counter buffers reused across [`VkBvh::trace`] calls.
struct Scratch {
    capacity: u64,
    rays: Buffer,
    hits: Buffer,
    counters: Buffer,
}

/// The wide layout on the device ([`Traversal::Wide`]) and its descriptor set.
struct WideBuffers {
    nodes: Buffer,
    triangles: Buffer,
    /// The instances in the wide top level's order; for one mesh, one zeroed instance.
    instances: Buffer,
    set: vk::DescriptorSet,
}

impl WideBuffers {
    fn destroy(&mut self, d: &ash::Device) {
        for b in [&mut self.nodes, &mut self.triangles, &mut self.instances] {
            b.destroy(d);
        }
    }
}

/// The arrays of a wide tree as uploaded: nodes, triangles, instances (one zeroed
/// instance for one mesh: every binding of the set is bound).
fn wide_arrays<'a>(
    w: &'a WideBvh,
    no_instances: &'a [bvhtrace_core::FlatInstance],
) -> [(&'static str, &'a [u8]); 3] {
    let instances = if w.is_instanced() {
        w.instances.as_slice()
    } else {
        no_instances
    };
    [
        ("wide nodes", bytemuck::cast_slice(&w.nodes)),
        ("wide triangles", bytemuck::cast_slice(&w.triangles)),
        ("wide instances", bytemuck::cast_slice(instances)),
    ]
}

/// A [`FlatBvh`] uploaded to a [`VkContext`]'s device as three storage buffers (nodes,
/// triangles, escapes: the layout of [`bvhtrace_core::flat`], byte for byte), ready for
/// every traversal; and, when the BVH has its wide layout (`FlatBvh::wide`), that too
/// for [`Traversal::Wide`]. Implements [`Tracer`], the interface shared with the CPU and
/// wgpu backends.
pub struct VkBvh {
    ctx: VkContext,
    nodes: Buffer,
    triangles: Buffer,
    escapes: Buffer,
    /// The instances of a two-level BVH; for one mesh, one zeroed instance the kernels
    /// never read (every binding of the set is bound).
    instances: Buffer,
    instanced: bool,
    pool: vk::DescriptorPool,
    set: vk::DescriptorSet,
    /// The wide layout, when the BVH had one at the upload.
    wide: Option<WideBuffers>,
    depth: u32,
    node_count: usize,
    triangle_count: usize,
    /// The host copy that finishes rays which spend the trip budget (only kept when
    /// [`bvhtrace_kernels::DriverTuning::finishes_on_cpu`]).
    host_copy: Option<Arc<FlatBvh>>,
    stats: UploadStats,
    scratch: Mutex<Option<Scratch>>,
    /// [`bvhtrace_kernels::mesh_fingerprint`] of the uploaded tree.
    mesh_fingerprint: u64,
    /// The kernels traced so far, each once ([`Tracer::kernels_used`]).
    used: Mutex<Vec<KernelKey>>,
    /// The instances' table every output carries, for a two-level BVH.
    instance_table: Option<Arc<bvhtrace_core::InstanceTable>>,
}

impl std::fmt::Debug for VkBvh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VkBvh")
            .field("depth", &self.depth)
            .field("nodes", &self.node_count)
            .field("triangles", &self.triangle_count)
            .field("host_copy", &self.host_copy.is_some())
            .field("stats", &self.stats)
            .finish()
    }
}

impl Drop for VkBvh {
    fn drop(&mut self) {
        let d = &self.ctx.inner.device;
        // SAFETY: every submission using these objects was waited for before its call
        // returned; the context (and device) outlives this value through `ctx`.
        unsafe {
            d.destroy_descriptor_pool(self.pool, None);
        }
        for b in [
            &mut self.nodes,
            &mut self.triangles,
            &mut self.escapes,
            &mut self.instances,
        ] {
            b.destroy(d);
        }
        if let Some(w) = &mut self.wide {
            w.destroy(d);
        }
        let scratch = match self.scratch.get_mut() {
            Ok(s) => s,
            Err(e) => e.into_inner(),
        };
        if let Some(mut s) = scratch.take() {
            s.destroy(d);
        }
    }
}

impl Scratch {
    fn new(ctx: &VkContext, capacity: u64) -> Result<Scratch, TraceError> {
        use vk::MemoryPropertyFlags as M;
        let host = M::HOST_VISIBLE | M::HOST_COHERENT;
        let storage = vk::BufferUsageFlags::STORAGE_BUFFER;
        let rays = ctx.buffer("rays", capacity * RAY_BYTES, storage, host, M::DEVICE_LOCAL)?;
        let mut keep = vec![rays];
        let mut more = |label, bytes, preferred| -> Result<(), TraceError> {
            let b = ctx.buffer(label, capacity * bytes, storage, host, preferred)?;
            keep.push(b);
            Ok(())
        };
        let made = more("hits", HIT_BYTES, M::HOST_CACHED)
            .and_then(|_| more("counters", COUNTERS_BYTES, M::HOST_CACHED));
        if let Err(e) = made {
            for mut b in keep {
                b.destroy(&ctx.inner.device);
            }
            return Err(e);
        }
        let counters = keep.pop();
        let hits = keep.pop();
        let rays = keep.pop();
        match (rays, hits, counters) {
            (Some(rays), Some(hits), Some(counters)) => Ok(Scratch {
                capacity,
                rays,
                hits,
                counters,
            }),
            _ => unreachable!("three buffers were made"),
        }
    }

    fn destroy(&mut self, d: &ash::Device) {
        for b in [&mut self.rays, &mut self.hits, &mut self.counters] {
            b.destroy(d);
        }
    }
}

/// Writes storage-buffer descriptors `(binding, buffer, offset, range)` into `set`.
fn write_set(d: &ash::Device, set: vk::DescriptorSet, entries: &[(u32, vk::Buffer, u64, u64)]) {
    let infos: Vec<[vk::DescriptorBufferInfo; 1]> = entries
        .iter()
        .map(|&(_, buffer, offset, range)| {
            [vk::DescriptorBufferInfo {
                buffer,
                offset,
                range,
            }]
        })
        .collect();
    let writes: Vec<vk::WriteDescriptorSet> = entries
        .iter()
        .zip(&infos)
        .map(|(&(binding, ..), info)| {
            vk::WriteDescriptorSet::default()
                .dst_set(set)
                .dst_binding(binding)
                .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                .buffer_info(info)
        })
        .collect();
    // SAFETY: the set and buffers belong to `d`; the set is not in use by a pending
    // submission.
    unsafe { d.update_descriptor_sets(&writes, &[]) };
}

/// Writes each `(buffer, bytes)` at the start of its device-local buffer through one
/// host-visible staging buffer, and waits until the kernels can read them.
fn copy_to_device(
    ctx: &VkContext,
    during: &'static str,
    copies: &[(vk::Buffer, &[u8])],
) -> Result<(), TraceError> {
    let align = |x: u64| x.div_ceil(16) * 16;
    let total: u64 = copies.iter().map(|(_, b)| align(b.len() as u64)).sum();
    let mut staging = ctx.buffer(
        "staging",
        total,
        vk::BufferUsageFlags::TRANSFER_SRC,
        vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT,
        vk::MemoryPropertyFlags::empty(),
    )?;
    let mut data = vec![0u8; total as usize];
    let mut regions = Vec::with_capacity(copies.len());
    let mut offset = 0u64;
    for &(dst, bytes) in copies {
        data[offset as usize..offset as usize + bytes.len()].copy_from_slice(bytes);
        regions.push((dst, offset, bytes.len() as u64));
        offset += align(bytes.len() as u64);
    }
    staging.write(&data);
    let result = ctx.submitter().and_then(|s| {
        ctx.submit_and_wait(&s, during, |d, cmd| {
            for &(dst, src_offset, size) in &regions {
                if size == 0 {
                    continue;
                }
                let region = [vk::BufferCopy {
                    src_offset,
                    dst_offset: 0,
                    size,
                }];
                // SAFETY: recording into the locked command buffer.
                unsafe { d.cmd_copy_buffer(cmd, staging.raw, dst, &region) };
            }
            let barrier = [vk::MemoryBarrier::default()
                .src_access_mask(vk::AccessFlags::TRANSFER_WRITE)
                .dst_access_mask(vk::AccessFlags::SHADER_READ)];
            // SAFETY: as above.
            unsafe {
                d.cmd_pipeline_barrier(
                    cmd,
                    vk::PipelineStageFlags::TRANSFER,
                    vk::PipelineStageFlags::COMPUTE_SHADER,
                    vk::DependencyFlags::empty(),
                    &barrier,
                    &[],
                    &[],
                )
            };
        })
    });
    staging.destroy(&ctx.inner.device);
    result
}

/// Device-local storage buffers holding `arrays` (name, bytes), filled through one staging
/// buffer and ready for the kernels; when a step fails, none is left behind.
fn device_buffers(
    ctx: &VkContext,
    during: &'static str,
    arrays: &[(&'static str, &[u8])],
) -> Result<Vec<Buffer>, TraceError> {
    use vk::BufferUsageFlags as U;
    use vk::MemoryPropertyFlags as M;
    let mut made: Vec<Buffer> = Vec::with_capacity(arrays.len());
    let result = (|| -> Result<(), TraceError> {
        for &(name, bytes) in arrays {
            made.push(ctx.buffer(
                name,
                bytes.len() as u64,
                U::STORAGE_BUFFER | U::TRANSFER_DST,
                M::DEVICE_LOCAL,
                M::empty(),
            )?);
        }
        let copies: Vec<(vk::Buffer, &[u8])> = made
            .iter()
            .zip(arrays)
            .map(|(b, (_, bytes))| (b.raw, *bytes))
            .collect();
        copy_to_device(ctx, during, &copies)
    })();
    if let Err(e) = result {
        for mut b in made {
            b.destroy(&ctx.inner.device);
        }
        return Err(e);
    }
    Ok(made)
}

/// Bytes of a wide tree's nodes, triangles and instances (as [`UploadStats`] counts them).
fn wide_bytes(w: &WideBvh) -> (u64, u64, u64) {
    (
        std::mem::size_of_val(w.nodes.as_slice()) as u64,
        std::mem::size_of_val(w.triangles.as_slice()) as u64,
        std::mem::size_of_val(w.instances.as_slice()) as u64,
    )
}

/// True when [`VkBvh::trace`] may have incomplete rays to finish on a host copy of the tree
/// (with the wide layout uploaded): when the context's tuning sets a trip budget, or when
/// the wide tree is deep enough for a ray to overflow the wide walk's stack (on any
/// device).
fn keeps_host_copy(ctx: &VkContext, wide: Option<&WideBvh>) -> bool {
    ctx.tuning().finishes_on_cpu() || wide.is_some_and(|w| wide_stack_may_overflow(w.depth))
}

/// A descriptor pool for `sets` sets of at most four storage buffers.
fn descriptor_pool(d: &ash::Device, sets: u32) -> Result<vk::DescriptorPool, TraceError> {
    let sizes = [vk::DescriptorPoolSize {
        ty: vk::DescriptorType::STORAGE_BUFFER,
        descriptor_count: 4 * sets,
    }];
    // SAFETY: plain object creation.
    unsafe {
        d.create_descriptor_pool(
            &vk::DescriptorPoolCreateInfo::default()
                .max_sets(sets)
                .pool_sizes(&sizes),
            None,
        )
    }
    .map_err(vkerr("creating a descriptor pool"))
}

impl VkBvh {
    /// Uploads `bvh`'s nodes, triangles and escape links (built first when they are not
    /// yet: [`FlatBvh::escapes`]) to device-local storage buffers (through one host-visible
    /// staging buffer), so that every traversal can run on it;
    /// and its wide layout when it has one (`bvh.wide`: [`FlatBvh::build_wide`] before the
    /// upload), for [`Traversal::Wide`]. An empty tree is [`TraceError::EmptyBvh`], escape
    /// links that do not fit the nodes [`TraceError::BadEscapeLinks`]; each array is
    /// checked against the device's limits (`maxStorageBufferRange`,
    /// `maxMemoryAllocationSize`) first, and [`TraceError::TooLarge`] names the array, its
    /// size and the limit. A tree deeper than
    /// [`FULL_STACK_SIZE`](bvhtrace_kernels::FULL_STACK_SIZE) uploads; only the full-stack
    /// walk refuses it ([`VkBvh::supports`]). When [`VkContext::tuning`] finishes rays on
    /// the CPU, or the wide tree is deep enough for the wide walk's stack to overflow
    /// ([`bvhtrace_kernels::wide_stack_may_overflow`]), the upload keeps a host copy of the
    /// tree for that.
    pub fn upload(ctx: &VkContext, bvh: &FlatBvh) -> Result<VkBvh, TraceError> {
        // Built (when not yet) before the clock starts, as the wgpu upload does.
        let escapes = bvh.escapes();
        let start = Instant::now();
        if bvh.nodes.is_empty() || bvh.triangles.is_empty() {
            return Err(TraceError::EmptyBvh);
        }
        bvh.check_escape_links()?;
        let wide = bvh.wide.clone();
        if let Some(w) = &wide {
            check_wide_top_level(w)?;
        }
        let no_instances = [bvhtrace_core::FlatInstance::zeroed()];
        let instances = if bvh.is_instanced() {
            bvh.instances.as_slice()
        } else {
            &no_instances
        };
        let mut arrays: Vec<(&'static str, &[u8])> = vec![
            ("nodes", bytemuck::cast_slice(&bvh.nodes)),
            ("triangles", bytemuck::cast_slice(&bvh.triangles)),
            ("escapes", bytemuck::cast_slice(escapes)),
            ("instances", bytemuck::cast_slice(instances)),
        ];
        if let Some(w) = &wide {
            arrays.extend(wide_arrays(w, &no_instances));
        }
        for &(name, bytes) in &arrays {
            check_buffer_size(ctx.limits(), name, bytes.len() as u64)?;
        }
        let d = &ctx.inner.device;
        let mut made = device_buffers(ctx, "uploading the BVH", &arrays)?.into_iter();
        let mut next = || {
            made.next()
                .unwrap_or_else(|| unreachable!("a buffer per array"))
        };
        let (nodes, triangles, escapes, instances) = (next(), next(), next(), next());
        let wide_buffers = wide.as_ref().map(|_| WideBuffers {
            nodes: next(),
            triangles: next(),
            instances: next(),
            set: vk::DescriptorSet::null(),
        });
        let wide_bytes = wide.as_ref().map_or((0, 0, 0), |w| wide_bytes(w));
        let mut bvh_gpu = VkBvh {
            ctx: ctx.clone(),
            nodes,
            triangles,
            escapes,
            instances,
            instanced: bvh.is_instanced(),
            pool: vk::DescriptorPool::null(),
            set: vk::DescriptorSet::null(),
            wide: wide_buffers,
            depth: bvh.depth,
            node_count: bvh.nodes.len(),
            triangle_count: bvh.triangles.len(),
            host_copy: keeps_host_copy(ctx, wide.as_deref()).then(|| Arc::new(bvh.clone())),
            mesh_fingerprint: bvhtrace_kernels::mesh_fingerprint(bvh),
            used: Mutex::new(Vec::new()),
            instance_table: bvhtrace_core::InstanceTable::of(bvh),
            stats: UploadStats {
                storage: BvhStorage::Buffers,
                nodes_bytes: arrays[0].1.len() as u64 + wide_bytes.0,
                triangles_bytes: arrays[1].1.len() as u64 + wide_bytes.1,
                escapes_bytes: arrays[2].1.len() as u64,
                instances_bytes: std::mem::size_of_val(bvh.instances.as_slice()) as u64
                    + wide_bytes.2,
                upload_ms: 0.0,
            },
            scratch: Mutex::new(None),
        };
        // From here on, dropping `bvh_gpu` frees everything.
        let sets = 1 + u32::from(bvh_gpu.wide.is_some());
        bvh_gpu.pool = descriptor_pool(d, sets)?;
        let layouts = vec![ctx.inner.set_layouts[0]; sets as usize];
        // SAFETY: allocating from the pool just made, sized for these sets.
        let allocated = unsafe {
            d.allocate_descriptor_sets(
                &vk::DescriptorSetAllocateInfo::default()
                    .descriptor_pool(bvh_gpu.pool)
                    .set_layouts(&layouts),
            )
        }
        .map_err(vkerr("allocating the BVH descriptor sets"))?;
        bvh_gpu.set = allocated[0];
        let whole = |b: &Buffer| (b.raw, 0, vk::WHOLE_SIZE);
        let entries = [
            (0, whole(&bvh_gpu.nodes)),
            (1, whole(&bvh_gpu.triangles)),
            (2, whole(&bvh_gpu.escapes)),
            (4, whole(&bvh_gpu.instances)),
        ]
        .map(|(i, (b, o, r))| (i, b, o, r));
        write_set(d, bvh_gpu.set, &entries);
        if let Some(w) = &mut bvh_gpu.wide {
            w.set = allocated[1];
        }
        bvh_gpu.write_wide_set();
        bvh_gpu.stats.upload_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(bvh_gpu)
    }

    /// Points the wide layout's descriptor set at its buffers: nodes, triangles and
    /// instances where the binary set has its own; the escape links' binding (read by no
    /// wide kernel, but bound as every binding is) at the binary escape links.
    fn write_wide_set(&self) {
        let Some(w) = &self.wide else { return };
        let whole = |b: &Buffer| (b.raw, 0, vk::WHOLE_SIZE);
        let entries = [
            (0, whole(&w.nodes)),
            (1, whole(&w.triangles)),
            (2, whole(&self.escapes)),
            (4, whole(&w.instances)),
        ]
        .map(|(i, (b, o, r))| (i, b, o, r));
        write_set(&self.ctx.inner.device, w.set, &entries);
    }

    /// True when the wide layout was uploaded (the BVH had it).
    pub fn has_wide(&self) -> bool {
        self.wide.is_some()
    }

    /// The context this BVH lives on.
    pub fn context(&self) -> &VkContext {
        &self.ctx
    }

    /// Sizes and time of the upload.
    pub fn stats(&self) -> &UploadStats {
        &self.stats
    }

    /// The tree's depth (the full-stack walk takes trees up to [`FULL_STACK_SIZE`](bvhtrace_kernels::FULL_STACK_SIZE) deep).
    pub fn depth(&self) -> u32 {
        self.depth
    }

    /// Nodes uploaded.
    pub fn node_count(&self) -> usize {
        self.node_count
    }

    /// Triangles uploaded.
    pub fn triangle_count(&self) -> usize {
        self.triangle_count
    }

    /// Writes `bvh` over this upload in place, its buffers kept (the `wgpu` backend's
    /// `GpuBvh::update`): the whole BVH after
    /// [`bvhtrace_core::InstancedBvh::refit_mesh`], or with `top_level_only` the top level's
    /// nodes, their escape links and the instances after
    /// [`bvhtrace_core::InstancedBvh::set_transforms`]. `bvh` must have the uploaded
    /// shape (nodes, triangles, instances); another shape is a new upload. An uploaded wide
    /// layout is collapsed again from `bvh` (its `wide`, which a refit leaves stale, is not
    /// read) and written whole, into new buffers only when the collapse came out with
    /// other sizes.
    pub fn update(&mut self, bvh: &FlatBvh, top_level_only: bool) -> Result<(), TraceError> {
        let shape = (bvh.nodes.len(), bvh.triangles.len(), bvh.is_instanced());
        let uploaded = (self.node_count, self.triangle_count, self.instanced);
        let instances_fit =
            !bvh.is_instanced() || bvh.instances.len() as u64 * 64 == self.instances.size;
        if shape != uploaded || !instances_fit || (top_level_only && !bvh.is_instanced()) {
            return Err(TraceError::BadBuffer {
                buffer: "nodes",
                problem: format!(
                    "an update needs the uploaded shape (nodes, triangles, instanced) {uploaded:?} \
                     and, for the top level only, a two-level BVH; got {shape:?}"
                ),
            });
        }
        let top = bvh.top_nodes as usize;
        let links = top.div_ceil(bvhtrace_core::flat::ESCAPE_BLOCK)
            * bvhtrace_core::flat::ESCAPE_BLOCK
            * bvhtrace_core::flat::OCTANTS;
        let mut copies: Vec<(vk::Buffer, &[u8])> = if top_level_only {
            vec![
                (self.nodes.raw, bytemuck::cast_slice(&bvh.nodes[..top])),
                (
                    self.escapes.raw,
                    bytemuck::cast_slice(&bvh.escapes()[..links]),
                ),
            ]
        } else {
            vec![
                (self.nodes.raw, bytemuck::cast_slice(&bvh.nodes)),
                (self.escapes.raw, bytemuck::cast_slice(bvh.escapes())),
                (self.triangles.raw, bytemuck::cast_slice(&bvh.triangles)),
            ]
        };
        if bvh.is_instanced() {
            copies.push((self.instances.raw, bytemuck::cast_slice(&bvh.instances)));
        }
        // The wide layout is collapsed again and written whole (its meshes' places follow
        // the top level's order); into new buffers when its sizes changed (the collapse
        // follows the boxes' areas).
        let wide = self
            .wide
            .is_some()
            .then(|| Arc::new(WideBvh::collapse(bvh)));
        let no_instances = [bvhtrace_core::FlatInstance::zeroed()];
        let mut remake = Vec::new();
        if let (Some(w), Some(up)) = (&wide, &self.wide) {
            check_wide_top_level(w)?;
            let arrays = wide_arrays(w, &no_instances);
            for &(name, bytes) in &arrays {
                check_buffer_size(self.ctx.limits(), name, bytes.len() as u64)?;
            }
            let bufs = [&up.nodes, &up.triangles, &up.instances];
            if bufs
                .iter()
                .zip(&arrays)
                .all(|(b, a)| b.size == a.1.len() as u64)
            {
                copies.extend(bufs.iter().zip(&arrays).map(|(b, a)| (b.raw, a.1)));
            } else {
                remake.extend(arrays);
            }
        }
        copy_to_device(&self.ctx, "updating the BVH", &copies)?;
        if !remake.is_empty() {
            let d = &self.ctx.inner.device;
            let mut made = device_buffers(&self.ctx, "updating the BVH", &remake)?.into_iter();
            if let (Some(up), Some(nodes), Some(triangles), Some(instances)) =
                (&mut self.wide, made.next(), made.next(), made.next())
            {
                // Every submission that read the old buffers has completed.
                let mut old = std::mem::replace(
                    up,
                    WideBuffers {
                        nodes,
                        triangles,
                        instances,
                        set: up.set,
                    },
                );
                old.destroy(d);
            }
            self.write_wide_set();
        }
        if let Some(w) = &wide {
            let (n, t, i) = wide_bytes(w);
            let binary = |b: &[u8]| b.len() as u64;
            self.stats.nodes_bytes = binary(bytemuck::cast_slice(&bvh.nodes)) + n;
            self.stats.triangles_bytes = binary(bytemuck::cast_slice(&bvh.triangles)) + t;
            self.stats.instances_bytes = binary(bytemuck::cast_slice(&bvh.instances)) + i;
        }
        self.host_copy = keeps_host_copy(&self.ctx, wide.as_deref()).then(|| {
            let mut copy = bvh.clone();
            copy.wide = wide.clone().or_else(|| bvh.wide.clone());
            Arc::new(copy)
        });
        self.depth = bvh.depth;
        self.instance_table = bvhtrace_core::InstanceTable::of(bvh);
        if !top_level_only {
            self.mesh_fingerprint = bvhtrace_kernels::mesh_fingerprint(bvh);
        }
        Ok(())
    }

    /// The kernel tracing `opts` on this upload, with the box test's parallel path when
    /// `parallel_rays` ([`KernelKey::for_rays`]).
    fn key(&self, opts: &TraceOptions, parallel_rays: bool) -> KernelKey {
        KernelKey {
            parallel_rays,
            ..KernelKey::new(BvhStorage::Buffers, opts).with_instances(self.instanced)
        }
    }

    /// Checks that `opts` can run on this upload and device: the full-stack walk needs a
    /// tree at most [`FULL_STACK_SIZE`](bvhtrace_kernels::FULL_STACK_SIZE) deep ([`TraceError::TooDeep`]), the f64 triangle
    /// test needs `shaderFloat64` ([`TraceError::PrecisionUnsupported`]), the wide walk
    /// the wide layout ([`TraceError::WideLayoutMissing`]: the BVH had none at the
    /// upload). The escape links are always uploaded.
    pub fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        check_depth(opts.traversal, self.depth)?;
        if opts.traversal.is_wide() && self.wide.is_none() {
            return Err(TraceError::WideLayoutMissing {
                missing: "it did not have when it was uploaded: call FlatBvh::build_wide \
                          before VkBvh::upload",
            });
        }
        self.ctx.supports_key(&self.key(opts, true))
    }

    /// Creates (and caches) the pipelines [`VkBvh::trace`] runs for `opts` (with the box
    /// test's parallel path and without it, see [`KernelKey::for_rays`]) ahead of the
    /// first trace, so that the first trace's time is not the compiler's.
    pub fn prepare(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.supports(opts)?;
        for parallel_rays in [true, false] {
            self.ctx.pipeline(self.key(opts, parallel_rays))?;
        }
        Ok(())
    }

    /// Traces `rays` as `opts` says (walk, query, triangle test, counters) and returns one
    /// hit per ray (and each ray's counters when `opts.counters`), the time between the
    /// dispatches' timestamps and the call's wall time. The results equal
    /// [`bvhtrace_core::trace_rays`]'s and the wgpu backend's bit for bit. Batches are
    /// split into dispatches within the device's limits ([`plan_dispatches`], as the wgpu
    /// path does), and into several submissions when one buffer cannot hold them
    /// ([`plan_submissions`]). Rays that spend the trip budget of a CPU driver are
    /// finished on the CPU ([`finish_incomplete`]; counted in `incomplete`).
    pub fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        // Checked before anything is uploaded; the rays are looked at once, and every
        // submission uses this kernel.
        self.supports(opts)?;
        let key = self.key(opts, true).for_rays(rays);
        let pipeline = self.ctx.pipeline(key)?;
        {
            let mut used = self
                .used
                .lock()
                .map_err(|_| TraceError::Poisoned("kernels used"))?;
            if !used.contains(&key) {
                used.push(key);
            }
        }
        let counters = opts.counters;
        // `supports` saw the wide layout uploaded for the wide walk.
        let bvh_set = match (&self.wide, opts.traversal.is_wide()) {
            (Some(w), true) => w.set,
            _ => self.set,
        };
        let start = Instant::now();
        let inner = &self.ctx.inner;
        let d = &inner.device;
        let mut out = TraceOutput {
            hits: Vec::with_capacity(rays.len()),
            counters: counters.then(|| Vec::with_capacity(rays.len())),
            gpu_ms: inner.timestamp_period_ns.map(|_| 0.0),
            wall_ms: 0.0,
            incomplete: 0,
            instances: self.instance_table.clone(),
        };
        let n = rays.len() as u64;
        if n == 0 {
            return Ok(out);
        }
        let limits = self.ctx.limits();
        let (per_submit, capacity) = plan_submissions(n, limits);

        let mut guard = self
            .scratch
            .lock()
            .map_err(|_| TraceError::Poisoned("scratch buffers"))?;
        if guard.as_ref().is_none_or(|s| s.capacity < capacity) {
            if let Some(mut old) = guard.take() {
                old.destroy(d);
            }
            *guard = Some(Scratch::new(&self.ctx, capacity)?);
        }
        let Some(s) = guard.as_ref() else {
            unreachable!("scratch was just created")
        };
        let sub = self.ctx.submitter()?;
        for batch in rays.chunks(per_submit as usize) {
            let count = batch.len() as u64;
            s.rays.write(bytemuck::cast_slice(batch));
            let dispatches = plan_dispatches(count, limits);
            let pool = descriptor_pool(d, dispatches.len() as u32)?;
            let traced = (|| -> Result<(), TraceError> {
                let layouts = vec![inner.set_layouts[1]; dispatches.len()];
                // SAFETY: allocating from the pool just made, sized for these sets.
                let sets = unsafe {
                    d.allocate_descriptor_sets(
                        &vk::DescriptorSetAllocateInfo::default()
                            .descriptor_pool(pool)
                            .set_layouts(&layouts),
                    )
                }
                .map_err(vkerr("allocating ray-batch descriptor sets"))?;
                for (set, dp) in sets.iter().zip(&dispatches) {
                    let (first, c) = (dp.first_ray, u64::from(dp.ray_count));
                    write_set(
                        d,
                        *set,
                        &[
                            (0, s.rays.raw, first * RAY_BYTES, c * RAY_BYTES),
                            (1, s.hits.raw, first * HIT_BYTES, c * HIT_BYTES),
                            (
                                2,
                                s.counters.raw,
                                first * COUNTERS_BYTES,
                                c * COUNTERS_BYTES,
                            ),
                        ],
                    );
                }
                let queries = sub.queries;
                let timed = inner.timestamp_period_ns.is_some();
                self.ctx
                    .submit_and_wait(&sub, "tracing a ray batch", |d, cmd| {
                        let bind = vk::PipelineBindPoint::COMPUTE;
                        // SAFETY: recording into the locked command buffer; every object
                        // belongs to this device and outlives the submission.
                        unsafe {
                            if timed {
                                d.cmd_reset_query_pool(cmd, queries, 0, 2);
                                d.cmd_write_timestamp(
                                    cmd,
                                    vk::PipelineStageFlags::TOP_OF_PIPE,
                                    queries,
                                    0,
                                );
                            }
                            d.cmd_bind_pipeline(cmd, bind, pipeline);
                            d.cmd_bind_descriptor_sets(
                                cmd,
                                bind,
                                inner.pipeline_layout,
                                0,
                                &[bvh_set],
                                &[],
                            );
                            for (set, dp) in sets.iter().zip(&dispatches) {
                                d.cmd_bind_descriptor_sets(
                                    cmd,
                                    bind,
                                    inner.pipeline_layout,
                                    1,
                                    &[*set],
                                    &[],
                                );
                                d.cmd_dispatch(cmd, dp.groups_x, dp.groups_y, 1);
                            }
                            if timed {
                                d.cmd_write_timestamp(
                                    cmd,
                                    vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                                    queries,
                                    1,
                                );
                            }
                            let barrier = [vk::MemoryBarrier::default()
                                .src_access_mask(vk::AccessFlags::SHADER_WRITE)
                                .dst_access_mask(vk::AccessFlags::HOST_READ)];
                            d.cmd_pipeline_barrier(
                                cmd,
                                vk::PipelineStageFlags::COMPUTE_SHADER,
                                vk::PipelineStageFlags::HOST,
                                vk::DependencyFlags::empty(),
                                &barrier,
                                &[],
                                &[],
                            );
                        }
                    })?;
                s.hits
                    .read_into((count * HIT_BYTES) as usize, &mut out.hits);
                if let Some(c) = out.counters.as_mut() {
                    s.counters.read_into((count * COUNTERS_BYTES) as usize, c);
                }
                if let (Some(period), Some(total)) =
                    (inner.timestamp_period_ns, out.gpu_ms.as_mut())
                {
                    let mut ts = [0u64; 2];
                    // SAFETY: both queries were written by the submission just waited for.
                    unsafe {
                        d.get_query_pool_results(
                            queries,
                            0,
                            &mut ts,
                            vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
                        )
                    }
                    .map_err(vkerr("reading timestamps"))?;
                    let ticks = (ts[1] & inner.timestamp_mask)
                        .wrapping_sub(ts[0] & inner.timestamp_mask)
                        & inner.timestamp_mask;
                    *total += ticks as f64 * period * 1e-6;
                }
                Ok(())
            })();
            // SAFETY: the submission using the sets has completed (or never started).
            unsafe { d.destroy_descriptor_pool(pool, None) };
            traced?;
        }
        drop(sub);
        drop(guard);
        if let Some(bvh) = self.host_copy.as_deref() {
            finish_incomplete(bvh, rays, opts, &mut out);
        }
        out.wall_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(out)
    }
}

impl Tracer for VkBvh {
    fn backend(&self) -> &'static str {
        "vulkan"
    }

    fn device_name(&self) -> String {
        let i = self.ctx.device_info();
        let (major, minor, _) = i.api_version;
        format!("{} ({:?}, Vulkan {major}.{minor})", i.name, i.kind)
    }

    fn default_traversal(&self) -> Traversal {
        Traversal::GPU_DEFAULT
    }

    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        VkBvh::supports(self, opts)
    }

    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        VkBvh::trace(self, rays, opts)
    }

    fn prepare(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        VkBvh::prepare(self, opts)
    }

    fn upload_stats(&self) -> Option<UploadStats> {
        Some(self.stats)
    }

    fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        let fingerprint = bvhtrace_kernels::mesh_fingerprint(bvh);
        let top_level_only = bvh.is_instanced() && fingerprint == self.mesh_fingerprint;
        VkBvh::update(self, bvh, top_level_only)
    }

    fn kernels_used(&self) -> Vec<KernelKey> {
        self.used.lock().map(|u| u.clone()).unwrap_or_default()
    }
}
