//! The front door opens every backend, with the same answers, and falls back honestly
//! when the tree exceeds a device limit. Without any Vulkan adapter the device cases print
//! SKIP.

use bvhtrace::core::{BuildOptions, FlatBvh, Ray, Traversal};
use bvhtrace::glam::Vec3;
use bvhtrace::gpu::{ContextOptions, wgpu};
use bvhtrace::{
    AdapterChoice, Backend, BvhStorage, DriverTuning, GpuContext, OpenOptions, TraceError,
    TraceOptions, Tracer,
};

/// A 16 x 16 grid of quads (512 triangles) in the z = 0 plane, from -1 to 1.
fn grid() -> FlatBvh {
    let n = 16;
    let at = |i: usize, j: usize| {
        Vec3::new(
            -1.0 + 2.0 * i as f32 / n as f32,
            -1.0 + 2.0 * j as f32 / n as f32,
            0.05 * ((i * 7 + j * 3) % 5) as f32,
        )
    };
    let mut tris = Vec::new();
    for i in 0..n {
        for j in 0..n {
            tris.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
            tris.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
        }
    }
    FlatBvh::build(&tris, &BuildOptions::default()).expect("the grid builds")
}

/// 32 x 32 rays down the z axis, some outside the grid.
fn rays() -> Vec<Ray> {
    (0..32 * 32)
        .map(|k| {
            let (x, y) = ((k % 32) as f32 / 13.0 - 1.2, (k / 32) as f32 / 13.0 - 1.2);
            Ray::new(Vec3::new(x, y, 3.0), Vec3::NEG_Z)
        })
        .collect()
}

fn no_device(e: &TraceError) -> bool {
    matches!(e, TraceError::NoAdapter { .. })
}

#[test]
fn every_backend_opens_and_answers_alike() {
    let bvh = grid();
    let rays = rays();
    let cpu = bvhtrace::open(&bvh, &OpenOptions::new(Backend::Cpu)).expect("the CPU opens");
    assert_eq!(cpu.backend, Backend::Cpu);
    assert_eq!(cpu.traversal, Traversal::CPU_DEFAULT);
    assert_eq!(cpu.storage, None);
    assert!(cpu.fallback.is_none() && cpu.tracer.upload_stats().is_none());
    let reference = cpu
        .tracer
        .trace(&rays, &TraceOptions::closest(Traversal::FullStack))
        .expect("the CPU traces");
    let hits = reference.hits.iter().filter(|h| h.is_hit()).count();
    assert!(hits > 100 && hits < rays.len(), "{hits} hits");

    for backend in [Backend::Auto, Backend::Wgpu, Backend::Vulkan] {
        let opened = match bvhtrace::open(&bvh, &OpenOptions::new(backend)) {
            Ok(o) => o,
            Err(e) if no_device(&e) => {
                eprintln!("SKIP {backend}: {e}");
                continue;
            }
            Err(e) => panic!("{backend}: {e}"),
        };
        eprintln!("{backend}: {} ({:?})", opened.summary(), opened.fallback);
        // Auto picks wgpu when there is an adapter; a named backend is what it says.
        let expected = if backend == Backend::Auto {
            Backend::Wgpu
        } else {
            backend
        };
        assert_eq!(opened.backend, expected);
        assert_eq!(Backend::of(&*opened.tracer), Some(expected));
        assert_eq!(opened.traversal, opened.tracer.default_traversal());
        assert!(opened.fallback.is_none(), "{:?}", opened.fallback);
        let stats = opened.tracer.upload_stats().expect("a device upload");
        assert_eq!(opened.storage, Some(stats.storage));
        // Only what the default walk reads went up: its escape links, no wide layout.
        assert_eq!(
            stats.escapes_bytes > 0,
            opened.traversal.needs_escapes(),
            "{stats:?}"
        );
        let out = opened
            .tracer
            .trace(&rays, &TraceOptions::closest(opened.traversal))
            .expect("the device traces");
        assert_eq!(out.hits, reference.hits, "{backend}");
        let ran = opened.tracer.kernels_used();
        assert_eq!(ran.len(), 1, "{backend}: {ran:?}");
    }
}

#[test]
fn a_walk_asked_for_is_uploaded_and_the_wide_layout_is_built_when_missing() {
    let bvh = grid();
    assert!(bvh.wide().is_none());
    let rays = rays();
    let reference = bvhtrace_core_trace(&bvh, &rays);
    for backend in [Backend::Cpu, Backend::Wgpu, Backend::Vulkan] {
        let opts = OpenOptions::new(backend)
            .with_traversal(Traversal::Wide)
            .with_traversal(Traversal::FullStack);
        let opened = match bvhtrace::open(&bvh, &opts) {
            Ok(o) => o,
            Err(e) if no_device(&e) => {
                eprintln!("SKIP {backend}: {e}");
                continue;
            }
            Err(e) => panic!("{backend}: {e}"),
        };
        assert_eq!(opened.traversal, Traversal::Wide, "{backend}");
        for walk in [Traversal::Wide, Traversal::FullStack] {
            let out = opened
                .tracer
                .trace(&rays, &TraceOptions::closest(walk))
                .unwrap_or_else(|e| panic!("{backend} {walk}: {e}"));
            assert_eq!(out.hits, reference, "{backend} {walk}");
        }
    }
}

fn bvhtrace_core_trace(bvh: &FlatBvh, rays: &[Ray]) -> Vec<bvhtrace::Hit> {
    bvhtrace::core::trace_rays(bvh, rays, &TraceOptions::closest(Traversal::FullStack)).hits
}

/// A wgpu device whose 2D textures are narrower than a texel row, so that the texture
/// storage fits no tree, with the CPU-driver tuning (which prefers textures) on any
/// adapter.
fn narrow_texture_context() -> Option<GpuContext> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    let instance = wgpu::Instance::new(desc);
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
    let Some(adapter) = adapters.first() else {
        eprintln!("SKIP: no Vulkan adapter");
        return None;
    };
    let limits = wgpu::Limits {
        max_texture_dimension_2d: 4096,
        ..adapter.limits()
    };
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("narrow textures"),
        required_limits: limits,
        ..Default::default()
    }))
    .expect("a device with lower limits than the adapter's");
    let options = ContextOptions {
        tuning: Some(DriverTuning::cpu_driver(2)),
        ..ContextOptions::default()
    };
    Some(
        GpuContext::from_device_with(device, queue, adapter.get_info(), &options)
            .expect("the tracer's limits are met"),
    )
}

#[test]
fn a_tree_over_the_texture_limit_goes_to_buffers_or_the_error_names_the_limit() {
    let Some(ctx) = narrow_texture_context() else {
        return;
    };
    assert_eq!(ctx.tuning().storage, BvhStorage::Textures);
    let bvh = grid();
    let rays = rays();
    let device = bvhtrace::Device::wgpu(ctx.clone());
    let opened = device
        .open(&bvh, &OpenOptions::default())
        .expect("buffers fit");
    assert_eq!(opened.storage, Some(BvhStorage::Buffers));
    assert_eq!(opened.traversal, Traversal::GPU_DEFAULT);
    let why = opened.fallback.as_deref().expect("the fallback is said");
    assert!(
        why.contains("texture storage")
            && why.contains("max_texture_dimension_2d")
            && why.contains("buffer storage instead"),
        "{why}"
    );
    let out = opened
        .tracer
        .trace(&rays, &TraceOptions::closest(opened.traversal))
        .expect("traces");
    assert_eq!(out.hits, bvhtrace_core_trace(&bvh, &rays));

    // Textures asked for: every walk is tried in them, and the error names each, the
    // limit and the storage.
    let textures = OpenOptions::default().with_storage(BvhStorage::Textures);
    let err = device.open(&bvh, &textures).expect_err("no texture fits");
    let text = err.to_string();
    assert!(
        matches!(&err, TraceError::DoesNotFit { tried, .. } if tried.len() == 3)
            && text.contains("max_texture_dimension_2d")
            && text.contains("in texture storage")
            && text.contains("the full-stack walk in texture storage"),
        "{err}"
    );
}

#[test]
fn a_named_adapter_that_is_not_there_is_an_error_not_the_cpu() {
    let opts = OpenOptions::new(Backend::Auto)
        .with_adapter(AdapterChoice::Named("no such adapter 0xdead".into()));
    match bvhtrace::open(grid(), &opts) {
        Err(TraceError::AdapterNotFound { wanted, .. }) => assert!(wanted.contains("0xdead")),
        Err(e) if no_device(&e) => eprintln!("SKIP: {e}"),
        Err(e) => panic!("{e}"),
        Ok(o) => panic!("opened {}", o.summary()),
    }
}

/// A filter given to the front door: the CPU applies it (the filtered triangles are not
/// hit), `auto` on a device goes to the CPU and says why, and a device backend asked for
/// by name refuses rather than tracing without it.
#[test]
fn a_filter_is_applied_on_the_cpu_and_refused_by_the_devices() {
    use bvhtrace::core::Candidate;
    use std::sync::Arc;
    let bvh = grid();
    let rays = rays();
    let even_only = |c: &Candidate| c.prim.is_multiple_of(2);
    let filter = bvhtrace::SharedFilter(Arc::new(even_only));
    let opts = |backend| OpenOptions {
        filter: Some(filter.clone()),
        ..OpenOptions::new(backend)
    };
    let closest = TraceOptions::closest(Traversal::FullStack);
    let cpu = bvhtrace::open(&bvh, &opts(Backend::Cpu)).expect("the CPU opens");
    let hits = cpu.tracer.trace(&rays, &closest).expect("traces").hits;
    let want = bvhtrace::core::trace_rays_filtered(&bvh, &rays, &closest, Some(&even_only)).hits;
    assert_eq!(hits, want);
    assert!(hits.iter().all(|h| !h.is_hit() || h.prim.is_multiple_of(2)));
    assert!(hits.iter().filter(|h| h.is_hit()).count() > 100);
    let auto = bvhtrace::open(&bvh, &opts(Backend::Auto)).expect("auto opens");
    assert_eq!(auto.backend, Backend::Cpu);
    assert_eq!(
        auto.tracer.trace(&rays, &closest).expect("traces").hits,
        want
    );
    match bvhtrace::open(&bvh, &opts(Backend::Wgpu)) {
        Err(TraceError::Unsupported { what, .. }) => {
            assert!(what.contains("hit filters"), "{what}")
        }
        Err(e) if no_device(&e) => eprintln!("SKIP the wgpu refusal: {e}"),
        other => panic!(
            "a device backend took a filter: {:?}",
            other.map(|o| o.backend)
        ),
    }
}

/// The CPU backend traces closest hits with the default walk in the CPU layout
/// (`FastCpuTracer`), bit for bit the core full stack's, on a mesh and after an update, and
/// any hits there too (the same verdicts); the rest (counters, other walks) on the core
/// walks; two-level trees (with the
/// rays' visibility mask) and alpha-masked trees in the layout too.
#[test]
fn the_cpu_backend_takes_the_cpu_layout_for_closest_hits() {
    use bvhtrace::{CpuTracer, FastCpuTracer, Query, Tracer};
    let bvh = grid();
    let rays = rays();
    let fast = FastCpuTracer::new(CpuTracer::new(&bvh));
    assert!(fast.has_layout());
    let core = CpuTracer::new(&bvh);
    let bits = |h: &[bvhtrace::Hit]| -> Vec<[u32; 4]> {
        h.iter()
            .map(|h| [h.prim, h.t.to_bits(), h.u.to_bits(), h.v.to_bits()])
            .collect()
    };
    for (opts, layout) in [
        (TraceOptions::closest(Traversal::FullStack), true),
        (TraceOptions::new(Traversal::FullStack, Query::Any), true),
        (
            TraceOptions::closest(Traversal::FullStack).with_counters(true),
            false,
        ),
        (TraceOptions::closest(Traversal::Stackless), false),
    ] {
        assert_eq!(fast.takes(&opts), layout, "{opts:?}");
        let (a, b) = (
            fast.trace(&rays, &opts).expect("trace"),
            core.trace(&rays, &opts).expect("trace"),
        );
        if opts.query == Query::Closest {
            assert_eq!(bits(&a.hits), bits(&b.hits), "{opts:?}");
        } else {
            // Any hit: the same verdict, each walk stopping at the hit it found first.
            let hit = |h: &[bvhtrace::Hit]| h.iter().map(|h| h.is_hit()).collect::<Vec<_>>();
            assert_eq!(hit(&a.hits), hit(&b.hits), "{opts:?}");
            assert!(a.hits.iter().any(|h| h.is_hit()));
        }
        assert_eq!(a.counters.is_some(), opts.counters);
    }
    let opened = bvhtrace::open(&bvh, &OpenOptions::new(Backend::Cpu)).expect("the CPU opens");
    assert!(
        opened.tracer.device_name().contains("CPU layout"),
        "{}",
        opened.tracer.device_name()
    );
    // A filter keeps every query on the core walks.
    let filtered = FastCpuTracer::new(
        CpuTracer::new(&bvh).with_filter(std::sync::Arc::new(|_: &bvhtrace::core::Candidate| true)),
    );
    assert!(!filtered.takes(&TraceOptions::closest(Traversal::FullStack)));
    // Two levels, the instances behind each other and seen by different rays' masks: in
    // the layout, the outputs the core walks'.
    let instances = (0..3)
        .map(|k| bvhtrace::core::Instance {
            mask: 1 << k,
            user_id: 10 + k,
            ..bvhtrace::core::Instance::new(
                0,
                bvhtrace::glam::Affine3A::from_translation(Vec3::new(0.1, 0.0, -(k as f32))),
            )
        })
        .collect();
    let mesh: Vec<_> = grid().triangles().iter().map(|t| t.corners()).collect();
    let ib = bvhtrace::core::InstancedBvh::build(&[mesh], instances, &BuildOptions::default())
        .expect("two levels");
    let fast = FastCpuTracer::new(CpuTracer::new(ib.bvh()));
    let core = CpuTracer::new(ib.bvh());
    assert!(fast.has_layout());
    for mask in [0xff, 0x02, 0x04, 0x00] {
        let opts = TraceOptions::closest(Traversal::FullStack).with_mask(mask);
        assert!(fast.takes(&opts));
        let (a, b) = (
            fast.trace(&rays, &opts).expect("trace"),
            core.trace(&rays, &opts).expect("trace"),
        );
        assert_eq!(bits(&a.hits), bits(&b.hits), "{opts:?}");
        assert_eq!(a.instances, b.instances);
        assert!(a.instances.is_some());
    }
    // Alpha masks: every third triangle of the grid cut away.
    use bvhtrace::core::masks::{MASK_OPAQUE, MASK_TRANSPARENT, MaskTables};
    let mut masked = grid();
    let states = (0..masked.triangle_count())
        .map(|p| {
            if p % 3 == 0 {
                MASK_TRANSPARENT
            } else {
                MASK_OPAQUE
            }
        })
        .collect();
    let tables = MaskTables::new(states, vec![], vec![], vec![], vec![]).expect("tables");
    masked
        .set_masks(Some(std::sync::Arc::new(tables)))
        .expect("masks");
    let fast = FastCpuTracer::new(CpuTracer::new(&masked));
    assert!(fast.has_layout());
    let opts = TraceOptions::closest(Traversal::FullStack);
    let core = CpuTracer::new(&masked);
    let (a, b) = (
        fast.trace(&rays, &opts).expect("trace"),
        core.trace(&rays, &opts).expect("trace"),
    );
    assert_eq!(bits(&a.hits), bits(&b.hits));
    assert_ne!(
        bits(&a.hits),
        bits(&fast_plain_hits(&rays)),
        "the masks cut"
    );
}

/// The unmasked grid's closest hits through the layout.
fn fast_plain_hits(rays: &[Ray]) -> Vec<bvhtrace::Hit> {
    use bvhtrace::{CpuTracer, FastCpuTracer, Tracer};
    let bvh = grid();
    let fast = FastCpuTracer::new(CpuTracer::new(&bvh));
    fast.trace(rays, &TraceOptions::closest(Traversal::FullStack))
        .expect("trace")
        .hits
}

/// A tree over a device's buffer limit, on a device without texture storage (WebGPU's
/// default limits, scaled down to the grid): in pages of one binding each when they are
/// few enough (traced as the CPU traces it); else, whichever storage is asked for, or
/// none, the error names the limit exceeded, the bytes and the storage tried, and says
/// that the device has no texture storage, rather than only the missing feature.
#[test]
fn a_tree_over_the_buffer_limit_is_an_error_naming_the_limit_bytes_and_storage() {
    use bvhtrace_mock::MockDevice;
    let bvh = grid();
    let node_bytes = std::mem::size_of_val(bvh.nodes());
    let mut limits = bvhtrace::engine::plan::DeviceLimits {
        max_storage_buffer_binding_size: (node_bytes / 2) as u64,
        max_buffer_size: (node_bytes / 2) as u64,
        max_compute_workgroups_per_dimension: 65_535,
        min_storage_buffer_offset_alignment: 256,
        max_texture_dimension_2d: 8192,
        max_storage_buffers_per_shader_stage: 8,
    };
    let device = bvhtrace::Device::mock(MockDevice::new().with_limits(limits));
    let opened = (device.open(&bvh, &OpenOptions::default())).expect("the tree in pages");
    let rays = [Ray::new(Vec3::new(0.1, 0.2, 5.0), Vec3::NEG_Z)];
    let opts = TraceOptions::closest(opened.traversal);
    let hits = opened.tracer.trace(&rays, &opts).expect("trace").hits;
    assert!(hits[0].is_hit());
    assert_eq!(
        hits,
        bvhtrace::CpuTracer::new(&bvh)
            .trace(&rays, &opts)
            .expect("cpu")
            .hits
    );
    // A kilobyte a binding: more pages than a tree may have.
    (
        limits.max_storage_buffer_binding_size,
        limits.max_buffer_size,
    ) = (1 << 10, 1 << 10);
    let device = bvhtrace::Device::mock(MockDevice::new().with_limits(limits));
    assert!(
        node_bytes > 16 << 10,
        "the grid's {node_bytes} node bytes fit"
    );
    for asked in [None, Some(BvhStorage::Buffers), Some(BvhStorage::Textures)] {
        let opts = match asked {
            Some(s) => OpenOptions::default().with_storage(s),
            None => OpenOptions::default(),
        };
        let err = device.open(&bvh, &opts).expect_err("nothing fits");
        let text = err.to_string();
        eprintln!("{asked:?}: {text}");
        assert!(
            matches!(
                err,
                TraceError::DoesNotFit { .. } | TraceError::TooLarge { .. }
            ),
            "{text}"
        );
        assert!(
            text.contains("max_storage_buffer_binding_size")
                && text.contains(&format!("the nodes buffer needs {node_bytes} bytes"))
                && text.contains("16384 bytes")
                && text.contains("in buffer storage"),
            "{asked:?}: {text}"
        );
        // Unless buffers were asked for, the missing texture storage is said too: as
        // well as the limit, never instead of it.
        if asked != Some(BvhStorage::Buffers) {
            assert!(
                text.contains("lacks the texture storage"),
                "{asked:?}: {text}"
            );
        }
    }
}

/// The wgpu tracer the front door opened records its walk into the caller's encoder,
/// reading the caller's rays and writing the caller's hits: the hits of its own trace,
/// with the phases of that trace's wall time reported; other backends offer no such call.
#[test]
fn the_front_door_records_into_the_callers_buffers() {
    let (bvh, rays) = (grid(), rays());
    let cpu = bvhtrace::open(&bvh, &OpenOptions::new(Backend::Cpu)).expect("the CPU opens");
    assert!(cpu.wgpu_bvh().is_none());
    let opened = match bvhtrace::open(&bvh, &OpenOptions::new(Backend::Wgpu)) {
        Ok(o) => o,
        Err(e) if no_device(&e) => return eprintln!("SKIP: {e}"),
        Err(e) => panic!("{e}"),
    };
    let opts = TraceOptions::closest(opened.traversal);
    let traced = opened
        .tracer
        .trace(&rays, &opts)
        .expect("the device traces");
    let phases = traced
        .phases
        .expect("a device trace says where its time went");
    assert!(phases.upload_ms >= 0.0 && phases.device_ms > 0.0 && phases.readback_ms >= 0.0);
    assert!(phases.upload_ms + phases.device_ms + phases.readback_ms <= traced.wall_ms);

    let gpu = opened.wgpu_bvh().expect("the wgpu backend's tracer");
    let (device, queue) = (gpu.context().device(), gpu.context().queue());
    use wgpu::BufferUsages as U;
    let n = rays.len() as u64;
    let buffer = |size: u64, usage| {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("the caller's"),
            size,
            usage,
            mapped_at_creation: false,
        })
    };
    let (ray_buf, hit_buf) = (
        buffer(32 * n, U::STORAGE | U::COPY_DST),
        buffer(16 * n, U::STORAGE | U::COPY_SRC),
    );
    let read = buffer(16 * n, U::MAP_READ | U::COPY_DST);
    queue.write_buffer(&ray_buf, 0, bytemuck::cast_slice(&rays));
    let mut encoder = device.create_command_encoder(&Default::default());
    let batch = bvhtrace::gpu::RayBatch {
        rays: &ray_buf,
        hits: &hit_buf,
        counters: None,
        ray_count: n,
    };
    gpu.record(&mut encoder, &batch, &opts, None)
        .expect("recorded");
    encoder.copy_buffer_to_buffer(&hit_buf, 0, &read, 0, 16 * n);
    queue.submit([encoder.finish()]);
    read.slice(..)
        .map_async(wgpu::MapMode::Read, |r| r.expect("mapped"));
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("polled");
    let hits: Vec<bvhtrace::Hit> =
        bytemuck::pod_collect_to_vec(&read.slice(..).get_mapped_range().expect("the hits"));
    assert_eq!(hits, traced.hits);
}
