//! A scene as a two-level BVH: one bottom-level BVH per mesh however many instances use
//! it, a top level over the instances ([`bvhtrace_core::InstancedBvh`]).

use bvhtrace_core::{BuildOptions, Instance, InstanceError, InstancedBvh, Triangle};
use glam::Affine3A;

use crate::Scene;

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
