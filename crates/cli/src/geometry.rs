//! Loading and building what a command traces ([`SceneBvh`]: flattened, or two levels),
//! and how it is reported.

use std::time::Instant;

use anyhow::{Context, Result};
use bvhtrace_core::{BuildOptions, FlatBvh};
use bvhtrace_scene::{Scene, SceneBvh};
use serde_json::{Value, json};

/// A loaded and built scene, with the times each step took.
pub struct Built {
    /// The scene as loaded (at `--time`, when given).
    pub scene: Scene,
    /// Its traced form.
    pub geometry: SceneBvh,
    /// Loading (and flattening) the scene, milliseconds.
    pub load_ms: f64,
    /// Building the BVH (both levels for two), milliseconds.
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
    // Two levels when the scene places meshes more than once and `flatten` is not asked
    // for; a scene of one instance traces as fast flattened (no top level to walk).
    let two_level = !flatten && scene.instances.len() > 1;
    let tris = if two_level {
        None
    } else {
        let t = scene.flattened_triangles();
        Some(t.with_context(|| format!("{spec}: cannot be flattened (drop --flatten?)"))?)
    };
    let load_ms = t0.elapsed().as_secs_f64() * 1e3;
    let t1 = Instant::now();
    let geometry = match tris {
        Some(tris) => {
            let bvh =
                FlatBvh::build(&tris, opts).with_context(|| format!("{spec}: BVH build failed"))?;
            SceneBvh::Flat { tris, bvh }
        }
        None => SceneBvh::Instanced(
            scene
                .instanced_bvh(opts)
                .with_context(|| format!("{spec}: two-level BVH build failed"))?,
        ),
    };
    let build_ms = t1.elapsed().as_secs_f64() * 1e3;
    Ok(Built {
        scene,
        geometry,
        load_ms,
        build_ms,
    })
}
