//! Curves on the device: a [`CurveBvh`] (triangles and curve segments in one tree)
//! uploaded as it is laid out, traced by the full-stack walk whose leaf visit tests each
//! slot's triangle or segment ([`ModuleSet::curves`]: `bvh_curve_buffers.wgsl` and
//! `curve.wgsl` in place of the static tree's files), the twin of [`CurveBvh::trace`].

use std::sync::Arc;

use bvhtrace_core::{CurveBvh, CurveKind, Hit, Query, Ray};
use bvhtrace_engine::compose::ModuleSet;
use bvhtrace_engine::walks::FULL_STACK_SIZE;

use crate::tree_kernel::{TreeKernel, TreeKernelDesc, block_on};
use crate::{GpuContext, GpuError, TraceError};

/// A tree of triangles and curves on the device (see the module docs).
#[derive(Debug)]
pub struct GpuCurveBvh {
    ctx: GpuContext,
    bvh: Arc<CurveBvh>,
    kernel: TreeKernel,
}

impl GpuCurveBvh {
    /// Uploads `bvh` (nodes, triangles, leaf slots, points and segments) and compiles its
    /// two pipelines, specialised for the curve kind and the triangle count. Refuses a
    /// tree deeper than the full-stack kernel's stack ([`TraceError::TooDeep`]) and arrays
    /// over the device's binding limit ([`TraceError::TooLarge`]).
    pub fn upload(ctx: &GpuContext, bvh: Arc<CurveBvh>) -> Result<GpuCurveBvh, GpuError> {
        if bvh.depth() > FULL_STACK_SIZE {
            return Err(TraceError::TooDeep {
                depth: bvh.depth(),
                max: FULL_STACK_SIZE,
            });
        }
        // An empty array still needs a buffer for its binding.
        let mut triangles = bvh.flat_triangles();
        let mut segments = bvh.kernel_segments();
        let mut points = bvh.curves().points.clone();
        triangles.resize(triangles.len().max(1), bytemuck::Zeroable::zeroed());
        segments.resize(segments.len().max(1), Default::default());
        points.resize(points.len().max(1), Default::default());
        let kind = CurveKind::ALL.iter().position(|&k| k == bvh.curves().kind);
        let kernel = TreeKernel::new(
            ctx,
            TreeKernelDesc {
                label: "a tree of curves",
                arrays: &[
                    ("nodes", bytemuck::cast_slice(bvh.nodes())),
                    ("triangles", bytemuck::cast_slice(&triangles)),
                    ("leaf slots", bytemuck::cast_slice(bvh.leaf_prims())),
                    ("curve points", bytemuck::cast_slice(&points)),
                    ("curve segments", bytemuck::cast_slice(&segments)),
                ],
                bindings: &[0, 1, 6, 7, 8],
                batch: &[0, 1],
                source: ModuleSet::curves().compose(0),
                constants: vec![
                    ("BVH_CURVE_KIND", kind.unwrap_or(0) as f64),
                    ("BVH_CURVE_TRIANGLES", bvh.triangle_count() as f64),
                ],
            },
        )?;
        Ok(GpuCurveBvh {
            ctx: ctx.clone(),
            bvh,
            kernel,
        })
    }

    /// The tree it traces.
    pub fn bvh(&self) -> &Arc<CurveBvh> {
        &self.bvh
    }

    /// Traces `rays` (see [`CurveBvh::trace`]: the same answers): closest or any hit.
    /// Rays the driver's trip budget cut short are answered on the CPU twin. Waits for the
    /// device: in a browser, await [`GpuCurveBvh::trace_async`].
    pub fn trace(&self, rays: &[Ray], query: Query) -> Result<Vec<Hit>, GpuError> {
        block_on(DURING, self.trace_async(rays, query))
    }

    /// [`GpuCurveBvh::trace`] as a future.
    pub async fn trace_async(&self, rays: &[Ray], query: Query) -> Result<Vec<Hit>, GpuError> {
        let twin = |i: usize| self.bvh.trace(&rays[i], query).0;
        (self.kernel)
            .trace(&self.ctx, DURING, (rays, None), query, twin)
            .await
    }
}

/// What the curves' errors say they were doing.
const DURING: &str = "tracing curves";
