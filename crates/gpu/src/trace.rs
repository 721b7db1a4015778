//! Tracing ray batches: the convenience [`GpuBvh::trace`] (slices in, hits out, timed) and
//! [`GpuBvh::record`] (into the caller's encoder, with the caller's buffers).

use std::num::NonZeroU64;
use std::sync::mpsc;
use std::time::Instant;

use bvhtrace_core::{Counters, FlatBvh, Hit, INCOMPLETE, Precision, Query, Ray, Traversal};

use crate::bvh::GpuBvh;
use crate::context::{GpuContext, GpuLimits};
use crate::error::GpuError;
use crate::shaders::{KernelVariant, RayInput, TEXEL_ROW, WORKGROUP_SIZE};

/// Bytes of one [`Ray`] on the device.
pub const RAY_BYTES: u64 = std::mem::size_of::<Ray>() as u64;
/// Bytes of one [`Hit`] on the device.
pub const HIT_BYTES: u64 = std::mem::size_of::<Hit>() as u64;
/// Bytes of one [`Counters`] on the device.
pub const COUNTERS_BYTES: u64 = std::mem::size_of::<Counters>() as u64;

/// The most rays one dispatch handles (about 4M: 128 MiB of rays). Larger batches are split
/// into several dispatches in one compute pass.
pub const MAX_RAYS_PER_DISPATCH: u64 = 1 << 22;

/// What to trace.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TraceOptions {
    /// How to walk the tree.
    pub traversal: Traversal,
    /// Closest or any hit.
    pub query: Query,
    /// Also write each ray's [`Counters`].
    pub counters: bool,
}

/// The result of [`GpuBvh::trace`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TraceOutput {
    /// One hit per ray, in ray order.
    pub hits: Vec<Hit>,
    /// One entry per ray when counters were asked for.
    pub counters: Option<Vec<Counters>>,
    /// Time the traversal kernels took on the GPU (timestamp queries around the compute
    /// pass), milliseconds; `None` when the device has no timestamp queries.
    pub gpu_ms: Option<f64>,
    /// Wall time of the whole call: uploading the rays, the dispatches and reading the
    /// results back, milliseconds (pipeline creation excluded).
    pub wall_ms: f64,
    /// Rays the kernel gave up on when they spent the adapter's loop-trip budget
    /// ([`GpuContext::trip_limit`](crate::GpuContext::trip_limit)), finished on the CPU
    /// twin (hits and counters as the kernel would have given them). 0 on ordinary scenes.
    pub incomplete: u64,
}

/// Replaces every [`INCOMPLETE`] hit in `out` by the CPU twin's answer for that ray on
/// `twin` (same traversal, query and precision; counters too when `out` has them) and
/// counts them in `out.incomplete`: what [`GpuBvh::trace`] does after the kernel, and any
/// other backend running these kernels should do too.
pub fn finish_incomplete(
    twin: &FlatBvh,
    rays: &[Ray],
    traversal: Traversal,
    query: Query,
    precision: Precision,
    out: &mut TraceOutput,
) {
    for (i, h) in out.hits.iter_mut().enumerate() {
        if h.prim != INCOMPLETE {
            continue;
        }
        let (hit, c) =
            bvhtrace_core::trace_ray_precision(twin, &rays[i], traversal, query, precision);
        *h = hit;
        if let Some(cs) = out.counters.as_mut() {
            cs[i] = c;
        }
        out.incomplete += 1;
    }
}

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
    /// Counters out: required when [`TraceOptions::counters`] is set, ignored otherwise.
    pub counters: Option<&'a wgpu::Buffer>,
    /// Number of rays.
    pub ray_count: u64,
}

/// One dispatch of a batch: rays `first_ray .. first_ray + ray_count` on a
/// `groups_x` x `groups_y` grid of [`WORKGROUP_SIZE`]-invocation workgroups.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dispatch {
    /// First ray of the chunk.
    pub first_ray: u64,
    /// Rays in the chunk.
    pub ray_count: u32,
    /// Workgroups along x.
    pub groups_x: u32,
    /// Workgroups along y (1 unless x would exceed the per-dimension limit).
    pub groups_y: u32,
}

/// Rays per dispatch on a device with these limits: at most [`MAX_RAYS_PER_DISPATCH`], at
/// most what one storage binding holds, a multiple of the workgroup size and of the
/// binding-offset alignment (so every chunk's buffer ranges are aligned).
pub fn rays_per_dispatch(limits: &GpuLimits) -> u64 {
    let align = u64::from(limits.min_storage_buffer_offset_alignment).max(1);
    let step = u64::from(WORKGROUP_SIZE).max(align);
    let by_binding = limits.max_storage_buffer_binding_size / RAY_BYTES;
    let dim = u64::from(limits.max_compute_workgroups_per_dimension.max(1));
    let by_groups = dim * dim * u64::from(WORKGROUP_SIZE);
    let max = MAX_RAYS_PER_DISPATCH.min(by_binding).min(by_groups);
    (max / step * step).max(step)
}

/// How a batch of `ray_count` rays is submitted: `(rays per submission, scratch capacity
/// in rays)`. A submission holds as many whole dispatches as one device buffer allows (at
/// least one); the scratch buffers hold one submission, and at least a workgroup.
pub fn plan_submissions(ray_count: u64, limits: &GpuLimits) -> (u64, u64) {
    let chunk = rays_per_dispatch(limits);
    let by_buffer = limits.max_buffer_size / RAY_BYTES / chunk * chunk;
    let per_submit = by_buffer.max(chunk);
    let capacity = ray_count.min(per_submit).max(u64::from(WORKGROUP_SIZE));
    (per_submit, capacity)
}

/// Splits a batch of `ray_count` rays into dispatches (see [`rays_per_dispatch`]).
pub fn plan_dispatches(ray_count: u64, limits: &GpuLimits) -> Vec<Dispatch> {
    let chunk = rays_per_dispatch(limits);
    let dim = limits.max_compute_workgroups_per_dimension.max(1);
    let mut out = Vec::new();
    let mut first = 0;
    while first < ray_count {
        let n = (ray_count - first).min(chunk);
        let groups = n.div_ceil(u64::from(WORKGROUP_SIZE)) as u32;
        let groups_x = groups.min(dim);
        out.push(Dispatch {
            first_ray: first,
            ray_count: n as u32,
            groups_x,
            groups_y: groups.div_ceil(groups_x),
        });
        first += n;
    }
    out
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
    crate::bvh::texel_rows(hits)
}

/// The most rays one upload to a ray texture holds: one dispatch, and no more rows than
/// the device allows.
fn ray_texture_capacity(limits: &GpuLimits) -> u64 {
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
                            crate::bvh::texel_rows(per_ray * capacity) as u32,
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
        .map_err(|e| GpuError::Wgpu {
            during: "reading results back",
            message: e.to_string(),
        })?;
    match bytemuck::try_cast_slice::<u8, T>(&view) {
        Ok(s) => out.extend_from_slice(s),
        Err(_) => out.extend(bytemuck::pod_collect_to_vec::<u8, T>(&view)),
    }
    Ok(())
}

impl GpuBvh {
    /// Compiles (and caches) the pipeline for these options ahead of the first trace, so
    /// that the first trace's timing is not the compiler's.
    pub fn prepare(&self, opts: &TraceOptions) -> Result<(), GpuError> {
        self.prepare_precision(opts, Precision::WatertightF32)
    }

    /// The kernel variant tracing `opts` with `precision`, its rays read from `input`, with
    /// the box test's parallel path when `parallel_rays` ([`KernelVariant::for_rays`]).
    fn variant(
        &self,
        opts: &TraceOptions,
        precision: Precision,
        input: RayInput,
        parallel_rays: bool,
    ) -> KernelVariant {
        KernelVariant {
            parallel_rays,
            ..KernelVariant::new(self.storage(), opts.traversal, opts.query, opts.counters)
                .with_precision(precision)
                .with_rays(input)
        }
    }

    /// [`GpuBvh::prepare`] for the kernels with the triangle test of `precision` (the ones
    /// [`GpuBvh::trace`] runs: rays read as [`RayInput::for_storage`] says, with the box
    /// test's parallel path and without it, see [`KernelVariant::for_rays`]).
    pub fn prepare_precision(
        &self,
        opts: &TraceOptions,
        precision: Precision,
    ) -> Result<(), GpuError> {
        self.supports(opts.traversal)?;
        let input = RayInput::for_storage(self.storage());
        for parallel_rays in [true, false] {
            self.ctx
                .pipeline(self.variant(opts, precision, input, parallel_rays))?;
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

    /// Traces `rays` and returns one hit per ray, with GPU and wall times.
    pub fn trace(
        &self,
        rays: &[Ray],
        traversal: Traversal,
        query: Query,
    ) -> Result<TraceOutput, GpuError> {
        self.trace_with(
            rays,
            &TraceOptions {
                traversal,
                query,
                counters: false,
            },
        )
    }

    /// [`GpuBvh::trace`], also returning each ray's counters (boxes and triangles tested).
    pub fn trace_counted(
        &self,
        rays: &[Ray],
        traversal: Traversal,
        query: Query,
    ) -> Result<TraceOutput, GpuError> {
        self.trace_with(
            rays,
            &TraceOptions {
                traversal,
                query,
                counters: true,
            },
        )
    }

    /// Traces `rays` as `opts` says: uploads them, dispatches the kernel (split as needed),
    /// reads the hits (and counters) back. Batches larger than one device buffer allows are
    /// traced in several submissions; times are summed.
    pub fn trace_with(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, GpuError> {
        self.trace_with_precision(rays, opts, Precision::WatertightF32)
    }

    /// [`GpuBvh::trace_with`] with the triangle test of `precision`
    /// ([`bvhtrace_core::Precision`]; the results equal
    /// [`bvhtrace_core::trace_batch_precision`]'s bit for bit). f64 needs a device with
    /// `SHADER_F64` ([`GpuContext::supports_precision`]); otherwise this returns
    /// [`GpuError::PrecisionUnsupported`].
    pub fn trace_with_precision(
        &self,
        rays: &[Ray],
        opts: &TraceOptions,
        precision: Precision,
    ) -> Result<TraceOutput, GpuError> {
        // The pipeline first: an unsupported traversal or precision fails before any
        // upload. The rays are looked at once, and every chunk uses this variant.
        self.supports(opts.traversal)?;
        let input = RayInput::for_storage(self.storage());
        let variant = self.variant(opts, precision, input, true).for_rays(rays);
        self.ctx.pipeline(variant)?;
        let parallel_rays = variant.parallel_rays;
        let start = Instant::now();
        let n = rays.len() as u64;
        let mut out = TraceOutput {
            hits: Vec::with_capacity(rays.len()),
            counters: opts.counters.then(|| Vec::with_capacity(rays.len())),
            gpu_ms: self.ctx.has_timestamps().then_some(0.0),
            wall_ms: 0.0,
            incomplete: 0,
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

        let mut guard = self.scratch.lock().map_err(|_| GpuError::Wgpu {
            during: "locking the scratch buffers",
            message: "a thread panicked while holding them".into(),
        })?;
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
                        precision,
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
            device.poll(wgpu::PollType::wait_indefinitely())?;
            let mut results = Vec::with_capacity(maps.len());
            for _ in 0..maps.len() {
                results.push(rx.recv().map_err(|_| GpuError::Wgpu {
                    during: "reading results back",
                    message: "a buffer mapping never completed".into(),
                })?);
            }
            let mapped = results.into_iter().collect::<Result<Vec<()>, _>>();
            let read = mapped.map_err(GpuError::from).and_then(|_| {
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
        if let Some(twin) = self.twin.as_deref() {
            finish_incomplete(twin, rays, opts.traversal, opts.query, precision, &mut out);
        }
        out.wall_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(out)
    }

    /// Records the traversal of `batch` into `encoder`, as one compute pass with one
    /// dispatch per chunk of at most [`rays_per_dispatch`] rays. `timestamp_writes`, when
    /// given, is attached to that pass (the device needs `TIMESTAMP_QUERY`).
    ///
    /// The buffers are checked (usage and size) before anything is recorded; the caller
    /// submits the encoder.
    pub fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: &RayBatch<'_>,
        opts: &TraceOptions,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) -> Result<(), GpuError> {
        self.record_precision(
            encoder,
            batch,
            opts,
            Precision::WatertightF32,
            timestamp_writes,
        )
    }

    /// [`GpuBvh::record`] with the triangle test of `precision`.
    pub fn record_precision(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: &RayBatch<'_>,
        opts: &TraceOptions,
        precision: Precision,
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
            precision,
            true,
            timestamp_writes,
        )
    }

    /// Records the traversal of `n` rays read from `rays`, hits (and counters) to the
    /// given buffers. A texture holds the whole batch in one dispatch. `parallel_rays` false
    /// leaves the box test's parallel path out: only when the host has seen that no ray
    /// needs it ([`KernelVariant::for_rays`]).
    #[allow(clippy::too_many_arguments)]
    fn record_rays(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rays: RaysBinding<'_>,
        counters: Option<&wgpu::Buffer>,
        n: u64,
        opts: &TraceOptions,
        precision: Precision,
        parallel_rays: bool,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) -> Result<(), GpuError> {
        self.supports(opts.traversal)?;
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
        let variant = self.variant(opts, precision, input, parallel_rays);
        let pipeline = self.ctx.pipeline(variant)?;
        let group0 =
            self.bind_group(variant.needs_escapes())
                .ok_or(GpuError::EscapesNotUploaded {
                    traversal: opts.traversal,
                })?;
        let device = self.ctx.device();
        let dispatches = plan_dispatches(n, self.ctx.limits());
        if matches!(rays, RaysBinding::Texture { .. }) && dispatches.len() > 1 {
            return Err(GpuError::BadBuffer {
                buffer: "rays",
                problem: format!("{n} rays in a ray texture are more than one dispatch"),
            });
        }
        let groups: Vec<wgpu::BindGroup> = dispatches
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
                    layout: self.ctx.batch_layout_for(opts.counters, input),
                    entries: &entries,
                })
            })
            .collect();
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("bvhtrace trace"),
            timestamp_writes,
        });
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, group0, &[]);
        for (d, g) in dispatches.iter().zip(&groups) {
            pass.set_bind_group(1, g, &[]);
            pass.dispatch_workgroups(d.groups_x, d.groups_y, 1);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(binding: u64, dim: u32, align: u32) -> GpuLimits {
        GpuLimits {
            max_storage_buffer_binding_size: binding,
            max_buffer_size: 1 << 40,
            max_compute_workgroups_per_dimension: dim,
            min_storage_buffer_offset_alignment: align,
            max_texture_dimension_2d: 8192,
        }
    }

    fn check(ray_count: u64, l: &GpuLimits) {
        let plan = plan_dispatches(ray_count, l);
        let chunk = rays_per_dispatch(l);
        let mut next = 0;
        for d in &plan {
            assert_eq!(d.first_ray, next, "{plan:?}");
            assert!(u64::from(d.ray_count) <= chunk);
            // Every chunk starts at an aligned offset in all three buffers.
            for stride in [RAY_BYTES, HIT_BYTES, COUNTERS_BYTES] {
                assert_eq!(
                    d.first_ray * stride % u64::from(l.min_storage_buffer_offset_alignment),
                    0
                );
            }
            assert!(u64::from(d.ray_count) * RAY_BYTES <= l.max_storage_buffer_binding_size);
            assert!(d.groups_x <= l.max_compute_workgroups_per_dimension);
            assert!(d.groups_y <= l.max_compute_workgroups_per_dimension);
            let threads = u64::from(d.groups_x) * u64::from(d.groups_y) * u64::from(WORKGROUP_SIZE);
            assert!(threads >= u64::from(d.ray_count));
            // No whole spare row of workgroups.
            assert!(
                threads - u64::from(d.ray_count)
                    < u64::from(d.groups_x) * u64::from(WORKGROUP_SIZE)
            );
            next += u64::from(d.ray_count);
        }
        assert_eq!(next, ray_count);
    }

    #[test]
    fn dispatch_plans_cover_the_batch_within_limits() {
        let lavapipe = limits(128 << 20, 65_535, 64);
        assert_eq!(rays_per_dispatch(&lavapipe), MAX_RAYS_PER_DISPATCH);
        for n in [
            0,
            1,
            63,
            64,
            65,
            1000,
            MAX_RAYS_PER_DISPATCH,
            MAX_RAYS_PER_DISPATCH + 1,
            3 * MAX_RAYS_PER_DISPATCH + 17,
        ] {
            check(n, &lavapipe);
        }
        // The 4M-ray chunk needs 65,536 workgroups: a 2D grid on this device.
        let plan = plan_dispatches(MAX_RAYS_PER_DISPATCH, &lavapipe);
        assert_eq!((plan[0].groups_x, plan[0].groups_y), (65_535, 2));
        // Small bindings, few workgroups per dimension, large alignment.
        let tight = limits(1 << 16, 7, 256);
        assert_eq!(rays_per_dispatch(&tight), 2048 / 256 * 256);
        for n in [1, 255, 256, 2047, 2048, 2049, 100_000] {
            check(n, &tight);
        }
        assert!(plan_dispatches(0, &tight).is_empty());
    }
}
