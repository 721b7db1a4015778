//! The top level of a two-level BVH rebuilt on the device when its instances move: the
//! instances' world boxes (computed on the host, conservative, as for the CPU's top level)
//! go to the device builder as one triangle per box
//! ([`bvhtrace_core::instance::box_triangle`]), one box per leaf, and the tree read back
//! replaces the top level ([`InstancedBvh::set_transforms_with`] checks it first).

use bvhtrace_core::instance::box_triangle;
use bvhtrace_core::{Aabb, InstancedBvh, Triangle};
use bvhtrace_kernels::TraceError;
use glam::Affine3A;

use crate::{GpuBuildOptions, GpuBuildTimes, GpuContext, GpuError};

impl GpuContext {
    /// Moves `bvh`'s instances to `transforms` (object to world, one per instance), as
    /// [`InstancedBvh::set_transforms`] does, with the top level built on the device by
    /// `opts`' builder (its leaf size is taken as 1: one instance per leaf). Returns the
    /// build's times. An unusable transform is an error naming the instance, a device
    /// failure the device's error; either leaves the BVH as it was. Write the result to an
    /// upload as any new pose (`Tracer::update` finds that only the top level moved).
    pub fn set_transforms_on_device(
        &self,
        bvh: &mut InstancedBvh,
        transforms: &[Affine3A],
        opts: &GpuBuildOptions,
    ) -> Result<GpuBuildTimes, GpuError> {
        let opts = GpuBuildOptions {
            max_leaf_size: 1,
            ..*opts
        };
        let (mut times, mut failed) = (None, None);
        let mut build = |boxes: &[Aabb]| {
            let tris: Vec<Triangle> = boxes.iter().map(box_triangle).collect();
            match self.build_bvh(&tris, &opts) {
                Ok((tree, t)) => {
                    times = Some(t);
                    Ok(tree)
                }
                Err(e) => {
                    let message = e.to_string();
                    failed = Some(e);
                    Err(message)
                }
            }
        };
        let placed = bvh.set_transforms_with(transforms, &mut build);
        match (placed, failed) {
            (_, Some(e)) => Err(e),
            (Err(e), None) => Err(TraceError::BadBuffer {
                buffer: "instances",
                problem: e.to_string(),
            }),
            (Ok(()), None) => Ok(times.unwrap_or_default()),
        }
    }
}
