//! bvhtrace's traversal kernels on raw Vulkan through [`ash`], for engines written on ash
//! rather than wgpu, and to measure what wgpu's layer costs.
//!
//! The WGSL is the wgpu path's: each [`KernelVariant`]'s module (`KernelVariant::source`,
//! composed by `bvhtrace_gpu` with the BVH in storage buffers); naga resolves its override
//! constants (and the same `TRIP_LIMIT` as the wgpu path) and writes SPIR-V for one entry
//! point. The BVH is uploaded in the flat layout of
//! [`bvhtrace_core::flat`], byte for byte, and the answers equal the wgpu path's and the
//! CPU twin's bit for bit.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use bvhtrace_core::{BuildOptions, FlatBvh, Query, Ray, Traversal};
//! use bvhtrace_vk::{VkBvh, VkContext};
//! use glam::Vec3;
//!
//! let tris = vec![[Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)]];
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let ctx = VkContext::new(None)?; // BVHTRACE_ADAPTER, else the best device
//! let gpu = VkBvh::upload(&ctx, &bvh)?;
//! let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
//! let out = gpu.trace(&rays, Traversal::Stackless, Query::Closest, false)?;
//! println!("{:?}: {:?} ms on the device, {} ms wall", out.hits[0], out.gpu_ms, out.wall_ms);
//! # Ok(()) }
//! ```
//!
//! * [`VkContext`]: instance (with `VK_LAYER_KHRONOS_validation` when asked for and
//!   installed), device, SPIR-V translation, pipelines, the command buffer and timestamp
//!   queries.
//! * [`VkBvh::upload`] / [`VkBvh::trace`]: the flat BVH in, hits (and counters) out.
//!
//! Every Vulkan object is destroyed when its owner drops; every failure is a [`VkError`].
#![warn(missing_docs)]

mod bvh;
mod context;
mod error;

pub use ash;
pub use bvh::VkBvh;
/// What [`VkBvh::trace`] returns: the wgpu path's type, so both backends report alike.
pub use bvhtrace_gpu::TraceOutput;
/// What an upload cost: the wgpu path's type, the same arrays and bytes.
pub use bvhtrace_gpu::UploadStats;
pub use bvhtrace_gpu::shaders::KernelVariant;
pub use context::{VALIDATION_ENV, VkContext, VkDeviceInfo, VkOptions, process_validation_errors};
pub use error::VkError;

/// The context and uploaded BVHs can be shared between threads (submissions are
/// serialised by the context).
const _: () = {
    const fn send_sync<T: Send + Sync>() {}
    send_sync::<VkContext>();
    send_sync::<VkBvh>();
};
