//! The one error type of the crate: every Vulkan, loader and shader-translation failure
//! comes back as a [`VkError`], never as a panic.

use ash::vk;

/// What went wrong.
#[derive(Debug, thiserror::Error)]
pub enum VkError {
    /// `libvulkan` could not be opened (no Vulkan loader installed).
    #[error(
        "cannot load the Vulkan loader (libvulkan): {0}; install a Vulkan driver \
         (for a CPU one: apt-get install mesa-vulkan-drivers)"
    )]
    LoaderMissing(String),
    /// The loader works but lists no device with a compute queue.
    #[error(
        "no Vulkan device with a compute queue{details}; install a Vulkan driver \
         (for a CPU one: apt-get install mesa-vulkan-drivers)"
    )]
    NoDevice {
        /// Extra context (may be empty).
        details: String,
    },
    /// The adapter asked for (argument or `BVHTRACE_ADAPTER`) is not among the devices.
    #[error("no Vulkan device named like '{wanted}'; available: {available}")]
    AdapterNotFound {
        /// The requested name (case-insensitive substring).
        wanted: String,
        /// The devices present, with their types.
        available: String,
    },
    /// `VK_ERROR_OUT_OF_DEVICE_MEMORY` or `VK_ERROR_OUT_OF_HOST_MEMORY`.
    #[error("Vulkan ran out of memory while {during} ({result})")]
    OutOfMemory {
        /// What the tracer was doing.
        during: &'static str,
        /// The Vulkan result.
        result: vk::Result,
    },
    /// `VK_ERROR_DEVICE_LOST`: the device is unusable; make a new [`crate::VkContext`].
    #[error("the Vulkan device was lost while {during}")]
    DeviceLost {
        /// What the tracer was doing.
        during: &'static str,
    },
    /// Any other failing Vulkan call.
    #[error("Vulkan error while {during}: {result}")]
    Vulkan {
        /// What the tracer was doing.
        during: &'static str,
        /// The Vulkan result.
        result: vk::Result,
    },
    /// No memory type with the properties a buffer needs.
    #[error("no Vulkan memory type for the {buffer} buffer (needs {needs:?})")]
    NoMemoryType {
        /// Which buffer.
        buffer: &'static str,
        /// The property flags required.
        needs: vk::MemoryPropertyFlags,
    },
    /// A BVH array is larger than one storage binding may be on this device.
    #[error(
        "the BVH's {buffer} array is {bytes} bytes, more than this device's \
         maxStorageBufferRange ({limit} bytes)"
    )]
    TooLarge {
        /// Which array.
        buffer: &'static str,
        /// Its size.
        bytes: u64,
        /// The device's limit.
        limit: u64,
    },
    /// The BVH's escape links do not fit its nodes; the stackless and short-stack walks
    /// would follow them out of the tree.
    #[error(transparent)]
    BadEscapeLinks(#[from] bvhtrace_core::flat::EscapeLinksMismatch),
    /// The full-stack kernel's stack cannot hold this tree.
    #[error(
        "the tree is {depth} levels deep, more than the full-stack kernel's stack \
         ({max}); use the stackless or short-stack traversal"
    )]
    TooDeep {
        /// The tree's depth.
        depth: u32,
        /// `FULL_STACK_SIZE`.
        max: u32,
    },
    /// The WGSL could not be parsed, validated, specialised or written as SPIR-V.
    #[error("shader translation failed while {during}: {message}")]
    Shader {
        /// The naga stage.
        during: &'static str,
        /// naga's message.
        message: String,
    },
    /// The device or this backend cannot run what was asked for.
    #[error("not supported: {0}")]
    Unsupported(String),
    /// A lock was poisoned by a panicking thread.
    #[error("a thread panicked while holding the {0}")]
    Poisoned(&'static str),
}

impl VkError {
    /// Maps a failing Vulkan result, naming what was being done.
    pub(crate) fn from_vk(during: &'static str, result: vk::Result) -> VkError {
        match result {
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
                VkError::OutOfMemory { during, result }
            }
            vk::Result::ERROR_DEVICE_LOST => VkError::DeviceLost { during },
            _ => VkError::Vulkan { during, result },
        }
    }
}

/// `result.map_err(vkerr("doing x"))`.
pub(crate) fn vkerr(during: &'static str) -> impl Fn(vk::Result) -> VkError {
    move |r| VkError::from_vk(during, r)
}
