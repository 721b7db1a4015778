//! The Vulkan instance and device, the kernels translated to SPIR-V, the compute pipelines
//! and the one command buffer everything is submitted through.

use std::collections::HashMap;
use std::ffi::{CStr, CString, c_void};
use std::ptr::NonNull;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use ash::vk;
use bvhtrace_engine::engine::BackendFeatures;
use bvhtrace_engine::pages::{MAX_PAGES, PAGE_BINDING_STRIDE};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::spirv::{self, SpirvTarget};
use bvhtrace_engine::{AdapterChoice, BvhStorage, DeviceKind, DriverTuning, KernelKey, TraceError};

use crate::build::{BuildProgram, destroy_program};
use crate::error::{from_vk, vkerr};

/// Environment variable front ends and tests read to turn on `VK_LAYER_KHRONOS_validation`
/// (`BVHTRACE_VK_VALIDATION=1`, passed on as [`VkOptions::validation`]); the library reads
/// no environment variable.
pub const VALIDATION_ENV: &str = "BVHTRACE_VK_VALIDATION";

/// Validation errors reported to any context of this process, including those reported
/// while a context is destroyed (leaked objects).
static PROCESS_VALIDATION_ERRORS: AtomicU64 = AtomicU64::new(0);

/// Validation errors reported so far to every context of this process, the destroyed ones
/// included (the layer reports leaked objects while a device is destroyed).
pub fn process_validation_errors() -> u64 {
    PROCESS_VALIDATION_ERRORS.load(Ordering::Relaxed)
}

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// How long a submission may take before the tracer gives up (10 minutes: lavapipe is slow
/// on big batches).
const FENCE_TIMEOUT_NS: u64 = 600_000_000_000;

/// Options of [`VkContext::with_options`].
#[derive(Clone, Debug, Default)]
pub struct VkOptions {
    /// Which device to open: [`AdapterChoice::Auto`] (the best device: discrete >
    /// integrated > virtual > CPU) or
    /// [`AdapterChoice::Named`] (a case-insensitive substring of the device name). The
    /// same choice as the wgpu backend's for the same list of devices.
    pub adapter: AdapterChoice,
    /// Enable `VK_LAYER_KHRONOS_validation` when it is installed (ignored otherwise; see
    /// [`VkContext::validation_enabled`]).
    pub validation: bool,
    /// The CPU-driver measures (`TRIP_LIMIT`, `DISPATCH_THREADS`, finishing rays on the
    /// CPU); `None` picks [`DriverTuning::for_device`] for the device's kind. This backend
    /// reads the BVH and the rays from storage buffers only, so
    /// [`DriverTuning::storage`] is always [`BvhStorage::Buffers`] here, whatever is given.
    pub tuning: Option<DriverTuning>,
    /// The largest storage binding the tracer makes, when below the device's own (`None`:
    /// the device's): a tree larger than it is split into pages of at most this size
    /// (`bvhtrace_engine::pages`), as on a device with that limit. To test the split on
    /// small scenes, or a browser's 128 MiB bindings natively.
    pub max_binding_bytes: Option<u64>,
}

/// The chosen device's description.
#[derive(Clone, Debug)]
pub struct VkDeviceInfo {
    /// `deviceName`.
    pub name: String,
    /// `deviceType`.
    pub device_type: vk::PhysicalDeviceType,
    /// `deviceType` as the backend-neutral kind ([`device_kind`]).
    pub kind: DeviceKind,
    /// `apiVersion`, as `(major, minor, patch)`.
    pub api_version: (u32, u32, u32),
    /// `driverVersion` (vendor-specific encoding).
    pub driver_version: u32,
}

/// A Vulkan device ready to trace: cheap to clone (shared), destroyed with its last clone
/// and the last [`crate::VkBvh`] uploaded on it.
#[derive(Clone)]
pub struct VkContext {
    pub(crate) inner: Arc<Inner>,
}

impl std::fmt::Debug for VkContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VkContext")
            .field("device", &self.inner.info.name)
            .field("limits", &self.inner.limits)
            .field("tuning", &self.inner.tuning)
            .field("timestamps", &self.inner.timestamp_period_ns.is_some())
            .field("validation", &self.inner.instance.debug.is_some())
            .finish()
    }
}

/// Entry, instance and debug messenger; destroyed after everything made from the device.
pub(crate) struct InstanceHolder {
    _entry: ash::Entry,
    pub(crate) instance: ash::Instance,
    debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    /// Validation messages of severity error; read through the messenger's user pointer,
    /// so boxed (stable address) and alive until the messenger is destroyed.
    errors: Box<AtomicU64>,
}

impl Drop for InstanceHolder {
    fn drop(&mut self) {
        // SAFETY: every object created from this instance (the device and its children) is
        // destroyed by `Inner::drop`, which runs before this field is dropped.
        unsafe {
            if let Some((loader, messenger)) = self.debug.take() {
                loader.destroy_debug_utils_messenger(messenger, None);
            }
            self.instance.destroy_instance(None);
        }
    }
}

/// The device [`VkContext::choose`] picked: its properties and compute queue family.
struct Chosen {
    pd: vk::PhysicalDevice,
    props: vk::PhysicalDeviceProperties,
    family: u32,
    family_props: vk::QueueFamilyProperties,
    name: String,
    kind: DeviceKind,
}

/// The command buffer, its fence and the timestamp pool, used one submission at a time.
pub(crate) struct Submitter {
    pub(crate) pool: vk::CommandPool,
    pub(crate) cmd: vk::CommandBuffer,
    pub(crate) fence: vk::Fence,
    pub(crate) queries: vk::QueryPool,
}

pub(crate) struct Inner {
    pub(crate) device: ash::Device,
    pub(crate) queue: vk::Queue,
    pub(crate) info: VkDeviceInfo,
    pub(crate) limits: DeviceLimits,
    /// Nanoseconds per timestamp tick, when the compute queue has timestamps.
    pub(crate) timestamp_period_ns: Option<f64>,
    pub(crate) timestamp_mask: u64,
    memory: vk::PhysicalDeviceMemoryProperties,
    /// The SPIR-V version, and whether naga may skip its buffer bounds checks
    /// (robustBufferAccess2 is on), as wgpu does.
    pub(crate) spirv: SpirvTarget,
    /// `maxPerStageDescriptorStorageBuffers`.
    pub(crate) storage_buffers_per_stage: u32,
    /// `shaderZeroInitializeWorkgroupMemory` is enabled: the device zeroes workgroup
    /// memory (else the programs that need it zeroed do it themselves).
    pub(crate) zero_workgroup: bool,
    /// `TRIP_LIMIT`, `DISPATCH_THREADS` and whether rays are finished on the CPU (storage
    /// is always buffers).
    tuning: DriverTuning,
    /// `shaderFloat64` is enabled (the f64 triangle test can run).
    float64: bool,
    pub(crate) set_layouts: [vk::DescriptorSetLayout; 2],
    /// The binding numbers of each set layout (set 0: the tree, with a slot per page of
    /// each array that may be split; set 1: the batch).
    pub(crate) set_bindings: [Vec<u32>; 2],
    pub(crate) pipeline_layout: vk::PipelineLayout,
    pipelines: Mutex<HashMap<KernelKey, vk::Pipeline>>,
    /// The device builders' programs, by builder name.
    pub(crate) build_programs: Mutex<HashMap<&'static str, Arc<BuildProgram>>>,
    pub(crate) submitter: Mutex<Submitter>,
    // Dropped last (after `Drop::drop` above destroyed the device).
    pub(crate) instance: InstanceHolder,
}

impl Drop for Inner {
    fn drop(&mut self) {
        // SAFETY: all handles were created from this device; null handles (objects never
        // created because construction failed half way) are ignored by vkDestroy*. Every
        // `VkBvh` holds an `Arc<Inner>`, so none of their objects outlives the device.
        unsafe {
            let d = &self.device;
            let _ = d.device_wait_idle();
            if let Ok(p) = self.pipelines.get_mut() {
                for (_, pipeline) in p.drain() {
                    d.destroy_pipeline(pipeline, None);
                }
            }
            if let Ok(p) = self.build_programs.get_mut() {
                for (_, program) in p.drain() {
                    destroy_program(d, &program);
                }
            }
            let s = match self.submitter.get_mut() {
                Ok(s) => s,
                Err(e) => e.into_inner(),
            };
            d.destroy_query_pool(s.queries, None);
            d.destroy_fence(s.fence, None);
            d.destroy_command_pool(s.pool, None);
            d.destroy_pipeline_layout(self.pipeline_layout, None);
            for l in self.set_layouts {
                d.destroy_descriptor_set_layout(l, None);
            }
            d.destroy_device(None);
        }
    }
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the layer passes valid callback data; `user` is the `AtomicU64` boxed in the
    // `InstanceHolder`, which outlives the messenger.
    unsafe {
        let message = data
            .as_ref()
            .and_then(|d| d.message_as_c_str())
            .map(|m| m.to_string_lossy().into_owned())
            .unwrap_or_default();
        if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR) {
            if let Some(count) = (user as *const AtomicU64).as_ref() {
                count.fetch_add(1, Ordering::Relaxed);
            }
            PROCESS_VALIDATION_ERRORS.fetch_add(1, Ordering::Relaxed);
            eprintln!("bvhtrace-vk validation error: {message}");
        } else if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::WARNING) {
            eprintln!("bvhtrace-vk validation warning: {message}");
        }
    }
    vk::FALSE
}

/// Vulkan's device type as the backend-neutral [`DeviceKind`] that
/// [`AdapterChoice::pick`] ranks and [`DriverTuning::for_device`] tunes for, so both
/// backends choose (and tune for) the same device for the same name or environment.
pub fn device_kind(t: vk::PhysicalDeviceType) -> DeviceKind {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => DeviceKind::DiscreteGpu,
        vk::PhysicalDeviceType::INTEGRATED_GPU => DeviceKind::IntegratedGpu,
        vk::PhysicalDeviceType::VIRTUAL_GPU => DeviceKind::VirtualGpu,
        vk::PhysicalDeviceType::CPU => DeviceKind::Cpu,
        _ => DeviceKind::Other,
    }
}

impl VkContext {
    /// Opens the device `choice` selects ([`AdapterChoice::Auto`]: the best one,
    /// discrete > integrated > virtual > CPU;
    /// [`AdapterChoice::Named`]: the first whose name contains the substring, any case):
    /// the same choice as `bvhtrace_gpu::GpuContext::new`, with the [`DriverTuning`] for
    /// its kind. Validation is off: turn it on with [`VkOptions::validation`] (front ends and
    /// tests may read [`VALIDATION_ENV`] for it; the library reads no environment variable).
    ///
    /// Fails with [`TraceError::NoAdapter`] when there is no Vulkan loader, driver or
    /// device with a compute queue, and [`TraceError::AdapterNotFound`] when no device
    /// has the name asked for; never panics.
    pub fn new(choice: AdapterChoice) -> Result<VkContext, TraceError> {
        Self::with_options(&VkOptions {
            adapter: choice,
            validation: false,
            tuning: None,
            max_binding_bytes: None,
        })
    }

    /// [`VkContext::new`] with explicit options.
    pub fn with_options(opts: &VkOptions) -> Result<VkContext, TraceError> {
        // SAFETY: loading libvulkan runs its initialisers; that is what a Vulkan
        // application does. All later calls use handles created here, on this instance.
        unsafe { Self::create(opts) }
    }

    /// The context: instance, device, then its objects, as `opts` says.
    ///
    /// # Safety
    /// Loads libvulkan and runs its initialisers: call it where any Vulkan application may
    /// (no other thread unloading the library). Everything made is owned by the context.
    unsafe fn create(opts: &VkOptions) -> Result<VkContext, TraceError> {
        // SAFETY: each step uses only the handles the one before made.
        unsafe {
            let holder = Self::instance(opts)?;
            let chosen = Self::choose(&holder.instance, &opts.adapter)?;
            let family = chosen.family;
            let mut inner = Self::open(holder, chosen, opts)?;
            Self::objects(&mut inner, family)?;
            Ok(VkContext {
                inner: Arc::new(inner),
            })
        }
    }

    /// The instance, with the validation layer and its messenger when asked for and
    /// installed.
    ///
    /// # Safety
    /// As [`VkContext::create`]: loads libvulkan. The holder destroys the messenger and
    /// the instance when dropped, after everything made from them.
    unsafe fn instance(opts: &VkOptions) -> Result<InstanceHolder, TraceError> {
        unsafe {
            let entry = ash::Entry::load().map_err(|e| TraceError::NoAdapter {
                details: format!(": cannot load libvulkan: {e}"),
            })?;
            let layers = entry
                .enumerate_instance_layer_properties()
                .map_err(vkerr("listing instance layers"))?;
            let has_validation = layers
                .iter()
                .any(|l| l.layer_name_as_c_str().is_ok_and(|n| n == VALIDATION_LAYER));
            let validation = opts.validation && has_validation;
            if opts.validation && !has_validation {
                eprintln!(
                    "bvhtrace-vk: {} is not installed; running without validation",
                    VALIDATION_LAYER.to_string_lossy()
                );
            }
            let app = vk::ApplicationInfo::default()
                .application_name(c"bvhtrace")
                .api_version(vk::API_VERSION_1_2);
            let layer_names = [VALIDATION_LAYER.as_ptr()];
            let ext_names = [ash::ext::debug_utils::NAME.as_ptr()];
            let mut ci = vk::InstanceCreateInfo::default().application_info(&app);
            if validation {
                ci = ci
                    .enabled_layer_names(&layer_names)
                    .enabled_extension_names(&ext_names);
            }
            let instance = match entry.create_instance(&ci, None) {
                Ok(i) => i,
                Err(vk::Result::ERROR_INCOMPATIBLE_DRIVER) => {
                    return Err(TraceError::NoAdapter {
                        details: " (the loader found no compatible driver)".into(),
                    });
                }
                Err(e) => return Err(from_vk("creating the Vulkan instance", e)),
            };
            let mut holder = InstanceHolder {
                _entry: entry.clone(),
                instance,
                debug: None,
                errors: Box::new(AtomicU64::new(0)),
            };
            if validation {
                let loader = ash::ext::debug_utils::Instance::new(&entry, &holder.instance);
                let info = vk::DebugUtilsMessengerCreateInfoEXT::default()
                    .message_severity(
                        vk::DebugUtilsMessageSeverityFlagsEXT::ERROR
                            | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING,
                    )
                    .message_type(
                        vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                            | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                            | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
                    )
                    .pfn_user_callback(Some(debug_callback))
                    .user_data(&*holder.errors as *const AtomicU64 as *mut c_void);
                let messenger = loader
                    .create_debug_utils_messenger(&info, None)
                    .map_err(vkerr("creating the validation messenger"))?;
                holder.debug = Some((loader, messenger));
            }
            Ok(holder)
        }
    }

    /// The device `adapter` picks among those with a compute queue.
    ///
    /// # Safety
    /// `instance` is a live instance; the physical device returned is only used while it
    /// lives.
    unsafe fn choose(
        instance: &ash::Instance,
        adapter: &AdapterChoice,
    ) -> Result<Chosen, TraceError> {
        unsafe {
            // Devices with a compute queue, described for `AdapterChoice::pick`.
            let mut candidates = Vec::new();
            let devices = instance
                .enumerate_physical_devices()
                .map_err(vkerr("listing Vulkan devices"))?;
            for &pd in &devices {
                let props = instance.get_physical_device_properties(pd);
                let families = instance.get_physical_device_queue_family_properties(pd);
                let compute =
                    |f: &vk::QueueFamilyProperties| f.queue_flags.contains(vk::QueueFlags::COMPUTE);
                let Some(family) = families.iter().position(compute) else {
                    continue;
                };
                let name = props.device_name_as_c_str().map(|n| n.to_string_lossy());
                candidates.push(Chosen {
                    pd,
                    props,
                    family: family as u32,
                    family_props: families[family],
                    name: name.unwrap_or_default().into_owned(),
                    kind: device_kind(props.device_type),
                });
            }
            if candidates.is_empty() {
                let n = devices.len();
                return Err(TraceError::NoAdapter {
                    details: match n {
                        0 => String::new(),
                        _ => format!(" ({n} Vulkan device(s), none with a compute queue)"),
                    },
                });
            }
            let named: Vec<(String, DeviceKind)> = candidates
                .iter()
                .map(|c| (c.name.clone(), c.kind))
                .collect();
            let index = adapter.pick(&named)?;
            Ok(candidates.swap_remove(index))
        }
    }

    /// The logical device on `c` with the features the kernels use, its limits and
    /// tuning; no objects yet.
    ///
    /// # Safety
    /// `c` was chosen on `holder`'s instance ([`VkContext::choose`]); the device made is
    /// owned by the returned [`Inner`], which destroys it before the instance.
    unsafe fn open(
        holder: InstanceHolder,
        c: Chosen,
        opts: &VkOptions,
    ) -> Result<Inner, TraceError> {
        unsafe {
            let (pd, props, family, kind) = (c.pd, c.props, c.family, c.kind);
            let instance = &holder.instance;
            // Buffers only, and each submission waited for (one command buffer).
            let tuning = DriverTuning {
                storage: BvhStorage::Buffers,
                in_flight: 1,
                ..opts
                    .tuning
                    .unwrap_or_else(|| DriverTuning::for_device(kind))
            };
            let info = VkDeviceInfo {
                name: c.name,
                device_type: props.device_type,
                kind,
                api_version: (
                    vk::api_version_major(props.api_version),
                    vk::api_version_minor(props.api_version),
                    vk::api_version_patch(props.api_version),
                ),
                driver_version: props.driver_version,
            };

            // Features: robustBufferAccess2 as wgpu uses it, f64 if a kernel wants it.
            let exts = instance
                .enumerate_device_extension_properties(pd)
                .map_err(vkerr("listing device extensions"))?;
            let has_ext = |name: &CStr| {
                exts.iter()
                    .any(|e| e.extension_name_as_c_str().is_ok_and(|n| n == name))
            };
            let mut robust2_query = vk::PhysicalDeviceRobustness2FeaturesEXT::default();
            let robust2 = if has_ext(ash::ext::robustness2::NAME) {
                let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut robust2_query);
                instance.get_physical_device_features2(pd, &mut f2);
                robust2_query.robust_buffer_access2 == vk::TRUE
            } else {
                false
            };
            // The device zeroes workgroup memory itself (the builders' programs need it
            // zeroed, as WGSL says): cheaper than naga's polyfill, as wgpu does.
            let zero_ext = ash::khr::zero_initialize_workgroup_memory::NAME;
            let mut zero_query = vk::PhysicalDeviceZeroInitializeWorkgroupMemoryFeatures::default();
            let zero_workgroup = has_ext(zero_ext) && {
                let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut zero_query);
                instance.get_physical_device_features2(pd, &mut f2);
                zero_query.shader_zero_initialize_workgroup_memory == vk::TRUE
            };
            let supported = instance.get_physical_device_features(pd);
            let features = vk::PhysicalDeviceFeatures::default()
                .robust_buffer_access(supported.robust_buffer_access == vk::TRUE)
                .shader_float64(supported.shader_float64 == vk::TRUE)
                .shader_int64(supported.shader_int64 == vk::TRUE);
            let mut robust2_enable =
                vk::PhysicalDeviceRobustness2FeaturesEXT::default().robust_buffer_access2(true);
            let mut zero_enable =
                vk::PhysicalDeviceZeroInitializeWorkgroupMemoryFeatures::default()
                    .shader_zero_initialize_workgroup_memory(true);
            let mut dev_exts = Vec::new();
            let priorities = [1.0f32];
            let queue_info = [vk::DeviceQueueCreateInfo::default()
                .queue_family_index(family)
                .queue_priorities(&priorities)];
            let mut dci = vk::DeviceCreateInfo::default()
                .queue_create_infos(&queue_info)
                .enabled_features(&features);
            let robust2 = robust2 && supported.robust_buffer_access == vk::TRUE;
            if robust2 {
                dev_exts.push(ash::ext::robustness2::NAME.as_ptr());
                dci = dci.push_next(&mut robust2_enable);
            }
            if zero_workgroup {
                dev_exts.push(zero_ext.as_ptr());
                dci = dci.push_next(&mut zero_enable);
            }
            dci = dci.enabled_extension_names(&dev_exts);
            let device = instance
                .create_device(pd, &dci, None)
                .map_err(vkerr("creating the Vulkan device"))?;
            let queue = device.get_device_queue(family, 0);
            let l = &props.limits;
            // One buffer lives in one allocation: maxMemoryAllocationSize (Vulkan 1.1);
            // Vulkan 1.0 states none, and 2^32 - 1 bytes is safe on every implementation.
            let max_allocation = if props.api_version >= vk::API_VERSION_1_1 {
                let mut m3 = vk::PhysicalDeviceMaintenance3Properties::default();
                let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut m3);
                instance.get_physical_device_properties2(pd, &mut p2);
                m3.max_memory_allocation_size
            } else {
                u64::from(u32::MAX)
            };
            let limits = DeviceLimits {
                max_storage_buffer_binding_size: u64::from(l.max_storage_buffer_range)
                    .min(opts.max_binding_bytes.unwrap_or(u64::MAX)),
                max_buffer_size: max_allocation,
                max_compute_workgroups_per_dimension: l.max_compute_work_group_count[0]
                    .min(l.max_compute_work_group_count[1]),
                min_storage_buffer_offset_alignment: l.min_storage_buffer_offset_alignment as u32,
                max_texture_dimension_2d: l.max_image_dimension2_d,
                max_storage_buffers_per_shader_stage: l.max_per_stage_descriptor_storage_buffers,
            };
            // `timestampValidBits` is 0 on queues without timestamps (whatever
            // `timestampComputeAndGraphics` says for the device as a whole).
            let timestamps = c.family_props.timestamp_valid_bits > 0 && l.timestamp_period > 0.0;
            let timestamp_mask = match c.family_props.timestamp_valid_bits {
                0 => 0,
                64.. => u64::MAX,
                b => (1u64 << b) - 1,
            };
            let spirv = SpirvTarget::for_vulkan(info.api_version.0, info.api_version.1, robust2);
            let memory = instance.get_physical_device_memory_properties(pd);

            // From here on, dropping `inner` destroys whatever was created.
            let inner = Inner {
                device,
                queue,
                info,
                limits,
                timestamp_period_ns: timestamps.then_some(f64::from(l.timestamp_period)),
                timestamp_mask,
                memory,
                spirv,
                storage_buffers_per_stage: l.max_per_stage_descriptor_storage_buffers,
                zero_workgroup,
                tuning,
                float64: supported.shader_float64 == vk::TRUE,
                set_layouts: [vk::DescriptorSetLayout::null(); 2],
                set_bindings: [Vec::new(), Vec::new()],
                pipeline_layout: vk::PipelineLayout::null(),
                pipelines: Mutex::new(HashMap::new()),
                build_programs: Mutex::new(HashMap::new()),
                submitter: Mutex::new(Submitter {
                    pool: vk::CommandPool::null(),
                    cmd: vk::CommandBuffer::null(),
                    fence: vk::Fence::null(),
                    queries: vk::QueryPool::null(),
                }),
                instance: holder,
            };
            Ok(inner)
        }
    }

    /// The descriptor set layouts, pipeline layout, command buffer, fence and timestamp
    /// queries of `inner` (dropping `inner` destroys whatever was made).
    ///
    /// # Safety
    /// `inner`'s device is live, with a queue of `family`, and none of these objects is
    /// made yet (each is written once, over its null handle).
    unsafe fn objects(inner: &mut Inner, family: u32) -> Result<(), TraceError> {
        let timestamps = inner.timestamp_period_ns.is_some();
        unsafe {
            let d = &inner.device;
            // Set 0: nodes, triangles, escapes, instances (4), alpha masks (5). Set 1: rays, hits,
            // counters. The kernels' binding numbers; every binding is always bound
            // (unused ones are not declared in the SPIR-V of an entry point that does not
            // use them).
            inner.set_bindings = [tree_bindings(&inner.limits), vec![0, 1, 2]];
            for set in 0..2 {
                let numbers = &inner.set_bindings[set];
                let bindings: Vec<vk::DescriptorSetLayoutBinding> = numbers
                    .iter()
                    .map(|&b| {
                        vk::DescriptorSetLayoutBinding::default()
                            .binding(b)
                            .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                            .descriptor_count(1)
                            .stage_flags(vk::ShaderStageFlags::COMPUTE)
                    })
                    .collect();
                inner.set_layouts[set] = d
                    .create_descriptor_set_layout(
                        &vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings),
                        None,
                    )
                    .map_err(vkerr("creating descriptor set layouts"))?;
            }
            inner.pipeline_layout = d
                .create_pipeline_layout(
                    &vk::PipelineLayoutCreateInfo::default().set_layouts(&inner.set_layouts),
                    None,
                )
                .map_err(vkerr("creating the pipeline layout"))?;
            let s = inner
                .submitter
                .get_mut()
                .map_err(|_| TraceError::Poisoned("submitter"))?;
            s.pool = d
                .create_command_pool(
                    &vk::CommandPoolCreateInfo::default()
                        .queue_family_index(family)
                        .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                    None,
                )
                .map_err(vkerr("creating the command pool"))?;
            s.cmd = d
                .allocate_command_buffers(
                    &vk::CommandBufferAllocateInfo::default()
                        .command_pool(s.pool)
                        .level(vk::CommandBufferLevel::PRIMARY)
                        .command_buffer_count(1),
                )
                .map_err(vkerr("allocating the command buffer"))?[0];
            s.fence = d
                .create_fence(&vk::FenceCreateInfo::default(), None)
                .map_err(vkerr("creating the fence"))?;
            if timestamps {
                s.queries = d
                    .create_query_pool(
                        &vk::QueryPoolCreateInfo::default()
                            .query_type(vk::QueryType::TIMESTAMP)
                            .query_count(2),
                        None,
                    )
                    .map_err(vkerr("creating the timestamp query pool"))?;
            }

            Ok(())
        }
    }

    /// The most pages of one array the tree's set binds ([`bvhtrace_engine::pages`]).
    pub(crate) fn page_slots(&self) -> u8 {
        page_slots(&self.inner.limits)
    }

    /// The device's description.
    pub fn device_info(&self) -> &VkDeviceInfo {
        &self.inner.info
    }

    /// The limits the tracer works within (the backend-neutral [`DeviceLimits`] the wgpu
    /// path uses too, filled from `VkPhysicalDeviceLimits`).
    pub fn limits(&self) -> &DeviceLimits {
        &self.inner.limits
    }

    /// True when dispatch times are measured with timestamp queries.
    pub fn has_timestamps(&self) -> bool {
        self.inner.timestamp_period_ns.is_some()
    }

    /// True when `VK_LAYER_KHRONOS_validation` is active on this context.
    pub fn validation_enabled(&self) -> bool {
        self.inner.instance.debug.is_some()
    }

    /// Validation errors reported so far (0 when validation is off).
    pub fn validation_errors(&self) -> u64 {
        self.inner.instance.errors.load(Ordering::Relaxed)
    }

    /// The CPU-driver measures the pipelines get ([`DriverTuning::constants`]:
    /// `TRIP_LIMIT`, `DISPATCH_THREADS`) and whether uploads keep a host copy to finish
    /// rays that spend the trip budget ([`DriverTuning::finishes_on_cpu`]): what
    /// [`VkOptions::tuning`] gave, else [`DriverTuning::for_device`] for the device's kind,
    /// always with [`BvhStorage::Buffers`].
    pub fn tuning(&self) -> &DriverTuning {
        &self.inner.tuning
    }

    /// What the kernels can read on this device: storage buffers only, no vertex
    /// attributes; f64 with `shaderFloat64` (which [`VkContext::new`] enables whenever the
    /// device has it).
    pub fn features(&self) -> BackendFeatures {
        BackendFeatures {
            textures: false,
            vertex_attributes: false,
            f64: self.inner.float64,
        }
    }

    /// The SPIR-V words of `key`'s kernel for this device, with this context's tuning
    /// ([`bvhtrace_engine::spirv::kernel`]), when [`VkContext::features`] allow it.
    pub fn spirv(&self, key: KernelKey) -> Result<Vec<u32>, TraceError> {
        self.features()
            .check(&key, || self.inner.info.name.clone())?;
        spirv::kernel(&key, &self.inner.tuning, &self.inner.spirv)
    }

    /// The compute pipeline of one kernel key, created on first use and cached.
    pub(crate) fn pipeline(&self, key: KernelKey) -> Result<vk::Pipeline, TraceError> {
        let mut cache = self
            .inner
            .pipelines
            .lock()
            .map_err(|_| TraceError::Poisoned("pipeline cache"))?;
        if let Some(p) = cache.get(&key) {
            return Ok(*p);
        }
        let words = self.spirv(key)?;
        // SAFETY: `words` is SPIR-V from naga's validated module, the layout this device's.
        let pipeline = unsafe {
            compute_pipeline(
                &self.inner.device,
                &words,
                key.entry_point(),
                self.inner.pipeline_layout,
            )?
        };
        cache.insert(key, pipeline);
        Ok(pipeline)
    }

    /// Locks the command buffer for one submission.
    pub(crate) fn submitter(&self) -> Result<MutexGuard<'_, Submitter>, TraceError> {
        self.inner
            .submitter
            .lock()
            .map_err(|_| TraceError::Poisoned("command buffer"))
    }

    /// Records with `record` into the command buffer, submits, and waits for completion.
    pub(crate) fn submit_and_wait(
        &self,
        s: &Submitter,
        during: &'static str,
        record: impl FnOnce(&ash::Device, vk::CommandBuffer),
    ) -> Result<(), TraceError> {
        let d = &self.inner.device;
        // SAFETY: the command buffer and fence belong to this device and are not in use
        // (the previous submission was waited for; the submitter lock is held).
        unsafe {
            d.reset_command_buffer(s.cmd, vk::CommandBufferResetFlags::empty())
                .map_err(vkerr(during))?;
            d.begin_command_buffer(
                s.cmd,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .map_err(vkerr(during))?;
            record(d, s.cmd);
            d.end_command_buffer(s.cmd).map_err(vkerr(during))?;
            let cmds = [s.cmd];
            let submit = [vk::SubmitInfo::default().command_buffers(&cmds)];
            d.queue_submit(self.inner.queue, &submit, s.fence)
                .map_err(vkerr(during))?;
            let waited = d.wait_for_fences(&[s.fence], true, FENCE_TIMEOUT_NS);
            // Reset even after a failure, so the next submission starts clean.
            let reset = d.reset_fences(&[s.fence]);
            match waited {
                Err(vk::Result::TIMEOUT) => {
                    // The fence may still signal: wait for the queue before reusing it.
                    let _ = d.queue_wait_idle(self.inner.queue);
                    let _ = d.reset_fences(&[s.fence]);
                    return Err(TraceError::Device {
                        during,
                        message: format!(
                            "the submission did not finish within {} s (vkWaitForFences \
                             returned VK_TIMEOUT)",
                            FENCE_TIMEOUT_NS / 1_000_000_000
                        ),
                    });
                }
                Err(e) => return Err(from_vk(during, e)),
                Ok(()) => {}
            }
            reset.map_err(vkerr(during))?;
        }
        Ok(())
    }

    /// Creates a buffer with its own memory: `required` memory properties, `preferred`
    /// ones when some memory type has them too; host-visible buffers stay mapped.
    pub(crate) fn buffer(
        &self,
        label: &'static str,
        size: u64,
        usage: vk::BufferUsageFlags,
        required: vk::MemoryPropertyFlags,
        preferred: vk::MemoryPropertyFlags,
    ) -> Result<Buffer, TraceError> {
        let d = &self.inner.device;
        let size = size.max(16);
        let info = vk::BufferCreateInfo::default()
            .size(size)
            .usage(usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: plain object creation on this device; on failure, dropping `b` destroys
        // what was made (freeing null memory is a no-op).
        unsafe {
            let mut b = Buffer {
                ctx: self.clone(),
                raw: d
                    .create_buffer(&info, None)
                    .map_err(vkerr("creating a buffer"))?,
                memory: vk::DeviceMemory::null(),
                size,
                mapped: None,
            };
            let req = d.get_buffer_memory_requirements(b.raw);
            let mem = &self.inner.memory;
            let types = &mem.memory_types[..mem.memory_type_count as usize];
            let fits = |i: usize, flags: vk::MemoryPropertyFlags| {
                req.memory_type_bits & (1 << i) != 0 && types[i].property_flags.contains(flags)
            };
            let index = (0..types.len())
                .find(|&i| fits(i, required | preferred))
                .or_else(|| (0..types.len()).find(|&i| fits(i, required)))
                .ok_or_else(|| TraceError::Device {
                    during: "allocating buffer memory",
                    message: format!(
                        "no Vulkan memory type for the {label} buffer has {required:?}"
                    ),
                })?;
            let alloc = vk::MemoryAllocateInfo::default()
                .allocation_size(req.size)
                .memory_type_index(index as u32);
            b.memory = d
                .allocate_memory(&alloc, None)
                .map_err(vkerr("allocating buffer memory"))?;
            d.bind_buffer_memory(b.raw, b.memory, 0)
                .map_err(vkerr("binding buffer memory"))?;
            if required.contains(vk::MemoryPropertyFlags::HOST_VISIBLE) {
                let p = d
                    .map_memory(b.memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty())
                    .map_err(vkerr("mapping buffer memory"))?;
                b.mapped = NonNull::new(p.cast::<u8>());
            }
            Ok(b)
        }
    }
}

/// A compute pipeline of entry point `entry` in SPIR-V `words` with `layout`; the shader
/// module is destroyed right after, and a failure destroys what was made.
///
/// # Safety
/// `words` must be valid SPIR-V with that entry point, and `layout` a pipeline layout of
/// `d` matching its bindings.
pub(crate) unsafe fn compute_pipeline(
    d: &ash::Device,
    words: &[u32],
    entry: &str,
    layout: vk::PipelineLayout,
) -> Result<vk::Pipeline, TraceError> {
    let name = CString::new(entry).map_err(|e| TraceError::Device {
        during: "creating a compute pipeline",
        message: format!("the entry point's name: {e}"),
    })?;
    // SAFETY: the caller's contract; the module lives until the pipeline is made.
    unsafe {
        let module = d
            .create_shader_module(&vk::ShaderModuleCreateInfo::default().code(words), None)
            .map_err(vkerr("creating a shader module"))?;
        let stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::COMPUTE)
            .module(module)
            .name(&name);
        let info = vk::ComputePipelineCreateInfo::default()
            .stage(stage)
            .layout(layout);
        let made = d.create_compute_pipelines(vk::PipelineCache::null(), &[info], None);
        d.destroy_shader_module(module, None);
        match made {
            Ok(p) => Ok(p[0]),
            Err((partial, e)) => {
                for p in partial {
                    d.destroy_pipeline(p, None);
                }
                Err(from_vk("creating a compute pipeline", e))
            }
        }
    }
}

/// Records a global memory barrier: `src` access in `from` stages before `dst` access in
/// `to` stages.
///
/// # Safety
/// `cmd` is recording, on `d`.
pub(crate) unsafe fn barrier(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    (from, src): (vk::PipelineStageFlags, vk::AccessFlags),
    (to, dst): (vk::PipelineStageFlags, vk::AccessFlags),
) {
    let barrier = [vk::MemoryBarrier::default()
        .src_access_mask(src)
        .dst_access_mask(dst)];
    let none = vk::DependencyFlags::empty();
    // SAFETY: the caller's.
    unsafe { d.cmd_pipeline_barrier(cmd, from, to, none, &barrier, &[], &[]) };
}

/// A buffer and its memory (mapped when host-visible), destroyed when dropped.
pub(crate) struct Buffer {
    /// Keeps the device alive until the buffer is destroyed.
    ctx: VkContext,
    pub(crate) raw: vk::Buffer,
    memory: vk::DeviceMemory,
    pub(crate) size: u64,
    mapped: Option<NonNull<u8>>,
}

// SAFETY: the mapping is only read or written by the owner while it holds the context's
// submitter lock or exclusive access; Vulkan handles are plain integers.
unsafe impl Send for Buffer {}
// SAFETY: as above.
unsafe impl Sync for Buffer {}

impl Buffer {
    /// Copies `data` to the start of a mapped (host-coherent) buffer.
    pub(crate) fn write(&self, data: &[u8]) {
        self.write_at(0, data);
    }

    /// Writes `data` into a mapped (host-coherent) buffer from byte `offset` on, as much
    /// as fits.
    pub(crate) fn write_at(&self, offset: u64, data: &[u8]) {
        let Some(p) = self.mapped else { return };
        let n = data.len().min(self.size.saturating_sub(offset) as usize);
        // SAFETY: the mapping covers `size` bytes, `offset + n` of them at most, and no
        // submission touching it is pending.
        unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), p.as_ptr().add(offset as usize), n) };
    }

    /// Copies the mapped (host-coherent) buffer's bytes from `at` into `out`, as many as
    /// both hold.
    pub(crate) fn read_at(&self, at: usize, out: &mut [u8]) {
        let Some(p) = self.mapped else { return };
        let n = out.len().min((self.size as usize).saturating_sub(at));
        // SAFETY: `at + n` is within the mapping's `size` bytes; the GPU finished writing
        // (fence waited).
        unsafe { std::ptr::copy_nonoverlapping(p.as_ptr().add(at), out.as_mut_ptr(), n) };
    }

    /// Appends the first `bytes` bytes of a mapped (host-coherent) buffer to `out` as `T`s.
    pub(crate) fn read_into<T: bytemuck::Pod>(&self, bytes: usize, out: &mut Vec<T>) {
        if self.mapped.is_none() {
            return;
        }
        let n = bytes.min(self.size as usize) / std::mem::size_of::<T>();
        let start = out.len();
        out.resize(start + n, T::zeroed());
        self.read_at(0, bytemuck::cast_slice_mut(&mut out[start..]));
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        let d = &self.ctx.inner.device;
        // SAFETY: created on `d`; no submission using it is pending (every submission is
        // waited for before its call returns).
        unsafe {
            if self.mapped.take().is_some() {
                d.unmap_memory(self.memory);
            }
            d.destroy_buffer(self.raw, None);
            d.free_memory(self.memory, None);
        }
    }
}

/// Pages per split array the tree's set layout has room for: as many as keep the set
/// layout and the batch's within the device's storage buffers per stage, at most
/// [`MAX_PAGES`].
fn page_slots(limits: &DeviceLimits) -> u8 {
    let fixed = 5 + 3;
    let spare = limits
        .max_storage_buffers_per_shader_stage
        .saturating_sub(fixed)
        / 3;
    (spare + 1).min(u32::from(MAX_PAGES)) as u8
}

/// The tree's set layout: nodes, triangles, escape links, instances, masks, and the
/// further pages' slots of the first three ([`PAGE_BINDING_STRIDE`] apart). Every binding
/// is bound (unused ones with a filler), as kernels of every shape share the layout.
fn tree_bindings(limits: &DeviceLimits) -> Vec<u32> {
    let mut b = vec![0, 1, 2, 4, 5];
    for p in 1..u32::from(page_slots(limits)) {
        b.extend([0, 1, 2].map(|x| x + PAGE_BINDING_STRIDE * p));
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The messenger counts what the layer reports: a zero-sized buffer is invalid usage
    /// (`VUID-VkBufferCreateInfo-size-00912`). Without the layer there is nothing to count.
    #[test]
    fn validation_errors_are_counted() {
        let ctx = match VkContext::with_options(&VkOptions {
            validation: true,
            ..VkOptions::default()
        }) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("SKIP validation_errors_are_counted: {e}");
                return;
            }
        };
        if !ctx.validation_enabled() {
            eprintln!("SKIP validation_errors_are_counted: no validation layer installed");
            return;
        }
        assert_eq!(ctx.validation_errors(), 0);
        let d = &ctx.inner.device;
        let info = vk::BufferCreateInfo::default()
            .size(0)
            .usage(vk::BufferUsageFlags::STORAGE_BUFFER);
        // SAFETY: deliberately invalid create info (size 0), reported by the layer; lavapipe
        // still returns a handle (or an error), destroyed right away.
        unsafe {
            if let Ok(b) = d.create_buffer(&info, None) {
                d.destroy_buffer(b, None);
            }
        }
        assert!(
            ctx.validation_errors() >= 1,
            "the layer's error was not counted"
        );
        assert!(process_validation_errors() >= 1);
    }
}
