//! eframe's wgpu configuration: Vulkan (WebGPU in a browser), the adapter the tracer would pick, and a device
//! with what [`GpuContext`] says the tracer needs and uses, so that the one device serves
//! both egui and the traversal kernels.

use std::sync::Arc;

use bvhtrace_gpu::{AdapterChoice, GpuContext, device_kind};
use eframe::egui_wgpu::{WgpuConfiguration, WgpuSetup, WgpuSetupCreateNew};
use eframe::wgpu;

/// The features to request on an adapter that has `adapter`:
/// [`GpuContext::required_features`] and those of [`GpuContext::optional_features`] it has.
pub fn device_features(adapter: wgpu::Features) -> wgpu::Features {
    GpuContext::required_features() | (adapter & GpuContext::optional_features())
}

/// The limits to request on an adapter with `adapter` limits: [`GpuContext::required_limits`]
/// raised to everything the adapter has (the tracer sizes its buffers and dispatches from
/// the device's limits; wgpu's defaults are conservative). An adapter below the required
/// limits gets its own, so that the window still opens and
/// [`GpuContext::from_device`] names the limit that is short.
pub fn device_limits(adapter: &wgpu::Limits) -> wgpu::Limits {
    let required = GpuContext::required_limits();
    if required.check_limits(adapter) {
        required.or_better_values_from(adapter)
    } else {
        adapter.clone()
    }
}

/// The wgpu configuration for the viewer's window. `adapter` is a name substring (as
/// `--adapter`); `None` honours `$BVHTRACE_ADAPTER`, else picks the best adapter that can
/// present to the window (a discrete GPU first, lavapipe last).
pub fn wgpu_configuration(adapter: Option<String>) -> WgpuConfiguration {
    // The library reads no environment variable: the flag, else $BVHTRACE_ADAPTER.
    let from_env = || {
        std::env::var(bvhtrace::ADAPTER_ENV)
            .ok()
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
    };
    let choice = AdapterChoice::from_name(adapter.or_else(from_env).as_deref());
    let mut create = WgpuSetupCreateNew::without_display_handle();
    create.instance_descriptor.backends = if cfg!(target_arch = "wasm32") {
        wgpu::Backends::BROWSER_WEBGPU
    } else {
        wgpu::Backends::from_env().unwrap_or(wgpu::Backends::VULKAN)
    };
    create.native_adapter_selector = Some(Arc::new(
        move |adapters: &[wgpu::Adapter], surface: Option<&wgpu::Surface<'_>>| {
            let usable: Vec<&wgpu::Adapter> = adapters
                .iter()
                .filter(|a| surface.is_none_or(|s| a.is_surface_supported(s)))
                .collect();
            let named: Vec<_> = usable
                .iter()
                .map(|a| {
                    let info = a.get_info();
                    (info.name, device_kind(info.device_type))
                })
                .collect();
            let i = choice.pick(&named).map_err(|e| e.to_string())?;
            Ok(usable[i].clone())
        },
    ));
    create.device_descriptor = Arc::new(|adapter: &wgpu::Adapter| wgpu::DeviceDescriptor {
        label: Some("bvhtrace viewer (egui and traversal)"),
        required_features: device_features(adapter.features()),
        required_limits: device_limits(&adapter.limits()),
        ..Default::default()
    });
    WgpuConfiguration {
        wgpu_setup: WgpuSetup::CreateNew(create),
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_device_asks_for_what_the_tracer_needs_and_the_adapter_has() {
        let optional = GpuContext::optional_features();
        assert_eq!(
            device_features(wgpu::Features::all()),
            GpuContext::required_features() | optional
        );
        assert_eq!(
            device_features(wgpu::Features::empty()),
            GpuContext::required_features()
        );
        let only_timestamps = device_features(wgpu::Features::TIMESTAMP_QUERY);
        assert!(only_timestamps.contains(GpuContext::required_features()));
        assert_eq!(
            only_timestamps & optional,
            wgpu::Features::TIMESTAMP_QUERY & optional
        );

        // A capable adapter: everything it has, which includes the required limits.
        let mut big = wgpu::Limits::default();
        big.max_storage_buffer_binding_size *= 4;
        big.max_buffer_size *= 4;
        let asked = device_limits(&big);
        assert!(GpuContext::required_limits().check_limits(&asked));
        assert!(asked.check_limits(&big), "more than the adapter has");
        assert_eq!(asked, big);
        // An adapter short of them: its own limits, for from_device to report.
        let mut small = wgpu::Limits::downlevel_defaults();
        small.max_compute_workgroup_storage_size = 1024;
        assert_eq!(device_limits(&small), small);
    }
}
