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

use bvhtrace_kernels::build::lbvh_source;

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

/// A dispatch of `count` invocations as a grid within the device's per-dimension limit:
/// `(x, y, invocations per row)`.
fn grid(count: u64, max_dim: u32) -> (u32, u32, u32) {
    let groups = count.div_ceil(u64::from(WG)).max(1);
    let x = groups.min(u64::from(max_dim)) as u32;
    let y = groups.div_ceil(u64::from(x)) as u32;
    (x, y, x * WG)
}

impl GpuContext {
    /// Builds a linear BVH over `tris` on the device and reads it back (one triangle per
    /// leaf, `prim` the triangle's index in `tris`), with the time of each step. The
    /// tree passes [`FlatBvh::check_invariants`]; build its escape links or wide layout
    /// on the CPU as for any tree. One triangle is built on the CPU (there is nothing to
    /// sort); no triangle is [`TraceError::EmptyBvh`]; a non-finite corner, or more
    /// triangles than the device's buffers hold, an error naming it.
    pub fn build_lbvh(&self, tris: &[Triangle]) -> Result<(FlatBvh, GpuBuildTimes), GpuError> {
        let n = tris.len();
        if n == 0 {
            return Err(TraceError::EmptyBvh);
        }
        bvhtrace_core::mesh::validate_triangles(tris).map_err(|e| TraceError::BadBuffer {
            buffer: "triangles",
            problem: e.to_string(),
        })?;
        if n == 1 {
            let bvh =
                FlatBvh::build(tris, &Default::default()).map_err(|e| TraceError::BadBuffer {
                    buffer: "triangles",
                    problem: e.to_string(),
                })?;
            return Ok((bvh, GpuBuildTimes::default()));
        }
        let n32 = n as u32;
        let nodes = 2 * n as u64 - 1;
        let limits = self.limits();
        for (buffer, bytes) in [
            ("triangles", n as u64 * 48),
            ("nodes", nodes * 32),
            ("node boxes", nodes * 32),
        ] {
            bvhtrace_kernels::check_buffer_size(limits, buffer, bytes)?;
        }
        let device = self.device();
        let t0 = Instant::now();
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
        let blocks = n32.div_ceil(BLOCK);
        let max_dim = limits.max_compute_workgroups_per_dimension;
        let (_, _, row) = grid(nodes, max_dim);
        let params: Vec<u8> = (0..4u32)
            .flat_map(|pass| {
                let mut bytes = vec![0u8; PARAMS_STRIDE as usize];
                bytes[..16].copy_from_slice(bytemuck::bytes_of(&Params {
                    n: n32,
                    shift: 8 * pass,
                    blocks,
                    row,
                }));
                bytes
            })
            .collect();
        use wgpu::BufferUsages as U;
        let (made, pipelines) = self.scoped("building a BVH on the device", || {
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
            let storage = U::STORAGE;
            let bounds_init: [u32; 6] = [u32::MAX, u32::MAX, u32::MAX, 0, 0, 0];
            let made = [
                init("lbvh params", &params, U::UNIFORM),
                init("lbvh input", bytemuck::cast_slice(&input), storage),
                init("lbvh bounds", bytemuck::cast_slice(&bounds_init), storage),
                empty("lbvh keys", n as u64 * 4, storage),
                empty("lbvh values", n as u64 * 4, storage),
                empty("lbvh keys (other)", n as u64 * 4, storage),
                empty("lbvh values (other)", n as u64 * 4, storage),
                empty("lbvh histograms", u64::from(blocks) * 256 * 4, storage),
                empty("lbvh children", (n as u64 - 1) * 8, storage),
                empty("lbvh first leaves", (n as u64 - 1) * 4, storage),
                empty("lbvh parents", nodes * 4, storage),
                empty("lbvh boxes", nodes * 32, storage),
                init(
                    "lbvh arrivals",
                    bytemuck::cast_slice(&vec![0u32; n - 1]),
                    storage,
                ),
                empty("lbvh nodes", nodes * 32, storage | U::COPY_SRC),
                empty("lbvh triangles", n as u64 * 48, storage | U::COPY_SRC),
                init("lbvh depth", &[0; 4], storage | U::COPY_SRC),
            ];
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("bvhtrace lbvh"),
                source: wgpu::ShaderSource::Wgsl(lbvh_source().into()),
            });
            let pipelines: Vec<wgpu::ComputePipeline> = ENTRIES
                .iter()
                .map(|entry| {
                    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                        label: Some(entry),
                        layout: None,
                        module: &module,
                        entry_point: Some(entry),
                        compilation_options: Default::default(),
                        cache: None,
                    })
                })
                .collect();
            (made, pipelines)
        })?;
        let upload_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        // The bind group of entry `e`, radix pass `pass` (its params, and which of the two
        // key and value buffers it reads).
        let group = |e: usize, pass: u32| {
            let swap = pass % 2 == 1;
            let entries: Vec<wgpu::BindGroupEntry<'_>> = BINDINGS[e]
                .iter()
                .map(|&b| {
                    let buffer = match b {
                        3 if swap => &made[5],
                        4 if swap => &made[6],
                        5 if swap => &made[3],
                        6 if swap => &made[4],
                        b => &made[b as usize],
                    };
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
                layout: &pipelines[e].get_bind_group_layout(0),
                entries: &entries,
            })
        };
        let queries = self.has_timestamps().then(|| {
            let set = device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("lbvh steps"),
                ty: wgpu::QueryType::Timestamp,
                count: 10,
            });
            let buffer = |usage| {
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("lbvh timestamps"),
                    size: 80,
                    usage,
                    mapped_at_creation: false,
                })
            };
            (
                set,
                buffer(U::QUERY_RESOLVE | U::COPY_SRC),
                buffer(U::MAP_READ | U::COPY_DST),
            )
        });
        let per_item = grid(n as u64, max_dim);
        let per_block = grid(u64::from(blocks) * u64::from(WG), max_dim);
        let per_node = grid(nodes, max_dim);
        let index = self.scoped("building a BVH on the device", || {
            let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("bvhtrace lbvh"),
            });
            // One compute pass per step, each timed when the device has timestamps.
            let steps: [&[Dispatch]; 5] = [
                &[(0, 0, per_item), (1, 0, per_item)],
                // Four passes: the sorted keys and values end in the first buffers.
                &[
                    (2, 0, per_block),
                    (3, 0, (1, 1, WG)),
                    (4, 0, per_block),
                    (2, 1, per_block),
                    (3, 1, (1, 1, WG)),
                    (4, 1, per_block),
                    (2, 2, per_block),
                    (3, 2, (1, 1, WG)),
                    (4, 2, per_block),
                    (2, 3, per_block),
                    (3, 3, (1, 1, WG)),
                    (4, 3, per_block),
                ],
                &[(5, 0, per_item)],
                &[(6, 0, per_item)],
                &[(7, 0, per_node)],
            ];
            for (k, step) in steps.iter().enumerate() {
                let timestamp_writes =
                    queries
                        .as_ref()
                        .map(|(set, _, _)| wgpu::ComputePassTimestampWrites {
                            query_set: set,
                            beginning_of_pass_write_index: Some(2 * k as u32),
                            end_of_pass_write_index: Some(2 * k as u32 + 1),
                        });
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(GpuBuildTimes::STAGES[k]),
                    timestamp_writes,
                });
                for &(e, radix, (x, y, _)) in step.iter() {
                    let g = group(e, radix);
                    pass.set_pipeline(&pipelines[e]);
                    pass.set_bind_group(0, &g, &[]);
                    pass.dispatch_workgroups(x, y, 1);
                }
            }
            if let Some((set, resolve, read)) = &queries {
                enc.resolve_query_set(set, 0..10, resolve, 0);
                enc.copy_buffer_to_buffer(resolve, 0, read, 0, 80);
            }
            let read = |label: &str, bytes: u64| {
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: bytes,
                    usage: U::MAP_READ | U::COPY_DST,
                    mapped_at_creation: false,
                })
            };
            let reads = [
                read("lbvh nodes readback", nodes * 32),
                read("lbvh triangles readback", n as u64 * 48),
                read("lbvh depth readback", 4),
            ];
            for (src, dst) in [13usize, 14, 15].iter().zip(&reads) {
                enc.copy_buffer_to_buffer(&made[*src], 0, dst, 0, dst.size());
            }
            (self.queue().submit([enc.finish()]), reads)
        })?;
        let (index, reads) = index;
        let mut maps: Vec<(&wgpu::Buffer, u64)> = reads.iter().map(|b| (b, b.size())).collect();
        maps.extend(queries.as_ref().map(|(_, _, read)| (read, 80)));
        pollster::block_on(map_all(device, index, &maps))?;
        let stages_ms = match &queries {
            Some((_, _, read)) => {
                let mut ticks: Vec<u64> = Vec::with_capacity(10);
                let got = read_mapped(read, 80, &mut ticks);
                read.unmap();
                got?;
                let period = f64::from(self.queue().get_timestamp_period()) * 1e-6;
                Some(std::array::from_fn(|k| {
                    ticks[2 * k + 1].saturating_sub(ticks[2 * k]) as f64 * period
                }))
            }
            None => None,
        };
        let build_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = Instant::now();
        let mut flat_nodes: Vec<FlatNode> = Vec::with_capacity(nodes as usize);
        let mut flat_tris: Vec<FlatTriangle> = Vec::with_capacity(n);
        let mut depth: Vec<u32> = Vec::with_capacity(1);
        let got = read_mapped(&reads[0], nodes * 32, &mut flat_nodes)
            .and_then(|_| read_mapped(&reads[1], n as u64 * 48, &mut flat_tris))
            .and_then(|_| read_mapped(&reads[2], 4, &mut depth));
        for r in &reads {
            r.unmap();
        }
        got?;
        let bvh = FlatBvh::from_parts(flat_nodes, flat_tris, depth[0]);
        let readback_ms = t2.elapsed().as_secs_f64() * 1e3;
        Ok((
            bvh,
            GpuBuildTimes {
                upload_ms,
                build_ms,
                readback_ms,
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
