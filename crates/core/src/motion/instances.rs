//! Moving instances: meshes placed by transforms that move over the shutter, as Embree's
//! instances with time steps move (the matrices interpolated entry by entry between
//! evenly spaced steps), traced in two levels: a moving top level over the instances, each
//! mesh's own static tree below, walked with the ray taken into the instance's space at
//! its time.

use bytemuck::{Pod, Zeroable};
use glam::{Affine3A, Mat4, Vec3, Vec4};

use crate::build::{BuildError, BuildOptions};
use crate::flat::{FlatBvh, FlatInstance, FlatNode, FlatTriangle, INSTANCE_LEAF};
use crate::geometry::Aabb;
use crate::instance::{InstanceError, check_transform, world_box};
use crate::mesh::Triangle;
use crate::ray::{Counters, Hit, Ray};
use crate::traverse::{Best, Query, TraceOptions, Traversal, trace_ray};

use super::tree::{TimeTree, trace_all};
use super::{MAX_TIME_STEPS, MotionBox, TimeBounds, time_segment};

/// A mesh placed by a transform that may move.
#[derive(Clone, Debug, PartialEq)]
pub struct MovingInstance {
    /// The mesh it places: an index into the meshes given to [`MotionInstancedBvh::build`].
    pub mesh: usize,
    /// Its object-to-world transforms (affine) at the time steps, evenly over the shutter;
    /// one for an instance that stays where it is.
    pub transforms: Vec<Mat4>,
}

impl MovingInstance {
    /// Its transform at the time of `(s, f)` ([`time_segment`]): step `s`'s and `s + 1`'s
    /// mixed entry by entry, `(1 - f) a + f b`.
    pub fn transform_at(&self, (s, f): (usize, f32)) -> Mat4 {
        match self.transforms.len() {
            1 => self.transforms[0],
            _ => self.transforms[s] * (1.0 - f) + self.transforms[s + 1] * f,
        }
    }

    /// Its world-to-object transform at the time of `seg`, as rows
    /// ([`FlatInstance::world_to_object`]): [`invert_rows`] of [`rows_of`] its transform
    /// then, the arithmetic the kernel of moving instances repeats.
    pub fn world_to_object_at(&self, seg: (usize, f32)) -> [[f32; 4]; 3] {
        invert_rows(&rows_of(&self.transform_at(seg)))
    }
}

/// The three rows of an affine transform (its last row is `0, 0, 0, 1`).
pub fn rows_of(m: &Mat4) -> [[f32; 4]; 3] {
    [m.row(0), m.row(1), m.row(2)].map(|r| r.to_array())
}

/// The inverse of the affine transform whose rows are `m`, as rows: its 3x3 part's inverse
/// is the cross products of its columns over its determinant, and the translation is taken
/// back through it. glam's `Vec3::cross` and `Vec3::dot` (scalar, no fused operations),
/// which the kernels' `bvh_invert_rows` writes out in their order, so the CPU and the
/// device take a ray into a moving instance alike. A singular transform gives infinite or
/// NaN rows (the ray then enters nothing).
pub fn invert_rows(m: &[[f32; 4]; 3]) -> [[f32; 4]; 3] {
    let col = |j: usize| Vec3::new(m[0][j], m[1][j], m[2][j]);
    let (c0, c1, c2, t) = (col(0), col(1), col(2), col(3));
    let rows = [c1.cross(c2), c2.cross(c0), c0.cross(c1)];
    let inv = 1.0 / c0.dot(rows[0]);
    rows.map(|r| {
        let s = r * inv;
        s.extend(-s.dot(t)).to_array()
    })
}

/// Why moving instances were refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InstanceMotionError {
    /// An instance names a mesh that is not there.
    #[error("instance {instance}: mesh {mesh} does not exist ({meshes} meshes)")]
    NoMesh {
        /// The instance.
        instance: usize,
        /// The mesh it names.
        mesh: usize,
        /// How many meshes there are.
        meshes: usize,
    },
    /// An instance has neither one transform nor as many as the others' steps.
    #[error(
        "instance {instance} has {got} transforms; each has 1 or {steps} (at most {MAX_TIME_STEPS})"
    )]
    Steps {
        /// The instance.
        instance: usize,
        /// Its transforms.
        got: usize,
        /// The steps of the instances that move.
        steps: usize,
    },
    /// A transform is not finite, not affine, or not invertible (in f32).
    #[error("instance {instance}, time step {step}: {problem}")]
    Transform {
        /// The instance.
        instance: usize,
        /// The step.
        step: usize,
        /// What is wrong with it.
        problem: String,
    },
    /// There is no instance to build over.
    #[error("no instances to build over")]
    NoInstances,
    /// A mesh could not be built.
    #[error("mesh {mesh}: {error}")]
    Mesh {
        /// The mesh.
        mesh: usize,
        /// Why.
        error: BuildError,
    },
}

/// Moving instances over static meshes, in two levels (see the module docs). Primitive
/// ids are numbered as the flattened scene numbers them: instance `i`'s triangles follow
/// those of the instances before it, in its mesh's order.
#[derive(Clone, Debug)]
pub struct MotionInstancedBvh {
    top: TimeTree,
    meshes: Vec<FlatBvh>,
    /// The meshes' triangles in input order, for [`MotionInstancedBvh::triangle_at`].
    mesh_triangles: Vec<Vec<Triangle>>,
    /// The instances in the top level's leaf order, each with its first primitive id.
    instances: Vec<(MovingInstance, u32)>,
    /// `(first primitive id, index into instances)`, by first id.
    by_first: Vec<(u32, usize)>,
}

impl MotionInstancedBvh {
    /// Builds each mesh's tree and the moving top level over the instances' boxes at
    /// every step (`bounds` as for [`super::MotionBvh`]), both with `opts`.
    pub fn build(
        meshes: &[Vec<Triangle>],
        instances: Vec<MovingInstance>,
        opts: &BuildOptions,
        bounds: TimeBounds,
    ) -> Result<MotionInstancedBvh, InstanceMotionError> {
        let steps = check(meshes, &instances)?;
        let trees = (meshes.iter().enumerate())
            .map(|(mesh, t)| {
                FlatBvh::build(t, opts).map_err(|error| InstanceMotionError::Mesh { mesh, error })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut boxes = Vec::with_capacity(instances.len() * steps);
        for (instance, inst) in instances.iter().enumerate() {
            let object = trees[inst.mesh].bounds();
            for k in 0..steps {
                let step = k.min(inst.transforms.len() - 1);
                let placed = placement(instance, step, &inst.transforms[step])?;
                boxes.push(world_box(&placed, &object));
            }
        }
        // Every mesh built, so the options are good: the top level cannot fail. One
        // instance per leaf, as the kernel's layout has it ([`MovingInstancesLayout`]).
        let top_opts = BuildOptions {
            max_leaf_size: 1,
            ..*opts
        };
        let (top, order) = TimeTree::build(&boxes, steps, &top_opts, bounds)
            .map_err(|_| InstanceMotionError::NoInstances)?;
        let mut first = Vec::with_capacity(instances.len());
        let mut next = 0u32;
        for inst in &instances {
            first.push(next);
            next += trees[inst.mesh].triangle_count() as u32;
        }
        let instances: Vec<(MovingInstance, u32)> = order
            .iter()
            .map(|&i| (instances[i as usize].clone(), first[i as usize]))
            .collect();
        let mut by_first: Vec<(u32, usize)> = (instances.iter().enumerate())
            .map(|(j, (_, f))| (*f, j))
            .collect();
        by_first.sort_unstable();
        Ok(MotionInstancedBvh {
            top,
            meshes: trees,
            mesh_triangles: meshes.to_vec(),
            instances,
            by_first,
        })
    }

    /// Number of time steps of the top level.
    pub fn time_steps(&self) -> usize {
        self.top.steps
    }

    /// The box around every instance over the whole shutter.
    pub fn bounds(&self) -> Aabb {
        self.top.nodes[0].aabb()
    }

    /// Triangle `prim` (the flattened numbering) in world space where its instance places
    /// it at `time`; `None` for an id past the last.
    pub fn triangle_at(&self, prim: u32, time: f32) -> Option<Triangle> {
        let k = self
            .by_first
            .partition_point(|&(f, _)| f <= prim)
            .checked_sub(1)?;
        let (first, j) = self.by_first[k];
        let (inst, _) = &self.instances[j];
        let tri = self.mesh_triangles[inst.mesh].get((prim - first) as usize)?;
        let m = inst.transform_at(time_segment(time, self.top.steps));
        Some(tri.map(|p| m.transform_point3(p)))
    }

    /// Every triangle placed, in world space where its instance places it at `time`, by
    /// primitive id (what the f64 oracle judges a ray at that time against).
    pub fn at(&self, time: f32) -> Vec<Triangle> {
        let seg = time_segment(time, self.top.steps);
        (self.by_first.iter())
            .flat_map(|&(_, j)| {
                let (inst, _) = &self.instances[j];
                let m = inst.transform_at(seg);
                let tris = &self.mesh_triangles[inst.mesh];
                tris.iter().map(move |t| t.map(|p| m.transform_point3(p)))
            })
            .collect()
    }

    /// Triangles placed: every instance's mesh's, counted once per instance.
    pub fn triangle_count(&self) -> usize {
        (self.instances.iter())
            .map(|(i, _)| self.mesh_triangles[i.mesh].len())
            .sum()
    }

    /// Levels of the top tree.
    pub fn depth(&self) -> u32 {
        self.top.depth
    }

    /// Bytes of both levels: the top level's nodes and step boxes, the meshes' nodes and
    /// triangles.
    pub fn byte_size(&self) -> usize {
        let (n, t, _) = self.meshes.iter().fold((0, 0, 0), |(a, b, c), m| {
            let (x, y, z) = m.byte_sizes();
            (a + x, b + y, c + z)
        });
        self.top.byte_size() + n + t
    }

    /// How the top level bounds time.
    pub fn time_bounds(&self) -> TimeBounds {
        self.top.bounds
    }

    /// The top level's nodes (depth first, one instance per leaf: a leaf's first is its
    /// instance's index in [`MotionInstancedBvh::placed`]; each box over the whole shutter).
    pub fn top_nodes(&self) -> &[FlatNode] {
        &self.top.nodes
    }

    /// [`MotionInstancedBvh::top_nodes`] with each leaf an instance leaf
    /// ([`INSTANCE_LEAF`]): one instance per leaf, its index in leaf order the leaf's first.
    pub fn top_instance_nodes(&self) -> Vec<FlatNode> {
        (self.top.nodes.iter())
            .map(|n| match n.is_leaf() {
                true => FlatNode {
                    meta: (1 << 2) | INSTANCE_LEAF,
                    ..*n
                },
                false => *n,
            })
            .collect()
    }

    /// The top level's nodes' boxes at every time step: node `i`'s at step `k` is entry
    /// `i * time_steps() + k` (empty with [`TimeBounds::Merged`]).
    pub fn top_step_boxes(&self) -> &[MotionBox] {
        &self.top.step_boxes
    }

    /// The meshes' trees, as [`MovingInstance::mesh`] numbers them.
    pub fn mesh_trees(&self) -> &[FlatBvh] {
        &self.meshes
    }

    /// The instances in the top level's leaf order, each with its first primitive id.
    pub fn placed(&self) -> &[(MovingInstance, u32)] {
        &self.instances
    }

    /// Both levels joined as the kernel of moving instances reads them (see
    /// [`MovingInstancesLayout`]).
    pub fn kernel_layout(&self) -> MovingInstancesLayout {
        let mut nodes = self.top_instance_nodes();
        let (mut triangles, mut roots) = (Vec::new(), Vec::new());
        let mut depth = 0;
        for mesh in &self.meshes {
            let (base, tri_base) = (nodes.len() as u32, triangles.len() as u32);
            roots.push(base);
            nodes.extend(mesh.nodes().iter().map(|n| FlatNode {
                right_or_first: n.right_or_first + if n.is_leaf() { tri_base } else { base },
                ..*n
            }));
            triangles.extend_from_slice(mesh.triangles());
            depth = depth.max(mesh.depth() + 1);
        }
        let mut transforms = Vec::new();
        let instances = (self.instances.iter())
            .map(|(inst, first)| {
                let record = MovingInstanceRecord {
                    root: roots[inst.mesh],
                    prim_base: *first,
                    first_transform: transforms.len() as u32,
                    transforms: inst.transforms.len() as u32,
                };
                transforms.extend(inst.transforms.iter().map(rows_of));
                record
            })
            .collect();
        MovingInstancesLayout {
            nodes,
            step_boxes: self.top.step_boxes.clone(),
            triangles,
            instances,
            transforms,
            depth: self.top.depth + depth,
        }
    }

    /// Traces one ray at `time` (clamped to `[0, 1]`; a NaN time is an invalid ray): the
    /// closest hit (the walks' hit rule over every instance) or any hit.
    pub fn trace(&self, ray: &Ray, time: f32, query: Query) -> (Hit, Counters) {
        self.top.trace(ray, time, query, |_, seg, n, best, c| {
            let first = n.right_or_first as usize;
            let mut taken = false;
            for j in first..first + n.count() as usize {
                taken |= self.visit_instance(j, ray, seg, query, best, c);
                if taken && query == Query::Any {
                    break;
                }
            }
            taken
        })
    }

    /// Traces `rays[i]` at `times[i]` in parallel (see [`MotionInstancedBvh::trace`]).
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace_rays(&self, rays: &[Ray], times: &[f32], query: Query) -> Vec<Hit> {
        trace_all(rays, times, |r, t| self.trace(r, t, query).0)
    }

    /// Walks instance `j`'s mesh with the ray in its space at the ray's time, for hits
    /// nearer than the best (or as near, for the hit rule's lower id); true when one was
    /// taken.
    fn visit_instance(
        &self,
        j: usize,
        ray: &Ray,
        seg: (usize, f32),
        query: Query,
        best: &mut Best,
        c: &mut Counters,
    ) -> bool {
        let (inst, first) = &self.instances[j];
        let placed = FlatInstance {
            world_to_object: inst.world_to_object_at(seg),
            ..FlatInstance::zeroed()
        };
        let object = Ray {
            t_max: if best.found { best.t.next_up() } else { best.t },
            ..placed.ray_to_object(ray)
        };
        if !object.is_valid() {
            return false;
        }
        let opts = TraceOptions::new(Traversal::FullStack, query).with_counters(true);
        let (h, k) = trace_ray(&self.meshes[inst.mesh], &object, &opts);
        *c += k;
        h.is_hit() && best.offer(h.t, first + h.prim, h.u, h.v)
    }
}

/// One moving instance as the kernel reads it: where its mesh's tree starts among the
/// joined nodes, its first primitive id, and its transforms. GPU layout: WGSL
/// `BvhMovingInstance` in `shaders/bvh_motion_instances.wgsl` (16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MovingInstanceRecord {
    /// Its mesh's root in [`MovingInstancesLayout::nodes`].
    pub root: u32,
    /// Its first primitive id: a hit on its mesh's triangle `p` reports `prim_base + p`.
    pub prim_base: u32,
    /// Its first transform in [`MovingInstancesLayout::transforms`].
    pub first_transform: u32,
    /// How many it has: 1 (it stays where it is) or the time steps.
    pub transforms: u32,
}

/// A [`MotionInstancedBvh`] joined into one tree for a device: the top level's nodes
/// (each leaf an instance leaf, [`INSTANCE_LEAF`], naming its instance) then every mesh's,
/// with child and triangle indices moved to where they now are; the top level's boxes at
/// every step; the meshes' triangles one after another; the instances in the top level's
/// leaf order; and their object-to-world transforms as rows ([`rows_of`]). A walk enters
/// an instance with [`MovingInstance::world_to_object_at`] the ray's time.
#[derive(Clone, Debug, PartialEq)]
pub struct MovingInstancesLayout {
    /// The nodes: the top level's `2n - 1` for `n` instances (one per leaf) first.
    pub nodes: Vec<FlatNode>,
    /// The top level's node `i`'s box at step `k`: entry `i * steps + k` (empty with
    /// merged bounds).
    pub step_boxes: Vec<MotionBox>,
    /// The meshes' triangles, each mesh's in its tree's leaf order.
    pub triangles: Vec<FlatTriangle>,
    /// The instances, in the top level's leaf order.
    pub instances: Vec<MovingInstanceRecord>,
    /// The instances' transforms, each as three rows.
    pub transforms: Vec<[[f32; 4]; 3]>,
    /// At most this many nodes on a full-stack walk's stack: the top level's depth and the
    /// deepest mesh's.
    pub depth: u32,
}

/// The common step count of `instances` (1 when none moves), after checking each.
fn check(
    meshes: &[Vec<Triangle>],
    instances: &[MovingInstance],
) -> Result<usize, InstanceMotionError> {
    if instances.is_empty() {
        return Err(InstanceMotionError::NoInstances);
    }
    let steps = instances
        .iter()
        .map(|i| i.transforms.len())
        .max()
        .unwrap_or(1);
    for (instance, inst) in instances.iter().enumerate() {
        if inst.mesh >= meshes.len() {
            return Err(InstanceMotionError::NoMesh {
                instance,
                mesh: inst.mesh,
                meshes: meshes.len(),
            });
        }
        let got = inst.transforms.len();
        if !(got == 1 || got == steps) || steps > MAX_TIME_STEPS || got == 0 {
            return Err(InstanceMotionError::Steps {
                instance,
                got,
                steps,
            });
        }
    }
    Ok(steps.max(2))
}

/// Instance `instance`'s transform at `step` in f64, checked as the static two levels check
/// an instance's ([`check_transform`]), and affine.
fn placement(
    instance: usize,
    step: usize,
    m: &Mat4,
) -> Result<glam::DAffine3, InstanceMotionError> {
    let refused = |problem: String| InstanceMotionError::Transform {
        instance,
        step,
        problem,
    };
    if m.row(3) != Vec4::W {
        return Err(refused(
            "the transform is not affine (its last row is not 0, 0, 0, 1)".into(),
        ));
    }
    match check_transform(instance, &Affine3A::from_mat4(*m)) {
        Ok((placed, _)) => Ok(placed),
        Err(InstanceError::BadInstance { problem, .. }) => Err(refused(problem)),
        Err(e) => Err(refused(e.to_string())),
    }
}
