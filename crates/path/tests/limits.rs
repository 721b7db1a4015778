//! The path tracer on a user's device made with WebGPU's default limits (8 storage buffers
//! a stage, 4 bind groups): the waves fit and trace the twin's paths; on a device that
//! binds fewer storage buffers than the waves need, the single kernel takes over with the
//! same sums, and says so.

use bvhtrace_core::{BuildOptions, FlatBvh, Traversal};
use bvhtrace_gpu::{AdapterChoice, GpuContext, wgpu};
use bvhtrace_path::{
    Accumulation, CpuPathTracer, GpuPathTracer, Lighting, PathKernel, PathParams, PathScene,
    PathWalk,
};

/// A context on a device of the best adapter created with `limits` and no features, as a
/// user following the wgpu examples would; `None` without Vulkan.
fn user_context(limits: wgpu::Limits) -> Option<GpuContext> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    let instance = wgpu::Instance::new(desc);
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
    let named: Vec<_> = (adapters.iter())
        .map(|a| {
            let i = a.get_info();
            (i.name.clone(), bvhtrace_gpu::device_kind(i.device_type))
        })
        .collect();
    let Ok(index) = AdapterChoice::Auto.pick(&named) else {
        eprintln!("SKIP path tracer limits: no Vulkan adapter");
        return None;
    };
    let adapter = &adapters[index];
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("a user's device"),
        required_limits: limits,
        ..Default::default()
    }))
    .expect("device");
    Some(GpuContext::from_device(device, queue, adapter.get_info()).expect("context"))
}

/// The Cornell box's sums on `ctx` asked of `kernel`, the kernel that ran, and whether
/// they are the twin's bit for bit.
fn cornell(ctx: &GpuContext, kernel: PathKernel) -> (PathKernel, bool) {
    let scene = bvhtrace_scene::load("builtin:cornell").expect("scene");
    let tris = scene.flattened_triangles().expect("triangles");
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let shading = PathScene::new(&scene, &tris).expect("shading");
    let camera = scene.camera_or_frame(4.0 / 3.0);
    let params = PathParams::new(&camera, (32, 24), &Lighting::default(), 6, &shading);
    let walk = PathWalk::Walk(Traversal::Stackless);
    let mut gpu = GpuPathTracer::with_kernel(ctx, &bvh, &shading, walk, kernel).expect("tracer");
    gpu.restart(params);
    gpu.add_samples(2).expect("samples");
    let (device, _) = gpu.read().expect("read");
    let twin = CpuPathTracer::new(&bvh, &tris, &shading, Traversal::Stackless).expect("twin");
    let mut sums = Accumulation::default();
    for sample in 0..2 {
        twin.add_sample(&PathParams { sample, ..params }, &mut sums);
    }
    assert!(bvhtrace_path::mean_luminance(&sums) > 0.01, "a dark image");
    (gpu.kernel(), device == sums)
}

#[test]
fn webgpus_default_limits_run_the_waves() {
    let Some(ctx) = user_context(wgpu::Limits::default()) else {
        return;
    };
    for kernel in [PathKernel::Wavefront, PathKernel::Megakernel] {
        let (ran, same) = cornell(&ctx, kernel);
        assert_eq!(ran, kernel, "WebGPU's 8 storage buffers a stage");
        assert!(same, "{kernel:?}: the sums differ from the twin's");
    }
}

#[test]
fn too_few_storage_buffers_for_the_waves_run_the_single_kernel() {
    // The stackless walk binds three, the single kernel three more, the waves one more.
    let limits = wgpu::Limits {
        max_storage_buffers_per_shader_stage: 6,
        ..wgpu::Limits::default()
    };
    let Some(ctx) = user_context(limits) else {
        return;
    };
    let (ran, same) = cornell(&ctx, PathKernel::Wavefront);
    assert_eq!(ran, PathKernel::Megakernel);
    assert!(same, "the sums differ from the twin's");
}
