//! Moving instances in the CPU layout: a [`MotionInstancedBvh`]'s moving top level
//! converted as a moving mesh's tree is ([`crate::moving`], one instance per leaf child),
//! and each static mesh converted once into the static layout ([`CpuBvh`]). At an
//! instance the walk does what the core's moving walk does (`MotionInstancedBvh::trace`):
//! the ray taken into the instance's space by its transform at the ray's time
//! (`MovingInstance::world_to_object_at`, then the core's own `FlatInstance::ray_to_object`),
//! its interval ended just past the best hit so far, the mesh walked from a fresh start (the
//! static layout's walk, which answers as the core's full stack), and its hit offered to
//! the best under the walks' hit rule with the instance's first primitive id added. So
//! the closest hit is the core walk's, bit for bit, under the layout's one exception.

use std::borrow::Borrow;

use bvhtrace_core::motion::{MotionInstancedBvh, MovingInstance, TimeBounds, time_segment};
use bvhtrace_core::{FlatInstance, Hit, Query, Ray};
use bytemuck::Zeroable;

use crate::Isa;
use crate::instanced::{self, MeshWalk, pop_still_hit};
use crate::lanes::{self, Lanes, Wide};
use crate::layout::{ConvertError, CpuBvh, LEAF, Level};
use crate::moving::{At, MovingCpuBvh, MovingTree, in_runs};
use crate::single::{Best, Entry, Site, WalkTree, order, untraced};
use crate::tests4::{self, MINMAX, Prepared, RayLanes, box8};

/// A [`MotionInstancedBvh`] in the CPU layout (see the module docs), converted by
/// [`MovingInstancesCpuBvh::from_motion`].
#[derive(Clone, Debug)]
pub struct MovingInstancesCpuBvh {
    /// The moving top level; a leaf child is `LEAF | instance`.
    top: MovingCpuBvh,
    /// Each mesh in the static layout.
    meshes: Vec<CpuBvh>,
    /// The instances in the top level's leaf order, each with its first primitive id.
    instances: Vec<(MovingInstance, u32)>,
    /// Entries the deepest mesh's walk takes.
    mesh_stack: usize,
}

impl MovingInstancesCpuBvh {
    /// Converts `m`: its top level, and each mesh once.
    pub fn from_motion(m: &MotionInstancedBvh) -> Result<MovingInstancesCpuBvh, ConvertError> {
        let nodes = m.top_instance_nodes();
        let tree = MovingTree {
            nodes: &nodes,
            step_boxes: m.top_step_boxes(),
            steps: m.time_steps(),
            bounds: m.time_bounds(),
        };
        let level = Level::Top(m.placed().len() as u32);
        let top = MovingCpuBvh::convert(&tree, level, &[], 0)?;
        let meshes = (m.mesh_trees().iter())
            .map(CpuBvh::from_flat)
            .collect::<Result<Vec<_>, _>>()?;
        let mesh_stack = (meshes.iter())
            .map(crate::single::stack_size)
            .max()
            .unwrap_or(0);
        Ok(MovingInstancesCpuBvh {
            top,
            meshes,
            instances: m.placed().to_vec(),
            mesh_stack,
        })
    }

    /// Number of time steps of the top level.
    pub fn time_steps(&self) -> usize {
        self.top.steps
    }

    /// Bytes of the top level (nodes and their step boxes) and of the meshes (nodes and
    /// blocks), each mesh counted once.
    pub fn byte_sizes(&self) -> (usize, usize) {
        let (n, b) = self.top.byte_sizes();
        let meshes = (self.meshes.iter())
            .map(|m| {
                let (n, b) = m.byte_sizes();
                n + b
            })
            .sum::<usize>();
        (n + b, meshes)
    }

    /// Traces `rays[i]` at `times[i]` (clamped to `[0, 1]`; a NaN time is an invalid ray)
    /// on all threads of the current rayon pool, with the fastest instruction set this CPU
    /// has: the closest hit (`MotionInstancedBvh::trace`'s) or any hit.
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace_rays(&self, rays: &[Ray], times: &[f32], query: Query) -> Vec<Hit> {
        self.trace_rays_with(rays, times, query, Isa::detect())
    }

    /// [`MovingInstancesCpuBvh::trace_rays`] with the instruction set `isa` (or the fastest
    /// this CPU has, when it lacks `isa`): the answers are the same whichever runs.
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace_rays_with(&self, rays: &[Ray], times: &[f32], query: Query, isa: Isa) -> Vec<Hit> {
        in_runs(rays, times, |r, t, h| self.trace_run(r, t, query, isa, h))
    }

    /// One thread's run of rays into `hits`.
    fn trace_run(&self, rays: &[Ray], times: &[f32], query: Query, isa: Isa, hits: &mut [Hit]) {
        let top = (crate::layout::WIDTH - 1) * self.top.depth as usize + 4;
        let mut stack = vec![Entry::default(); top + self.mesh_stack];
        let s = stack.as_mut_slice();
        type P = lanes::Portable;
        type PP = lanes::Pair<P>;
        match isa.or_available() {
            Isa::Portable => {
                run::<P, PP, instanced::Plain<P, PP>>(self, rays, times, query, hits, s)
            }
            #[cfg(target_arch = "x86_64")]
            Isa::Sse2 => {
                type S = lanes::Sse;
                type SP = lanes::Pair<S>;
                run::<S, SP, instanced::Plain<S, SP>>(self, rays, times, query, hits, s)
            }
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `or_available` returned Avx2, so the CPU has what `Isa::Avx2` needs.
            Isa::Avx2 => unsafe { run_avx2(self, rays, times, query, hits, s) },
            #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
            Isa::Simd128 => {
                type S = lanes::Simd128;
                type SP = lanes::Pair<S>;
                run::<S, SP, instanced::Plain<S, SP>>(self, rays, times, query, hits, s)
            }
            #[allow(unreachable_patterns)]
            _ => unreachable!("or_available gives only what this target compiles"),
        }
    }
}

/// The walks over `rays` at `times`, monomorphised for the lanes, the mesh walks `M`, the
/// query and the bounds.
#[inline(always)]
fn run<L: Lanes, W: Wide, M: MeshWalk>(
    bvh: &MovingInstancesCpuBvh,
    rays: &[Ray],
    times: &[f32],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    let linear = bvh.top.bounds == TimeBounds::Linear;
    match (query, linear) {
        (Query::Closest, true) => run_as::<L, W, M, false, true>(bvh, rays, times, hits, stack),
        (Query::Closest, false) => run_as::<L, W, M, false, false>(bvh, rays, times, hits, stack),
        (Query::Any, true) => run_as::<L, W, M, true, true>(bvh, rays, times, hits, stack),
        (Query::Any, false) => run_as::<L, W, M, true, false>(bvh, rays, times, hits, stack),
    }
}

/// [`run`] for one query and one kind of bounds: rays prepared eight at a time, then each
/// walked at its time.
#[inline(always)]
fn run_as<L: Lanes, W: Wide, M: MeshWalk, const ANY: bool, const LINEAR: bool>(
    bvh: &MovingInstancesCpuBvh,
    rays: &[Ray],
    times: &[f32],
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    // Plain loops, no closures: a closure is compiled apart from the AVX2 caller.
    let mut start = 0;
    while start < rays.len() {
        let end = (start + tests4::RAYS).min(rays.len());
        let group = &rays[start..end];
        let p = Prepared::for_boxes::<W>(group);
        let enter = p.may_enter::<W>(bvh.top.scene_box.as_ref());
        for (i, ray) in group.iter().enumerate() {
            let time = times[start + i];
            hits[start + i] = if p.valid >> i & 1 == 0 || time.is_nan() {
                untraced(ray)
            } else if enter >> i & 1 == 0 || bvh.top.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
                Best::start(ray).into_hit()
            } else {
                // One step: instances that stay where they are, at every time.
                let (s, f) = match bvh.top.steps {
                    1 => (0, 0.0),
                    steps => time_segment(time, steps),
                };
                let q = RayLanes::<L, W>::from_prepared(&p, ray, i);
                let w = Top {
                    bvh,
                    at: At::<LINEAR> {
                        bvh: &bvh.top,
                        s,
                        f,
                    },
                    ray,
                    q: &q,
                };
                let signed = ray.t_min < 0.0 || q.parallel;
                for_ray_kind!(q.parallel, signed, q.kz, |SIGNED, PARALLEL, KZ| {
                    top::<L, W, M, ANY, LINEAR, SIGNED, PARALLEL, KZ>(&w, stack)
                })
            };
        }
        start = end;
    }
}

/// What the top-level walk reads: the tree at the ray's time, the world ray and its lanes.
struct Top<'a, L, W, const LINEAR: bool> {
    bvh: &'a MovingInstancesCpuBvh,
    at: At<'a, LINEAR>,
    ray: &'a Ray,
    q: &'a RayLanes<L, W>,
}

/// The top-level walk from node 0 (as `instanced::top`, the nodes at the ray's time);
/// `SIGNED`, `PARALLEL` and `KZ` as in [`box8`]. Inlined only where optimised (see
/// `single::walk`).
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn top<
    L: Lanes,
    W: Wide,
    M: MeshWalk,
    const ANY: bool,
    const LINEAR: bool,
    const SIGNED: bool,
    const PARALLEL: bool,
    const KZ: usize,
>(
    w: &Top<'_, L, W, LINEAR>,
    stack: &mut [Entry],
) -> Hit {
    let q = w.q;
    let mut best = Best::start(w.ray);
    let mut sp = 0;
    let mut child = 0u32;
    loop {
        if child & LEAF == 0 {
            let node = w.at.node(child);
            let n = node.borrow();
            let b = box8::<L, W, SIGNED, PARALLEL, KZ, MINMAX>(n, q, best.t, !ANY && best.found);
            if b.hit != 0 {
                child = order::<W, ANY>(n, &b, stack, &mut sp);
                continue;
            }
        } else if visit::<L, W, M, ANY, LINEAR>(
            w,
            (child & !LEAF) as usize,
            &mut best,
            &mut stack[sp..],
        ) && ANY
        {
            return best.into_hit();
        }
        match pop_still_hit::<ANY>(stack, &mut sp, q.t_max_s, &best) {
            Some(c) => child = c,
            None => return best.into_hit(),
        }
    }
}

/// Instance `j` at the ray's time, as the core's `visit_instance`: the ray in its space by
/// its transform then, its interval ended just past the best so far, its mesh walked from
/// a fresh start; true when the mesh's hit was taken.
#[inline(always)]
fn visit<L: Lanes, W: Wide, M: MeshWalk, const ANY: bool, const LINEAR: bool>(
    w: &Top<'_, L, W, LINEAR>,
    j: usize,
    best: &mut Best,
    stack: &mut [Entry],
) -> bool {
    let (inst, first) = &w.bvh.instances[j];
    let placed = FlatInstance {
        world_to_object: inst.world_to_object_at((w.at.s, w.at.f)),
        ..FlatInstance::zeroed()
    };
    let object = Ray {
        t_max: if best.found { best.t.next_up() } else { best.t },
        ..placed.ray_to_object(w.ray)
    };
    let mesh = &w.bvh.meshes[inst.mesh];
    if !object.is_valid() || mesh.nodes.is_empty() || !(object.t_min <= object.t_max) {
        return false;
    }
    let (h, _) = M::walk::<ANY, false>(mesh, &object, Best::start(&object), 0, Site::PLAIN, stack);
    h.found && best.offer(h.t, first + h.prim, h.u, h.v)
}

/// [`run`] with SSE lanes for the triangles and AVX lanes for the boxes, the mesh walks
/// compiled likewise, all with AVX2 enabled.
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT ([`Isa::Avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
unsafe fn run_avx2(
    bvh: &MovingInstancesCpuBvh,
    rays: &[Ray],
    times: &[f32],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    run::<lanes::Sse, lanes::Avx8, instanced::Avx2>(bvh, rays, times, query, hits, stack)
}
