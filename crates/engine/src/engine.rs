//! One engine under every device backend. What wgpu, ash and the backends to come share
//! is written here once, over the small [`DeviceApi`] trait: the upload (arrays, limit
//! checks, stats, the host copy, the depth and wide-layout rules) and the trace driver
//! (the kernel key, submissions, scratch growth, readback, timing, finishing incomplete
//! rays, the kernels used, updates). A backend only creates, writes and binds its arrays
//! and scratch, and runs one batch.

use std::collections::VecDeque;
use std::future::Future;
use std::sync::{Arc, Mutex};

use web_time::Instant;

use bvhtrace_core::{
    Counters, FlatBvh, Hit, INCOMPLETE, InstanceTable, Ray, TraceOptions, TraceOutput, TracePhases,
    Traversal, WideBvh,
};

use crate::compose::WORKGROUP_SIZE;
use crate::device::DriverTuning;
use crate::error::TraceError;
use crate::key::KernelKey;
use crate::pages::{Pages, check_storage_buffers};
use crate::plan::{DeviceLimits, rays_per_dispatch, rays_per_submission, submissions_in_flight};
use crate::storage::{BvhStorage, RayInput, TEXEL_ROW};
use crate::tracer::{
    SendSync, TraceFuture, Tracer, check_update_shape, finish_incomplete_hits, mesh_fingerprint,
    tree_shape,
};
use crate::upload::{
    ArrayRole, DeviceArray, UploadOptions, UploadStats, binary_arrays, check_wide_top_level,
    stats_of, wide_arrays,
};
use crate::walks::{Layout, check_depth, may_overflow, walk};

/// Where the wide layout is missing, and the fix ([`TraceError::WideLayoutMissing`]).
pub const WIDE_NOT_UPLOADED: &str = "this upload left out: list Traversal::Wide in \
     UploadOptions::traversals (an upload without options takes it when the tree has one: \
     FlatBvh::build_wide)";

/// What an update writes again.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Update {
    /// Every node, triangle and instance (after a refit: boxes and corners moved).
    Everything,
    /// The top level of a two-level BVH and its instances (after new transforms). An
    /// uploaded wide layout is collapsed again and written whole either way: its meshes'
    /// places follow the top level's order.
    TopLevel,
}

/// How the uploaded arrays are laid out, for a backend binding them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ArraysLayout {
    /// Buffers or texel textures.
    pub storage: BvhStorage,
    /// A two-level tree: the bind groups have the instances (binding 4).
    pub instanced: bool,
    /// Alpha masks: the bind groups have them (binding 5).
    pub masks: bool,
    /// How the binary layout's arrays are split over bindings ([`crate::pages`]).
    pub pages: Pages,
    /// How the wide layout's arrays are split.
    pub wide_pages: Pages,
}

impl ArraysLayout {
    /// The split of the layout `traversal` reads.
    pub fn pages_for(&self, traversal: Traversal) -> Pages {
        match walk(traversal).is_wide() {
            true => self.wide_pages,
            false => self.pages,
        }
    }
}

/// One write of an update: the array's bytes from its start (`replace` false: the device
/// array keeps its size), or a new array in its place (`replace`: its size changed).
#[derive(Clone, Debug)]
pub struct ArrayWrite<'a> {
    /// What to write.
    pub array: DeviceArray<'a>,
    /// True when the array is made anew (and rebound).
    pub replace: bool,
}

/// The scratch a trace needs: rays, hits and their readback copy for `capacity` rays,
/// counters too when `counters`, the rays read from `input`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScratchPlan {
    /// Rays it holds.
    pub capacity: u64,
    /// With counters (and their readback copy).
    pub counters: bool,
    /// Where the kernels read the rays from.
    pub input: RayInput,
}

/// One submission of a trace: `rays` through the kernel `key` (the BVH group of
/// `key.traversal`).
#[derive(Clone, Copy)]
pub struct Batch<'a> {
    /// The kernel.
    pub key: KernelKey,
    /// The rays, at most the scratch's capacity.
    pub rays: &'a [Ray],
}

/// Where a finished submission's hits and counters are appended, in order.
pub struct BatchOut<'a> {
    /// Where the hits go.
    pub hits: &'a mut Vec<Hit>,
    /// Where the counters go, when asked for.
    pub counters: Option<&'a mut Vec<Counters>>,
}

/// What one submission of a trace took: the kernels' time on the device when it measures
/// it, and where the wall time went.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BatchTimes {
    /// The kernels, from timestamp queries, milliseconds.
    pub gpu_ms: Option<f64>,
    /// Upload, device and readback, measured on the host.
    pub phases: TracePhases,
}

/// What a backend's kernels can read beyond what every backend's read (the BVH, rays and
/// hits in storage buffers, the f32 triangle tests): the engine refuses, with one error
/// for every backend, an upload or a kernel that needs more.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BackendFeatures {
    /// The BVH and the rays in texel textures ([`BvhStorage::Textures`]).
    pub textures: bool,
    /// Per-vertex attributes bound beside the triangles.
    pub vertex_attributes: bool,
    /// The f64 triangle test (`SHADER_F64`, `shaderFloat64`).
    pub f64: bool,
}

impl BackendFeatures {
    /// `Ok` when `key`'s kernel reads nothing beyond these features; `device` names the
    /// device in the error (asked only then).
    pub fn check(&self, key: &KernelKey, device: impl Fn() -> String) -> Result<(), TraceError> {
        if key.precision.needs_f64() && !self.f64 {
            return Err(TraceError::PrecisionUnsupported {
                precision: key.precision,
                adapter: device(),
            });
        }
        self.check_storage(key.storage, &device)?;
        let missing = |feature, needed_for| TraceError::MissingFeature {
            adapter: device(),
            feature,
            needed_for,
        };
        if !self.textures && key.rays == RayInput::Texture {
            return Err(missing("texture storage", "the rays in textures"));
        }
        if !self.vertex_attributes && key.attributes.normals {
            return Err(missing("vertex attributes", "vertex normals"));
        }
        Ok(())
    }

    /// `Ok` when the BVH can be kept in `storage`: what an upload checks before anything
    /// is made, and every kernel key again.
    pub fn check_storage(
        &self,
        storage: BvhStorage,
        device: impl Fn() -> String,
    ) -> Result<(), TraceError> {
        match storage == BvhStorage::Textures && !self.textures {
            true => Err(TraceError::MissingFeature {
                adapter: device(),
                feature: "texture storage",
                needed_for: "the BVH in textures (BvhStorage::Textures)",
            }),
            false => Ok(()),
        }
    }
}

/// What a device API does for the [`Engine`]; everything else is the engine's. A new
/// device backend (wgpu, ash, the test backend over bytes) is one more implementation.
///
/// Methods that make device objects wait until they are ready for the kernels; a batch
/// waits for its own submission only.
pub trait DeviceApi: SendSync {
    /// The uploaded arrays, and whatever binds them (bind groups, descriptor sets).
    type Arrays: SendSync;
    /// The per-tracer scratch of a submission (rays, hits, counters, readback).
    type Scratch: SendSync;
    /// A submission not yet read back ([`DeviceApi::submit_batch`]).
    type Submitted: SendSync;

    /// The backend's name ([`Tracer::backend`]).
    fn name(&self) -> &'static str;
    /// The device's name ([`Tracer::device_name`]).
    fn device_name(&self) -> String;
    /// The limits the engine plans within.
    fn limits(&self) -> &DeviceLimits;
    /// The CPU-driver measures in force (trip budget, default storage).
    fn tuning(&self) -> &DriverTuning;
    /// True when batches report GPU time.
    fn has_timestamps(&self) -> bool;
    /// What this backend and device can read beyond every backend's kernels.
    fn features(&self) -> BackendFeatures;
    /// Builds (and caches) `key`'s pipeline.
    fn prepare_kernel(&self, key: KernelKey) -> Result<(), TraceError>;
    /// Creates and fills `arrays` and binds them (the binary layout's arrays and the wide
    /// layout's in groups of their own).
    fn create_arrays(
        &self,
        layout: ArraysLayout,
        arrays: &[DeviceArray<'_>],
    ) -> Result<Self::Arrays, TraceError>;
    /// Writes `writes` over `arrays` (rebinding replaced ones).
    fn write_arrays(
        &self,
        arrays: &mut Self::Arrays,
        layout: ArraysLayout,
        writes: &[ArrayWrite<'_>],
    ) -> Result<(), TraceError>;
    /// Creates the scratch `plan` asks for.
    fn create_scratch(&self, plan: &ScratchPlan) -> Result<Self::Scratch, TraceError>;
    /// Writes the batch's rays to `scratch` and submits its kernel (within
    /// [`crate::plan::plan_dispatches`]) and the copies of its hits (and counters) for
    /// reading back. A backend may return before the device is done; the engine submits
    /// on other scratch meanwhile ([`DriverTuning::in_flight`]) and reuses this scratch
    /// only after [`DeviceApi::finish_batch`].
    fn submit_batch(
        &self,
        arrays: &Self::Arrays,
        scratch: &Self::Scratch,
        batch: Batch<'_>,
    ) -> Result<Self::Submitted, TraceError>;
    /// Waits for `submitted` (made on `scratch`) and appends its hits (and counters) to
    /// `out`; the GPU time of the batch when the device measures it, and its phases from
    /// the submission's start. A future, so that a backend whose readback completes on an
    /// event loop (WebGPU in a browser) need not block.
    fn finish_batch<'a>(
        &'a self,
        scratch: &'a Self::Scratch,
        submitted: Self::Submitted,
        out: BatchOut<'a>,
    ) -> impl Future<Output = Result<BatchTimes, TraceError>> + 'a;
}

/// What an upload holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UploadedTree {
    /// Buffers or textures.
    pub storage: BvhStorage,
    /// A two-level tree.
    pub instanced: bool,
    /// The tree's alpha masks were uploaded.
    pub masks: bool,
    /// The binary layout was uploaded.
    pub binary: bool,
    /// The escape links were uploaded.
    pub escapes: bool,
    /// The wide layout was uploaded.
    pub wide: bool,
    /// The binary tree's depth.
    pub depth: u32,
    /// [`tree_shape`] of the uploaded tree.
    pub shape: (usize, usize, usize, u32),
    /// How the binary layout's arrays are split over bindings ([`crate::pages`]).
    pub pages: Pages,
    /// How the wide layout's arrays are split.
    pub wide_pages: Pages,
}

impl UploadedTree {
    /// What the bind groups hold, as a backend binds them.
    pub fn layout(&self) -> ArraysLayout {
        ArraysLayout {
            storage: self.storage,
            instanced: self.instanced,
            masks: self.masks,
            pages: self.pages,
            wide_pages: self.wide_pages,
        }
    }
}

/// The scratch kept between traces, with the plan it was made for.
struct Kept<S> {
    plan: ScratchPlan,
    scratch: S,
}

/// The tree the rays a device gives up on are finished on, with the wide layout that was
/// uploaded (collapsed from the tree, not a copy of it).
struct HostCopy {
    bvh: Arc<FlatBvh>,
    wide: Option<Arc<WideBvh>>,
}

/// A BVH on a device through backend `B`, ready to trace: the upload, the trace driver
/// and the update, written once for every backend. Implements [`Tracer`].
pub struct Engine<B: DeviceApi> {
    backend: B,
    arrays: B::Arrays,
    tree: UploadedTree,
    /// Bytes of each uploaded array's data, to learn whether an update keeps its size.
    sizes: Vec<((ArrayRole, u8), usize)>,
    stats: UploadStats,
    /// The binary layout's part of `stats`, which an update leaves as it is.
    binary_stats: UploadStats,
    /// The tree incomplete rays are finished on ([`Engine::keeps_host_copy`]).
    host_copy: Option<HostCopy>,
    /// The scratch between traces, one per submission in flight; a trace takes it out
    /// while it runs.
    scratch: Mutex<Vec<Kept<B::Scratch>>>,
    mesh_fingerprint: u64,
    used: Mutex<Vec<KernelKey>>,
    /// The instances' table every output carries, for a two-level tree.
    instances: Option<Arc<InstanceTable>>,
}

impl<B: DeviceApi> std::fmt::Debug for Engine<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine")
            .field("backend", &self.backend.name())
            .field("tree", &self.tree)
            .field("host_copy", &self.host_copy.is_some())
            .field("stats", &self.stats)
            .finish()
    }
}

/// The wide layout of `bvh`: its own when it has one, else `bvh` collapsed.
fn wide_of(bvh: &FlatBvh) -> Arc<WideBvh> {
    bvh.wide()
        .cloned()
        .unwrap_or_else(|| Arc::new(WideBvh::collapse(bvh)))
}

/// Checks that the kernel tracing `opts` on an upload laid out as `layout` binds no more
/// storage buffers than the device allows: only a tree split into pages can bind more
/// than every device allows ([`crate::pages`]).
fn check_bindings(
    layout: &ArraysLayout,
    opts: &TraceOptions,
    limits: &DeviceLimits,
) -> Result<(), TraceError> {
    let pages = layout.pages_for(opts.traversal);
    if pages.is_one() || layout.storage == BvhStorage::Textures {
        return Ok(());
    }
    let key = KernelKey::new(layout.storage, opts)
        .with_instances(layout.instanced)
        .with_masks(layout.masks)
        .with_pages(pages);
    let needed_for = "a tree larger than one binding, split into pages of one binding each,";
    check_storage_buffers(key.bindings().len() as u64, limits, needed_for)
}

/// Escape links of the top level's blocks: whole blocks hold its links (the last one may
/// hold a mesh's too, written with their current, unchanged values).
fn top_links(top_nodes: u32) -> usize {
    use bvhtrace_core::flat::{ESCAPE_BLOCK, OCTANTS};
    (top_nodes as usize).div_ceil(ESCAPE_BLOCK) * ESCAPE_BLOCK * OCTANTS
}

/// The most rays one upload to a ray texture holds: one dispatch, and no more rows than
/// the device allows.
fn ray_texture_capacity(limits: &DeviceLimits) -> u64 {
    let by_rows = u64::from(TEXEL_ROW / 2) * u64::from(limits.max_texture_dimension_2d);
    rays_per_dispatch(limits).min(by_rows)
}

/// The output of a trace of `rays` rays before any batch: the one place outputs are made.
pub fn new_output(
    rays: usize,
    opts: &TraceOptions,
    timed: bool,
    instances: Option<Arc<InstanceTable>>,
) -> TraceOutput {
    TraceOutput {
        hits: Vec::with_capacity(rays),
        counters: opts.counters.then(|| Vec::with_capacity(rays)),
        gpu_ms: timed.then_some(0.0),
        wall_ms: 0.0,
        incomplete: 0,
        instances,
        phases: Some(TracePhases::default()),
    }
}

impl<B: DeviceApi> Engine<B> {
    /// Uploads `bvh` through `backend` as `opts` says. The rules every backend follows:
    /// an empty tree is [`TraceError::EmptyBvh`]; a tree deeper than the full stack is
    /// [`TraceError::TooDeep`] when [`Traversal::FullStack`] is listed (and at trace time
    /// for that walk); escape links that do not fit the nodes are
    /// [`TraceError::BadEscapeLinks`] when a listed walk follows them; the wide layout is
    /// the tree's own or, without one, the tree collapsed; every array is checked against
    /// the device's limits before anything is made ([`TraceError::TooLarge`] names it).
    /// The upload keeps a host copy of the tree when incomplete rays may come back.
    pub fn upload(backend: B, bvh: &FlatBvh, opts: &UploadOptions) -> Result<Self, TraceError> {
        if bvh.nodes().is_empty() || bvh.triangles().is_empty() {
            return Err(TraceError::EmptyBvh);
        }
        for &traversal in &opts.traversals {
            check_depth(traversal, bvh.depth())?;
        }
        let storage = opts.storage.unwrap_or(backend.tuning().storage);
        (backend.features()).check_storage(storage, || backend.device_name())?;
        let (binary, with_escapes) = (opts.binary(), opts.escapes() && opts.binary());
        if with_escapes {
            bvh.check_escape_links()?;
            // Built (when not yet) before the clock starts.
            bvh.escapes();
        }
        let wide = opts.wide().then(|| wide_of(bvh));
        if let Some(w) = &wide {
            check_wide_top_level(w)?;
        }
        let limits = backend.limits();
        let (mut arrays, mut pages) = (Vec::new(), Pages::ONE);
        if binary {
            let links = with_escapes.then(|| bvh.escapes().len());
            let part = binary_arrays(bvh, storage, bvh.nodes().len(), true, links);
            pages = Pages::plan(storage, &part, limits)?;
            arrays = pages.split(part);
        }
        let mut wide_pages = Pages::ONE;
        if let Some(w) = &wide {
            let part = wide_arrays(w, storage, bvh.masks().map(|m| &**m));
            wide_pages = Pages::plan(storage, &part, limits)?;
            arrays.extend(wide_pages.split(part));
        }
        for a in &arrays {
            a.check(limits)?;
        }
        let layout = ArraysLayout {
            storage,
            instanced: bvh.is_instanced(),
            masks: bvh.masks().is_some(),
            pages,
            wide_pages,
        };
        for &traversal in &opts.traversals {
            let opts = TraceOptions::closest(traversal);
            check_bindings(&layout, &opts, limits)?;
        }
        let start = Instant::now();
        let made = backend.create_arrays(layout, &arrays)?;
        let stats = UploadStats {
            upload_ms: start.elapsed().as_secs_f64() * 1e3,
            ..stats_of(storage, &arrays)
        };
        let binary_stats = stats_of(
            storage,
            &arrays[..arrays.iter().filter(|a| !a.role.is_wide()).count()],
        );
        let host_copy = Self::host_copy_of(&backend, bvh, wide.clone());
        Ok(Engine {
            tree: UploadedTree {
                storage,
                instanced: bvh.is_instanced(),
                masks: bvh.masks().is_some(),
                binary,
                escapes: with_escapes,
                wide: opts.wide(),
                depth: bvh.depth(),
                shape: tree_shape(bvh),
                pages,
                wide_pages,
            },
            sizes: arrays
                .iter()
                .map(|a| ((a.role, a.page), a.bytes.len()))
                .collect(),
            stats,
            binary_stats,
            host_copy,
            scratch: Mutex::new(Vec::new()),
            mesh_fingerprint: mesh_fingerprint(bvh),
            used: Mutex::new(Vec::new()),
            instances: InstanceTable::of(bvh),
            arrays: made,
            backend,
        })
    }

    /// The tree incomplete rays are finished on, with the wide layout uploaded (`wide`):
    /// kept when the backend's tuning sets a trip budget, or when the wide tree is deep
    /// enough for a ray to overflow the wide walk's stack (on any device).
    fn host_copy_of(backend: &B, bvh: &FlatBvh, wide: Option<Arc<WideBvh>>) -> Option<HostCopy> {
        let deep = wide
            .as_ref()
            .is_some_and(|w| may_overflow(Traversal::Wide, w.depth));
        (backend.tuning().finishes_on_cpu() || deep).then(|| HostCopy {
            wide: wide.or_else(|| bvh.wide().cloned()),
            bvh: Arc::new(bvh.clone()),
        })
    }

    /// True when this upload keeps a copy of the tree on the host, to finish the rays a
    /// CPU driver's trip budget or the wide walk's stack leaves incomplete.
    pub fn keeps_host_copy(&self) -> bool {
        self.host_copy.is_some()
    }

    /// After the device changed this upload's one-mesh tree in place (a refit there):
    /// `bvh`, read back, becomes the host copy. Nothing is written to the device. `bvh`
    /// must have the upload's shape.
    pub fn refitted_on_device(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        check_update_shape(self.tree.shape, bvh)?;
        self.host_copy = Self::host_copy_of(&self.backend, bvh, None);
        Ok(())
    }

    /// The backend the arrays live on.
    pub fn device(&self) -> &B {
        &self.backend
    }

    /// The backend's arrays.
    pub fn arrays(&self) -> &B::Arrays {
        &self.arrays
    }

    /// What the upload holds.
    pub fn tree(&self) -> &UploadedTree {
        &self.tree
    }

    /// What the upload holds and cost (both layouts together).
    pub fn stats(&self) -> &UploadStats {
        &self.stats
    }

    /// Where both layouts live, buffers or textures; the rays of a trace follow it.
    pub fn storage(&self) -> BvhStorage {
        self.tree.storage
    }

    /// True when the wide layout was uploaded.
    pub fn has_wide(&self) -> bool {
        self.tree.wide
    }

    /// True when the escape links were uploaded.
    pub fn has_escapes(&self) -> bool {
        self.tree.escapes
    }

    /// True when the tree's alpha masks were uploaded (its bind groups have them,
    /// binding 5).
    pub fn has_masks(&self) -> bool {
        self.tree.masks
    }

    /// True for a two-level BVH (its bind groups have the instances, binding 4).
    pub fn is_instanced(&self) -> bool {
        self.tree.instanced
    }

    /// The binary tree's depth (edges on its longest root-to-leaf path).
    pub fn depth(&self) -> u32 {
        self.tree.depth
    }

    /// Number of nodes uploaded.
    pub fn node_count(&self) -> usize {
        self.tree.shape.0
    }

    /// Number of triangles uploaded.
    pub fn triangle_count(&self) -> usize {
        self.tree.shape.1
    }

    /// Where the kernels read their rays from: textures with the BVH in textures.
    pub fn ray_input(&self) -> RayInput {
        RayInput::for_storage(self.tree.storage)
    }

    /// The kernel tracing `opts` on this upload, with rays from `input`, with the box
    /// test's parallel path when `parallel_rays` ([`KernelKey::for_rays`]).
    pub fn key(&self, opts: &TraceOptions, input: RayInput, parallel_rays: bool) -> KernelKey {
        KernelKey {
            parallel_rays,
            ..KernelKey::new(self.tree.storage, opts)
                .with_rays(input)
                .with_instances(self.tree.instanced)
                .with_masks(self.tree.masks)
                .with_pages(self.tree.layout().pages_for(opts.traversal))
        }
    }

    /// Checks that this upload holds what `traversal` reads, and that the tree fits its
    /// stack.
    pub fn supports_traversal(&self, traversal: Traversal) -> Result<(), TraceError> {
        let w = walk(traversal);
        match w.layout {
            Layout::Wide if !self.tree.wide => {
                return Err(TraceError::WideLayoutMissing {
                    missing: WIDE_NOT_UPLOADED,
                });
            }
            Layout::Binary if !self.tree.binary => {
                return Err(TraceError::TraversalNotUploaded { traversal });
            }
            _ => {}
        }
        if w.escapes && !self.tree.escapes {
            return Err(TraceError::EscapesNotUploaded { traversal });
        }
        check_depth(traversal, self.tree.depth)
    }

    /// Checks that `opts` can run on this upload and device ([`Tracer::supports`]).
    pub fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.supports_traversal(opts.traversal)?;
        check_bindings(&self.tree.layout(), opts, self.backend.limits())?;
        let key = self.key(opts, self.ray_input(), true);
        (self.backend.features()).check(&key, || self.backend.device_name())
    }

    /// Builds the pipelines [`Engine::trace`] runs for `opts` (with the box test's
    /// parallel path and without it) ahead of the first trace.
    pub fn prepare(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.supports(opts)?;
        for parallel_rays in [true, false] {
            self.backend
                .prepare_kernel(self.key(opts, self.ray_input(), parallel_rays))?;
        }
        Ok(())
    }

    /// Counts `key` among the kernels that ran ([`Tracer::kernels_used`]).
    pub fn note_used(&self, key: KernelKey) -> Result<(), TraceError> {
        let mut used = self
            .used
            .lock()
            .map_err(|_| TraceError::Poisoned("kernels used"))?;
        if !used.contains(&key) {
            used.push(key);
        }
        Ok(())
    }

    /// `(rays per submission, scratch capacity, scratches)` for a batch of `n` rays from
    /// `input`: a ray texture holds one dispatch; with submissions in flight
    /// ([`DriverTuning::in_flight`]) each carries at most the tuning's `submission_rays`,
    /// on as many scratches as are in flight at once.
    fn submissions(&self, n: u64, input: RayInput) -> (u64, u64, usize) {
        let limits = self.backend.limits();
        let mut most = rays_per_submission(limits);
        if input == RayInput::Texture {
            most = most.min(ray_texture_capacity(limits));
        }
        let (per_submit, slots) = submissions_in_flight(n, most, self.backend.tuning());
        let capacity = n.min(per_submit).max(u64::from(WORKGROUP_SIZE));
        (per_submit, capacity, slots)
    }

    /// Traces `rays` as `opts` says: the kernel built first (an unsupported option fails
    /// before any upload), the batch split into submissions the scratch holds, each waited
    /// for and read back, GPU times summed, incomplete rays finished on the host copy.
    pub fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        if cfg!(target_arch = "wasm32") {
            // Blocking would stop the browser's event loop, which completes the readback.
            return Err(TraceError::Device {
                during: "tracing",
                message: "a browser cannot wait for its GPU: use trace_async".into(),
            });
        }
        pollster::block_on(self.trace_async(rays, opts))
    }

    /// [`Engine::trace`] as a future: what a program in a browser awaits.
    pub async fn trace_async(
        &self,
        rays: &[Ray],
        opts: &TraceOptions,
    ) -> Result<TraceOutput, TraceError> {
        self.supports(opts)?;
        let input = self.ray_input();
        // The rays' scan counts in the wall time (and the upload), a kernel's first
        // compilation does not.
        let scan = Instant::now();
        let key = self.key(opts, input, true).for_rays(rays);
        let scan_ms = scan.elapsed().as_secs_f64() * 1e3;
        self.backend.prepare_kernel(key)?;
        self.note_used(key)?;
        let start = Instant::now();
        let mut out = new_output(
            rays.len(),
            opts,
            self.backend.has_timestamps(),
            self.instances.clone(),
        );
        if rays.is_empty() {
            return Ok(out);
        }
        let (per_submit, capacity, slots) = self.submissions(rays.len() as u64, input);
        let kept = self.take_scratch(slots, capacity, opts.counters, input)?;
        let traced = self
            .run_batches(&kept[..slots], key, rays, per_submit, &mut out)
            .await;
        self.keep_scratch(kept);
        traced?;
        out.incomplete =
            self.finish_incomplete(rays, opts, &mut out.hits, out.counters.as_deref_mut());
        out.wall_ms = scan_ms + start.elapsed().as_secs_f64() * 1e3;
        if let Some(p) = out.phases.as_mut() {
            p.upload_ms += scan_ms;
        }
        Ok(out)
    }

    /// Runs `rays` through `key` in submissions of `per_submit` rays, one on each of
    /// `kept`'s scratches in turn, as many in flight as there are scratches: the oldest is
    /// read back before its scratch takes the next. The hits, counters and GPU times go
    /// into `out`, in order.
    async fn run_batches(
        &self,
        kept: &[Kept<B::Scratch>],
        key: KernelKey,
        rays: &[Ray],
        per_submit: u64,
        out: &mut TraceOutput,
    ) -> Result<(), TraceError> {
        let mut in_flight: VecDeque<(usize, B::Submitted)> = VecDeque::with_capacity(kept.len());
        for (i, part) in rays.chunks(per_submit as usize).enumerate() {
            if in_flight.len() == kept.len() {
                self.finish_oldest(kept, &mut in_flight, out).await?;
            }
            let slot = i % kept.len();
            let batch = Batch { key, rays: part };
            let submitted = self
                .backend
                .submit_batch(&self.arrays, &kept[slot].scratch, batch)?;
            in_flight.push_back((slot, submitted));
        }
        while !in_flight.is_empty() {
            self.finish_oldest(kept, &mut in_flight, out).await?;
        }
        Ok(())
    }

    /// Reads the oldest submission of `in_flight` back into `out`.
    async fn finish_oldest(
        &self,
        kept: &[Kept<B::Scratch>],
        in_flight: &mut VecDeque<(usize, B::Submitted)>,
        out: &mut TraceOutput,
    ) -> Result<(), TraceError> {
        let Some((slot, submitted)) = in_flight.pop_front() else {
            return Ok(());
        };
        let to = BatchOut {
            hits: &mut out.hits,
            counters: out.counters.as_mut(),
        };
        let times = self
            .backend
            .finish_batch(&kept[slot].scratch, submitted, to)
            .await?;
        if let (Some(total), Some(ms)) = (out.gpu_ms.as_mut(), times.gpu_ms) {
            *total += ms;
        }
        out.phases = out.phases.map(|p| p + times.phases);
        Ok(())
    }

    /// At least `slots` scratches for a trace of `capacity` rays a submission (with
    /// counters when `counters`), taken out of the upload for as long as the trace runs:
    /// those kept when they hold enough, else new ones (counters once asked for are kept
    /// from then on, and scratch only grows). A trace running beside it on another thread
    /// makes its own.
    fn take_scratch(
        &self,
        slots: usize,
        capacity: u64,
        counters: bool,
        input: RayInput,
    ) -> Result<Vec<Kept<B::Scratch>>, TraceError> {
        let mut kept = std::mem::take(
            &mut *self
                .scratch
                .lock()
                .map_err(|_| TraceError::Poisoned("scratch buffers"))?,
        );
        let held = kept.iter().map(|k| k.plan.capacity).max().unwrap_or(0);
        let had_counters = kept.iter().any(|k| k.plan.counters);
        // Scratch too small, or without counters when they are asked for, is freed first.
        kept.retain(|k| k.plan.capacity >= capacity && (k.plan.counters || !counters));
        let plan = ScratchPlan {
            capacity: capacity.max(held),
            counters: counters || had_counters,
            input,
        };
        while kept.len() < slots {
            kept.push(Kept {
                plan,
                scratch: self.backend.create_scratch(&plan)?,
            });
        }
        Ok(kept)
    }

    /// Puts a trace's scratches back for the next trace; of two traces that ran at once,
    /// the one with more scratch is kept.
    fn keep_scratch(&self, kept: Vec<Kept<B::Scratch>>) {
        let total = |v: &[Kept<B::Scratch>]| v.iter().map(|k| k.plan.capacity).sum::<u64>();
        if let Ok(mut slot) = self.scratch.lock()
            && total(&slot) < total(&kept)
        {
            *slot = kept;
        }
    }

    /// Replaces every [`INCOMPLETE`] hit by the CPU walk's answer on the host copy (and
    /// its counters, when given): what the kernels leave under a CPU driver's trip budget
    /// or when the wide stack would overflow. Returns how many were finished; 0 when this
    /// upload keeps no host copy (no ray can come back incomplete).
    pub fn finish_incomplete(
        &self,
        rays: &[Ray],
        opts: &TraceOptions,
        hits: &mut [Hit],
        counters: Option<&mut [Counters]>,
    ) -> u64 {
        match &self.host_copy {
            Some(h) => {
                finish_incomplete_hits(&h.bvh, h.wide.as_deref(), rays, opts, hits, counters)
            }
            None => {
                debug_assert!(!hits.iter().any(|h| h.prim == INCOMPLETE));
                0
            }
        }
    }

    /// Makes `bvh` the traced tree ([`Tracer::update`]): only the top level and the
    /// instances are written when the meshes of a two-level tree did not change.
    pub fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        let fingerprint = mesh_fingerprint(bvh);
        let what = if bvh.is_instanced() && fingerprint == self.mesh_fingerprint {
            Update::TopLevel
        } else {
            Update::Everything
        };
        self.write_update(bvh, what, fingerprint)
    }

    /// Writes `bvh` over this upload in place, as `what` says: its shape must be the
    /// upload's, and [`Update::TopLevel`] needs a two-level tree. An uploaded wide layout
    /// is collapsed again from `bvh` (its `wide`, which a refit leaves stale, is not read)
    /// and written whole, into new arrays only when the collapse came out with other sizes.
    pub fn update_with(&mut self, bvh: &FlatBvh, what: Update) -> Result<(), TraceError> {
        // A top-level update leaves the meshes, and so their fingerprint, as they were.
        let fingerprint = match what {
            Update::TopLevel => self.mesh_fingerprint,
            Update::Everything => mesh_fingerprint(bvh),
        };
        self.write_update(bvh, what, fingerprint)
    }

    /// [`Engine::update_with`] with the fingerprint of `bvh`'s meshes already known, so the
    /// meshes are hashed once per update.
    fn write_update(
        &mut self,
        bvh: &FlatBvh,
        what: Update,
        fingerprint: u64,
    ) -> Result<(), TraceError> {
        check_update_shape(self.tree.shape, bvh)?;
        if bvh.masks().is_some() != self.tree.masks {
            return Err(TraceError::BadBuffer {
                buffer: "alpha masks",
                problem: format!(
                    "the upload was made {} alpha masks and the update has {}: upload again",
                    if self.tree.masks { "with" } else { "without" },
                    if bvh.masks().is_some() {
                        "some"
                    } else {
                        "none"
                    }
                ),
            });
        }
        let top_only = what == Update::TopLevel;
        if top_only && !bvh.is_instanced() {
            return Err(TraceError::BadBuffer {
                buffer: "nodes",
                problem: "Update::TopLevel needs a two-level tree; this one is one mesh".into(),
            });
        }
        let storage = self.tree.storage;
        let wide = self.tree.wide.then(|| Arc::new(WideBvh::collapse(bvh)));
        let mut arrays = Vec::new();
        if self.tree.binary {
            // Textures are written whole; buffers only as far as the change goes.
            let part = top_only && storage == BvhStorage::Buffers;
            let nodes = if part {
                bvh.top_nodes() as usize
            } else {
                bvh.nodes().len()
            };
            let links = self.tree.escapes.then(|| match part {
                true => top_links(bvh.top_nodes()),
                false => bvh.escapes().len(),
            });
            arrays = binary_arrays(bvh, storage, nodes, !top_only, links);
        }
        if let Some(w) = &wide {
            check_wide_top_level(w)?;
            arrays.extend(wide_arrays(w, storage, bvh.masks().map(|m| &**m)));
        }
        let layout = self.tree.layout();
        let wide_part = arrays.split_off(arrays.iter().take_while(|a| !a.role.is_wide()).count());
        let mut arrays = layout.pages.split(arrays);
        // The wide arrays come last: their stats before the arrays go to the writes.
        let wide_from = arrays.len();
        if !wide_part.is_empty() {
            let limits = self.backend.limits();
            if Pages::plan(storage, &wide_part, limits)? != layout.wide_pages {
                return Err(TraceError::BadBuffer {
                    buffer: "wide nodes",
                    problem: "the wide layout collapsed again needs another split over the \
                              device's bindings than the upload's: upload again"
                        .into(),
                });
            }
            arrays.extend(layout.wide_pages.split(wide_part));
        }
        for a in &arrays {
            a.check(self.backend.limits())?;
        }
        let wide_stats = stats_of(storage, &arrays[wide_from..]);
        let mut writes = Vec::with_capacity(arrays.len());
        for array in arrays {
            let at = (array.role, array.page);
            let old = self.sizes.iter_mut().find(|(r, _)| *r == at);
            // Only the wide layout's sizes may change (the collapse follows the boxes).
            let replace = match old {
                Some((_, size))
                    if (array.role.is_wide() || array.role == ArrayRole::Masks)
                        && *size != array.bytes.len() =>
                {
                    *size = array.bytes.len();
                    true
                }
                Some(_) => false,
                None => {
                    self.sizes.push((at, array.bytes.len()));
                    true
                }
            };
            writes.push(ArrayWrite { array, replace });
        }
        self.backend
            .write_arrays(&mut self.arrays, layout, &writes)?;
        if wide.is_some() {
            let w = wide_stats;
            let b = self.binary_stats;
            self.stats = UploadStats {
                nodes_bytes: b.nodes_bytes + w.nodes_bytes,
                triangles_bytes: b.triangles_bytes + w.triangles_bytes,
                instances_bytes: b.instances_bytes + w.instances_bytes,
                masks_bytes: b.masks_bytes + w.masks_bytes,
                ..self.stats
            };
        }
        self.host_copy = Self::host_copy_of(&self.backend, bvh, wide.clone());
        self.tree.depth = bvh.depth();
        self.mesh_fingerprint = fingerprint;
        self.instances = InstanceTable::of(bvh);
        Ok(())
    }

    /// Runs `f` on the scratches kept between traces (none before the first trace; one per
    /// submission in flight).
    pub fn with_scratch<T>(&self, f: impl FnOnce(&[&B::Scratch]) -> T) -> T {
        match self.scratch.lock() {
            Ok(g) => f(&g.iter().map(|k| &k.scratch).collect::<Vec<_>>()),
            Err(_) => f(&[]),
        }
    }
}

/// A type that traces through an [`Engine`] (the device backends' BVH types): it is a
/// [`Tracer`] by that engine, with nothing to write again.
pub trait HasEngine: SendSync {
    /// The backend of the engine.
    type Device: DeviceApi;
    /// The engine.
    fn engine(&self) -> &Engine<Self::Device>;
    /// The engine, to update.
    fn engine_mut(&mut self) -> &mut Engine<Self::Device>;
}

impl<B: DeviceApi> HasEngine for Engine<B> {
    type Device = B;
    fn engine(&self) -> &Engine<B> {
        self
    }
    fn engine_mut(&mut self) -> &mut Engine<B> {
        self
    }
}

impl<T: HasEngine + 'static> Tracer for T {
    fn backend(&self) -> &'static str {
        self.engine().backend.name()
    }

    fn device_name(&self) -> String {
        self.engine().backend.device_name()
    }

    fn default_traversal(&self) -> Traversal {
        self.engine().backend.tuning().walk
    }

    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.engine().supports(opts)
    }

    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        self.engine().trace(rays, opts)
    }

    fn trace_async<'a>(&'a self, rays: &'a [Ray], opts: &'a TraceOptions) -> TraceFuture<'a> {
        Box::pin(self.engine().trace_async(rays, opts))
    }

    fn prepare(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.engine().prepare(opts)
    }

    fn upload_stats(&self) -> Option<UploadStats> {
        Some(self.engine().stats)
    }

    fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        self.engine_mut().update(bvh)
    }

    fn kernels_used(&self) -> Vec<KernelKey> {
        let used = self.engine().used.lock();
        used.map(|u| u.clone()).unwrap_or_default()
    }

    fn as_any(&self) -> Option<&dyn std::any::Any> {
        Some(self)
    }
}
