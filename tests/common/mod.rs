//! The conformance suite's tracer factory: every device backend of our walks, opened
//! through the front door once per test, so each parity test runs on each tracer, beside
//! the CPU twin. A new backend is one more line in [`BACKENDS`] (the stress suite on the
//! devices, `tests/stress_devices.rs`, takes the same list).
#![allow(dead_code)]

use bvhtrace::engine::walks::check_depth;
use bvhtrace::{
    AdapterChoice, Backend, BvhStorage, Device, DriverTuning, OpenOptions, TraceError, Tracer,
};
use bvhtrace_core::{FlatBvh, Traversal};
use bvhtrace_gpu::GpuContext;
use bvhtrace_vk::VkContext;

/// The device backends of our walks the suite checks against the CPU twin, bit for bit.
pub const BACKENDS: [Backend; 3] = [Backend::Wgpu, Backend::Vulkan, Backend::Mock];

/// The devices the tracers run on; a backend without a device is left out (SKIP printed),
/// so the suite still checks the others.
pub struct Devices {
    /// Each of [`BACKENDS`] that opened, in its order, with the tuning asked for and the
    /// Vulkan validation layer on (when installed): every test checks that it reported no
    /// error ([`Devices::check_validation`]).
    pub devices: Vec<Device>,
}

impl Devices {
    /// Every backend on its own choice of device, with the device's tuning: opened once
    /// per test binary and shared by its tests, so that each kernel is compiled once.
    pub fn open(test: &str) -> &'static Devices {
        static SHARED: std::sync::OnceLock<Devices> = std::sync::OnceLock::new();
        SHARED.get_or_init(|| Devices::with_tuning(test, None))
    }

    /// [`Devices::open`] with every backend on `tuning` (`None`: the device's own; a
    /// storage the device lacks gives way to the other).
    pub fn with_tuning(test: &str, tuning: Option<DriverTuning>) -> Devices {
        let devices = BACKENDS
            .iter()
            .filter_map(|&b| skip_without_device(test, b, open(b, tuning)))
            .collect();
        Devices { devices }
    }

    /// These devices again, each with its tuning changed by `f`.
    pub fn retuned(&self, f: impl Fn(DriverTuning) -> DriverTuning) -> Devices {
        let devices = self
            .devices
            .iter()
            .map(|d| {
                let tuning = d.tuning().map(&f);
                open(d.backend(), tuning).expect("the device opens again, retuned")
            })
            .collect();
        Devices { devices }
    }

    /// True when some device opened.
    pub fn any(&self) -> bool {
        !self.devices.is_empty()
    }

    /// The wgpu context, when wgpu opened.
    pub fn wgpu(&self) -> Option<&GpuContext> {
        self.devices.iter().find_map(Device::wgpu_context)
    }

    /// The Vulkan context, when ash opened.
    pub fn vk(&self) -> Option<&VkContext> {
        self.devices.iter().find_map(Device::vulkan_context)
    }

    /// ash's validation layer reported no error (on shared devices: in any test so far).
    pub fn check_validation(&self) {
        if let Some(vk) = self.vk() {
            assert_eq!(vk.validation_errors(), 0, "Vulkan validation errors");
        }
    }
}

/// `backend` on the best adapter with `tuning`, the validation layer on.
fn open(backend: Backend, tuning: Option<DriverTuning>) -> Result<Device, TraceError> {
    Device::new(&OpenOptions {
        adapter: AdapterChoice::Auto,
        validation: true,
        tuning,
        ..OpenOptions::new(backend)
    })
}

/// The device, or `None` after SKIP when the machine has no such device.
fn skip_without_device(
    test: &str,
    backend: Backend,
    device: Result<Device, TraceError>,
) -> Option<Device> {
    match device {
        Ok(d) => Some(d),
        Err(e @ TraceError::NoAdapter { .. }) => {
            eprintln!("SKIP {test} on {backend}: {e}");
            None
        }
        Err(e) => panic!("{test}: cannot open {backend}: {e}"),
    }
}

/// Every tracer over `bvh`: the CPU twin first; then each device in each storage it
/// offers (every walk the tree allows uploaded, the wide layout too). A tracer whose
/// upload refuses `bvh` is an error here.
pub fn tracers<'a>(devices: &Devices, bvh: &'a FlatBvh) -> Vec<Box<dyn Tracer + 'a>> {
    let mut out: Vec<Box<dyn Tracer + 'a>> = vec![Box::new(bvhtrace::CpuTracer::new(bvh))];
    let walks: Vec<Traversal> = (Traversal::ALL.into_iter())
        .filter(|&t| check_depth(t, bvh.depth()).is_ok())
        .collect();
    for device in &devices.devices {
        for storage in BvhStorage::ALL {
            let opts = OpenOptions {
                traversals: walks.clone(),
                storage: Some(storage),
                ..OpenOptions::default()
            };
            let opened = device.open_owned(bvh, &opts).expect("upload");
            if opened.storage != Some(storage) {
                eprintln!(
                    "SKIP {} in {storage:?}: {:?}",
                    device.backend(),
                    opened.fallback
                );
                continue;
            }
            let stats = opened.tracer.upload_stats().expect("an upload");
            assert_eq!(
                stats.storage, storage,
                "the layouts in the storage asked for"
            );
            out.push(opened.tracer);
        }
    }
    out
}

/// A tracer's name in failures: its backend, and where a device keeps the tree.
pub fn name(t: &dyn Tracer) -> String {
    match t.upload_stats() {
        Some(s) => format!("{} ({:?})", t.backend(), s.storage),
        None => t.backend().to_string(),
    }
}
