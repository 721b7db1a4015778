//! bvhtrace on wgpu: the BVH built on the CPU ([`bvhtrace_core::FlatBvh`]) traversed by
//! WGSL compute kernels.
//!
//! Every kernel is the twin of a CPU walk in [`bvhtrace_core::traverse`], operation for
//! operation, so device and CPU answers are compared ray by ray.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! // The same code as docs/design.md's "One engine, one front door".
//! use bvhtrace_gpu::core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal};
//! use bvhtrace_gpu::{AdapterChoice, CpuTracer, GpuBvh, GpuContext, Tracer, UploadOptions};
//! use bvhtrace_gpu::glam::Vec3;
//!
//! let tris = vec![[Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)]];
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let ctx = GpuContext::new(AdapterChoice::Auto)?; // or GpuContext::from_device(yours...)
//! let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all())?;
//! let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
//! let opts = TraceOptions::closest(Traversal::Stackless);
//! for tracer in [&gpu as &dyn Tracer, &CpuTracer::new(&bvh)] {
//!     let out = tracer.trace(&rays, &opts)?;
//!     println!("{}: {:?} in {:.3} ms", tracer.backend(), out.hits[0], out.wall_ms);
//! }
//! # Ok(()) }
//! ```
//!
//! # Features and limits
//! The tracer needs no wgpu feature and [`GpuContext::required_limits`] (which
//! `wgpu::Limits::default()` satisfies); it uses `TIMESTAMP_QUERY` and `SHADER_F64` when
//! the device has them ([`GpuContext::optional_features`]). [`GpuContext::new`] creates
//! such a device; [`GpuContext::from_device`] wraps yours and tells you what is missing.
//!
//! * [`GpuContext`]: the device (headless, or yours), its limits, the pipeline cache and
//!   the [`DriverTuning`] (measures that only help CPU drivers such as lavapipe).
//! * [`GpuBvh::upload`]: nodes, triangles, and the escape links only when a traversal needs
//!   them, each checked against the device's limits.
//! * [`Tracer::trace`]: ray slices in, [`TraceOutput`] out (hits, counters, GPU and wall
//!   milliseconds); [`GpuBvh::record`]: the same into your own encoder and buffers.
//!   [`GpuBvh`] implements [`Tracer`], the interface shared with the CPU and ash backends.
//! * [`GpuBvh::wgsl_library`] and [`GpuBvh::bind_group_for`]: the traversal functions in
//!   your own WGSL (`bvh_trace_closest`, `bvh_trace_any`, `bvh_hit_surface`), composed for
//!   what the upload holds, one mesh or two levels; a library of another shape is an error.
//! * [`TraceOutput::instance_hit`]: a hit's instance (index, user id) and primitive in its
//!   mesh, for a two-level BVH.
#![warn(missing_docs)]

pub mod backend;
mod build;
mod bvh;
mod context;
mod curves;
mod library;
mod motion;
#[cfg(not(target_arch = "wasm32"))]
mod ray_query;
mod trace;
mod tree_kernel;

pub use build::{
    GpuBuildOptions, GpuBuildTimes, GpuBuilderKind, GpuMorph, GpuRefit, GpuSkin, RefitTimes,
    RefitVertices,
};
pub use bvh::{BvhBindGroup, GpuBvh};
pub use bvhtrace_engine::UploadOptions;
pub use bvhtrace_engine::engine::Update;
pub use context::{ContextOptions, GpuContext, device_kind};
pub use curves::GpuCurveBvh;
pub use motion::{GpuMotionBvh, GpuMotionInstancedBvh};
#[cfg(not(target_arch = "wasm32"))]
pub use ray_query::RayQueryBvh;

/// The backend name of the ray-query tracer (`RayQueryBvh`'s [`Tracer::backend`]).
pub const RAY_QUERY_BACKEND: &str = "ray-query";
pub use trace::RayBatch;

pub use bvhtrace_core::{InstanceHit, InstanceTable};
pub use bvhtrace_engine::compose::VertexAttributes;
pub use bvhtrace_engine::core::{Query, TraceOptions, TraceOutput, Traversal};
pub use bvhtrace_engine::key::Composition;
pub use bvhtrace_engine::plan::DeviceLimits;
pub use bvhtrace_engine::{
    AdapterChoice, BvhLibrary, BvhStorage, CpuTracer, DriverTuning, KernelKey, LibraryShape,
    TraceError, Tracer, UploadStats, wgsl_library,
};

/// The error type of this crate: [`TraceError`], shared by every backend.
pub type GpuError = TraceError;

/// Re-exported so users need not depend on the same versions by hand.
pub use bvhtrace_core as core;
pub use bvhtrace_engine as engine;
pub use glam;
pub use wgpu;
