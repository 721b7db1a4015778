//! Motion blur on the device: a [`MotionBvh`] uploaded as it is laid out, traced by the
//! full-stack walk over its boxes and triangles at each ray's time
//! ([`ModuleSet::motion`]: `bvh_motion_buffers.wgsl` and `entry_ray_times.wgsl` in place of
//! the static tree's files), the twin of [`MotionBvh::trace`] bit for bit.

use std::sync::Arc;

use bvhtrace_core::motion::{MotionBox, MotionBvh, TimeBounds};
use bvhtrace_core::traverse::untraced;
use bvhtrace_core::{Hit, INCOMPLETE, Query, Ray};
use bvhtrace_engine::compose::ModuleSet;
use bvhtrace_engine::plan::{Dispatch, plan_dispatches};
use bvhtrace_engine::walks::FULL_STACK_SIZE;

use crate::tree_kernel::{TreeKernel, TreeKernelDesc};
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
        if cfg!(target_arch = "wasm32") {
            return Err(TraceError::Device {
                during: "tracing a moving mesh",
                message: "a browser cannot wait for its GPU: use trace_async".into(),
            });
        }
        pollster::block_on(self.trace_async(rays, times, query))
    }

    /// [`GpuMotionBvh::trace`] as a future.
    pub async fn trace_async(
        &self,
        rays: &[Ray],
        times: &[f32],
        query: Query,
    ) -> Result<Vec<Hit>, GpuError> {
        assert_eq!(rays.len(), times.len(), "one time per ray");
        let mut hits = Vec::with_capacity(rays.len());
        for d in plan_dispatches(rays.len() as u64, self.ctx.limits()) {
            let range = d.first_ray as usize..d.first_ray as usize + d.ray_count as usize;
            let (r, t) = (&rays[range.clone()], &times[range]);
            hits.extend(self.trace_chunk(r, t, query, &d).await?);
        }
        for (i, h) in hits.iter_mut().enumerate() {
            if times[i].is_nan() {
                *h = untraced(&rays[i]);
            } else if h.prim == INCOMPLETE {
                *h = self.bvh.trace(&rays[i], times[i], query).0;
            }
        }
        Ok(hits)
    }

    /// One dispatch `d` over `rays` at `times`: their hits.
    async fn trace_chunk(
        &self,
        rays: &[Ray],
        times: &[f32],
        query: Query,
        d: &Dispatch,
    ) -> Result<Vec<Hit>, GpuError> {
        // NaN times are answered on the host; the kernel sees 0.
        let times: Vec<f32> = times
            .iter()
            .map(|&t| if t.is_nan() { 0.0 } else { t })
            .collect();
        let extra = [(3, bytemuck::cast_slice(&times))];
        (self.kernel)
            .dispatch(&self.ctx, "tracing a moving mesh", (rays, &extra), query, d)
            .await
    }
}
