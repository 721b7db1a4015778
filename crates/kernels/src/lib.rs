//! What every bvhtrace backend shares, with no device API in it: the WGSL kernels and
//! their composition, the kernel key, the binding table, dispatch planning, device limits,
//! the CPU-driver measures, the [`Tracer`] interface and the one error type.
//!
//! The wgpu backend (`bvhtrace-gpu`) and the ash backend (`bvhtrace-vk`) both build on
//! this crate, so an engine written on ash does not pull in wgpu.
//!
//! * [`Tracer`]: one interface over the CPU walks ([`CpuTracer`]) and the device backends.
//! * [`KernelKey`]: what one kernel is (storage, traversal, query, precision, counters,
//!   where the rays come from, attributes): its WGSL source, bindings and constants.
//! * [`wgsl_library`]: the traversal functions for your own WGSL, composed for what the
//!   upload holds ([`LibraryShape`], [`BvhLibrary`]).
//! * [`DriverTuning`]: the measures that only help CPU drivers such as lavapipe.
//! * [`plan_dispatches`], [`DeviceLimits`]: how a batch fits a device.
//! * [`Engine`] over a [`Backend`]: the upload and the trace driver every device backend
//!   shares ([`engine`], [`upload`]).
//! * [`builder::build_bvh`] over a [`builder::BuildDevice`]: the device BVH builders'
//!   host side, shared by every device backend.
//! * [`TraceError`]: everything that can go wrong, on every backend.
#![warn(missing_docs)]

pub mod build;
pub mod builder;
mod device;
pub mod engine;
mod error;
pub mod key;
mod plan;
pub mod ray_query;
#[cfg(feature = "spirv")]
pub mod spirv;
mod tracer;
pub mod upload;
pub mod wgsl;

pub use bvhtrace_core;
pub use bvhtrace_core::{Query, TraceOptions, TraceOutput, Traversal};
pub use device::{
    ADAPTER_ENV, AdapterChoice, CPU_DRIVER_TRIP_LIMIT, DeviceKind, DriverTuning,
    MAX_DISPATCH_THREADS,
};
pub use engine::{Backend, BackendFeatures, Engine, HasEngine, SendSync, Update, new_output};
pub use error::TraceError;
pub use key::{BindingInfo, Composition, KernelKey, PerElement, VertexAttributes};
pub use plan::{
    COUNTERS_BYTES, DeviceLimits, Dispatch, HIT_BYTES, MAX_RAYS_PER_DISPATCH, RAY_BYTES,
    UploadStats, check_buffer_size, check_depth, check_wide_top_level, finish_incomplete,
    finish_incomplete_hits, plan_dispatches, plan_submissions, rays_per_dispatch, texel_rows,
};
pub use tracer::{
    CpuTracer, TraceFuture, Tracer, check_update_shape, mesh_fingerprint, tree_shape,
};
pub use upload::{UploadOptions, check_texels, texel_extent};
pub use wgsl::{
    BATCH_GROUP, BVH_GROUP, BvhLibrary, BvhStorage, FULL_STACK_SIZE, LibraryShape, RayInput,
    STACK_LANES, TEXEL_ROW, WIDE_STACK_GROUPS, WORKGROUP_SIZE, kernel_source, wgsl_library,
    wide_stack_may_overflow,
};
