//! What is particular to the wgpu backend's API, on lavapipe in CI: upload options and
//! the errors of uploads and traces that do not fit them (walks or layouts left out, trees
//! too deep, escape links missing), the storages' layouts and byte counts, and `record`
//! into a caller's encoder with the caller's buffers. Ray-by-ray parity with the CPU twin,
//! for wgpu in both storages as for every tracer, is the conformance suite
//! (`tests/conformance.rs`). Without any Vulkan adapter the tests print SKIP.

use bvhtrace_core::{Query, Ray, TraceOptions, Traversal, trace_rays};
use bvhtrace_gpu::engine::engine::HasEngine;
use bvhtrace_gpu::{
    AdapterChoice, BvhStorage, CpuTracer, GpuBvh, GpuContext, GpuError, Tracer, UploadOptions,
};
use glam::Vec3;

mod support;
use support::one_triangle;

/// The wgpu context, or `None` after SKIP when there is no Vulkan adapter.
fn context() -> Option<GpuContext> {
    match GpuContext::new(AdapterChoice::Auto) {
        Ok(ctx) => {
            eprintln!(
                "GPU: {} ({:?}, {}), timestamps: {}",
                ctx.adapter_info().name,
                ctx.adapter_info().device_type,
                ctx.adapter_info().driver_info,
                ctx.has_timestamps()
            );
            Some(ctx)
        }
        Err(e @ GpuError::NoAdapter { .. }) => {
            eprintln!("SKIP wgpu_api: {e}");
            None
        }
        Err(e) => panic!("cannot open a GPU: {e}"),
    }
}

/// The binary walks' upload checks: escape links left out or not matching, a tree too deep
/// for the full stack, an empty batch.
#[test]
fn upload_checks_and_errors() {
    let Some(ctx) = context() else { return };
    let bvh = one_triangle();
    // Full stack only: no escapes uploaded, and the escape-link traversals are refused.
    let gpu = GpuBvh::upload(
        &ctx,
        &bvh,
        &UploadOptions::for_traversal(Traversal::FullStack),
    )
    .expect("upload");
    assert!(gpu.escapes_buffer().is_none());
    assert_eq!(gpu.stats().escapes_bytes, 0);
    let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
    assert!(matches!(
        gpu.trace(
            &rays,
            &TraceOptions::new(Traversal::Stackless, Query::Closest)
        ),
        Err(GpuError::EscapesNotUploaded { .. })
    ));
    let out = gpu
        .trace(
            &rays,
            &TraceOptions::new(Traversal::FullStack, Query::Closest),
        )
        .expect("trace");
    assert_eq!(out.hits[0].prim, 0);
    assert_eq!(out.hits[0].t, 5.0);
    // An empty batch.
    let out = gpu
        .trace(
            &[],
            &TraceOptions::new(Traversal::FullStack, Query::Closest),
        )
        .expect("trace");
    assert!(out.hits.is_empty());
    // A chain-like tree deeper than the full stack: refused for the full stack only.
    let mut deep = bvh.clone();
    *deep.parts_mut().depth = bvhtrace_gpu::engine::walks::FULL_STACK_SIZE + 1;
    assert!(matches!(
        GpuBvh::upload(&ctx, &deep, &UploadOptions::all()),
        Err(GpuError::TooDeep { .. })
    ));
    assert!(
        GpuBvh::upload(
            &ctx,
            &deep,
            &UploadOptions::for_traversal(Traversal::Stackless)
        )
        .is_ok()
    );
    // Escape links that do not match the nodes: refused for the walks that follow them.
    let mut unlinked = bvh.clone();
    unlinked.set_escapes(Vec::new());
    let err = GpuBvh::upload(
        &ctx,
        &unlinked,
        &UploadOptions::for_traversal(Traversal::ShortStack(4)),
    )
    .expect_err("no escape links");
    assert!(
        matches!(
            err,
            GpuError::BadEscapeLinks(bvhtrace_core::flat::EscapeLinksMismatch {
                nodes: 1,
                found: 0,
                ..
            })
        ),
        "{err}"
    );
    assert!(err.to_string().contains("escape_links"), "{err}");
    assert!(
        GpuBvh::upload(
            &ctx,
            &unlinked,
            &UploadOptions::for_traversal(Traversal::FullStack)
        )
        .is_ok()
    );
}

/// The wide walk and the wide layout: refused without it, uploaded alone or beside the
/// binary layout in either storage.
#[test]
fn upload_of_the_wide_layout() {
    let Some(ctx) = context() else { return };
    let bvh = one_triangle();
    let gpu = GpuBvh::upload(
        &ctx,
        &bvh,
        &UploadOptions::for_traversal(Traversal::FullStack),
    )
    .expect("upload");
    let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
    // The wide walk needs the wide layout: refused, naming the fix, by an upload without
    // it; the CPU tracer of a BVH without it collapses one beside the tree.
    let wide = TraceOptions::closest(Traversal::Wide);
    let err = gpu
        .trace(&rays, &wide)
        .expect_err("no wide layout uploaded");
    assert!(
        matches!(err, GpuError::WideLayoutMissing { .. })
            && err.to_string().contains("UploadOptions::traversals"),
        "{err}"
    );
    assert!(matches!(
        gpu.bind_group(Traversal::Wide),
        Err(GpuError::WideLayoutMissing { .. })
    ));
    let collapsed = CpuTracer::new(&bvh).trace(&rays, &wide).expect("collapsed");
    let built = CpuTracer::new(bvh.clone().with_wide()).trace(&rays, &wide);
    assert_eq!(collapsed.hits, built.expect("built").hits);
    // A wide-only upload (converted from the binary tree, since it has no wide layout):
    // the wide layout alone, in the storage asked for (one node of five texels, one
    // triangle of three: no padding); the binary walks refused.
    for storage in [BvhStorage::Textures, BvhStorage::Buffers] {
        let only = UploadOptions::for_traversal(Traversal::Wide).with_storage(storage);
        let gpu = GpuBvh::upload(&ctx, &bvh, &only).expect("wide-only upload");
        let w = bvhtrace_core::WideBvh::collapse(&bvh);
        let (nodes, tris) = w.byte_sizes();
        let stats = gpu.stats();
        assert_eq!(
            (
                stats.nodes_bytes,
                stats.triangles_bytes,
                stats.escapes_bytes
            ),
            (nodes as u64, tris as u64, 0),
            "{storage:?}: {stats:?}"
        );
        let textures = storage == BvhStorage::Textures;
        assert!(gpu.nodes_buffer().is_none());
        assert_eq!(
            (gpu.wide_buffers().is_some(), gpu.wide_textures().is_some()),
            (!textures, textures),
            "{storage:?}"
        );
        let out = gpu.trace(&rays, &wide).expect("wide trace");
        assert_eq!((out.hits[0].prim, out.hits[0].t), (0, 5.0));
        for traversal in [Traversal::FullStack, Traversal::Stackless] {
            let err = gpu
                .trace(&rays, &TraceOptions::closest(traversal))
                .expect_err("binary layout left out");
            assert!(
                matches!(err, GpuError::TraversalNotUploaded { .. })
                    && err.to_string().contains("UploadOptions::traversals"),
                "{err}"
            );
        }
        // Both layouts: the stats add up, each walk binds its own group.
        let both = UploadOptions::for_traversal(Traversal::FullStack)
            .with_storage(storage)
            .with_traversal(Traversal::Wide);
        let gpu = GpuBvh::upload(&ctx, &bvh, &both).expect("upload");
        let binary = GpuBvh::upload(
            &ctx,
            &bvh,
            &UploadOptions::for_traversal(Traversal::FullStack).with_storage(storage),
        )
        .expect("upload");
        assert_eq!(
            gpu.stats().total_bytes(),
            binary.stats().total_bytes() + (nodes + tris) as u64
        );
        let a = gpu
            .bind_group(Traversal::Wide)
            .expect("wide group")
            .group()
            .clone();
        let b = gpu
            .bind_group(Traversal::FullStack)
            .expect("binary group")
            .group()
            .clone();
        assert_ne!(a, b);
        for traversal in [Traversal::FullStack, Traversal::Wide] {
            let out = gpu
                .trace(&rays, &TraceOptions::closest(traversal))
                .expect("trace");
            assert_eq!((out.hits[0].prim, out.hits[0].t), (0, 5.0), "{traversal}");
        }
    }
}

/// `record` into the caller's encoder with the caller's buffers (and its buffer checks).
#[test]
fn record_into_user_encoder() {
    let Some(ctx) = context() else { return };
    let bvh = one_triangle();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).expect("upload");
    let rays: Vec<Ray> = (0..1000)
        .map(|i| {
            Ray::new(
                Vec3::new(-1.5 + 3.0 * i as f32 / 1000.0, 0.0, 5.0),
                Vec3::NEG_Z,
            )
        })
        .collect();
    use bvhtrace_gpu::wgpu;
    use wgpu::util::DeviceExt;
    let device = ctx.device();
    let rays_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: None,
        contents: bytemuck_cast(&rays),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let hits_buf = device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: 16 * 1000,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let small = device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: 16 * 999,
        usage: wgpu::BufferUsages::STORAGE,
        mapped_at_creation: false,
    });
    let read = device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: 16 * 1000,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let opts = TraceOptions::closest(Traversal::ShortStack(4));
    let mut enc = device.create_command_encoder(&Default::default());
    let batch = |hits| bvhtrace_gpu::RayBatch {
        rays: &rays_buf,
        hits,
        counters: None,
        ray_count: 1000,
    };
    assert!(matches!(
        gpu.record(&mut enc, &batch(&small), &opts, None),
        Err(GpuError::BadBuffer { buffer: "hits", .. })
    ));
    gpu.record(&mut enc, &batch(&hits_buf), &opts, None)
        .expect("record");
    enc.copy_buffer_to_buffer(&hits_buf, 0, &read, 0, 16 * 1000);
    ctx.queue().submit([enc.finish()]);
    read.slice(..)
        .map_async(wgpu::MapMode::Read, |r| r.expect("map"));
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("poll");
    let view = read.slice(..).get_mapped_range().expect("mapped");
    let words: Vec<u32> = view
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let cpu = trace_rays(&bvh, &rays, &TraceOptions::new(opts.traversal, opts.query)).hits;
    for (i, h) in cpu.iter().enumerate() {
        assert_eq!(words[4 * i + 1], h.prim, "ray {i}");
        assert_eq!(words[4 * i], h.t.to_bits(), "ray {i}");
    }
}

fn bytemuck_cast(rays: &[Ray]) -> &[u8] {
    // Ray is Pod (bvhtrace_core derives it); avoid a direct bytemuck dependency here.
    let len = std::mem::size_of_val(rays);
    // SAFETY: `Ray` is `#[repr(C)]`, `Pod`, 32 bytes without padding.
    unsafe { std::slice::from_raw_parts(rays.as_ptr().cast::<u8>(), len) }
}

/// `GpuBvh::update` with the part to write named (`Update::TopLevel` after the instances
/// moved, `Update::Everything` after a refit), and the bytes it then holds: after a
/// flattening refit that changes the wide collapse's node count, the wide nodes take what
/// the wide kernel's bindings need (`KernelKey::upload_bytes`; textures: whole rows), and
/// the upload what the binary tree's plus those. Parity after updates, through
/// `Tracer::update`, is the conformance suite's.
#[test]
fn named_updates_and_their_bytes() {
    use bvhtrace_gpu::Update;
    let Some(ctx) = context() else { return };
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    for storage in [BvhStorage::Buffers, BvhStorage::Textures] {
        let mut ib = scene
            .instanced_bvh(&bvhtrace_core::BuildOptions::default())
            .expect("two levels");
        let opts = UploadOptions::all()
            .with_storage(storage)
            .with_traversal(Traversal::Wide);
        let mut gpu = GpuBvh::upload(&ctx, ib.bvh(), &opts).expect("upload");
        let rays = support::parity_rays(ib.bvh());
        let moved: Vec<glam::Affine3A> = ib
            .instances()
            .iter()
            .map(|i| glam::Affine3A::from_translation(Vec3::new(0.2, 0.1, 0.0)) * i.transform)
            .collect();
        ib.set_transforms(&moved).expect("new transforms");
        gpu.engine_mut()
            .update_with(ib.bvh(), Update::TopLevel)
            .expect("top-level update");
        let opts = TraceOptions::closest(Traversal::FullStack);
        assert_eq!(
            gpu.trace(&rays, &opts).expect("trace").hits,
            trace_rays(ib.bvh(), &rays, &opts).hits,
            "{storage:?}: after a top-level update"
        );
        let mut tris: Vec<_> = ib.mesh_bvh(1).triangles().to_vec();
        tris.sort_by_key(|t| t.prim);
        let flat: Vec<bvhtrace_core::Triangle> = tris
            .iter()
            .map(|t| t.corners().map(|p| p * Vec3::new(1.0, 0.05, 1.0)))
            .collect();
        ib.refit_mesh(1, &flat).expect("refit");
        gpu.engine_mut()
            .update_with(ib.bvh(), Update::Everything)
            .expect("update after flattening");
        let wide = bvhtrace_core::WideBvh::collapse(ib.bvh());
        let wide_bytes =
            bvhtrace_gpu::KernelKey::new(storage, &TraceOptions::closest(Traversal::Wide))
                .with_instances(true)
                .upload_bytes(
                    wide.nodes.len() as u64,
                    wide.triangles.len() as u64,
                    wide.instances.len() as u64,
                );
        let node_bytes = match storage {
            BvhStorage::Buffers => gpu.wide_buffers().map(|(n, _)| n.size()),
            BvhStorage::Textures => gpu
                .wide_textures()
                .map(|(n, _)| u64::from(n.width()) * u64::from(n.height()) * 16),
        };
        assert_eq!(node_bytes, Some(wide_bytes.nodes_bytes), "{storage:?}");
        let binary = GpuBvh::upload(&ctx, ib.bvh(), &UploadOptions::all().with_storage(storage))
            .expect("upload");
        assert_eq!(
            gpu.stats().total_bytes(),
            binary.stats().total_bytes() + wide_bytes.total_bytes(),
            "{storage:?}"
        );
        // A named top-level update of a one-mesh tree, or of another shape: refused.
        assert!(matches!(
            gpu.engine_mut()
                .update_with(&one_triangle(), Update::Everything),
            Err(GpuError::BadBuffer { .. })
        ));
    }
}

/// `left_out` names exactly what the device lacks, one line each.
#[test]
fn left_out_names_what_the_device_lacks() {
    let Some(ctx) = context() else { return };
    let lines = ctx.left_out();
    let says = |what: &str| lines.iter().any(|l| l.starts_with(what));
    let features = ctx.features();
    assert_eq!(says("texture storage"), !features.textures, "{lines:?}");
    assert_eq!(says("the f64 triangle test"), !features.f64, "{lines:?}");
    assert_eq!(says("GPU timings"), !ctx.has_timestamps(), "{lines:?}");
    assert_eq!(
        lines.len(),
        usize::from(!features.textures)
            + usize::from(!features.f64)
            + usize::from(!ctx.has_timestamps()),
        "{lines:?}"
    );
}
