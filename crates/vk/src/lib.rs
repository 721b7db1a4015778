//! bvhtrace's traversal kernels on raw Vulkan through [`ash`], for engines written on ash
//! rather than wgpu, and to measure what wgpu's layer costs. This crate does not depend on
//! wgpu: what it shares with the wgpu backend (`bvhtrace-gpu`) comes from the
//! backend-neutral [`bvhtrace_engine`] (re-exported as [`engine`]).
//!
//! The WGSL is the wgpu path's: each [`KernelKey`](engine::KernelKey)'s module
//! ([`KernelKey::source`](engine::KernelKey::source), with the BVH in storage buffers);
//! naga resolves its override constants (and the same [`DriverTuning`] constants,
//! `TRIP_LIMIT` and `DISPATCH_THREADS`, as the wgpu path) and writes SPIR-V for one entry
//! point. The BVH is uploaded in the flat layout of [`bvhtrace_core::flat`], byte for byte,
//! and the answers equal the wgpu path's and the CPU twin's ([`bvhtrace_core::trace_rays`])
//! bit for bit.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use bvhtrace_vk::core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal};
//! use bvhtrace_vk::{AdapterChoice, Tracer, UploadOptions, VkBvh, VkContext};
//! use glam::Vec3;
//!
//! let tris = vec![[Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)]];
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let ctx = VkContext::new(AdapterChoice::Auto)?; // the best device
//! let gpu = VkBvh::upload(&ctx, &bvh, &UploadOptions::fitting(&bvh))?; // every walk it can take
//! let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
//! let out = gpu.trace(&rays, &TraceOptions::closest(Traversal::Stackless))?;
//! println!("{:?}: {:?} ms on the device, {} ms wall", out.hits[0], out.gpu_ms, out.wall_ms);
//! // The same through the interface every backend implements.
//! let tracer: &dyn Tracer = &gpu;
//! let opts = TraceOptions::closest(tracer.default_traversal()).with_counters(true);
//! let again = tracer.trace(&rays, &opts)?;
//! assert_eq!(again.hits, out.hits);
//! println!("{} on {}", tracer.backend(), tracer.device_name());
//! # Ok(()) }
//! ```
//!
//! * [`VkContext`]: instance (with `VK_LAYER_KHRONOS_validation` when asked for and
//!   installed), the device [`AdapterChoice`] picks, its [`DriverTuning`], SPIR-V
//!   translation, the pipeline cache keyed by [`KernelKey`](engine::KernelKey), the
//!   command buffer and timestamp queries.
//! * [`VkBvh::upload`] / [`Tracer::trace`]: the flat BVH in, hits (and counters) out as a
//!   [`TraceOutput`], for the [`TraceOptions`] asked for. [`VkBvh`] implements
//!   [`Tracer`], the interface shared with the CPU and wgpu backends.
//!
//! * [`VkContext::build_bvh`]: the device BVH builders ([`GpuBuilderKind`]), the host side
//!   and WGSL the wgpu backend runs, so the same tree on the same device.
//!
//! Every Vulkan object is destroyed when its owner drops; every failure is a
//! [`TraceError`], the error type of every backend (a Vulkan result becomes
//! [`TraceError::OutOfMemory`], [`TraceError::DeviceLost`] or [`TraceError::Device`]; no
//! loader or device [`TraceError::NoAdapter`]).
#![warn(missing_docs)]

mod build;
mod bvh;
mod context;
mod error;

pub use ash;
pub use bvh::{Ash, VkBvh};
pub use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes, GpuBuilderKind};
pub use context::{
    VALIDATION_ENV, VkContext, VkDeviceInfo, VkOptions, device_kind, process_validation_errors,
};

/// Re-exported so users need not depend on the same versions by hand.
pub use bvhtrace_core as core;
pub use bvhtrace_engine as engine;
pub use bvhtrace_engine::{
    AdapterChoice, DeviceKind, DriverTuning, TraceError, Tracer, UploadOptions, UploadStats,
};

/// The context and uploaded BVHs can be shared between threads (submissions are
/// serialised by the context).
const _: () = {
    const fn send_sync<T: Send + Sync>() {}
    send_sync::<VkContext>();
    send_sync::<VkBvh>();
};
