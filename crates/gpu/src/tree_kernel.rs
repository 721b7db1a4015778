//! What the tracers over a tree of their own layout (moving meshes, curves) share: their
//! arrays checked against the device's binding limit and uploaded to group 0, the
//! full-stack walk's entry point compiled for closest and any hit, and the dispatches over
//! a batch of rays (group 1: rays at binding 0, hits at 1, the batch's other inputs after).

use bvhtrace_core::{Hit, INCOMPLETE, Query, Ray};
use bvhtrace_engine::plan::{Dispatch, plan_dispatches};
use wgpu::util::DeviceExt;

use crate::build::read_after_async;
use crate::context::storage_entry;
use crate::{GpuContext, GpuError, TraceError};

/// The entry point (the full-stack walk's, hits only).
const ENTRY: &str = "bvh_trace_full_stack_main";

/// Waits for a trace on the device where the platform can; a browser cannot (the error
/// says what was `during`: await the tracer's `trace_async` there).
pub(crate) fn block_on<T>(
    during: &'static str,
    trace: impl std::future::Future<Output = Result<T, GpuError>>,
) -> Result<T, GpuError> {
    if cfg!(target_arch = "wasm32") {
        return Err(TraceError::Device {
            during,
            message: "a browser cannot wait for its GPU: use trace_async".into(),
        });
    }
    pollster::block_on(trace)
}

/// A tree's bind group and the two pipelines that walk it.
#[derive(Debug)]
pub(crate) struct TreeKernel {
    /// Closest hit, any hit.
    pipelines: [wgpu::ComputePipeline; 2],
    batch_layout: wgpu::BindGroupLayout,
    tree: wgpu::BindGroup,
}

/// What [`TreeKernel::new`] makes: `label` names it in errors and debuggers; `arrays` are
/// the tree's `(name, bytes)` at `bindings` of group 0; `batch` the group 1 bindings of a
/// batch (rays, hits, then any other input); `source` the composed WGSL; `constants` its
/// overrides besides the query and the driver's.
pub(crate) struct TreeKernelDesc<'a> {
    pub label: &'static str,
    pub arrays: &'a [(&'static str, &'a [u8])],
    pub bindings: &'a [u32],
    pub batch: &'a [u32],
    pub source: String,
    pub constants: Vec<(&'static str, f64)>,
}

impl TreeKernel {
    /// Uploads the arrays and compiles both pipelines. Refuses an array over the device's
    /// binding limit ([`TraceError::TooLarge`]).
    pub fn new(ctx: &GpuContext, desc: TreeKernelDesc<'_>) -> Result<TreeKernel, GpuError> {
        let limit = ctx.limits().max_storage_buffer_binding_size;
        if let Some((buffer, bytes)) = desc.arrays.iter().find(|(_, b)| b.len() as u64 > limit) {
            return Err(TraceError::TooLarge {
                buffer,
                bytes: bytes.len() as u64,
                limit,
                limit_name: "max_storage_buffer_binding_size",
                storage: None,
            });
        }
        let device = ctx.device();
        let (tree_layout, batch_layout, tree) = ctx.scoped(desc.label, || {
            let buffers: Vec<wgpu::Buffer> = (desc.arrays.iter())
                .map(|(label, contents)| {
                    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some(label),
                        contents,
                        usage: wgpu::BufferUsages::STORAGE,
                    })
                })
                .collect();
            let layout = |label, bindings: &[u32], read_only: &dyn Fn(u32) -> bool| {
                let entries: Vec<_> = (bindings.iter())
                    .map(|&b| storage_entry(b, read_only(b)))
                    .collect();
                device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                    label: Some(label),
                    entries: &entries,
                })
            };
            let tree_layout = layout(desc.label, desc.bindings, &|_| true);
            // The hits (binding 1) are written; every other batch input is read.
            let batch_layout = layout("rays", desc.batch, &|b| b != 1);
            let entries: Vec<_> = (desc.bindings.iter().zip(&buffers))
                .map(|(&binding, b)| wgpu::BindGroupEntry {
                    binding,
                    resource: b.as_entire_binding(),
                })
                .collect();
            let tree = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(desc.label),
                layout: &tree_layout,
                entries: &entries,
            });
            (tree_layout, batch_layout, tree)
        })?;
        let pipelines = ctx.scoped(desc.label, || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(desc.label),
                source: wgpu::ShaderSource::Wgsl(desc.source.into()),
            });
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(desc.label),
                bind_group_layouts: &[Some(&tree_layout), Some(&batch_layout)],
                immediate_size: 0,
            });
            [0.0, 1.0].map(|any| {
                let mut constants = vec![("BVH_ANY_HIT", any)];
                constants.extend(desc.constants.iter().copied());
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
        })?;
        Ok(TreeKernel {
            pipelines,
            batch_layout,
            tree,
        })
    }

    /// `rays` traced in as many dispatches as the device's limits need, each ray's time
    /// at batch binding 3 when `times` are given (a NaN time given as 0: the caller
    /// answers those rays itself); rays the driver's trip budget cut short are answered by
    /// `twin(i)`, the CPU twin's hit of ray `i`.
    pub async fn trace(
        &self,
        ctx: &GpuContext,
        during: &'static str,
        (rays, times): (&[Ray], Option<&[f32]>),
        query: Query,
        twin: impl Fn(usize) -> Hit,
    ) -> Result<Vec<Hit>, GpuError> {
        if let Some(times) = times {
            assert_eq!(rays.len(), times.len(), "one time per ray");
        }
        let mut hits = Vec::with_capacity(rays.len());
        for d in plan_dispatches(rays.len() as u64, ctx.limits()) {
            let range = d.first_ray as usize..d.first_ray as usize + d.ray_count as usize;
            let t: Vec<f32> = (times.map_or(&[][..], |t| &t[range.clone()]).iter())
                .map(|&t| if t.is_nan() { 0.0 } else { t })
                .collect();
            let times_input = [(3, bytemuck::cast_slice(&t))];
            let extra: &[(u32, &[u8])] = if times.is_some() { &times_input } else { &[] };
            let r = &rays[range];
            hits.extend(self.dispatch(ctx, during, (r, extra), query, &d).await?);
        }
        for (i, h) in hits.iter_mut().enumerate() {
            if h.prim == INCOMPLETE {
                *h = twin(i);
            }
        }
        Ok(hits)
    }

    /// One dispatch `d` over `rays`, with the batch's other inputs `extra` (each at its
    /// binding): their hits.
    async fn dispatch(
        &self,
        ctx: &GpuContext,
        during: &'static str,
        (rays, extra): (&[Ray], &[(u32, &[u8])]),
        query: Query,
        d: &Dispatch,
    ) -> Result<Vec<Hit>, GpuError> {
        let device = ctx.device();
        let hit_bytes = (rays.len() * size_of::<Hit>()) as u64;
        let (enc, hits) = ctx.scoped(during, || {
            let init = |label, contents: &[u8]| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE,
                })
            };
            let ray_buf = init("rays", bytemuck::cast_slice(rays));
            let inputs: Vec<(u32, wgpu::Buffer)> = (extra.iter())
                .map(|&(binding, bytes)| (binding, init("batch input", bytes)))
                .collect();
            let hits = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("hits"),
                size: hit_bytes,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let mut entries = vec![(0, &ray_buf), (1, &hits)];
            entries.extend(inputs.iter().map(|(b, buf)| (*b, buf)));
            let entries: Vec<_> = (entries.into_iter())
                .map(|(binding, b)| wgpu::BindGroupEntry {
                    binding,
                    resource: b.as_entire_binding(),
                })
                .collect();
            let batch = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("rays"),
                layout: &self.batch_layout,
                entries: &entries,
            });
            let mut enc = device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(during),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipelines[usize::from(query == Query::Any)]);
                pass.set_bind_group(0, &self.tree, &[]);
                pass.set_bind_group(1, &batch, &[]);
                pass.dispatch_workgroups(d.groups_x, d.groups_y, 1);
            }
            (enc, hits)
        })?;
        let bytes = read_after_async(ctx, during, enc, &[(&hits, hit_bytes)])
            .await?
            .concat();
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }
}
