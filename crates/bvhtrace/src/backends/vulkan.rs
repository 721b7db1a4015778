//! The Vulkan backend: our walks on raw Vulkan through ash (`bvhtrace-vk`), the same
//! kernels as wgpu's, the tree in storage buffers. Not in a browser.

use std::any::Any;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::{DriverTuning, TraceError};
use bvhtrace_vk::{VkBvh, VkContext, VkOptions};

use super::interface::{DeviceInterface, OpenResult, Tree, uploaded};
use crate::open::{EngineDevice, open_engine};
use crate::{Backend, Device, OpenOptions};

/// A Vulkan device through ash.
struct VulkanDevice {
    ctx: VkContext,
}

/// [`Backend::Vulkan`] on the adapter `opts` asks for.
pub(crate) fn open(opts: &OpenOptions) -> Result<Arc<dyn DeviceInterface>, TraceError> {
    let ctx = VkContext::with_options(&VkOptions {
        adapter: opts.adapter.clone(),
        validation: opts.validation,
        tuning: opts.tuning,
        max_binding_bytes: opts.max_binding_bytes,
    })?;
    Ok(Arc::new(VulkanDevice { ctx }))
}

impl DeviceInterface for VulkanDevice {
    fn backend(&self) -> Backend {
        Backend::Vulkan
    }

    fn name(&self) -> String {
        let i = self.ctx.device_info();
        format!("{} ({:?})", i.name, i.kind)
    }

    fn tuning(&self) -> Option<DriverTuning> {
        Some(*self.ctx.tuning())
    }

    fn limits(&self) -> Option<DeviceLimits> {
        Some(*self.ctx.limits())
    }

    fn open<'t, 'a>(
        &self,
        tree: Tree<'t, 'a>,
        opts: &OpenOptions,
        _auto: bool,
    ) -> OpenResult<'t, 'a> {
        let device = EngineDevice {
            backend: Backend::Vulkan,
            name: &self.name(),
            features: self.ctx.features(),
            tuning: *self.ctx.tuning(),
        };
        uploaded(tree, |bvh| {
            open_engine(&device, opts, |u| VkBvh::upload(&self.ctx, bvh, u))
        })
    }

    fn build_bvh(
        &self,
        tris: &[Triangle],
        opts: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
        self.ctx.build_bvh(tris, opts)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl Device {
    /// A Vulkan context the caller opened (shared between many scenes; not in a
    /// browser).
    pub fn vulkan(ctx: VkContext) -> Device {
        Device::from_interface(Arc::new(VulkanDevice { ctx }))
    }

    /// The Vulkan context, on the Vulkan backend (its validation layer's count, its
    /// device's details).
    pub fn vulkan_context(&self) -> Option<&VkContext> {
        (self.inner.as_any().downcast_ref::<VulkanDevice>()).map(|d| &d.ctx)
    }
}
