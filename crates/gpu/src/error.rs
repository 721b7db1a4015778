//! The crate's error type.

use bvhtrace_core::Traversal;

/// Everything that can go wrong on the GPU side. Nothing in this crate panics on bad input
/// or a missing device: it returns one of these.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No Vulkan adapter at all (no driver, or no Vulkan loader).
    #[error(
        "no Vulkan adapter found{details}. Install a Vulkan driver; without a GPU, Mesa's \
         CPU driver lavapipe works: `sudo apt-get install mesa-vulkan-drivers` (Debian/Ubuntu) \
         or `sudo dnf install mesa-vulkan-drivers` (Fedora); `vulkaninfo --summary` should \
         then list `llvmpipe`"
    )]
    NoAdapter {
        /// Extra context (empty, or starting with a separator).
        details: String,
    },
    /// `BVHTRACE_ADAPTER` (or the explicit choice) names no adapter.
    #[error("no Vulkan adapter name contains {wanted:?} (available: {available})")]
    AdapterNotFound {
        /// The requested substring.
        wanted: String,
        /// The adapters that exist, comma-separated.
        available: String,
    },
    /// The adapter refused to create a device.
    #[error("could not create a device on {adapter}: {source}")]
    RequestDevice {
        /// The adapter's name.
        adapter: String,
        /// wgpu's reason.
        source: wgpu::RequestDeviceError,
    },
    /// A buffer would be larger than the device allows.
    #[error(
        "the {buffer} buffer needs {bytes} bytes but the device's {limit_name} is {limit} bytes: \
         the scene is too large for this device"
    )]
    TooLarge {
        /// Which buffer (`nodes`, `triangles`, `escapes`, `rays`, ...).
        buffer: &'static str,
        /// Bytes it needs.
        bytes: u64,
        /// The limit it exceeds.
        limit: u64,
        /// The limit's name in `wgpu::Limits`.
        limit_name: &'static str,
    },
    /// The tree is deeper than the full-stack kernel's stack.
    #[error(
        "the BVH is {depth} levels deep but the full-stack kernel's stack holds {max} entries; \
         use the stackless or short-stack traversal, or rebuild with a smaller max_depth"
    )]
    TooDeep {
        /// The tree's depth.
        depth: u32,
        /// `FULL_STACK_SIZE`.
        max: u32,
    },
    /// The BVH has no node.
    #[error("the BVH is empty: nothing to upload")]
    EmptyBvh,
    /// The BVH's escape links do not fit its nodes; the stackless and short-stack walks
    /// would follow them out of the tree.
    #[error(transparent)]
    BadEscapeLinks(#[from] bvhtrace_core::flat::EscapeLinksMismatch),
    /// The traversal needs the escape links, which were not uploaded.
    #[error(
        "the {traversal} traversal needs the escape links, which this upload left out \
         (list it in UploadOptions::traversals)"
    )]
    EscapesNotUploaded {
        /// The traversal asked for.
        traversal: Traversal,
    },
    /// The kernel's triangle test needs a device feature this one lacks.
    #[error(
        "the {precision} triangle test needs the SHADER_F64 feature, which the adapter \
         {adapter} does not offer; use watertight-f32 or moller-trumbore-f32"
    )]
    PrecisionUnsupported {
        /// The precision asked for.
        precision: bvhtrace_core::Precision,
        /// The adapter's name.
        adapter: String,
    },
    /// A user buffer given to [`crate::GpuBvh::record`] does not fit the batch.
    #[error("the {buffer} buffer: {problem}")]
    BadBuffer {
        /// Which buffer (`rays`, `hits`, `counters`).
        buffer: &'static str,
        /// What is wrong with it.
        problem: String,
    },
    /// wgpu reported a validation, out-of-memory or internal error.
    #[error("wgpu error while {during}: {message}")]
    Wgpu {
        /// What the crate was doing.
        during: &'static str,
        /// wgpu's message.
        message: String,
    },
    /// Mapping a read-back buffer failed.
    #[error("reading results back failed: {0}")]
    Map(#[from] wgpu::BufferAsyncError),
    /// Waiting for the device failed (device lost, timeout).
    #[error("waiting for the GPU failed: {0}")]
    Poll(#[from] wgpu::PollError),
}
