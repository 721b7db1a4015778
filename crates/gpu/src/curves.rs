//! Curves on the device: a [`CurveBvh`] (triangles and curve segments in one tree)
//! uploaded as it is laid out, traced by the full-stack walk whose leaf visit tests each
//! slot's triangle or segment ([`ModuleSet::curves`]: `bvh_curve_buffers.wgsl` and
//! `curve.wgsl` in place of the static tree's files), the twin of [`CurveBvh::trace`].

use std::sync::Arc;

use bvhtrace_core::{CurveBvh, CurveKind, Hit, INCOMPLETE, Query, Ray};
use bvhtrace_engine::compose::ModuleSet;
use bvhtrace_engine::plan::{Dispatch, plan_dispatches};
use bvhtrace_engine::walks::FULL_STACK_SIZE;
use wgpu::util::DeviceExt;

use crate::build::read_after_async;
use crate::context::storage_entry;
use crate::{GpuContext, GpuError, TraceError};

/// The entry point of the curves' module (the full-stack walk's, hits only).
const ENTRY: &str = "bvh_trace_full_stack_main";

/// A tree of triangles and curves on the device (see the module docs).
#[derive(Debug)]
pub struct GpuCurveBvh {
    ctx: GpuContext,
    bvh: Arc<CurveBvh>,
    /// Closest hit, any hit.
    pipelines: [wgpu::ComputePipeline; 2],
    batch_layout: wgpu::BindGroupLayout,
    tree: wgpu::BindGroup,
}

impl GpuCurveBvh {
    /// Uploads `bvh` (nodes, triangles, leaf slots, points and segments) and compiles its
    /// two pipelines. Refuses a tree deeper than the full-stack kernel's stack
    /// ([`TraceError::TooDeep`]) and arrays over the device's binding limit
    /// ([`TraceError::TooLarge`]).
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
        let arrays: [(&'static str, &[u8]); 5] = [
            ("nodes", bytemuck::cast_slice(bvh.nodes())),
            ("triangles", bytemuck::cast_slice(&triangles)),
            ("leaf slots", bytemuck::cast_slice(bvh.leaf_prims())),
            ("curve points", bytemuck::cast_slice(&points)),
            ("curve segments", bytemuck::cast_slice(&segments)),
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
        let bindings = [0, 1, 6, 7, 8];
        let made = ctx.scoped("uploading a tree of curves", || {
            let buffers = arrays.map(|(label, contents)| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE,
                })
            });
            let tree_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("tree of curves"),
                entries: &bindings.map(|b| storage_entry(b, true)),
            });
            let batch_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("rays"),
                entries: &[storage_entry(0, true), storage_entry(1, false)],
            });
            let tree = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("tree of curves"),
                layout: &tree_layout,
                entries: &std::array::from_fn::<_, 5, _>(|i| wgpu::BindGroupEntry {
                    binding: bindings[i],
                    resource: buffers[i].as_entire_binding(),
                }),
            });
            (tree_layout, batch_layout, tree)
        })?;
        let (tree_layout, batch_layout, tree) = made;
        let pipelines = Self::pipelines(ctx, &bvh, [&tree_layout, &batch_layout])?;
        Ok(GpuCurveBvh {
            ctx: ctx.clone(),
            bvh,
            pipelines,
            batch_layout,
            tree,
        })
    }

    /// The closest-hit and any-hit pipelines, specialised for the curve kind, the
    /// triangle count and the driver.
    fn pipelines(
        ctx: &GpuContext,
        bvh: &CurveBvh,
        layouts: [&wgpu::BindGroupLayout; 2],
    ) -> Result<[wgpu::ComputePipeline; 2], GpuError> {
        let device = ctx.device();
        let kind = CurveKind::ALL.iter().position(|&k| k == bvh.curves().kind);
        ctx.scoped("compiling the curves' kernel", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("bvhtrace curves"),
                source: wgpu::ShaderSource::Wgsl(ModuleSet::curves().compose(0).into()),
            });
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("bvhtrace curves"),
                bind_group_layouts: &[Some(layouts[0]), Some(layouts[1])],
                immediate_size: 0,
            });
            [0.0, 1.0].map(|any| {
                let mut constants = vec![
                    ("BVH_ANY_HIT", any),
                    ("BVH_CURVE_KIND", kind.unwrap_or(0) as f64),
                    ("BVH_CURVE_TRIANGLES", bvh.triangle_count() as f64),
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
    pub fn bvh(&self) -> &Arc<CurveBvh> {
        &self.bvh
    }

    /// Traces `rays` (see [`CurveBvh::trace`]: the same answers): closest or any hit.
    /// Rays the driver's trip budget cut short are answered on the CPU twin. Waits for the
    /// device: in a browser, await [`GpuCurveBvh::trace_async`].
    pub fn trace(&self, rays: &[Ray], query: Query) -> Result<Vec<Hit>, GpuError> {
        if cfg!(target_arch = "wasm32") {
            return Err(TraceError::Device {
                during: "tracing curves",
                message: "a browser cannot wait for its GPU: use trace_async".into(),
            });
        }
        pollster::block_on(self.trace_async(rays, query))
    }

    /// [`GpuCurveBvh::trace`] as a future.
    pub async fn trace_async(&self, rays: &[Ray], query: Query) -> Result<Vec<Hit>, GpuError> {
        let mut hits = Vec::with_capacity(rays.len());
        for d in plan_dispatches(rays.len() as u64, self.ctx.limits()) {
            let range = d.first_ray as usize..d.first_ray as usize + d.ray_count as usize;
            hits.extend(self.trace_chunk(&rays[range], query, &d).await?);
        }
        for (h, r) in hits.iter_mut().zip(rays) {
            if h.prim == INCOMPLETE {
                *h = self.bvh.trace(r, query).0;
            }
        }
        Ok(hits)
    }

    /// One dispatch `d` over `rays`, its rays.
    async fn trace_chunk(
        &self,
        rays: &[Ray],
        query: Query,
        d: &Dispatch,
    ) -> Result<Vec<Hit>, GpuError> {
        let device = self.ctx.device();
        let hit_bytes = (rays.len() * size_of::<Hit>()) as u64;
        let (enc, hits) = self.ctx.scoped("tracing curves", || {
            let ray_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("rays"),
                contents: bytemuck::cast_slice(rays),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let hits = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("hits"),
                size: hit_bytes,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let batch = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("rays"),
                layout: &self.batch_layout,
                entries: &[(0, &ray_buf), (1, &hits)].map(|(binding, b)| wgpu::BindGroupEntry {
                    binding,
                    resource: b.as_entire_binding(),
                }),
            });
            let mut enc = device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("bvhtrace curves"),
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
            "reading the curves' hits",
            enc,
            &[(&hits, hit_bytes)],
        )
        .await?
        .concat();
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }
}
