//! The top level of a two-level BVH rebuilt on the device when its instances move: the
//! instances' world boxes (computed on the host, conservative, as for the CPU's top level)
//! go to the device builder as one triangle per box
//! ([`bvhtrace_core::instance::box_triangle`]), one box per leaf, and the tree read back
//! replaces the top level ([`InstancedBvh::set_transforms_with`] checks it first).

use bvhtrace_core::instance::box_triangle;
use bvhtrace_core::{Aabb, InstancedBvh, Triangle};
use bvhtrace_engine::TraceError;
use glam::Affine3A;

use crate::{GpuBuildOptions, GpuBuildTimes, GpuContext, GpuError};

impl GpuContext {
    /// Moves `bvh`'s instances to `transforms` (object to world, one per instance), as
    /// [`InstancedBvh::set_transforms`] does, with the top level built on the device by
    /// `opts`' builder (its leaf size is taken as 1: one instance per leaf). Returns the
    /// build's times. An unusable transform is an error naming the instance, a device
    /// failure the device's error; either leaves the BVH as it was. Write the result to an
    /// upload as any new pose (`Tracer::update` finds that only the top level moved).
    ///
    /// This waits for the device, so it is an error in a browser: await
    /// [`GpuContext::set_transforms_on_device_async`] there.
    pub fn set_transforms_on_device(
        &self,
        bvh: &mut InstancedBvh,
        transforms: &[Affine3A],
        opts: &GpuBuildOptions,
    ) -> Result<GpuBuildTimes, GpuError> {
        if cfg!(target_arch = "wasm32") {
            return Err(TraceError::Device {
                during: "building a top level on the device",
                message: "a browser cannot wait for its GPU: use set_transforms_on_device_async"
                    .into(),
            });
        }
        pollster::block_on(self.set_transforms_on_device_async(bvh, transforms, opts))
    }

    /// [`GpuContext::set_transforms_on_device`] as a future, awaiting the device's build
    /// ([`GpuContext::build_bvh_async`]): what a program in a browser awaits.
    pub async fn set_transforms_on_device_async(
        &self,
        bvh: &mut InstancedBvh,
        transforms: &[Affine3A],
        opts: &GpuBuildOptions,
    ) -> Result<GpuBuildTimes, GpuError> {
        let bad = |e: bvhtrace_core::InstanceError| TraceError::BadBuffer {
            buffer: "instances",
            problem: e.to_string(),
        };
        let boxes = bvh.world_boxes(transforms).map_err(bad)?;
        let tris: Vec<Triangle> = boxes.iter().map(box_triangle).collect();
        let opts = GpuBuildOptions {
            max_leaf_size: 1,
            ..*opts
        };
        let (tree, times) = self.build_bvh_async(&tris, &opts).await?;
        // The tree is checked against the same boxes before it replaces the top level.
        let mut given = Some(tree);
        let mut build = |_: &[Aabb]| given.take().ok_or_else(|| "built once".to_string());
        bvh.set_transforms_with(transforms, &mut build)
            .map_err(bad)?;
        Ok(times)
    }
}
