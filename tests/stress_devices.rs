//! The stress suite (`crates/stress/tests/suite/mod.rs`) on the devices of the
//! conformance suite's factory (`common::BACKENDS`): each on every case, but ash only on
//! the `instances-*` cases (its one-mesh kernels are wgpu's, checked by the conformance
//! suite), each compared with the CPU twins bit for bit, on tracers from the front door's
//! factories (`bvhtrace::Device::tracer_factory`), rows named after each backend. Without a
//! Vulkan adapter those rows are skipped, saying why.

#[path = "../crates/stress/tests/suite/mod.rs"]
mod suite;

mod common;

use std::sync::Arc;

use bvhtrace::{ADAPTER_ENV, AdapterChoice, Backend, Device, DriverTuning, OpenOptions};
use bvhtrace_stress::{Backends, DeviceTracers, wgpu_trees};

/// The devices of the factory that run only the two-level cases.
const TWO_LEVELS_ONLY: [Backend; 1] = [Backend::Vulkan];

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
        backend: device.backend().name().to_string(),
        name: device.name(),
        tuning: device.tuning().unwrap_or(DriverTuning::GPU),
        bit_for_bit: device.backend().bit_for_bit(),
        open: Arc::new(device.tracer_factory()),
        open_motion: device.wgpu_context().cloned().map(wgpu_trees::motion_on),
        open_curves: device.wgpu_context().cloned().map(wgpu_trees::curves_on),
    })
}

/// The CPU twins and `devices`, each that opens (one that does not is skipped, saying why).
fn with_devices(devices: &[Backend]) -> Backends {
    let mut b = Backends::new(true);
    for &d in devices {
        match device(d) {
            Ok(t) => b = b.with(t),
            Err(e) => println!("SKIP the {d} rows: {e}"),
        }
    }
    b
}

/// The CPU twins and the devices of every case.
fn backends() -> Backends {
    let every: Vec<Backend> = (common::BACKENDS.into_iter())
        .filter(|b| !TWO_LEVELS_ONLY.contains(b))
        .collect();
    with_devices(&every)
}

/// The CPU twins and every device of the factory.
fn two_level_backends() -> Backends {
    with_devices(&common::BACKENDS)
}
