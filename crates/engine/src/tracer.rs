//! One tracing interface over every backend, and the CPU walks behind it: the tracer of
//! the CPU backend, and what finishes the rays a device gives up on.

use std::borrow::Borrow;
use std::sync::{Arc, OnceLock};

use bvhtrace_core::{
    Counters, FlatBvh, Hit, HitFilter, INCOMPLETE, Ray, TraceOptions, TraceOutput, Traversal,
    WideBvh,
};

use crate::error::TraceError;
use crate::key::KernelKey;
use crate::upload::UploadStats;

/// `Send + Sync`, except in a browser: there wgpu's objects are neither, and one thread
/// runs everything.
#[cfg(not(target_arch = "wasm32"))]
pub trait SendSync: Send + Sync {}
#[cfg(not(target_arch = "wasm32"))]
impl<T: Send + Sync> SendSync for T {}
/// `Send + Sync`, except in a browser: there wgpu's objects are neither, and one thread
/// runs everything.
#[cfg(target_arch = "wasm32")]
pub trait SendSync {}
#[cfg(target_arch = "wasm32")]
impl<T> SendSync for T {}

/// What [`Tracer::trace_async`] returns.
pub type TraceFuture<'a> =
    std::pin::Pin<Box<dyn std::future::Future<Output = Result<TraceOutput, TraceError>> + 'a>>;

/// Something that traces rays through one BVH: the CPU walks ([`CpuTracer`]), the wgpu
/// backend (`bvhtrace_gpu::GpuBvh`) or the ash backend (`bvhtrace_vk::VkBvh`). Given the
/// same rays and options, every implementation returns the same hits bit for bit.
///
/// Implementations are `Send + Sync` (except in a browser, which runs one thread): one
/// uploaded BVH can be traced from several threads at once.
pub trait Tracer: SendSync {
    /// The backend's name: `cpu`, `wgpu` or `vulkan`.
    fn backend(&self) -> &'static str;

    /// The device that traces: the adapter's name and type, or the CPU's thread count.
    fn device_name(&self) -> String;

    /// The walk this backend runs fastest; what a front end uses when none is asked for.
    fn default_traversal(&self) -> Traversal;

    /// `Ok` when [`Tracer::trace`] can run `opts` here; otherwise the error it would
    /// return (escape links not uploaded, no wide layout for the wide walk, a tree too
    /// deep for the full stack, a precision the device lacks).
    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError>;

    /// The walks this tracer answers, one of each kind in [`Traversal::ALL`]'s order (a
    /// short stack listed answers for any size): what a front end offers its user, rather
    /// than predicting what an upload holds.
    fn traversals(&self) -> Vec<Traversal> {
        (Traversal::ALL.into_iter())
            .filter(|&t| self.supports(&TraceOptions::closest(t)).is_ok())
            .collect()
    }

    /// Traces `rays` as `opts` says: one hit per ray, in order, with counters when asked
    /// for, and the times.
    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError>;

    /// [`Tracer::trace`] as a future, for a program that must not block: in a browser, the
    /// GPU's answer arrives on the event loop, so a page awaits this (`trace` refuses
    /// there). The CPU walks finish before the future is returned.
    fn trace_async<'a>(&'a self, rays: &'a [Ray], opts: &'a TraceOptions) -> TraceFuture<'a> {
        Box::pin(std::future::ready(self.trace(rays, opts)))
    }

    /// Does the one-time work for `opts` ahead of the first trace (compiling pipelines),
    /// so that the first trace's time is not the compiler's. Nothing to do on the CPU.
    fn prepare(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.supports(opts)
    }

    /// What the upload to the device holds and cost; `None` on the CPU.
    fn upload_stats(&self) -> Option<UploadStats> {
        None
    }

    /// Milliseconds the device's driver spent building its own acceleration structures
    /// at the last upload or update (the ray-query tracer); `None` for our walks, whose
    /// tree is built on the CPU.
    fn device_build_ms(&self) -> Option<f64> {
        None
    }

    /// Bytes of the BVH held on the device (0 on the CPU).
    fn uploaded_bytes(&self) -> u64 {
        self.upload_stats().map_or(0, |s| s.total_bytes())
    }

    /// Makes `bvh` the tree this tracer traces, in place: `bvh` is the traced tree after a
    /// change of the same shape (instances moved with
    /// `InstancedBvh::set_transforms`, meshes refitted with `InstancedBvh::refit_mesh`).
    /// The tracer works out what changed: when only the top level of a two-level tree did,
    /// only it and the instances are written. A tree of another shape (node, triangle or
    /// instance count) is a [`TraceError::BadBuffer`]: open a new tracer for it.
    fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError>;

    /// The kernels this tracer has run, each once, in the order of their first use; empty
    /// on the CPU. What a front end reports as the pipelines that ran.
    fn kernels_used(&self) -> Vec<KernelKey> {
        Vec::new()
    }

    /// The tracer as its own type, for its backend's own calls (the wgpu backend's
    /// `GpuBvh::record`, into the caller's encoder and buffers), by downcasting; `None`
    /// for a tracer that borrows its tree.
    fn as_any(&self) -> Option<&dyn std::any::Any> {
        None
    }
}

/// The shape an update must keep: node, triangle and instance counts and the top level's
/// node count.
pub fn tree_shape(bvh: &FlatBvh) -> (usize, usize, usize, u32) {
    (
        bvh.nodes().len(),
        bvh.triangles().len(),
        bvh.instances().len(),
        bvh.top_nodes(),
    )
}

/// A 64-bit fingerprint of the mesh part of a two-level tree (the nodes below the top
/// level and every triangle): what an update compares to learn whether only the top level
/// moved. 0 for one mesh.
pub fn mesh_fingerprint(bvh: &FlatBvh) -> u64 {
    if !bvh.is_instanced() {
        return 0;
    }
    let nodes: &[u8] = bytemuck::cast_slice(&bvh.nodes()[bvh.top_nodes() as usize..]);
    let tris: &[u8] = bytemuck::cast_slice(bvh.triangles());
    let mut h = [0xcbf2_9ce4_8422_2325u64; 4];
    for part in [nodes, tris] {
        // Four independent lanes so the multiplies overlap; every word counts.
        let mut words = part.chunks_exact(32);
        for w in &mut words {
            for (lane, c) in h.iter_mut().zip(w.chunks_exact(8)) {
                let x = u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]);
                *lane = (*lane ^ x).wrapping_mul(0x0000_0100_0000_01b3);
            }
        }
        for (i, &b) in words.remainder().iter().enumerate() {
            h[i % 4] = (h[i % 4] ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
        h[0] ^= part.len() as u64;
    }
    h.iter().fold(0u64, |a, &x| {
        a.rotate_left(17) ^ x.wrapping_mul(0x9e37_79b9_7f4a_7c15)
    })
}

/// [`TraceError::BadBuffer`] unless `bvh` has the `uploaded` shape ([`tree_shape`]).
pub fn check_update_shape(
    uploaded: (usize, usize, usize, u32),
    bvh: &FlatBvh,
) -> Result<(), TraceError> {
    let shape = tree_shape(bvh);
    if shape != uploaded {
        return Err(TraceError::BadBuffer {
            buffer: "nodes",
            problem: format!(
                "an update needs the traced tree's shape (nodes, triangles, instances, \
                 top-level nodes) {uploaded:?}; got {shape:?}: open a new tracer for it"
            ),
        });
    }
    Ok(())
}

/// The CPU walks of [`bvhtrace_core::traverse`] over a borrowed or owned tree (`&FlatBvh`,
/// `Arc<FlatBvh>` or `FlatBvh`), on the current rayon pool, with a hit filter when given
/// one ([`CpuTracer::with_filter`]). The wide walk takes the tree's wide layout, or one
/// collapsed from it on the first wide trace and kept beside it.
#[derive(Clone)]
pub struct CpuTracer<B = std::sync::Arc<FlatBvh>> {
    bvh: B,
    /// The tree given to [`Tracer::update`], which replaces `bvh` from then on.
    updated: Option<Arc<FlatBvh>>,
    /// The wide layout collapsed for a tree without one.
    wide: OnceLock<Arc<WideBvh>>,
    filter: Option<Arc<dyn HitFilter + Send>>,
}

impl<B: std::fmt::Debug> std::fmt::Debug for CpuTracer<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CpuTracer")
            .field("bvh", &self.bvh)
            .field("updated", &self.updated.is_some())
            .field("filter", &self.filter.is_some())
            .finish()
    }
}

impl<B: Borrow<FlatBvh>> CpuTracer<B> {
    /// Traces through `bvh`.
    pub fn new(bvh: B) -> Self {
        CpuTracer {
            bvh,
            updated: None,
            wide: OnceLock::new(),
            filter: None,
        }
    }

    /// Passes every walk's candidate hits through `filter`, your own rule (alpha masks need
    /// none: the walks cut by the BVH's own, `FlatBvh::masks`).
    pub fn with_filter(mut self, filter: Arc<dyn HitFilter + Send>) -> Self {
        self.filter = Some(filter);
        self
    }

    /// True when candidates pass through a filter ([`CpuTracer::with_filter`]).
    pub fn has_filter(&self) -> bool {
        self.filter.is_some()
    }

    /// The tree.
    pub fn bvh(&self) -> &FlatBvh {
        self.updated.as_deref().unwrap_or_else(|| self.bvh.borrow())
    }

    /// The wide layout: the tree's own, else collapsed from it now (once).
    pub fn wide(&self) -> &WideBvh {
        match self.bvh().wide() {
            Some(w) => w,
            None => self
                .wide
                .get_or_init(|| Arc::new(WideBvh::collapse(self.bvh()))),
        }
    }
}

impl<B: Borrow<FlatBvh> + Send + Sync> Tracer for CpuTracer<B> {
    fn backend(&self) -> &'static str {
        "cpu"
    }

    fn device_name(&self) -> String {
        format!("cpu ({} threads)", rayon::current_num_threads())
    }

    fn default_traversal(&self) -> Traversal {
        Traversal::CPU_DEFAULT
    }

    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        if opts.traversal.needs_escapes() {
            self.bvh().check_escape_links()?;
        }
        Ok(())
    }

    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        self.supports(opts)?;
        let filter = self.filter.as_deref().map(|f| f as &dyn HitFilter);
        let wide = opts.traversal.is_wide().then(|| self.wide());
        Ok(bvhtrace_core::trace_rays_in(
            self.bvh(),
            wide,
            rays,
            opts,
            filter,
        ))
    }

    fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        check_update_shape(tree_shape(self.bvh()), bvh)?;
        self.updated = Some(Arc::new(bvh.clone()));
        self.wide = OnceLock::new();
        Ok(())
    }
}

/// Replaces every [`INCOMPLETE`] hit in `out` by the CPU walk's answer for that ray on
/// `bvh` (same options; counters too when `out` has them) and counts them in
/// `out.incomplete`: what a device backend does after a kernel that ran under a trip
/// budget ([`crate::DriverTuning::trip_limit`]), or a wide walk whose stack would have
/// overflowed ([`crate::walks::DepthRule::FinishOnHost`]). The wide walk takes `bvh`'s wide
/// layout, or the tree collapsed here first: the same conversion the uploads make.
pub fn finish_incomplete(bvh: &FlatBvh, rays: &[Ray], opts: &TraceOptions, out: &mut TraceOutput) {
    out.incomplete += finish_incomplete_hits(
        bvh,
        None,
        rays,
        opts,
        &mut out.hits,
        out.counters.as_deref_mut(),
    );
}

/// [`finish_incomplete`] over the hits (and counters) themselves, as a recording caller
/// holds them, the wide walk on `wide` when given (else the tree's own, else collapsed
/// here): returns how many rays were finished.
pub fn finish_incomplete_hits(
    bvh: &FlatBvh,
    wide: Option<&WideBvh>,
    rays: &[Ray],
    opts: &TraceOptions,
    hits: &mut [Hit],
    mut counters: Option<&mut [Counters]>,
) -> u64 {
    if !hits.iter().any(|h| h.prim == INCOMPLETE) {
        return 0;
    }
    let collapsed;
    let wide = match (opts.traversal.is_wide(), wide.or(bvh.wide().map(|w| &**w))) {
        (true, None) => {
            collapsed = WideBvh::collapse(bvh);
            Some(&collapsed)
        }
        (_, w) => w,
    };
    let mut stack = Vec::new();
    let mut finished = 0;
    for (i, h) in hits.iter_mut().enumerate() {
        if h.prim != INCOMPLETE {
            continue;
        }
        let (hit, cost) = bvhtrace_core::trace_ray_in(bvh, wide, &rays[i], opts, None, &mut stack);
        *h = hit;
        if let Some(cs) = counters.as_deref_mut() {
            cs[i] = cost.counters();
        }
        finished += 1;
    }
    finished
}
