//! `bvhtrace-viewer [SCENE]`: see `bvhtrace_viewer::cli::Args` (or `--help`).

use std::process::ExitCode;

use bvhtrace_viewer::app::{Shared, ViewerApp};
use bvhtrace_viewer::cli::Args;
use clap::Parser;
use eframe::egui;

/// Gives the process a private `XDG_RUNTIME_DIR` (`$TMPDIR/bvhtrace-runtime-UID`, mode
/// 0700, ours) when it has none, so that Mesa's Vulkan drivers print no error for it.
fn private_runtime_dir() {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    if std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|v| !v.is_empty()) {
        return;
    }
    let Ok(uid) = std::fs::metadata("/proc/self").map(|m| m.uid()) else {
        return;
    };
    let dir = std::env::temp_dir().join(format!("bvhtrace-runtime-{uid}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    if std::fs::symlink_metadata(&dir)
        .is_ok_and(|m| m.is_dir() && m.uid() == uid && m.permissions().mode() & 0o077 == 0)
    {
        // SAFETY: first thing in `main`, before any other thread exists.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", dir) };
    }
}

fn main() -> ExitCode {
    private_runtime_dir();
    let args = Args::parse();
    if let Some(path) = &args.screenshot
        && let Err(e) = bvhtrace_viewer::png::check_writable(path)
    {
        eprintln!("error: {e}");
        return ExitCode::FAILURE;
    }
    let shared = Shared::default();
    let (w, h) = args.size;
    let options = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default()
            .with_title("bvhtrace viewer")
            .with_inner_size([w as f32, h as f32])
            .with_drag_and_drop(true),
        renderer: eframe::Renderer::Wgpu,
        wgpu_options: bvhtrace_viewer::setup::wgpu_configuration(args.adapter.clone()),
        ..Default::default()
    };
    let app_args = args.clone();
    let app_shared = shared.clone();
    let run = eframe::run_native(
        "bvhtrace viewer",
        options,
        Box::new(move |cc| Ok(Box::new(ViewerApp::new(cc, &app_args, app_shared)))),
    );
    if let Err(e) = run {
        eprintln!(
            "error: could not open the viewer window: {e}\n\
             (it needs a display, e.g. `xvfb-run -a bvhtrace-viewer ...` on a headless \
             machine, and a Vulkan driver: `apt-get install mesa-vulkan-drivers` gives the \
             CPU driver lavapipe)"
        );
        return ExitCode::FAILURE;
    }
    if args.screenshot.is_none() {
        return ExitCode::SUCCESS;
    }
    let result = shared.outcome.lock().ok().and_then(|mut o| o.take());
    match result {
        Some(Ok(msg)) => {
            eprintln!("{msg}");
            ExitCode::SUCCESS
        }
        Some(Err(msg)) => {
            eprintln!("error: {msg}");
            ExitCode::FAILURE
        }
        None => {
            eprintln!("error: the window closed before the screenshot was taken");
            ExitCode::FAILURE
        }
    }
}
