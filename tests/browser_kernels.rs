//! Every kernel variant compiles in a browser: the composed WGSL of each key (both
//! storages, every walk, query, counters, one mesh or two levels), and of the trees of
//! their own layout (moving meshes, moving instances, curves), goes to headless Chromium's WebGPU (Tint, the compiler Chrome uses,
//! on SwiftShader), which compiles the module and builds the pipeline with the key's
//! override constants. naga accepting the WGSL is not enough: Tint also applies WGSL's
//! rules on constant expressions and uniformity. Any compiler message or pipeline error
//! fails the test, naming the key.
//!
//! Needs Debian's `chromium` (installed by `.ci/run`); without it the test prints SKIP.
//! `BVHTRACE_CHROMIUM` names another binary.

use std::time::Duration;

use bvhtrace_integration::browser::{self, Report};

use bvhtrace_gpu::engine::compose::ModuleSet;
use bvhtrace_gpu::engine::pages::Pages;
use bvhtrace_gpu::engine::{BvhStorage, DriverTuning, KernelKey};
use bvhtrace_gpu::{TraceOptions, Traversal};

/// The variants: every walk, query, counters setting, one mesh or two levels, with the
/// BVH in buffers (what a page on WebGPU composes) and in textures; and each walk over a
/// tree split into two pages an array (`bvhtrace_engine::pages`), within WebGPU's default
/// of 8 storage buffers per stage.
fn variants() -> Vec<KernelKey> {
    let split = Pages {
        log2_bytes: 27,
        nodes: 2,
        triangles: 2,
        escapes: 2,
    };
    let paged = Traversal::ALL
        .map(|t| KernelKey::new(BvhStorage::Buffers, &TraceOptions::closest(t)).with_pages(split));
    [BvhStorage::Buffers, BvhStorage::Textures]
        .into_iter()
        .flat_map(|storage| KernelKey::all_for_k(storage, 6))
        .chain(paged)
        .collect()
}

/// One variant for the page: its name, WGSL, entry point and override constants (the
/// driver's added).
fn variant(
    name: String,
    source: String,
    entry: &str,
    constants: &[(&str, f64)],
) -> serde_json::Value {
    let constants: serde_json::Map<String, serde_json::Value> = (constants.iter().copied())
        .chain(DriverTuning::GPU.constants())
        .map(|(name, v)| (name.to_string(), v.into()))
        .collect();
    serde_json::json!({ "name": name, "source": source, "entry": entry, "constants": constants })
}

/// The trees of their own layout (`bvhtrace_gpu::GpuMotionBvh`, `GpuMotionInstancedBvh`,
/// `GpuCurveBvh`): the moving modules' full-stack entry point for closest hits with
/// linear bounds and any hit with merged ones, the curves' for closest hits of every kind
/// (each pipeline costs SwiftShader seconds: the constants pick code paths, covered so).
fn tree_variants() -> Vec<serde_json::Value> {
    let entry = "bvh_trace_full_stack_main";
    let mut out = Vec::new();
    for (name, module) in [
        ("motion", ModuleSet::motion()),
        ("motion-instances", ModuleSet::motion_instances()),
    ] {
        let source = module.compose(0);
        for (any, linear) in [(0.0, 1.0), (1.0, 0.0)] {
            let c = [
                ("BVH_ANY_HIT", any),
                ("BVH_LINEAR_BOUNDS", linear),
                ("BVH_TIME_STEPS", 9.0),
            ];
            out.push(variant(format!("{name} {c:?}"), source.clone(), entry, &c));
        }
    }
    let source = ModuleSet::curves().compose(0);
    for kind in 0..4 {
        let c = [
            ("BVH_ANY_HIT", 0.0),
            ("BVH_CURVE_KIND", kind as f64),
            ("BVH_CURVE_TRIANGLES", 2.0),
        ];
        out.push(variant(format!("curves {c:?}"), source.clone(), entry, &c));
    }
    out
}

/// The page: compiles each variant with `getCompilationInfo`, builds its pipeline, and
/// writes one line per variant (`ok NAME` or `error NAME: MESSAGE`) into `<pre id=out>`.
fn page(keys: &[KernelKey]) -> (String, usize) {
    let mut list: Vec<serde_json::Value> = keys
        .iter()
        .map(|k| {
            variant(
                format!("{k:?}"),
                k.source(),
                k.entry_point(),
                &k.constants(),
            )
        })
        .collect();
    list.extend(tree_variants());
    let count = list.len();
    let page = format!(
        r#"<!doctype html><meta charset="utf-8"><pre id="out">running</pre><script>
const variants = {};
(async () => {{
  const out = [];
  try {{
    const adapter = await navigator.gpu.requestAdapter();
    const l = adapter.limits;
    const device = await adapter.requestDevice({{ requiredLimits: {{
      maxStorageBuffersPerShaderStage: l.maxStorageBuffersPerShaderStage,
      maxStorageTexturesPerShaderStage: l.maxStorageTexturesPerShaderStage,
      maxComputeWorkgroupStorageSize: l.maxComputeWorkgroupStorageSize,
    }} }});
    out.push(`adapter ${{adapter.info.vendor}} ${{adapter.info.architecture}}`);
    const modules = new Map();
    for (const v of variants) {{
      device.pushErrorScope("validation");
      // Variants differing only in override constants share one module.
      if (!modules.has(v.source)) {{
        const module = device.createShaderModule({{ code: v.source }});
        const info = await module.getCompilationInfo();
        modules.set(v.source, [module, info.messages.filter(m => m.type === "error")
          .map(m => `${{m.lineNum}}:${{m.linePos}} ${{m.message}}`)]);
      }}
      const [module, compiled] = modules.get(v.source);
      const errors = [...compiled];
      let pipeline = "";
      try {{
        await device.createComputePipelineAsync({{ layout: "auto",
          compute: {{ module, entryPoint: v.entry, constants: v.constants }} }});
      }} catch (e) {{ pipeline = String(e.message || e); }}
      const scope = await device.popErrorScope();
      if (scope) errors.push(scope.message);
      if (pipeline) errors.push(pipeline);
      out.push(errors.length ? `error ${{v.name}}: ${{errors.join(" | ")}}` : `ok ${{v.name}}`);
    }}
  }} catch (e) {{ out.push(`error page: ${{e}}`); }}
  out.push("done");
  document.getElementById("out").textContent = out.join("\n");
  await fetch("/result", {{ method: "POST", body: out.join("\n") }});
}})();
</script>"#,
        serde_json::Value::Array(list)
    );
    (page, count)
}

#[test]
fn every_kernel_variant_compiles_in_chromium() {
    let Some(chromium) = browser::chromium() else {
        eprintln!("SKIP every_kernel_variant_compiles_in_chromium: no chromium installed");
        return;
    };
    let keys = variants();
    let (page, count) = page(&keys);
    let page = page.into_bytes();
    let served = move |path: &str| (path == "/").then(|| page.clone());
    let dom = match browser::run_page(&chromium, served, "/", Duration::from_secs(600)) {
        Ok(Report::Result(bytes)) => String::from_utf8_lossy(&bytes).into_owned(),
        other => panic!("the page failed: {other:?}"),
    };
    let lines: Vec<&str> = dom.lines().collect();
    let first = lines.iter().position(|l| l.contains("adapter "));
    eprintln!("{}", first.map_or("no adapter line", |i| lines[i]));
    let ok = lines.iter().filter(|l| l.starts_with("ok ")).count();
    let errors: Vec<&&str> = lines.iter().filter(|l| l.starts_with("error ")).collect();
    assert!(
        errors.is_empty(),
        "{} of {} variants failed in Chromium:\n{}",
        errors.len(),
        count,
        errors
            .iter()
            .map(|e| e.chars().take(600).collect::<String>())
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert!(
        lines.iter().any(|l| l.trim_end().ends_with("done")),
        "the page did not finish:\n{dom}"
    );
    assert_eq!(ok, count, "variants compiled");
    eprintln!("browser kernels: {ok} variants compile in Chromium");
}
