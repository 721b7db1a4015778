//! The ray-query backend: the device's own acceleration structures walked by its ray
//! queries, through wgpu (`bvhtrace_gpu::RayQueryBvh`). Not in a browser: WebGPU has no
//! ray queries.

use std::any::Any;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, Traversal, Triangle};
use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::{DriverTuning, TraceError, Tracer};
use bvhtrace_gpu::{GpuContext, RayQueryBvh};

use super::interface::{DeviceInterface, OpenResult, TimedOpen, Tree, uploaded};
use super::wgpu::{WgpuDevice, adapter_name, context};
use crate::open::exceeds_a_limit;
use crate::{Backend, Device, OpenOptions, Opened, TimedScene};

/// A wgpu device with ray queries, tracing with them; our walks on the same device when
/// [`Backend::Auto`]'s tree exceeds a limit of the ray-query upload.
struct RayQueryDevice {
    walks: WgpuDevice,
}

/// The device's ray queries on `ctx`, an error naming the feature when it has none.
pub(crate) fn on(ctx: GpuContext) -> Result<Arc<dyn DeviceInterface>, TraceError> {
    if !ctx.has_ray_queries() {
        return Err(TraceError::MissingFeature {
            feature: "EXPERIMENTAL_RAY_QUERY",
            needed_for: "the ray-query backend (Mesa 25's lavapipe has it; see the README)",
            adapter: ctx.adapter_info().name.clone(),
        });
    }
    Ok(Arc::new(RayQueryDevice {
        walks: WgpuDevice { ctx },
    }))
}

/// [`Backend::RayQuery`] on the adapter `opts` asks for.
pub(crate) fn open(opts: &OpenOptions) -> Result<Arc<dyn DeviceInterface>, TraceError> {
    on(context(opts, true)?)
}

impl RayQueryDevice {
    /// The tree in the device's acceleration structures; only `opts.traversals` is read,
    /// for [`Opened::traversal`] (the driver walks whatever it is asked).
    fn upload(&self, bvh: &FlatBvh, opts: &OpenOptions) -> Result<Opened<'static>, TraceError> {
        let rq = RayQueryBvh::upload(&self.walks.ctx, bvh)?;
        Ok(Opened {
            device: rq.device_name(),
            tracer: Box::new(rq),
            backend: Backend::RayQuery,
            storage: None,
            traversal: (opts.traversals.first().copied()).unwrap_or(Traversal::GPU_DEFAULT),
            fallback: None,
            choice: None,
        })
    }
}

impl DeviceInterface for RayQueryDevice {
    fn backend(&self) -> Backend {
        Backend::RayQuery
    }

    fn name(&self) -> String {
        adapter_name(&self.walks.ctx)
    }

    fn tuning(&self) -> Option<DriverTuning> {
        Some(*self.walks.ctx.tuning())
    }

    fn limits(&self) -> Option<DeviceLimits> {
        Some(*self.walks.ctx.limits())
    }

    fn open<'t, 'a>(
        &self,
        tree: Tree<'t, 'a>,
        opts: &OpenOptions,
        auto: bool,
    ) -> OpenResult<'t, 'a> {
        uploaded(tree, |bvh| match self.upload(bvh, opts) {
            Err(e) if auto && exceeds_a_limit(&e) => {
                let mut o = self.walks.upload(bvh, opts)?;
                o.fallback = Some(format!(
                    "the scene does not fit the ray-query upload ({e}); tracing with our walks"
                ));
                Ok(o)
            }
            other => other,
        })
    }

    fn open_timed(&self, scene: &TimedScene) -> Result<TimedOpen, TraceError> {
        let note = format!(
            "wgpu's ray queries have no motion blur or curves: {} traces with our walks on \
             the device",
            scene.name()
        );
        Ok((crate::timed::on_wgpu(&self.walks.ctx, scene)?, Some(note)))
    }

    fn build_bvh(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
        self.walks.ctx.build_bvh(tris, opts)
    }

    fn wgpu_context(&self) -> Option<&GpuContext> {
        Some(&self.walks.ctx)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl Device {
    /// A wgpu device the caller opened with ray queries
    /// ([`GpuContext::has_ray_queries`]), tracing with them (not in a browser).
    pub fn ray_query(ctx: GpuContext) -> Result<Device, TraceError> {
        Ok(Device::from_interface(on(ctx)?))
    }
}
