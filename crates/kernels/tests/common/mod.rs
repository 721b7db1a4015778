//! naga helpers the kernels crate's tests share: parse WGSL, validate it, and compile one
//! kernel variant's entry point to SPIR-V with its override constants resolved.
#![allow(dead_code)]

use bvhtrace_kernels::KernelKey;
use naga::Module;
use naga::valid::{Capabilities, ModuleInfo, ValidationFlags, Validator};

/// Parses WGSL, panicking with naga's report.
pub fn parse(source: &str) -> Module {
    naga::front::wgsl::parse_str(source).unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)))
}

/// Validates with every check and `capabilities`.
pub fn validate_with(module: &Module, capabilities: Capabilities) -> ModuleInfo {
    Validator::new(ValidationFlags::all(), capabilities)
        .validate(module)
        .unwrap_or_else(|e| panic!("{e:?}"))
}

/// Validates with every check and the default capabilities.
pub fn validate(module: &Module) -> ModuleInfo {
    validate_with(module, Capabilities::default())
}

/// Compiles `variant`'s entry point in `module` to SPIR-V with its override constants, and
/// checks that something came out.
pub fn compile_variant(module: &Module, info: &ModuleInfo, variant: &KernelKey) {
    let mut constants = naga::back::PipelineConstants::default();
    for (name, value) in variant.constants() {
        constants.insert(name.to_string(), value);
    }
    let entry = variant.entry_point();
    let (m, i) = naga::back::pipeline_constants::process_overrides(
        module,
        info,
        Some((naga::ShaderStage::Compute, entry)),
        &constants,
    )
    .unwrap_or_else(|e| panic!("{variant:?}: {e}"));
    let words = naga::back::spv::write_vec(
        &m,
        &i,
        &naga::back::spv::Options::default(),
        Some(&naga::back::spv::PipelineOptions {
            shader_stage: naga::ShaderStage::Compute,
            entry_point: entry.to_string(),
        }),
    )
    .unwrap_or_else(|e| panic!("{variant:?}: {e}"));
    assert!(words.len() > 100, "{variant:?}: SPIR-V too short");
}
