//! Embedding the tracer in a user's own program: a device created with WebGPU's default
//! limits and no features either traces (buffer storage) or gets an error naming what is
//! missing, never a panic; and one uploaded BVH is traced from several threads at once.

use bvhtrace_core::{BuildOptions, FlatBvh, Precision, Ray, TraceOptions, Traversal, trace_rays};
use bvhtrace_gpu::{
    AdapterChoice, BvhStorage, ContextOptions, DriverTuning, GpuBvh, GpuContext, TraceError,
    UploadOptions, wgpu,
};
use glam::Vec3;

/// A device of the adapter `BVHTRACE_ADAPTER` or the best one names, created with `limits`
/// and no features, as a user following the wgpu examples would; `None` without Vulkan.
fn user_device(limits: wgpu::Limits) -> Option<(wgpu::Device, wgpu::Queue, wgpu::AdapterInfo)> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    let instance = wgpu::Instance::new(desc);
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
    let named: Vec<_> = adapters
        .iter()
        .map(|a| {
            let i = a.get_info();
            (i.name.clone(), bvhtrace_gpu::device_kind(i.device_type))
        })
        .collect();
    let Ok(index) = AdapterChoice::Auto.pick(&named) else {
        eprintln!("SKIP embedding: no Vulkan adapter");
        return None;
    };
    let adapter = &adapters[index];
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("a user's device"),
        required_limits: limits,
        ..Default::default()
    }))
    .expect("device");
    Some((device, queue, adapter.get_info()))
}

fn scene() -> (FlatBvh, Vec<Ray>) {
    let tris = bvhtrace_scene::load("builtin:icosphere:3")
        .expect("scene")
        .flatten()
        .triangles()
        .expect("triangles");
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let rays = (0..4096)
        .map(|i| {
            let (x, y) = ((i % 64) as f32 / 32.0 - 1.0, (i / 64) as f32 / 32.0 - 1.0);
            Ray::new(Vec3::new(x, y, 5.0), Vec3::new(0.05 * x, 0.0, -1.0))
        })
        .collect();
    (bvh, rays)
}

#[test]
fn a_device_with_default_limits_traces_or_says_what_is_missing() {
    let Some((device, queue, info)) = user_device(wgpu::Limits::default()) else {
        return;
    };
    let (bvh, rays) = scene();
    // Automatic tuning: WebGPU's default four storage textures per stage are too few for
    // the texture storage, so even a CPU driver gets buffers.
    let ctx = GpuContext::from_device(device.clone(), queue.clone(), info.clone())
        .expect("default limits are enough");
    assert_eq!(ctx.tuning().storage, BvhStorage::Buffers);
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    for traversal in [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(4),
    ] {
        let opts = TraceOptions::closest(traversal).with_counters(true);
        let out = gpu.trace(&rays, &opts).expect("trace");
        assert_eq!(out.hits, trace_rays(&bvh, &rays, &opts).hits, "{traversal}");
    }
    // Asking for texture storage on this device: an error naming the limit.
    let textures = ContextOptions {
        tuning: Some(DriverTuning::cpu_driver(2)),
        ..ContextOptions::default()
    };
    match GpuContext::from_device_with(device.clone(), queue.clone(), info.clone(), &textures) {
        Err(TraceError::LimitTooLow { limit, .. }) => {
            assert_eq!(limit, "max_storage_textures_per_shader_stage")
        }
        other => panic!("{other:?}"),
    }
    // No SHADER_F64 was requested: f64 is refused with an error, not a panic.
    let f64 = TraceOptions::closest(Traversal::Stackless).with_precision(Precision::WatertightF64);
    assert!(matches!(
        gpu.trace(&rays, &f64),
        Err(TraceError::PrecisionUnsupported { .. })
    ));
}

#[test]
fn a_device_below_the_required_limits_is_refused_by_name() {
    // WebGPU's downlevel defaults allow four storage buffers per stage (the kernels bind up
    // to six) and 16,352 bytes of workgroup memory (32 short of the traversal stacks).
    let Some((device, queue, info)) = user_device(wgpu::Limits::downlevel_defaults()) else {
        return;
    };
    match GpuContext::from_device(device, queue, info) {
        Err(
            e @ TraceError::LimitTooLow {
                limit, has, needs, ..
            },
        ) => {
            assert!(
                [
                    "max_storage_buffers_per_shader_stage",
                    "max_compute_workgroup_storage_size"
                ]
                .contains(&limit),
                "{limit}"
            );
            assert!(has < needs);
            assert!(e.to_string().contains("required limits"), "{e}");
        }
        other => panic!("{other:?}"),
    }
    // Exactly the required limits are enough.
    let Some((device, queue, info)) = user_device(GpuContext::required_limits()) else {
        return;
    };
    let ctx = GpuContext::from_device(device, queue, info).expect("required limits suffice");
    let (bvh, rays) = scene();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    let opts = TraceOptions::closest(Traversal::Stackless);
    assert_eq!(
        gpu.trace(&rays, &opts).expect("trace").hits,
        trace_rays(&bvh, &rays, &opts).hits
    );
}

/// A device whose textures are narrower than a row of texels (`TEXEL_ROW`): the texture
/// storage of either layout is refused before anything is created, naming the texture, the
/// limit and the way out; the same uploads in buffers trace.
#[test]
fn texture_storage_beyond_the_texture_limit_is_refused_by_name() {
    let limits = wgpu::Limits {
        max_texture_dimension_2d: bvhtrace_gpu::kernels::TEXEL_ROW / 2,
        max_storage_textures_per_shader_stage: 8,
        ..GpuContext::required_limits()
    };
    let Some((device, queue, info)) = user_device(limits) else {
        return;
    };
    let options = ContextOptions {
        tuning: Some(DriverTuning::cpu_driver(2)),
        ..ContextOptions::default()
    };
    let ctx = GpuContext::from_device_with(device, queue, info, &options).expect("context");
    let (bvh, rays) = scene();
    for (traversal, texture) in [
        (Traversal::Stackless, "node texels"),
        (Traversal::Wide, "wide node texels"),
    ] {
        let upload = UploadOptions::for_traversal(traversal);
        match GpuBvh::upload(&ctx, &bvh, &upload) {
            Err(e @ TraceError::TooLarge { buffer, .. }) => {
                assert_eq!(buffer, texture);
                let msg = e.to_string();
                assert!(
                    msg.contains("max_texture_dimension_2d") && msg.contains("BvhStorage::Buffers"),
                    "{msg}"
                );
            }
            other => panic!("{traversal}: {other:?}"),
        }
        let gpu =
            GpuBvh::upload(&ctx, &bvh, &upload.with_storage(BvhStorage::Buffers)).expect("buffers");
        let opts = TraceOptions::closest(traversal);
        let cpu = trace_rays(&bvh.clone().with_wide(), &rays, &opts).hits;
        assert_eq!(
            gpu.trace(&rays, &opts).expect("trace").hits,
            cpu,
            "{traversal}"
        );
    }
}

/// `GpuBvh` is `Send + Sync`: four threads trace their own rays through one upload at the
/// same time, each getting the CPU's answers.
#[test]
fn one_upload_is_traced_from_several_threads_at_once() {
    let ctx = match GpuContext::new(AdapterChoice::Auto) {
        Ok(ctx) => ctx,
        Err(e @ TraceError::NoAdapter { .. }) => {
            eprintln!("SKIP embedding: {e}");
            return;
        }
        Err(e) => panic!("{e}"),
    };
    let (bvh, rays) = scene();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    let opts = TraceOptions::closest(Traversal::Stackless).with_counters(true);
    std::thread::scope(|s| {
        let handles: Vec<_> = rays
            .chunks(rays.len() / 4)
            .enumerate()
            .map(|(i, part)| {
                let (gpu, opts, bvh) = (&gpu, &opts, &bvh);
                s.spawn(move || {
                    // Different lengths per thread, so the shared scratch buffers regrow.
                    let part = &part[..part.len() - 100 * i];
                    for _ in 0..3 {
                        let out = gpu.trace(part, opts).expect("trace");
                        assert_eq!(out.hits, trace_rays(bvh, part, opts).hits, "thread {i}");
                    }
                })
            })
            .collect();
        for h in handles {
            h.join().expect("a tracing thread panicked");
        }
    });
}
