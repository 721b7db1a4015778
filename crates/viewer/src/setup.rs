//! eframe's wgpu configuration: Vulkan, the adapter the tracer would pick, and a device
//! with the adapter's own limits and `TIMESTAMP_QUERY` when it has it, so that the one
//! device serves both egui and the traversal kernels.

use std::sync::Arc;

use bvhtrace_gpu::{AdapterChoice, pick_adapter};
use eframe::egui_wgpu::{WgpuConfiguration, WgpuSetup, WgpuSetupCreateNew};
use eframe::wgpu;

/// The wgpu configuration for the viewer's window. `adapter` is a name substring (as
/// `--adapter`); `None` honours `$BVHTRACE_ADAPTER`, else picks the best adapter that can
/// present to the window (a discrete GPU first, lavapipe last).
pub fn wgpu_configuration(adapter: Option<String>) -> WgpuConfiguration {
    let choice = match adapter {
        Some(n) => AdapterChoice::Named(n),
        None => AdapterChoice::Auto,
    };
    let wanted = choice.wanted_name();
    let mut create = WgpuSetupCreateNew::without_display_handle();
    create.instance_descriptor.backends =
        wgpu::Backends::from_env().unwrap_or(wgpu::Backends::VULKAN);
    create.native_adapter_selector = Some(Arc::new(
        move |adapters: &[wgpu::Adapter], surface: Option<&wgpu::Surface<'_>>| {
            let usable: Vec<&wgpu::Adapter> = adapters
                .iter()
                .filter(|a| surface.is_none_or(|s| a.is_surface_supported(s)))
                .collect();
            let infos: Vec<wgpu::AdapterInfo> = usable.iter().map(|a| a.get_info()).collect();
            let i = pick_adapter(&infos, wanted.as_deref()).map_err(|e| e.to_string())?;
            Ok(usable[i].clone())
        },
    ));
    create.device_descriptor = Arc::new(|adapter: &wgpu::Adapter| {
        let mut features = wgpu::Features::empty();
        if adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY) {
            features |= wgpu::Features::TIMESTAMP_QUERY;
        }
        wgpu::DeviceDescriptor {
            label: Some("bvhtrace viewer (egui and traversal)"),
            required_features: features,
            // The tracer sizes its buffers and dispatches from the device's limits: ask for
            // everything the adapter has rather than wgpu's conservative defaults.
            required_limits: adapter.limits(),
            ..Default::default()
        }
    });
    WgpuConfiguration {
        wgpu_setup: WgpuSetup::CreateNew(create),
        ..Default::default()
    }
}
