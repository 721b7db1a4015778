//! The BVH built on the device: a linear BVH (Karras 2012) in WGSL compute
//! ([`build_lbvh.wgsl`](../../../shaders/build_lbvh.wgsl)), written straight into the flat
//! layout every walk reads and read back as a [`FlatBvh`], so the CPU walks, the checks
//! and every upload take it as they take a CPU-built tree.
//!
//! The steps, each a dispatch: the centroids' bounds, 30-bit Morton codes, a stable radix
//! sort of (code, index) in four 8-bit passes, the hierarchy from common prefixes, boxes
//! bottom up, and the depth-first layout with one triangle per leaf. Same input, same
//! tree: the sort is stable and equal codes split by index.

use std::time::Instant;

use bvhtrace_core::flat::{FlatNode, FlatTriangle};
use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_kernels::TraceError;
use wgpu::util::DeviceExt;

use crate::trace::{map_all, read_mapped};
use crate::{GpuContext, GpuError};

/// Invocations per workgroup (`LBVH_WG`) and keys per radix block (`LBVH_BLOCK`).
const WG: u32 = 256;
const BLOCK: u32 = 1024;

/// What a device build cost, milliseconds of wall time.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpuBuildTimes {
    /// Uploading the triangles.
    pub upload_ms: f64,
    /// The dispatches, waited for.
    pub build_ms: f64,
    /// Reading the nodes and triangles back into a [`FlatBvh`].
    pub readback_ms: f64,
    /// Device time of each step ([`GpuBuildTimes::STAGES`]), from timestamp queries;
    /// `None` on a device without them.
    pub stages_ms: Option<[f64; 5]>,
}

impl GpuBuildTimes {
    /// The steps `stages_ms` times.
    pub const STAGES: [&'static str; 5] = [
        "bounds and Morton codes",
        "radix sort",
        "hierarchy",
        "boxes",
        "flat layout",
    ];
}

/// The entry points, in the order they run.
const ENTRIES: [&str; 8] = bvhtrace_kernels::build::LBVH_ENTRIES;

/// The bindings each entry point reads or writes (its auto layout's), in `ENTRIES` order.
const BINDINGS: [&[u32]; 8] = [
    &[0, 1, 2],
    &[0, 1, 2, 3, 4],
    &[0, 3, 7],
    &[0, 7],
    &[0, 3, 4, 5, 6, 7],
    &[0, 3, 8, 9, 10],
    &[0, 1, 4, 8, 10, 11, 12],
    &[0, 1, 4, 8, 9, 10, 11, 13, 14, 15],
];

/// The uniform block (`LbvhParams`), one per radix pass at 256-byte offsets.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    n: u32,
    shift: u32,
    blocks: u32,
    row: u32,
}

const PARAMS_STRIDE: u64 = 256;

/// One dispatch of a step: the entry point's index, its radix pass, its grid.
type Dispatch = (usize, u32, (u32, u32, u32));

/// The bindings that hold the build's output: nodes, triangles, depth.
const OUTPUT: [u32; 3] = [13, 14, 15];

/// A dispatch of `count` invocations as a grid within the device's per-dimension limit:
/// `(x, y, invocations per row)`.
fn grid(count: u64, max_dim: u32) -> (u32, u32, u32) {
    let groups = count.div_ceil(u64::from(WG)).max(1);
    let x = groups.min(u64::from(max_dim)) as u32;
    let y = groups.div_ceil(u64::from(x)) as u32;
    (x, y, x * WG)
}

/// One build's buffers, by binding (`build_lbvh.wgsl`'s group 0), and its sizes.
struct Lbvh {
    buffers: Vec<wgpu::Buffer>,
    /// Triangles, nodes, radix blocks.
    n: u64,
    nodes: u64,
    blocks: u32,
}

/// The timestamp queries around each step, and the buffers they are read through.
struct StepQueries {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
}

impl StepQueries {
    const BYTES: u64 = 2 * 8 * GpuBuildTimes::STAGES.len() as u64;

    fn new(device: &wgpu::Device) -> StepQueries {
        let buffer = |usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("lbvh timestamps"),
                size: Self::BYTES,
                usage,
                mapped_at_creation: false,
            })
        };
        use wgpu::BufferUsages as U;
        StepQueries {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("lbvh steps"),
                ty: wgpu::QueryType::Timestamp,
                count: 2 * GpuBuildTimes::STAGES.len() as u32,
            }),
            resolve: buffer(U::QUERY_RESOLVE | U::COPY_SRC),
            read: buffer(U::MAP_READ | U::COPY_DST),
        }
    }

    /// Each step's milliseconds, from the mapped read buffer (unmapped after).
    fn stages_ms(&self, queue: &wgpu::Queue) -> Result<[f64; 5], GpuError> {
        let mut ticks: Vec<u64> = Vec::with_capacity(10);
        let got = read_mapped(&self.read, Self::BYTES, &mut ticks);
        self.read.unmap();
        got?;
        let period = f64::from(queue.get_timestamp_period()) * 1e-6;
        Ok(std::array::from_fn(|k| {
            ticks[2 * k + 1].saturating_sub(ticks[2 * k]) as f64 * period
        }))
    }
}

impl Lbvh {
    /// Uploads `tris` (as `FlatTriangle`s numbered in input order) and makes every other
    /// buffer of the build (zeroed by wgpu, the bounds set to an empty range).
    fn upload(ctx: &GpuContext, tris: &[Triangle]) -> Result<Lbvh, GpuError> {
        let n = tris.len() as u64;
        let nodes = 2 * n - 1;
        let blocks = (n as u32).div_ceil(BLOCK);
        let limits = ctx.limits();
        for (buffer, bytes) in [
            ("triangles", n * 48),
            ("nodes", nodes * 32),
            ("node boxes", nodes * 32),
        ] {
            bvhtrace_kernels::check_buffer_size(limits, buffer, bytes)?;
        }
        let input: Vec<FlatTriangle> = tris
            .iter()
            .enumerate()
            .map(|(i, t)| FlatTriangle {
                v0: t[0].to_array(),
                prim: i as u32,
                v1: t[1].to_array(),
                _pad1: 0,
                v2: t[2].to_array(),
                _pad2: 0,
            })
            .collect();
        let (_, _, row) = grid(nodes, limits.max_compute_workgroups_per_dimension);
        let params: Vec<u8> = (0..4u32)
            .flat_map(|pass| {
                let mut bytes = vec![0u8; PARAMS_STRIDE as usize];
                bytes[..16].copy_from_slice(bytemuck::bytes_of(&Params {
                    n: n as u32,
                    shift: 8 * pass,
                    blocks,
                    row,
                }));
                bytes
            })
            .collect();
        let device = ctx.device();
        use wgpu::BufferUsages as U;
        let buffers = ctx.scoped("uploading a build", || {
            let init = |label: &str, contents: &[u8], usage| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage,
                })
            };
            let empty = |label: &str, bytes: u64, usage| {
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: bytes.max(16),
                    usage,
                    mapped_at_creation: false,
                })
            };
            let (storage, out) = (U::STORAGE, U::STORAGE | U::COPY_SRC);
            let bounds_init: [u32; 6] = [u32::MAX, u32::MAX, u32::MAX, 0, 0, 0];
            vec![
                init("lbvh params", &params, U::UNIFORM),
                init("lbvh input", bytemuck::cast_slice(&input), storage),
                init("lbvh bounds", bytemuck::cast_slice(&bounds_init), storage),
                empty("lbvh keys", n * 4, storage),
                empty("lbvh values", n * 4, storage),
                empty("lbvh keys (other)", n * 4, storage),
                empty("lbvh values (other)", n * 4, storage),
                empty("lbvh histograms", u64::from(blocks) * 256 * 4, storage),
                empty("lbvh children", (n - 1) * 8, storage),
                empty("lbvh first leaves", (n - 1) * 4, storage),
                empty("lbvh parents", nodes * 4, storage),
                empty("lbvh boxes", nodes * 32, storage),
                empty("lbvh arrivals", (n - 1) * 4, storage),
                empty("lbvh nodes", nodes * 32, out),
                empty("lbvh triangles", n * 48, out),
                empty("lbvh depth", 4, out),
            ]
        })?;
        Ok(Lbvh {
            buffers,
            n,
            nodes,
            blocks,
        })
    }

    /// The bind group of entry `e` in radix pass `pass`: that pass's params, and the key
    /// and value buffers swapped on odd passes.
    fn group(
        &self,
        device: &wgpu::Device,
        pipeline: &wgpu::ComputePipeline,
        e: usize,
        pass: u32,
    ) -> wgpu::BindGroup {
        let swap = pass % 2 == 1;
        let entries: Vec<wgpu::BindGroupEntry<'_>> = BINDINGS[e]
            .iter()
            .map(|&b| {
                let slot = match b {
                    3 | 4 if swap => b + 2,
                    5 | 6 if swap => b - 2,
                    b => b,
                };
                let buffer = &self.buffers[slot as usize];
                let resource = if b == 0 {
                    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer,
                        offset: u64::from(pass) * PARAMS_STRIDE,
                        size: std::num::NonZeroU64::new(16),
                    })
                } else {
                    buffer.as_entire_binding()
                };
                wgpu::BindGroupEntry {
                    binding: b,
                    resource,
                }
            })
            .collect();
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(ENTRIES[e]),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// Every step's dispatches, one compute pass per step ([`GpuBuildTimes::STAGES`]), each
    /// timed when `queries` are given.
    fn record(
        &self,
        ctx: &GpuContext,
        pipelines: &[wgpu::ComputePipeline],
        enc: &mut wgpu::CommandEncoder,
        queries: Option<&StepQueries>,
    ) {
        let max_dim = ctx.limits().max_compute_workgroups_per_dimension;
        let per_item = grid(self.n, max_dim);
        let per_block = grid(u64::from(self.blocks) * u64::from(WG), max_dim);
        let per_node = grid(self.nodes, max_dim);
        // Four radix passes of count, scan and scatter: the sorted keys and values end in
        // the first buffers.
        let sort: Vec<Dispatch> = (0..4)
            .flat_map(|pass| {
                [
                    (2, pass, per_block),
                    (3, pass, (1, 1, WG)),
                    (4, pass, per_block),
                ]
            })
            .collect();
        let steps: [&[Dispatch]; 5] = [
            &[(0, 0, per_item), (1, 0, per_item)],
            &sort,
            &[(5, 0, per_item)],
            &[(6, 0, per_item)],
            &[(7, 0, per_node)],
        ];
        for (k, step) in steps.iter().enumerate() {
            let timestamp_writes = queries.map(|q| wgpu::ComputePassTimestampWrites {
                query_set: &q.set,
                beginning_of_pass_write_index: Some(2 * k as u32),
                end_of_pass_write_index: Some(2 * k as u32 + 1),
            });
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(GpuBuildTimes::STAGES[k]),
                timestamp_writes,
            });
            for &(e, radix, (x, y, _)) in step.iter() {
                let g = self.group(ctx.device(), &pipelines[e], e, radix);
                pass.set_pipeline(&pipelines[e]);
                pass.set_bind_group(0, &g, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        if let Some(q) = queries {
            enc.resolve_query_set(
                &q.set,
                0..2 * GpuBuildTimes::STAGES.len() as u32,
                &q.resolve,
                0,
            );
            enc.copy_buffer_to_buffer(&q.resolve, 0, &q.read, 0, StepQueries::BYTES);
        }
    }

    /// Copies of the output (nodes, triangles, depth) into buffers to map.
    fn copy_out(&self, device: &wgpu::Device, enc: &mut wgpu::CommandEncoder) -> Vec<wgpu::Buffer> {
        OUTPUT
            .iter()
            .map(|&b| {
                let src = &self.buffers[b as usize];
                let dst = device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("lbvh readback"),
                    size: src.size(),
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                enc.copy_buffer_to_buffer(src, 0, &dst, 0, src.size());
                dst
            })
            .collect()
    }

    /// The mapped copies as a tree (the copies unmapped after).
    fn read(&self, reads: &[wgpu::Buffer]) -> Result<FlatBvh, GpuError> {
        let mut nodes: Vec<FlatNode> = Vec::with_capacity(self.nodes as usize);
        let mut tris: Vec<FlatTriangle> = Vec::with_capacity(self.n as usize);
        let mut depth: Vec<u32> = Vec::with_capacity(1);
        let got = read_mapped(&reads[0], self.nodes * 32, &mut nodes)
            .and_then(|_| read_mapped(&reads[1], self.n * 48, &mut tris))
            .and_then(|_| read_mapped(&reads[2], 4, &mut depth));
        for r in reads {
            r.unmap();
        }
        got?;
        Ok(FlatBvh::from_parts(nodes, tris, depth[0]))
    }
}

impl GpuContext {
    /// Builds a linear BVH over `tris` on the device and reads it back (one triangle per
    /// leaf, `prim` the triangle's index in `tris`), with the time of each step. The
    /// tree passes [`FlatBvh::check_invariants`]; build its escape links or wide layout
    /// on the CPU as for any tree. One triangle is built on the CPU (there is nothing to
    /// sort); no triangle is [`TraceError::EmptyBvh`]; a non-finite corner, or more
    /// triangles than the device's buffers hold, an error naming it. The pipelines are
    /// compiled on the first build and kept.
    pub fn build_lbvh(&self, tris: &[Triangle]) -> Result<(FlatBvh, GpuBuildTimes), GpuError> {
        let bad_input = |e: &dyn std::fmt::Display| TraceError::BadBuffer {
            buffer: "triangles",
            problem: e.to_string(),
        };
        match tris.len() {
            0 => return Err(TraceError::EmptyBvh),
            1 => {
                let bvh = FlatBvh::build(tris, &Default::default()).map_err(|e| bad_input(&e))?;
                return Ok((bvh, GpuBuildTimes::default()));
            }
            _ => bvhtrace_core::mesh::validate_triangles(tris).map_err(|e| bad_input(&e))?,
        }
        let pipelines = self.lbvh_pipelines()?;
        let t0 = Instant::now();
        let lbvh = Lbvh::upload(self, tris)?;
        let upload_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        let device = self.device();
        let queries = self.has_timestamps().then(|| StepQueries::new(device));
        let (index, reads) = self.scoped("building a BVH on the device", || {
            let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("bvhtrace lbvh"),
            });
            lbvh.record(self, &pipelines, &mut enc, queries.as_ref());
            let reads = lbvh.copy_out(device, &mut enc);
            (self.queue().submit([enc.finish()]), reads)
        })?;
        let mut maps: Vec<(&wgpu::Buffer, u64)> = reads.iter().map(|b| (b, b.size())).collect();
        maps.extend(queries.as_ref().map(|q| (&q.read, StepQueries::BYTES)));
        pollster::block_on(map_all(device, index, &maps))?;
        let stages_ms = queries.map(|q| q.stages_ms(self.queue())).transpose()?;
        let build_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = Instant::now();
        let bvh = lbvh.read(&reads)?;
        Ok((
            bvh,
            GpuBuildTimes {
                upload_ms,
                build_ms,
                readback_ms: t2.elapsed().as_secs_f64() * 1e3,
                stages_ms,
            },
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grids_stay_within_the_limit() {
        assert_eq!(grid(1, 65535), (1, 1, 256));
        let (x, y, row) = grid(1 << 24, 65535);
        assert!(x <= 65535 && u64::from(x) * u64::from(y) * 256 >= 1 << 24);
        assert_eq!(row, x * 256);
    }
}
