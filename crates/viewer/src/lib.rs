//! bvhtrace-viewer: an interactive egui window over the bvhtrace GPU traversal.
//!
//! The window is drawn by eframe's wgpu renderer, and the rays are traced on **the same
//! wgpu device**: [`app::ViewerApp::new`] takes eframe's `wgpu_render_state` and wraps its
//! device and queue with [`bvhtrace_gpu::GpuContext::from_device`]. The traced image is
//! written into a wgpu texture on that device and registered with egui's renderer.
//!
//! * [`camera`]: orbit, pan, zoom and fly moves, and `bvhtrace render` flags.
//! * [`shade`]: hits to pixels (the CLI's shading modes) and progressive accumulation.
//! * [`jobs`]: scene loading, BVH building and upload off the UI thread (in a browser,
//!   between frames); batches traced on the GPU that may finish on a later frame (in a
//!   browser); the resulting
//!   [`jobs::BuiltBvh`] holds the upload ([`bvhtrace_gpu::GpuBvh`]) and the CPU twin
//!   ([`bvhtrace_gpu::CpuTracer`]), falls back from the first to the second, and moves an
//!   animated scene to a new time ([`jobs::BuiltBvh::pose`]: two levels rebuild only their
//!   top level, updated on the device in place).
//! * [`app`]: the eframe application; [`cli`]: the command line; [`setup`]: eframe's wgpu
//!   configuration (the adapter choice, and the features and limits
//!   [`bvhtrace_gpu::GpuContext`] asks for).
#![warn(missing_docs)]

pub mod app;
pub mod camera;
pub mod cli;
pub mod display;
pub mod jobs;
pub mod path_mode;
pub mod png;
pub mod setup;
pub mod shade;
