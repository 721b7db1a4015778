//! Motion blur on the device: a [`MotionBvh`] uploaded as it is laid out, traced by the
//! full-stack walk over its boxes and triangles at each ray's time
//! ([`ModuleSet::motion`]: `bvh_motion_buffers.wgsl` and `entry_ray_times.wgsl` in place of
//! the static tree's files), the twin of [`MotionBvh::trace`] bit for bit.

use std::sync::Arc;

use bvhtrace_core::motion::{MotionBox, MotionBvh, MotionInstancedBvh, TimeBounds};
use bvhtrace_core::traverse::untraced;
use bvhtrace_core::{Hit, Query, Ray};
use bvhtrace_engine::compose::ModuleSet;
use bvhtrace_engine::walks::FULL_STACK_SIZE;

use crate::tree_kernel::{TreeKernel, TreeKernelDesc, block_on};
use crate::{GpuContext, GpuError, TraceError};

/// A moving mesh's tree on the device (see the module docs).
#[derive(Debug)]
pub struct GpuMotionBvh {
    ctx: GpuContext,
    bvh: Arc<MotionBvh>,
    kernel: TreeKernel,
}

impl GpuMotionBvh {
    /// Uploads `bvh` (nodes, triangles at every step, and each node's box at every step
    /// with linear bounds) and compiles its two pipelines, specialised for the tree's steps
    /// and bounds. Refuses a tree deeper than the full-stack kernel's stack
    /// ([`TraceError::TooDeep`]) and arrays over the device's binding limit
    /// ([`TraceError::TooLarge`]).
    pub fn upload(ctx: &GpuContext, bvh: Arc<MotionBvh>) -> Result<GpuMotionBvh, GpuError> {
        if bvh.depth() > FULL_STACK_SIZE {
            return Err(TraceError::TooDeep {
                depth: bvh.depth(),
                max: FULL_STACK_SIZE,
            });
        }
        // Merged bounds read no step box; the binding still needs a buffer.
        let dummy = [MotionBox::default()];
        let boxes = match bvh.time_bounds() {
            TimeBounds::Linear => bvh.step_boxes(),
            TimeBounds::Merged => &dummy[..],
        };
        let linear = bvh.time_bounds() == TimeBounds::Linear;
        let kernel = TreeKernel::new(
            ctx,
            TreeKernelDesc {
                label: "a moving mesh's tree",
                arrays: &[
                    ("nodes", bytemuck::cast_slice(bvh.nodes())),
                    ("triangles", bytemuck::cast_slice(bvh.triangles())),
                    ("step boxes", bytemuck::cast_slice(boxes)),
                ],
                bindings: &[0, 1, 6],
                batch: &[0, 1, 3],
                source: ModuleSet::motion().compose(0),
                constants: vec![
                    ("BVH_TIME_STEPS", bvh.time_steps() as f64),
                    ("BVH_LINEAR_BOUNDS", if linear { 1.0 } else { 0.0 }),
                ],
            },
        )?;
        Ok(GpuMotionBvh {
            ctx: ctx.clone(),
            bvh,
            kernel,
        })
    }

    /// The tree it traces.
    pub fn bvh(&self) -> &Arc<MotionBvh> {
        &self.bvh
    }

    /// Traces `rays[i]` at `times[i]` (see [`MotionBvh::trace`]: the same answers, bit for
    /// bit): closest or any hit. Rays the driver's trip budget cut short, and rays whose
    /// time is NaN, are answered on the CPU twin. Waits for the device: in a browser,
    /// await [`GpuMotionBvh::trace_async`].
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, GpuError> {
        block_on(DURING, self.trace_async(rays, times, query))
    }

    /// [`GpuMotionBvh::trace`] as a future.
    pub async fn trace_async(
        &self,
        rays: &[Ray],
        times: &[f32],
        query: Query,
    ) -> Result<Vec<Hit>, GpuError> {
        let twin = |r: &Ray, t: f32| self.bvh.trace(r, t, query).0;
        trace_timed(&self.ctx, &self.kernel, (rays, times), query, twin).await
    }
}

/// What a moving tree's errors say it was doing.
const DURING: &str = "tracing a moving scene";

/// `rays[i]` at `times[i]` traced on `kernel` (a tree of the moving layouts); rays whose
/// time is NaN are invalid ([`untraced`]), and rays the driver's trip budget cut short are
/// answered by `twin`.
async fn trace_timed(
    ctx: &GpuContext,
    kernel: &TreeKernel,
    (rays, times): (&[Ray], &[f32]),
    query: Query,
    twin: impl Fn(&Ray, f32) -> Hit,
) -> Result<Vec<Hit>, GpuError> {
    let twin = |i: usize| twin(&rays[i], times[i]);
    let mut hits = (kernel.trace(ctx, DURING, (rays, Some(times)), query, twin)).await?;
    for (h, (r, t)) in hits.iter_mut().zip(rays.iter().zip(times)) {
        if t.is_nan() {
            *h = untraced(r);
        }
    }
    Ok(hits)
}

/// Moving instances on the device: a [`MotionInstancedBvh`] joined into one tree
/// ([`bvhtrace_core::motion::MovingInstancesLayout`]: the moving top level, then the static meshes) and traced by
/// the full-stack walk, which enters each instance with its transform at the ray's time
/// ([`ModuleSet::motion_instances`]), the twin of [`MotionInstancedBvh::trace`] bit for
/// bit.
#[derive(Debug)]
pub struct GpuMotionInstancedBvh {
    ctx: GpuContext,
    bvh: Arc<MotionInstancedBvh>,
    kernel: TreeKernel,
}

impl GpuMotionInstancedBvh {
    /// Uploads `bvh` joined ([`MotionInstancedBvh::kernel_layout`]) and compiles its two
    /// pipelines, specialised for its steps and bounds. Refuses a tree whose two levels
    /// together are deeper than the full-stack kernel's stack ([`TraceError::TooDeep`]) and
    /// arrays over the device's binding limit ([`TraceError::TooLarge`]).
    pub fn upload(
        ctx: &GpuContext,
        bvh: Arc<MotionInstancedBvh>,
    ) -> Result<GpuMotionInstancedBvh, GpuError> {
        let layout = bvh.kernel_layout();
        if layout.depth > FULL_STACK_SIZE {
            return Err(TraceError::TooDeep {
                depth: layout.depth,
                max: FULL_STACK_SIZE,
            });
        }
        // Merged bounds read no step box; the binding still needs a buffer.
        let dummy = [MotionBox::default()];
        let linear = bvh.time_bounds() == TimeBounds::Linear;
        let boxes = if linear {
            &layout.step_boxes[..]
        } else {
            &dummy[..]
        };
        let kernel = TreeKernel::new(
            ctx,
            TreeKernelDesc {
                label: "moving instances' tree",
                arrays: &[
                    ("nodes", bytemuck::cast_slice(&layout.nodes)),
                    ("triangles", bytemuck::cast_slice(&layout.triangles)),
                    ("instances", bytemuck::cast_slice(&layout.instances)),
                    ("step boxes", bytemuck::cast_slice(boxes)),
                    (
                        "instance transforms",
                        bytemuck::cast_slice(&layout.transforms),
                    ),
                ],
                bindings: &[0, 1, 4, 6, 7],
                batch: &[0, 1, 3],
                source: ModuleSet::motion_instances().compose(0),
                constants: vec![
                    ("BVH_TIME_STEPS", bvh.time_steps() as f64),
                    ("BVH_LINEAR_BOUNDS", if linear { 1.0 } else { 0.0 }),
                ],
            },
        )?;
        Ok(GpuMotionInstancedBvh {
            ctx: ctx.clone(),
            bvh,
            kernel,
        })
    }

    /// The instances it traces.
    pub fn bvh(&self) -> &Arc<MotionInstancedBvh> {
        &self.bvh
    }

    /// Traces `rays[i]` at `times[i]` (see [`MotionInstancedBvh::trace`]: the same answers,
    /// bit for bit): closest or any hit. Rays the driver's trip budget cut short, and rays
    /// whose time is NaN, are answered on the CPU twin. Waits for the device: in a browser,
    /// await [`GpuMotionInstancedBvh::trace_async`].
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, GpuError> {
        block_on(DURING, self.trace_async(rays, times, query))
    }

    /// [`GpuMotionInstancedBvh::trace`] as a future.
    pub async fn trace_async(
        &self,
        rays: &[Ray],
        times: &[f32],
        query: Query,
    ) -> Result<Vec<Hit>, GpuError> {
        let twin = |r: &Ray, t: f32| self.bvh.trace(r, t, query).0;
        trace_timed(&self.ctx, &self.kernel, (rays, times), query, twin).await
    }
}
