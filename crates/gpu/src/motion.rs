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
use wgpu::util::DeviceExt;

use crate::build::read_after_async;
use crate::context::storage_entry;
use crate::{GpuContext, GpuError, TraceError};

/// The entry point of the motion module (the full-stack walk's, hits only).
const ENTRY: &str = "bvh_trace_full_stack_main";

/// A moving mesh's tree on the device (see the module docs).
#[derive(Debug)]
pub struct GpuMotionBvh {
    ctx: GpuContext,
    bvh: Arc<MotionBvh>,
    /// Closest hit, any hit.
    pipelines: [wgpu::ComputePipeline; 2],
    batch_layout: wgpu::BindGroupLayout,
    tree: wgpu::BindGroup,
}

impl GpuMotionBvh {
    /// Uploads `bvh` (nodes, triangles at every step, and each node's box at every step
    /// with linear bounds) and compiles its two pipelines. Refuses a tree deeper than the
    /// full-stack kernel's stack ([`TraceError::TooDeep`]) and arrays over the device's
    /// binding limit ([`TraceError::TooLarge`]).
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
        let arrays: [(&'static str, &[u8]); 3] = [
            ("nodes", bytemuck::cast_slice(bvh.nodes())),
            ("triangles", bytemuck::cast_slice(bvh.triangles())),
            ("step boxes", bytemuck::cast_slice(boxes)),
        ];
        let limit = ctx.limits().max_storage_buffer_binding_size;
        if let Some((buffer, bytes)) = arrays.iter().find(|(_, b)| b.len() as u64 > limit) {
            return Err(TraceError::TooLarge {
                buffer,
                bytes: bytes.len() as u64,
                limit,
                limit_name: "max_storage_buffer_binding_size",
                storage: None,
            });
        }
        let device = ctx.device();
        let made = ctx.scoped("uploading a moving mesh's tree", || {
            let buffers = arrays.map(|(label, contents)| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE,
                })
            });
            let tree_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("moving tree"),
                entries: &[0, 1, 6].map(|b| storage_entry(b, true)),
            });
            let batch_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("timed rays"),
                entries: &[
                    storage_entry(0, true),
                    storage_entry(1, false),
                    storage_entry(3, true),
                ],
            });
            let tree = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("moving tree"),
                layout: &tree_layout,
                entries: &[(0, 0), (1, 1), (6, 2)].map(|(binding, i)| wgpu::BindGroupEntry {
                    binding,
                    resource: buffers[i].as_entire_binding(),
                }),
            });
            (tree_layout, batch_layout, tree)
        })?;
        let (tree_layout, batch_layout, tree) = made;
        let pipelines = Self::pipelines(ctx, &bvh, [&tree_layout, &batch_layout])?;
        Ok(GpuMotionBvh {
            ctx: ctx.clone(),
            bvh,
            pipelines,
            batch_layout,
            tree,
        })
    }

    /// The closest-hit and any-hit pipelines of the motion module, specialised for the
    /// tree's steps and bounds and the driver.
    fn pipelines(
        ctx: &GpuContext,
        bvh: &MotionBvh,
        layouts: [&wgpu::BindGroupLayout; 2],
    ) -> Result<[wgpu::ComputePipeline; 2], GpuError> {
        let device = ctx.device();
        ctx.scoped("compiling the motion kernel", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("bvhtrace motion"),
                source: wgpu::ShaderSource::Wgsl(ModuleSet::motion().compose(0).into()),
            });
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("bvhtrace motion"),
                bind_group_layouts: &[Some(layouts[0]), Some(layouts[1])],
                immediate_size: 0,
            });
            let flag = |b: bool| if b { 1.0 } else { 0.0 };
            [false, true].map(|any| {
                let mut constants = vec![
                    ("BVH_ANY_HIT", flag(any)),
                    ("BVH_TIME_STEPS", bvh.time_steps() as f64),
                    (
                        "BVH_LINEAR_BOUNDS",
                        flag(bvh.time_bounds() == TimeBounds::Linear),
                    ),
                ];
                constants.extend(ctx.tuning().constants());
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(ENTRY),
                    layout: Some(&layout),
                    module: &module,
                    entry_point: Some(ENTRY),
                    compilation_options: wgpu::PipelineCompilationOptions {
                        constants: &constants,
                        zero_initialize_workgroup_memory: false,
                    },
                    cache: None,
                })
            })
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

    /// One dispatch `d` over `rays`, its rays.
    async fn trace_chunk(
        &self,
        rays: &[Ray],
        times: &[f32],
        query: Query,
        d: &Dispatch,
    ) -> Result<Vec<Hit>, GpuError> {
        let device = self.ctx.device();
        // NaN times are answered on the host; the kernel sees 0.
        let times: Vec<f32> = times
            .iter()
            .map(|&t| if t.is_nan() { 0.0 } else { t })
            .collect();
        let hit_bytes = (rays.len() * size_of::<Hit>()) as u64;
        let (enc, hits) = self.ctx.scoped("tracing a moving mesh", || {
            let init = |label, contents: &[u8]| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE,
                })
            };
            let ray_buf = init("rays", bytemuck::cast_slice(rays));
            let time_buf = init("ray times", bytemuck::cast_slice(&times));
            let hits = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("hits"),
                size: hit_bytes,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let batch = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("timed rays"),
                layout: &self.batch_layout,
                entries: &[(0, &ray_buf), (1, &hits), (3, &time_buf)].map(|(binding, b)| {
                    wgpu::BindGroupEntry {
                        binding,
                        resource: b.as_entire_binding(),
                    }
                }),
            });
            let mut enc = device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("bvhtrace motion"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipelines[usize::from(query == Query::Any)]);
                pass.set_bind_group(0, &self.tree, &[]);
                pass.set_bind_group(1, &batch, &[]);
                pass.dispatch_workgroups(d.groups_x, d.groups_y, 1);
            }
            (enc, hits)
        })?;
        let bytes = read_after_async(
            &self.ctx,
            "reading a moving mesh's hits",
            enc,
            &[(&hits, hit_bytes)],
        )
        .await?
        .concat();
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }
}
