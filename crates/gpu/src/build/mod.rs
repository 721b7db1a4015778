//! The BVH built on the device, in WGSL compute, written straight into the flat layout
//! every walk reads and read back as a [`FlatBvh`], so the CPU walks, the checks and every
//! upload take it as they take a CPU-built tree.
//!
//! Both builders start the same way ([`build_morton.wgsl`](../../../shaders/build_morton.wgsl)):
//! the centroids' bounds, 30-bit Morton codes, and a stable radix sort of (code, index) in
//! four 8-bit passes. Then:
//! * [`GpuBuilderKind::Lbvh`] ([`build_lbvh.wgsl`](../../../shaders/build_lbvh.wgsl)): the
//!   hierarchy from common prefixes (Karras 2012), boxes bottom up, one triangle a leaf;
//!   the fastest build, the poorest tree;
//! * [`GpuBuilderKind::Ploc`] ([`build_ploc.wgsl`](../../../shaders/build_ploc.wgsl)):
//!   locally-ordered clustering (Meister and Bittner 2018), mutual nearest neighbours
//!   along the Morton order merged until one cluster is left, leaves collapsed by the
//!   SAH; a tree close to the CPU's binned SAH.
//!
//! Same input, same tree: the sort is stable, equal codes split by index, and the
//! clustering's ties break by place.

mod morph;
mod ploc;
mod refit;
mod skin;
mod top;

pub use morph::GpuMorph;
pub use refit::{GpuRefit, RefitTimes, RefitVertices};
pub use skin::GpuSkin;

use bvhtrace_core::flat::{FlatNode, FlatTriangle};
use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_kernels::TraceError;
use bvhtrace_kernels::build::Step;
use web_time::Instant;
use wgpu::util::DeviceExt;

use crate::trace::{map_all, read_mapped};
use crate::{GpuContext, GpuError};

/// Invocations per workgroup (`MORTON_WG`) and keys per radix block (`MORTON_BLOCK`).
const WG: u32 = 256;
const BLOCK: u32 = 1024;

/// Which device builder ([`GpuContext::build_bvh`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum GpuBuilderKind {
    /// A linear BVH (Karras 2012): one triangle a leaf, the fastest build.
    Lbvh,
    /// Locally-ordered clustering (PLOC), leaves collapsed by the SAH: the better tree.
    #[default]
    Ploc,
}

impl GpuBuilderKind {
    /// Both, in the order reports list them.
    pub const ALL: [GpuBuilderKind; 2] = [GpuBuilderKind::Lbvh, GpuBuilderKind::Ploc];

    /// The name on the command line (`gpu-lbvh`, `gpu-ploc`).
    pub fn name(self) -> &'static str {
        match self {
            GpuBuilderKind::Lbvh => "gpu-lbvh",
            GpuBuilderKind::Ploc => "gpu-ploc",
        }
    }

    /// The steps after the sort.
    fn steps(self) -> &'static [Step] {
        match self {
            GpuBuilderKind::Lbvh => &bvhtrace_kernels::build::LBVH_STEPS,
            GpuBuilderKind::Ploc => &bvhtrace_kernels::build::PLOC_STEPS,
        }
    }

    /// The builder's WGSL module.
    pub(crate) fn source(self) -> String {
        match self {
            GpuBuilderKind::Lbvh => bvhtrace_kernels::build::lbvh_source(),
            GpuBuilderKind::Ploc => bvhtrace_kernels::build::ploc_source(),
        }
    }

    /// Every entry point the builder runs, the Morton steps first.
    pub(crate) fn entries(self) -> impl Iterator<Item = &'static str> {
        bvhtrace_kernels::build::MORTON_STEPS
            .iter()
            .chain(self.steps())
            .map(|(entry, _)| *entry)
    }
}

impl std::fmt::Display for GpuBuilderKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// How to build on the device ([`GpuContext::build_bvh`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GpuBuildOptions {
    /// Which builder.
    pub builder: GpuBuilderKind,
    /// [`GpuBuilderKind::Ploc`]: how many places each side a cluster searches for its
    /// nearest neighbour (1..=64; 16 by default, as in the paper).
    pub radius: u32,
    /// [`GpuBuilderKind::Ploc`]: the most triangles a leaf may hold (1..=16; 8, as
    /// `BuildOptions` has).
    pub max_leaf_size: u32,
    /// [`GpuBuilderKind::Ploc`]: the SAH cost of a traversal step, relative to
    /// `cost_intersection` (the leaf collapse's rule, as `BuildOptions` has).
    pub cost_traversal: f32,
    /// [`GpuBuilderKind::Ploc`]: the SAH cost of a triangle test.
    pub cost_intersection: f32,
}

impl Default for GpuBuildOptions {
    fn default() -> Self {
        let cpu = bvhtrace_core::BuildOptions::default();
        GpuBuildOptions {
            builder: GpuBuilderKind::default(),
            radius: 16,
            max_leaf_size: cpu.max_leaf_size as u32,
            cost_traversal: cpu.cost_traversal,
            cost_intersection: cpu.cost_intersection,
        }
    }
}

impl GpuBuildOptions {
    /// The options with `builder`, the rest default.
    pub fn with_builder(builder: GpuBuilderKind) -> Self {
        GpuBuildOptions {
            builder,
            ..Default::default()
        }
    }

    /// A setting out of range, as an error naming it.
    fn check(&self) -> Result<(), GpuError> {
        let bad = |problem: String| {
            Err(TraceError::BadBuffer {
                buffer: "device build options",
                problem,
            })
        };
        if !(1..=64).contains(&self.radius) {
            return bad(format!("radius {} is outside 1..=64", self.radius));
        }
        if !(1..=16).contains(&self.max_leaf_size) {
            return bad(format!(
                "max_leaf_size {} is outside 1..=16",
                self.max_leaf_size
            ));
        }
        let costs = [self.cost_traversal, self.cost_intersection];
        if costs.iter().any(|c| !c.is_finite() || *c <= 0.0) {
            return bad(format!("costs {costs:?} must be finite and positive"));
        }
        Ok(())
    }
}

/// What a device build cost, milliseconds of wall time.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GpuBuildTimes {
    /// Uploading the triangles.
    pub upload_ms: f64,
    /// The dispatches, waited for.
    pub build_ms: f64,
    /// Reading the nodes and triangles back into a [`FlatBvh`].
    pub readback_ms: f64,
    /// Device time of each step, in the order they ran (for example "radix sort"), from
    /// timestamp queries; empty on a device without them.
    pub stages_ms: Vec<(&'static str, f64)>,
    /// [`GpuBuilderKind::Ploc`]: the clustering's iterations (0 for the linear BVH).
    pub iterations: u32,
}

/// The uniform block of the Morton steps (`MortonParams`), one per radix pass at
/// 256-byte offsets.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct MortonParams {
    n: u32,
    shift: u32,
    blocks: u32,
    row: u32,
}

const PARAMS_STRIDE: u64 = 256;

/// One dispatch: the entry point's index in [`GpuBuilderKind::entries`], its radix pass,
/// its grid.
type Dispatch = (usize, u32, (u32, u32, u32));

/// A dispatch of `count` invocations as a grid within the device's per-dimension limit:
/// `(x, y, invocations per row)`.
fn grid(count: u64, max_dim: u32) -> (u32, u32, u32) {
    let groups = count.div_ceil(u64::from(WG)).max(1);
    let x = groups.min(u64::from(max_dim)) as u32;
    let y = groups.div_ceil(u64::from(x)) as u32;
    (x, y, x * WG)
}

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
            wgpu::ComputePassTimestampWrites {
                query_set: &self.set,
                beginning_of_pass_write_index: Some(2 * k),
                end_of_pass_write_index: Some(2 * k + 1),
            }
        })
    }

    /// Resolves the pairs written so far into the read buffer.
    fn resolve(&self, enc: &mut wgpu::CommandEncoder) {
        let used = self.names.borrow().len() as u32;
        if used > 0 {
            enc.resolve_query_set(&self.set, 0..2 * used, &self.resolve, 0);
            enc.copy_buffer_to_buffer(&self.resolve, 0, &self.read, 0, 16 * u64::from(used));
        }
    }

    fn bytes(&self) -> u64 {
        (16 * self.names.borrow().len() as u64).max(16)
    }

    /// Each step's milliseconds, pairs of one name summed, from the mapped read buffer
    /// (unmapped after).
    fn stages_ms(&self, queue: &wgpu::Queue) -> Result<Vec<(&'static str, f64)>, GpuError> {
        let mut ticks: Vec<u64> = Vec::new();
        let got = read_mapped(&self.read, self.bytes(), &mut ticks);
        self.read.unmap();
        got?;
        let period = f64::from(queue.get_timestamp_period()) * 1e-6;
        let mut out: Vec<(&'static str, f64)> = Vec::new();
        for (k, name) in self.names.borrow().iter().enumerate() {
            let ms = ticks[2 * k + 1].saturating_sub(ticks[2 * k]) as f64 * period;
            match out.iter_mut().find(|(n, _)| n == name) {
                Some((_, sum)) => *sum += ms,
                None => out.push((name, ms)),
            }
        }
        Ok(out)
    }
}

/// One build's buffers, by binding (group 0 of the builder's module), and its sizes.
struct Build {
    kind: GpuBuilderKind,
    buffers: Vec<wgpu::Buffer>,
    /// Triangles, nodes, radix blocks.
    n: u64,
    nodes: u64,
    blocks: u32,
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
    let mapped = map_all(ctx.device(), index, maps).await;
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
/// other, copied into one read-back buffer, submitted, waited for and returned.
fn read_after(
    ctx: &GpuContext,
    during: &'static str,
    mut enc: wgpu::CommandEncoder,
    sources: &[(&wgpu::Buffer, u64)],
) -> Result<Vec<u8>, GpuError> {
    let total: u64 = sources.iter().map(|(_, n)| n).sum();
    let usage = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
    let read = empty(ctx.device(), "read back", total, usage);
    let mut at = 0;
    for &(src, n) in sources {
        enc.copy_buffer_to_buffer(src, 0, &read, at, n);
        at += n;
    }
    submit_and_map(ctx, during, enc, &[(&read, total)])?;
    let mut bytes: Vec<u8> = Vec::new();
    let got = read_mapped(&read, total, &mut bytes);
    read.unmap();
    got.map(|_| bytes)
}

impl Build {
    /// Uploads `tris` (as `FlatTriangle`s numbered in input order) and makes the Morton
    /// steps' buffers (bindings 0 to 7) and the builder's.
    fn upload(
        ctx: &GpuContext,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<Build, GpuError> {
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
                bytes[..16].copy_from_slice(bytemuck::bytes_of(&MortonParams {
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
            let storage = U::STORAGE;
            let bounds_init: [u32; 6] = [u32::MAX, u32::MAX, u32::MAX, 0, 0, 0];
            let mut b = vec![
                init(device, "morton params", &params, U::UNIFORM),
                init(
                    device,
                    "morton input",
                    bytemuck::cast_slice(&input),
                    storage,
                ),
                init(
                    device,
                    "morton bounds",
                    bytemuck::cast_slice(&bounds_init),
                    storage,
                ),
                empty(device, "morton keys", n * 4, storage),
                empty(device, "morton values", n * 4, storage),
                empty(device, "morton keys (other)", n * 4, storage),
                empty(device, "morton values (other)", n * 4, storage),
                empty(
                    device,
                    "morton histograms",
                    u64::from(blocks) * 256 * 4,
                    storage,
                ),
            ];
            match opts.builder {
                GpuBuilderKind::Lbvh => b.extend(lbvh_buffers(device, n)),
                GpuBuilderKind::Ploc => b.extend(ploc::buffers(device, n, opts)),
            }
            b
        })?;
        Ok(Build {
            kind: opts.builder,
            buffers,
            n,
            nodes,
            blocks,
        })
    }

    /// The bind group of `pipelines[e]` (binding `bindings`) in radix pass `pass`: that
    /// pass's params, and the key and value buffers swapped on odd passes.
    fn group(
        &self,
        device: &wgpu::Device,
        pipeline: &wgpu::ComputePipeline,
        (entry, bindings): Step,
        pass: u32,
    ) -> wgpu::BindGroup {
        let swap = pass % 2 == 1;
        let entries: Vec<wgpu::BindGroupEntry<'_>> = bindings
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
            label: Some(entry),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// The step of entry `e` ([`GpuBuilderKind::entries`] order).
    fn step(&self, e: usize) -> Step {
        let morton = &bvhtrace_kernels::build::MORTON_STEPS;
        morton
            .get(e)
            .copied()
            .unwrap_or_else(|| self.kind.steps()[e - morton.len()])
    }

    /// One compute pass named `name` (timed when `queries` has a pair left) running
    /// `dispatches` in order.
    fn pass(
        &self,
        ctx: &GpuContext,
        pipelines: &[wgpu::ComputePipeline],
        enc: &mut wgpu::CommandEncoder,
        queries: Option<&StepQueries>,
        name: &'static str,
        dispatches: &[Dispatch],
    ) {
        let timestamp_writes = queries.and_then(|q| q.writes(name));
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(name),
            timestamp_writes,
        });
        for &(e, radix, (x, y, _)) in dispatches {
            let g = self.group(ctx.device(), &pipelines[e], self.step(e), radix);
            pass.set_pipeline(&pipelines[e]);
            pass.set_bind_group(0, &g, &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
    }

    /// The Morton steps: bounds and codes, then the four radix passes of count, scan and
    /// scatter (the sorted keys and values end in the first buffers).
    fn record_sort(
        &self,
        ctx: &GpuContext,
        pipelines: &[wgpu::ComputePipeline],
        enc: &mut wgpu::CommandEncoder,
        queries: Option<&StepQueries>,
    ) {
        let max_dim = ctx.limits().max_compute_workgroups_per_dimension;
        let per_item = grid(self.n, max_dim);
        let per_block = grid(u64::from(self.blocks) * u64::from(WG), max_dim);
        let sort: Vec<Dispatch> = (0..4)
            .flat_map(|pass| {
                [
                    (2, pass, per_block),
                    (3, pass, (1, 1, WG)),
                    (4, pass, per_block),
                ]
            })
            .collect();
        let codes = [(0, 0, per_item), (1, 0, per_item)];
        self.pass(
            ctx,
            pipelines,
            enc,
            queries,
            "bounds and Morton codes",
            &codes,
        );
        self.pass(ctx, pipelines, enc, queries, "radix sort", &sort);
    }

    /// Copies of the buffers at `bindings` into buffers to map.
    fn copy_out(
        &self,
        device: &wgpu::Device,
        enc: &mut wgpu::CommandEncoder,
        bindings: &[u32],
    ) -> Vec<wgpu::Buffer> {
        bindings
            .iter()
            .map(|&b| {
                let src = &self.buffers[b as usize];
                let dst = empty(
                    device,
                    "build readback",
                    src.size(),
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                );
                enc.copy_buffer_to_buffer(src, 0, &dst, 0, src.size());
                dst
            })
            .collect()
    }

    /// The end of every build: copies of `outputs` (the flat nodes, the triangles and a
    /// buffer of `u32` holding the depth at `depth_at`) and the timestamps recorded into
    /// `enc`, which is submitted and waited for; then the tree read back.
    async fn read_back(
        &self,
        ctx: &GpuContext,
        mut enc: wgpu::CommandEncoder,
        outputs: [u32; 3],
        depth_at: usize,
        queries: Option<StepQueries>,
    ) -> Result<ReadBack, GpuError> {
        let reads = self.copy_out(ctx.device(), &mut enc, &outputs);
        if let Some(q) = &queries {
            q.resolve(&mut enc);
        }
        let mut maps: Vec<(&wgpu::Buffer, u64)> = reads.iter().map(|b| (b, b.size())).collect();
        maps.extend(queries.as_ref().map(|q| (&q.read, q.bytes())));
        submit_and_map_async(ctx, "building a BVH on the device", enc, &maps).await?;
        let stages_ms = match queries {
            Some(q) => q.stages_ms(ctx.queue())?,
            None => Vec::new(),
        };
        let t = Instant::now();
        let mut nodes: Vec<FlatNode> = Vec::with_capacity(self.nodes as usize);
        let mut tris: Vec<FlatTriangle> = Vec::with_capacity(self.n as usize);
        let mut words: Vec<u32> = Vec::new();
        let got = read_mapped(&reads[0], reads[0].size(), &mut nodes)
            .and_then(|_| read_mapped(&reads[1], self.n * 48, &mut tris))
            .and_then(|_| read_mapped(&reads[2], reads[2].size(), &mut words));
        for r in &reads {
            r.unmap();
        }
        got?;
        // A collapsed tree has fewer flat nodes than were allocated: a leaf's count says
        // how many triangles it holds, and the nodes are in depth-first order.
        let used = flat_nodes_used(&nodes);
        nodes.truncate(used);
        let bvh = FlatBvh::from_parts(nodes, tris, words[depth_at]);
        Ok(ReadBack {
            bvh,
            words,
            stages_ms,
            readback_ms: t.elapsed().as_secs_f64() * 1e3,
        })
    }
}

/// A build's tree as read back, with the words of its depth buffer, each step's device
/// time and the read back's milliseconds.
struct ReadBack {
    bvh: FlatBvh,
    words: Vec<u32>,
    stages_ms: Vec<(&'static str, f64)>,
    readback_ms: f64,
}

/// How many nodes of a depth-first flat layout the root's tree covers.
fn flat_nodes_used(nodes: &[FlatNode]) -> usize {
    let mut k = 0usize;
    // The last node in depth-first order is the right-most leaf: follow right children.
    while let Some(node) = nodes.get(k) {
        if node.count() > 0 {
            return k + 1;
        }
        k = node.right_or_first as usize;
    }
    nodes.len()
}

/// The linear BVH's flat nodes, triangles and depth (bindings of `build_lbvh.wgsl`).
const LBVH_OUTPUTS: [u32; 3] = [11, 12, 13];

/// The linear BVH's buffers, bindings 8 to 13 of `build_lbvh.wgsl`.
fn lbvh_buffers(device: &wgpu::Device, n: u64) -> Vec<wgpu::Buffer> {
    use wgpu::BufferUsages as U;
    let nodes = 2 * n - 1;
    let (storage, out) = (U::STORAGE, U::STORAGE | U::COPY_SRC);
    vec![
        empty(device, "lbvh links", nodes * 16, storage),
        empty(device, "lbvh boxes", nodes * 32, storage),
        empty(device, "lbvh arrivals", (n - 1) * 4, storage),
        empty(device, "lbvh nodes", nodes * 32, out),
        empty(device, "lbvh triangles", n * 48, out),
        empty(device, "lbvh depth", 4, out),
    ]
}

impl Build {
    /// The linear BVH after the sort: hierarchy, boxes and flat layout, one pass each.
    fn record_lbvh(
        &self,
        ctx: &GpuContext,
        pipelines: &[wgpu::ComputePipeline],
        enc: &mut wgpu::CommandEncoder,
        queries: Option<&StepQueries>,
    ) {
        let max_dim = ctx.limits().max_compute_workgroups_per_dimension;
        let per_item = grid(self.n, max_dim);
        let per_node = grid(self.nodes, max_dim);
        self.pass(
            ctx,
            pipelines,
            enc,
            queries,
            "hierarchy",
            &[(5, 0, per_item)],
        );
        self.pass(ctx, pipelines, enc, queries, "boxes", &[(6, 0, per_item)]);
        self.pass(
            ctx,
            pipelines,
            enc,
            queries,
            "flat layout",
            &[(7, 0, per_node)],
        );
    }
}

impl GpuContext {
    /// Builds a BVH over `tris` on the device with `opts` and reads it back (`prim` the
    /// triangle's index in `tris`), with the time of each step. The tree passes
    /// [`FlatBvh::check_invariants`]; build its escape links or wide layout on the CPU as
    /// for any tree. One triangle is built on the CPU (there is nothing to sort); no
    /// triangle is [`TraceError::EmptyBvh`]; a non-finite corner, an option out of range,
    /// more triangles than the device's buffers hold, or a device with fewer than
    /// [`bvhtrace_kernels::build::BUILD_STORAGE_BUFFERS`] storage buffers per stage, an
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
        opts.check()?;
        if let Some(one) = self.check_build_input(tris)? {
            return Ok((one, GpuBuildTimes::default()));
        }
        let pipelines = self.build_pipelines(opts.builder)?;
        let t0 = Instant::now();
        let build = Build::upload(self, tris, opts)?;
        let upload_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        let device = self.device();
        let (done, iterations) = match opts.builder {
            GpuBuilderKind::Lbvh => {
                let queries = self.has_timestamps().then(|| StepQueries::new(device, 5));
                let mut enc = device.create_command_encoder(&Default::default());
                build.record_sort(self, &pipelines, &mut enc, queries.as_ref());
                build.record_lbvh(self, &pipelines, &mut enc, queries.as_ref());
                let done = build.read_back(self, enc, LBVH_OUTPUTS, 0, queries).await?;
                (done, 0)
            }
            GpuBuilderKind::Ploc => ploc::run(self, &build, &pipelines).await?,
        };
        let build_ms = t1.elapsed().as_secs_f64() * 1e3 - done.readback_ms;
        Ok((
            done.bvh,
            GpuBuildTimes {
                upload_ms,
                build_ms,
                readback_ms: done.readback_ms,
                stages_ms: done.stages_ms,
                iterations,
            },
        ))
    }

    /// The checks before a device build: no triangle is an error, one triangle is built
    /// on the CPU and returned, more are checked for non-finite corners, and the device
    /// for enough storage buffers per stage.
    fn check_build_input(&self, tris: &[Triangle]) -> Result<Option<FlatBvh>, GpuError> {
        let bad_input = |e: &dyn std::fmt::Display| TraceError::BadBuffer {
            buffer: "triangles",
            problem: e.to_string(),
        };
        match tris.len() {
            0 => return Err(TraceError::EmptyBvh),
            1 => {
                let bvh = FlatBvh::build(tris, &Default::default()).map_err(|e| bad_input(&e))?;
                return Ok(Some(bvh));
            }
            _ => bvhtrace_core::mesh::validate_triangles(tris).map_err(|e| bad_input(&e))?,
        }
        let have = self.device().limits().max_storage_buffers_per_shader_stage;
        let need = bvhtrace_kernels::build::BUILD_STORAGE_BUFFERS;
        if have < need {
            return Err(TraceError::Unsupported {
                backend: "device builder",
                what: format!(
                    "a device with {have} storage buffers per shader stage: building needs \
                     {need}"
                ),
            });
        }
        Ok(None)
    }

    /// [`GpuContext::build_bvh`] with the linear BVH ([`GpuBuilderKind::Lbvh`]).
    pub fn build_lbvh(&self, tris: &[Triangle]) -> Result<(FlatBvh, GpuBuildTimes), GpuError> {
        self.build_bvh(tris, &GpuBuildOptions::with_builder(GpuBuilderKind::Lbvh))
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

    #[test]
    fn options_out_of_range_are_errors() {
        assert!(GpuBuildOptions::default().check().is_ok());
        for bad in [
            GpuBuildOptions {
                radius: 0,
                ..Default::default()
            },
            GpuBuildOptions {
                max_leaf_size: 17,
                ..Default::default()
            },
            GpuBuildOptions {
                cost_traversal: f32::NAN,
                ..Default::default()
            },
        ] {
            assert!(bad.check().is_err(), "{bad:?}");
        }
    }
}
