//! The clustering builder's host side: its buffers, and its iterations recorded in batches
//! whose sizes the device sets itself (indirect dispatch), with the cluster count read
//! back after each batch until one cluster is left.

use bvhtrace_kernels::TraceError;

use super::{Build, GpuBuildOptions, ReadBack, StepQueries, empty, grid, init};
use crate::trace::read_mapped;
use crate::{GpuContext, GpuError};

/// The uniform block of `build_ploc.wgsl` (`PlocParams`).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PlocParams {
    radius: u32,
    max_leaf: u32,
    cost_traversal: f32,
    cost_intersection: f32,
}

/// Entry points, as indices into `GpuBuilderKind::Ploc.entries()` (after the five Morton
/// steps).
const LEAVES: usize = 5;
const PREPARE: usize = 6;
const NEIGHBOURS: usize = 7;
const MERGE: usize = 8;
const BLOCK_SUMS: usize = 9;
const SCAN: usize = 10;
const COMPACT: usize = 11;
const FLATTEN: usize = 12;

/// Bindings: the state, the dispatch sizes, the flat nodes and triangles.
const STATE: usize = 9;
const ARGS: usize = 10;
const OUT_NODES: u32 = 18;
const OUT_TRIANGLES: u32 = 19;

/// The state's words (`ploc_state`): clusters left, the depth, iterations run.
const LEFT: usize = 2;
const DEPTH: usize = 3;
const ITERATIONS: usize = 5;

/// Iterations a batch records. Clusters shrink by about a third an iteration, so the
/// first batch finishes most builds; iterations past the last cluster dispatch nothing.
const BATCH: u32 = 24;

/// Batches that get timestamps.
const TIMED_BATCHES: u32 = 8;

/// The buffers of bindings 8 to 19 (`build_ploc.wgsl`).
pub(super) fn buffers(device: &wgpu::Device, n: u64, opts: &GpuBuildOptions) -> Vec<wgpu::Buffer> {
    use wgpu::BufferUsages as U;
    let nodes = 2 * n - 1;
    let blocks = n.div_ceil(1024);
    let params = PlocParams {
        radius: opts.radius,
        max_leaf: opts.max_leaf_size,
        cost_traversal: opts.cost_traversal,
        cost_intersection: opts.cost_intersection,
    };
    let count = n as u32;
    // The last iteration's clusters (none yet), the next node number, clusters left,
    // depth, blocks, iterations, pairing places.
    let state: [u32; 8] = [u32::MAX, count, count, 0, 0, 0, 0, 0];
    let (storage, out) = (U::STORAGE, U::STORAGE | U::COPY_SRC);
    vec![
        init(
            device,
            "ploc params",
            bytemuck::bytes_of(&params),
            U::UNIFORM,
        ),
        init(device, "ploc state", bytemuck::cast_slice(&state), out),
        empty(device, "ploc dispatch sizes", 24, storage | U::INDIRECT),
        empty(device, "ploc clusters", n * 4, storage),
        empty(device, "ploc merged", n * 4, storage),
        empty(device, "ploc nearest", n * 4, storage),
        empty(device, "ploc block sums", blocks * 4, storage),
        empty(device, "ploc boxes", nodes * 32, storage),
        empty(device, "ploc info", nodes * 16, storage),
        empty(device, "ploc links", nodes * 16, storage),
        empty(device, "ploc nodes", nodes * 32, out),
        empty(device, "ploc triangles", n * 48, out),
    ]
}

/// The clusters left, from the mapped copy of the state (unmapped after).
fn clusters_left(read: &wgpu::Buffer) -> Result<u32, GpuError> {
    let mut state: Vec<u32> = Vec::new();
    let got = read_mapped(read, 32, &mut state);
    read.unmap();
    got?;
    Ok(state[LEFT])
}

impl Build {
    /// `BATCH` iterations in one compute pass, the sizes of all but the fixed ones read
    /// from the dispatch-size buffer `ploc_prepare` writes.
    fn record_batch(
        &self,
        groups: &[Option<wgpu::BindGroup>],
        pipelines: &[wgpu::ComputePipeline],
        enc: &mut wgpu::CommandEncoder,
        queries: Option<&StepQueries>,
    ) {
        let timestamp_writes = queries.and_then(|q| q.writes("clustering"));
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("clustering"),
            timestamp_writes,
        });
        let args = &self.buffers[ARGS];
        for _ in 0..BATCH {
            for (e, indirect) in [
                (PREPARE, None),
                (NEIGHBOURS, Some(0)),
                (MERGE, Some(0)),
                (BLOCK_SUMS, Some(12)),
                (SCAN, None),
                (COMPACT, Some(12)),
            ] {
                pass.set_pipeline(&pipelines[e]);
                pass.set_bind_group(0, groups[e].as_ref(), &[]);
                match indirect {
                    Some(offset) => pass.dispatch_workgroups_indirect(args, offset),
                    None => pass.dispatch_workgroups(1, 1, 1),
                }
            }
        }
    }

    /// A copy of the state to map.
    fn copy_state(&self, device: &wgpu::Device, enc: &mut wgpu::CommandEncoder) -> wgpu::Buffer {
        self.copy_out(device, enc, &[STATE as u32]).remove(0)
    }
}

/// Runs the clustering build whose buffers `build` holds: the sort, the leaves and a
/// first batch in one submission, more batches while clusters are left, then the flat
/// layout. Returns the tree read back and the iterations that ran. Each batch's count is
/// awaited, so in a browser the event loop runs meanwhile.
pub(super) async fn run(
    ctx: &GpuContext,
    build: &Build,
    pipelines: &[wgpu::ComputePipeline],
) -> Result<(ReadBack, u32), GpuError> {
    let device = ctx.device();
    let max_dim = ctx.limits().max_compute_workgroups_per_dimension;
    let queries = ctx
        .has_timestamps()
        .then(|| StepQueries::new(device, 4 + TIMED_BATCHES));
    let groups: Vec<Option<wgpu::BindGroup>> = (0..pipelines.len())
        .map(|e| {
            (PREPARE..=COMPACT)
                .contains(&e)
                .then(|| build.group(device, &pipelines[e], build.step(e), 0))
        })
        .collect();
    let mut enc = device.create_command_encoder(&Default::default());
    build.record_sort(ctx, pipelines, &mut enc, queries.as_ref());
    let per_item = grid(build.n, max_dim);
    build.pass(
        ctx,
        pipelines,
        &mut enc,
        queries.as_ref(),
        "clustering",
        &[(LEAVES, 0, per_item)],
    );
    let mut left = build.n as u32;
    let mut batches = 0u32;
    let mut first = Some(enc);
    while left > 1 {
        let mut enc = first
            .take()
            .unwrap_or_else(|| device.create_command_encoder(&Default::default()));
        build.record_batch(&groups, pipelines, &mut enc, queries.as_ref());
        let read = build.copy_state(device, &mut enc);
        super::submit_and_map_async(
            ctx,
            "building a BVH on the device",
            enc,
            &[(&read, read.size())],
        )
        .await?;
        let now = clusters_left(&read)?;
        batches += 1;
        // Every iteration merges at least once, so the count falls every batch; a batch
        // in which it does not is a fault, reported rather than looped on.
        if now >= left {
            return Err(TraceError::Unsupported {
                backend: "device builder",
                what: format!(
                    "a finished clustering: it stopped at {now} clusters after {batches} \
                     batches"
                ),
            });
        }
        left = now;
    }
    let mut enc = device.create_command_encoder(&Default::default());
    let per_node = grid(build.nodes, max_dim);
    build.pass(
        ctx,
        pipelines,
        &mut enc,
        queries.as_ref(),
        "flat layout",
        &[(FLATTEN, 0, per_node)],
    );
    let done = build
        .read_back(
            ctx,
            enc,
            [OUT_NODES, OUT_TRIANGLES, STATE as u32],
            DEPTH,
            queries,
        )
        .await?;
    let iterations = done.words[ITERATIONS];
    Ok((done, iterations))
}
