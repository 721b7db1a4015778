//! What every backend module implements ([`DeviceInterface`]) and what they share: the
//! tree a tracer is opened on, the answer of an open, a backend opened with what to say of
//! it.

use std::any::Any;
use std::borrow::Borrow;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::tracer::SendSync;
use bvhtrace_engine::{DriverTuning, TraceError};
use bvhtrace_gpu::GpuContext;

use crate::{Backend, OpenOptions, Opened, TimedScene, TimedTracer};

/// A tree kept for as long as a tracer lives, borrowed, shared or owned.
pub(crate) struct Kept<'a>(Box<dyn Borrow<FlatBvh> + Send + Sync + 'a>);

impl Borrow<FlatBvh> for Kept<'_> {
    fn borrow(&self) -> &FlatBvh {
        (*self.0).borrow()
    }
}

/// The tree a tracer is opened on: kept by a tracer that traces it in place (the CPU
/// walks), or only read during the call (a device upload; a tracer that traces in place
/// then keeps a copy).
pub(crate) enum Tree<'t, 'a> {
    /// Kept as given.
    Kept(Kept<'a>),
    /// Read during the call.
    Read(&'t FlatBvh),
}

impl<'t, 'a> Tree<'t, 'a> {
    /// `bvh`, to be kept as given.
    pub(crate) fn kept<B: Borrow<FlatBvh> + Send + Sync + 'a>(bvh: B) -> Tree<'t, 'a> {
        Tree::Kept(Kept(Box::new(bvh)))
    }

    /// The tree.
    pub(crate) fn get(&self) -> &FlatBvh {
        match self {
            Tree::Kept(k) => k.borrow(),
            Tree::Read(t) => t,
        }
    }

    /// The tree to keep: as given, or a shared copy of one only read.
    pub(crate) fn keep(self) -> Kept<'a> {
        match self {
            Tree::Kept(k) => k,
            Tree::Read(t) => Kept(Box::new(Arc::new(t.clone()))),
        }
    }
}

/// What [`DeviceInterface::open_timed`] returns: the tracer, and a note when it is not
/// what the backend's name promises.
pub(crate) type TimedOpen = (Box<dyn TimedTracer>, Option<String>);

/// What [`DeviceInterface::open`] returns: the opened tracer, or the error with the tree
/// given back when another backend may take it (so that [`Backend::Auto`] can open the
/// CPU walks on it instead).
pub(crate) type OpenResult<'t, 'a> = Result<Opened<'a>, (TraceError, Option<Tree<'t, 'a>>)>;

/// An opened backend: what the front door asks of each.
pub(crate) trait DeviceInterface: SendSync + Any {
    /// Which backend.
    fn backend(&self) -> Backend;

    /// The adapter's name and type, or `cpu`.
    fn name(&self) -> String;

    /// The CPU-driver measures in force (`None` on the CPU).
    fn tuning(&self) -> Option<DriverTuning>;

    /// The limits uploads and batches are planned within (`None` on the CPU).
    fn limits(&self) -> Option<DeviceLimits>;

    /// True when its tracers apply a hit filter written in Rust (the CPU walks).
    fn applies_rust_filters(&self) -> bool {
        false
    }

    /// Opens a tracer on `tree` as `opts` says; `auto` when opened as [`Backend::Auto`]
    /// (a backend may then fall back within its device, as ray queries to our walks).
    fn open<'t, 'a>(
        &self,
        tree: Tree<'t, 'a>,
        opts: &OpenOptions,
        auto: bool,
    ) -> OpenResult<'t, 'a>;

    /// Builds a BVH over `tris` with a device builder, read back.
    fn build_bvh(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError>;

    /// Opens a tracer for a scene in time or with curves, with a note when it is not
    /// traced as this backend traces flat trees. By default our walks on the device's wgpu
    /// context, where it has one.
    fn open_timed(&self, scene: &TimedScene) -> Result<TimedOpen, TraceError> {
        match self.wgpu_context() {
            Some(ctx) => Ok((crate::timed::on_wgpu(ctx, scene)?, None)),
            None => Err(crate::timed::unsupported(self.backend(), scene)),
        }
    }

    /// The wgpu context it traces on (our walks or the device's ray queries), for a caller
    /// that composes its own WGSL on the same device.
    fn wgpu_context(&self) -> Option<&GpuContext> {
        None
    }

    /// For a backend module's own accessors ([`crate::Device`]'s, downcast; none in a
    /// browser).
    #[cfg_attr(target_arch = "wasm32", allow(dead_code))]
    fn as_any(&self) -> &dyn Any;
}

/// [`DeviceInterface::open`] for a backend that uploads the tree and keeps nothing of it:
/// `upload`'s answer, or its error with the tree given back.
pub(crate) fn uploaded<'t, 'a>(
    tree: Tree<'t, 'a>,
    upload: impl FnOnce(&FlatBvh) -> Result<Opened<'static>, TraceError>,
) -> OpenResult<'t, 'a> {
    match upload(tree.get()) {
        Ok(o) => Ok(o),
        Err(e) => Err((e, Some(tree))),
    }
}

/// A backend opened by [`super::open`], and what to say of it.
pub(crate) struct OpenedDevice {
    pub(crate) device: Arc<dyn DeviceInterface>,
    /// Why this is not the backend asked for.
    pub(crate) fallback: Option<String>,
    /// Why [`Backend::Auto`] chose ray queries or our walks.
    pub(crate) choice: Option<String>,
}

impl OpenedDevice {
    /// `device`, as asked.
    pub(crate) fn plain(device: Arc<dyn DeviceInterface>) -> OpenedDevice {
        OpenedDevice {
            device,
            fallback: None,
            choice: None,
        }
    }
}

/// The error of a backend without a device builder.
pub(crate) fn no_device_builder(backend: Backend) -> TraceError {
    TraceError::Unsupported {
        backend: backend.name(),
        what: "building a BVH on a device (gpu-ploc, gpu-lbvh): it has no device to build \
               on; open wgpu or Vulkan, or build on the CPU (FlatBvh::build)"
            .into(),
    }
}
