//! The one error type of every backend.

use bvhtrace_core::{Precision, Traversal};

use crate::storage::BvhStorage;

/// `bytes` in MiB, for a sentence.
fn mib(bytes: u64) -> String {
    match bytes < 1 << 20 {
        true => format!("{:.1} KiB", bytes as f64 / 1024.0),
        false => format!("{:.1} MiB", bytes as f64 / f64::from(1 << 20)),
    }
}

/// Everything that can go wrong while choosing a device, uploading a BVH or tracing, on
/// any backend. Nothing in bvhtrace panics on bad input or a missing device: it returns
/// one of these.
#[derive(Debug, thiserror::Error)]
pub enum TraceError {
    /// No usable device: no Vulkan loader, no driver, or no adapter with a compute queue.
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
    /// The adapter asked for by name (or by `BVHTRACE_ADAPTER`) does not exist.
    #[error("no Vulkan adapter name contains {wanted:?} (available: {available})")]
    AdapterNotFound {
        /// The requested substring.
        wanted: String,
        /// The adapters that exist, comma-separated.
        available: String,
    },
    /// The device lacks a feature the tracer needs for this job.
    #[error("the device {adapter} lacks the {feature} feature, which {needed_for} needs")]
    MissingFeature {
        /// The feature's name (`SHADER_F64`, ...).
        feature: &'static str,
        /// What needs it.
        needed_for: &'static str,
        /// The adapter's name.
        adapter: String,
    },
    /// One of the device's limits is below what the tracer needs.
    #[error(
        "the device's {limit} is {has}, below the {needs} that {needed_for} needs; create the \
         device with at least the tracer's required limits"
    )]
    LimitTooLow {
        /// The limit's name, as in `wgpu::Limits`.
        limit: &'static str,
        /// The device's value.
        has: u64,
        /// The value needed.
        needs: u64,
        /// What needs it.
        needed_for: &'static str,
    },
    /// A buffer or texture would be larger than the device allows.
    #[error(
        "the {buffer} {} needs {bytes} bytes ({}) but the device's {limit_name} is {limit} \
         bytes ({}): the scene is too large for this device{}",
        if storage.is_some_and(|s| s == BvhStorage::Textures) { "texture" } else { "buffer" },
        mib(*bytes),
        mib(*limit),
        storage.map_or(String::new(), |s| format!(" in {} storage", s.name()))
    )]
    TooLarge {
        /// Which array (`nodes`, `triangles`, `escapes`, `rays`, ...).
        buffer: &'static str,
        /// Bytes it needs.
        bytes: u64,
        /// The limit it exceeds.
        limit: u64,
        /// The limit's name.
        limit_name: &'static str,
        /// Where the tree was to be kept, for an array of the tree (`None` for the rays).
        storage: Option<BvhStorage>,
    },
    /// The tree fits the device in none of the storages and walks tried: each, and why.
    #[error("the scene does not fit {device}: {}", tried.join("; "))]
    DoesNotFit {
        /// The device.
        device: String,
        /// Each storage and walk tried, with the limit it exceeded, and what the device
        /// does not offer.
        tried: Vec<String>,
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
    /// The traversal reads a layout the upload left out (the binary one, when only
    /// [`Traversal::Wide`] was listed).
    #[error(
        "the {traversal} traversal reads the binary layout, which this upload left out \
         (list it in UploadOptions::traversals)"
    )]
    TraversalNotUploaded {
        /// The traversal asked for.
        traversal: Traversal,
    },
    /// The wide traversal needs the wide layout (`FlatBvh::wide`), which the BVH or its
    /// upload does not have.
    #[error("the wide traversal needs the BVH's wide layout (FlatBvh::wide), which {missing}")]
    WideLayoutMissing {
        /// Where it is missing, and the fix.
        missing: &'static str,
    },
    /// The kernel's triangle test needs a device feature this one lacks.
    #[error(
        "the {precision} triangle test needs the SHADER_F64 feature, which the adapter \
         {adapter} does not offer; use watertight-f32 or moller-trumbore-f32"
    )]
    PrecisionUnsupported {
        /// The precision asked for.
        precision: Precision,
        /// The adapter's name.
        adapter: String,
    },
    /// A caller's buffer given to a recording call does not fit the batch.
    #[error("the {buffer} buffer: {problem}")]
    BadBuffer {
        /// Which buffer (`rays`, `hits`, `counters`).
        buffer: &'static str,
        /// What is wrong with it.
        problem: String,
    },
    /// The device ran out of memory.
    #[error("the device ran out of memory while {during}: {message}")]
    OutOfMemory {
        /// What the tracer was doing.
        during: &'static str,
        /// The driver's or wgpu's message.
        message: String,
    },
    /// The device was lost (driver reset, hang, removal).
    #[error("the device was lost while {during}")]
    DeviceLost {
        /// What the tracer was doing.
        during: &'static str,
    },
    /// Any other error the device API reported (a wgpu validation error, a Vulkan result,
    /// a failed mapping or wait, shader translation).
    #[error("device error while {during}: {message}")]
    Device {
        /// What the tracer was doing.
        during: &'static str,
        /// The API's message.
        message: String,
    },
    /// The tracer cannot answer what was asked in the way asked: the ray-query tracer has
    /// no counters and no choice of triangle test (the device's acceleration structure
    /// answers the queries).
    #[error("the {backend} tracer does not offer {what}")]
    Unsupported {
        /// The tracer's backend name.
        backend: &'static str,
        /// What it does not offer, and what to do instead.
        what: String,
    },
    /// A lock was poisoned by a thread that panicked while holding it.
    #[error("a thread panicked while holding the {0}")]
    Poisoned(&'static str),
    /// An own shader's traversal library was composed for another upload than the one it
    /// is bound to (storage, one mesh or two levels, layout, or a walk not uploaded): its
    /// walk would read bindings the upload does not have, or miss ones it has.
    #[error(
        "the WGSL library was composed for {library}, but the upload holds {upload}; compose \
         it with GpuBvh::wgsl_library of this upload"
    )]
    LibraryMismatch {
        /// What the library was composed for (`LibraryShape`'s `Display`).
        library: String,
        /// What the upload holds.
        upload: String,
    },
    /// A shader of yours, compiled after the traversal library, does not compile: where,
    /// counted in your own source's lines, and the compiler's words.
    #[error("{label}{}: {message}", place(*line, *column))]
    Shader {
        /// The shader's label.
        label: String,
        /// The line of your source (1-based), when the compiler gave one; 0 when the
        /// error lies in the library itself.
        line: Option<u32>,
        /// The column (1-based, in bytes), with the line.
        column: Option<u32>,
        /// What the compiler said.
        message: String,
    },
}

/// `:line:column` for a sentence (` (in the bvhtrace library)` for line 0), or nothing.
fn place(line: Option<u32>, column: Option<u32>) -> String {
    match (line, column) {
        (Some(0), _) => " (in the bvhtrace library)".to_string(),
        (Some(l), Some(c)) => format!(":{l}:{c}"),
        (Some(l), None) => format!(":{l}"),
        _ => String::new(),
    }
}

impl TraceError {
    /// A [`TraceError::Device`] error from any displayable cause.
    pub fn device(during: &'static str, cause: impl std::fmt::Display) -> TraceError {
        TraceError::Device {
            during,
            message: cause.to_string(),
        }
    }
}
