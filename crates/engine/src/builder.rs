//! The device BVH builders' host side, written once for every backend over the small
//! [`BuildDevice`] trait: the options and their checks, the upload, the Morton sort, the
//! linear BVH, the clustering loop, the read back into a [`FlatBvh`] and the timing. A
//! backend only makes buffers, compiles the builder's programs ([`crate::programs`]), binds
//! buffers by binding number, records dispatches and submits and reads buffers back.
//!
//! Both builders start the same way (`build_morton.wgsl`): the centroids' bounds, 30-bit
//! Morton codes, and a stable radix sort of (code, index) in four 8-bit passes. Then:
//! * [`GpuBuilderKind::Lbvh`] (`build_lbvh.wgsl`): the hierarchy from common prefixes
//!   (Karras 2012), boxes bottom up, one triangle a leaf; the fastest build, the poorest
//!   tree;
//! * [`GpuBuilderKind::Ploc`] (`build_ploc.wgsl`): locally-ordered clustering (Meister and
//!   Bittner 2018), mutual nearest neighbours along the Morton order merged until one
//!   cluster is left, leaves collapsed by the SAH; a tree close to the CPU's binned SAH.
//!
//! Same input, same tree: the sort is stable, equal codes split by index, and the
//! clustering's ties break by place; so two backends on one device build the same tree.

use std::future::Future;

use bvhtrace_core::flat::{FlatNode, FlatTriangle};
use bvhtrace_core::{FlatBvh, Triangle};
use web_time::Instant;

use crate::error::TraceError;
use crate::plan::{DeviceLimits, check_buffer_size};
use crate::programs::{self, LBVH_STEPS, MORTON_STEPS, PLOC_STEPS, Step};

/// Invocations per workgroup (`MORTON_WG`) and keys per radix block (`MORTON_BLOCK`).
pub const WG: u32 = 256;
const BLOCK: u32 = 1024;

/// Bytes between the uniform blocks of successive dispatches (one per radix pass).
pub const PARAMS_STRIDE: u64 = 256;

/// What a failed build step was doing.
const BUILDING: &str = "building a BVH on the device";

/// Which device builder.
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
            GpuBuilderKind::Lbvh => &LBVH_STEPS,
            GpuBuilderKind::Ploc => &PLOC_STEPS,
        }
    }

    /// The builder's WGSL module ([`programs::lbvh_source`], [`programs::ploc_source`]).
    pub fn source(self) -> String {
        match self {
            GpuBuilderKind::Lbvh => programs::lbvh_source(),
            GpuBuilderKind::Ploc => programs::ploc_source(),
        }
    }

    /// Every step the builder runs, the Morton steps first: the order of
    /// [`GpuBuilderKind::entries`], and of a program's entry points.
    pub fn all_steps(self) -> impl Iterator<Item = Step> {
        MORTON_STEPS.iter().chain(self.steps()).copied()
    }

    /// Every entry point the builder runs, the Morton steps first.
    pub fn entries(self) -> impl Iterator<Item = &'static str> {
        self.all_steps().map(|(entry, _)| entry)
    }

    /// The step of entry `e` ([`GpuBuilderKind::entries`] order).
    #[cfg(test)]
    fn step(self, e: usize) -> Step {
        MORTON_STEPS
            .get(e)
            .copied()
            .unwrap_or_else(|| self.steps()[e - MORTON_STEPS.len()])
    }
}

impl std::fmt::Display for GpuBuilderKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// How to build on the device.
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
    pub fn check(&self) -> Result<(), TraceError> {
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

/// What a builder buffer is bound as.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BufferKind {
    /// A uniform block.
    Uniform,
    /// A storage buffer (also a copy source, for reading back).
    Storage,
    /// A storage buffer that also holds indirect dispatch sizes.
    Indirect,
}

/// One buffer bound at `binding` of group 0: `size` bytes from `offset` (the rest of the
/// buffer when `None`).
pub struct Binding<'a, B> {
    /// The binding number in the WGSL.
    pub binding: u32,
    /// The buffer.
    pub buffer: &'a B,
    /// Where the bound range starts.
    pub offset: u64,
    /// How long it is, or `None` for the rest of the buffer.
    pub size: Option<u64>,
}

/// How many workgroups a dispatch runs.
pub enum Grid<'a, B> {
    /// `(x, y)` workgroups (one deep).
    Groups(u32, u32),
    /// The three `u32` sizes at this byte offset of this buffer, written by the device.
    Indirect(&'a B, u64),
}

/// One dispatch: entry point `entry` (its index in [`GpuBuilderKind::entries`]) with the
/// buffers `bound` binds, over `grid`.
pub struct Dispatch<'a, D: BuildDevice + ?Sized> {
    /// The entry point's index.
    pub entry: usize,
    /// Its bind group ([`BuildDevice::bind`]).
    pub bound: &'a D::Bound,
    /// Its workgroups.
    pub grid: Grid<'a, D::Buffer>,
}

/// What a device does for the builder; everything else is [`build_bvh`]'s. Each call that
/// records only appends to a recording; only [`BuildDevice::submit_and_read`] runs work,
/// in the order recorded, each dispatch seeing every earlier one's writes.
pub trait BuildDevice {
    /// A buffer.
    type Buffer;
    /// A builder's compiled entry points, in [`GpuBuilderKind::entries`] order.
    type Program;
    /// Buffers bound for one entry point (a bind group, a descriptor set).
    type Bound;
    /// Commands recorded, not yet submitted.
    type Recording;
    /// Timestamp queries, taken in pairs around passes.
    type Timer;

    /// The limits the build plans within.
    fn limits(&self) -> &DeviceLimits;
    /// Storage buffers one entry point may bind.
    fn storage_buffers_per_stage(&self) -> u32;
    /// The programs of builder `kind`, compiled on first use and kept.
    fn program(&self, kind: GpuBuilderKind) -> Result<Self::Program, TraceError>;
    /// A buffer of `bytes` (at least 16) holding `contents` at its start, zeroes after.
    fn buffer(
        &self,
        label: &'static str,
        kind: BufferKind,
        bytes: u64,
        contents: Option<&[u8]>,
    ) -> Result<Self::Buffer, TraceError>;
    /// The buffers `bindings` bound for entry point `entry` of `program`.
    fn bind(
        &self,
        program: &Self::Program,
        entry: usize,
        bindings: &[Binding<'_, Self::Buffer>],
    ) -> Result<Self::Bound, TraceError>;
    /// Timestamp queries for `pairs` passes, or `None` on a device without them.
    fn timer(&self, pairs: u32) -> Result<Option<Self::Timer>, TraceError>;
    /// An empty recording.
    fn begin(&self) -> Result<Self::Recording, TraceError>;
    /// Records `dispatches` of `program` in order, timed by pair `timed` when given.
    fn pass(
        &self,
        rec: &mut Self::Recording,
        program: &Self::Program,
        timed: Option<(&Self::Timer, u32)>,
        dispatches: &[Dispatch<'_, Self>],
    );
    /// Submits `rec` (a failure named `during`) and, once it is done, the first bytes of
    /// each of `reads`, and the milliseconds of the first `pairs` of `timer` when given. A
    /// future, so that a device whose read back completes on an event loop (WebGPU in a
    /// browser) need not block.
    fn submit_and_read<'a>(
        &'a self,
        rec: Self::Recording,
        during: &'static str,
        reads: &'a [(&'a Self::Buffer, u64)],
        timer: Option<(&'a Self::Timer, u32)>,
    ) -> impl Future<Output = Result<(Vec<Vec<u8>>, Vec<f64>), TraceError>> + 'a;
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

/// The uniform block of `build_ploc.wgsl` (`PlocParams`).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PlocParams {
    radius: u32,
    max_leaf: u32,
    cost_traversal: f32,
    cost_intersection: f32,
}

/// A dispatch of `count` invocations as a grid within the device's per-dimension limit:
/// `(x, y, invocations per row)`.
pub fn grid(count: u64, max_dim: u32) -> (u32, u32, u32) {
    let groups = count.div_ceil(u64::from(WG)).max(1);
    let x = groups.min(u64::from(max_dim)) as u32;
    let y = groups.div_ceil(u64::from(x)) as u32;
    (x, y, x * WG)
}

/// PLOC entry points, as indices into `GpuBuilderKind::Ploc.entries()` (after the five
/// Morton steps).
const LEAVES: usize = 5;
const PREPARE: usize = 6;
const NEIGHBOURS: usize = 7;
const MERGE: usize = 8;
const BLOCK_SUMS: usize = 9;
const SCAN: usize = 10;
const COMPACT: usize = 11;
const FLATTEN: usize = 12;

/// PLOC bindings: the state, the dispatch sizes, the flat nodes and triangles.
const STATE: usize = 9;
const ARGS: usize = 10;
const PLOC_OUTPUTS: [usize; 3] = [18, 19, STATE];

/// The PLOC state's words (`ploc_state`): clusters left, the depth, iterations run.
const LEFT: usize = 2;
const DEPTH: usize = 3;
const ITERATIONS: usize = 5;

/// Iterations a batch records. Clusters shrink by about a third an iteration, so the
/// first batch finishes most builds; iterations past the last cluster dispatch nothing.
const BATCH: u32 = 24;

/// Batches that get timestamps.
const TIMED_BATCHES: u32 = 8;

/// The linear BVH's flat nodes, triangles and depth (bindings of `build_lbvh.wgsl`).
const LBVH_OUTPUTS: [usize; 3] = [11, 12, 13];

/// One build's buffers (by binding, group 0 of the builder's module), bind groups and
/// timestamps, and its sizes.
struct Build<'d, D: BuildDevice> {
    dev: &'d D,
    kind: GpuBuilderKind,
    program: D::Program,
    buffers: Vec<D::Buffer>,
    /// Bind groups by entry point, then radix pass (one for entries outside the sort).
    groups: Vec<Vec<D::Bound>>,
    timer: Option<D::Timer>,
    /// The name of each timestamp pair taken so far.
    timed: Vec<&'static str>,
    pairs: u32,
    /// Triangles, nodes, radix blocks.
    n: u64,
    nodes: u64,
    blocks: u32,
}

/// A build's tree as read back, with the words of its depth buffer, each step's device
/// time and the read back's milliseconds.
struct ReadBack {
    bvh: FlatBvh,
    words: Vec<u32>,
    stages_ms: Vec<(&'static str, f64)>,
    readback_ms: f64,
}

/// The triangles as the builder reads them, numbered in input order.
fn flat_input(tris: &[Triangle]) -> Vec<FlatTriangle> {
    tris.iter()
        .enumerate()
        .map(|(i, t)| FlatTriangle {
            v0: t[0].to_array(),
            prim: i as u32,
            v1: t[1].to_array(),
            _pad1: 0,
            v2: t[2].to_array(),
            _pad2: 0,
        })
        .collect()
}

impl<'d, D: BuildDevice> Build<'d, D> {
    /// Uploads `tris` and makes the Morton steps' buffers (bindings 0 to 7) and the
    /// builder's.
    fn upload(
        dev: &'d D,
        program: D::Program,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<Self, TraceError> {
        let n = tris.len() as u64;
        let nodes = 2 * n - 1;
        let blocks = (n as u32).div_ceil(BLOCK);
        let limits = dev.limits();
        for (buffer, bytes) in [
            ("triangles", n * 48),
            ("nodes", nodes * 32),
            ("node boxes", nodes * 32),
        ] {
            check_buffer_size(limits, buffer, bytes)?;
        }
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
        let bounds_init: [u32; 6] = [u32::MAX, u32::MAX, u32::MAX, 0, 0, 0];
        let input = flat_input(tris);
        use BufferKind::{Storage, Uniform};
        let mut buffers = vec![
            dev.buffer("morton params", Uniform, params.len() as u64, Some(&params))?,
            dev.buffer(
                "morton input",
                Storage,
                n * 48,
                Some(bytemuck::cast_slice(&input)),
            )?,
            dev.buffer(
                "morton bounds",
                Storage,
                24,
                Some(bytemuck::cast_slice(&bounds_init)),
            )?,
        ];
        for label in [
            "morton keys",
            "morton values",
            "morton keys (other)",
            "morton values (other)",
        ] {
            buffers.push(dev.buffer(label, Storage, n * 4, None)?);
        }
        let histograms = u64::from(blocks) * 256 * 4;
        buffers.push(dev.buffer("morton histograms", Storage, histograms, None)?);
        match opts.builder {
            GpuBuilderKind::Lbvh => buffers.extend(lbvh_buffers(dev, n)?),
            GpuBuilderKind::Ploc => buffers.extend(ploc_buffers(dev, n, opts)?),
        }
        Ok(Build {
            dev,
            kind: opts.builder,
            program,
            buffers,
            groups: Vec::new(),
            timer: None,
            timed: Vec::new(),
            pairs: 0,
            n,
            nodes,
            blocks,
        })
    }

    /// Every entry point's bind groups (the radix steps' one per pass: that pass's
    /// params, and the key and value buffers swapped on odd passes), and `pairs`
    /// timestamp pairs.
    fn bind_all(&mut self, pairs: u32) -> Result<(), TraceError> {
        let steps: Vec<Step> = self.kind.all_steps().collect();
        for (e, (_, bindings)) in steps.into_iter().enumerate() {
            let passes = if (2..=4).contains(&e) { 4 } else { 1 };
            let mut per_pass = Vec::with_capacity(passes);
            for pass in 0..passes as u64 {
                let swap = pass % 2 == 1;
                let list: Vec<Binding<'_, D::Buffer>> = bindings
                    .iter()
                    .map(|&b| {
                        let slot = match b {
                            3 | 4 if swap => b + 2,
                            5 | 6 if swap => b - 2,
                            b => b,
                        };
                        let uniform = b == 0;
                        Binding {
                            binding: b,
                            buffer: &self.buffers[slot as usize],
                            offset: if uniform { pass * PARAMS_STRIDE } else { 0 },
                            size: uniform.then_some(16),
                        }
                    })
                    .collect();
                per_pass.push(self.dev.bind(&self.program, e, &list)?);
            }
            self.groups.push(per_pass);
        }
        self.timer = self.dev.timer(pairs)?;
        self.pairs = pairs;
        Ok(())
    }

    /// The next timestamp pair, named `name`, while pairs are left.
    fn next_pair(&mut self, name: &'static str) -> Option<u32> {
        let k = self.timed.len() as u32;
        (self.timer.is_some() && k < self.pairs).then(|| {
            self.timed.push(name);
            k
        })
    }

    /// One pass named `name` (timed while pairs are left) running `dispatches` (entry,
    /// radix pass, grid) in order.
    fn pass(
        &mut self,
        rec: &mut D::Recording,
        name: &'static str,
        dispatches: &[(usize, usize, (u32, u32, u32))],
    ) {
        let k = self.next_pair(name);
        let list: Vec<Dispatch<'_, D>> = dispatches
            .iter()
            .map(|&(e, pass, (x, y, _))| Dispatch {
                entry: e,
                bound: &self.groups[e][pass],
                grid: Grid::Groups(x, y),
            })
            .collect();
        let timed = self.timer.as_ref().zip(k);
        self.dev.pass(rec, &self.program, timed, &list);
    }

    /// The Morton steps: bounds and codes, then the four radix passes of count, scan and
    /// scatter (the sorted keys and values end in the first buffers).
    fn record_sort(&mut self, rec: &mut D::Recording) {
        let max_dim = self.dev.limits().max_compute_workgroups_per_dimension;
        let per_item = grid(self.n, max_dim);
        let per_block = grid(u64::from(self.blocks) * u64::from(WG), max_dim);
        let sort: Vec<(usize, usize, (u32, u32, u32))> = (0..4)
            .flat_map(|pass| {
                [
                    (2, pass, per_block),
                    (3, pass, (1, 1, WG)),
                    (4, pass, per_block),
                ]
            })
            .collect();
        let codes = [(0, 0, per_item), (1, 0, per_item)];
        self.pass(rec, "bounds and Morton codes", &codes);
        self.pass(rec, "radix sort", &sort);
    }

    /// The linear BVH after the sort: hierarchy, boxes and flat layout, one pass each.
    fn record_lbvh(&mut self, rec: &mut D::Recording) {
        let max_dim = self.dev.limits().max_compute_workgroups_per_dimension;
        let per_item = grid(self.n, max_dim);
        let per_node = grid(self.nodes, max_dim);
        self.pass(rec, "hierarchy", &[(5, 0, per_item)]);
        self.pass(rec, "boxes", &[(6, 0, per_item)]);
        self.pass(rec, "flat layout", &[(7, 0, per_node)]);
    }

    /// The end of every build: `rec` submitted, then the flat nodes, the triangles and a
    /// buffer of `u32` holding the depth at `depth_at` (`outputs`), and the timestamps,
    /// read back into the tree.
    async fn read_back(
        &self,
        rec: D::Recording,
        outputs: [usize; 3],
        depth_words: u64,
        depth_at: usize,
    ) -> Result<ReadBack, TraceError> {
        let reads = [
            (&self.buffers[outputs[0]], self.nodes * 32),
            (&self.buffers[outputs[1]], self.n * 48),
            (&self.buffers[outputs[2]], depth_words * 4),
        ];
        let used = self.timed.len() as u32;
        let timer = self.timer.as_ref().map(|t| (t, used));
        let (bytes, ms) = self
            .dev
            .submit_and_read(rec, BUILDING, &reads, timer)
            .await?;
        let mut stages_ms: Vec<(&'static str, f64)> = Vec::new();
        for (name, ms) in self.timed.iter().zip(ms) {
            match stages_ms.iter_mut().find(|(n, _)| n == name) {
                Some((_, sum)) => *sum += ms,
                None => stages_ms.push((name, ms)),
            }
        }
        let t = Instant::now();
        let [nodes, tris, words] = match <[Vec<u8>; 3]>::try_from(bytes) {
            Ok(b) => b,
            Err(got) => return Err(short_read(got.len())),
        };
        let mut nodes: Vec<FlatNode> = bytemuck::pod_collect_to_vec(&nodes);
        let tris: Vec<FlatTriangle> = bytemuck::pod_collect_to_vec(&tris);
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&words);
        let depth = *words.get(depth_at).ok_or_else(|| short_read(words.len()))?;
        // A collapsed tree has fewer flat nodes than were allocated: a leaf's count says
        // how many triangles it holds, and the nodes are in depth-first order.
        let used = flat_nodes_used(&nodes);
        nodes.truncate(used);
        let bvh = FlatBvh::from_parts(nodes, tris, depth);
        Ok(ReadBack {
            bvh,
            words,
            stages_ms,
            readback_ms: t.elapsed().as_secs_f64() * 1e3,
        })
    }
}

/// A read back that came back shorter than asked for.
fn short_read(got: usize) -> TraceError {
    TraceError::Device {
        during: BUILDING,
        message: format!("the read back came back short ({got})"),
    }
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

/// The linear BVH's buffers, bindings 8 to 13 of `build_lbvh.wgsl`.
fn lbvh_buffers<D: BuildDevice>(dev: &D, n: u64) -> Result<Vec<D::Buffer>, TraceError> {
    let nodes = 2 * n - 1;
    [
        ("lbvh links", nodes * 16),
        ("lbvh boxes", nodes * 32),
        ("lbvh arrivals", (n - 1) * 4),
        ("lbvh nodes", nodes * 32),
        ("lbvh triangles", n * 48),
        ("lbvh depth", 4),
    ]
    .into_iter()
    .map(|(label, bytes)| dev.buffer(label, BufferKind::Storage, bytes, None))
    .collect()
}

/// The clustering builder's buffers, bindings 8 to 19 of `build_ploc.wgsl`.
fn ploc_buffers<D: BuildDevice>(
    dev: &D,
    n: u64,
    opts: &GpuBuildOptions,
) -> Result<Vec<D::Buffer>, TraceError> {
    let nodes = 2 * n - 1;
    let blocks = n.div_ceil(u64::from(BLOCK));
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
    use BufferKind::{Indirect, Storage, Uniform};
    let mut out = vec![
        dev.buffer(
            "ploc params",
            Uniform,
            16,
            Some(bytemuck::bytes_of(&params)),
        )?,
        dev.buffer(
            "ploc state",
            Storage,
            32,
            Some(bytemuck::cast_slice(&state)),
        )?,
        dev.buffer("ploc dispatch sizes", Indirect, 24, None)?,
    ];
    for (label, bytes) in [
        ("ploc clusters", n * 4),
        ("ploc merged", n * 4),
        ("ploc nearest", n * 4),
        ("ploc block sums", blocks * 4),
        ("ploc boxes", nodes * 32),
        ("ploc info", nodes * 16),
        ("ploc links", nodes * 16),
        ("ploc nodes", nodes * 32),
        ("ploc triangles", n * 48),
    ] {
        out.push(dev.buffer(label, Storage, bytes, None)?);
    }
    Ok(out)
}

impl<D: BuildDevice> Build<'_, D> {
    /// `BATCH` iterations in one pass, the sizes of all but the fixed ones read from the
    /// dispatch-size buffer `ploc_prepare` writes.
    fn record_batch(&mut self, rec: &mut D::Recording) {
        let k = self.next_pair("clustering");
        let args = &self.buffers[ARGS];
        let mut list: Vec<Dispatch<'_, D>> = Vec::with_capacity(6 * BATCH as usize);
        for _ in 0..BATCH {
            for (e, indirect) in [
                (PREPARE, None),
                (NEIGHBOURS, Some(0)),
                (MERGE, Some(0)),
                (BLOCK_SUMS, Some(12)),
                (SCAN, None),
                (COMPACT, Some(12)),
            ] {
                list.push(Dispatch {
                    entry: e,
                    bound: &self.groups[e][0],
                    grid: match indirect {
                        Some(offset) => Grid::Indirect(args, offset),
                        None => Grid::Groups(1, 1),
                    },
                });
            }
        }
        let timed = self.timer.as_ref().zip(k);
        self.dev.pass(rec, &self.program, timed, &list);
    }

    /// The clustering build: the sort, the leaves and a first batch in one submission,
    /// more batches while clusters are left, then the flat layout. Returns the tree read
    /// back and the iterations that ran. Each batch's count is awaited, so in a browser
    /// the event loop runs meanwhile.
    async fn run_ploc(&mut self) -> Result<(ReadBack, u32), TraceError> {
        let max_dim = self.dev.limits().max_compute_workgroups_per_dimension;
        let mut rec = self.dev.begin()?;
        self.record_sort(&mut rec);
        let per_item = grid(self.n, max_dim);
        self.pass(&mut rec, "clustering", &[(LEAVES, 0, per_item)]);
        let mut left = self.n as u32;
        let mut batches = 0u32;
        let mut first = Some(rec);
        while left > 1 {
            let mut rec = match first.take() {
                Some(rec) => rec,
                None => self.dev.begin()?,
            };
            self.record_batch(&mut rec);
            let reads = [(&self.buffers[STATE], 32)];
            let (bytes, _) = self
                .dev
                .submit_and_read(rec, BUILDING, &reads, None)
                .await?;
            let state: Vec<u32> = bytes
                .first()
                .map(|b| bytemuck::pod_collect_to_vec(b))
                .unwrap_or_default();
            let now = *state.get(LEFT).ok_or_else(|| short_read(state.len()))?;
            batches += 1;
            // Every iteration merges at least once, so the count falls every batch; a
            // batch in which it does not is a fault, reported rather than looped on.
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
        let mut rec = self.dev.begin()?;
        let per_node = grid(self.nodes, max_dim);
        self.pass(&mut rec, "flat layout", &[(FLATTEN, 0, per_node)]);
        let done = self.read_back(rec, PLOC_OUTPUTS, 8, DEPTH).await?;
        let iterations = done.words.get(ITERATIONS).copied().unwrap_or(0);
        Ok((done, iterations))
    }
}

/// The checks before a device build: no triangle is an error, one triangle is built on
/// the CPU and returned, more are checked for non-finite corners, and the device for
/// enough storage buffers per stage.
fn check_input<D: BuildDevice>(dev: &D, tris: &[Triangle]) -> Result<Option<FlatBvh>, TraceError> {
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
    let have = dev.storage_buffers_per_stage();
    let need = programs::BUILD_STORAGE_BUFFERS;
    if have < need {
        return Err(TraceError::Unsupported {
            backend: "device builder",
            what: format!(
                "a device with {have} storage buffers per shader stage: building needs {need}"
            ),
        });
    }
    Ok(None)
}

/// Builds a BVH over `tris` on `dev` with `opts` and reads it back (`prim` the triangle's
/// index in `tris`), with the time of each step. The tree passes
/// [`FlatBvh::check_invariants`]; build its escape links or wide layout on the CPU as for
/// any tree. One triangle is built on the CPU (there is nothing to sort); no triangle is
/// [`TraceError::EmptyBvh`]; a non-finite corner, an option out of range, more triangles
/// than the device's buffers hold, or a device with fewer than
/// [`programs::BUILD_STORAGE_BUFFERS`] storage buffers per stage, an error naming it.
pub async fn build_bvh<D: BuildDevice>(
    dev: &D,
    tris: &[Triangle],
    opts: &GpuBuildOptions,
) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
    opts.check()?;
    if let Some(one) = check_input(dev, tris)? {
        return Ok((one, GpuBuildTimes::default()));
    }
    let program = dev.program(opts.builder)?;
    let t0 = Instant::now();
    let mut build = Build::upload(dev, program, tris, opts)?;
    let upload_ms = t0.elapsed().as_secs_f64() * 1e3;
    let t1 = Instant::now();
    let (done, iterations) = match opts.builder {
        GpuBuilderKind::Lbvh => {
            build.bind_all(5)?;
            let mut rec = dev.begin()?;
            build.record_sort(&mut rec);
            build.record_lbvh(&mut rec);
            (build.read_back(rec, LBVH_OUTPUTS, 1, 0).await?, 0)
        }
        GpuBuilderKind::Ploc => {
            build.bind_all(4 + TIMED_BATCHES)?;
            build.run_ploc().await?
        }
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

/// [`build_bvh`], waited for: for a device whose submissions complete without an event
/// loop (not in a browser).
pub fn build_bvh_blocking<D: BuildDevice>(
    dev: &D,
    tris: &[Triangle],
    opts: &GpuBuildOptions,
) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
    pollster::block_on(build_bvh(dev, tris, opts))
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

    #[test]
    fn steps_follow_the_entry_order() {
        for kind in GpuBuilderKind::ALL {
            let steps: Vec<Step> = kind.all_steps().collect();
            for (e, step) in steps.iter().enumerate() {
                assert_eq!(kind.step(e), *step);
            }
        }
        assert_eq!(GpuBuilderKind::Ploc.step(LEAVES).0, "ploc_leaves");
        assert_eq!(GpuBuilderKind::Ploc.step(FLATTEN).0, "ploc_flatten");
    }
}
