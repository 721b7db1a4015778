//! The BVH built on the device, in WGSL compute, written straight into the flat layout
//! every walk reads and read back as a [`FlatBvh`], so the CPU walks, the checks and every
//! upload take it as they take a CPU-built tree.
//!
//! The builders' host side (upload, sort, linear BVH, clustering loop, read back, timing)
//! is [`bvhtrace_engine::builder`], shared with the ash backend; this module gives it
//! wgpu's buffers, bind groups, compute passes and mappings ([`BuildDevice`]). The
//! programs that move a built tree's vertices (refit, skinning, morph targets) and the
//! top level's rebuild are here too.

mod morph;
mod refit;
mod skin;
mod top;

pub use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes, GpuBuilderKind};
pub use morph::GpuMorph;
pub use refit::{GpuRefit, RefitTimes, RefitVertices};
pub use skin::GpuSkin;

use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_engine::TraceError;
use bvhtrace_engine::builder::{BufferKind, BuildDevice, Dispatch, Grid, Read, ReadDone};
use bvhtrace_engine::plan::DeviceLimits;
use wgpu::util::DeviceExt;

use crate::trace::{map_all, read_mapped};
use crate::{GpuContext, GpuError};
use web_time::Instant;

pub(crate) use bvhtrace_engine::builder::{PARAMS_STRIDE, grid};

/// The timestamp queries around each step, the name of each pair, and the buffers they
/// are read through.
struct StepQueries {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
    names: std::cell::RefCell<Vec<&'static str>>,
    pairs: u32,
}

impl StepQueries {
    fn new(device: &wgpu::Device, pairs: u32) -> StepQueries {
        let bytes = 16 * u64::from(pairs);
        let buffer = |usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("build timestamps"),
                size: bytes,
                usage,
                mapped_at_creation: false,
            })
        };
        use wgpu::BufferUsages as U;
        StepQueries {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("build steps"),
                ty: wgpu::QueryType::Timestamp,
                count: 2 * pairs,
            }),
            resolve: buffer(U::QUERY_RESOLVE | U::COPY_SRC),
            read: buffer(U::MAP_READ | U::COPY_DST),
            names: Default::default(),
            pairs,
        }
    }

    /// The next pair's writes, named `name`; `None` once every pair is taken.
    fn writes(&self, name: &'static str) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        let mut names = self.names.borrow_mut();
        let k = names.len() as u32;
        (k < self.pairs).then(|| {
            names.push(name);
            self.writes_at(k)
        })
    }

    /// Pair `k`'s writes around a pass.
    fn writes_at(&self, k: u32) -> wgpu::ComputePassTimestampWrites<'_> {
        wgpu::ComputePassTimestampWrites {
            query_set: &self.set,
            beginning_of_pass_write_index: Some(2 * k),
            end_of_pass_write_index: Some(2 * k + 1),
        }
    }

    /// Resolves the pairs written so far into the read buffer.
    fn resolve(&self, enc: &mut wgpu::CommandEncoder) {
        self.resolve_pairs(enc, self.names.borrow().len() as u32);
    }

    /// Resolves the first `used` pairs into the read buffer.
    fn resolve_pairs(&self, enc: &mut wgpu::CommandEncoder, used: u32) {
        if used > 0 {
            enc.resolve_query_set(&self.set, 0..2 * used, &self.resolve, 0);
            enc.copy_buffer_to_buffer(&self.resolve, 0, &self.read, 0, 16 * u64::from(used));
        }
    }

    /// The milliseconds of each of the first `used` pairs, from the mapped read buffer
    /// (unmapped after).
    fn pairs_ms(&self, queue: &wgpu::Queue, used: u32) -> Result<Vec<f64>, GpuError> {
        let mut ticks: Vec<u64> = Vec::new();
        let got = read_mapped(&self.read, 16 * u64::from(used).max(1), &mut ticks);
        self.read.unmap();
        got?;
        let period = f64::from(queue.get_timestamp_period()) * 1e-6;
        Ok((0..used as usize)
            .map(|k| ticks[2 * k + 1].saturating_sub(ticks[2 * k]) as f64 * period)
            .collect())
    }

    fn bytes(&self) -> u64 {
        (16 * self.names.borrow().len() as u64).max(16)
    }

    /// Each step's milliseconds, pairs of one name summed, from the mapped read buffer
    /// (unmapped after).
    fn stages_ms(&self, queue: &wgpu::Queue) -> Result<Vec<(&'static str, f64)>, GpuError> {
        let names = self.names.borrow();
        let all = self.pairs_ms(queue, names.len() as u32)?;
        let mut out: Vec<(&'static str, f64)> = Vec::new();
        for (&ms, name) in all.iter().zip(names.iter()) {
            match out.iter_mut().find(|(n, _)| n == name) {
                Some((_, sum)) => *sum += ms,
                None => out.push((name, ms)),
            }
        }
        Ok(out)
    }
}

/// A buffer of `bytes` (at least 16), zeroed by wgpu.
fn empty(
    device: &wgpu::Device,
    label: &str,
    bytes: u64,
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16),
        usage,
        mapped_at_creation: false,
    })
}

fn init(
    device: &wgpu::Device,
    label: &str,
    contents: &[u8],
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents,
        usage,
    })
}

/// Submits `enc` (a failure named `during`) and resolves once each of `maps` (a buffer and
/// its first bytes) is mapped for reading. In a browser the mappings complete on the event
/// loop, and an error of the work before (a program the browser's compiler rejected, an
/// upload) is reported here, ahead of a failed mapping.
async fn submit_and_map_async(
    ctx: &GpuContext,
    during: &'static str,
    enc: wgpu::CommandEncoder,
    maps: &[(&wgpu::Buffer, u64)],
) -> Result<(), GpuError> {
    let index = ctx.scoped(during, || ctx.queue().submit([enc.finish()]))?;
    let mapped = map_all(ctx, index, maps).await;
    ctx.deferred_errors().await?;
    mapped
}

/// [`submit_and_map_async`], waited for (blocks: not for a browser).
fn submit_and_map(
    ctx: &GpuContext,
    during: &'static str,
    enc: wgpu::CommandEncoder,
    maps: &[(&wgpu::Buffer, u64)],
) -> Result<(), GpuError> {
    pollster::block_on(submit_and_map_async(ctx, during, enc, maps))
}

/// After the work recorded in `enc`: the first bytes of each of `sources`, one after the
/// other, copied into one read-back buffer, submitted, waited for and returned (the
/// builder's read back, [`BuildDevice::submit_and_read`], waited for).
fn read_after(
    ctx: &GpuContext,
    during: &'static str,
    enc: wgpu::CommandEncoder,
    sources: &[(&wgpu::Buffer, u64)],
) -> Result<Vec<u8>, GpuError> {
    Ok(pollster::block_on(read_after_async(ctx, during, enc, sources))?.concat())
}

/// [`read_after`] as a future, each source's bytes apart (`GpuContext::read_buffers`).
pub(crate) async fn read_after_async(
    ctx: &GpuContext,
    during: &'static str,
    enc: wgpu::CommandEncoder,
    sources: &[(&wgpu::Buffer, u64)],
) -> Result<Vec<Vec<u8>>, GpuError> {
    let mut parts: Vec<Vec<u8>> = sources.iter().map(|&(_, n)| vec![0; n as usize]).collect();
    let mut reads: Vec<Read<'_, wgpu::Buffer>> = sources
        .iter()
        .zip(&mut parts)
        .map(|(&(buffer, _), into)| Read { buffer, into })
        .collect();
    let dev = Wgpu(ctx);
    dev.submit_and_read(enc, during, &mut reads, None).await?;
    drop(reads);
    Ok(parts)
}

/// The wgpu side of the device builder: buffers, bind groups, compute passes (with
/// timestamp writes) and mappings on a [`GpuContext`].
struct Wgpu<'a>(&'a GpuContext);

impl BuildDevice for Wgpu<'_> {
    type Buffer = wgpu::Buffer;
    type Program = Vec<wgpu::ComputePipeline>;
    type Bound = wgpu::BindGroup;
    type Recording = wgpu::CommandEncoder;
    type Timer = StepQueries;

    fn limits(&self) -> &DeviceLimits {
        self.0.limits()
    }

    fn storage_buffers_per_stage(&self) -> u32 {
        self.0
            .device()
            .limits()
            .max_storage_buffers_per_shader_stage
    }

    fn program(&self, kind: GpuBuilderKind) -> Result<Self::Program, TraceError> {
        self.0.build_pipelines(kind)
    }

    fn buffer(
        &self,
        label: &'static str,
        kind: BufferKind,
        bytes: u64,
        contents: Option<&[u8]>,
    ) -> Result<wgpu::Buffer, TraceError> {
        use wgpu::BufferUsages as U;
        let usage = match kind {
            BufferKind::Uniform => U::UNIFORM,
            BufferKind::Storage => U::STORAGE | U::COPY_SRC,
            BufferKind::Indirect => U::STORAGE | U::INDIRECT,
        };
        let device = self.0.device();
        self.0.scoped("uploading a build", || match contents {
            None => empty(device, label, bytes, usage),
            Some(c) if c.len() as u64 >= bytes.max(16) => init(device, label, c, usage),
            Some(c) => {
                let mut padded = c.to_vec();
                padded.resize(bytes.max(16) as usize, 0);
                init(device, label, &padded, usage)
            }
        })
    }

    fn bind(
        &self,
        program: &Self::Program,
        entry: usize,
        bindings: &[bvhtrace_engine::builder::Binding<'_, wgpu::Buffer>],
    ) -> Result<wgpu::BindGroup, TraceError> {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = bindings
            .iter()
            .map(|b| wgpu::BindGroupEntry {
                binding: b.binding,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: b.buffer,
                    offset: b.offset,
                    size: b.size.and_then(std::num::NonZeroU64::new),
                }),
            })
            .collect();
        let pipeline = program.get(entry).ok_or(TraceError::Device {
            during: "binding a device build",
            message: format!("no entry point {entry}"),
        })?;
        Ok(self
            .0
            .device()
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("device build"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            }))
    }

    fn timer(&self, pairs: u32) -> Result<Option<StepQueries>, TraceError> {
        Ok(self
            .0
            .has_timestamps()
            .then(|| StepQueries::new(self.0.device(), pairs)))
    }

    fn begin(&self) -> Result<wgpu::CommandEncoder, TraceError> {
        Ok(self.0.device().create_command_encoder(&Default::default()))
    }

    fn pass(
        &self,
        rec: &mut wgpu::CommandEncoder,
        program: &Self::Program,
        timed: Option<(&StepQueries, u32)>,
        dispatches: &[Dispatch<'_, Self>],
    ) {
        let timestamp_writes = timed.map(|(q, k)| q.writes_at(k));
        let mut pass = rec.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("device build"),
            timestamp_writes,
        });
        for d in dispatches {
            pass.set_pipeline(&program[d.entry]);
            pass.set_bind_group(0, d.bound, &[]);
            match d.grid {
                Grid::Groups(x, y) => pass.dispatch_workgroups(x, y, 1),
                Grid::Indirect(args, offset) => pass.dispatch_workgroups_indirect(args, offset),
            }
        }
    }

    async fn submit_and_read<'a, 'b: 'a>(
        &'a self,
        mut enc: wgpu::CommandEncoder,
        during: &'static str,
        reads: &'a mut [Read<'b, wgpu::Buffer>],
        timer: Option<(&'a StepQueries, u32)>,
    ) -> Result<ReadDone, TraceError> {
        let ctx = self.0;
        let total: u64 = reads.iter().map(|r| r.into.len() as u64).sum();
        let usage = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
        let read = empty(ctx.device(), "read back", total.max(4), usage);
        let mut at = 0;
        for r in reads.iter() {
            let n = r.into.len() as u64;
            enc.copy_buffer_to_buffer(r.buffer, 0, &read, at, n);
            at += n;
        }
        let timer = timer.filter(|(_, used)| *used > 0);
        if let Some((q, used)) = timer {
            q.resolve_pairs(&mut enc, used);
        }
        let mut maps = vec![(&read, total.max(4))];
        maps.extend(timer.map(|(q, used)| (&q.read, 16 * u64::from(used))));
        submit_and_map_async(ctx, during, enc, &maps).await?;
        let copying = Instant::now();
        let got = read
            .slice(..)
            .get_mapped_range()
            .map_err(|e| GpuError::device("reading results back", e))
            .map(|view| {
                let mut at = 0usize;
                for r in reads.iter_mut() {
                    let n = r.into.len();
                    r.into.copy_from_slice(&view[at..at + n]);
                    at += n;
                }
            });
        read.unmap();
        got?;
        let copy_ms = copying.elapsed().as_secs_f64() * 1e3;
        let pairs_ms = match timer {
            Some((q, used)) => q.pairs_ms(ctx.queue(), used)?,
            None => Vec::new(),
        };
        Ok(ReadDone { pairs_ms, copy_ms })
    }
}

impl GpuContext {
    /// Builds a BVH over `tris` on the device with `opts` and reads it back (`prim` the
    /// triangle's index in `tris`), with the time of each step. The tree passes
    /// [`FlatBvh::check_invariants`]; build its escape links or wide layout on the CPU as
    /// for any tree. One triangle is built on the CPU (there is nothing to sort); no
    /// triangle is [`TraceError::EmptyBvh`]; a non-finite corner, an option out of range,
    /// more triangles than the device's buffers hold, or a device with fewer than
    /// [`bvhtrace_engine::programs::BUILD_STORAGE_BUFFERS`] storage buffers per stage, an
    /// error naming it. The pipelines are compiled on a builder's first build and kept.
    ///
    /// This waits for the device, so it is an error in a browser, where a page must not
    /// block: await [`GpuContext::build_bvh_async`] there.
    pub fn build_bvh(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), GpuError> {
        if cfg!(target_arch = "wasm32") {
            // Blocking would stop the browser's event loop, which completes the read back.
            return Err(TraceError::Device {
                during: "building a BVH on the device",
                message: "a browser cannot wait for its GPU: use build_bvh_async".into(),
            });
        }
        pollster::block_on(self.build_bvh_async(tris, opts))
    }

    /// [`GpuContext::build_bvh`] as a future: the same build, the same tree and errors,
    /// awaiting the device instead of waiting for it. What a program in a browser
    /// awaits; natively the future waits for the device when polled.
    pub async fn build_bvh_async(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), GpuError> {
        bvhtrace_engine::builder::build_bvh(&Wgpu(self), tris, opts).await
    }

    /// [`GpuContext::build_bvh`] with the linear BVH ([`GpuBuilderKind::Lbvh`]).
    pub fn build_lbvh(&self, tris: &[Triangle]) -> Result<(FlatBvh, GpuBuildTimes), GpuError> {
        self.build_bvh(tris, &GpuBuildOptions::with_builder(GpuBuilderKind::Lbvh))
    }
}
