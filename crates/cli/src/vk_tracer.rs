//! `--backend vulkan`: the same WGSL kernels on raw Vulkan through ash (`bvhtrace-vk`),
//! behind the [`Tracer`] interface so render and bench treat it like the wgpu backend.

use anyhow::Result;
use bvhtrace_core::{FlatBvh, Precision, Query, Ray, Traversal};
use bvhtrace_gpu::BvhStorage;
use bvhtrace_gpu::shaders::KernelVariant;
use bvhtrace_vk::{VkBvh, VkContext};

use crate::tracer::{Traced, Tracer};

impl<'a> Tracer<'a> {
    /// Opens a Vulkan device through ash (`adapter`, else `BVHTRACE_ADAPTER`, else the best
    /// device) and uploads the BVH; returns the tracer and the upload time in ms.
    pub fn vulkan(bvh: &FlatBvh, adapter: Option<&str>) -> Result<(Tracer<'a>, f64)> {
        let ctx = VkContext::new(adapter)?;
        let gpu = VkBvh::upload(&ctx, bvh)?;
        let ms = gpu.stats().upload_ms;
        Ok((Tracer::Vulkan(Box::new(gpu)), ms))
    }

    /// The ash BVH, when this is the Vulkan backend.
    pub fn vk_bvh(&self) -> Option<&VkBvh> {
        match self {
            Tracer::Vulkan(g) => Some(g),
            _ => None,
        }
    }
}

/// The device's name and type, as `Tracer::adapter` reports it.
pub fn adapter(g: &VkBvh) -> String {
    let i = g.context().device_info();
    format!("{} ({:?}, Vulkan via ash)", i.name, i.device_type)
}

/// Bytes of the uploaded BVH arrays.
pub fn uploaded_bytes(g: &VkBvh) -> u64 {
    g.stats().total_bytes()
}

/// Traces one batch with the kernel for `traversal`, `query` and `precision`.
pub fn trace(
    g: &VkBvh,
    rays: &[Ray],
    traversal: Traversal,
    query: Query,
    precision: Precision,
    counters: bool,
) -> Result<Traced> {
    let variant = KernelVariant::new(BvhStorage::Buffers, traversal, query, counters)
        .with_precision(precision);
    let out = g.trace_variant(rays, variant)?;
    Ok(Traced {
        hits: out.hits,
        counters: out.counters,
        wall_ms: out.wall_ms,
        gpu_ms: out.gpu_ms,
    })
}
