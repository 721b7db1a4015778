//! What a hit answers beyond its primitive id: the instance it lies in (index and user
//! id) and the primitive within that instance's mesh, as Embree's `instID`/`primID`; and,
//! for a two-level BVH, where secondary rays leave it, the CPU twin of the WGSL library's
//! `bvh_hit_surface`.
//!
//! Every tracer attaches an [`InstanceTable`] to its [`TraceOutput`] for a two-level BVH
//! ([`TraceOutput::instance_hit`]), so no caller needs the `InstancedBvh` to split ids.

use std::sync::Arc;

use glam::Vec3;

use crate::flat::{FlatBvh, FlatInstance};
use crate::mesh::Triangle;
use crate::ray::{Hit, INCOMPLETE, Ray};
use crate::surface::{SurfacePoint, offset_ray_origin};
use crate::traverse::TraceOutput;

/// The instances of a two-level BVH as its hits need them: each one's first primitive id
/// and user id, in `FlatBvh::instances` order (that of `InstancedBvh::instances`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct InstanceTable {
    /// `FlatInstance::prim_base` of each instance, non-decreasing.
    prim_base: Vec<u32>,
    /// `FlatInstance::user_id` of each instance.
    user_id: Vec<u32>,
}

/// One hit's place: the instance it lies in and the primitive within the instance's mesh.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct InstanceHit {
    /// The instance's index in `FlatBvh::instances` (and `InstancedBvh::instances`).
    pub instance: u32,
    /// The instance's user id (`Instance::user_id`).
    pub user_id: u32,
    /// The primitive's index within the instance's mesh.
    pub prim: u32,
}

impl InstanceTable {
    /// The table of `bvh`'s instances; `None` for one mesh. Cheap (two `u32` per
    /// instance): the tracers build it at upload and share it with every output.
    pub fn of(bvh: &FlatBvh) -> Option<Arc<InstanceTable>> {
        bvh.is_instanced().then(|| {
            Arc::new(InstanceTable {
                prim_base: bvh.instances.iter().map(|i| i.prim_base).collect(),
                user_id: bvh.instances.iter().map(|i| i.user_id).collect(),
            })
        })
    }

    /// Number of instances.
    pub fn len(&self) -> usize {
        self.prim_base.len()
    }

    /// True when there is no instance.
    pub fn is_empty(&self) -> bool {
        self.prim_base.is_empty()
    }

    /// The instance and mesh primitive of primitive id `prim` as a trace reports it;
    /// `None` for a miss code (`MISS`, `INVALID_RAY`, `INCOMPLETE`) or an id before the
    /// first instance's. An id past the last instance's mesh is not checked (no trace
    /// reports one; `InstancedBvh::locate` knows the meshes' sizes).
    pub fn locate(&self, prim: u32) -> Option<InstanceHit> {
        if prim >= INCOMPLETE {
            return None;
        }
        let i = self
            .prim_base
            .partition_point(|&b| b <= prim)
            .checked_sub(1)?;
        Some(InstanceHit {
            instance: i as u32,
            user_id: self.user_id[i],
            prim: prim - self.prim_base[i],
        })
    }
}

impl TraceOutput {
    /// Ray `i`'s hit located in its instance; `None` for a miss (or an invalid or
    /// incomplete ray), for a one-mesh BVH (whose `hits[i].prim` is already the mesh's
    /// primitive), and for `i` out of range.
    pub fn instance_hit(&self, i: usize) -> Option<InstanceHit> {
        let table = self.instances.as_ref()?;
        table.locate(self.hits.get(i)?.prim)
    }

    /// [`TraceOutput::instance_hit`] of every ray, in ray order.
    pub fn instance_hits(&self) -> impl Iterator<Item = Option<InstanceHit>> + '_ {
        (0..self.hits.len()).map(|i| self.instance_hit(i))
    }
}

impl FlatInstance {
    /// An object-space normal in world space: multiplied by the transpose of
    /// `world_to_object` (the inverse transpose of the object-to-world transform), product
    /// by product, left to right: the arithmetic of WGSL's `bvh_normal_to_world`. Not
    /// normalised.
    pub fn normal_to_world(&self, n: Vec3) -> Vec3 {
        let m = &self.world_to_object;
        let col = |k: usize| m[0][k] * n.x + m[1][k] * n.y + m[2][k] * n.z;
        Vec3::new(col(0), col(1), col(2))
    }
}

/// `n` normalised (`n * (1 / sqrt(n . n))`, glam's `normalize`) and flipped to face
/// against `dir`; `-dir` normalised for a zero `n`. What `surface::facing_normal` does
/// after its cross product.
fn face_against(n: Vec3, dir: Vec3) -> Vec3 {
    let n = if n.length_squared() > 0.0 {
        n.normalize()
    } else {
        -dir.normalize()
    };
    if n.dot(dir) > 0.0 { -n } else { n }
}

/// Where secondary rays leave `hit`, a hit of the world-space `ray` on `tri` (the
/// triangle's corners in its mesh's space) inside `inst`: the CPU twin of WGSL's
/// `bvh_hit_surface` on a two-level BVH, operation for operation. The normal is the
/// object-space `(v1 - v0) x (v2 - v0)` taken to world space
/// ([`FlatInstance::normal_to_world`]), normalised and facing the incoming ray; the point
/// is `origin + t dir` in world space (the object-to-world transform is not uploaded),
/// moved off the surface by [`offset_ray_origin`]. For one mesh, `Hit::surface` is the
/// twin (the point from the barycentrics).
pub fn instance_surface(hit: &Hit, tri: &Triangle, inst: &FlatInstance, ray: &Ray) -> SurfacePoint {
    let (o, d) = (Vec3::from(ray.origin), Vec3::from(ray.dir));
    let n_object = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
    let normal = face_against(inst.normal_to_world(n_object), d);
    let p = Vec3::new(o.x + d.x * hit.t, o.y + d.y * hit.t, o.z + d.z * hit.t);
    SurfacePoint {
        origin: offset_ray_origin(p, normal),
        normal,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::facing_normal;

    #[test]
    fn locate_splits_ids_and_refuses_miss_codes() {
        let t = InstanceTable {
            prim_base: vec![0, 10, 10, 25],
            user_id: vec![7, 8, 9, 42],
        };
        let at = |p| t.locate(p).map(|h| (h.instance, h.user_id, h.prim));
        assert_eq!(at(0), Some((0, 7, 0)));
        assert_eq!(at(9), Some((0, 7, 9)));
        // An empty mesh's instance (8) is never the answer: the last of equal bases wins.
        assert_eq!(at(10), Some((2, 9, 0)));
        assert_eq!(at(30), Some((3, 42, 5)));
        assert_eq!(at(crate::MISS), None);
        assert_eq!(at(crate::INVALID_RAY), None);
        assert_eq!(at(INCOMPLETE), None);
    }

    #[test]
    fn identity_instance_faces_as_the_one_mesh_normal() {
        let inst = FlatInstance {
            world_to_object: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
            ],
            root: 0,
            prim_base: 0,
            mask: 0xff,
            user_id: 0,
        };
        let tri: Triangle = [
            Vec3::ZERO,
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(0.0, 3.0, 0.0),
        ];
        let ray = Ray::new(Vec3::new(0.5, 0.5, 4.0), Vec3::new(0.1, 0.0, -1.0));
        let hit = Hit {
            t: 4.0,
            prim: 0,
            u: 0.25,
            v: 0.125,
        };
        let s = instance_surface(&hit, &tri, &inst, &ray);
        assert_eq!(s.normal, facing_normal(&tri, Vec3::from(ray.dir)));
        assert_eq!(s.normal, Vec3::Z);
        assert!(
            s.origin.z > 0.0,
            "the origin is on the incoming side: {}",
            s.origin
        );
    }
}
