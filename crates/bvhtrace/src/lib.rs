//! bvhtrace's front door: open the best tracer for a BVH, or the one named, with a
//! storage, layout and walk that fit the device; build trees on that device too.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use bvhtrace::core::{BuildOptions, FlatBvh, Ray};
//! use bvhtrace::glam::Vec3;
//! use bvhtrace::{Backend, OpenOptions, TraceOptions};
//!
//! let tris = vec![[Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)]];
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let opened = bvhtrace::open(&bvh, &OpenOptions::new(Backend::Auto))?;
//! if let Some(why) = &opened.fallback {
//!     eprintln!("note: {why}");
//! }
//! let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
//! let out = opened.tracer.trace(&rays, &TraceOptions::closest(opened.traversal))?;
//! println!("{}: {:?}", opened.summary(), out.hits[0]);
//! # Ok(()) }
//! ```
//!
//! * [`Backend`]: every way to trace, by name (`auto`, `cpu`, `wgpu` or `gpu`, `vulkan`,
//!   `ray-query`).
//! * [`open`]: the tracer [`OpenOptions`] asks for, as an [`Opened`] that says what was
//!   chosen (backend, device, storage, walk) and any fallback, as a sentence.
//! * [`Device`]: a backend opened once, to open tracers on for many trees and to build
//!   trees on ([`Device::build_bvh`]); [`Device::wgpu`] and [`Device::vulkan`] take a
//!   device the caller owns.
//! * [`Tracer`]: what every opened tracer is; [`Tracer::traversals`] for the walks it
//!   answers, [`Tracer::update`] after the scene moved, [`Tracer::kernels_used`] and
//!   [`Tracer::upload_stats`] for what ran and what was uploaded.
//!
//! * [`open_timed`]: a scene in time (a moving mesh, moving instances) or with curves
//!   ([`TimedScene`]), traced with a time per ray ([`TimedTracer`]) on the CPU or wgpu.
//!
//! Each backend is one module behind one object-safe trait; the library reads no
//! environment variable: a front end that honours [`ADAPTER_ENV`] or `VALIDATION_ENV`
//! passes them on in [`OpenOptions`].
#![warn(missing_docs)]

mod backend;
mod backends;
mod device;
mod open;
mod timed;

pub use backend::{Backend, Kernels, UnknownBackend};
pub use backends::cpu::FastCpuTracer;
pub use device::Device;
pub use open::{OpenOptions, Opened, SharedFilter, open};
pub use timed::{OpenedTimed, TimedScene, TimedTracer, open_timed};

pub use bvhtrace_core::{
    BuildOptions, FlatBvh, Hit, Query, Ray, TraceOptions, TraceOutput, Traversal,
};
pub use bvhtrace_cpu::{Tiles, tile_order};
pub use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes, GpuBuilderKind};
pub use bvhtrace_engine::device::ADAPTER_ENV;
pub use bvhtrace_engine::{
    AdapterChoice, BvhStorage, CpuTracer, DriverTuning, KernelKey, TraceError, Tracer, UploadStats,
};
pub use bvhtrace_gpu::GpuContext;
#[cfg(not(target_arch = "wasm32"))]
pub use bvhtrace_vk::{VALIDATION_ENV, VkContext};

/// Re-exported so users need not depend on the same versions by hand.
pub use bvhtrace_core as core;
pub use bvhtrace_engine as engine;
pub use bvhtrace_gpu as gpu;
pub use bvhtrace_gpu::glam;
#[cfg(not(target_arch = "wasm32"))]
pub use bvhtrace_vk as vk;
