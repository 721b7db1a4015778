//! Embedding the tracer in a user's own program: a device created with WebGPU's default
//! limits and no features either traces (buffer storage) or gets an error naming what is
//! missing, never a panic; and one uploaded BVH is traced from several threads at once.

use bvhtrace_core::{BuildOptions, FlatBvh, Precision, Ray, TraceOptions, Traversal, trace_rays};
use bvhtrace_gpu::{
    AdapterChoice, BvhStorage, ContextOptions, DriverTuning, GpuBvh, GpuContext, TraceError,
    Tracer, UploadOptions, wgpu,
};
use glam::Vec3;

// The example's pipeline and pass, which this file's own shader shares.
#[path = "../examples/own_shader.rs"]
#[allow(dead_code)]
mod own_shader;

mod support;

/// A device of the adapter `BVHTRACE_ADAPTER` or the best one names, created with `limits`
/// and no features, as a user following the wgpu examples would; `None` without Vulkan.
fn user_device(limits: wgpu::Limits) -> Option<(wgpu::Device, wgpu::Queue, wgpu::AdapterInfo)> {
    user_device_with(|_| limits)
}

/// [`user_device`] with the limits chosen from the adapter.
fn user_device_with(
    limits: impl FnOnce(&wgpu::Adapter) -> wgpu::Limits,
) -> Option<(wgpu::Device, wgpu::Queue, wgpu::AdapterInfo)> {
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
        required_limits: limits(adapter),
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

/// The limits the docs recommend buy the fast path: on a CPU driver the texture storage
/// (what `GpuContext::new` picks there), where the required limits alone give buffers; on a
/// GPU, buffers either way. The answers are the same.
#[test]
fn recommended_limits_buy_the_fast_path() {
    let Some((device, queue, info)) = user_device_with(GpuContext::recommended_limits) else {
        return;
    };
    let cpu_driver =
        bvhtrace_gpu::device_kind(info.device_type) == bvhtrace_gpu::engine::DeviceKind::Cpu;
    let fast = GpuContext::from_device(device, queue, info).expect("recommended limits suffice");
    let expected = if cpu_driver {
        BvhStorage::Textures
    } else {
        BvhStorage::Buffers
    };
    assert_eq!(fast.tuning().storage, expected);
    let Some((device, queue, info)) = user_device(GpuContext::required_limits()) else {
        return;
    };
    let least = GpuContext::from_device(device, queue, info).expect("required limits suffice");
    assert_eq!(least.tuning().storage, BvhStorage::Buffers);
    let (bvh, rays) = scene();
    let opts = TraceOptions::closest(Traversal::Stackless);
    let hits = |ctx: &GpuContext| {
        let gpu = GpuBvh::upload(ctx, &bvh, &UploadOptions::all()).expect("upload");
        assert_eq!(gpu.tree().storage, ctx.tuning().storage);
        gpu.trace(&rays, &opts).expect("trace").hits
    };
    assert_eq!(hits(&fast), hits(&least));
}

/// A device whose textures are narrower than a row of texels (`TEXEL_ROW`): the texture
/// storage of either layout is refused before anything is created, naming the texture, the
/// limit and the way out; the same uploads in buffers trace.
#[test]
fn texture_storage_beyond_the_texture_limit_is_refused_by_name() {
    let limits = wgpu::Limits {
        max_texture_dimension_2d: bvhtrace_gpu::engine::storage::TEXEL_ROW / 2,
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

/// A user's shader over the library: per ray, an any-hit trace, then the closest hit with
/// `bvh_hit_surface` and the hit's instance, 16 words per ray.
const OWN_SHADER: &str = r#"
@group(1) @binding(0) var<storage, read> rays: array<BvhRay>;
@group(1) @binding(1) var<storage, read_write> out: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = gid.x;
    if (i >= arrayLength(&rays)) {
        return;
    }
    let ray = rays[i];
    // Any-hit first: the closest trace after it must set the hit's triangle and instance.
    let any = bvh_trace_any(ray, lane).hit;
    let hit = bvh_trace_closest(ray, lane).hit;
    let b = i * 16u;
    out[b] = bitcast<u32>(hit.t);
    out[b + 1u] = hit.prim;
    out[b + 2u] = bitcast<u32>(hit.u);
    out[b + 3u] = bitcast<u32>(hit.v);
    out[b + 13u] = any.prim;
    if (hit.prim < BVH_INCOMPLETE) {
        let s = bvh_hit_surface(ray, hit);
        out[b + 4u] = bitcast<u32>(s.origin.x);
        out[b + 5u] = bitcast<u32>(s.origin.y);
        out[b + 6u] = bitcast<u32>(s.origin.z);
        out[b + 7u] = bitcast<u32>(s.normal.x);
        out[b + 8u] = bitcast<u32>(s.normal.y);
        out[b + 9u] = bitcast<u32>(s.normal.z);
        out[b + 10u] = bvh_hit_user_id();
        out[b + 11u] = bvh_hit_mesh_prim(hit);
        out[b + 12u] = bvh_hit_instance_index();
    }
}
"#;

/// What [`OWN_SHADER`] wrote for one ray.
#[derive(Debug)]
struct OwnAnswer {
    hit: bvhtrace_core::Hit,
    surface: bvhtrace_core::surface::SurfacePoint,
    user_id: u32,
    mesh_prim: u32,
    instance: u32,
    any_prim: u32,
}

/// Runs [`OWN_SHADER`] composed with `library` over `gpu` (bound with `bind_group_for`).
fn run_own_shader(
    gpu: &GpuBvh,
    library: &bvhtrace_gpu::BvhLibrary,
    rays: &[Ray],
) -> Vec<OwnAnswer> {
    run_own_shader_with(gpu, library, "", rays)
}

/// [`run_own_shader`] with more of the user's WGSL (a filter the library calls).
fn run_own_shader_with(
    gpu: &GpuBvh,
    library: &bvhtrace_gpu::BvhLibrary,
    more: &str,
    rays: &[Ray],
) -> Vec<OwnAnswer> {
    use wgpu::util::DeviceExt;
    let ctx = gpu.context();
    let device = ctx.device();
    let bvh_group = gpu
        .bind_group_for(library)
        .expect("the library's bind group");
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("own wgsl"),
        source: wgpu::ShaderSource::Wgsl(format!("{library}\n{OWN_SHADER}\n{more}").into()),
    });
    let words = rays.len() * 16;
    let ray_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("rays"),
        contents: bytemuck::cast_slice(rays),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let buffer = |usage| {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("out"),
            size: (words * 4) as u64,
            usage,
            mapped_at_creation: false,
        })
    };
    let out = buffer(wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC);
    let readback = buffer(wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST);
    let entry = |binding, read_only| {
        own_shader::layout_entry(binding, wgpu::BufferBindingType::Storage { read_only })
    };
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("own wgsl group 1"),
        entries: &[entry(0, true), entry(1, false)],
    });
    let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("own wgsl group 1"),
        layout: &layout,
        entries: &[own_shader::bind(0, &ray_buffer), own_shader::bind(1, &out)],
    });
    let pipeline = own_shader::pipeline(ctx, "own wgsl", &module, bvh_group.layout(), &layout);
    let mut encoder = own_shader::encode_pass(
        device,
        &pipeline,
        bvh_group.group(),
        &group,
        [(rays.len() as u32).div_ceil(64), 1, 1],
    );
    encoder.copy_buffer_to_buffer(&out, 0, &readback, 0, (words * 4) as u64);
    ctx.queue().submit([encoder.finish()]);
    let (tx, rx) = std::sync::mpsc::channel();
    readback.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("poll");
    rx.recv().expect("mapped").expect("map");
    let w: Vec<u32> = bytemuck::cast_slice(&readback.get_mapped_range(..).expect("range")).to_vec();
    let f = |k: usize| f32::from_bits(w[k]);
    (0..rays.len())
        .map(|i| {
            let b = i * 16;
            OwnAnswer {
                hit: bvhtrace_core::Hit {
                    t: f(b),
                    prim: w[b + 1],
                    u: f(b + 2),
                    v: f(b + 3),
                },
                surface: bvhtrace_core::surface::SurfacePoint {
                    origin: Vec3::new(f(b + 4), f(b + 5), f(b + 6)),
                    normal: Vec3::new(f(b + 7), f(b + 8), f(b + 9)),
                },
                user_id: w[b + 10],
                mesh_prim: w[b + 11],
                instance: w[b + 12],
                any_prim: w[b + 13],
            }
        })
        .collect()
}

/// Four placements of two meshes (one mirrored, one scaled unevenly), with user ids.
fn two_level_scene() -> bvhtrace_core::InstancedBvh {
    use bvhtrace_core::{Instance, InstancedBvh};
    use glam::{Affine3A, Quat};
    let mesh = |spec| {
        bvhtrace_scene::load(spec)
            .expect("scene")
            .flatten()
            .triangles()
            .expect("triangles")
    };
    let meshes = vec![mesh("builtin:icosphere:2"), mesh("builtin:icosphere:1")];
    let place = |mesh, transform, user_id| Instance {
        user_id,
        ..Instance::new(mesh, transform)
    };
    let instances = vec![
        place(0, Affine3A::from_translation(Vec3::new(-1.2, 0.0, 0.0)), 11),
        place(
            1,
            Affine3A::from_scale_rotation_translation(
                Vec3::new(0.6, 1.2, 0.8),
                Quat::from_rotation_z(0.5),
                Vec3::new(1.2, 0.3, 0.0),
            ),
            22,
        ),
        place(
            0,
            Affine3A::from_scale_rotation_translation(
                Vec3::new(-0.5, 0.5, 0.5),
                Quat::IDENTITY,
                Vec3::new(0.0, -1.0, 1.0),
            ),
            33,
        ),
        place(1, Affine3A::from_translation(Vec3::new(0.3, 1.1, -0.5)), 44),
    ];
    InstancedBvh::build(&meshes, instances, &BuildOptions::default()).expect("two levels")
}

/// The corners, in its mesh's space, of mesh primitive `prim` of instance `instance`.
fn object_triangle(ib: &bvhtrace_core::InstancedBvh, instance: u32, prim: u32) -> [Vec3; 3] {
    let mesh = &ib.meshes()[ib.instances()[instance as usize].mesh as usize];
    let tris =
        &ib.bvh().triangles()[mesh.tri_base as usize..(mesh.tri_base + mesh.triangles) as usize];
    tris.iter()
        .find(|t| t.prim == prim)
        .expect("the mesh holds the primitive")
        .corners()
}

fn same_hit(a: &bvhtrace_core::Hit, b: &bvhtrace_core::Hit) -> bool {
    a.prim == b.prim
        && a.t.to_bits() == b.t.to_bits()
        && a.u.to_bits() == b.u.to_bits()
        && a.v.to_bits() == b.v.to_bits()
}

/// Own WGSL on a two-level upload, in both storages and with each walk, returns
/// `trace()`'s hits bit for bit; the hit's instance, user id and mesh primitive (in WGSL,
/// and `TraceOutput::instance_hit` of `trace()`) are `InstancedBvh::locate`'s; and
/// `bvh_hit_surface` equals its CPU twin `instance_surface` bit for bit.
#[test]
fn own_wgsl_on_two_levels_returns_the_traced_hits_and_instances() {
    let Some(ctx) = support::context("embedding") else {
        return;
    };
    let ib = two_level_scene();
    let (_, rays) = scene();
    for storage in [BvhStorage::Buffers, BvhStorage::Textures] {
        let upload = UploadOptions::all()
            .with_traversal(Traversal::Wide)
            .with_storage(storage);
        let gpu = GpuBvh::upload(&ctx, ib.bvh(), &upload).expect("upload");
        for walk in [Traversal::Stackless, Traversal::FullStack, Traversal::Wide] {
            let what = format!("{storage:?}, {walk}");
            let library = gpu.wgsl_library(walk, 0).expect("library");
            assert!(library.shape().instanced, "{what}");
            let own = run_own_shader(&gpu, &library, &rays);
            let traced = gpu
                .trace(&rays, &TraceOptions::closest(walk))
                .expect("trace");
            let mut hits = 0;
            for (i, (o, t)) in own.iter().zip(&traced.hits).enumerate() {
                assert!(
                    same_hit(&o.hit, t),
                    "{what}: ray {i}: own {:?}, trace {t:?}",
                    o.hit
                );
                assert_eq!(
                    o.any_prim < bvhtrace_core::INCOMPLETE,
                    t.is_hit(),
                    "{what}: ray {i} any-hit"
                );
                if !t.is_hit() {
                    assert_eq!(traced.instance_hit(i), None);
                    continue;
                }
                hits += 1;
                let (inst, prim) = ib.locate(t.prim).expect("locate");
                let user_id = ib.instances()[inst as usize].user_id;
                let located = traced.instance_hit(i).expect("trace locates the hit");
                assert_eq!(
                    (located.instance, located.user_id, located.prim),
                    (inst, user_id, prim),
                    "{what}: ray {i}: TraceOutput::instance_hit"
                );
                assert_eq!(
                    (o.instance, o.user_id, o.mesh_prim),
                    (inst, user_id, prim),
                    "{what}: ray {i}: the WGSL hit's instance"
                );
                let tri = object_triangle(&ib, inst, prim);
                let cpu = bvhtrace_core::hits::instance_surface(
                    t,
                    &tri,
                    &ib.bvh().instances()[inst as usize],
                    &rays[i],
                );
                assert_eq!(
                    (
                        o.surface.origin.to_array().map(f32::to_bits),
                        o.surface.normal.to_array().map(f32::to_bits)
                    ),
                    (
                        cpu.origin.to_array().map(f32::to_bits),
                        cpu.normal.to_array().map(f32::to_bits)
                    ),
                    "{what}: ray {i}: bvh_hit_surface {:?} against the CPU's {cpu:?}",
                    o.surface
                );
            }
            assert!(hits > 500, "{what}: {hits} hits");
        }
    }
}

/// On one mesh, `bvh_hit_surface` is `Hit::surface` bit for bit, and the hit's instance
/// is 0 with its own primitive.
#[test]
fn own_wgsl_hit_surface_equals_the_cpu_surface_on_one_mesh() {
    let Some(ctx) = support::context("embedding") else {
        return;
    };
    let tris = bvhtrace_scene::load("builtin:icosphere:3")
        .expect("scene")
        .flatten()
        .triangles()
        .expect("triangles");
    let (bvh, rays) = scene();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    let library = gpu.wgsl_library(Traversal::Stackless, 0).expect("library");
    let own = run_own_shader(&gpu, &library, &rays);
    let traced = gpu
        .trace(&rays, &TraceOptions::closest(Traversal::Stackless))
        .expect("trace");
    assert!(traced.instances.is_none());
    let mut hits = 0;
    for (i, (o, t)) in own.iter().zip(&traced.hits).enumerate() {
        assert!(same_hit(&o.hit, t), "ray {i}: own {:?}, trace {t:?}", o.hit);
        if !t.is_hit() {
            continue;
        }
        hits += 1;
        assert_eq!(
            (o.instance, o.user_id, o.mesh_prim),
            (0, 0, t.prim),
            "ray {i}"
        );
        let cpu = t.surface(&tris[t.prim as usize], Vec3::from(rays[i].dir));
        assert_eq!(
            (
                o.surface.origin.to_array().map(f32::to_bits),
                o.surface.normal.to_array().map(f32::to_bits)
            ),
            (
                cpu.origin.to_array().map(f32::to_bits),
                cpu.normal.to_array().map(f32::to_bits)
            ),
            "ray {i}: bvh_hit_surface {:?} against Hit::surface {cpu:?}",
            o.surface
        );
    }
    assert!(hits > 500, "{hits} hits");
}

/// A filter rule as the CPU walks take it.
type Rule = dyn Fn(&bvhtrace_core::Candidate) -> bool + Sync;

/// A filter of the user's, in WGSL, composed into the library's walks
/// (`LibraryShape::with_filter`), cuts the same candidates as the same rule given to the
/// CPU walks as a closure: closest and any hit, bit for bit, one mesh (every third
/// primitive skipped) and two levels (one instance skipped, and a mesh primitive in the
/// others).
#[test]
fn own_wgsl_filters_equal_the_cpu_closure() {
    use bvhtrace_core::{Candidate, HitFilter, Query, trace_rays_filtered};
    let Some(ctx) = support::context("embedding") else {
        return;
    };
    let (bvh, rays) = scene();
    let ib = two_level_scene();
    let cases: [(&FlatBvh, &str, &Rule); 2] = [
        (
            &bvh,
            "fn skip_thirds(c: BvhCandidate) -> bool { return c.prim % 3u != 0u; }",
            &|c: &Candidate| !c.prim.is_multiple_of(3),
        ),
        (
            ib.bvh(),
            "fn skip_thirds(c: BvhCandidate) -> bool { return c.instance != 1u && c.mesh_prim != 7u; }",
            &|c: &Candidate| c.instance != Some(1) && c.mesh_prim != 7,
        ),
    ];
    for (bvh, wgsl, rule) in cases {
        let gpu = GpuBvh::upload(&ctx, bvh, &UploadOptions::all()).expect("upload");
        for walk in [Traversal::FullStack, Traversal::Stackless] {
            let shape = gpu.library_shape(walk).with_filter("skip_thirds");
            let library = bvhtrace_gpu::wgsl_library(shape, 0);
            let own = run_own_shader_with(&gpu, &library, wgsl, &rays);
            let cpu = |query| {
                let opts = TraceOptions::new(walk, query);
                trace_rays_filtered(bvh, &rays, &opts, Some(&rule as &dyn HitFilter)).hits
            };
            let (closest, any) = (cpu(Query::Closest), cpu(Query::Any));
            let plain = trace_rays(bvh, &rays, &TraceOptions::closest(walk)).hits;
            let mut cut = 0;
            for (i, o) in own.iter().enumerate() {
                assert!(
                    same_hit(&o.hit, &closest[i]),
                    "{walk} ray {i}: own {:?}, cpu {:?}",
                    o.hit,
                    closest[i]
                );
                assert_eq!(o.any_prim, any[i].prim, "{walk} ray {i}: any hit");
                cut += usize::from(plain[i].prim != closest[i].prim);
            }
            assert!(cut > 50, "{walk}: the filter changed {cut} hits");
        }
    }
}

/// Own WGSL over a masked upload (`scenes/foliage.gltf`, whose tree carries its alpha
/// masks): the library composes the masks in and answers as `trace()` does, bit for bit,
/// one level and two.
#[test]
fn own_wgsl_on_a_masked_scene_cuts_as_the_kernels_do() {
    let Some(ctx) = support::context("embedding") else {
        return;
    };
    let scene = bvhtrace_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/foliage.gltf"
    ))
    .expect("foliage");
    for flatten in [true, false] {
        let traced = scene
            .tracing_bvh(&BuildOptions::default(), flatten)
            .expect("bvh");
        let bvh = traced.bvh();
        assert!(bvh.masks().is_some());
        let b = bvh.bounds();
        let rays = bvhtrace_scene::Camera::frame(b.min, b.max, 1.0).rays(64, 64);
        let gpu = GpuBvh::upload(&ctx, bvh, &UploadOptions::all()).expect("upload");
        let library = gpu.wgsl_library(Traversal::Stackless, 0).expect("library");
        assert!(library.shape().masks && library.source().contains("bvh_masks"));
        let own = run_own_shader(&gpu, &library, &rays);
        let traced = gpu
            .trace(&rays, &TraceOptions::closest(Traversal::Stackless))
            .expect("trace");
        for (i, (o, t)) in own.iter().zip(&traced.hits).enumerate() {
            assert!(same_hit(&o.hit, t), "ray {i}: own {:?}, trace {t:?}", o.hit);
        }
    }
}

/// A library composed for another upload is refused by `bind_group_for` with an error
/// naming both shapes, never bound to find nothing: one mesh against two levels, and
/// buffers against textures; and a walk the upload lacks is refused when composing.
#[test]
fn a_mismatched_library_is_a_clear_error() {
    let Some(ctx) = support::context("embedding") else {
        return;
    };
    let ib = two_level_scene();
    let upload =
        UploadOptions::for_traversal(Traversal::Stackless).with_storage(BvhStorage::Buffers);
    let gpu = GpuBvh::upload(&ctx, ib.bvh(), &upload).expect("upload");
    let one_mesh =
        bvhtrace_gpu::LibraryShape::new(BvhStorage::Buffers, false, Traversal::Stackless);
    let textures =
        bvhtrace_gpu::LibraryShape::new(BvhStorage::Textures, true, Traversal::Stackless);
    for (shape, names) in [
        (one_mesh, ["one mesh", "two levels"]),
        (textures, ["Textures", "Buffers"]),
    ] {
        let library = bvhtrace_gpu::wgsl_library(shape, 0);
        match gpu.bind_group_for(&library) {
            Err(e @ TraceError::LibraryMismatch { .. }) => {
                let msg = e.to_string();
                assert!(names.iter().all(|n| msg.contains(n)), "{msg}");
            }
            Err(e) => panic!("another error for {shape}: {e}"),
            Ok(_) => panic!("a library for {shape} was bound to a two-level upload in buffers"),
        }
    }
    // The right library binds; the wide walk was not uploaded.
    let library = gpu.wgsl_library(Traversal::Stackless, 0).expect("library");
    assert!(gpu.bind_group_for(&library).is_ok());
    assert!(matches!(
        gpu.wgsl_library(Traversal::Wide, 0),
        Err(TraceError::WideLayoutMissing { .. })
    ));
}

/// A shader of yours that does not compile, after the library: an error, never wgpu's
/// panic, whose line and column count from your own source (a typo's line, and a type
/// error the validator finds); the same source corrected compiles.
#[test]
fn your_shader_that_does_not_compile_is_an_error_in_your_lines() {
    let Some(ctx) = support::context("embedding") else {
        return;
    };
    let (bvh, _) = scene();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    let library = gpu.wgsl_library(Traversal::Stackless, 0).expect("library");
    let shader = |call: &str, value: &str| {
        format!(
            "@group(1) @binding(0) var<storage, read_write> out: array<u32>;\n\
             \n\
             @compute @workgroup_size(64)\n\
             fn main(@builtin(local_invocation_index) lane: u32) {{\n\
             \x20   let ray = BvhRay(vec3<f32>(0.0), 0.0, vec3<f32>(0.0, 0.0, 1.0), 1e30);\n\
             \x20   let r = {call}(ray, lane);\n\
             \x20   let n: u32 = {value};\n\
             \x20   out[lane] = r.hit.prim + n;\n\
             }}\n"
        )
    };
    let good = shader("bvh_trace_closest", "1u");
    ctx.shader_module(&library, &good, "good.wgsl")
        .expect("the corrected shader compiles");
    for (source, line, what) in [
        (shader("bvh_trace_closestt", "1u"), 6, "bvh_trace_closestt"),
        (shader("bvh_trace_closest", "1.5"), 7, ""),
    ] {
        match ctx.shader_module(&library, &source, "mine.wgsl") {
            Err(e @ TraceError::Shader { .. }) => {
                let TraceError::Shader {
                    line: Some(l),
                    column: Some(c),
                    ..
                } = &e
                else {
                    panic!("no line and column: {e}")
                };
                assert_eq!(*l, line, "{e}");
                let msg = e.to_string();
                assert!(
                    msg.starts_with(&format!("mine.wgsl:{line}:{c}: ")) && msg.contains(what),
                    "{msg}"
                );
                eprintln!("{msg}");
            }
            Err(e) => panic!("another error: {e}"),
            Ok(_) => panic!("line {line}'s error compiled"),
        }
    }
}
