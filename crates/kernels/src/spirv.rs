//! The kernels as SPIR-V, for backends that hand Vulkan their shaders themselves (the ash
//! backend; wgpu translates the same WGSL itself): naga resolves a key's override constants
//! and writes its one entry point, groups and bindings as the WGSL numbers them.

use naga::back::spv;
use naga::proc::BoundsCheckPolicy;

use crate::device::DriverTuning;
use crate::error::TraceError;
use crate::key::KernelKey;

/// The SPIR-V a device takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SpirvTarget {
    /// The SPIR-V version, `(major, minor)`.
    pub version: (u8, u8),
    /// The device checks buffer bounds itself (`robustBufferAccess2`), so naga skips its
    /// own buffer checks, as wgpu does.
    pub robust_buffers: bool,
}

impl SpirvTarget {
    /// The newest SPIR-V a Vulkan `major.minor` device takes (1.0, 1.3, then 1.5 from
    /// Vulkan 1.2 on).
    pub fn for_vulkan(major: u32, minor: u32, robust_buffers: bool) -> SpirvTarget {
        let version = match (major, minor) {
            (1, 0) => (1, 0),
            (1, 1) => (1, 3),
            _ => (1, 5),
        };
        SpirvTarget {
            version,
            robust_buffers,
        }
    }
}

/// A translation failure: which stage failed, and naga's report.
fn failed(stage: &str, message: impl std::fmt::Display) -> TraceError {
    TraceError::Device {
        during: "translating the kernels to SPIR-V",
        message: format!("{stage}: {message}"),
    }
}

/// The SPIR-V words of `key`'s kernel: its WGSL module ([`KernelKey::source`], what the
/// wgpu path compiles for the same key) with its override constants
/// ([`KernelKey::constants`] and `tuning`'s: `TRIP_LIMIT`, `DISPATCH_THREADS`) resolved,
/// one entry point ([`KernelKey::entry_point`]).
pub fn kernel(
    key: &KernelKey,
    tuning: &DriverTuning,
    target: &SpirvTarget,
) -> Result<Vec<u32>, TraceError> {
    let source = key.source();
    let module = naga::front::wgsl::parse_str(&source)
        .map_err(|e| failed("parsing the WGSL", e.emit_to_string(&source)))?;
    let info = naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .map_err(|e| failed("validating the WGSL", e.emit_to_string(&source)))?;
    let mut constants = naga::back::PipelineConstants::default();
    for (name, value) in key.constants().into_iter().chain(tuning.constants()) {
        constants.insert(name.to_string(), value);
    }
    entry_point(&module, &info, key.entry_point(), &constants, target)
}

/// The SPIR-V words of the compute entry point `entry` of a validated `module`, with the
/// override `constants` resolved.
pub fn entry_point(
    module: &naga::Module,
    info: &naga::valid::ModuleInfo,
    entry: &str,
    constants: &naga::back::PipelineConstants,
    target: &SpirvTarget,
) -> Result<Vec<u32>, TraceError> {
    let stage = naga::ShaderStage::Compute;
    let (module, info) = naga::back::pipeline_constants::process_overrides(
        module,
        info,
        Some((stage, entry)),
        constants,
    )
    .map_err(|e| failed("resolving override constants", e))?;
    let checked = BoundsCheckPolicy::Restrict;
    let options = spv::Options {
        lang_version: target.version,
        flags: spv::WriterFlags::empty(),
        bounds_check_policies: naga::proc::BoundsCheckPolicies {
            index: checked,
            buffer: match target.robust_buffers {
                true => BoundsCheckPolicy::Unchecked,
                false => checked,
            },
            image_load: checked,
            binding_array: BoundsCheckPolicy::Unchecked,
        },
        zero_initialize_workgroup_memory: spv::ZeroInitializeWorkgroupMemoryMode::None,
        ..Default::default()
    };
    let pipeline = spv::PipelineOptions {
        shader_stage: stage,
        entry_point: entry.to_string(),
    };
    spv::write_vec(&module, &info, &options, Some(&pipeline))
        .map_err(|e| failed("writing SPIR-V", e))
}
