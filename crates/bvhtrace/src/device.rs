//! [`Device`]: a backend opened once, to open tracers and build trees on.

use std::borrow::Borrow;
use std::fmt;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, Traversal, Triangle};
use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::tracer::SendSync;
use bvhtrace_engine::{DriverTuning, TraceError, Tracer};

use crate::backends;
use crate::backends::interface::{DeviceInterface, Tree};
use crate::open::exceeds_a_limit;
use crate::{Backend, OpenOptions, Opened};

/// A backend opened once (the device and its pipeline cache), to open tracers on for many
/// trees and to build trees on. Cheap to clone: the device is shared.
#[derive(Clone)]
pub struct Device {
    pub(crate) inner: Arc<dyn DeviceInterface>,
    /// Opened as [`Backend::Auto`]: a tree over the device's limits goes to the CPU.
    pub(crate) auto: bool,
    /// Why this is not the backend asked for.
    fallback: Option<String>,
    /// Why [`Backend::Auto`] chose what it did on a device with ray queries.
    choice: Option<String>,
}

impl fmt::Debug for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Device")
            .field("backend", &self.backend())
            .field("name", &self.name())
            .field("fallback", &self.fallback)
            .finish()
    }
}

impl Device {
    /// Opens the backend and adapter `opts` asks for ([`Backend::Auto`]: wgpu on the best
    /// Vulkan adapter, with its ray queries where it has them in hardware, else the CPU,
    /// saying why in [`Device::fallback`] and [`Device::choice`]).
    pub fn new(opts: &OpenOptions) -> Result<Device, TraceError> {
        let opened = backends::open(opts)?;
        Ok(Device {
            inner: opened.device,
            auto: opts.backend == Backend::Auto,
            fallback: opened.fallback,
            choice: opened.choice,
        })
    }

    /// A device the caller opened by hand (a backend module's constructor).
    pub(crate) fn from_interface(inner: Arc<dyn DeviceInterface>) -> Device {
        Device {
            inner,
            auto: false,
            fallback: None,
            choice: None,
        }
    }

    /// The CPU walks.
    pub fn cpu() -> Device {
        Device::from_interface(backends::cpu::device())
    }

    /// The backend (never [`Backend::Auto`]).
    pub fn backend(&self) -> Backend {
        self.inner.backend()
    }

    /// The adapter's name and type, or `cpu`.
    pub fn name(&self) -> String {
        self.inner.name()
    }

    /// Why this is not the backend asked for (`None` when it is).
    pub fn fallback(&self) -> Option<&str> {
        self.fallback.as_deref()
    }

    /// Why [`Backend::Auto`] chose ray queries or our walks, on a device that offers ray
    /// queries: hardware ray tracing is the faster path, a CPU driver's software ray
    /// queries are not (`None` on a device without them, and for a named backend).
    pub fn choice(&self) -> Option<&str> {
        self.choice.as_deref()
    }

    /// The CPU-driver measures in force on a device backend (`None` on the CPU).
    pub fn tuning(&self) -> Option<DriverTuning> {
        self.inner.tuning()
    }

    /// The limits uploads and batches are planned within (`None` on the CPU).
    pub fn limits(&self) -> Option<DeviceLimits> {
        self.inner.limits()
    }

    /// The wgpu context, on a wgpu device (our walks or its ray queries): for your own
    /// WGSL on the same device.
    pub fn wgpu_context(&self) -> Option<&bvhtrace_gpu::GpuContext> {
        self.inner.wgpu_context()
    }

    /// Builds a BVH over `tris` on this device, with the device builders
    /// ([`GpuBuildOptions`]: PLOC or LBVH, in WGSL compute) on the same device its tracers
    /// trace on, and reads the tree back. The CPU backend has no device to build on: an
    /// error saying so (the CPU builders are `FlatBvh::build`). Not in a browser, which
    /// cannot wait for its GPU (`GpuContext::build_bvh_async` there).
    pub fn build_bvh(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
        self.inner.build_bvh(tris, opts)
    }

    /// Opens a tracer for `bvh` on this device, as [`crate::open`] does (`opts.backend`,
    /// `opts.adapter` and `opts.tuning` were the device's business and are not read).
    pub fn open<'a, B>(&self, bvh: B, opts: &OpenOptions) -> Result<Opened<'a>, TraceError>
    where
        B: Borrow<FlatBvh> + Send + Sync + 'a,
    {
        self.open_tree(Tree::kept(bvh), opts)
    }

    /// [`Device::open`] for a tracer that keeps no borrow of `bvh` (a device upload, or
    /// the CPU walks on a shared copy): what a tracer factory hands out.
    pub fn open_owned(
        &self,
        bvh: &FlatBvh,
        opts: &OpenOptions,
    ) -> Result<Opened<'static>, TraceError> {
        self.open_tree(Tree::Read(bvh), opts)
    }

    /// Opens on `tree`: a hit filter written in Rust goes to the CPU ([`Backend::Auto`])
    /// or is refused; a tree over this device's limits goes to the CPU for
    /// [`Backend::Auto`].
    fn open_tree<'a>(
        &self,
        tree: Tree<'_, 'a>,
        opts: &OpenOptions,
    ) -> Result<Opened<'a>, TraceError> {
        if opts.filter.is_some() && !self.inner.applies_rust_filters() {
            if !self.auto {
                return Err(TraceError::Unsupported {
                    backend: self.backend().name(),
                    what: "hit filters written in Rust: the CPU backend applies them (alpha \
                           masks travel with the BVH instead, FlatBvh::set_masks)"
                        .into(),
                });
            }
            let why = "only the CPU walks apply a hit filter written in Rust: tracing on the CPU";
            return backends::cpu::open(tree, opts, Some(why.into()));
        }
        match self.inner.open(tree, opts, self.auto) {
            Ok(mut o) => {
                o.choice = self.choice.clone();
                o.fallback = o.fallback.or_else(|| self.fallback.clone());
                Ok(o)
            }
            Err((e, Some(tree))) if self.auto && exceeds_a_limit(&e) => {
                let why = format!(
                    "the scene does not fit {} ({e}); tracing on the CPU",
                    self.name()
                );
                backends::cpu::open(tree, opts, Some(why))
            }
            Err((e, _)) => Err(e),
        }
    }

    /// A tracer factory on this device: each call opens a tracer for the tree, uploaded
    /// for the walks listed ([`Device::open_owned`]). For a test suite or a stress run that
    /// takes tracers from its caller.
    pub fn tracer_factory(
        &self,
    ) -> impl Fn(&FlatBvh, &[Traversal]) -> Result<Box<dyn Tracer>, TraceError> + SendSync + 'static
    {
        let device = self.clone();
        move |bvh, walks| {
            let opts = OpenOptions {
                traversals: walks.to_vec(),
                ..OpenOptions::default()
            };
            Ok(device.open_owned(bvh, &opts)?.tracer)
        }
    }
}
