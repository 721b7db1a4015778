//! A scene as a two-level BVH: one bottom-level BVH per mesh however many instances use
//! it, a top level over the instances ([`bvhtrace_core::InstancedBvh`]).

use bvhtrace_core::{
    BuildError, BuildOptions, FlatBvh, Instance, InstanceError, InstancedBvh, Triangle,
};
use glam::Affine3A;

use crate::{Scene, SceneError};

/// Why [`Scene::tracing_bvh`] could not make the BVH to trace.
#[derive(Debug, thiserror::Error)]
pub enum TracingBvhError {
    /// The scene could not be flattened into world-space triangles (too many over all
    /// instances, or bad geometry).
    #[error("cannot be flattened: {0}")]
    Flatten(SceneError),
    /// The flattened triangles' BVH could not be built.
    #[error("BVH build failed: {0}")]
    Build(BuildError),
    /// The two-level BVH could not be built (a bad mesh or instance transform).
    #[error("two-level BVH build failed: {0}")]
    TwoLevel(InstanceError),
    /// The caller's builder ([`Scene::tracing_bvh_with`]) failed, in its words.
    #[error("BVH build failed: {0}")]
    Builder(String),
}

/// A scene as traced: one BVH over its world-space triangles (flattened), or two levels.
pub enum SceneBvh {
    /// Every instance's triangles in world space, in one BVH; `tris[prim]`.
    Flat {
        /// The triangles by primitive id ([`Scene::flattened_triangles`]).
        tris: Vec<Triangle>,
        /// Their BVH.
        bvh: FlatBvh,
    },
    /// A BVH per mesh and a top level over the instances ([`Scene::instanced_bvh`]).
    Instanced(InstancedBvh),
}

impl SceneBvh {
    /// The BVH every backend traces.
    pub fn bvh(&self) -> &FlatBvh {
        match self {
            SceneBvh::Flat { bvh, .. } => bvh,
            SceneBvh::Instanced(i) => i.bvh(),
        }
    }

    /// The world-space corners of the primitive a hit names; `None` for a miss code or an
    /// id out of range.
    pub fn triangle(&self, prim: u32) -> Option<Triangle> {
        match self {
            SceneBvh::Flat { tris, .. } => tris.get(prim as usize).copied(),
            SceneBvh::Instanced(i) => i.world_triangle(prim),
        }
    }

    /// Triangles traced: over all instances for two levels.
    pub fn triangle_count(&self) -> u64 {
        match self {
            SceneBvh::Flat { tris, .. } => tris.len() as u64,
            SceneBvh::Instanced(i) => i.instanced_primitives(),
        }
    }

    /// Converts the BVH into the wide layout as well, for [`bvhtrace_core::Traversal::Wide`]
    /// ([`FlatBvh::build_wide`]).
    pub fn build_wide(&mut self) {
        match self {
            SceneBvh::Flat { bvh, .. } => bvh.build_wide(),
            SceneBvh::Instanced(i) => i.build_wide(),
        }
    }

    /// True for two levels.
    pub fn is_two_level(&self) -> bool {
        matches!(self, SceneBvh::Instanced(_))
    }
}

impl Scene {
    /// True when [`Scene::tracing_bvh`] builds two levels: the scene places meshes more
    /// than once and `flatten` is not asked for. A scene of one instance traces as fast
    /// flattened (no top level to walk).
    pub fn traces_in_two_levels(&self, flatten: bool) -> bool {
        !flatten && self.instances.len() > 1
    }

    /// The BVH to trace this scene with: two levels when [`Scene::traces_in_two_levels`],
    /// else one BVH over the world-space triangles ([`Scene::flattened_triangles`]), each
    /// built with `opts`. The one rule the CLI and the viewer share.
    pub fn tracing_bvh(
        &self,
        opts: &BuildOptions,
        flatten: bool,
    ) -> Result<SceneBvh, TracingBvhError> {
        if self.traces_in_two_levels(flatten) {
            let i = self
                .instanced_bvh(opts)
                .map_err(TracingBvhError::TwoLevel)?;
            return Ok(self.with_masks(SceneBvh::Instanced(i)));
        }
        let tris = self
            .flattened_triangles()
            .map_err(TracingBvhError::Flatten)?;
        let bvh = FlatBvh::build(&tris, opts).map_err(TracingBvhError::Build)?;
        Ok(self.with_masks(SceneBvh::Flat { tris, bvh }))
    }

    /// `traced` with this scene's alpha masks attached ([`Scene::alpha_masks`]).
    fn with_masks(&self, mut traced: SceneBvh) -> SceneBvh {
        if let Some(m) = self.alpha_masks(&traced) {
            // The tables were made for this very tree, so they fit it.
            let _ = traced.set_masks(Some(std::sync::Arc::new(m)));
        }
        traced
    }

    /// [`Scene::tracing_bvh`] with each tree (the flattened triangles', or each mesh's
    /// under a top level the CPU builds) built by `build`, for example on the device
    /// (`GpuContext::build_bvh`). `build` sees a triangle list and returns a one-mesh
    /// BVH whose `prim` numbers that list, or its error in words.
    pub fn tracing_bvh_with(
        &self,
        flatten: bool,
        build: impl Fn(&[Triangle]) -> Result<FlatBvh, String>,
    ) -> Result<SceneBvh, TracingBvhError> {
        if self.traces_in_two_levels(flatten) {
            let (meshes, instances) = self.two_level_parts().map_err(TracingBvhError::TwoLevel)?;
            let trees = meshes
                .iter()
                .enumerate()
                .map(|(i, tris)| {
                    build(tris).map_err(|e| TracingBvhError::Builder(format!("mesh {i}: {e}")))
                })
                .collect::<Result<Vec<_>, _>>()?;
            let i = InstancedBvh::new(trees, instances).map_err(TracingBvhError::TwoLevel)?;
            return Ok(self.with_masks(SceneBvh::Instanced(i)));
        }
        let tris = self
            .flattened_triangles()
            .map_err(TracingBvhError::Flatten)?;
        let bvh = build(&tris).map_err(TracingBvhError::Builder)?;
        Ok(self.with_masks(SceneBvh::Flat { tris, bvh }))
    }

    /// The scene's meshes and instances as a two-level BVH, each mesh built with `opts`.
    /// Primitive ids number the instances' triangles in instance order, as
    /// [`Scene::flatten`] does (so the two forms name the same triangles); meshes without
    /// triangles and their instances are left out (they add no primitive). Instance `k` of
    /// the BVH is [`Scene::instances`]`[two_level_instances()[k]]`. A transform that is not
    /// finite or not invertible is an error naming the instance.
    pub fn instanced_bvh(&self, opts: &BuildOptions) -> Result<InstancedBvh, InstanceError> {
        let (meshes, instances) = self.two_level_parts()?;
        InstancedBvh::build(&meshes, instances, opts)
    }

    /// The scene instances the two-level BVH keeps, in its order (those of meshes with
    /// triangles).
    pub fn two_level_instances(&self) -> Vec<usize> {
        (0..self.instances.len())
            .filter(|&i| {
                self.meshes
                    .get(self.instances[i].mesh)
                    .is_some_and(|m| !m.is_empty())
            })
            .collect()
    }

    /// The meshes with triangles (as triangle lists) and the instances of them, mesh
    /// indices renumbered.
    fn two_level_parts(&self) -> Result<(Vec<Vec<Triangle>>, Vec<Instance>), InstanceError> {
        let mut index = vec![u32::MAX; self.meshes.len()];
        let mut meshes = Vec::new();
        for (i, m) in self.meshes.iter().enumerate() {
            if m.is_empty() {
                continue;
            }
            let tris = m
                .triangle_mesh()
                .triangles()
                .map_err(|e| InstanceError::BadMesh {
                    mesh: i,
                    problem: e.to_string(),
                })?;
            index[i] = meshes.len() as u32;
            meshes.push(tris);
        }
        let instances = self
            .two_level_instances()
            .into_iter()
            .map(|i| {
                let inst = &self.instances[i];
                let mut out = Instance::new(index[inst.mesh], Affine3A::from_mat4(inst.transform));
                out.user_id = i as u32;
                out
            })
            .collect();
        Ok((meshes, instances))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    #[test]
    fn a_callers_builder_makes_the_same_trees_and_its_errors_name_the_mesh() {
        let opts = BuildOptions::default();
        for (spec, flatten) in [("builtin:spheres", false), ("builtin:spheres", true)] {
            let scene = crate::load(spec).expect("loads");
            let want = scene.tracing_bvh(&opts, flatten).expect("builds");
            let got = scene
                .tracing_bvh_with(flatten, |t| {
                    FlatBvh::build(t, &opts).map_err(|e| e.to_string())
                })
                .expect("builds");
            assert_eq!(got.bvh().nodes(), want.bvh().nodes(), "{spec} {flatten}");
            assert_eq!(
                got.bvh().triangles(),
                want.bvh().triangles(),
                "{spec} {flatten}"
            );
            let err = scene
                .tracing_bvh_with(flatten, |_| Err("no device".into()))
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default();
            let named = if flatten {
                "no device"
            } else {
                "mesh 0: no device"
            };
            assert!(err.contains(named), "{err}");
        }
    }

    #[test]
    fn several_placements_trace_in_two_levels_unless_flattened() {
        let opts = BuildOptions::default();
        let spheres = crate::load("builtin:spheres").expect("loads");
        assert!(spheres.instances.len() > 1);
        assert!(spheres.traces_in_two_levels(false) && !spheres.traces_in_two_levels(true));
        let two = spheres.tracing_bvh(&opts, false).expect("builds");
        let flat = spheres.tracing_bvh(&opts, true).expect("builds");
        assert!(two.is_two_level() && !flat.is_two_level());
        assert_eq!(two.triangle_count(), flat.triangle_count());
        // Both forms name the same world-space triangles.
        let (a, b) = (
            two.triangle(7).expect("in range"),
            flat.triangle(7).expect("in range"),
        );
        for (p, q) in a.iter().zip(&b) {
            assert!((*p - *q).abs().max_element() < 1e-4, "{p} against {q}");
        }
        let cornell = crate::load("builtin:cornell").expect("loads");
        assert_eq!(cornell.instances.len(), 1);
        let one = cornell.tracing_bvh(&opts, false).expect("builds");
        assert!(!one.is_two_level());
        assert_eq!(one.triangle_count(), cornell.triangle_count() as u64);
    }

    #[test]
    fn a_bad_placement_is_an_error_naming_the_level() {
        let mut s = crate::load("builtin:spheres").expect("loads");
        s.instances[1].transform = Mat4::from_scale(glam::Vec3::ZERO);
        let Err(e) = s.tracing_bvh(&BuildOptions::default(), false) else {
            panic!("a singular transform cannot be inverted");
        };
        assert!(matches!(e, TracingBvhError::TwoLevel(_)), "{e}");
        assert!(
            e.to_string().starts_with("two-level BVH build failed"),
            "{e}"
        );
    }
}
