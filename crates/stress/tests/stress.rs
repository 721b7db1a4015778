//! The stress suite (`suite/mod.rs`) on the CPU twins. This crate opens no backend: the
//! same suite runs on the GPU kernels in the workspace's `tests/stress_devices.rs`, which
//! takes its tracers from the front door.

mod suite;

use bvhtrace_stress::Backends;

/// The CPU twins, reported.
fn backends() -> Backends {
    Backends::cpu_only()
}

/// No device here.
fn two_level_backends() -> Backends {
    Backends::cpu_only()
}
