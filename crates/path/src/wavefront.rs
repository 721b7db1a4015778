//! The path tracer as waves ([`PathKernel::Wavefront`], `shaders/path_wavefront.wgsl`):
//! each wave takes every live path one vertex further and queues those that go on, the
//! paths kept in a device buffer between waves; runs of whole rows, at most
//! [`MAX_WAVE_PATHS`] pixels, bound that buffer. The sums equal the single kernel's bit
//! for bit.

use bvhtrace_engine::shaders::{PATH_WAVE_PREPARE, PATH_WAVEFRONT};
use bvhtrace_gpu::{BvhLibrary, GpuContext, wgpu};
use bytemuck::{Pod, Zeroable};

use crate::PathError;
use crate::device::{bind_buffers, buffer_layout, compute_pipeline, refused};
use crate::scene::PathParams;

/// How the device follows a sample's paths.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PathKernel {
    /// One invocation per pixel follows its path to the end (`path_main`): the paths'
    /// state stays in registers, but a workgroup runs until its longest path ends.
    Megakernel,
    /// Waves of one vertex per live path, the paths in a device buffer between waves and
    /// the live ones queued, so that no invocation idles beside a longer path. The
    /// default: 1.1-1.3x the single kernel's samples per second on lavapipe
    /// (docs/design.md). It binds one storage buffer more than the single kernel: a
    /// device that binds too few a stage gets the single kernel
    /// ([`crate::GpuPathTracer::kernel`] says which).
    #[default]
    Wavefront,
}

/// The most paths one run of waves keeps: 80 bytes of state and a word in each queue
/// each, 22 MiB. Measured on lavapipe, runs of 2^16 to 2^18 paths trace 1.1-1.3x faster
/// than runs of 2^20 (a wave's states stay in the CPU's cache); on a GPU a run of 2^18
/// still fills the device many times over.
pub const MAX_WAVE_PATHS: u32 = 1 << 18;

/// A path between two waves (WGSL `PathState`, 80 bytes): its ray, random numbers'
/// key and count, bounces, throughput, last bounce's density and normal, and radiance.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct PathState {
    /// The ray's origin.
    pub origin: [f32; 3],
    /// Bounces taken.
    pub depth: u32,
    /// The ray's direction.
    pub dir: [f32; 3],
    /// The last bounce's density.
    pub last_pdf: f32,
    /// The product of the bounces' weights.
    pub throughput: [f32; 3],
    /// The random numbers' key.
    pub key: u32,
    /// The last bounce's normal.
    pub last_n: [f32; 3],
    /// Random numbers drawn.
    pub count: u32,
    /// The radiance gathered so far.
    pub radiance: [f32; 3],
    /// Padding to 16 bytes.
    pub pad: u32,
}

/// One run of waves (WGSL `PathWave`): its rows, and the queues' capacity.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct WaveParams {
    /// The run's first row.
    pub first_row: u32,
    /// Rows in the run.
    pub rows: u32,
    /// Paths each of the two queues holds.
    pub capacity: u32,
    /// Padding to 16 bytes.
    pub pad: u32,
}

/// The wavefront kernel's WGSL as composed after a traversal library.
pub fn wavefront_source() -> String {
    format!("{}\n{}", crate::kernel_source(), PATH_WAVEFRONT.1)
}

/// The wavefront's pipelines and the buffers its waves share.
pub(crate) struct Wavefront {
    start: wgpu::ComputePipeline,
    extend: wgpu::ComputePipeline,
    prepare: wgpu::ComputePipeline,
    prepare_group: wgpu::BindGroup,
    layout: wgpu::BindGroupLayout,
    uniform: wgpu::Buffer,
    /// `path_stats`, its words 4 to 7 the waves' control.
    stats: wgpu::Buffer,
    args: wgpu::Buffer,
    /// The paths and queues for runs of `rows` rows of `capacity` pixels, and their group.
    paths: Option<Paths>,
    /// The most paths a run keeps.
    pub(crate) max_paths: u32,
}

fn buffer(ctx: &GpuContext, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
    ctx.device().create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage,
        mapped_at_creation: false,
    })
}

impl Wavefront {
    /// Compiles the waves' kernels after `library`, with the BVH's group 0 and the path
    /// tracer's group 1 laid out as `layouts`, its counts in `stats` (`path_stats`, whose
    /// words 4 to 7 the waves' control). An error where the device refuses them (more
    /// storage buffers than it binds a stage).
    pub(crate) async fn new(
        ctx: &GpuContext,
        library: &BvhLibrary,
        layouts: [&wgpu::BindGroupLayout; 2],
        (constants, stats): (&[(&str, f64)], &wgpu::Buffer),
    ) -> Result<Wavefront, PathError> {
        let module =
            (ctx.shader_module_async(library, &wavefront_source(), "path_wavefront.wgsl")).await?;
        let device = ctx.device();
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        use wgpu::BufferBindingType as B;
        let rw = B::Storage { read_only: false };
        let layout = buffer_layout(device, "path waves", &[B::Uniform, rw]);
        let groups = [layouts[0], layouts[1], &layout];
        let start = compute_pipeline(device, (&module, "path_wave_start"), &groups, constants);
        let extend = compute_pipeline(device, (&module, "path_wave_extend"), &groups, constants);
        use wgpu::BufferUsages as U;
        let uniform = buffer(ctx, "path wave", 16, U::UNIFORM | U::COPY_DST);
        let args = buffer(
            ctx,
            "path wave dispatch",
            12,
            U::STORAGE | U::INDIRECT | U::COPY_DST,
        );
        let prepare_layout = buffer_layout(device, "path wave prepare", &[rw, rw]);
        let prepare_module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(PATH_WAVE_PREPARE.0),
            source: wgpu::ShaderSource::Wgsl(PATH_WAVE_PREPARE.1.into()),
        });
        let entry = (&prepare_module, "path_wave_prepare");
        let prepare = compute_pipeline(device, entry, &[&prepare_layout], &[]);
        let prepare_group = bind_buffers(
            device,
            "path wave prepare",
            &prepare_layout,
            &[stats, &args],
        );
        refused(scope.pop().await, "making the path tracer's waves")?;
        Ok(Wavefront {
            start,
            extend,
            prepare,
            prepare_group,
            layout,
            uniform,
            stats: stats.clone(),
            args,
            paths: None,
            max_paths: MAX_WAVE_PATHS,
        })
    }

    /// Sizes the paths and queues for a `width` x `height` frame: runs of as many whole
    /// rows as [`Wavefront::max_paths`] and the device's bindings allow (one row at least).
    pub(crate) fn resize(&mut self, ctx: &GpuContext, (width, height): (u32, u32)) {
        let state = std::mem::size_of::<PathState>() as u64;
        let limits = ctx.device().limits();
        let bound = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        // A path's state and its place in each of the two queues.
        let limit = bound / (state + 8);
        let most = limit.min(u64::from(self.max_paths));
        let width = u64::from(width.max(1));
        let rows = (most / width).clamp(1, u64::from(height.max(1)));
        let capacity = (rows * width) as u32;
        if self
            .paths
            .as_ref()
            .is_some_and(|p| (p.capacity, p.rows) == (capacity, rows as u32))
        {
            return;
        }
        use wgpu::BufferUsages as U;
        // The states, then two queues of a word a path.
        // Read as vec4 words: whole ones.
        let bytes = (u64::from(capacity) * (state + 8)).next_multiple_of(16);
        let paths = buffer(ctx, "path states and queues", bytes, U::STORAGE);
        let group = bind_buffers(
            ctx.device(),
            "path waves",
            &self.layout,
            &[&self.uniform, &paths],
        );
        self.paths = Some(Paths {
            capacity,
            rows: rows as u32,
            group,
        });
    }

    /// Submits one sample of `params`' frame: per run of rows, the camera paths and their
    /// first vertex, then one wave per further bounce.
    pub(crate) fn submit_sample(
        &self,
        ctx: &GpuContext,
        groups: [&wgpu::BindGroup; 2],
        params: &PathParams,
    ) -> Result<(), PathError> {
        let Some(paths) = &self.paths else {
            return Err(PathError::Setting("a wave before restart".into()));
        };
        let mut first_row = 0;
        while first_row < params.height {
            let rows = (params.height - first_row).min(paths.rows);
            let wave = WaveParams {
                first_row,
                rows,
                capacity: paths.capacity,
                pad: 0,
            };
            let queue = ctx.queue();
            queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&wave));
            queue.write_buffer(&self.stats, 16, &[0; 16]);
            let mut encoder = ctx.device().create_command_encoder(&Default::default());
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("path waves"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.start);
                pass.set_bind_group(0, groups[0], &[]);
                pass.set_bind_group(1, groups[1], &[]);
                pass.set_bind_group(2, &paths.group, &[]);
                pass.dispatch_workgroups(params.width.div_ceil(8), rows.div_ceil(8), 1);
                for _ in 1..params.max_depth {
                    pass.set_pipeline(&self.prepare);
                    pass.set_bind_group(0, &self.prepare_group, &[]);
                    pass.dispatch_workgroups(1, 1, 1);
                    pass.set_pipeline(&self.extend);
                    pass.set_bind_group(0, groups[0], &[]);
                    pass.dispatch_workgroups_indirect(&self.args, 0);
                }
            }
            ctx.queue().submit([encoder.finish()]);
            first_row += rows;
        }
        Ok(())
    }
}

/// The paths and queues of a run of waves.
struct Paths {
    /// Paths a run keeps: its rows' pixels.
    capacity: u32,
    /// Rows a run takes.
    rows: u32,
    group: wgpu::BindGroup,
}
