//! naga helpers the engine crate's tests share: parse WGSL, validate it, and compile one
//! kernel variant's entry point to SPIR-V with its override constants resolved; the
//! storages and walks the variant tests go through. `crates/gpu/tests/features.rs`
//! includes it through `#[path]`.
#![allow(dead_code)]

use bvhtrace_engine::core::Traversal;
use bvhtrace_engine::shaders::{self, Wgsl};
use bvhtrace_engine::{BvhStorage, KernelKey};
use naga::Module;
use naga::valid::{Capabilities, ModuleInfo, ValidationFlags, Validator};

/// Both BVH storages.
pub const STORAGES: [BvhStorage; 2] = [BvhStorage::Buffers, BvhStorage::Textures];

/// A walk of each kind (the short stack at one size).
pub const TRAVERSALS: [Traversal; 4] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(6),
    Traversal::Wide,
];

/// The files every module of the binary walks composes, whatever its storage.
pub const SHARED_FILES: [Wgsl; 12] = [
    shaders::TYPES,
    shaders::RAY,
    shaders::SURFACE,
    shaders::TEXEL,
    shaders::BOX,
    shaders::TRIANGLE_HIT,
    shaders::TRIANGLE,
    shaders::TRAVERSE_COMMON,
    shaders::TRAVERSE_INSTANCES,
    shaders::TRAVERSE_STACK,
    shaders::TRAVERSE_FULL_STACK,
    shaders::TRAVERSE_SHORT_STACK,
];

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
    compile_entry(
        module,
        info,
        variant.entry_point(),
        &constants,
        &format!("{variant:?}"),
    );
}

/// Compiles the compute entry point `entry` of `module` to SPIR-V with the override
/// `constants`, and checks that something came out; `what` names it in a failure.
pub fn compile_entry(
    module: &Module,
    info: &ModuleInfo,
    entry: &str,
    constants: &naga::back::PipelineConstants,
    what: &str,
) {
    let (m, i) = naga::back::pipeline_constants::process_overrides(
        module,
        info,
        Some((naga::ShaderStage::Compute, entry)),
        constants,
    )
    .unwrap_or_else(|e| panic!("{what}: {e}"));
    let words = naga::back::spv::write_vec(
        &m,
        &i,
        &naga::back::spv::Options::default(),
        Some(&naga::back::spv::PipelineOptions {
            shader_stage: naga::ShaderStage::Compute,
            entry_point: entry.to_string(),
        }),
    )
    .unwrap_or_else(|e| panic!("{what}: {e}"));
    assert!(words.len() > 100, "{what}: SPIR-V too short");
}
