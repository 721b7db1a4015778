//! The stress suite (`crates/stress/tests/suite/mod.rs`) on the GPU kernels: through wgpu
//! (rows `gpu`) on every case and through ash (rows `vk`) on the `instances-*` cases, each
//! compared with the CPU twins bit for bit, on tracers from the front door's factories
//! (`bvhtrace::Device::tracer_factory`). Without a Vulkan adapter the GPU rows are
//! skipped, saying why.

#[path = "../crates/stress/tests/suite/mod.rs"]
mod suite;

use std::sync::Arc;

use bvhtrace::{ADAPTER_ENV, AdapterChoice, Backend, Device, DriverTuning, OpenOptions};
use bvhtrace_stress::{Backends, DeviceTracers};

/// `backend` on `$BVHTRACE_ADAPTER` (else the best adapter), as a tracer factory.
fn device(backend: Backend) -> Result<DeviceTracers, String> {
    let adapter = std::env::var(ADAPTER_ENV)
        .ok()
        .filter(|s| !s.trim().is_empty())
        .map_or(AdapterChoice::Auto, |s| {
            AdapterChoice::Named(s.trim().into())
        });
    let device =
        Device::new(&OpenOptions::new(backend).with_adapter(adapter)).map_err(|e| e.to_string())?;
    Ok(DeviceTracers {
        name: device.name(),
        tuning: device.tuning().unwrap_or(DriverTuning::GPU),
        open: Arc::new(device.tracer_factory()),
    })
}

/// The CPU twins and wgpu.
fn backends() -> Backends {
    Backends::new(true).with_gpu(device(Backend::Wgpu))
}

/// `backends` and ash.
fn with_vk(backends: Backends) -> Backends {
    backends.with_vulkan(device(Backend::Vulkan))
}
