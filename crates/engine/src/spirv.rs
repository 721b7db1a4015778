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
    let none = spv::ZeroInitializeWorkgroupMemoryMode::None;
    write_entry(module, info, entry, constants, target, none)
}

/// How one entry point of a program binds a buffer in group 0.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EntryBinding {
    /// The binding number.
    pub binding: u32,
    /// A uniform block (else a storage buffer).
    pub uniform: bool,
}

/// One entry point of a program: its SPIR-V words and the group-0 buffers it reads.
#[derive(Clone, Debug)]
pub struct EntrySpirv {
    /// The entry point's name.
    pub name: &'static str,
    /// Its SPIR-V.
    pub words: Vec<u32>,
    /// The buffers of group 0 it uses, by binding number.
    pub bindings: Vec<EntryBinding>,
}

/// Each of `entries` of the WGSL module `source` (a device program: a builder) as SPIR-V,
/// with the group-0 buffers it uses. Workgroup memory starts zeroed, as WGSL says (and
/// wgpu does): by the device when `device_zeroes_workgroup` (Vulkan's
/// `shaderZeroInitializeWorkgroupMemory` is enabled), else by the program itself.
pub fn program(
    source: &str,
    entries: &[&'static str],
    target: &SpirvTarget,
    device_zeroes_workgroup: bool,
) -> Result<Vec<EntrySpirv>, TraceError> {
    let zero = match device_zeroes_workgroup {
        true => spv::ZeroInitializeWorkgroupMemoryMode::Native,
        false => spv::ZeroInitializeWorkgroupMemoryMode::Polyfill,
    };
    let module = naga::front::wgsl::parse_str(source)
        .map_err(|e| failed("parsing the WGSL", e.emit_to_string(source)))?;
    let info = naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .map_err(|e| failed("validating the WGSL", e.emit_to_string(source)))?;
    let constants = naga::back::PipelineConstants::default();
    entries
        .iter()
        .map(|&name| {
            let index = module
                .entry_points
                .iter()
                .position(|p| p.name == name)
                .ok_or_else(|| failed("finding the entry point", name))?;
            let used = info.get_entry_point(index);
            let bindings = module
                .global_variables
                .iter()
                .filter(|(handle, _)| !used[*handle].is_empty())
                .filter_map(|(_, var)| {
                    let b = var.binding.as_ref().filter(|b| b.group == 0)?;
                    Some(EntryBinding {
                        binding: b.binding,
                        uniform: var.space == naga::AddressSpace::Uniform,
                    })
                })
                .collect();
            let words = write_entry(&module, &info, name, &constants, target, zero)?;
            Ok(EntrySpirv {
                name,
                words,
                bindings,
            })
        })
        .collect()
}

/// [`entry_point`], with workgroup memory zeroed as `zero_workgroup` says.
fn write_entry(
    module: &naga::Module,
    info: &naga::valid::ModuleInfo,
    entry: &str,
    constants: &naga::back::PipelineConstants,
    target: &SpirvTarget,
    zero_workgroup: spv::ZeroInitializeWorkgroupMemoryMode,
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
        zero_initialize_workgroup_memory: zero_workgroup,
        ..Default::default()
    };
    let pipeline = spv::PipelineOptions {
        shader_stage: stage,
        entry_point: entry.to_string(),
    };
    spv::write_vec(&module, &info, &options, Some(&pipeline))
        .map_err(|e| failed("writing SPIR-V", e))
}
