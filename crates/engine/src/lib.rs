//! The engine under every bvhtrace device backend, with no device API in it: the WGSL
//! kernels and their composition, the table of walks, the kernel key, the upload plan and
//! the trace driver, the [`Tracer`] interface and the one error type.
//!
//! The wgpu backend (`bvhtrace-gpu`), the ash backend (`bvhtrace-vk`) and the test
//! backend (`bvhtrace-mock`) implement [`engine::DeviceApi`] (make and write arrays, make
//! the ray scratch, run one batch); [`Engine`] does the rest for each, so an engine written
//! on ash does not pull in wgpu.
//!
//! For users:
//! * [`Tracer`]: one interface over the CPU walks ([`CpuTracer`]) and the device backends.
//! * [`UploadOptions`], [`UploadStats`], [`BvhStorage`]: what an upload holds, where.
//! * [`wgsl_library`]: the traversal functions for your own WGSL, composed for what the
//!   upload holds ([`LibraryShape`], [`BvhLibrary`]).
//! * [`AdapterChoice`], [`DeviceKind`], [`DriverTuning`]: which device, and the measures
//!   that only help CPU drivers such as lavapipe.
//! * [`KernelKey`]: what one kernel is (storage, walk, query, precision, counters, where
//!   the rays come from, attributes): a front end reports the kernels that ran by it.
//! * [`TraceError`]: everything that can go wrong, on every backend.
//!
//! For backend implementers, in their modules: [`engine`] (the device trait and the
//! engine), [`walks`] (the table of walks), [`compose`] and [`shaders`] (the WGSL),
//! [`upload`] (the arrays), [`pages`] (arrays over one binding), [`plan`] (dispatches within a device's limits), [`tracer`]
//! (finishing rays on the host), [`builder`] and [`programs`] (the device builders, the
//! refit, skins and morphs), [`ray_query`] (the device's own ray queries), `spirv` (the
//! kernels for Vulkan, with the `spirv` feature).
#![warn(missing_docs)]

pub mod builder;
pub mod compose;
pub mod device;
pub mod engine;
mod error;
pub mod key;
mod library;
pub mod pages;
pub mod plan;
pub mod programs;
pub mod ray_query;
pub mod shaders;
#[cfg(feature = "spirv")]
pub mod spirv;
pub mod storage;
pub mod tracer;
pub mod upload;
pub mod walks;

pub use bvhtrace_core as core;
pub use device::{AdapterChoice, DeviceKind, DriverTuning};
pub use engine::Engine;
pub use error::TraceError;
pub use key::KernelKey;
pub use library::{BvhLibrary, LibraryShape, wgsl_library};
pub use storage::BvhStorage;
pub use tracer::{CpuTracer, Tracer};
pub use upload::{UploadOptions, UploadStats};
