//! Headless device creation and the per-device state shared by every upload: the shader
//! module, the bind group layouts and the pipeline cache.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use bvhtrace_core::Precision;

use crate::error::GpuError;
use crate::features::{Composition, ModuleSet, PipelineFeatures};
use crate::shaders::{BvhStorage, KernelVariant, RayInput};

fn storage_index(storage: BvhStorage) -> usize {
    match storage {
        BvhStorage::Buffers => 0,
        BvhStorage::Textures => 1,
    }
}

/// Environment variable naming the adapter to use: any substring of its name,
/// case-insensitive (for example `llvmpipe` or `nvidia`).
pub const ADAPTER_ENV: &str = "BVHTRACE_ADAPTER";

/// Which Vulkan adapter [`GpuContext::new`] opens.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum AdapterChoice {
    /// `$BVHTRACE_ADAPTER` when it is set and not empty; otherwise the best adapter:
    /// a discrete GPU, else an integrated one, else a virtual one, else a CPU driver
    /// (lavapipe), ties broken by enumeration order.
    #[default]
    Auto,
    /// The first adapter whose name contains this substring (case-insensitive); for a
    /// command-line flag. Takes precedence over `$BVHTRACE_ADAPTER`.
    Named(String),
}

/// The adapter limits the tracer works within (a copy of the device's `wgpu::Limits`
/// fields that matter here).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuLimits {
    /// Largest storage buffer binding, bytes.
    pub max_storage_buffer_binding_size: u64,
    /// Largest buffer, bytes.
    pub max_buffer_size: u64,
    /// Most workgroups in one dispatch dimension.
    pub max_compute_workgroups_per_dimension: u32,
    /// Alignment of storage buffer binding offsets, bytes.
    pub min_storage_buffer_offset_alignment: u32,
    /// Largest 2D texture side, texels (bounds [`crate::BvhStorage::Textures`] uploads).
    pub max_texture_dimension_2d: u32,
}

impl GpuLimits {
    /// The fields of `limits`.
    pub fn from_wgpu(limits: &wgpu::Limits) -> Self {
        GpuLimits {
            max_storage_buffer_binding_size: limits.max_storage_buffer_binding_size,
            max_buffer_size: limits.max_buffer_size,
            max_compute_workgroups_per_dimension: limits.max_compute_workgroups_per_dimension,
            min_storage_buffer_offset_alignment: limits.min_storage_buffer_offset_alignment,
            max_texture_dimension_2d: limits.max_texture_dimension_2d,
        }
    }
}

/// A device and queue with the tracer's shared state. Cheap to clone (reference counted);
/// every [`crate::GpuBvh`] keeps a clone.
#[derive(Clone)]
pub struct GpuContext {
    inner: Arc<Inner>,
}

struct Inner {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: GpuLimits,
    timestamps: bool,
    /// The `TRIP_LIMIT` override ([`crate::shaders::trip_limit_for`]).
    trip_limit: u32,
    /// The `DISPATCH_THREADS` override ([`crate::shaders::dispatch_threads_for`]).
    dispatch_threads: AtomicU32,
    /// Shader modules, by the files composed.
    modules: Mutex<HashMap<ModuleSet, wgpu::ShaderModule>>,
    /// BVH group layouts: `[buffers, textures][without escapes, with escapes]`.
    bvh_layouts: [[wgpu::BindGroupLayout; 2]; 2],
    /// Batch group layouts: `[without counters, with counters]`.
    batch_layouts: [[wgpu::BindGroupLayout; 2]; 2],
    /// Pipelines, by their full feature set.
    pipelines: Mutex<HashMap<PipelineFeatures, wgpu::ComputePipeline>>,
    /// [`GpuContext::pipeline`] composes everything ([`Composition::EverythingOn`]).
    everything_on: AtomicBool,
    /// Shader modules and pipelines created so far ([`GpuContext::compile_counts`]).
    modules_compiled: AtomicU64,
    pipelines_compiled: AtomicU64,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.inner.info.name)
            .field("backend", &self.inner.info.backend)
            .field("limits", &self.inner.limits)
            .field("timestamps", &self.inner.timestamps)
            .finish()
    }
}

fn type_rank(t: wgpu::DeviceType) -> u32 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    }
}

/// Picks an adapter among `infos` for `choice` (the environment already applied): the
/// index of the chosen one. Pure, for the tests.
pub fn pick_adapter(infos: &[wgpu::AdapterInfo], wanted: Option<&str>) -> Result<usize, GpuError> {
    if infos.is_empty() {
        return Err(GpuError::NoAdapter {
            details: String::new(),
        });
    }
    match wanted {
        Some(w) => {
            let lw = w.to_lowercase();
            infos
                .iter()
                .position(|i| i.name.to_lowercase().contains(&lw))
                .ok_or_else(|| GpuError::AdapterNotFound {
                    wanted: w.to_string(),
                    available: infos
                        .iter()
                        .map(|i| format!("{} ({:?})", i.name, i.device_type))
                        .collect::<Vec<_>>()
                        .join(", "),
                })
        }
        None => Ok(infos
            .iter()
            .enumerate()
            .min_by_key(|(i, info)| (type_rank(info.device_type), *i))
            .map(|(i, _)| i)
            .unwrap_or(0)),
    }
}

impl AdapterChoice {
    /// The name substring to look for, the environment applied: `Named` wins, then a
    /// non-empty `$BVHTRACE_ADAPTER`, else `None` (the best adapter).
    pub fn wanted_name(&self) -> Option<String> {
        match self {
            AdapterChoice::Named(n) => Some(n.clone()),
            AdapterChoice::Auto => std::env::var(ADAPTER_ENV)
                .ok()
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty()),
        }
    }
}

fn storage_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

impl GpuContext {
    /// Opens a Vulkan device headlessly on the adapter `choice` selects (see
    /// [`AdapterChoice`]). Enables `TIMESTAMP_QUERY` when the adapter has it and takes the
    /// adapter's own limits (storage binding and buffer sizes, workgroup counts).
    ///
    /// Fails with [`GpuError::NoAdapter`] (which tells the user to install
    /// `mesa-vulkan-drivers`) when there is no Vulkan adapter; never panics.
    pub fn new(choice: AdapterChoice) -> Result<GpuContext, GpuError> {
        pollster::block_on(Self::new_async(choice))
    }

    /// [`GpuContext::new`], as a future.
    pub async fn new_async(choice: AdapterChoice) -> Result<GpuContext, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN;
        // Validation layers are rarely installed; wgpu's own validation stays on.
        desc.flags = wgpu::InstanceFlags::empty().with_env();
        let instance = wgpu::Instance::new(desc);
        let adapters = instance.enumerate_adapters(wgpu::Backends::VULKAN).await;
        let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
        let index = pick_adapter(&infos, choice.wanted_name().as_deref())?;
        let adapter = &adapters[index];
        let info = infos[index].clone();

        let mut features = wgpu::Features::empty();
        if adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY) {
            features |= wgpu::Features::TIMESTAMP_QUERY;
        }
        // For the f64 triangle test (`Precision::WatertightF64`), where the adapter has it.
        if adapter.features().contains(wgpu::Features::SHADER_F64) {
            features |= wgpu::Features::SHADER_F64;
        }

        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("bvhtrace"),
                required_features: features,
                required_limits: adapter.limits(),
                ..Default::default()
            })
            .await
            .map_err(|source| GpuError::RequestDevice {
                adapter: info.name.clone(),
                source,
            })?;
        Ok(Self::from_device(device, queue, info))
    }

    /// Wraps a device someone else created (an application, the egui viewer). The tracer
    /// uses that device's limits and, when it was created with `TIMESTAMP_QUERY`, reports
    /// GPU times.
    pub fn from_device(
        device: wgpu::Device,
        queue: wgpu::Queue,
        adapter_info: wgpu::AdapterInfo,
    ) -> GpuContext {
        let limits = GpuLimits::from_wgpu(&device.limits());
        let timestamps = device.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let layout = |label: &str, entries: &[wgpu::BindGroupLayoutEntry]| {
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries,
            })
        };
        // Read-only storage textures, not sampled ones: lavapipe fetches a sampled texel
        // through its per-lane mip-level logic (about 140 instructions per fetch), a storage
        // texel with one address computation and a vector gather (`bvh_textures.wgsl`).
        let storage_texture_entry = |binding, format, access| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::StorageTexture {
                access,
                format,
                view_dimension: wgpu::TextureViewDimension::D2,
            },
            count: None,
        };
        let texture_entry = |binding, format| {
            storage_texture_entry(binding, format, wgpu::StorageTextureAccess::ReadOnly)
        };
        let (rgba, r) = (
            wgpu::TextureFormat::Rgba32Uint,
            wgpu::TextureFormat::R32Uint,
        );
        let bvh_layouts = [
            [
                layout(
                    "bvhtrace bvh buffers",
                    &[storage_entry(0, true), storage_entry(1, true)],
                ),
                layout(
                    "bvhtrace bvh buffers+escapes",
                    &[
                        storage_entry(0, true),
                        storage_entry(1, true),
                        storage_entry(2, true),
                    ],
                ),
            ],
            [
                layout(
                    "bvhtrace bvh textures",
                    &[texture_entry(0, rgba), texture_entry(1, rgba)],
                ),
                layout(
                    "bvhtrace bvh textures+escapes",
                    &[
                        texture_entry(0, rgba),
                        texture_entry(1, rgba),
                        texture_entry(2, r),
                    ],
                ),
            ],
        ];
        // [buffer rays, texture rays] x [hits, hits + counters].
        let batch_layout = |rays: RayInput, counters: bool| {
            let mut entries = match rays {
                RayInput::Buffer => vec![storage_entry(0, true), storage_entry(1, false)],
                RayInput::Texture => vec![
                    texture_entry(0, rgba),
                    storage_texture_entry(1, rgba, wgpu::StorageTextureAccess::WriteOnly),
                ],
            };
            if counters {
                entries.push(storage_entry(2, false));
            }
            layout(
                &format!("bvhtrace batch ({rays:?} rays, counters {counters})"),
                &entries,
            )
        };
        let batch_layouts = [RayInput::Buffer, RayInput::Texture]
            .map(|rays| [false, true].map(|counters| batch_layout(rays, counters)));
        let trip_limit = crate::shaders::trip_limit_for(&adapter_info);
        let dispatch_threads = AtomicU32::new(crate::shaders::dispatch_threads_for(&adapter_info));
        GpuContext {
            inner: Arc::new(Inner {
                device,
                queue,
                info: adapter_info,
                limits,
                trip_limit,
                dispatch_threads,
                timestamps,
                modules: Default::default(),
                bvh_layouts,
                batch_layouts,
                pipelines: Mutex::new(HashMap::new()),
                everything_on: AtomicBool::new(false),
                modules_compiled: AtomicU64::new(0),
                pipelines_compiled: AtomicU64::new(0),
            }),
        }
    }

    /// The kernels' loop-trip budget per ray on this adapter
    /// ([`crate::shaders::trip_limit_for`]); `u32::MAX` is unbounded.
    pub fn trip_limit(&self) -> u32 {
        self.inner.trip_limit
    }

    /// The device.
    pub fn device(&self) -> &wgpu::Device {
        &self.inner.device
    }

    /// The queue.
    pub fn queue(&self) -> &wgpu::Queue {
        &self.inner.queue
    }

    /// The adapter's description (name, type, driver).
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.inner.info
    }

    /// The limits the tracer works within.
    pub fn limits(&self) -> &GpuLimits {
        &self.inner.limits
    }

    /// True when GPU times are measured (the device has `TIMESTAMP_QUERY`).
    pub fn has_timestamps(&self) -> bool {
        self.inner.timestamps
    }

    /// The layout of the BVH bind group (group 0 of the kernels; any group of yours, see
    /// [`crate::wgsl_library`]): bindings 0 (nodes) and 1 (triangles), plus 2 (escapes)
    /// when `with_escapes`, as buffers or textures.
    pub fn bvh_layout(&self, storage: BvhStorage, with_escapes: bool) -> &wgpu::BindGroupLayout {
        &self.inner.bvh_layouts[storage_index(storage)][usize::from(with_escapes)]
    }

    /// The storage an upload uses when [`crate::UploadOptions::storage`] is `None`.
    pub fn default_storage(&self) -> BvhStorage {
        BvhStorage::default_for(self.inner.info.device_type)
    }

    /// The layout of the batch bind group (group 1) with the rays in a buffer: bindings 0
    /// (rays) and 1 (hits), plus 2 (counters) when `with_counters`.
    pub fn batch_layout(&self, with_counters: bool) -> &wgpu::BindGroupLayout {
        self.batch_layout_for(with_counters, RayInput::Buffer)
    }

    /// [`GpuContext::batch_layout`] with the rays read from `rays`.
    pub fn batch_layout_for(&self, with_counters: bool, rays: RayInput) -> &wgpu::BindGroupLayout {
        let r = usize::from(rays == RayInput::Texture);
        &self.inner.batch_layouts[r][usize::from(with_counters)]
    }

    /// Runs `f` inside validation and out-of-memory error scopes; an error either reported
    /// becomes a [`GpuError::Wgpu`].
    pub(crate) fn scoped<T>(
        &self,
        during: &'static str,
        f: impl FnOnce() -> T,
    ) -> Result<T, GpuError> {
        let device = &self.inner.device;
        let oom = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let value = f();
        let v = pollster::block_on(validation.pop());
        let o = pollster::block_on(oom.pop());
        match v.or(o) {
            None => Ok(value),
            Some(e) => Err(GpuError::Wgpu {
                during,
                message: e.to_string(),
            }),
        }
    }

    /// True when kernels with this triangle test can run on this device (f64 needs
    /// `SHADER_F64`, which [`GpuContext::new`] requests whenever the adapter has it).
    pub fn supports_precision(&self, precision: Precision) -> bool {
        !precision.needs_f64()
            || self
                .inner
                .device
                .features()
                .contains(wgpu::Features::SHADER_F64)
    }

    /// How [`GpuContext::pipeline`] composes modules: only what each pipeline needs (the
    /// default), or everything (the baseline of `bvhtrace bench-trace --everything-on`).
    /// Both kinds stay cached side by side, so switching back does not recompile.
    pub fn set_composition(&self, composition: Composition) {
        self.inner
            .everything_on
            .store(composition == Composition::EverythingOn, Ordering::Relaxed);
    }

    /// See [`GpuContext::set_composition`].
    pub fn composition(&self) -> Composition {
        if self.inner.everything_on.load(Ordering::Relaxed) {
            Composition::EverythingOn
        } else {
            Composition::Specialised
        }
    }

    /// `(shader modules, pipelines)` created by this context so far: cache hits do not
    /// count, so a test can check that switching back to a feature set does not recompile.
    pub fn compile_counts(&self) -> (u64, u64) {
        (
            self.inner.modules_compiled.load(Ordering::Relaxed),
            self.inner.pipelines_compiled.load(Ordering::Relaxed),
        )
    }

    /// The `DISPATCH_THREADS` override the pipelines get: the worker threads a CPU driver
    /// splits each dispatch among ([`crate::shaders::dispatch_threads_for`]), 1 on GPUs.
    pub fn dispatch_threads(&self) -> u32 {
        self.inner.dispatch_threads.load(Ordering::Relaxed)
    }

    /// Sets the `DISPATCH_THREADS` override for the pipelines created from now on (and
    /// forgets the cached ones): for a driver whose thread count the context cannot see.
    /// Any value gives the same hits; clamped to `1..=MAX_DISPATCH_THREADS`.
    pub fn set_dispatch_threads(&self, threads: u32) -> Result<(), GpuError> {
        let t = threads.clamp(1, crate::shaders::MAX_DISPATCH_THREADS);
        self.inner.dispatch_threads.store(t, Ordering::Relaxed);
        self.inner.pipelines.lock().map_err(|_| poisoned())?.clear();
        Ok(())
    }

    /// Forgets every cached module and pipeline (for timing pipeline creation).
    pub fn clear_pipeline_cache(&self) -> Result<(), GpuError> {
        self.inner.pipelines.lock().map_err(|_| poisoned())?.clear();
        self.inner.modules.lock().map_err(|_| poisoned())?.clear();
        Ok(())
    }

    fn module(&self, set: &ModuleSet) -> Result<wgpu::ShaderModule, GpuError> {
        if !self.supports_precision(set.precision) {
            return Err(GpuError::PrecisionUnsupported {
                precision: set.precision,
                adapter: self.inner.info.name.clone(),
            });
        }
        if let Some(m) = self.inner.modules.lock().map_err(|_| poisoned())?.get(set) {
            return Ok(m.clone());
        }
        let source = set.compose(crate::shaders::BVH_GROUP);
        let module = self.scoped("compiling the WGSL kernels", || {
            self.inner
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some("bvhtrace kernels"),
                    source: wgpu::ShaderSource::Wgsl(source.into()),
                })
        })?;
        self.inner.modules_compiled.fetch_add(1, Ordering::Relaxed);
        // Another thread may have won the race; either module is fine.
        Ok(self
            .inner
            .modules
            .lock()
            .map_err(|_| poisoned())?
            .entry(*set)
            .or_insert(module)
            .clone())
    }

    /// The compute pipeline for one kernel variant, composed as
    /// [`GpuContext::composition`] says (by default only what the variant needs, see
    /// [`PipelineFeatures`]); created on first use and cached by its full feature set.
    pub fn pipeline(&self, variant: KernelVariant) -> Result<wgpu::ComputePipeline, GpuError> {
        self.pipeline_for(&PipelineFeatures::new(variant).with_composition(self.composition()))
    }

    /// The compute pipeline for `features`, created on first use and cached by the whole
    /// feature set (variant, attributes, composition). Its layout binds what the entry point
    /// reads: the escape links only for the walks that read them, counters only when on.
    pub fn pipeline_for(
        &self,
        features: &PipelineFeatures,
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        if let Some(p) = self
            .inner
            .pipelines
            .lock()
            .map_err(|_| poisoned())?
            .get(features)
        {
            return Ok(p.clone());
        }
        let variant = features.variant;
        let module = self.module(&features.module_set())?;
        let device = &self.inner.device;
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("bvhtrace trace"),
            bind_group_layouts: &[
                Some(self.bvh_layout(variant.storage, variant.needs_escapes())),
                Some(self.batch_layout_for(variant.counters, variant.rays)),
            ],
            immediate_size: 0,
        });
        let mut constants = variant.constants();
        constants.push(("TRIP_LIMIT", f64::from(self.inner.trip_limit)));
        constants.push(("DISPATCH_THREADS", f64::from(self.dispatch_threads())));
        let pipeline = self.scoped("creating a trace pipeline", || {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(variant.entry_point()),
                layout: Some(&layout),
                module: &module,
                entry_point: Some(variant.entry_point()),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    zero_initialize_workgroup_memory: false,
                },
                cache: None,
            })
        })?;
        self.inner
            .pipelines_compiled
            .fetch_add(1, Ordering::Relaxed);
        self.inner
            .pipelines
            .lock()
            .map_err(|_| poisoned())?
            .insert(*features, pipeline.clone());
        Ok(pipeline)
    }
}

fn poisoned() -> GpuError {
    GpuError::Wgpu {
        during: "locking the pipeline cache",
        message: "a thread panicked while holding it".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(name: &str, device_type: wgpu::DeviceType) -> wgpu::AdapterInfo {
        wgpu::AdapterInfo {
            name: name.into(),
            device_type,
            ..wgpu::AdapterInfo::new(wgpu::DeviceType::Other, wgpu::Backend::Vulkan)
        }
    }

    #[test]
    fn adapters_are_ranked_and_named() {
        let list = [
            info("llvmpipe (LLVM 15.0.6, 256 bits)", wgpu::DeviceType::Cpu),
            info("Intel(R) UHD Graphics", wgpu::DeviceType::IntegratedGpu),
            info("NVIDIA GeForce RTX 4090", wgpu::DeviceType::DiscreteGpu),
        ];
        assert_eq!(pick_adapter(&list, None).ok(), Some(2));
        assert_eq!(pick_adapter(&list[..2], None).ok(), Some(1));
        assert_eq!(pick_adapter(&list[..1], None).ok(), Some(0));
        assert_eq!(pick_adapter(&list, Some("LLVMPIPE")).ok(), Some(0));
        assert_eq!(pick_adapter(&list, Some("uhd")).ok(), Some(1));
        match pick_adapter(&list, Some("radeon")) {
            Err(GpuError::AdapterNotFound { wanted, available }) => {
                assert_eq!(wanted, "radeon");
                assert!(available.contains("llvmpipe") && available.contains("RTX 4090"));
            }
            other => panic!("{other:?}"),
        }
        let err = pick_adapter(&[], None).expect_err("no adapter");
        assert!(err.to_string().contains("mesa-vulkan-drivers"), "{err}");
        assert_eq!(
            AdapterChoice::Named("x".into()).wanted_name().as_deref(),
            Some("x")
        );
    }
}
