//! The device BVH builders on ash: [`bvhtrace_engine::builder`]'s host side (the one the
//! wgpu backend runs) over Vulkan buffers, descriptor sets, compute pipelines from the
//! builders' WGSL (through naga, as the trace kernels) and one command buffer.

use std::cell::RefCell;
use std::future::Future;
use std::sync::Arc;

use ash::vk;
use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_engine::TraceError;
use bvhtrace_engine::builder::{
    Binding, BufferKind, BuildDevice, Dispatch, GpuBuildOptions, GpuBuildTimes, GpuBuilderKind,
    Grid, Read, ReadDone,
};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::spirv::{self, EntryBinding};

use crate::VkContext;
use crate::context::compute_pipeline;
use crate::context::{Buffer, barrier};
use crate::error::vkerr;

/// One entry point of a builder: its pipeline, layouts and the group-0 buffers it binds.
pub(crate) struct BuildEntry {
    pipeline: vk::Pipeline,
    layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
    bindings: Vec<EntryBinding>,
}

/// A builder's entry points, in [`GpuBuilderKind::entries`] order; destroyed with the
/// context ([`destroy_program`]).
pub(crate) struct BuildProgram {
    entries: Vec<BuildEntry>,
}

/// Destroys what `program` holds.
///
/// # Safety
/// Made on `d`; no submission using it is pending.
pub(crate) unsafe fn destroy_program(d: &ash::Device, program: &BuildProgram) {
    // SAFETY: the caller's.
    unsafe {
        for e in &program.entries {
            d.destroy_pipeline(e.pipeline, None);
            d.destroy_pipeline_layout(e.layout, None);
            d.destroy_descriptor_set_layout(e.set_layout, None);
        }
    }
}

fn descriptor_type(b: &EntryBinding) -> vk::DescriptorType {
    match b.uniform {
        true => vk::DescriptorType::UNIFORM_BUFFER,
        false => vk::DescriptorType::STORAGE_BUFFER,
    }
}

impl VkContext {
    /// Builds a BVH over `tris` on this device with `opts` and reads it back: the same
    /// builders, host side and WGSL as `bvhtrace_gpu::GpuContext::build_bvh`, so the same
    /// tree on the same device, node for node. The tree passes
    /// [`FlatBvh::check_invariants`]. One triangle is built on the CPU; no triangle is
    /// [`TraceError::EmptyBvh`]; a non-finite corner, an option out of range or more
    /// triangles than the device's buffers hold, an error naming it. The pipelines are
    /// compiled on a builder's first build and kept.
    pub fn build_bvh(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
        let dev = AshBuild {
            ctx: self,
            pending: RefCell::default(),
        };
        bvhtrace_engine::builder::build_bvh_blocking(&dev, tris, opts)
    }

    /// The entry points of builder `kind`, compiled on first use and kept.
    fn build_program(&self, kind: GpuBuilderKind) -> Result<Arc<BuildProgram>, TraceError> {
        let mut cache = self
            .inner
            .build_programs
            .lock()
            .map_err(|_| TraceError::Poisoned("build programs"))?;
        if let Some(p) = cache.get(kind.name()) {
            return Ok(p.clone());
        }
        let entries: Vec<&'static str> = kind.entries().collect();
        let inner = &self.inner;
        let compiled =
            spirv::program(&kind.source(), &entries, &inner.spirv, inner.zero_workgroup)?;
        let mut program = BuildProgram {
            entries: Vec::new(),
        };
        for entry in &compiled {
            match self.build_entry(entry) {
                Ok(e) => program.entries.push(e),
                Err(err) => {
                    // SAFETY: made just now on this device, never submitted.
                    unsafe { destroy_program(&self.inner.device, &program) };
                    return Err(err);
                }
            }
        }
        let program = Arc::new(program);
        cache.insert(kind.name(), program.clone());
        Ok(program)
    }

    /// One entry point's set layout (its group-0 buffers), pipeline layout and pipeline.
    fn build_entry(&self, entry: &spirv::EntrySpirv) -> Result<BuildEntry, TraceError> {
        let d = &self.inner.device;
        let bindings: Vec<vk::DescriptorSetLayoutBinding> = entry
            .bindings
            .iter()
            .map(|b| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(b.binding)
                    .descriptor_type(descriptor_type(b))
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE)
            })
            .collect();
        let mut out = BuildEntry {
            pipeline: vk::Pipeline::null(),
            layout: vk::PipelineLayout::null(),
            set_layout: vk::DescriptorSetLayout::null(),
            bindings: entry.bindings.clone(),
        };
        // SAFETY: plain object creation on this device; on failure what was made is
        // destroyed (null handles are ignored); the module is destroyed right after the
        // pipeline is made from it.
        unsafe {
            let made = (|| -> Result<(), TraceError> {
                out.set_layout = d
                    .create_descriptor_set_layout(
                        &vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings),
                        None,
                    )
                    .map_err(vkerr("creating a builder's set layout"))?;
                let set_layouts = [out.set_layout];
                out.layout = d
                    .create_pipeline_layout(
                        &vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts),
                        None,
                    )
                    .map_err(vkerr("creating a builder's pipeline layout"))?;
                out.pipeline = compute_pipeline(d, &entry.words, entry.name, out.layout)?;
                Ok(())
            })();
            if let Err(e) = made {
                destroy_program(d, &BuildProgram { entries: vec![out] });
                return Err(e);
            }
        }
        Ok(out)
    }
}

/// A descriptor set for one entry point, in a pool of its own, destroyed when dropped.
pub(crate) struct Bound {
    ctx: VkContext,
    pool: vk::DescriptorPool,
    set: vk::DescriptorSet,
}

impl Drop for Bound {
    fn drop(&mut self) {
        // SAFETY: every submission using the set was waited for before its call returned.
        unsafe {
            self.ctx
                .inner
                .device
                .destroy_descriptor_pool(self.pool, None)
        };
    }
}

/// Timestamp queries in pairs, destroyed when dropped.
pub(crate) struct Timer {
    ctx: VkContext,
    pool: vk::QueryPool,
}

impl Drop for Timer {
    fn drop(&mut self) {
        // SAFETY: every submission writing the queries was waited for.
        unsafe { self.ctx.inner.device.destroy_query_pool(self.pool, None) };
    }
}

/// A recorded command, replayed into the command buffer when submitted.
pub(crate) enum Cmd {
    /// A dispatch: pipeline, its layout, the set bound, the workgroups.
    Dispatch {
        pipeline: vk::Pipeline,
        layout: vk::PipelineLayout,
        set: vk::DescriptorSet,
        grid: VkGrid,
    },
    /// A timestamp into query `index` of `pool`, at the top (start) or bottom (end).
    Stamp {
        pool: vk::QueryPool,
        index: u32,
        end: bool,
    },
}

/// A dispatch's workgroups: counts, or read from a buffer at an offset.
pub(crate) enum VkGrid {
    Groups(u32, u32),
    Indirect(vk::Buffer, u64),
}

/// What the next submission starts with: buffers to zero, staging copies
/// `(staging, destination, bytes)` (the staging buffers kept until then), query pools to
/// reset.
#[derive(Default)]
struct Pending {
    zero: Vec<vk::Buffer>,
    copies: Vec<(vk::Buffer, vk::Buffer, u64)>,
    staging: Vec<Buffer>,
    resets: Vec<(vk::QueryPool, u32)>,
}

/// One build on a [`VkContext`]: what [`bvhtrace_engine::builder::build_bvh`] needs of
/// the device.
struct AshBuild<'a> {
    ctx: &'a VkContext,
    pending: RefCell<Pending>,
}

impl AshBuild<'_> {
    /// Records the pending start of a submission, then `cmds`, each dispatch followed by
    /// a barrier, into `cmd`.
    ///
    /// # Safety
    /// `cmd` is recording, on this device; every object named outlives the submission.
    unsafe fn record(
        &self,
        d: &ash::Device,
        cmd: vk::CommandBuffer,
        pending: &Pending,
        cmds: &[Cmd],
    ) {
        use vk::{AccessFlags as A, PipelineStageFlags as S};
        let compute = (S::COMPUTE_SHADER, A::SHADER_WRITE);
        let next = (
            S::COMPUTE_SHADER | S::DRAW_INDIRECT,
            A::SHADER_READ | A::SHADER_WRITE | A::INDIRECT_COMMAND_READ | A::UNIFORM_READ,
        );
        let bind = vk::PipelineBindPoint::COMPUTE;
        // SAFETY: the caller's.
        unsafe {
            for &b in &pending.zero {
                d.cmd_fill_buffer(cmd, b, 0, vk::WHOLE_SIZE, 0);
            }
            for &(src, dst, size) in &pending.copies {
                let region = [vk::BufferCopy {
                    src_offset: 0,
                    dst_offset: 0,
                    size,
                }];
                d.cmd_copy_buffer(cmd, src, dst, &region);
            }
            for &(pool, count) in &pending.resets {
                d.cmd_reset_query_pool(cmd, pool, 0, count);
            }
            barrier(d, cmd, (S::TRANSFER, A::TRANSFER_WRITE), next);
            for c in cmds {
                match *c {
                    Cmd::Dispatch {
                        pipeline,
                        layout,
                        set,
                        ref grid,
                    } => {
                        d.cmd_bind_pipeline(cmd, bind, pipeline);
                        d.cmd_bind_descriptor_sets(cmd, bind, layout, 0, &[set], &[]);
                        match *grid {
                            VkGrid::Groups(x, y) => d.cmd_dispatch(cmd, x, y, 1),
                            VkGrid::Indirect(b, offset) => d.cmd_dispatch_indirect(cmd, b, offset),
                        }
                        barrier(d, cmd, compute, next);
                    }
                    Cmd::Stamp { pool, index, end } => {
                        let stage = match end {
                            true => S::BOTTOM_OF_PIPE,
                            false => S::TOP_OF_PIPE,
                        };
                        d.cmd_write_timestamp(cmd, stage, pool, index);
                    }
                }
            }
            barrier(d, cmd, compute, (S::TRANSFER, A::TRANSFER_READ));
        }
    }

    /// [`BuildDevice::submit_and_read`], waited for.
    fn submit_blocking(
        &self,
        rec: Vec<Cmd>,
        during: &'static str,
        reads: &mut [Read<'_, Buffer>],
        timer: Option<(&Timer, u32)>,
    ) -> Result<ReadDone, TraceError> {
        use vk::MemoryPropertyFlags as M;
        let total: u64 = reads.iter().map(|r| r.into.len() as u64).sum();
        let read = self.ctx.buffer(
            "build read back",
            total,
            vk::BufferUsageFlags::TRANSFER_DST,
            M::HOST_VISIBLE | M::HOST_COHERENT,
            M::HOST_CACHED,
        )?;
        let pending = std::mem::take(&mut *self.pending.borrow_mut());
        let s = self.ctx.submitter()?;
        self.ctx.submit_and_wait(&s, during, |d, cmd| {
            // SAFETY: recording into the locked command buffer; the pending staging
            // buffers, the sets and the buffers outlive this call, which waits.
            unsafe {
                self.record(d, cmd, &pending, &rec);
                let mut at = 0;
                for r in reads.iter() {
                    let (src, n) = (r.buffer, r.into.len() as u64);
                    let region = [vk::BufferCopy {
                        src_offset: 0,
                        dst_offset: at,
                        size: n,
                    }];
                    d.cmd_copy_buffer(cmd, src.raw, read.raw, &region);
                    at += n;
                }
                use vk::{AccessFlags as A, PipelineStageFlags as S};
                barrier(
                    d,
                    cmd,
                    (S::TRANSFER, A::TRANSFER_WRITE),
                    (S::HOST, A::HOST_READ),
                );
            }
        })?;
        drop(s);
        drop(pending);
        let copying = std::time::Instant::now();
        let mut at = 0usize;
        for r in reads.iter_mut() {
            read.read_at(at, r.into);
            at += r.into.len();
        }
        let copy_ms = copying.elapsed().as_secs_f64() * 1e3;
        let pairs_ms = match timer {
            Some((t, used)) if used > 0 => self.pairs_ms(t, used)?,
            _ => Vec::new(),
        };
        Ok(ReadDone { pairs_ms, copy_ms })
    }

    /// The milliseconds of the first `used` pairs of `timer`.
    fn pairs_ms(&self, timer: &Timer, used: u32) -> Result<Vec<f64>, TraceError> {
        let inner = &self.ctx.inner;
        let period = inner.timestamp_period_ns.unwrap_or(0.0);
        let mut ticks = vec![0u64; 2 * used as usize];
        // SAFETY: every query was written by a submission waited for.
        unsafe {
            inner.device.get_query_pool_results(
                timer.pool,
                0,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .map_err(vkerr("reading timestamps"))?;
        let mask = inner.timestamp_mask;
        Ok(ticks
            .chunks_exact(2)
            .map(|p| ((p[1] & mask).wrapping_sub(p[0] & mask) & mask) as f64 * period * 1e-6)
            .collect())
    }
}

impl BuildDevice for AshBuild<'_> {
    type Buffer = Buffer;
    type Program = Arc<BuildProgram>;
    type Bound = Bound;
    type Recording = Vec<Cmd>;
    type Timer = Timer;

    fn limits(&self) -> &DeviceLimits {
        self.ctx.limits()
    }

    fn storage_buffers_per_stage(&self) -> u32 {
        self.ctx.inner.storage_buffers_per_stage
    }

    fn program(&self, kind: GpuBuilderKind) -> Result<Arc<BuildProgram>, TraceError> {
        self.ctx.build_program(kind)
    }

    fn buffer(
        &self,
        label: &'static str,
        kind: BufferKind,
        bytes: u64,
        contents: Option<&[u8]>,
    ) -> Result<Buffer, TraceError> {
        use vk::BufferUsageFlags as U;
        use vk::MemoryPropertyFlags as M;
        let usage = U::TRANSFER_DST
            | match kind {
                BufferKind::Uniform => U::UNIFORM_BUFFER,
                BufferKind::Storage => U::STORAGE_BUFFER | U::TRANSFER_SRC,
                BufferKind::Indirect => U::STORAGE_BUFFER | U::INDIRECT_BUFFER,
            };
        let b = self
            .ctx
            .buffer(label, bytes, usage, M::DEVICE_LOCAL, M::empty())?;
        let mut pending = self.pending.borrow_mut();
        match contents {
            None => pending.zero.push(b.raw),
            Some(c) => {
                let mut data = c.to_vec();
                data.resize(b.size as usize, 0);
                let host = M::HOST_VISIBLE | M::HOST_COHERENT;
                let staging =
                    self.ctx
                        .buffer("staging", b.size, U::TRANSFER_SRC, host, M::empty())?;
                staging.write(&data);
                pending.copies.push((staging.raw, b.raw, b.size));
                pending.staging.push(staging);
            }
        }
        Ok(b)
    }

    fn bind(
        &self,
        program: &Arc<BuildProgram>,
        entry: usize,
        bindings: &[Binding<'_, Buffer>],
    ) -> Result<Bound, TraceError> {
        let e = program.entries.get(entry).ok_or(TraceError::Device {
            during: "binding a device build",
            message: format!("no entry point {entry}"),
        })?;
        let d = &self.ctx.inner.device;
        let uniforms = e.bindings.iter().filter(|b| b.uniform).count() as u32;
        let storage = e.bindings.len() as u32 - uniforms;
        let sizes: Vec<vk::DescriptorPoolSize> = [
            (vk::DescriptorType::UNIFORM_BUFFER, uniforms),
            (vk::DescriptorType::STORAGE_BUFFER, storage),
        ]
        .into_iter()
        .filter(|(_, n)| *n > 0)
        .map(|(ty, descriptor_count)| vk::DescriptorPoolSize {
            ty,
            descriptor_count,
        })
        .collect();
        let info = vk::DescriptorPoolCreateInfo::default()
            .max_sets(1)
            .pool_sizes(&sizes);
        // SAFETY: plain object creation; dropping `out` destroys the pool and its set.
        let mut out = Bound {
            ctx: self.ctx.clone(),
            pool: unsafe { d.create_descriptor_pool(&info, None) }
                .map_err(vkerr("creating a descriptor pool"))?,
            set: vk::DescriptorSet::null(),
        };
        let layouts = [e.set_layout];
        let info = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(out.pool)
            .set_layouts(&layouts);
        // SAFETY: allocating from the pool just made, sized for this set.
        out.set = unsafe { d.allocate_descriptor_sets(&info) }
            .map_err(vkerr("allocating a descriptor set"))?[0];
        let used: Vec<(&EntryBinding, &Binding<'_, Buffer>)> = e
            .bindings
            .iter()
            .filter_map(|eb| Some((eb, bindings.iter().find(|b| b.binding == eb.binding)?)))
            .collect();
        let infos: Vec<[vk::DescriptorBufferInfo; 1]> = used
            .iter()
            .map(|(_, b)| {
                [vk::DescriptorBufferInfo {
                    buffer: b.buffer.raw,
                    offset: b.offset,
                    range: b.size.unwrap_or(vk::WHOLE_SIZE),
                }]
            })
            .collect();
        let writes: Vec<vk::WriteDescriptorSet> = used
            .iter()
            .zip(&infos)
            .map(|((eb, _), info)| {
                vk::WriteDescriptorSet::default()
                    .dst_set(out.set)
                    .dst_binding(eb.binding)
                    .descriptor_type(descriptor_type(eb))
                    .buffer_info(info)
            })
            .collect();
        // SAFETY: the set and buffers belong to this device; the set is not in use.
        unsafe { d.update_descriptor_sets(&writes, &[]) };
        Ok(out)
    }

    fn timer(&self, pairs: u32) -> Result<Option<Timer>, TraceError> {
        if !self.ctx.has_timestamps() || pairs == 0 {
            return Ok(None);
        }
        let d = &self.ctx.inner.device;
        let info = vk::QueryPoolCreateInfo::default()
            .query_type(vk::QueryType::TIMESTAMP)
            .query_count(2 * pairs);
        // SAFETY: plain object creation on this device.
        let pool = unsafe { d.create_query_pool(&info, None) }
            .map_err(vkerr("creating a timestamp query pool"))?;
        self.pending.borrow_mut().resets.push((pool, 2 * pairs));
        Ok(Some(Timer {
            ctx: self.ctx.clone(),
            pool,
        }))
    }

    fn begin(&self) -> Result<Vec<Cmd>, TraceError> {
        Ok(Vec::new())
    }

    fn pass(
        &self,
        rec: &mut Vec<Cmd>,
        program: &Arc<BuildProgram>,
        timed: Option<(&Timer, u32)>,
        dispatches: &[Dispatch<'_, Self>],
    ) {
        let stamp = |index, end| {
            timed.map(|(t, k)| Cmd::Stamp {
                pool: t.pool,
                index: 2 * k + index,
                end,
            })
        };
        rec.extend(stamp(0, false));
        for dp in dispatches {
            let Some(e) = program.entries.get(dp.entry) else {
                continue;
            };
            rec.push(Cmd::Dispatch {
                pipeline: e.pipeline,
                layout: e.layout,
                set: dp.bound.set,
                grid: match dp.grid {
                    Grid::Groups(x, y) => VkGrid::Groups(x, y),
                    Grid::Indirect(b, offset) => VkGrid::Indirect(b.raw, offset),
                },
            });
        }
        rec.extend(stamp(1, true));
    }

    fn submit_and_read<'a, 'b: 'a>(
        &'a self,
        rec: Vec<Cmd>,
        during: &'static str,
        reads: &'a mut [Read<'b, Buffer>],
        timer: Option<(&'a Timer, u32)>,
    ) -> impl Future<Output = Result<ReadDone, TraceError>> + 'a {
        std::future::ready(self.submit_blocking(rec, during, reads, timer))
    }
}
