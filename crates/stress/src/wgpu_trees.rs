//! Our walks of moving meshes and of curves on a wgpu device the caller opened, as the
//! factories [`crate::DeviceTracers`] takes (feature `wgpu`).

use std::sync::Arc;

use bvhtrace_core::{Hit, Query, Ray};
use bvhtrace_gpu::{GpuContext, GpuCurveBvh, GpuMotionBvh, GpuMotionInstancedBvh};

use crate::{MovingTree, OpenCurves, OpenMotion, TraceTimed};

/// Uploads moving scenes' trees to `ctx` ([`GpuMotionBvh`], [`GpuMotionInstancedBvh`]).
pub fn motion_on(ctx: GpuContext) -> OpenMotion {
    Arc::new(move |tree| {
        let trace: TraceTimed = match tree {
            MovingTree::Mesh(bvh) => {
                let gpu = GpuMotionBvh::upload(&ctx, bvh).map_err(|e| e.to_string())?;
                Box::new(move |rays: &[Ray], times: &[f32], q: Query| {
                    gpu.trace(rays, times, q).map_err(|e| e.to_string())
                })
            }
            MovingTree::Instances(bvh) => {
                let gpu = GpuMotionInstancedBvh::upload(&ctx, bvh).map_err(|e| e.to_string())?;
                Box::new(move |rays: &[Ray], times: &[f32], q: Query| {
                    gpu.trace(rays, times, q).map_err(|e| e.to_string())
                })
            }
        };
        Ok(trace)
    })
}

/// Uploads trees of curves to `ctx` ([`GpuCurveBvh`]).
pub fn curves_on(ctx: GpuContext) -> OpenCurves {
    Arc::new(move |bvh| {
        let gpu = GpuCurveBvh::upload(&ctx, bvh).map_err(|e| e.to_string())?;
        let trace = move |rays: &[Ray], _: &[f32], q: Query| -> Result<Vec<Hit>, String> {
            gpu.trace(rays, q).map_err(|e| e.to_string())
        };
        Ok(Box::new(trace) as TraceTimed)
    })
}
