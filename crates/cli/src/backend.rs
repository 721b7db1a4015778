//! Choosing the backend a command traces on: every one is a `bvhtrace_kernels::Tracer`,
//! so render and bench do not care which.

use anyhow::Result;
use bvhtrace_core::{FlatBvh, Traversal};
use bvhtrace_gpu::{AdapterChoice, CpuTracer, GpuBvh, GpuContext, Tracer, UploadOptions};
use bvhtrace_vk::{VkBvh, VkContext};

/// Which backend traces.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Backend {
    /// WGSL kernels through wgpu (falls back to the CPU when there is no adapter).
    Gpu,
    /// The CPU walks.
    Cpu,
    /// The same kernels on raw Vulkan through ash (`bvhtrace-vk`, BVH in storage
    /// buffers); an error when there is no Vulkan device.
    Vulkan,
}

/// Opens `backend` on the adapter named `adapter` (else `BVHTRACE_ADAPTER`, else the best)
/// and uploads `bvh` for `traversals`. Without a wgpu adapter, `Gpu` says why and falls
/// back to the CPU.
pub fn open<'a>(
    backend: Backend,
    adapter: Option<&str>,
    bvh: &'a FlatBvh,
    traversals: &[Traversal],
) -> Result<Box<dyn Tracer + 'a>> {
    let choice = AdapterChoice::from_name(adapter);
    Ok(match backend {
        Backend::Cpu => Box::new(CpuTracer::new(bvh)),
        Backend::Vulkan => Box::new(VkBvh::upload(&VkContext::new(choice)?, bvh)?),
        Backend::Gpu => {
            let upload = UploadOptions {
                traversals: traversals.to_vec(),
                storage: None,
            };
            match GpuContext::new(choice).and_then(|ctx| GpuBvh::upload(&ctx, bvh, &upload)) {
                Ok(gpu) => Box::new(gpu),
                Err(e) => {
                    eprintln!("note: no usable GPU ({e}); tracing on the CPU instead");
                    Box::new(CpuTracer::new(bvh))
                }
            }
        }
    })
}
