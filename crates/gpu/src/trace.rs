//! Tracing ray batches: the convenience [`GpuBvh::trace`] (slices in, hits out, timed) and
//! [`GpuBvh::record`] (into the caller's encoder, with the caller's buffers).

use std::collections::HashMap;
use std::num::NonZeroU64;
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Poll, Waker};

use bvhtrace_core::{Counters, Hit, Ray, TraceOptions, TracePhases};
use bvhtrace_engine::KernelKey;
use bvhtrace_engine::engine::{Batch, BatchOut, BatchTimes, ScratchPlan};
use bvhtrace_engine::plan::{COUNTERS_BYTES, HIT_BYTES, RAY_BYTES, plan_dispatches};
use bvhtrace_engine::storage::{RayInput, TEXEL_ROW, texel_rows};
use web_time::Instant;

use crate::GpuError;
use crate::backend::WgpuArrays;
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
pub struct Scratch {
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
                    height: texel_rows(count) as u32,
                    depth_or_array_layers: 1,
                },
            ),
        }
    }

    /// Uploads `rays` to the start of the store.
    fn write(&self, queue: &wgpu::Queue, rays: &[Ray]) {
        match self {
            RayStore::Buffer(b, _) => queue.write_buffer(b, 0, bytemuck::cast_slice(rays)),
            RayStore::Texture(t) => {
                crate::backend::write_texels(queue, &t.rays, bytemuck::cast_slice(rays), 16)
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

/// Bytes of one row of the hit texture: [`TEXEL_ROW`] hits (a multiple of 256, as texture
/// copies want).
const HIT_ROW_BYTES: u64 = TEXEL_ROW as u64 * HIT_BYTES;

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
    /// Device bytes of the scratch: rays, hits and their readback copy, and the counters
    /// (with theirs) once a trace asked for them.
    pub(crate) fn bytes(&self) -> u64 {
        self.rays.bytes()
            + self.hits_read.size()
            + self
                .counters
                .as_ref()
                .map_or(0, |c| c.out.size() + c.read.size())
    }

    pub(crate) fn new(ctx: &GpuContext, plan: &ScratchPlan) -> Scratch {
        use wgpu::BufferUsages as U;
        let (written, read_back, mapped) = (
            U::STORAGE | U::COPY_DST,
            U::STORAGE | U::COPY_SRC,
            U::MAP_READ | U::COPY_DST,
        );
        let device = ctx.device();
        let buf = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(&format!("bvhtrace {label}")),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let n = plan.capacity;
        let texels = |label, per_ray| {
            let format = wgpu::TextureFormat::Rgba32Uint;
            let rows = texel_rows(per_ray * n) as u32;
            let t = crate::backend::storage_texture(ctx, label, format, TEXEL_ROW, rows);
            let v = t.create_view(&Default::default());
            (t, v)
        };
        let (rays, hits_read) = match plan.input {
            RayInput::Buffer => (
                RayStore::Buffer(
                    buf("rays", n * RAY_BYTES, written),
                    buf("hits", n * HIT_BYTES, read_back),
                ),
                n * HIT_BYTES,
            ),
            RayInput::Texture => {
                let ((rays, rays_view), (hits, hits_view)) = (
                    texels("bvhtrace ray texels", 2),
                    texels("bvhtrace hit texels", 1),
                );
                let textures = RayTextures {
                    rays,
                    rays_view,
                    hits,
                    hits_view,
                };
                (
                    RayStore::Texture(Box::new(textures)),
                    texel_rows(n) * HIT_ROW_BYTES,
                )
            }
        };
        Scratch {
            rays,
            hits_read: buf("hits read", hits_read, mapped),
            counters: plan.counters.then(|| CounterBuffers {
                out: buf("counters", n * COUNTERS_BYTES, read_back),
                read: buf("counters read", n * COUNTERS_BYTES, mapped),
            }),
            queries: ctx.has_timestamps().then(|| Queries {
                set: device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("bvhtrace timestamps"),
                    ty: wgpu::QueryType::Timestamp,
                    count: 2,
                }),
                resolve: buf("timestamps resolve", 16, U::QUERY_RESOLVE | U::COPY_SRC),
                read: buf("timestamps read", 16, mapped),
            }),
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

/// `count` elements of `stride` bytes of `buffer` from element `first`, bound.
pub(crate) fn binding(
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
pub(crate) fn read_mapped<T: bytemuck::Pod>(
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

/// A batch submitted on a [`Scratch`] and not yet read back.
pub struct Submitted {
    index: wgpu::SubmissionIndex,
    count: u64,
    counters: bool,
    start: Instant,
    submitted: Instant,
}

/// Uploads `batch`'s rays to the scratch, records its kernel and the readback copies and
/// submits them, without waiting.
pub(crate) fn submit_batch(
    ctx: &GpuContext,
    arrays: &WgpuArrays,
    s: &Scratch,
    batch: Batch<'_>,
) -> Result<Submitted, GpuError> {
    let start = Instant::now();
    let count = batch.rays.len() as u64;
    let counter_buffers = if batch.key.counters {
        s.counters.as_ref()
    } else {
        None
    };
    let (queue, device) = (ctx.queue(), ctx.device());
    let index = ctx.scoped("tracing a ray batch", || -> Result<_, GpuError> {
        s.rays.write(queue, batch.rays);
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
        let pass = Pass {
            rays: s.rays.binding(),
            counters: counter_buffers.map(|c| &c.out),
            count,
            timestamp_writes: tw,
        };
        record_pass(ctx, arrays, batch.key, &mut enc, pass)?;
        s.rays.copy_hits(&mut enc, &s.hits_read, count);
        if let Some(c) = counter_buffers {
            enc.copy_buffer_to_buffer(&c.out, 0, &c.read, 0, count * COUNTERS_BYTES);
        }
        if let Some(q) = &s.queries {
            enc.resolve_query_set(&q.set, 0..2, &q.resolve, 0);
            enc.copy_buffer_to_buffer(&q.resolve, 0, &q.read, 0, 16);
        }
        Ok(queue.submit([enc.finish()]))
    })??;
    Ok(Submitted {
        index,
        count,
        counters: counter_buffers.is_some(),
        start,
        submitted: Instant::now(),
    })
}

/// Waits for `sub` (made on `s`), and appends its hits (and counters) to `out`; the GPU
/// time in milliseconds when the device measures it, and the phases.
pub(crate) async fn finish_batch(
    ctx: &GpuContext,
    s: &Scratch,
    sub: Submitted,
    out: BatchOut<'_>,
) -> Result<BatchTimes, GpuError> {
    let Submitted {
        index,
        count,
        counters,
        start,
        submitted,
    } = sub;
    let counter_buffers = if counters { s.counters.as_ref() } else { None };
    let queue = ctx.queue();
    let mut maps = vec![(&s.hits_read, count * HIT_BYTES)];
    maps.extend(counter_buffers.map(|c| (&c.read, count * COUNTERS_BYTES)));
    maps.extend(s.queries.as_ref().map(|q| (&q.read, 16)));
    let mapped = map_all(ctx, index, &maps).await;
    // In a browser, a kernel the browser's compiler rejected (or any failed step before)
    // is only known now: its error comes first.
    ctx.deferred_errors().await?;
    mapped?;
    let done = Instant::now();
    let read = (|| -> Result<Option<f64>, GpuError> {
        read_mapped(&s.hits_read, count * HIT_BYTES, out.hits)?;
        if let (Some(c), Some(b)) = (out.counters, counter_buffers) {
            read_mapped::<Counters>(&b.read, count * COUNTERS_BYTES, c)?;
        }
        let Some(q) = &s.queries else { return Ok(None) };
        let mut ts: Vec<u64> = Vec::with_capacity(2);
        read_mapped(&q.read, 16, &mut ts)?;
        let ticks = ts[1].saturating_sub(ts[0]) as f64;
        Ok(Some(ticks * f64::from(queue.get_timestamp_period()) * 1e-6))
    })();
    for (b, _) in &maps {
        b.unmap();
    }
    Ok(BatchTimes {
        gpu_ms: read?,
        phases: TracePhases::since(start, submitted, done),
    })
}

/// Buffer mappings not yet completed: their callbacks count down and wake the waiting
/// task (a browser calls them from its event loop; natively `poll` calls them).
struct Mappings {
    left: usize,
    failed: Option<wgpu::BufferAsyncError>,
    waker: Option<Waker>,
}

/// The mappings' state, even after a panicking callback.
fn lock(m: &Mutex<Mappings>) -> MutexGuard<'_, Mappings> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// Maps the first bytes of each buffer for reading, after the submission `index` (and
/// only it, with what came before it on the queue) has completed.
pub(crate) async fn map_all(
    ctx: &GpuContext,
    index: wgpu::SubmissionIndex,
    maps: &[(&wgpu::Buffer, u64)],
) -> Result<(), GpuError> {
    ctx.count_readback();
    let device = ctx.device();
    let state = Arc::new(Mutex::new(Mappings {
        left: maps.len(),
        failed: None,
        waker: None,
    }));
    for (b, bytes) in maps {
        let state = state.clone();
        b.slice(..*bytes).map_async(wgpu::MapMode::Read, move |r| {
            let mut m = lock(&state);
            m.left -= 1;
            if let Err(e) = r {
                m.failed.get_or_insert(e);
            }
            if let Some(w) = m.waker.take() {
                w.wake();
            }
        });
    }
    // Waits natively; returns at once in a browser, where the event loop maps them.
    device
        .poll(wgpu::PollType::Wait {
            submission_index: Some(index),
            timeout: None,
        })
        .map_err(|e| GpuError::device("waiting for the GPU", e))?;
    std::future::poll_fn(|cx| {
        let mut m = lock(&state);
        if m.left > 0 {
            m.waker = Some(cx.waker().clone());
            return Poll::Pending;
        }
        Poll::Ready(match m.failed.take() {
            Some(e) => Err(GpuError::device("reading results back", e)),
            None => Ok(()),
        })
    })
    .await
}

/// One compute pass of [`record_pass`]: `count` rays from `rays`, counters to `counters`.
struct Pass<'a> {
    rays: RaysBinding<'a>,
    counters: Option<&'a wgpu::Buffer>,
    count: u64,
    timestamp_writes: Option<wgpu::ComputePassTimestampWrites<'a>>,
}

impl GpuBvh {
    /// Records the traversal of `batch` into `encoder`, as one compute pass with one
    /// dispatch per chunk of at most [`rays_per_dispatch`](bvhtrace_engine::plan::rays_per_dispatch)
    /// rays. `timestamp_writes`, when given, is attached to that pass (the device needs
    /// `TIMESTAMP_QUERY`). The bind groups for the caller's buffers are made once and
    /// reused while the same buffers come back.
    ///
    /// The buffers are checked (usage and size) before anything is recorded; the caller
    /// submits the encoder. Rays are never [`bvhtrace_core::INCOMPLETE`] here unless the
    /// context's tuning sets a trip budget (CPU drivers), or the wide walk meets a wide
    /// tree deeper than its stack ([`bvhtrace_engine::walks::may_overflow`]): once the hits
    /// (and counters) are read back, [`GpuBvh::finish_incomplete`] finishes those.
    pub fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: &RayBatch<'_>,
        opts: &TraceOptions,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) -> Result<(), GpuError> {
        self.engine.supports(opts)?;
        let key = self.engine.key(opts, RayInput::Buffer, true);
        let pass = Pass {
            rays: RaysBinding::Buffer {
                rays: batch.rays,
                hits: batch.hits,
            },
            counters: batch.counters,
            count: batch.ray_count,
            timestamp_writes,
        };
        record_pass(self.context(), self.engine.arrays(), key, encoder, pass)?;
        self.engine.note_used(key)
    }

    /// Replaces the [`bvhtrace_core::INCOMPLETE`] hits of a recorded trace (read back by
    /// the caller) by the CPU walk's answer on this upload's host copy, counters too when
    /// given; returns how many were finished (0 when the upload keeps no host copy: no ray
    /// can come back incomplete).
    pub fn finish_incomplete(
        &self,
        rays: &[Ray],
        opts: &TraceOptions,
        hits: &mut [Hit],
        counters: Option<&mut [Counters]>,
    ) -> u64 {
        self.engine.finish_incomplete(rays, opts, hits, counters)
    }
}

/// Records the traversal of `pass.count` rays through `key`'s kernel, hits (and counters)
/// to the given buffers. A texture holds the whole batch in one dispatch.
fn record_pass(
    ctx: &GpuContext,
    arrays: &WgpuArrays,
    key: KernelKey,
    encoder: &mut wgpu::CommandEncoder,
    pass: Pass<'_>,
) -> Result<(), GpuError> {
    let n = pass.count;
    if let RaysBinding::Buffer { rays, hits } = pass.rays {
        check_buffer("rays", rays, n, RAY_BYTES)?;
        check_buffer("hits", hits, n, HIT_BYTES)?;
    }
    let counters = if key.counters {
        let c = pass.counters.ok_or(GpuError::BadBuffer {
            buffer: "counters",
            problem: "counters were asked for but no counters buffer was given".into(),
        })?;
        check_buffer("counters", c, n, COUNTERS_BYTES)?;
        Some(c)
    } else {
        None
    };
    let pipeline = ctx.pipeline(key)?;
    // The engine checked that the upload holds what the traversal reads.
    let (group0, _) = arrays
        .group(key.traversal)
        .ok_or(GpuError::TraversalNotUploaded {
            traversal: key.traversal,
        })?;
    let dispatches = plan_dispatches(n, ctx.limits());
    if matches!(pass.rays, RaysBinding::Texture { .. }) && dispatches.len() > 1 {
        return Err(GpuError::BadBuffer {
            buffer: "rays",
            problem: format!("{n} rays in a ray texture are more than one dispatch"),
        });
    }
    let groups = batch_groups(ctx, arrays, pass.rays, counters, n)?;
    let mut cpass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
        label: Some("bvhtrace trace"),
        timestamp_writes: pass.timestamp_writes,
    });
    cpass.set_pipeline(&pipeline);
    cpass.set_bind_group(0, group0, &[]);
    for (d, g) in dispatches.iter().zip(groups.iter()) {
        cpass.set_bind_group(1, g, &[]);
        cpass.dispatch_workgroups(d.groups_x, d.groups_y, 1);
    }
    Ok(())
}

/// The batch bind groups (one per dispatch) for these resources: made on first use and
/// kept while the same resources come back, so a caller recording every frame into the
/// same buffers makes none. At most [`BATCH_GROUPS_KEPT`] sets are kept; they hold
/// references to the buffers.
fn batch_groups(
    ctx: &GpuContext,
    arrays: &WgpuArrays,
    rays: RaysBinding<'_>,
    counters: Option<&wgpu::Buffer>,
    n: u64,
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
    let mut cache = arrays
        .batch_groups
        .lock()
        .map_err(|_| GpuError::Poisoned("batch bind groups"))?;
    if let Some(g) = cache.get(&key) {
        return Ok(g.clone());
    }
    let input = match rays {
        RaysBinding::Buffer { .. } => RayInput::Buffer,
        RaysBinding::Texture { .. } => RayInput::Texture,
    };
    let layout = ctx.batch_layout(counters.is_some(), input);
    let groups: Vec<wgpu::BindGroup> = plan_dispatches(n, ctx.limits())
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
            ctx.device().create_bind_group(&wgpu::BindGroupDescriptor {
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
