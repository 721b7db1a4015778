//! The stress suite (`crates/stress/tests/suite/mod.rs`) on the devices: our walks through
//! wgpu on every case and through ash on the `instances-*` cases, each compared with the
//! CPU twins bit for bit, on tracers from the front door's factories
//! (`bvhtrace::Device::tracer_factory`), rows named after each backend. Without a Vulkan
//! adapter those rows are skipped, saying why.

#[path = "../crates/stress/tests/suite/mod.rs"]
mod suite;

use std::sync::Arc;

use bvhtrace::{ADAPTER_ENV, AdapterChoice, Backend, Device, DriverTuning, OpenOptions};
use bvhtrace_stress::{Backends, DeviceTracers};

/// The devices every case runs on.
const EVERY_CASE: [Backend; 1] = [Backend::Wgpu];

/// The devices the two-level cases run on as well.
const TWO_LEVELS: [Backend; 1] = [Backend::Vulkan];

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
    with_devices(&EVERY_CASE)
}

/// `backends` and the devices of the two-level cases.
fn two_level_backends() -> Backends {
    with_devices(&[EVERY_CASE.as_slice(), TWO_LEVELS.as_slice()].concat())
}
