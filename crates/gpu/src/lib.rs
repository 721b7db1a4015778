//! bvhtrace on the GPU: the BVH built on the CPU ([`bvhtrace_core::FlatBvh`]) traversed by
//! WGSL compute kernels through wgpu on Vulkan.
//!
//! Every kernel is the twin of a CPU traversal in [`bvhtrace_core::traverse`], operation
//! for operation, so GPU and CPU answers are compared ray by ray.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use bvhtrace_core::{FlatBvh, Query, Ray, Traversal, BuildOptions};
//! use bvhtrace_gpu::{AdapterChoice, GpuBvh, GpuContext, UploadOptions};
//! use glam::Vec3;
//!
//! let tris = vec![[Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)]];
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let ctx = GpuContext::new(AdapterChoice::Auto)?; // lavapipe in CI, the best GPU otherwise
//! let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::for_traversal(Traversal::Stackless))?;
//! let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
//! let out = gpu.trace(&rays, Traversal::Stackless, Query::Closest)?;
//! println!("{:?} in {:?} ms on the GPU, {} ms wall", out.hits[0], out.gpu_ms, out.wall_ms);
//! # Ok(()) }
//! ```
//!
//! * [`GpuContext`]: the device (headless, or shared with [`GpuContext::from_device`]),
//!   its limits, the shader module and the pipeline cache.
//! * [`GpuBvh::upload`]: nodes, triangles, and the escape links only when a traversal needs
//!   them, each checked against the device's limits, as storage buffers or textures
//!   ([`BvhStorage`]; textures are much faster on lavapipe).
//! * [`GpuBvh::trace`] / [`GpuBvh::trace_counted`] / [`GpuBvh::trace_with`]: ray slices in,
//!   [`TraceOutput`] out (hits, counters, GPU and wall milliseconds);
//!   [`GpuBvh::record`]: the same into your own encoder and buffers.
//! * [`PipelineFeatures`]: what one job needs (traversal, query, counters, per-vertex
//!   attributes), from which its WGSL module, bindings and upload are derived, leaving
//!   out everything else; the key of the pipeline cache.
//! * [`wgsl_library`]: the traversal functions for your own WGSL (see [`shaders`]).
#![warn(missing_docs)]

mod bvh;
mod context;
mod error;
pub mod features;
pub mod shaders;
mod trace;

pub use bvh::{GpuBvh, UploadOptions, UploadStats};
pub use context::{ADAPTER_ENV, AdapterChoice, GpuContext, GpuLimits, pick_adapter};
pub use error::GpuError;
pub use features::{
    BindingInfo, Composition, ENTRY_POINT_FILES, Entries, ModuleSet, PerElement, PipelineFeatures,
    VertexAttributes,
};
pub use shaders::{
    BvhStorage, CPU_DRIVER_TRIP_LIMIT, FULL_STACK_SIZE, RayInput, STACK_LANES, TEXEL_ROW,
    WORKGROUP_SIZE, kernel_source, trip_limit_for, wgsl_library,
};
pub use trace::{
    COUNTERS_BYTES, Dispatch, HIT_BYTES, MAX_RAYS_PER_DISPATCH, RAY_BYTES, RayBatch, TraceOptions,
    TraceOutput, finish_incomplete, plan_dispatches, plan_submissions, rays_per_dispatch,
};

/// Re-exported so users need not depend on the same wgpu version by hand.
pub use wgpu;
