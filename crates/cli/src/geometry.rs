//! What a command traces: one BVH over the scene's world-space triangles (flattened), or
//! two levels (a BVH per mesh, a top level over the instances).

use std::time::Instant;

use anyhow::{Context, Result};
use bvhtrace_core::{BuildOptions, FlatBvh, InstancedBvh, Triangle};
use bvhtrace_scene::Scene;
use serde_json::{Value, json};

/// The traced form of a scene.
pub enum Geometry {
    /// Every instance's triangles in world space, in one BVH; `tris[prim]`.
    Flat {
        /// The triangles by primitive id.
        tris: Vec<Triangle>,
        /// Their BVH.
        bvh: FlatBvh,
    },
    /// A BVH per mesh and a top level over the instances.
    Instanced(InstancedBvh),
}

/// A loaded and built scene, with the times each step took.
pub struct Built {
    /// The scene as loaded (at `--time`, when given).
    pub scene: Scene,
    /// Its traced form.
    pub geometry: Geometry,
    /// Loading (and flattening) the scene, milliseconds.
    pub load_ms: f64,
    /// Building the BVH (both levels for two), milliseconds.
    pub build_ms: f64,
}

impl Geometry {
    /// The BVH every backend traces.
    pub fn bvh(&self) -> &FlatBvh {
        match self {
            Geometry::Flat { bvh, .. } => bvh,
            Geometry::Instanced(i) => i.bvh(),
        }
    }

    /// The world-space corners of the primitive a hit names (`prim` is a hit's: in range).
    pub fn triangle(&self, prim: u32) -> Triangle {
        match self {
            Geometry::Flat { tris, .. } => tris[prim as usize],
            Geometry::Instanced(i) => i.world_triangle(prim).unwrap_or_default(),
        }
    }

    /// Triangles traced: over all instances for two levels.
    pub fn triangle_count(&self) -> u64 {
        match self {
            Geometry::Flat { tris, .. } => tris.len() as u64,
            Geometry::Instanced(i) => i.instanced_primitives(),
        }
    }

    /// `instances`, `meshes` and, for two levels, the bytes of each level, as JSON fields.
    pub fn json(&self, scene: &Scene) -> Value {
        match self {
            Geometry::Flat { .. } => json!({
                "form": "flattened",
                "instances": scene.instance_count(),
                "meshes": scene.meshes.len(),
            }),
            Geometry::Instanced(i) => {
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
            Geometry::Flat { tris, bvh }
        }
        None => Geometry::Instanced(
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
