//! Loading and building what a command traces ([`SceneBvh`]: flattened, or two levels),
//! and how it is reported.

use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use bvhtrace::{Device, GpuBuildOptions, GpuBuilderKind};
use bvhtrace_core::{BuildOptions, BuilderKind, FlatBvh, Triangle};
use bvhtrace_scene::{LoadOptions, Scene, SceneBvh, TracingBvhError};
use serde_json::{Value, json};

/// A builder the commands offer: one of the CPU's, or one that builds on the device
/// (`gpu-ploc`, `gpu-lbvh`) and reads the tree back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Builder {
    /// A CPU builder.
    Cpu(BuilderKind),
    /// A device builder.
    Device(GpuBuilderKind),
}

impl std::str::FromStr for Builder {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if let Some(k) = GpuBuilderKind::ALL.into_iter().find(|k| k.name() == s) {
            return Ok(Builder::Device(k));
        }
        s.parse::<BuilderKind>().map(Builder::Cpu).map_err(|_| {
            format!(
                "unknown builder '{s}' (expected sah, sweep-sah, median, midpoint, sbvh, \
                 gpu-ploc or gpu-lbvh)"
            )
        })
    }
}

impl Builder {
    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Builder::Cpu(k) => k.name(),
            Builder::Device(k) => k.name(),
        }
    }
}

impl std::fmt::Display for Builder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Builds one-mesh BVHs the way the flags say: on the CPU with its options, or on the
/// command's device ([`Device::build_bvh`]), the one it traces on.
pub struct TreeBuilder {
    cpu: BuildOptions,
    device: Option<(Device, GpuBuildOptions)>,
}

impl TreeBuilder {
    /// `builder` with the CPU's `cpu` options (their costs also rule a device build's
    /// leaves); a device builder builds on `device`, an error without one.
    pub fn new(builder: Builder, cpu: BuildOptions, device: Option<&Device>) -> Result<Self> {
        let device = match builder {
            Builder::Cpu(_) => None,
            Builder::Device(kind) => {
                if cpu.optimize {
                    anyhow::bail!("--optimize reinserts in the CPU builders' trees, not {kind}'s");
                }
                let device = device.with_context(|| {
                    format!("--builder {kind} builds on a device, and this command opened none")
                })?;
                let opts = GpuBuildOptions {
                    cost_traversal: cpu.cost_traversal,
                    cost_intersection: cpu.cost_intersection,
                    ..GpuBuildOptions::with_builder(kind)
                };
                Some((device.clone(), opts))
            }
        };
        Ok(TreeBuilder { cpu, device })
    }

    /// The BVH over `tris`, or the builder's error in words.
    pub fn build(&self, tris: &[Triangle]) -> Result<FlatBvh, String> {
        let built = match &self.device {
            None => return FlatBvh::build(tris, &self.cpu).map_err(|e| e.to_string()),
            Some((device, opts)) => device.build_bvh(tris, opts),
        };
        built.map(|(bvh, _)| bvh).map_err(|e| e.to_string())
    }
}

/// A loaded and built scene, with the times each step took.
pub struct Built {
    /// The scene as loaded (at `--time`, when given).
    pub scene: Scene,
    /// Its traced form.
    pub geometry: SceneBvh,
    /// Loading the scene, milliseconds.
    pub load_ms: f64,
    /// Flattening it (for one level) and building the BVH (both levels for two),
    /// milliseconds.
    pub build_ms: f64,
}

/// `instances`, `meshes` and, for two levels, the bytes of each level, as JSON fields.
pub fn json(geo: &SceneBvh, scene: &Scene) -> Value {
    match geo {
        SceneBvh::Flat { .. } => json!({
            "form": "flattened",
            "instances": scene.instance_count(),
            "meshes": scene.meshes.len(),
        }),
        SceneBvh::Instanced(i) => {
            let (top, meshes) = i.level_bytes();
            json!({
                "form": "two-level",
                "instances": i.instances().len(),
                "meshes": i.meshes().len(),
                "top_level_bytes": top,
                "mesh_bytes": meshes,
            })
        }
    }
}

/// The shared scenes folder: `$BVHTRACE_SCENES` when set and not empty, else the one the
/// scene library finds walking up from here.
pub fn shared_scenes_dir() -> Option<std::path::PathBuf> {
    match std::env::var_os("BVHTRACE_SCENES") {
        Some(v) if !v.is_empty() => Some(v.into()),
        _ => bvhtrace_scene::shared_scenes_dir(),
    }
}

/// Loads `spec`, `builtin:grid`'s meshes from the shared scenes folder.
pub fn load_scene(spec: &str) -> Result<Scene> {
    let opts = LoadOptions::with_meshes(shared_scenes_dir());
    Ok(bvhtrace_scene::load_with(spec, &opts)?)
}

/// Loads `spec` for a command that traces triangles alone (the benchmarks, `cost`): a scene
/// with curves is refused, naming them, rather than timed without them.
pub fn load_triangle_scene(spec: &str) -> Result<Scene> {
    let scene = load_scene(spec)?;
    if let Some(c) = scene.curves.as_ref().filter(|c| !c.is_empty()) {
        anyhow::bail!(
            "{spec}: this command traces triangles, and the scene's {} {} curve segments would be left out (`bvhtrace render` traces curves; docs/curves-bench.sh times them)",
            c.len(),
            c.kind.name()
        );
    }
    Ok(scene)
}

/// Loads `spec` (at time `time` when given), prints its warnings, and builds it with
/// `builder`.
pub fn load_and_build(
    spec: &str,
    builder: &TreeBuilder,
    flatten: bool,
    time: Option<f32>,
) -> Result<Built> {
    let t0 = Instant::now();
    let mut scene = load_scene(spec)?;
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    if let Some(t) = time {
        if !t.is_finite() {
            anyhow::bail!("--time must be finite, got {t}");
        }
        scene.set_time(t);
    }
    let load_ms = t0.elapsed().as_secs_f64() * 1e3;
    let t1 = Instant::now();
    let geometry = match builder.device {
        None => scene.tracing_bvh(&builder.cpu, flatten),
        Some(_) => scene.tracing_bvh_with(flatten, |tris| builder.build(tris)),
    };
    let geometry = geometry.map_err(|e| match e {
        TracingBvhError::Flatten(_) if flatten => anyhow!("{spec}: {e} (drop --flatten?)"),
        e => anyhow!("{spec}: {e}"),
    })?;
    let build_ms = t1.elapsed().as_secs_f64() * 1e3;
    Ok(Built {
        scene,
        geometry,
        load_ms,
        build_ms,
    })
}
