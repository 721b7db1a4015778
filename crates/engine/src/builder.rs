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
    /// [`GpuBuilderKind::Ploc`]: the clustering iterations submitted with the sort, before
    /// the host first reads the cluster count back (1..=4096); `None`, as many as builds of
    /// this size usually need, so that most builds wait on the device once. Iterations
    /// past the last merge dispatch nothing; too few cost more submissions, never
    /// another tree.
    pub first_iterations: Option<u32>,
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
            first_iterations: None,
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
        if let Some(k) = self.first_iterations.filter(|k| !(1..=4096).contains(k)) {
            return bad(format!("first_iterations {k} is outside 1..=4096"));
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
    /// Submits `rec` (a failure named `during`) and, once it is done, copies the first
    /// bytes of each of `reads`' buffers into its slice (as many as the slice holds); the
    /// milliseconds of the first `pairs` of `timer` when given, and of the copies. A
    /// future, so that a device whose read back completes on an event loop (WebGPU in a
    /// browser) need not block.
    fn submit_and_read<'a, 'b: 'a>(
        &'a self,
        rec: Self::Recording,
        during: &'static str,
        reads: &'a mut [Read<'b, Self::Buffer>],
        timer: Option<(&'a Self::Timer, u32)>,
    ) -> impl Future<Output = Result<ReadDone, TraceError>> + 'a;
}

/// What [`BuildDevice::submit_and_read`] measured.
#[derive(Clone, Debug, Default)]
pub struct ReadDone {
    /// Device milliseconds of each timestamp pair asked for.
    pub pairs_ms: Vec<f64>,
    /// Host milliseconds copying the mapped bytes out.
    pub copy_ms: f64,
}

/// One buffer read back by [`BuildDevice::submit_and_read`]: its first `into.len()` bytes,
/// copied into `into` (the caller's typed vector, so the bytes are copied once).
pub struct Read<'a, B> {
    /// The buffer read.
    pub buffer: &'a B,
    /// Where its bytes go.
    pub into: &'a mut [u8],
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

/// Iterations a batch records when the first submission left clusters (rare: see
/// [`first_iterations`]); iterations past the last cluster dispatch nothing.
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
    /// [`GpuBuildOptions::first_iterations`].
    first_iterations: Option<u32>,
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
    (tris.iter().enumerate())
        .map(|(i, t)| FlatTriangle::new(t, i as u32))
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
            first_iterations: opts.first_iterations,
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
        depth_words: usize,
        depth_at: usize,
    ) -> Result<ReadBack, TraceError> {
        let t = Instant::now();
        // Zeroed vectors are fresh pages the copy writes once: the bytes move only there.
        let mut nodes: Vec<FlatNode> = bytemuck::zeroed_vec(self.nodes as usize);
        let mut tris: Vec<FlatTriangle> = bytemuck::zeroed_vec(self.n as usize);
        let mut words = vec![0u32; depth_words];
        let mut reads = [
            Read {
                buffer: &self.buffers[outputs[0]],
                into: bytemuck::cast_slice_mut(&mut nodes),
            },
            Read {
                buffer: &self.buffers[outputs[1]],
                into: bytemuck::cast_slice_mut(&mut tris),
            },
            Read {
                buffer: &self.buffers[outputs[2]],
                into: bytemuck::cast_slice_mut(&mut words),
            },
        ];
        let used = self.timed.len() as u32;
        let timer = self.timer.as_ref().map(|t| (t, used));
        let submitted = Instant::now();
        let done = self
            .dev
            .submit_and_read(rec, BUILDING, &mut reads, timer)
            .await?;
        // The wait for the device counts as building; the copies and the rest, reading.
        let waited = submitted.elapsed().as_secs_f64() * 1e3 - done.copy_ms;
        let mut stages_ms: Vec<(&'static str, f64)> = Vec::new();
        for (name, ms) in self.timed.iter().zip(done.pairs_ms) {
            match stages_ms.iter_mut().find(|(n, _)| n == name) {
                Some((_, sum)) => *sum += ms,
                None => stages_ms.push((name, ms)),
            }
        }
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
            readback_ms: t.elapsed().as_secs_f64() * 1e3 - waited,
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
    // The last node in depth-first order is the right-most leaf: follow right children,
    // which come after their parents (a layout that does not, such as the zeroes of an
    // unfinished clustering, is left whole).
    while let Some(node) = nodes.get(k) {
        if node.count() > 0 {
            return k + 1;
        }
        let right = node.right_or_first as usize;
        if right <= k {
            break;
        }
        k = right;
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
    /// `iterations` iterations in one pass, the sizes of all but the fixed ones read from
    /// the dispatch-size buffer `ploc_prepare` writes (none once one cluster is left).
    fn record_iterations(&mut self, rec: &mut D::Recording, iterations: u32) {
        let k = self.next_pair("clustering");
        let args = &self.buffers[ARGS];
        let mut list: Vec<Dispatch<'_, D>> = Vec::with_capacity(6 * iterations as usize);
        for _ in 0..iterations {
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

    /// The clustering build. One submission holds the sort, the leaves, the iterations
    /// most builds of this size need ([`first_iterations`]), the flat layout (which does
    /// nothing while clusters are left) and the read back: one wait in all. When clusters
    /// were left, batches of [`BATCH`] iterations follow, each reading the count back, then
    /// the flat layout and the read back again. Returns the tree and the iterations run.
    /// Each submission is awaited, so in a browser the event loop runs meanwhile.
    async fn run_ploc(&mut self) -> Result<(ReadBack, u32), TraceError> {
        let max_dim = self.dev.limits().max_compute_workgroups_per_dimension;
        let mut rec = self.dev.begin()?;
        self.record_sort(&mut rec);
        let per_item = grid(self.n, max_dim);
        self.pass(&mut rec, "clustering", &[(LEAVES, 0, per_item)]);
        let first = self.first_iterations.unwrap_or(first_iterations(self.n));
        self.record_iterations(&mut rec, first);
        self.record_flatten(&mut rec);
        let mut done = self.read_back(rec, PLOC_OUTPUTS, 8, DEPTH).await?;
        let mut left = clusters_left(&done.words)?;
        if left > 1 {
            let mut batches = 0u32;
            while left > 1 {
                let mut rec = self.dev.begin()?;
                self.record_iterations(&mut rec, BATCH);
                let mut state = [0u32; 8];
                let mut reads = [Read {
                    buffer: &self.buffers[STATE],
                    into: bytemuck::cast_slice_mut(&mut state),
                }];
                self.dev
                    .submit_and_read(rec, BUILDING, &mut reads, None)
                    .await?;
                let now = clusters_left(&state)?;
                batches += 1;
                // Every iteration merges at least once, so the count falls every batch; a
                // batch in which it does not is a fault, reported rather than looped on.
                if now >= left {
                    return Err(TraceError::Unsupported {
                        backend: "device builder",
                        what: format!(
                            "a finished clustering: it stopped at {now} clusters after \
                             {batches} more batches"
                        ),
                    });
                }
                left = now;
            }
            let mut rec = self.dev.begin()?;
            self.record_flatten(&mut rec);
            done = self.read_back(rec, PLOC_OUTPUTS, 8, DEPTH).await?;
        }
        let iterations = done.words.get(ITERATIONS).copied().unwrap_or(0);
        Ok((done, iterations))
    }

    /// The flat layout of the clustered tree, one pass.
    fn record_flatten(&mut self, rec: &mut D::Recording) {
        let per_node = grid(
            self.nodes,
            self.dev.limits().max_compute_workgroups_per_dimension,
        );
        self.pass(rec, "flat layout", &[(FLATTEN, 0, per_node)]);
    }
}

/// Clusters left, from the words of the PLOC state.
fn clusters_left(state: &[u32]) -> Result<u32, TraceError> {
    state
        .get(LEFT)
        .copied()
        .ok_or_else(|| short_read(state.len()))
}

/// Iterations the first submission of a clustering build of `n` triangles records: about
/// as many as most builds of that size run (43 for 69K triangles, 49 for 269K, 57 for
/// 6.7M), with room; one cluster left, an iteration dispatches nothing.
fn first_iterations(n: u64) -> u32 {
    let log2 = 64 - n.max(1).leading_zeros();
    3 * log2 + 8
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
            GpuBuildOptions {
                first_iterations: Some(0),
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

    #[test]
    fn the_first_submission_covers_the_iterations_builds_took() {
        // Iterations measured on lavapipe and the H200 (docs/benchmarks.md).
        for (n, took) in [
            (69_451, 43),
            (268_686, 49),
            (1_612_116, 57),
            (6_717_150, 57),
        ] {
            let first = first_iterations(n);
            assert!(
                first >= took && first <= 2 * took,
                "{n}: {first} against {took}"
            );
        }
    }
}
