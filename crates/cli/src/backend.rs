//! Opening the backend a command traces on, through the front door (`bvhtrace::open`),
//! with what the library does not read: the environment.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Result;
use bvhtrace::{
    ADAPTER_ENV, AdapterChoice, Device, DriverTuning, FlatBvh, OpenOptions, Opened, Traversal,
};
use bvhtrace_stress::{DeviceTracers, StressDevice};

pub use bvhtrace::Backend;

/// The adapter a command opens: the `--adapter` flag, else a non-empty
/// `$BVHTRACE_ADAPTER`, else the best.
pub fn adapter_choice(flag: Option<&str>) -> AdapterChoice {
    let from_env = || {
        std::env::var(ADAPTER_ENV)
            .ok()
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
    };
    match flag.map(str::to_string).or_else(from_env) {
        Some(name) => AdapterChoice::Named(name),
        None => AdapterChoice::Auto,
    }
}

/// The front door's options: `backend` on `adapter` (with the environment), for
/// `traversals` (empty: the backend's default, settled before the upload).
pub fn options(backend: Backend, adapter: Option<&str>, traversals: &[Traversal]) -> OpenOptions {
    OpenOptions {
        backend,
        adapter: adapter_choice(adapter),
        traversals: traversals.to_vec(),
        validation: std::env::var(bvhtrace::VALIDATION_ENV).is_ok_and(|v| v == "1"),
        ..OpenOptions::default()
    }
}

/// Opens `opts`'s backend once, for many trees; a fallback is said on stderr.
pub fn device(opts: &OpenOptions) -> Result<Device> {
    let device = Device::new(opts)?;
    for why in device.fallback().into_iter().chain(device.choice()) {
        eprintln!("note: {why}");
    }
    Ok(device)
}

/// Opens a tracer for `bvh` on `device`; a fallback is said on stderr.
pub fn open_on<'a>(device: &Device, bvh: &'a FlatBvh, opts: &OpenOptions) -> Result<Opened<'a>> {
    let opened = device.open(bvh, opts)?;
    if let Some(why) = opened
        .fallback
        .as_deref()
        .filter(|w| Some(*w) != device.fallback())
    {
        eprintln!("note: {why}");
    }
    Ok(opened)
}

/// Opens `backend` on the adapter named `adapter` (else `$BVHTRACE_ADAPTER`, else the
/// best) and uploads `bvh` for `traversals`, with every candidate hit passed through
/// `filter` when there is one (a scene's masked materials: the CPU walks apply it, `auto`
/// goes to the CPU for it, a device backend refuses it); a fallback is said on stderr.
pub fn open<'a>(
    backend: Backend,
    adapter: Option<&str>,
    bvh: &'a FlatBvh,
    traversals: &[Traversal],
    filter: Option<bvhtrace::SharedFilter>,
) -> Result<Opened<'a>> {
    let opts = OpenOptions {
        filter,
        ..options(backend, adapter, traversals)
    };
    let opened = bvhtrace::open(bvh, &opts)?;
    for why in opened.fallback.iter().chain(&opened.choice) {
        eprintln!("note: {why}");
    }
    Ok(opened)
}

/// A device backend for `bvhtrace stress`, opened through the front door (with the
/// environment): its adapter's name, its measures, and a factory of tracers on it.
pub fn stress_device(which: StressDevice) -> std::result::Result<DeviceTracers, String> {
    let backend = match which {
        StressDevice::Gpu => Backend::Wgpu,
        StressDevice::Vk => Backend::Vulkan,
        StressDevice::RayQuery => Backend::RayQuery,
    };
    let device = Device::new(&options(backend, None, &[])).map_err(|e| e.to_string())?;
    let name = match (device.wgpu_context(), device.vulkan_context()) {
        (Some(c), _) => c.adapter_info().name.clone(),
        (_, Some(c)) => c.device_info().name.clone(),
        _ => device.name(),
    };
    Ok(DeviceTracers {
        name,
        tuning: device.tuning().unwrap_or(DriverTuning::GPU),
        open: Arc::new(device.tracer_factory()),
    })
}

/// Gives the process a private `XDG_RUNTIME_DIR` (under the temp dir, mode 0700) when it
/// has none, so that Mesa's Vulkan drivers do not print an error for it on a headless
/// machine. Called first thing in `main`, before any thread or Vulkan call.
pub fn private_runtime_dir() {
    if std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|v| !v.is_empty()) {
        return;
    }
    if let Some(dir) = make_private_dir() {
        // SAFETY: called at the start of `main`, before any other thread exists, so no
        // other thread reads the environment while it changes.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", dir) };
    }
}

/// `$TMPDIR/bvhtrace-runtime-UID`, created with mode 0700 and owned by this user; `None`
/// when it cannot be (another user's directory of that name, a read-only temp dir).
#[cfg(unix)]
fn make_private_dir() -> Option<PathBuf> {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    // This process's own uid, without libc: the owner of its /proc entry.
    let uid = std::fs::metadata("/proc/self").ok()?.uid();
    let dir = std::env::temp_dir().join(format!("bvhtrace-runtime-{uid}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    let meta = std::fs::symlink_metadata(&dir).ok()?;
    (meta.is_dir() && meta.uid() == uid && meta.permissions().mode() & 0o077 == 0).then_some(dir)
}

#[cfg(not(unix))]
fn make_private_dir() -> Option<PathBuf> {
    None
}
