//! The path tracer on a wgpu device: the kernel composed after the traversal library of
//! an upload (our walk, or the device's ray queries), its resources in group 1, one
//! submission per sample adding to the sums on the device (one dispatch, or the waves of
//! `wavefront.rs`).

use bvhtrace_core::{FlatBvh, Traversal};
use bvhtrace_engine::shaders::{PATH_DISPLAY, PATH_ENVIRONMENT, PATH_SAMPLING, PATH_TRACE};
#[cfg(not(target_arch = "wasm32"))]
use bvhtrace_gpu::RayQueryBvh;
use bvhtrace_gpu::wgpu::util::DeviceExt;
use bvhtrace_gpu::{BvhLibrary, GpuBvh, GpuContext, GpuError, UploadOptions, wgpu};

use crate::material::PathMaterial;
use crate::scene::{PathLight, PathParams, PathScene};
use crate::wavefront::{PathKernel, Wavefront};
use crate::{Accumulation, PathError, PathStats};

/// What the kernel's rays are walked by.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PathWalk {
    /// Our walk, over the upload of the tree in the context's storage.
    Walk(Traversal),
    /// The device's ray queries over its own acceleration structure (wgpu's
    /// `EXPERIMENTAL_RAY_QUERY`); the hits agree with our walks' under the rule of
    /// docs/design.md, not bit for bit.
    RayQueries,
}

/// The upload the kernel reads, kept alive with its bind group.
enum Upload {
    Walk(Box<GpuBvh>),
    #[cfg(not(target_arch = "wasm32"))]
    RayQueries(Box<RayQueryBvh>),
}

/// The path tracer on a device: the BVH uploaded, the kernel compiled, the sums on the
/// device. [`GpuPathTracer::restart`] sets the camera and lights and starts the sum over;
/// each [`GpuPathTracer::add_samples`] adds samples without reading anything back;
/// [`GpuPathTracer::read`] reads the sums.
pub struct GpuPathTracer {
    ctx: GpuContext,
    _upload: Upload,
    kernel: Kernel,
    bvh_group: wgpu::BindGroup,
    layout: wgpu::BindGroupLayout,
    /// The shading data (`path_data`: [`shading_words`]).
    data: wgpu::Buffer,
    params_buffer: wgpu::Buffer,
    stats_buffer: wgpu::Buffer,
    accum: Option<(wgpu::Buffer, wgpu::BindGroup)>,
    params: PathParams,
    walk: PathWalk,
    display: Option<Display>,
    /// Samples the device has finished (counted by `on_submitted_work_done`).
    finished: std::sync::Arc<std::sync::atomic::AtomicU32>,
    /// The sample count the display texture shows (`None`: none yet, or stale).
    shown: Option<u32>,
}

/// The counts of `path_stats` and the wavefront's control words after them.
pub(crate) const STATS_BYTES: usize = 32;

/// The kernel that follows the paths.
enum Kernel {
    Mega(wgpu::ComputePipeline),
    Waves(Box<Wavefront>),
}

/// The tone-mapping pass and the texture it writes (`shaders/path_display.wgsl`).
struct Display {
    /// The exposure it was last written with.
    exposure: f32,
    pipeline: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
    texture: wgpu::Texture,
    group: wgpu::BindGroup,
}

/// The kernel's WGSL as composed after a traversal library (`bvhtrace_engine::wgsl_library`):
/// its sampling functions, then the kernel (entry point `path_main`, group 1 its own).
pub fn kernel_source() -> String {
    format!(
        "{}\n{}\n{}",
        PATH_SAMPLING.1, PATH_ENVIRONMENT.1, PATH_TRACE.1
    )
}

impl GpuPathTracer {
    /// Uploads `bvh` (one mesh, or two levels: its primitive ids number `scene.prims`) for
    /// `traversal`'s walk and compiles the kernel for it.
    pub fn new(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        scene: &PathScene,
        traversal: Traversal,
    ) -> Result<GpuPathTracer, PathError> {
        Self::with_walk(ctx, bvh, scene, PathWalk::Walk(traversal))
    }

    /// [`GpuPathTracer::new`] with the rays walked by `walk`. Blocks until the device has
    /// compiled the kernel: in a browser use [`GpuPathTracer::with_walk_async`].
    pub fn with_walk(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        scene: &PathScene,
        walk: PathWalk,
    ) -> Result<GpuPathTracer, PathError> {
        Self::with_kernel(ctx, bvh, scene, walk, PathKernel::default())
    }

    /// [`GpuPathTracer::with_walk`] with the paths followed by `kernel`. Blocks until the
    /// device has compiled it: in a browser use [`GpuPathTracer::with_kernel_async`].
    pub fn with_kernel(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        scene: &PathScene,
        walk: PathWalk,
        kernel: PathKernel,
    ) -> Result<GpuPathTracer, PathError> {
        if cfg!(target_arch = "wasm32") {
            return Err(PathError::Setting(
                "a browser cannot wait for its GPU: use GpuPathTracer::with_kernel_async".into(),
            ));
        }
        pollster::block_on(Self::with_kernel_async(ctx, bvh, scene, walk, kernel))
    }

    /// [`GpuPathTracer::with_walk`] as a future: what a page awaits (the browser compiles
    /// the kernel on its event loop).
    pub async fn with_walk_async(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        scene: &PathScene,
        walk: PathWalk,
    ) -> Result<GpuPathTracer, PathError> {
        Self::with_kernel_async(ctx, bvh, scene, walk, PathKernel::default()).await
    }

    /// [`GpuPathTracer::with_walk_async`] with the paths followed by `kernel`.
    pub async fn with_kernel_async(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        scene: &PathScene,
        walk: PathWalk,
        kernel: PathKernel,
    ) -> Result<GpuPathTracer, PathError> {
        // Two levels number the flattened scene's triangles instance by instance.
        if !bvh.is_instanced() && scene.prims.len() != crate::scene::primitives(bvh) {
            return Err(PathError::Scene(format!(
                "the shading data has {} primitives, the BVH {}",
                scene.prims.len(),
                crate::scene::primitives(bvh)
            )));
        }
        let (upload, library) = match walk {
            PathWalk::Walk(t) => {
                let up = GpuBvh::upload(ctx, bvh, &UploadOptions::for_traversal(t))?;
                let library = up.wgsl_library(t, 0)?;
                (Upload::Walk(Box::new(up)), library)
            }
            #[cfg(not(target_arch = "wasm32"))]
            PathWalk::RayQueries => {
                let up = RayQueryBvh::upload(ctx, bvh)?;
                let library = up.wgsl_library(0);
                (Upload::RayQueries(Box::new(up)), library)
            }
            #[cfg(target_arch = "wasm32")]
            PathWalk::RayQueries => {
                return Err(PathError::Setting("WebGPU has no ray queries".into()));
            }
        };
        let bvh_group = match &upload {
            Upload::Walk(u) => u.bind_group_for(&library)?,
            #[cfg(not(target_arch = "wasm32"))]
            Upload::RayQueries(u) => u.bind_group_for(&library)?,
        };
        let (bvh_group, bvh_layout) = (bvh_group.group().clone(), bvh_group.layout().clone());
        let layout = group_layout(ctx.device());
        let init = |label, contents: &[u8], usage| {
            ctx.device()
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage,
                })
        };
        use wgpu::BufferUsages as U;
        let data = init(
            "path shading data",
            bytemuck::cast_slice(&shading_words(scene)),
            U::STORAGE,
        );
        let params = PathParams::default();
        let params_buffer = init(
            "path params",
            bytemuck::bytes_of(&params),
            U::UNIFORM | U::COPY_DST,
        );
        let stats_buffer = init(
            "path stats",
            &[0; STATS_BYTES],
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        // The device's trip budget: a ray that spends it ends its path (counted), never hangs.
        let constants = [("BVH_TRIP_LIMIT", f64::from(ctx.tuning().trip_limit))];
        let layouts = [&bvh_layout, &layout];
        let waves = match kernel {
            PathKernel::Megakernel => None,
            // Where the device binds too few storage buffers a stage for the waves (one
            // more than the single kernel), the single kernel.
            PathKernel::Wavefront => {
                (Wavefront::new(ctx, &library, layouts, (&constants, &stats_buffer)).await).ok()
            }
        };
        let kernel = match waves {
            Some(w) => Kernel::Waves(Box::new(w)),
            None => Kernel::Mega(pipeline(ctx, &library, layouts, &constants).await?),
        };
        Ok(GpuPathTracer {
            ctx: ctx.clone(),
            _upload: upload,
            kernel,
            bvh_group,
            layout,
            data,
            params_buffer,
            stats_buffer,
            accum: None,
            params,
            walk,
            display: None,
            finished: Default::default(),
            shown: None,
        })
    }

    /// What the rays are walked by.
    pub fn walk(&self) -> PathWalk {
        self.walk
    }

    /// Bounds the paths one run of waves keeps ([`PathKernel::Wavefront`]; 80 bytes each,
    /// [`crate::wavefront::MAX_WAVE_PATHS`] at most), from the next restart: fewer use less
    /// device memory and take more runs a sample. The single kernel keeps none.
    pub fn set_max_wave_paths(&mut self, paths: u32) {
        if let Kernel::Waves(w) = &mut self.kernel {
            w.max_paths = paths.clamp(1, crate::wavefront::MAX_WAVE_PATHS);
        }
    }

    /// What follows the paths.
    pub fn kernel(&self) -> PathKernel {
        match self.kernel {
            Kernel::Mega(_) => PathKernel::Megakernel,
            Kernel::Waves(_) => PathKernel::Wavefront,
        }
    }

    /// Starts the sum over with `params` (camera, size, lights, depth, seed): call it on any
    /// change of view, scene or setting. The next sample is sample 0, whatever
    /// `params.sample` says.
    pub fn restart(&mut self, params: PathParams) {
        let size = u64::from(params.width) * u64::from(params.height) * 16;
        let fits = self
            .accum
            .as_ref()
            .is_some_and(|(b, _)| b.size() == size.max(16));
        if !fits {
            let buffer = self.ctx.device().create_buffer(&wgpu::BufferDescriptor {
                label: Some("path accumulation"),
                size: size.max(16),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let group = self.group(&buffer);
            self.accum = Some((buffer, group));
            // Its bind group read the old sums.
            self.display = None;
        }
        if let Kernel::Waves(w) = &mut self.kernel {
            w.resize(&self.ctx, (params.width, params.height));
        }
        self.params = PathParams {
            sample: 0,
            ..params
        };
        self.ctx
            .queue()
            .write_buffer(&self.stats_buffer, 0, &[0; STATS_BYTES]);
    }

    /// Samples per pixel summed so far.
    pub fn samples(&self) -> u32 {
        self.params.sample
    }

    /// The parameters of the next sample.
    pub fn params(&self) -> &PathParams {
        &self.params
    }

    /// The device buffer of the sums (`array<vec4<f32>>`, one per pixel row by row: RGB
    /// and the sample count), for a renderer to show without reading it back; `None`
    /// before [`GpuPathTracer::restart`].
    pub fn accumulation_buffer(&self) -> Option<&wgpu::Buffer> {
        self.accum.as_ref().map(|(b, _)| b)
    }

    fn group(&self, accum: &wgpu::Buffer) -> wgpu::BindGroup {
        let buffers = [&self.params_buffer, accum, &self.stats_buffer, &self.data];
        bind_buffers(
            self.ctx.device(),
            "path tracer group 1",
            &self.layout,
            &buffers,
        )
    }

    /// Submits one sample (its parameters written through the queue first).
    fn submit_sample(&self) -> Result<(), PathError> {
        let Some((_, group)) = &self.accum else {
            return Err(PathError::Setting("add_samples before restart".into()));
        };
        let p = self.params;
        if p.width == 0 || p.height == 0 {
            return Err(PathError::Setting(format!(
                "a {}x{} frame has no pixels",
                p.width, p.height
            )));
        }
        let queue = self.ctx.queue();
        queue.write_buffer(&self.params_buffer, 0, bytemuck::bytes_of(&p));
        let pipeline = match &self.kernel {
            Kernel::Mega(pipeline) => pipeline,
            Kernel::Waves(w) => return w.submit_sample(&self.ctx, [&self.bvh_group, group], &p),
        };
        let mut encoder = self
            .ctx
            .device()
            .create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("path tracer"),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &self.bvh_group, &[]);
            pass.set_bind_group(1, group, &[]);
            pass.dispatch_workgroups(p.width.div_ceil(8), p.height.div_ceil(8), 1);
        }
        queue.submit([encoder.finish()]);
        Ok(())
    }

    /// Adds `n` samples per pixel on the device: one submission each (each reads its
    /// index from the parameters); nothing is read back.
    pub fn add_samples(&mut self, n: u32) -> Result<(), PathError> {
        for _ in 0..n {
            self.submit_sample()?;
            self.params.sample += 1;
            let (finished, sample) = (self.finished.clone(), self.params.sample);
            self.ctx.queue().on_submitted_work_done(move || {
                finished.fetch_max(sample, std::sync::atomic::Ordering::Relaxed);
            });
        }
        Ok(())
    }

    /// Samples submitted that the device has not finished yet: a renderer that adds
    /// samples each frame keeps this small, so that the device's queue (and a readback
    /// behind it) does not grow without end where frames outrun the device (a page without
    /// vsync). Counted when the device reports the work done.
    pub fn samples_in_flight(&self) -> u32 {
        // Natively the callbacks run as the device is polled: without waiting.
        let _ = self.ctx.device().poll(wgpu::PollType::Poll);
        let finished = self.finished.load(std::sync::atomic::Ordering::Relaxed);
        self.params.sample.saturating_sub(finished)
    }

    /// Tone maps the sums into an RGBA8 texture of the frame's size (sRGB-encoded, as a
    /// renderer such as egui shows an `Rgba8Unorm` texture), on the device, reading nothing
    /// back: what a viewer draws each frame. The texture is the same one until the frame's
    /// size changes; `exposure` scales the radiance first.
    pub fn display(&mut self, exposure: f32) -> Result<&wgpu::Texture, PathError> {
        let Some((accum, _)) = &self.accum else {
            return Err(PathError::Setting("display before restart".into()));
        };
        // Nothing new to show: no work for the device.
        let fresh = matches!((&self.display, self.shown),
            (Some(d), Some(n)) if n == self.params.sample && d.exposure == exposure);
        if fresh {
            let d = self
                .display
                .as_ref()
                .ok_or(PathError::Setting("no display".into()))?;
            return Ok(&d.texture);
        }
        let (w, h) = (self.params.width, self.params.height);
        let size = wgpu::Extent3d {
            width: w.max(1),
            height: h.max(1),
            depth_or_array_layers: 1,
        };
        let device = self.ctx.device();
        let fits = (self.display.as_ref()).is_some_and(|d| d.texture.size() == size);
        if !fits {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(PATH_DISPLAY.0),
                source: wgpu::ShaderSource::Wgsl(PATH_DISPLAY.1.into()),
            });
            let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("path display"),
                layout: None,
                module: &module,
                entry_point: Some("path_display_main"),
                compilation_options: Default::default(),
                cache: None,
            });
            let texture = device.create_texture(&wgpu::TextureDescriptor {
                label: Some("path display"),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::STORAGE_BINDING
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            });
            let uniform = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("path display"),
                size: 16,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let view = texture.create_view(&Default::default());
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("path display"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: uniform.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: accum.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: wgpu::BindingResource::TextureView(&view),
                    },
                ],
            });
            self.display = Some(Display {
                exposure,
                pipeline,
                uniform,
                texture,
                group,
            });
        }
        let Some(d) = &mut self.display else {
            return Err(PathError::Setting("no display".into()));
        };
        d.exposure = exposure;
        let words = [w, h, exposure.to_bits(), 0];
        self.ctx
            .queue()
            .write_buffer(&d.uniform, 0, bytemuck::cast_slice(&words));
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&d.pipeline);
            pass.set_bind_group(0, &d.group, &[]);
            pass.dispatch_workgroups(w.div_ceil(8), h.div_ceil(8), 1);
        }
        self.ctx.queue().submit([encoder.finish()]);
        self.shown = Some(self.params.sample);
        Ok(&d.texture)
    }

    /// The texture [`GpuPathTracer::display`] last wrote (`None` before it ran).
    pub fn display_texture(&self) -> Option<&wgpu::Texture> {
        self.display.as_ref().map(|d| &d.texture)
    }

    /// Waits until the device has finished the samples submitted so far (reads nothing).
    pub fn wait(&self) -> Result<(), PathError> {
        self.ctx
            .device()
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| {
                PathError::Gpu(GpuError::Device {
                    during: "path tracing",
                    message: e.to_string(),
                })
            })
    }

    /// Reads the sums and the counts of what the paths could not trace back from the
    /// device (waits for the samples submitted so far): one readback
    /// (`GpuContext::readbacks`). Blocks: in a browser use [`GpuPathTracer::read_async`].
    pub fn read(&self) -> Result<(Accumulation, PathStats), PathError> {
        pollster::block_on(self.read_async())
    }

    /// [`GpuPathTracer::read`] as a future (what a page awaits); it owns what it reads,
    /// so it may outlive the borrow (`spawn_local`).
    pub fn read_async(
        &self,
    ) -> impl std::future::Future<Output = Result<(Accumulation, PathStats), PathError>> + 'static
    {
        let ctx = self.ctx.clone();
        let accum = self.accum.as_ref().map(|(b, _)| b.clone());
        let stats = self.stats_buffer.clone();
        let params = self.params;
        async move {
            let accum = accum.ok_or(PathError::Setting("read before restart".into()))?;
            let during = "reading the path tracer's sums";
            let bytes = ctx.read_buffers_async(during, &[&accum, &stats]).await?;
            Ok(unpack(&params, &bytes))
        }
    }
}

/// `path_data`: the scene's texture words and environment map, then its materials,
/// primitives and lights, their offsets in header words 4, 5 and 6
/// (`shaders/path_trace.wgsl`).
pub(crate) fn shading_words(scene: &PathScene) -> Vec<u32> {
    use crate::textures::HEADER_WORDS;
    let mut words = scene.textures.words.clone();
    // The header's offsets at least (none for a scene made by hand).
    words.resize(words.len().max(HEADER_WORDS), 0);
    words[4] = words.len() as u32;
    words.extend_from_slice(bytemuck::cast_slice::<PathMaterial, u32>(&scene.materials));
    words[5] = words.len() as u32;
    words.extend(scene.prims.iter().flatten());
    words[6] = words.len() as u32;
    words.extend_from_slice(bytemuck::cast_slice::<PathLight, u32>(&scene.lights));
    words
}

/// The sums and counts from their bytes.
fn unpack(p: &PathParams, bytes: &[Vec<u8>]) -> (Accumulation, PathStats) {
    let n = p.width as usize * p.height as usize;
    let sums: Vec<[f32; 4]> = bytemuck::pod_collect_to_vec(&bytes[0][..n * 16]);
    let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes[1][..16]);
    let image = Accumulation {
        width: p.width,
        height: p.height,
        sums,
    };
    let stats = PathStats {
        incomplete: u64::from(words[0]),
        not_finite: u64::from(words[1]),
        rays: u64::from(words[2]),
    };
    (image, stats)
}

/// Group 1: the parameters, materials, primitives, lights, sums, counts and textures.
fn group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    use wgpu::BufferBindingType as B;
    let kinds = [
        B::Uniform,
        B::Storage { read_only: false },
        B::Storage { read_only: false },
        B::Storage { read_only: true },
    ];
    buffer_layout(device, "path tracer group 1", &kinds)
}

/// A compute bind group layout of buffers, binding `i` of kind `kinds[i]`.
pub(crate) fn buffer_layout(
    device: &wgpu::Device,
    label: &str,
    kinds: &[wgpu::BufferBindingType],
) -> wgpu::BindGroupLayout {
    let entries: Vec<wgpu::BindGroupLayoutEntry> = (kinds.iter().enumerate())
        .map(|(i, &ty)| wgpu::BindGroupLayoutEntry {
            binding: i as u32,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        })
        .collect();
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(label),
        entries: &entries,
    })
}

/// `buffers`, whole, at bindings 0, 1, ... of `layout`.
pub(crate) fn bind_buffers(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::BindGroupLayout,
    buffers: &[&wgpu::Buffer],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = (buffers.iter().enumerate())
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: b.as_entire_binding(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &entries,
    })
}

/// Entry point `entry` of `module` over the bind groups `layouts`, its override
/// `constants` set (workgroup memory not zeroed: the walks write before they read).
pub(crate) fn compute_pipeline(
    device: &wgpu::Device,
    (module, entry): (&wgpu::ShaderModule, &str),
    layouts: &[&wgpu::BindGroupLayout],
    constants: &[(&str, f64)],
) -> wgpu::ComputePipeline {
    let groups: Vec<Option<&wgpu::BindGroupLayout>> = layouts.iter().map(|&l| Some(l)).collect();
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(entry),
        bind_group_layouts: &groups,
        immediate_size: 0,
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: Some(&pipeline_layout),
        module,
        entry_point: Some(entry),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants,
            zero_initialize_workgroup_memory: false,
        },
        cache: None,
    })
}

/// What a validation scope `caught` while making `during`'s pipelines (a device that
/// binds fewer storage buffers a stage than they read refuses them), as an error.
pub(crate) fn refused(caught: Option<wgpu::Error>, during: &'static str) -> Result<(), PathError> {
    match caught {
        Some(e) => Err(PathError::Gpu(GpuError::Device {
            during,
            message: e.to_string(),
        })),
        None => Ok(()),
    }
}

/// The kernel after `library`, its pipeline with the BVH in group 0 and ours in group 1.
async fn pipeline(
    ctx: &GpuContext,
    library: &BvhLibrary,
    layouts: [&wgpu::BindGroupLayout; 2],
    constants: &[(&str, f64)],
) -> Result<wgpu::ComputePipeline, PathError> {
    let module = (ctx.shader_module_async(library, &kernel_source(), "path_trace.wgsl")).await?;
    let device = ctx.device();
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let pipeline = compute_pipeline(device, (&module, "path_main"), &layouts, constants);
    refused(scope.pop().await, "making the path tracer's kernel")?;
    Ok(pipeline)
}
