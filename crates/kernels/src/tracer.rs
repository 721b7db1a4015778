//! One tracing interface over every backend.

use std::borrow::Borrow;

use bvhtrace_core::{FlatBvh, Ray, TraceOptions, TraceOutput, Traversal};

use crate::error::TraceError;
use crate::plan::UploadStats;

/// Something that traces rays through one BVH: the CPU walks ([`CpuTracer`]), the wgpu
/// backend (`bvhtrace_gpu::GpuBvh`) or the ash backend (`bvhtrace_vk::VkBvh`). Given the
/// same rays and options, every implementation returns the same hits bit for bit.
///
/// Implementations are `Send + Sync`: one uploaded BVH can be traced from several threads
/// at once.
pub trait Tracer: Send + Sync {
    /// The backend's name: `cpu`, `wgpu` or `vulkan`.
    fn backend(&self) -> &'static str;

    /// The device that traces: the adapter's name and type, or the CPU's thread count.
    fn device_name(&self) -> String;

    /// The walk this backend runs fastest; what a front end uses when none is asked for.
    fn default_traversal(&self) -> Traversal;

    /// `Ok` when [`Tracer::trace`] can run `opts` here; otherwise the error it would
    /// return (escape links not uploaded, no wide layout for the wide walk, a tree too
    /// deep for the full stack, a precision the device lacks).
    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError>;

    /// Traces `rays` as `opts` says: one hit per ray, in order, with counters when asked
    /// for, and the times.
    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError>;

    /// Does the one-time work for `opts` ahead of the first trace (compiling pipelines),
    /// so that the first trace's time is not the compiler's. Nothing to do on the CPU.
    fn prepare(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.supports(opts)
    }

    /// What the upload to the device holds and cost; `None` on the CPU.
    fn upload_stats(&self) -> Option<UploadStats> {
        None
    }

    /// Bytes of the BVH held on the device (0 on the CPU).
    fn uploaded_bytes(&self) -> u64 {
        self.upload_stats().map_or(0, |s| s.total_bytes())
    }
}

/// The CPU walks of [`bvhtrace_core::traverse`] over a borrowed or owned tree (`&FlatBvh`,
/// `Arc<FlatBvh>` or `FlatBvh`), on the current rayon pool.
#[derive(Clone, Debug)]
pub struct CpuTracer<B = std::sync::Arc<FlatBvh>> {
    bvh: B,
}

impl<B: Borrow<FlatBvh>> CpuTracer<B> {
    /// Traces through `bvh`.
    pub fn new(bvh: B) -> Self {
        CpuTracer { bvh }
    }

    /// The tree.
    pub fn bvh(&self) -> &FlatBvh {
        self.bvh.borrow()
    }
}

impl<B: Borrow<FlatBvh> + Send + Sync> Tracer for CpuTracer<B> {
    fn backend(&self) -> &'static str {
        "cpu"
    }

    fn device_name(&self) -> String {
        format!("cpu ({} threads)", rayon::current_num_threads())
    }

    fn default_traversal(&self) -> Traversal {
        Traversal::CPU_DEFAULT
    }

    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        if opts.traversal.needs_escapes() {
            self.bvh().check_escape_links()?;
        }
        if opts.traversal.is_wide() && self.bvh().wide.is_none() {
            return Err(TraceError::WideLayoutMissing {
                missing: "this BVH does not have: call FlatBvh::build_wide (or with_wide) first",
            });
        }
        Ok(())
    }

    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        self.supports(opts)?;
        Ok(bvhtrace_core::trace_rays(self.bvh(), rays, opts))
    }
}
