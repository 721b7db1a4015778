//! `bvhtrace-viewer [SCENE]`: see `bvhtrace_viewer::cli::Args` (or `--help`).

use std::process::ExitCode;
use std::sync::{Arc, Mutex};

use bvhtrace_viewer::app::{Outcome, ViewerApp};
use bvhtrace_viewer::cli::Args;
use clap::Parser;
use eframe::egui;

fn main() -> ExitCode {
    let args = Args::parse();
    if let Some(path) = &args.screenshot
        && let Err(e) = bvhtrace_viewer::png::check_writable(path)
    {
        eprintln!("error: {e}");
        return ExitCode::FAILURE;
    }
    let outcome: Outcome = Arc::new(Mutex::new(None));
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
    let app_outcome = outcome.clone();
    let run = eframe::run_native(
        "bvhtrace viewer",
        options,
        Box::new(move |cc| Ok(Box::new(ViewerApp::new(cc, &app_args, app_outcome)))),
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
    let result = outcome.lock().ok().and_then(|mut o| o.take());
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
