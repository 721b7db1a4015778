//! Headless device creation and the per-device state shared by every upload: the shader
//! module, the bind group layouts and the pipeline cache.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use bvhtrace_core::Precision;
use bvhtrace_engine::compose::ModuleSet;
use bvhtrace_engine::compose::WORKGROUP_SIZE;
use bvhtrace_engine::engine::BackendFeatures;
use bvhtrace_engine::key::Composition;
use bvhtrace_engine::pages::{PAGE_BINDING_STRIDE, Pages};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::storage::RayInput;
use bvhtrace_engine::walks::{FULL_STACK_SIZE, STACK_LANES};
use bvhtrace_engine::{AdapterChoice, BvhStorage, DeviceKind, DriverTuning, KernelKey};

use crate::GpuError;

/// wgpu's adapter type as a [`DeviceKind`].
pub fn device_kind(t: wgpu::DeviceType) -> DeviceKind {
    match t {
        wgpu::DeviceType::DiscreteGpu => DeviceKind::DiscreteGpu,
        wgpu::DeviceType::IntegratedGpu => DeviceKind::IntegratedGpu,
        wgpu::DeviceType::VirtualGpu => DeviceKind::VirtualGpu,
        wgpu::DeviceType::Cpu => DeviceKind::Cpu,
        wgpu::DeviceType::Other => DeviceKind::Other,
    }
}

/// Where [`GpuContext::new_async`] looks for adapters: Vulkan natively, the browser's
/// WebGPU in a browser.
const BACKENDS: wgpu::Backends = if cfg!(target_arch = "wasm32") {
    wgpu::Backends::BROWSER_WEBGPU
} else {
    wgpu::Backends::VULKAN
};

/// The adapters to choose from: every Vulkan adapter, or the one a browser offers.
async fn adapters(instance: &wgpu::Instance) -> Vec<wgpu::Adapter> {
    if cfg!(target_arch = "wasm32") {
        let options = wgpu::RequestAdapterOptions::default();
        instance
            .request_adapter(&options)
            .await
            .into_iter()
            .collect()
    } else {
        instance.enumerate_adapters(BACKENDS).await
    }
}

/// Storage textures the texture storage binds in one stage: three for the BVH, two for
/// the rays and hits.
const STORAGE_TEXTURES_USED: u32 = 5;

/// How a [`GpuContext`] runs its kernels. The defaults suit every device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ContextOptions {
    /// The CPU-driver measures; `None` picks [`DriverTuning::for_device`] for the adapter
    /// (falling back to buffer storage on a device with too few storage-texture bindings).
    pub tuning: Option<DriverTuning>,
    /// Compose only what each kernel needs (the default), or everything (a benchmark's
    /// baseline).
    pub composition: Composition,
    /// Ask for wgpu's `EXPERIMENTAL_RAY_QUERY` when the adapter offers it, for the
    /// ray-query tracer ([`crate::RayQueryBvh`]). Off by default: wgpu's experimental
    /// features are opted into one by one.
    pub ray_queries: bool,
    /// The largest storage binding the tracer makes, when below the device's own (`None`:
    /// the device's): a tree larger than it is split into pages of at most this size
    /// (`bvhtrace_engine::pages`), as on a device with that limit. To test the split on
    /// small scenes, or a browser's 128 MiB bindings natively.
    pub max_binding_bytes: Option<u64>,
    /// Create the device with WebGPU's default limits (`wgpu::Limits::default()`: what a
    /// page's `requestDevice()` gets when it asks for nothing: 128 MiB storage bindings,
    /// 8 storage buffers per stage) instead of the adapter's own. Where a program shares
    /// its device with a page that asked for nothing, or to see what such a device takes.
    pub webgpu_default_limits: bool,
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
    limits: DeviceLimits,
    timestamps: bool,
    /// The CPU-driver measures in force.
    tuning: DriverTuning,
    composition: Composition,
    /// Shader modules, by the files composed.
    modules: Mutex<HashMap<ModuleSet, wgpu::ShaderModule>>,
    /// BVH group layouts: `[buffers, textures][without escapes, with escapes]`.
    bvh_layouts: [[[[wgpu::BindGroupLayout; 2]; 2]; 2]; 2],
    /// Batch group layouts: `[without counters, with counters]`.
    batch_layouts: [[wgpu::BindGroupLayout; 2]; 2],
    /// Pipelines, by their key.
    pipelines: Mutex<HashMap<KernelKey, wgpu::ComputePipeline>>,
    /// Shader modules and pipelines created so far ([`GpuContext::compile_counts`]).
    modules_compiled: AtomicU64,
    pipelines_compiled: AtomicU64,
    /// Mappings for reading made so far ([`GpuContext::readbacks`]).
    readbacks: AtomicU64,
    /// The pipelines of the device builders (`GpuContext::build_bvh`) and the refit
    /// (`GpuRefit`), by program name, made on first use.
    device_programs: Mutex<HashMap<String, Vec<wgpu::ComputePipeline>>>,
    /// In a browser, the error scopes of the work done since the last trace, popped and
    /// awaited by that trace ([`GpuContext::deferred_errors`]).
    #[cfg(target_arch = "wasm32")]
    deferred: Mutex<Vec<(&'static str, DeferredScope)>>,
}

/// A popped error scope whose answer a browser gives on its event loop.
#[cfg(target_arch = "wasm32")]
type DeferredScope = std::pin::Pin<Box<dyn std::future::Future<Output = Option<wgpu::Error>>>>;

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.inner.info.name)
            .field("backend", &self.inner.info.backend)
            .field("limits", &self.inner.limits)
            .field("timestamps", &self.inner.timestamps)
            .field("tuning", &self.inner.tuning)
            .finish()
    }
}

/// An error scope's error as ours.
fn scope_error(during: &'static str, e: wgpu::Error) -> GpuError {
    match e {
        wgpu::Error::OutOfMemory { .. } => GpuError::OutOfMemory {
            during,
            message: e.to_string(),
        },
        e => GpuError::device(during, e),
    }
}

/// A compute-stage storage-buffer binding.
/// What a BVH bind group (group 0 of the kernels) holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct BvhGroupShape {
    pub storage: BvhStorage,
    /// The escape links (binding 2).
    pub escapes: bool,
    /// The instances of a two-level tree (binding 4).
    pub instances: bool,
    /// The alpha masks (binding 5).
    pub masks: bool,
    /// How the nodes, triangles and escape links are split over bindings.
    pub pages: Pages,
}

impl BvhGroupShape {
    fn label(&self) -> String {
        let BvhGroupShape {
            storage,
            escapes,
            instances,
            masks,
            pages,
        } = self;
        format!(
            "bvhtrace bvh ({storage:?}, escapes {escapes}, instances {instances}, masks \
             {masks}, {pages:?})"
        )
    }

    /// The layout's entries: nodes, triangles (and escape links) as buffers or read-only
    /// storage textures, a buffer per further page, the instances and masks as buffers.
    fn entries(&self) -> Vec<wgpu::BindGroupLayoutEntry> {
        let texture = |binding, format| {
            storage_texture_entry(binding, format, wgpu::StorageTextureAccess::ReadOnly)
        };
        let (rgba, r) = (
            wgpu::TextureFormat::Rgba32Uint,
            wgpu::TextureFormat::R32Uint,
        );
        let mut split = vec![0, 1];
        if self.escapes {
            split.push(2);
        }
        let mut entries = Vec::new();
        for &b in &split {
            entries.push(match (self.storage, b) {
                (BvhStorage::Buffers, _) => storage_entry(b, true),
                (BvhStorage::Textures, 2) => texture(b, r),
                (BvhStorage::Textures, _) => texture(b, rgba),
            });
        }
        // The instances are a buffer with either storage (few, and read once a visit).
        if self.instances {
            entries.push(storage_entry(4, true));
        }
        if self.masks {
            entries.push(storage_entry(5, true));
        }
        for &b in &split {
            for p in 1..u32::from(self.pages.of_binding(b)) {
                entries.push(storage_entry(b + PAGE_BINDING_STRIDE * p, true));
            }
        }
        entries
    }
}

/// A storage texture's entry. Read-only storage textures, not sampled ones, hold the tree:
/// lavapipe fetches a sampled texel through its per-lane mip-level logic (about 140
/// instructions per fetch), a storage texel with one address computation and a vector
/// gather (`bvh_textures.wgsl`).
fn storage_texture_entry(
    binding: u32,
    format: wgpu::TextureFormat,
    access: wgpu::StorageTextureAccess,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::StorageTexture {
            access,
            format,
            view_dimension: wgpu::TextureViewDimension::D2,
        },
        count: None,
    }
}

pub(crate) fn storage_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
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
    /// The features a device must have for the tracer: none.
    pub fn required_features() -> wgpu::Features {
        wgpu::Features::empty()
    }

    /// The features the tracer uses when a device has them: `TIMESTAMP_QUERY` (GPU times
    /// in [`TraceOutput::gpu_ms`](bvhtrace_engine::TraceOutput::gpu_ms)) and `SHADER_F64`
    /// (the f64 triangle test, [`bvhtrace_core::Precision::WatertightF64`]).
    pub fn optional_features() -> wgpu::Features {
        wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::SHADER_F64
    }

    /// The least limits a device must have for the tracer: WebGPU's downlevel defaults,
    /// with the 16 KiB of workgroup memory the traversal stacks take, 64 invocations per
    /// workgroup, two bind groups and six storage buffers per stage. Request at least
    /// these (or `wgpu::Limits::default()`, which has them) when you create a device for
    /// [`GpuContext::from_device`]; [`GpuContext::recommended_limits`] says what buys the
    /// fast path on an adapter. Each upload is checked against the device's own limits.
    pub fn required_limits() -> wgpu::Limits {
        wgpu::Limits {
            max_bind_groups: 2,
            max_storage_buffers_per_shader_stage: 6,
            max_compute_workgroup_storage_size: STACK_LANES * FULL_STACK_SIZE * 4,
            max_compute_invocations_per_workgroup: WORKGROUP_SIZE,
            max_compute_workgroup_size_x: WORKGROUP_SIZE,
            ..wgpu::Limits::downlevel_defaults()
        }
    }

    /// The limits to request from `adapter` for the tracer's fast path there:
    /// [`GpuContext::required_limits`] raised to the adapter's own buffer, texture and
    /// dispatch sizes and storage textures per stage. Which limits buy which path:
    /// * [`GpuContext::required_limits`] (or `wgpu::Limits::default()`) buys every walk with
    ///   the BVH in storage buffers, the layout GPUs trace fastest;
    /// * on a CPU driver (lavapipe), the texture storage that is several times faster there
    ///   also needs 5 storage textures per stage and texture sides beyond WebGPU's defaults,
    ///   which these limits include when the adapter has them;
    /// * larger buffer and binding sizes allow larger scenes on any device, and more storage
    ///   buffers per stage let a tree larger than one binding be split into pages.
    pub fn recommended_limits(adapter: &wgpu::Adapter) -> wgpu::Limits {
        let a = adapter.limits();
        let r = Self::required_limits();
        wgpu::Limits {
            max_storage_textures_per_shader_stage: a
                .max_storage_textures_per_shader_stage
                .max(r.max_storage_textures_per_shader_stage),
            max_texture_dimension_2d: a.max_texture_dimension_2d.max(r.max_texture_dimension_2d),
            max_storage_buffer_binding_size: a
                .max_storage_buffer_binding_size
                .max(r.max_storage_buffer_binding_size),
            // A tree over one binding is split into pages, one binding each.
            max_storage_buffers_per_shader_stage: a
                .max_storage_buffers_per_shader_stage
                .max(r.max_storage_buffers_per_shader_stage),
            max_buffer_size: a.max_buffer_size.max(r.max_buffer_size),
            max_compute_workgroups_per_dimension: a
                .max_compute_workgroups_per_dimension
                .max(r.max_compute_workgroups_per_dimension),
            ..r
        }
    }

    /// Opens a Vulkan device headlessly on the adapter `choice` selects (see
    /// [`AdapterChoice`]), with the adapter's own limits and the
    /// [optional features](GpuContext::optional_features) it has.
    ///
    /// Fails with [`TraceError::NoAdapter`](crate::TraceError::NoAdapter) (which tells the
    /// user to install `mesa-vulkan-drivers`) when there is no Vulkan adapter; never panics.
    pub fn new(choice: AdapterChoice) -> Result<GpuContext, GpuError> {
        Self::new_with(choice, &ContextOptions::default())
    }

    /// [`GpuContext::new`] with `options`.
    pub fn new_with(
        choice: AdapterChoice,
        options: &ContextOptions,
    ) -> Result<GpuContext, GpuError> {
        pollster::block_on(Self::new_async(choice, options))
    }

    /// [`GpuContext::new_with`], as a future.
    pub async fn new_async(
        choice: AdapterChoice,
        options: &ContextOptions,
    ) -> Result<GpuContext, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = BACKENDS;
        // Validation layers are rarely installed; wgpu's own validation stays on. No
        // `with_env`: the library reads no environment variable.
        desc.flags = wgpu::InstanceFlags::empty();
        let instance = wgpu::Instance::new(desc);
        let adapters = adapters(&instance).await;
        let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
        let named: Vec<(String, DeviceKind)> = infos
            .iter()
            .map(|i| (i.name.clone(), device_kind(i.device_type)))
            .collect();
        let index = choice.pick(&named)?;
        let adapter = &adapters[index];
        let info = infos[index].clone();
        let mut features = adapter.features() & Self::optional_features();
        let ray_queries = options.ray_queries
            && adapter
                .features()
                .contains(wgpu::Features::EXPERIMENTAL_RAY_QUERY);
        if ray_queries {
            features |= wgpu::Features::EXPERIMENTAL_RAY_QUERY;
        }
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("bvhtrace"),
                required_features: features,
                required_limits: match options.webgpu_default_limits {
                    true => wgpu::Limits::default(),
                    false => adapter.limits(),
                },
                experimental_features: if ray_queries {
                    // SAFETY: wgpu asks callers to acknowledge that its experimental
                    // features may hold bugs; only the ray-query tracer uses this one,
                    // and its answers are checked against the CPU walks in the tests.
                    unsafe { wgpu::ExperimentalFeatures::enabled() }
                } else {
                    wgpu::ExperimentalFeatures::disabled()
                },
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::Device {
                during: "creating a device",
                message: format!("{}: {e}", info.name),
            })?;
        Self::from_device_with(device, queue, info, options)
    }

    /// Wraps a device someone else created (an application, the egui viewer), with the
    /// [`DriverTuning`] for its adapter type. The device needs the
    /// [required features](GpuContext::required_features) and
    /// [limits](GpuContext::required_limits), and the tracer uses the
    /// [optional features](GpuContext::optional_features) it was created with; anything
    /// missing is a [`TraceError::LimitTooLow`](crate::TraceError::LimitTooLow), not a
    /// failure later.
    pub fn from_device(
        device: wgpu::Device,
        queue: wgpu::Queue,
        adapter_info: wgpu::AdapterInfo,
    ) -> Result<GpuContext, GpuError> {
        Self::from_device_with(device, queue, adapter_info, &ContextOptions::default())
    }

    /// [`GpuContext::from_device`] with `options`.
    // In a browser wgpu's objects are neither Send nor Sync, and one thread uses them.
    #[cfg_attr(target_arch = "wasm32", allow(clippy::arc_with_non_send_sync))]
    pub fn from_device_with(
        device: wgpu::Device,
        queue: wgpu::Queue,
        adapter_info: wgpu::AdapterInfo,
        options: &ContextOptions,
    ) -> Result<GpuContext, GpuError> {
        let wl = device.limits();
        let need = Self::required_limits();
        // Every limit of `required_limits`, each named as wgpu names it.
        let mut failed = None;
        need.check_limits_with_fail_fn(&wl, false, |limit, needs, has| {
            failed.get_or_insert((limit, has, needs));
        });
        if let Some((limit, has, needs)) = failed {
            return Err(GpuError::LimitTooLow {
                limit,
                has,
                needs,
                needed_for: "the traversal kernels",
            });
        }
        let textures_ok = wl.max_storage_textures_per_shader_stage >= STORAGE_TEXTURES_USED;
        let tuning = match options.tuning {
            Some(t) if t.storage == BvhStorage::Textures && !textures_ok => {
                return Err(GpuError::LimitTooLow {
                    limit: "max_storage_textures_per_shader_stage",
                    has: u64::from(wl.max_storage_textures_per_shader_stage),
                    needs: u64::from(STORAGE_TEXTURES_USED),
                    needed_for: "texture storage (DriverTuning::storage)",
                });
            }
            Some(t) => t,
            None => {
                let mut t = DriverTuning::for_device(device_kind(adapter_info.device_type));
                if !textures_ok {
                    t.storage = BvhStorage::Buffers;
                }
                t
            }
        };
        let limits = DeviceLimits {
            max_storage_buffer_binding_size: (wl.max_storage_buffer_binding_size)
                .min(options.max_binding_bytes.unwrap_or(u64::MAX)),
            max_buffer_size: wl.max_buffer_size,
            max_compute_workgroups_per_dimension: wl.max_compute_workgroups_per_dimension,
            min_storage_buffer_offset_alignment: wl.min_storage_buffer_offset_alignment,
            max_texture_dimension_2d: wl.max_texture_dimension_2d,
            max_storage_buffers_per_shader_stage: wl.max_storage_buffers_per_shader_stage,
        };
        let timestamps = device.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let layout = |label: &str, entries: &[wgpu::BindGroupLayoutEntry]| {
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries,
            })
        };
        let texture_entry = |binding, format| {
            storage_texture_entry(binding, format, wgpu::StorageTextureAccess::ReadOnly)
        };
        let rgba = wgpu::TextureFormat::Rgba32Uint;
        // [buffers, textures] x [escapes or not] x [instances or not] x [masks or not].
        let bvh_layout = |storage: BvhStorage, escapes: bool, instances: bool, masks: bool| {
            let shape = BvhGroupShape {
                storage,
                escapes,
                instances,
                masks,
                pages: Pages::ONE,
            };
            layout(&shape.label(), &shape.entries())
        };
        let bvh_layouts = [BvhStorage::Buffers, BvhStorage::Textures].map(|s| {
            [false, true]
                .map(|e| [false, true].map(|i| [false, true].map(|m| bvh_layout(s, e, i, m))))
        });
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
        Ok(GpuContext {
            inner: Arc::new(Inner {
                device,
                queue,
                info: adapter_info,
                limits,
                tuning,
                composition: options.composition,
                timestamps,
                modules: Default::default(),
                #[cfg(target_arch = "wasm32")]
                deferred: Default::default(),
                bvh_layouts,
                batch_layouts,
                pipelines: Mutex::new(HashMap::new()),
                device_programs: Mutex::new(HashMap::new()),
                modules_compiled: AtomicU64::new(0),
                readbacks: AtomicU64::new(0),
                pipelines_compiled: AtomicU64::new(0),
            }),
        })
    }

    /// The CPU-driver measures in force ([`ContextOptions::tuning`]).
    pub fn tuning(&self) -> &DriverTuning {
        &self.inner.tuning
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
    pub fn limits(&self) -> &DeviceLimits {
        &self.inner.limits
    }

    /// True when GPU times are measured (the device has `TIMESTAMP_QUERY`).
    pub fn has_timestamps(&self) -> bool {
        self.inner.timestamps
    }

    /// True when the device was created with wgpu's `EXPERIMENTAL_RAY_QUERY`, so a
    /// [`crate::RayQueryBvh`] can be uploaded to it ([`ContextOptions::ray_queries`]).
    pub fn has_ray_queries(&self) -> bool {
        self.inner
            .device
            .features()
            .contains(wgpu::Features::EXPERIMENTAL_RAY_QUERY)
    }

    /// The layout of the BVH bind group (group 0 of the kernels; any group of yours, see
    /// [`crate::wgsl_library`]): bindings 0 (nodes) and 1 (triangles), plus 2 (escapes)
    /// when `with_escapes`, as buffers or textures, plus 4 (the instances buffer) when
    /// `with_instances` (a two-level BVH), plus 5 (the alpha masks buffer) when
    /// `with_masks` (`FlatBvh::masks`).
    pub fn bvh_layout(
        &self,
        storage: BvhStorage,
        with_escapes: bool,
        with_instances: bool,
        with_masks: bool,
    ) -> &wgpu::BindGroupLayout {
        &self.inner.bvh_layouts[usize::from(storage == BvhStorage::Textures)]
            [usize::from(with_escapes)][usize::from(with_instances)][usize::from(with_masks)]
    }

    /// [`GpuContext::bvh_layout`] for a BVH group of any shape: a tree split into pages
    /// ([`bvhtrace_engine::pages`]) binds one buffer per page, in a layout made for it
    /// (WebGPU takes layouts with the same entries as one).
    pub(crate) fn bvh_layout_of(&self, shape: BvhGroupShape) -> wgpu::BindGroupLayout {
        if shape.pages.is_one() {
            return (self.bvh_layout(shape.storage, shape.escapes, shape.instances, shape.masks))
                .clone();
        }
        let desc = wgpu::BindGroupLayoutDescriptor {
            label: Some(&shape.label()),
            entries: &shape.entries(),
        };
        self.inner.device.create_bind_group_layout(&desc)
    }

    /// The layout of the batch bind group (group 1): bindings 0 (rays) and 1 (hits) read
    /// from `rays`, plus 2 (counters) when `with_counters`.
    pub(crate) fn batch_layout(
        &self,
        with_counters: bool,
        rays: RayInput,
    ) -> &wgpu::BindGroupLayout {
        let r = usize::from(rays == RayInput::Texture);
        &self.inner.batch_layouts[r][usize::from(with_counters)]
    }

    /// Runs `f` inside validation and out-of-memory error scopes; an error either reported
    /// becomes a [`GpuError`] (in a browser, returned by the next trace). wgpu's error
    /// scopes are per thread (its `std` feature, which this crate enables), so threads
    /// tracing one upload at once do not see each other's.
    pub(crate) fn scoped<T>(
        &self,
        during: &'static str,
        f: impl FnOnce() -> T,
    ) -> Result<T, GpuError> {
        let device = &self.inner.device;
        let oom = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let value = f();
        let (v, o) = (validation.pop(), oom.pop());
        #[cfg(target_arch = "wasm32")]
        {
            // A browser answers on its event loop, which must not be blocked: the next
            // trace awaits the answer.
            let answer = Box::pin(async move { v.await.or(o.await) });
            if let Ok(mut d) = self.inner.deferred.lock() {
                d.push((during, answer));
            }
            Ok(value)
        }
        #[cfg(not(target_arch = "wasm32"))]
        match pollster::block_on(v).or(pollster::block_on(o)) {
            None => Ok(value),
            Some(e) => Err(scope_error(during, e)),
        }
    }

    /// The first error of the work done since the last call, in a browser, where error
    /// scopes answer on the event loop (shader compilation by the browser's compiler,
    /// uploads, submissions); natively [`GpuContext::scoped`] has reported them already.
    pub(crate) async fn deferred_errors(&self) -> Result<(), GpuError> {
        #[cfg(target_arch = "wasm32")]
        {
            let scopes = match self.inner.deferred.lock() {
                Ok(mut d) => std::mem::take(&mut *d),
                Err(_) => Vec::new(),
            };
            let mut first = None;
            for (during, answer) in scopes {
                if let Some(e) = answer.await {
                    first.get_or_insert(scope_error(during, e));
                }
            }
            if let Some(e) = first {
                return Err(e);
            }
        }
        Ok(())
    }

    /// What this device leaves out, one line each: texture storage without enough
    /// storage-texture bindings (the BVH then goes to buffers), the f64 triangle test
    /// without `SHADER_F64`, GPU timings without `TIMESTAMP_QUERY` (traces report wall
    /// time only). Empty when nothing is left out; what a front end or page shows.
    pub fn left_out(&self) -> Vec<String> {
        let features = self.features();
        let mut out = Vec::new();
        if !features.textures {
            let has = self
                .inner
                .device
                .limits()
                .max_storage_textures_per_shader_stage;
            out.push(format!(
                "texture storage: {has} storage textures per shader stage, {STORAGE_TEXTURES_USED} \
                 needed (the BVH goes to storage buffers)"
            ));
        }
        if !features.f64 {
            out.push("the f64 triangle test: no SHADER_F64".to_string());
        }
        if !self.inner.timestamps {
            out.push("GPU timings: no TIMESTAMP_QUERY (traces report wall time only)".into());
        }
        out
    }

    /// True when kernels with this triangle test can run on this device (f64 needs
    /// `SHADER_F64`, which [`GpuContext::new`] requests whenever the adapter has it).
    pub fn supports_precision(&self, precision: Precision) -> bool {
        !precision.needs_f64() || self.features().f64
    }

    /// What the kernels can read on this device: textures with enough storage-texture
    /// bindings, vertex attributes, f64 with `SHADER_F64`.
    pub fn features(&self) -> BackendFeatures {
        let device = &self.inner.device;
        BackendFeatures {
            textures: device.limits().max_storage_textures_per_shader_stage
                >= STORAGE_TEXTURES_USED,
            vertex_attributes: true,
            f64: device.features().contains(wgpu::Features::SHADER_F64),
        }
    }

    /// How the pipelines are composed ([`ContextOptions::composition`]).
    pub fn composition(&self) -> Composition {
        self.inner.composition
    }

    /// `(shader modules, pipelines)` created by this context so far: cache hits do not
    /// count, so a test can check that switching back to a feature set does not recompile.
    /// A benchmark hook: only with the `bench-hooks` feature (off by default).
    #[cfg(feature = "bench-hooks")]
    pub fn compile_counts(&self) -> (u64, u64) {
        (
            self.inner.modules_compiled.load(Ordering::Relaxed),
            self.inner.pipelines_compiled.load(Ordering::Relaxed),
        )
    }

    /// Readbacks made through this context so far: each wait for buffers mapped for
    /// reading (a trace's hits, a device build's tree, [`GpuContext::read_buffers`]) counts
    /// one. What a renderer checks to keep its steady frames free of them.
    pub fn readbacks(&self) -> u64 {
        self.inner.readbacks.load(Ordering::Relaxed)
    }

    pub(crate) fn count_readback(&self) {
        self.inner.readbacks.fetch_add(1, Ordering::Relaxed);
    }

    /// Copies the whole of each of `buffers` (each with `COPY_SRC`) to a mappable buffer
    /// after the work submitted so far, and reads them (one readback, counted by
    /// [`GpuContext::readbacks`]). `during` names the step in an error. Blocks: in a
    /// browser use [`GpuContext::read_buffers_async`].
    pub fn read_buffers(
        &self,
        during: &'static str,
        buffers: &[&wgpu::Buffer],
    ) -> Result<Vec<Vec<u8>>, GpuError> {
        pollster::block_on(self.read_buffers_async(during, buffers))
    }

    /// [`GpuContext::read_buffers`] as a future (what a page awaits).
    pub async fn read_buffers_async(
        &self,
        during: &'static str,
        buffers: &[&wgpu::Buffer],
    ) -> Result<Vec<Vec<u8>>, GpuError> {
        let encoder = self
            .device()
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("bvhtrace read back"),
            });
        let reads: Vec<(&wgpu::Buffer, u64)> = buffers.iter().map(|b| (*b, b.size())).collect();
        crate::build::read_after_async(self, during, encoder, &reads).await
    }

    /// A device builder's pipelines, in [`crate::GpuBuilderKind::entries`] order, compiled
    /// on first use.
    pub(crate) fn build_pipelines(
        &self,
        kind: crate::GpuBuilderKind,
    ) -> Result<Vec<wgpu::ComputePipeline>, GpuError> {
        let entries: Vec<&'static str> = kind.entries().collect();
        self.device_program(kind.name(), || kind.source(), &entries)
    }

    /// The pipelines of one of the device's own programs (a builder, the refit) called
    /// `name`: module `source`, one pipeline per entry point in `entries`' order, compiled
    /// on first use and kept.
    pub(crate) fn device_program(
        &self,
        name: &str,
        source: impl FnOnce() -> String,
        entries: &[&'static str],
    ) -> Result<Vec<wgpu::ComputePipeline>, GpuError> {
        let mut cached = self
            .inner
            .device_programs
            .lock()
            .map_err(|_| GpuError::Poisoned("device programs"))?;
        if let Some(p) = cached.get(name) {
            return Ok(p.clone());
        }
        let device = &self.inner.device;
        let made = self.scoped("compiling a device program", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(source().into()),
            });
            entries
                .iter()
                .map(|&entry| {
                    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                        label: Some(entry),
                        layout: None,
                        module: &module,
                        entry_point: Some(entry),
                        compilation_options: Default::default(),
                        cache: None,
                    })
                })
                .collect::<Vec<_>>()
        })?;
        cached.insert(name.to_string(), made.clone());
        Ok(made)
    }

    fn module(&self, set: &ModuleSet) -> Result<wgpu::ShaderModule, GpuError> {
        if let Some(m) = self.inner.modules.lock().map_err(|_| poisoned())?.get(set) {
            return Ok(m.clone());
        }
        let source = set.compose(bvhtrace_engine::compose::BVH_GROUP);
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

    /// The compute pipeline for `key` (composed as [`GpuContext::composition`] says),
    /// created on first use and cached by its key. Its layout binds what the entry point
    /// reads: the escape links only for the walks that read them, counters only when on.
    pub(crate) fn pipeline(&self, key: KernelKey) -> Result<wgpu::ComputePipeline, GpuError> {
        let key = key.with_composition(self.composition());
        if let Some(p) = self
            .inner
            .pipelines
            .lock()
            .map_err(|_| poisoned())?
            .get(&key)
        {
            return Ok(p.clone());
        }
        let module = self.module(&key.module_set())?;
        let device = &self.inner.device;
        let mut constants = key.constants();
        constants.extend(self.inner.tuning.constants());
        let pipeline = self.scoped("creating a trace pipeline", || {
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("bvhtrace trace"),
                bind_group_layouts: &[
                    Some(&self.bvh_layout_of(BvhGroupShape {
                        storage: key.storage,
                        escapes: key.needs_escapes(),
                        instances: key.instances,
                        masks: key.masks,
                        pages: key.pages,
                    })),
                    Some(self.batch_layout(key.counters, key.rays)),
                ],
                immediate_size: 0,
            });
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(key.entry_point()),
                layout: Some(&layout),
                module: &module,
                entry_point: Some(key.entry_point()),
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
            .insert(key, pipeline.clone());
        Ok(pipeline)
    }
}

fn poisoned() -> GpuError {
    GpuError::Poisoned("pipeline cache")
}
