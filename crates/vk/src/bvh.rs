//! The BVH in storage buffers and the ray-batch API: [`VkBvh`], the engine
//! ([`bvhtrace_engine::Engine`]) over the ash implementation of its [`DeviceApi`].

use std::time::Instant;

use bytemuck::Zeroable;

use ash::vk;

use bvhtrace_core::{FlatBvh, TracePhases};
#[cfg(doc)]
use bvhtrace_engine::core::Traversal;
use bvhtrace_engine::engine::{
    ArrayWrite, ArraysLayout, BackendFeatures, Batch, BatchOut, BatchTimes, DeviceApi, HasEngine,
    ScratchPlan, UploadedTree,
};
use bvhtrace_engine::pages::{PAGE_BINDING_STRIDE, too_many_buffers};
use bvhtrace_engine::plan::{COUNTERS_BYTES, DeviceLimits, HIT_BYTES, RAY_BYTES, plan_dispatches};
use bvhtrace_engine::upload::{ArrayRole, DeviceArray};
#[cfg(doc)]
use bvhtrace_engine::{BvhStorage, Tracer};
use bvhtrace_engine::{DriverTuning, Engine, KernelKey, TraceError, UploadOptions, UploadStats};

use crate::context::{Buffer, VkContext, barrier};
use crate::error::vkerr;

/// The Vulkan device behind a [`VkBvh`]: the engine's backend on ash.
pub struct Ash {
    ctx: VkContext,
}

/// Host-visible ray, hit and counter buffers reused across traces.
pub struct Scratch {
    rays: Buffer,
    hits: Buffer,
    counters: Buffer,
}

/// The uploaded arrays, each in a device-local storage buffer, and their descriptor sets.
pub struct Arrays {
    /// Each array (each page of a split one) by role and page.
    buffers: Vec<((ArrayRole, u8), Buffer)>,
    /// One zeroed instance, bound where the upload has no array: every binding of a set is
    /// bound (the instances of one mesh, escape links the wide walk never reads, the masks
    /// of a BVH without them).
    filler: Buffer,
    /// The binary layout's set and the wide layout's.
    sets: Sets,
}

/// A descriptor pool and the sets allocated from it, destroyed when dropped.
struct Sets {
    ctx: VkContext,
    pool: vk::DescriptorPool,
    sets: Vec<vk::DescriptorSet>,
}

impl Sets {
    /// `count` sets of the kernels' set layout `layout` (0: the BVH, 1: the batch).
    fn new(ctx: &VkContext, layout: usize, count: u32) -> Result<Sets, TraceError> {
        let d = &ctx.inner.device;
        let sizes = [vk::DescriptorPoolSize {
            ty: vk::DescriptorType::STORAGE_BUFFER,
            descriptor_count: ctx.inner.set_bindings[layout].len() as u32 * count,
        }];
        let info = vk::DescriptorPoolCreateInfo::default()
            .max_sets(count)
            .pool_sizes(&sizes);
        // SAFETY: plain object creation; dropping `out` destroys the pool and its sets.
        let mut out = Sets {
            ctx: ctx.clone(),
            pool: unsafe { d.create_descriptor_pool(&info, None) }
                .map_err(vkerr("creating a descriptor pool"))?,
            sets: Vec::new(),
        };
        let layouts = vec![ctx.inner.set_layouts[layout]; count as usize];
        let info = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(out.pool)
            .set_layouts(&layouts);
        // SAFETY: allocating from the pool just made, sized for these sets.
        out.sets = unsafe { d.allocate_descriptor_sets(&info) }
            .map_err(vkerr("allocating descriptor sets"))?;
        Ok(out)
    }
}

impl Drop for Sets {
    fn drop(&mut self) {
        // SAFETY: every submission using the sets was waited for before its call returned.
        unsafe {
            self.ctx
                .inner
                .device
                .destroy_descriptor_pool(self.pool, None)
        };
    }
}

impl Arrays {
    /// Page `page` of the array in `role`, or the filler where there is none.
    fn raw(&self, role: ArrayRole, page: u8) -> vk::Buffer {
        self.buffers
            .iter()
            .find(|(r, _)| *r == (role, page))
            .map_or(self.filler.raw, |(_, b)| b.raw)
    }

    fn has(&self, role: ArrayRole, page: u8) -> bool {
        self.buffers.iter().any(|(r, _)| *r == (role, page))
    }

    /// Points the sets at the buffers: the wide set at the wide layout's arrays, with the
    /// binary escape links at binding 2 as every binding is bound; each binding of the
    /// set layout gets its array's page, or the filler.
    fn bind(&self) {
        use ArrayRole as R;
        let ctx = &self.sets.ctx.inner;
        let d = &ctx.device;
        for (set, roles) in [
            [R::Nodes, R::Triangles, R::Escapes, R::Instances, R::Masks],
            [
                R::WideNodes,
                R::WideTriangles,
                R::Escapes,
                R::WideInstances,
                R::WideMasks,
            ],
        ]
        .iter()
        .enumerate()
        {
            if !self.has(roles[0], 0) {
                continue;
            }
            let e: Vec<_> = (ctx.set_bindings[0].iter())
                .map(|&binding| {
                    let page = (binding / PAGE_BINDING_STRIDE) as u8;
                    let role = roles
                        .iter()
                        .find(|r| r.binding() == binding % PAGE_BINDING_STRIDE);
                    let raw = role.map_or(self.filler.raw, |&r| self.raw(r, page));
                    (binding, raw, 0, vk::WHOLE_SIZE)
                })
                .collect();
            write_set(d, self.sets.sets[set], &e);
        }
    }
}

impl Scratch {
    fn new(ctx: &VkContext, capacity: u64) -> Result<Scratch, TraceError> {
        use vk::MemoryPropertyFlags as M;
        let buffer = |label, bytes, preferred| {
            let host = M::HOST_VISIBLE | M::HOST_COHERENT;
            let usage = vk::BufferUsageFlags::STORAGE_BUFFER;
            ctx.buffer(label, capacity * bytes, usage, host, preferred)
        };
        Ok(Scratch {
            rays: buffer("rays", RAY_BYTES, M::DEVICE_LOCAL)?,
            hits: buffer("hits", HIT_BYTES, M::HOST_CACHED)?,
            counters: buffer("counters", COUNTERS_BYTES, M::HOST_CACHED)?,
        })
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

/// Bytes one staging buffer holds at most: larger uploads are staged in turns.
const STAGING_BYTES: u64 = 256 << 20;

/// Writes each `(buffer, bytes)` at the start of its device-local buffer through
/// host-visible staging buffers of at most [`STAGING_BYTES`] (or one array, when larger),
/// and waits until the kernels can read them.
fn copy_to_device(
    ctx: &VkContext,
    during: &'static str,
    copies: &[(vk::Buffer, &[u8])],
) -> Result<(), TraceError> {
    let align = |x: u64| x.div_ceil(16) * 16;
    let mut start = 0;
    while start < copies.len() {
        let mut end = start + 1;
        let mut total = align(copies[start].1.len() as u64);
        while end < copies.len() && total + align(copies[end].1.len() as u64) <= STAGING_BYTES {
            total += align(copies[end].1.len() as u64);
            end += 1;
        }
        stage(ctx, during, &copies[start..end], total)?;
        start = end;
    }
    Ok(())
}

/// [`copy_to_device`] of `copies`, `total` bytes with their alignment, through one
/// staging buffer.
fn stage(
    ctx: &VkContext,
    during: &'static str,
    copies: &[(vk::Buffer, &[u8])],
    total: u64,
) -> Result<(), TraceError> {
    let align = |x: u64| x.div_ceil(16) * 16;
    let staging = ctx.buffer(
        "staging",
        total.max(16),
        vk::BufferUsageFlags::TRANSFER_SRC,
        vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT,
        vk::MemoryPropertyFlags::empty(),
    )?;
    let mut regions = Vec::with_capacity(copies.len());
    let mut offset = 0u64;
    for &(dst, bytes) in copies {
        staging.write_at(offset, bytes);
        regions.push((dst, offset, bytes.len() as u64));
        offset += align(bytes.len() as u64);
    }
    let s = ctx.submitter()?;
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
        use vk::{AccessFlags as A, PipelineStageFlags as S};
        // SAFETY: as above.
        unsafe {
            barrier(
                d,
                cmd,
                (S::TRANSFER, A::TRANSFER_WRITE),
                (S::COMPUTE_SHADER, A::SHADER_READ),
            )
        };
    })
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
    let made = arrays
        .iter()
        .map(|&(name, bytes)| {
            let usage = U::STORAGE_BUFFER | U::TRANSFER_DST;
            ctx.buffer(name, bytes.len() as u64, usage, M::DEVICE_LOCAL, M::empty())
        })
        .collect::<Result<Vec<Buffer>, TraceError>>()?;
    let copies: Vec<(vk::Buffer, &[u8])> = made
        .iter()
        .zip(arrays)
        .map(|(b, (_, bytes))| (b.raw, *bytes))
        .collect();
    copy_to_device(ctx, during, &copies)?;
    Ok(made)
}

impl Ash {
    /// Records the batch's dispatches (one of `sets` each) into `cmd`.
    fn dispatch(
        &self,
        arrays: &Arrays,
        s: &Scratch,
        key: KernelKey,
        count: u64,
        sets: &Sets,
    ) -> Result<impl FnOnce(&ash::Device, vk::CommandBuffer, vk::QueryPool), TraceError> {
        let inner = &self.ctx.inner;
        let d = &inner.device;
        let pipeline = self.ctx.pipeline(key)?;
        let dispatches = plan_dispatches(count, self.ctx.limits());
        let sets = sets.sets.clone();
        for (set, dp) in sets.iter().zip(&dispatches) {
            let (first, c) = (dp.first_ray, u64::from(dp.ray_count));
            let range = |b: &Buffer, stride| (b.raw, first * stride, c * stride);
            let [(r, ro, rl), (h, ho, hl), (k, ko, kl)] = [
                range(&s.rays, RAY_BYTES),
                range(&s.hits, HIT_BYTES),
                range(&s.counters, COUNTERS_BYTES),
            ];
            write_set(d, *set, &[(0, r, ro, rl), (1, h, ho, hl), (2, k, ko, kl)]);
        }
        let bvh_set = arrays.sets.sets[usize::from(key.traversal.is_wide())];
        let (timed, layout) = (inner.timestamp_period_ns.is_some(), inner.pipeline_layout);
        Ok(move |d: &ash::Device, cmd, queries| {
            let bind = vk::PipelineBindPoint::COMPUTE;
            let stamp = |stage, index| {
                // SAFETY: recording into the locked command buffer.
                unsafe { d.cmd_write_timestamp(cmd, stage, queries, index) }
            };
            // SAFETY: recording into the locked command buffer; every object belongs to
            // this device and outlives the submission.
            unsafe {
                if timed {
                    d.cmd_reset_query_pool(cmd, queries, 0, 2);
                    stamp(vk::PipelineStageFlags::TOP_OF_PIPE, 0);
                }
                d.cmd_bind_pipeline(cmd, bind, pipeline);
                d.cmd_bind_descriptor_sets(cmd, bind, layout, 0, &[bvh_set], &[]);
                for (set, dp) in sets.iter().zip(&dispatches) {
                    d.cmd_bind_descriptor_sets(cmd, bind, layout, 1, &[*set], &[]);
                    d.cmd_dispatch(cmd, dp.groups_x, dp.groups_y, 1);
                }
                if timed {
                    stamp(vk::PipelineStageFlags::BOTTOM_OF_PIPE, 1);
                }
                use vk::{AccessFlags as A, PipelineStageFlags as S};
                let (from, to) = (
                    (S::COMPUTE_SHADER, A::SHADER_WRITE),
                    (S::HOST, A::HOST_READ),
                );
                barrier(d, cmd, from, to);
            }
        })
    }

    /// The GPU time between the batch's two timestamps, milliseconds.
    fn gpu_ms(&self, queries: vk::QueryPool) -> Result<Option<f64>, TraceError> {
        let inner = &self.ctx.inner;
        let Some(period) = inner.timestamp_period_ns else {
            return Ok(None);
        };
        let mut ts = [0u64; 2];
        // SAFETY: both queries were written by the submission just waited for.
        unsafe {
            inner.device.get_query_pool_results(
                queries,
                0,
                &mut ts,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .map_err(vkerr("reading timestamps"))?;
        let mask = inner.timestamp_mask;
        let ticks = (ts[1] & mask).wrapping_sub(ts[0] & mask) & mask;
        Ok(Some(ticks as f64 * period * 1e-6))
    }
}

/// A ray batch submitted and waited for: its hits are in the scratch's mapped buffers.
pub struct Waited {
    count: u64,
    start: Instant,
    submitted: Instant,
    done: Instant,
    gpu_ms: Option<f64>,
}

impl DeviceApi for Ash {
    type Arrays = Arrays;
    type Scratch = Scratch;
    type Submitted = Waited;

    fn name(&self) -> &'static str {
        "vulkan"
    }

    fn device_name(&self) -> String {
        let i = self.ctx.device_info();
        let (major, minor, _) = i.api_version;
        format!("{} ({:?}, Vulkan {major}.{minor})", i.name, i.kind)
    }

    fn limits(&self) -> &DeviceLimits {
        self.ctx.limits()
    }

    fn tuning(&self) -> &DriverTuning {
        self.ctx.tuning()
    }

    fn has_timestamps(&self) -> bool {
        self.ctx.inner.timestamp_period_ns.is_some()
    }

    fn features(&self) -> BackendFeatures {
        self.ctx.features()
    }

    fn prepare_kernel(&self, key: KernelKey) -> Result<(), TraceError> {
        self.ctx.pipeline(key).map(|_| ())
    }

    fn create_arrays(
        &self,
        _layout: ArraysLayout,
        arrays: &[DeviceArray<'_>],
    ) -> Result<Arrays, TraceError> {
        let slots = self.ctx.page_slots();
        if let Some(a) = arrays.iter().find(|a| a.page >= slots) {
            return Err(too_many_buffers(
                u64::from(self.ctx.limits().max_storage_buffers_per_shader_stage),
                8 + 3 * u64::from(a.page),
                "a tree split into pages of one binding each",
            ));
        }
        let zero = [bvhtrace_core::FlatInstance::zeroed()];
        let mut named: Vec<(&'static str, &[u8])> = vec![("filler", bytemuck::cast_slice(&zero))];
        named.extend(arrays.iter().map(|a| (a.name(), &*a.bytes)));
        let mut made = device_buffers(&self.ctx, "uploading the BVH", &named)?.into_iter();
        let filler = made
            .next()
            .unwrap_or_else(|| unreachable!("a buffer per array"));
        let buffers = arrays.iter().map(|a| (a.role, a.page)).zip(made).collect();
        let out = Arrays {
            buffers,
            filler,
            sets: Sets::new(&self.ctx, 0, 2)?,
        };
        out.bind();
        Ok(out)
    }

    fn write_arrays(
        &self,
        arrays: &mut Arrays,
        _layout: ArraysLayout,
        writes: &[ArrayWrite<'_>],
    ) -> Result<(), TraceError> {
        let (copies, remake): (Vec<_>, Vec<_>) = writes
            .iter()
            .partition(|w| !w.replace && arrays.has(w.array.role, w.array.page));
        let copies: Vec<(vk::Buffer, &[u8])> = copies
            .iter()
            .map(|w| (arrays.raw(w.array.role, w.array.page), &*w.array.bytes))
            .collect();
        copy_to_device(&self.ctx, "updating the BVH", &copies)?;
        if remake.is_empty() {
            return Ok(());
        }
        let named: Vec<(&'static str, &[u8])> = remake
            .iter()
            .map(|w| (w.array.name(), &*w.array.bytes))
            .collect();
        let made = device_buffers(&self.ctx, "updating the BVH", &named)?;
        for (w, b) in remake.iter().zip(made) {
            let at = (w.array.role, w.array.page);
            // Every submission that read the old buffer has completed: it may drop.
            if let Some(i) = arrays.buffers.iter().position(|(r, _)| *r == at) {
                arrays.buffers[i] = (at, b);
            } else {
                arrays.buffers.push((at, b));
            }
        }
        arrays.bind();
        Ok(())
    }

    fn create_scratch(&self, plan: &ScratchPlan) -> Result<Scratch, TraceError> {
        Scratch::new(&self.ctx, plan.capacity)
    }

    // The submission is waited for on its fence: ready when first polled.
    // Each submission is waited for here: the hits are in the mapped scratch when
    // `finish_batch` reads them.
    fn submit_batch(
        &self,
        arrays: &Arrays,
        s: &Scratch,
        batch: Batch<'_>,
    ) -> Result<Waited, TraceError> {
        let start = Instant::now();
        let count = batch.rays.len() as u64;
        let sub = self.ctx.submitter()?;
        s.rays.write(bytemuck::cast_slice(batch.rays));
        let dispatches = plan_dispatches(count, self.ctx.limits()).len() as u32;
        // Dropped after the submission reading them was waited for.
        let sets = Sets::new(&self.ctx, 1, dispatches)?;
        let record = self.dispatch(arrays, s, batch.key, count, &sets)?;
        let queries = sub.queries;
        // The command buffer is recorded inside the submission: its time is the device's.
        let submitted = Instant::now();
        self.ctx
            .submit_and_wait(&sub, "tracing a ray batch", |d, cmd| {
                record(d, cmd, queries)
            })?;
        Ok(Waited {
            count,
            start,
            submitted,
            done: Instant::now(),
            gpu_ms: self.gpu_ms(queries)?,
        })
    }

    async fn finish_batch<'a>(
        &'a self,
        s: &'a Scratch,
        w: Waited,
        out: BatchOut<'a>,
    ) -> Result<BatchTimes, TraceError> {
        s.hits.read_into((w.count * HIT_BYTES) as usize, out.hits);
        if let Some(c) = out.counters {
            s.counters.read_into((w.count * COUNTERS_BYTES) as usize, c);
        }
        Ok(BatchTimes {
            gpu_ms: w.gpu_ms,
            phases: TracePhases::since(w.start, w.submitted, w.done),
        })
    }
}

/// A [`FlatBvh`] uploaded to a [`VkContext`]'s device as storage buffers (nodes, triangles,
/// escapes, instances: the layout of [`bvhtrace_core::flat`], byte for byte), and the wide
/// layout for [`Traversal::Wide`]. Implements [`Tracer`], the interface shared with the CPU
/// and wgpu backends, through the engine ([`Engine`]) every device backend shares
/// ([`HasEngine::engine`] gives it, for what only a backend implementer asks of it).
pub struct VkBvh {
    engine: Engine<Ash>,
}

impl HasEngine for VkBvh {
    type Device = Ash;
    fn engine(&self) -> &Engine<Ash> {
        &self.engine
    }
    fn engine_mut(&mut self) -> &mut Engine<Ash> {
        &mut self.engine
    }
}

impl std::fmt::Debug for VkBvh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VkBvh")
            .field("tree", self.engine.tree())
            .field("stats", self.engine.stats())
            .finish()
    }
}

impl VkBvh {
    /// Uploads `bvh` as `opts` says, to device-local storage buffers (through one
    /// host-visible staging buffer), by the rules every backend follows
    /// ([`Engine::upload`]: the arrays the listed walks read, the wide layout collapsed
    /// when a wide walk is listed and the tree has none; the limits are
    /// `maxStorageBufferRange` and `maxMemoryAllocationSize`). [`BvhStorage::Textures`] is
    /// a [`TraceError::MissingFeature`]: this backend has buffers only.
    /// [`UploadOptions::fitting`] uploads for every walk the tree can take.
    pub fn upload(
        ctx: &VkContext,
        bvh: &FlatBvh,
        opts: &UploadOptions,
    ) -> Result<VkBvh, TraceError> {
        let backend = Ash { ctx: ctx.clone() };
        Ok(VkBvh {
            engine: Engine::upload(backend, bvh, opts)?,
        })
    }

    /// What the upload holds: one mesh or two levels, masks, layouts, depth.
    pub fn tree(&self) -> &UploadedTree {
        self.engine.tree()
    }

    /// What the upload holds and cost (both layouts together).
    pub fn stats(&self) -> &UploadStats {
        self.engine.stats()
    }

    /// The context this BVH lives on.
    pub fn context(&self) -> &VkContext {
        &self.engine.device().ctx
    }
}
