//! [`Backend::Auto`]'s choice: wgpu on the best adapter, its ray queries where they run
//! on ray-tracing hardware, the CPU walks when there is no adapter.

use std::sync::Arc;

use bvhtrace_engine::TraceError;

use super::interface::OpenedDevice;
use super::wgpu::{WgpuDevice, context};
use super::{cpu, ray_query};
#[cfg(doc)]
use crate::Backend;
use crate::OpenOptions;

/// [`Backend::Auto`]: wgpu on the best adapter, with its ray queries where they run on
/// ray-tracing hardware (any adapter but a CPU driver, where our walks are several times
/// faster), saying why when the device offers them; the CPU walks when there is no
/// adapter at all, saying so.
pub(crate) fn open(opts: &OpenOptions) -> Result<OpenedDevice, TraceError> {
    let ctx = match context(opts, true) {
        Ok(ctx) => ctx,
        Err(e @ TraceError::NoAdapter { .. }) => {
            return Ok(OpenedDevice {
                fallback: Some(format!(
                    "there is no Vulkan adapter ({e}); tracing on the CPU"
                )),
                ..OpenedDevice::plain(cpu::device())
            });
        }
        Err(e) => return Err(e),
    };
    if !ctx.has_ray_queries() {
        return Ok(OpenedDevice::plain(Arc::new(WgpuDevice { ctx })));
    }
    let name = ctx.adapter_info().name.clone();
    if ctx.adapter_info().device_type == bvhtrace_gpu::wgpu::DeviceType::Cpu {
        let why = format!(
            "{name} offers ray queries, but it is a CPU driver, where they run in software and \
             our walks trace several times faster; tracing with our walks"
        );
        return Ok(OpenedDevice {
            choice: Some(why),
            ..OpenedDevice::plain(Arc::new(WgpuDevice { ctx }))
        });
    }
    Ok(OpenedDevice {
        choice: Some(format!(
            "{name} has ray queries in hardware; tracing with them"
        )),
        ..OpenedDevice::plain(ray_query::on(ctx)?)
    })
}
