//! A scene as a two-level BVH: one bottom-level BVH per mesh however many instances use
//! it, a top level over the instances ([`bvhtrace_core::InstancedBvh`]).

use bvhtrace_core::{BuildOptions, FlatBvh, Instance, InstanceError, InstancedBvh, Triangle};
use glam::Affine3A;

use crate::Scene;

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
