//! Opening the backend a command traces on, through the front door (`bvhtrace::open`),
//! with what the library does not read: the environment.

use std::path::PathBuf;

use anyhow::Result;
use bvhtrace::{ADAPTER_ENV, AdapterChoice, FlatBvh, OpenOptions, Opened, Traversal};

pub use bvhtrace::{Backend, Device};

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
