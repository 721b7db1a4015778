//! The test backend: the engine over a device of bytes whose kernels are the CPU twins
//! (`bvhtrace-mock`), with limits a test sets. Not fast and not for tracing: for testing a
//! front end, and the engine's path through the front door, without a GPU.

use std::any::Any;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_engine::DriverTuning;
use bvhtrace_engine::TraceError;
use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes};
use bvhtrace_engine::engine::DeviceApi;
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_mock::{MockBvh, MockDevice};

use super::interface::{DeviceInterface, OpenResult, Tree, no_device_builder, uploaded};
use crate::open::{EngineDevice, open_engine};
use crate::{Backend, Device, OpenOptions};

/// The mock device.
struct Mock {
    device: MockDevice,
}

/// [`Backend::Mock`] with WebGPU's default limits (the binding size capped as asked) and
/// the tuning asked for (there is one
/// mock: the adapter asked for is not read).
pub(crate) fn open(opts: &OpenOptions) -> Result<Arc<dyn DeviceInterface>, TraceError> {
    let mut device = MockDevice::new();
    if let Some(most) = opts.max_binding_bytes {
        let mut limits = *device.limits();
        limits.max_storage_buffer_binding_size = limits.max_storage_buffer_binding_size.min(most);
        device = device.with_limits(limits);
    }
    Ok(Arc::new(Mock {
        device: match opts.tuning {
            Some(t) => device.with_tuning(t),
            None => device,
        },
    }))
}

impl DeviceInterface for Mock {
    fn backend(&self) -> Backend {
        Backend::Mock
    }

    fn name(&self) -> String {
        self.device.name()
    }

    fn tuning(&self) -> Option<DriverTuning> {
        Some(*DeviceApi::tuning(&self.device))
    }

    fn limits(&self) -> Option<DeviceLimits> {
        Some(*DeviceApi::limits(&self.device))
    }

    fn open<'t, 'a>(
        &self,
        tree: Tree<'t, 'a>,
        opts: &OpenOptions,
        _auto: bool,
    ) -> OpenResult<'t, 'a> {
        let device = EngineDevice {
            backend: Backend::Mock,
            name: &self.device.name(),
            features: self.device.features(),
            tuning: *DeviceApi::tuning(&self.device),
        };
        uploaded(tree, |bvh| {
            open_engine(&device, opts, |u| MockBvh::upload(&self.device, bvh, u))
        })
    }

    fn build_bvh(
        &self,
        _: &[Triangle],
        _: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
        Err(no_device_builder(Backend::Mock))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl Device {
    /// The test backend on `device` (its limits and features the test's).
    pub fn mock(device: MockDevice) -> Device {
        Device::from_interface(Arc::new(Mock { device }))
    }
}
