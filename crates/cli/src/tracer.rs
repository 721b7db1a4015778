//! One interface over the CPU and GPU backends, so render and bench do not care which.

use std::time::Instant;

use anyhow::Result;
use bvhtrace_core::{
    Counters, FlatBvh, Hit, Precision, Query, Ray, Traversal, trace_batch_counted_precision,
    trace_batch_precision,
};
use bvhtrace_gpu::{
    AdapterChoice, BvhStorage, GpuBvh, GpuContext, TraceOptions, UploadOptions, UploadStats,
};

/// Where rays are traced.
pub enum Tracer<'a> {
    /// The CPU reference traversals (rayon over rays).
    Cpu(&'a FlatBvh),
    /// The WGSL kernels through wgpu.
    Gpu(Box<GpuBvh>),
    /// The same, on a BVH uploaded elsewhere.
    GpuRef(&'a GpuBvh),
    /// The same kernels on raw Vulkan through ash (`--backend vulkan`).
    Vulkan(Box<bvhtrace_vk::VkBvh>),
}

/// The answer to one batch.
pub struct Traced {
    pub hits: Vec<Hit>,
    pub counters: Option<Vec<Counters>>,
    /// Wall time including (for the GPU) ray upload and readback.
    pub wall_ms: f64,
    /// Kernel time from GPU timestamps, when there are any.
    pub gpu_ms: Option<f64>,
}

/// What the GPU upload needs to include for a job.
pub struct GpuSetup<'s> {
    pub adapter: Option<&'s str>,
    pub traversal: Traversal,
}

impl<'a> Tracer<'a> {
    fn gpu_bvh(&self) -> Option<&GpuBvh> {
        match self {
            Tracer::Cpu(_) => None,
            Tracer::Gpu(g) => Some(g),
            Tracer::GpuRef(g) => Some(g),
            Tracer::Vulkan(_) => None,
        }
    }

    /// Opens a GPU and uploads the BVH; returns the tracer and the upload time in ms.
    pub fn gpu(bvh: &FlatBvh, setup: &GpuSetup) -> Result<(Tracer<'a>, f64)> {
        let choice = match setup.adapter {
            Some(name) => AdapterChoice::Named(name.to_string()),
            None => AdapterChoice::Auto,
        };
        let ctx = GpuContext::new(choice)?;
        let start = Instant::now();
        let gpu = GpuBvh::upload(&ctx, bvh, &UploadOptions::for_traversal(setup.traversal))?;
        Ok((
            Tracer::Gpu(Box::new(gpu)),
            start.elapsed().as_secs_f64() * 1e3,
        ))
    }

    /// `"cpu"` or `"gpu"`.
    pub fn backend(&self) -> &'static str {
        if self.vk_bvh().is_some() {
            return "vulkan";
        }
        if self.gpu_bvh().is_some() {
            "gpu"
        } else {
            "cpu"
        }
    }

    /// The adapter's name, or the CPU's thread count.
    pub fn adapter(&self) -> String {
        if let Some(v) = self.vk_bvh() {
            return crate::vk_tracer::adapter(v);
        }
        match self.gpu_bvh() {
            None => format!("cpu ({} threads)", rayon::current_num_threads()),
            Some(g) => {
                let i = g.context().adapter_info();
                format!("{} ({:?}, {:?})", i.name, i.device_type, i.backend)
            }
        }
    }

    /// Bytes uploaded to the GPU (0 on the CPU).
    pub fn uploaded_bytes(&self) -> u64 {
        if let Some(v) = self.vk_bvh() {
            return crate::vk_tracer::uploaded_bytes(v);
        }
        self.gpu_bvh().map_or(0, |g| g.stats().total_bytes())
    }

    /// The upload's statistics and storage (GPU only).
    pub fn upload(&self) -> Option<(UploadStats, BvhStorage)> {
        self.gpu_bvh().map(|g| (*g.stats(), g.storage()))
    }

    /// Traces one batch (watertight f32, the default precision).
    pub fn trace(
        &self,
        rays: &[Ray],
        traversal: Traversal,
        query: Query,
        counters: bool,
    ) -> Result<Traced> {
        self.trace_precision(rays, traversal, query, Precision::WatertightF32, counters)
    }

    /// Traces one batch with the triangle test of `precision`.
    pub fn trace_precision(
        &self,
        rays: &[Ray],
        traversal: Traversal,
        query: Query,
        precision: Precision,
        counters: bool,
    ) -> Result<Traced> {
        match (self, self.gpu_bvh()) {
            (Tracer::Cpu(bvh), _) => {
                let start = Instant::now();
                let (hits, c) = if counters {
                    let (h, c) =
                        trace_batch_counted_precision(bvh, rays, traversal, query, precision);
                    (h, Some(c))
                } else {
                    (
                        trace_batch_precision(bvh, rays, traversal, query, precision),
                        None,
                    )
                };
                Ok(Traced {
                    hits,
                    counters: c,
                    wall_ms: start.elapsed().as_secs_f64() * 1e3,
                    gpu_ms: None,
                })
            }
            (Tracer::Vulkan(v), _) => {
                crate::vk_tracer::trace(v, rays, traversal, query, precision, counters)
            }
            (_, Some(g)) => {
                let out = g.trace_with_precision(
                    rays,
                    &TraceOptions {
                        traversal,
                        query,
                        counters,
                    },
                    precision,
                )?;
                Ok(Traced {
                    hits: out.hits,
                    counters: out.counters,
                    wall_ms: out.wall_ms,
                    gpu_ms: out.gpu_ms,
                })
            }
            (_, None) => unreachable!("a GPU tracer has a GPU BVH"),
        }
    }
}
