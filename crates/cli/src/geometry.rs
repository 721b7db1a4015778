//! Loading and building what a command traces ([`SceneBvh`]: flattened, or two levels),
//! and how it is reported.

use std::time::Instant;

use anyhow::{Result, anyhow};
use bvhtrace_core::BuildOptions;
use bvhtrace_scene::{Scene, SceneBvh, TracingBvhError};
use serde_json::{Value, json};

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

/// Loads `spec` (at time `time` when given), prints its warnings, and builds it.
pub fn load_and_build(
    spec: &str,
    opts: &BuildOptions,
    flatten: bool,
    time: Option<f32>,
) -> Result<Built> {
    let t0 = Instant::now();
    let mut scene = bvhtrace_scene::load(spec)?;
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
    let geometry = scene.tracing_bvh(opts, flatten).map_err(|e| match e {
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
