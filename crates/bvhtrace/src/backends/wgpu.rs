//! The wgpu backend: our WGSL walks through wgpu (`bvhtrace-gpu`), natively on Vulkan and
//! in a browser on WebGPU.

use std::any::Any;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::{DriverTuning, TraceError};
use bvhtrace_gpu::{ContextOptions, GpuBvh, GpuContext};

use super::interface::{DeviceInterface, OpenResult, Tree, uploaded};
use crate::open::{EngineDevice, open_engine};
use crate::{Backend, Device, OpenOptions, Opened};

/// A wgpu device tracing with our walks.
pub(crate) struct WgpuDevice {
    pub(crate) ctx: GpuContext,
}

/// The adapter's name and type.
pub(crate) fn adapter_name(ctx: &GpuContext) -> String {
    let i = ctx.adapter_info();
    format!("{} ({:?})", i.name, i.device_type)
}

impl WgpuDevice {
    /// Our walks on `ctx`, `tree` uploaded for the storage and walks of the ladder.
    pub(crate) fn upload(
        &self,
        bvh: &FlatBvh,
        opts: &OpenOptions,
    ) -> Result<Opened<'static>, TraceError> {
        let device = EngineDevice {
            backend: Backend::Wgpu,
            name: &adapter_name(&self.ctx),
            features: self.ctx.features(),
            tuning: *self.ctx.tuning(),
        };
        open_engine(&device, opts, |u| GpuBvh::upload(&self.ctx, bvh, u))
    }
}

impl DeviceInterface for WgpuDevice {
    fn backend(&self) -> Backend {
        Backend::Wgpu
    }

    fn name(&self) -> String {
        adapter_name(&self.ctx)
    }

    fn tuning(&self) -> Option<DriverTuning> {
        Some(*self.ctx.tuning())
    }

    fn limits(&self) -> Option<DeviceLimits> {
        Some(*self.ctx.limits())
    }

    fn open<'t, 'a>(
        &self,
        tree: Tree<'t, 'a>,
        opts: &OpenOptions,
        _auto: bool,
    ) -> OpenResult<'t, 'a> {
        uploaded(tree, |bvh| self.upload(bvh, opts))
    }

    fn build_bvh(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
        self.ctx.build_bvh(tris, opts)
    }

    fn wgpu_context(&self) -> Option<&GpuContext> {
        Some(&self.ctx)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// The wgpu context `opts` asks for, with ray queries when `ray_queries` and the adapter
/// has them.
pub(crate) fn context(opts: &OpenOptions, ray_queries: bool) -> Result<GpuContext, TraceError> {
    let options = ContextOptions {
        tuning: opts.tuning,
        ray_queries,
        max_binding_bytes: opts.max_binding_bytes,
        ..ContextOptions::default()
    };
    GpuContext::new_with(opts.adapter.clone(), &options)
}

/// [`Backend::Wgpu`] on the adapter `opts` asks for.
pub(crate) fn open(opts: &OpenOptions) -> Result<Arc<dyn DeviceInterface>, TraceError> {
    Ok(Arc::new(WgpuDevice {
        ctx: context(opts, false)?,
    }))
}

impl Device {
    /// A wgpu device the caller opened (an application's, eframe's), tracing with our
    /// walks.
    pub fn wgpu(ctx: GpuContext) -> Device {
        Device::from_interface(Arc::new(WgpuDevice { ctx }))
    }
}
