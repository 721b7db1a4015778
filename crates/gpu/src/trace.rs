//! Tracing ray batches: the convenience [`GpuBvh::trace`] (slices in, hits out, timed) and
//! [`GpuBvh::record`] (into the caller's encoder, with the caller's buffers).

use std::collections::HashMap;
use std::num::NonZeroU64;
use std::sync::mpsc;
use std::time::Instant;

use bvhtrace_core::{Ray, TraceOptions, TraceOutput, Traversal};
use bvhtrace_kernels::{
    COUNTERS_BYTES, DeviceLimits, HIT_BYTES, KernelKey, RAY_BYTES, RayInput, TEXEL_ROW, Tracer,
    finish_incomplete, plan_dispatches, plan_submissions, rays_per_dispatch, texel_rows,
};

use crate::GpuError;
use crate::bvh::GpuBvh;
use crate::context::GpuContext;

/// The caller's buffers for [`GpuBvh::record`]. Rays are read from offset 0 of `rays`
/// (32 bytes each, the layout of [`Ray`]); hits are written from offset 0 of `hits`
/// (16 bytes each) and counters from offset 0 of `counters` (8 bytes each). Each buffer
/// needs `STORAGE` usage and room for `ray_count` entries; any size is accepted: the batch
/// is split into dispatches within the device's limits.
#[derive(Clone, Copy, Debug)]
pub struct RayBatch<'a> {
    /// Rays in.
    pub rays: &'a wgpu::Buffer,
    /// Hits out.
    pub hits: &'a wgpu::Buffer,
    /// Counters out: required when `TraceOptions::counters` is set, ignored otherwise.
    pub counters: Option<&'a wgpu::Buffer>,
    /// Number of rays.
    pub ray_count: u64,
}

/// Device buffers reused by [`GpuBvh::trace`] across calls.
pub(crate) struct Scratch {
    capacity: u64,
    rays: RayStore,
    /// The hits' readback copy: `capacity` hits, or whole rows of the hit texture.
    hits_read: wgpu::Buffer,
    /// Allocated only once a trace asks for counters.
    counters: Option<CounterBuffers>,
    queries: Option<Queries>,
}

/// Where [`GpuBvh::trace`] uploads the rays and finds the hits ([`RayInput`]).
enum RayStore {
    /// Rays, and hits.
    Buffer(wgpu::Buffer, wgpu::Buffer),
    /// [`TEXEL_ROW`] texels wide: two texels per ray, one per hit
    /// (`entry_rays_texture.wgsl`).
    Texture(Box<RayTextures>),
}

/// The ray and hit textures of [`RayStore::Texture`], with their views.
struct RayTextures {
    rays: wgpu::Texture,
    rays_view: wgpu::TextureView,
    hits: wgpu::Texture,
    hits_view: wgpu::TextureView,
}

impl RayStore {
    fn bytes(&self) -> u64 {
        match self {
            RayStore::Buffer(r, h) => r.size() + h.size(),
            RayStore::Texture(t) => {
                let texels = |t: &wgpu::Texture| u64::from(t.width()) * u64::from(t.height());
                (texels(&t.rays) + texels(&t.hits)) * 16
            }
        }
    }

    fn binding(&self) -> RaysBinding<'_> {
        match self {
            RayStore::Buffer(rays, hits) => RaysBinding::Buffer { rays, hits },
            RayStore::Texture(t) => RaysBinding::Texture {
                rays: &t.rays_view,
                hits: &t.hits_view,
            },
        }
    }

    /// Records the copy of the first `count` hits into `read`: the first `count` hits of a
    /// buffer, or the rows of the hit texture that hold them (row-major, so the hits come
    /// first, in order).
    fn copy_hits(&self, encoder: &mut wgpu::CommandEncoder, read: &wgpu::Buffer, count: u64) {
        match self {
            RayStore::Buffer(_, hits) => {
                encoder.copy_buffer_to_buffer(hits, 0, read, 0, count * HIT_BYTES)
            }
            RayStore::Texture(t) => encoder.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: &t.hits,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: read,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(HIT_ROW_BYTES as u32),
                        rows_per_image: None,
                    },
                },
                wgpu::Extent3d {
                    width: TEXEL_ROW,
                    height: hit_rows(count) as u32,
                    depth_or_array_layers: 1,
                },
            ),
        }
    }

    /// Uploads `rays` to the start of the store.
    fn write(&self, queue: &wgpu::Queue, rays: &[Ray]) {
        match self {
            RayStore::Buffer(b, _) => queue.write_buffer(b, 0, bytemuck::cast_slice(rays)),
            RayStore::Texture(textures) => {
                let t = &textures.rays;
                // Whole rows, then the rest of the last row.
                let per_row = (TEXEL_ROW / 2) as usize;
                let full = rays.len() / per_row;
                for (row, part, width, height) in [
                    (0, &rays[..full * per_row], TEXEL_ROW, full as u32),
                    (
                        full as u32,
                        &rays[full * per_row..],
                        2 * (rays.len() % per_row) as u32,
                        1,
                    ),
                ] {
                    if part.is_empty() {
                        continue;
                    }
                    queue.write_texture(
                        wgpu::TexelCopyTextureInfo {
                            texture: t,
                            mip_level: 0,
                            origin: wgpu::Origin3d { x: 0, y: row, z: 0 },
                            aspect: wgpu::TextureAspect::All,
                        },
                        bytemuck::cast_slice(part),
                        wgpu::TexelCopyBufferLayout {
                            offset: 0,
                            bytes_per_row: Some(width * 16),
                            rows_per_image: None,
                        },
                        wgpu::Extent3d {
                            width,
                            height,
                            depth_or_array_layers: 1,
                        },
                    );
                }
            }
        }
    }
}

/// The rays a recorded dispatch reads and the hits it writes.
#[derive(Clone, Copy)]
enum RaysBinding<'a> {
    Buffer {
        rays: &'a wgpu::Buffer,
        hits: &'a wgpu::Buffer,
    },
    /// Ray `i` of the batch is ray `i` of the textures: the batch is one dispatch.
    Texture {
        rays: &'a wgpu::TextureView,
        hits: &'a wgpu::TextureView,
    },
}

impl RaysBinding<'_> {
    fn input(self) -> RayInput {
        match self {
            RaysBinding::Buffer { .. } => RayInput::Buffer,
            RaysBinding::Texture { .. } => RayInput::Texture,
        }
    }
}

/// Bytes of one row of the hit texture: [`TEXEL_ROW`] hits (a multiple of 256, as texture
/// copies want).
const HIT_ROW_BYTES: u64 = TEXEL_ROW as u64 * HIT_BYTES;

/// Rows of the hit texture holding `hits` hits.
fn hit_rows(hits: u64) -> u64 {
    texel_rows(hits)
}

/// The most rays one upload to a ray texture holds: one dispatch, and no more rows than
/// the device allows.
fn ray_texture_capacity(limits: &DeviceLimits) -> u64 {
    let by_rows = u64::from(TEXEL_ROW / 2) * u64::from(limits.max_texture_dimension_2d);
    rays_per_dispatch(limits).min(by_rows)
}

/// The counters out, and their readback copy.
struct CounterBuffers {
    out: wgpu::Buffer,
    read: wgpu::Buffer,
}

struct Queries {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
}

impl Scratch {
    fn new(ctx: &GpuContext, capacity: u64, with_counters: bool, input: RayInput) -> Scratch {
        let device = ctx.device();
        let buf = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        use wgpu::BufferUsages as U;
        let queries = ctx.has_timestamps().then(|| Queries {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("bvhtrace timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: 2,
            }),
            resolve: buf(
                "bvhtrace timestamps resolve",
                16,
                U::QUERY_RESOLVE | U::COPY_SRC,
            ),
            read: buf("bvhtrace timestamps read", 16, U::MAP_READ | U::COPY_DST),
        });
        Scratch {
            capacity,
            rays: match input {
                RayInput::Buffer => RayStore::Buffer(
                    buf(
                        "bvhtrace rays",
                        capacity * RAY_BYTES,
                        U::STORAGE | U::COPY_DST,
                    ),
                    buf(
                        "bvhtrace hits",
                        capacity * HIT_BYTES,
                        U::STORAGE | U::COPY_SRC,
                    ),
                ),
                RayInput::Texture => {
                    let texels = |label, per_ray| {
                        let t = crate::bvh::storage_texture(
                            ctx,
                            label,
                            wgpu::TextureFormat::Rgba32Uint,
                            TEXEL_ROW,
                            texel_rows(per_ray * capacity) as u32,
                        );
                        let v = t.create_view(&Default::default());
                        (t, v)
                    };
                    let (rays, rays_view) = texels("bvhtrace ray texels", 2);
                    let (hits, hits_view) = texels("bvhtrace hit texels", 1);
                    RayStore::Texture(Box::new(RayTextures {
                        rays,
                        rays_view,
                        hits,
                        hits_view,
                    }))
                }
            },
            hits_read: buf(
                "bvhtrace hits read",
                match input {
                    RayInput::Buffer => capacity * HIT_BYTES,
                    RayInput::Texture => hit_rows(capacity) * HIT_ROW_BYTES,
                },
                U::MAP_READ | U::COPY_DST,
            ),
            counters: with_counters.then(|| CounterBuffers {
                out: buf(
                    "bvhtrace counters",
                    capacity * COUNTERS_BYTES,
                    U::STORAGE | U::COPY_SRC,
                ),
                read: buf(
                    "bvhtrace counters read",
                    capacity * COUNTERS_BYTES,
                    U::MAP_READ | U::COPY_DST,
                ),
            }),
            queries,
        }
    }
}

fn check_buffer(
    buffer: &'static str,
    b: &wgpu::Buffer,
    count: u64,
    stride: u64,
) -> Result<(), GpuError> {
    if !b.usage().contains(wgpu::BufferUsages::STORAGE) {
        return Err(GpuError::BadBuffer {
            buffer,
            problem: format!("needs STORAGE usage (has {:?})", b.usage()),
        });
    }
    let need = count.saturating_mul(stride);
    if b.size() < need {
        return Err(GpuError::BadBuffer {
            buffer,
            problem: format!(
                "{} bytes is too small for {count} entries of {stride} bytes ({need} bytes)",
                b.size()
            ),
        });
    }
    Ok(())
}

fn binding(
    buffer: &wgpu::Buffer,
    first: u64,
    count: u64,
    stride: u64,
) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer,
        offset: first * stride,
        size: NonZeroU64::new(count * stride),
    })
}

/// Reads a mapped range as a vector of `T` (copying; alignment-safe).
fn read_mapped<T: bytemuck::Pod>(
    buffer: &wgpu::Buffer,
    bytes: u64,
    out: &mut Vec<T>,
) -> Result<(), GpuError> {
    let view = buffer
        .slice(..bytes)
        .get_mapped_range()
        .map_err(|e| GpuError::device("reading results back", e))?;
    match bytemuck::try_cast_slice::<u8, T>(&view) {
        Ok(s) => out.extend_from_slice(s),
        Err(_) => out.extend(bytemuck::pod_collect_to_vec::<u8, T>(&view)),
    }
    Ok(())
}

impl GpuBvh {
    /// The kernel tracing `opts` with this upload's storage, reading its rays from
    /// `input`, with the box test's parallel path when `parallel_rays`
    /// ([`KernelKey::for_rays`]).
    fn key(&self, opts: &TraceOptions, input: RayInput, parallel_rays: bool) -> KernelKey {
        KernelKey {
            parallel_rays,
            ..KernelKey::new(self.storage(), opts)
                .with_rays(input)
                .with_instances(self.is_instanced())
        }
    }

    /// Checks that `opts` can run on this upload and device: the walk's data was uploaded
    /// and fits its stack, the precision's feature is there.
    pub fn supports(&self, opts: &TraceOptions) -> Result<(), GpuError> {
        self.supports_traversal(opts.traversal)?;
        if !self.ctx.supports_precision(opts.precision) {
            return Err(GpuError::PrecisionUnsupported {
                precision: opts.precision,
                adapter: self.ctx.adapter_info().name.clone(),
            });
        }
        Ok(())
    }

    /// Compiles (and caches) the pipelines [`GpuBvh::trace`] runs for `opts` (with the box
    /// test's parallel path and without it, see [`KernelKey::for_rays`]) ahead of the
    /// first trace, so that the first trace's time is not the compiler's.
    pub fn prepare(&self, opts: &TraceOptions) -> Result<(), GpuError> {
        self.supports(opts)?;
        let input = RayInput::for_storage(self.storage());
        for parallel_rays in [true, false] {
            self.ctx.pipeline(self.key(opts, input, parallel_rays))?;
        }
        Ok(())
    }

    /// Device bytes of the buffers [`GpuBvh::trace`] keeps between calls: rays, hits and
    /// their readback copy, and the counters (with theirs) only once a trace asked for them.
    pub fn scratch_bytes(&self) -> u64 {
        self.scratch
            .lock()
            .ok()
            .and_then(|g| {
                g.as_ref().map(|s| {
                    s.rays.bytes()
                        + s.hits_read.size()
                        + s.counters
                            .as_ref()
                            .map_or(0, |c| c.out.size() + c.read.size())
                })
            })
            .unwrap_or(0)
    }

    /// Traces `rays` as `opts` says: uploads them, dispatches the kernel (split as
    /// needed), reads the hits (and counters) back. The results equal
    /// [`bvhtrace_core::trace_rays`]'s bit for bit. Batches larger than one device buffer
    /// allows are traced in several submissions; times are summed. f64 needs a device
    /// with `SHADER_F64` ([`GpuContext::supports_precision`]).
    pub fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, GpuError> {
        // The pipeline first: an unsupported traversal or precision fails before any
        // upload. The rays are looked at once, and every chunk uses this kernel.
        self.supports(opts)?;
        let input = RayInput::for_storage(self.storage());
        let key = self.key(opts, input, true).for_rays(rays);
        self.ctx.pipeline(key)?;
        let parallel_rays = key.parallel_rays;
        let start = Instant::now();
        let n = rays.len() as u64;
        let mut out = TraceOutput {
            hits: Vec::with_capacity(rays.len()),
            counters: opts.counters.then(|| Vec::with_capacity(rays.len())),
            gpu_ms: self.ctx.has_timestamps().then_some(0.0),
            wall_ms: 0.0,
            incomplete: 0,
            instances: self.instance_table.clone(),
        };
        if n == 0 {
            return Ok(out);
        }
        // With the BVH in textures (CPU drivers), the rays go in a texture too, one
        // dispatch per submission (`RayInput::Texture`).
        let (mut per_submit, mut capacity) = plan_submissions(n, self.ctx.limits());
        if input == RayInput::Texture {
            per_submit = per_submit.min(ray_texture_capacity(self.ctx.limits()));
            capacity = capacity.min(per_submit);
        }

        let mut guard = self
            .scratch
            .lock()
            .map_err(|_| GpuError::Poisoned("scratch buffers"))?;
        // Counter buffers only once counters are asked for; kept from then on.
        let had_counters = guard.as_ref().is_some_and(|s| s.counters.is_some());
        if guard.as_ref().is_none_or(|s| {
            s.capacity < capacity
                || (opts.counters && s.counters.is_none())
                || s.rays.binding().input() != input
        }) {
            let capacity = capacity.max(guard.as_ref().map_or(0, |s| s.capacity));
            *guard = None; // free the old buffers first
            *guard = Some(self.ctx.scoped("allocating ray buffers", || {
                Scratch::new(&self.ctx, capacity, opts.counters || had_counters, input)
            })?);
        }
        let Some(s) = guard.as_ref() else {
            unreachable!("scratch was just created")
        };
        let counter_buffers = if opts.counters {
            s.counters.as_ref()
        } else {
            None
        };
        let device = self.ctx.device();
        let queue = self.ctx.queue();
        let period_ns = f64::from(queue.get_timestamp_period());

        for batch in rays.chunks(per_submit as usize) {
            let count = batch.len() as u64;
            let hit_bytes = count * HIT_BYTES;
            let counter_bytes = count * COUNTERS_BYTES;
            self.ctx
                .scoped("tracing a ray batch", || -> Result<(), GpuError> {
                    s.rays.write(queue, batch);
                    let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("bvhtrace trace"),
                    });
                    let tw = s
                        .queries
                        .as_ref()
                        .map(|q| wgpu::ComputePassTimestampWrites {
                            query_set: &q.set,
                            beginning_of_pass_write_index: Some(0),
                            end_of_pass_write_index: Some(1),
                        });
                    self.record_rays(
                        &mut enc,
                        s.rays.binding(),
                        counter_buffers.map(|c| &c.out),
                        count,
                        opts,
                        parallel_rays,
                        tw,
                    )?;
                    s.rays.copy_hits(&mut enc, &s.hits_read, count);
                    if let Some(c) = counter_buffers {
                        enc.copy_buffer_to_buffer(&c.out, 0, &c.read, 0, counter_bytes);
                    }
                    if let Some(q) = &s.queries {
                        enc.resolve_query_set(&q.set, 0..2, &q.resolve, 0);
                        enc.copy_buffer_to_buffer(&q.resolve, 0, &q.read, 0, 16);
                    }
                    queue.submit([enc.finish()]);
                    Ok(())
                })??;

            let (tx, rx) = mpsc::channel();
            let mut maps = vec![(&s.hits_read, hit_bytes)];
            if let Some(c) = counter_buffers {
                maps.push((&c.read, counter_bytes));
            }
            if let Some(q) = &s.queries {
                maps.push((&q.read, 16));
            }
            for (b, bytes) in &maps {
                let tx = tx.clone();
                b.slice(..*bytes).map_async(wgpu::MapMode::Read, move |r| {
                    let _ = tx.send(r);
                });
            }
            drop(tx);
            device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| GpuError::device("waiting for the GPU", e))?;
            let mut results = Vec::with_capacity(maps.len());
            for _ in 0..maps.len() {
                results.push(rx.recv().map_err(|_| {
                    GpuError::device("reading results back", "a buffer mapping never completed")
                })?);
            }
            let mapped = results.into_iter().collect::<Result<Vec<()>, _>>();
            let read = mapped
                .map_err(|e| GpuError::device("reading results back", e))
                .and_then(|_| {
                    read_mapped(&s.hits_read, hit_bytes, &mut out.hits)?;
                    if let (Some(c), Some(b)) = (out.counters.as_mut(), counter_buffers) {
                        read_mapped(&b.read, counter_bytes, c)?;
                    }
                    if let Some(q) = &s.queries {
                        let mut ts: Vec<u64> = Vec::with_capacity(2);
                        read_mapped(&q.read, 16, &mut ts)?;
                        let ticks = ts[1].saturating_sub(ts[0]) as f64;
                        if let Some(g) = out.gpu_ms.as_mut() {
                            *g += ticks * period_ns * 1e-6;
                        }
                    }
                    Ok(())
                });
            for (b, _) in &maps {
                b.unmap();
            }
            read?;
        }
        if let Some(bvh) = self.host_copy.as_deref() {
            finish_incomplete(bvh, rays, opts, &mut out);
        }
        out.wall_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(out)
    }

    /// Records the traversal of `batch` into `encoder`, as one compute pass with one
    /// dispatch per chunk of at most [`rays_per_dispatch`] rays. `timestamp_writes`, when
    /// given, is attached to that pass (the device needs `TIMESTAMP_QUERY`). The bind
    /// groups for the caller's buffers are made once and reused while the same buffers come
    /// back.
    ///
    /// The buffers are checked (usage and size) before anything is recorded; the caller
    /// submits the encoder. Rays are never [`bvhtrace_core::INCOMPLETE`] here unless the
    /// context's tuning sets a trip budget (CPU drivers), or the wide walk meets a wide
    /// tree deeper than its stack ([`bvhtrace_kernels::wide_stack_may_overflow`]): finish
    /// those with [`bvhtrace_kernels::finish_incomplete`].
    pub fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: &RayBatch<'_>,
        opts: &TraceOptions,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) -> Result<(), GpuError> {
        self.record_rays(
            encoder,
            RaysBinding::Buffer {
                rays: batch.rays,
                hits: batch.hits,
            },
            batch.counters,
            batch.ray_count,
            opts,
            true,
            timestamp_writes,
        )
    }

    /// Records the traversal of `n` rays read from `rays`, hits (and counters) to the
    /// given buffers. A texture holds the whole batch in one dispatch. `parallel_rays` false
    /// leaves the box test's parallel path out: only when the host has seen that no ray
    /// needs it ([`KernelKey::for_rays`]).
    #[allow(clippy::too_many_arguments)]
    fn record_rays(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rays: RaysBinding<'_>,
        counters: Option<&wgpu::Buffer>,
        n: u64,
        opts: &TraceOptions,
        parallel_rays: bool,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) -> Result<(), GpuError> {
        self.supports(opts)?;
        if let RaysBinding::Buffer { rays, hits } = rays {
            check_buffer("rays", rays, n, RAY_BYTES)?;
            check_buffer("hits", hits, n, HIT_BYTES)?;
        }
        let counters = if opts.counters {
            let c = counters.ok_or(GpuError::BadBuffer {
                buffer: "counters",
                problem: "counters were asked for but no counters buffer was given".into(),
            })?;
            check_buffer("counters", c, n, COUNTERS_BYTES)?;
            Some(c)
        } else {
            None
        };
        let input = rays.input();
        let key = self.key(opts, input, parallel_rays);
        let pipeline = self.ctx.pipeline(key)?;
        {
            let mut used = self
                .used
                .lock()
                .map_err(|_| GpuError::Poisoned("kernels used"))?;
            if !used.contains(&key) {
                used.push(key);
            }
        }
        let group0 = self.bind_group(opts.traversal)?;
        let dispatches = plan_dispatches(n, self.ctx.limits());
        if matches!(rays, RaysBinding::Texture { .. }) && dispatches.len() > 1 {
            return Err(GpuError::BadBuffer {
                buffer: "rays",
                problem: format!("{n} rays in a ray texture are more than one dispatch"),
            });
        }
        let groups = self.batch_groups(rays, counters, n, opts.counters)?;
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("bvhtrace trace"),
            timestamp_writes,
        });
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, group0.group(), &[]);
        for (d, g) in dispatches.iter().zip(groups.iter()) {
            pass.set_bind_group(1, g, &[]);
            pass.dispatch_workgroups(d.groups_x, d.groups_y, 1);
        }
        Ok(())
    }

    /// The batch bind groups (one per dispatch) for these resources: made on first use and
    /// kept while the same resources come back, so a caller recording every frame into the
    /// same buffers makes none. At most [`BATCH_GROUPS_KEPT`] sets are kept; they hold
    /// references to the buffers.
    fn batch_groups(
        &self,
        rays: RaysBinding<'_>,
        counters: Option<&wgpu::Buffer>,
        n: u64,
        with_counters: bool,
    ) -> Result<std::sync::Arc<Vec<wgpu::BindGroup>>, GpuError> {
        let key = BatchKey {
            rays: match rays {
                RaysBinding::Buffer { rays, hits } => (
                    BatchResource::Buffer(rays.clone()),
                    BatchResource::Buffer(hits.clone()),
                ),
                RaysBinding::Texture { rays, hits } => (
                    BatchResource::View(rays.clone()),
                    BatchResource::View(hits.clone()),
                ),
            },
            counters: counters.cloned(),
            ray_count: n,
        };
        let mut cache = self
            .batch_groups
            .lock()
            .map_err(|_| GpuError::Poisoned("batch bind groups"))?;
        if let Some(g) = cache.get(&key) {
            return Ok(g.clone());
        }
        let device = self.ctx.device();
        let layout = self.ctx.batch_layout(with_counters, rays.input());
        let groups: Vec<wgpu::BindGroup> = plan_dispatches(n, self.ctx.limits())
            .iter()
            .map(|d| {
                let (first, count) = (d.first_ray, u64::from(d.ray_count));
                let (r, h) = match rays {
                    RaysBinding::Buffer { rays, hits } => (
                        binding(rays, first, count, RAY_BYTES),
                        binding(hits, first, count, HIT_BYTES),
                    ),
                    RaysBinding::Texture { rays, hits } => (
                        wgpu::BindingResource::TextureView(rays),
                        wgpu::BindingResource::TextureView(hits),
                    ),
                };
                let mut entries = vec![
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: r,
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: h,
                    },
                ];
                if let Some(c) = counters {
                    entries.push(wgpu::BindGroupEntry {
                        binding: 2,
                        resource: binding(c, first, count, COUNTERS_BYTES),
                    });
                }
                device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("bvhtrace batch"),
                    layout,
                    entries: &entries,
                })
            })
            .collect();
        if cache.len() >= BATCH_GROUPS_KEPT {
            cache.clear();
        }
        let groups = std::sync::Arc::new(groups);
        cache.insert(key, groups.clone());
        Ok(groups)
    }
}

/// How many sets of batch bind groups one [`GpuBvh`] keeps.
pub(crate) const BATCH_GROUPS_KEPT: usize = 16;

/// One resource of a batch bind group.
#[derive(Clone, PartialEq, Eq, Hash)]
enum BatchResource {
    Buffer(wgpu::Buffer),
    View(wgpu::TextureView),
}

/// What a set of batch bind groups was made for.
#[derive(Clone, PartialEq, Eq, Hash)]
pub(crate) struct BatchKey {
    rays: (BatchResource, BatchResource),
    counters: Option<wgpu::Buffer>,
    ray_count: u64,
}

/// The batch bind groups a [`GpuBvh`] keeps.
pub(crate) type BatchGroups = HashMap<BatchKey, std::sync::Arc<Vec<wgpu::BindGroup>>>;

impl Tracer for GpuBvh {
    fn backend(&self) -> &'static str {
        "wgpu"
    }

    fn device_name(&self) -> String {
        let i = self.ctx.adapter_info();
        format!("{} ({:?}, {:?})", i.name, i.device_type, i.backend)
    }

    fn default_traversal(&self) -> Traversal {
        Traversal::GPU_DEFAULT
    }

    fn supports(&self, opts: &TraceOptions) -> Result<(), GpuError> {
        GpuBvh::supports(self, opts)
    }

    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, GpuError> {
        GpuBvh::trace(self, rays, opts)
    }

    fn prepare(&self, opts: &TraceOptions) -> Result<(), GpuError> {
        GpuBvh::prepare(self, opts)
    }

    fn upload_stats(&self) -> Option<bvhtrace_kernels::UploadStats> {
        Some(*self.stats())
    }

    fn update(&mut self, bvh: &bvhtrace_core::FlatBvh) -> Result<(), GpuError> {
        let fingerprint = bvhtrace_kernels::mesh_fingerprint(bvh);
        let what = if bvh.is_instanced() && fingerprint == self.mesh_fingerprint {
            crate::Update::TopLevel
        } else {
            crate::Update::Everything
        };
        GpuBvh::update(self, bvh, what)
    }

    fn kernels_used(&self) -> Vec<KernelKey> {
        self.used.lock().map(|u| u.clone()).unwrap_or_default()
    }
}
