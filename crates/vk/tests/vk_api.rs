//! What is particular to the ash backend's API: object lifetime (create and drop in a
//! loop, no leak reported by the validation layer), errors rather than panics (unknown
//! adapters, trees too deep, arrays too large, bad escape links, no driver at all), the
//! driver tuning a context takes, the `Tracer` interface's description of the device, and
//! updates with the part to write named. Ray-by-ray parity with the CPU twin, for ash as
//! for every tracer, is the workspace's conformance suite (`tests/conformance.rs`): this
//! crate's tests need no wgpu. Runs on lavapipe in CI; prints SKIP and passes only when
//! there is no Vulkan loader or device at all.

use bvhtrace_core::{FlatBvh, Precision, Query, Ray, TraceOptions, Traversal};
use bvhtrace_vk::engine::BvhStorage;
use bvhtrace_vk::engine::engine::{HasEngine, Update};
use bvhtrace_vk::engine::walks::FULL_STACK_SIZE;
use bvhtrace_vk::{
    AdapterChoice, DriverTuning, TraceError, Tracer, UploadOptions, VkBvh, VkContext, VkOptions,
};
use glam::Vec3;

#[path = "../../../tests/support/mod.rs"]
mod support;
use support::{SceneCase, cpu_counted, deep_tree, load_scene, one_triangle, parity_rays};

/// A context with validation on (when the layer is installed), or `None` (SKIP) when this
/// machine has no Vulkan at all.
fn context(test: &str) -> Option<VkContext> {
    context_with(test, None)
}

/// [`context`] with the given driver tuning (`None`: the device's own).
fn context_with(test: &str, tuning: Option<DriverTuning>) -> Option<VkContext> {
    match VkContext::with_options(&VkOptions {
        adapter: AdapterChoice::Auto,
        validation: true,
        tuning,
        max_binding_bytes: None,
    }) {
        Ok(ctx) => {
            eprintln!(
                "ash: {:?}, validation {}",
                ctx.device_info(),
                ctx.validation_enabled()
            );
            Some(ctx)
        }
        Err(e @ TraceError::NoAdapter { .. }) => {
            eprintln!("SKIP {test}: {e}");
            None
        }
        Err(e) => panic!("cannot open a Vulkan device: {e}"),
    }
}

/// Every object is destroyed: making and dropping the backend many times neither fails
/// nor exhausts anything (and the validation layer, when present, reports no leak).
#[test]
fn create_and_drop_in_a_loop() {
    let Some(first) = context("create and drop") else {
        return;
    };
    let bvh = one_triangle();
    let rays = [
        Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z),
        Ray::new(Vec3::new(3.0, 0.0, 5.0), Vec3::NEG_Z),
    ];
    assert_eq!(first.validation_errors(), 0);
    drop(first);
    for i in 0..20 {
        let ctx = VkContext::with_options(&VkOptions {
            validation: true,
            ..VkOptions::default()
        })
        .unwrap_or_else(|e| panic!("iteration {i}: {e}"));
        let gpu = VkBvh::upload(&ctx, &bvh, &UploadOptions::fitting(&bvh))
            .unwrap_or_else(|e| panic!("iteration {i}: {e}"));
        let opts = TraceOptions::closest(Traversal::ShortStack(4)).with_counters(i % 2 == 0);
        let out = gpu
            .trace(&rays, &opts)
            .unwrap_or_else(|e| panic!("iteration {i}: {e}"));
        assert_eq!(out.hits[0].prim, 0, "iteration {i}");
        assert_eq!(out.hits[0].t, 5.0, "iteration {i}");
        assert_eq!(out.hits[1].prim, bvhtrace_core::MISS, "iteration {i}");
        assert_eq!(ctx.validation_errors(), 0, "iteration {i}");
        // Drop order on purpose differs: the BVH keeps the device alive.
        if i % 2 == 0 {
            drop(ctx);
            drop(gpu);
        } else {
            drop(gpu);
            drop(ctx);
        }
    }
    // Leaked objects are reported while a device or instance is destroyed.
    assert_eq!(
        bvhtrace_vk::process_validation_errors(),
        0,
        "validation errors (leaks?) in this process"
    );
}

#[test]
fn errors_are_errors_not_panics() {
    let Some(ctx) = context("errors") else { return };
    // An unknown adapter names itself and lists what there is.
    match VkContext::new(AdapterChoice::Named("no-such-gpu-xyz".into())) {
        Err(e @ TraceError::AdapterNotFound { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains("no-such-gpu-xyz"), "{msg}");
            assert!(msg.contains(&ctx.device_info().name), "{msg}");
        }
        other => panic!("expected AdapterNotFound, got {other:?}"),
    }
    // The device's own name (any case) finds it.
    let name = ctx.device_info().name.to_uppercase();
    let again = VkContext::new(AdapterChoice::from_name(Some(&name))).expect("found by name");
    assert_eq!(again.device_info().name, ctx.device_info().name);

    // A tree deeper than the full-stack kernel's stack is refused for that traversal only.
    let deep = deep_tree();
    assert!(deep.depth() > FULL_STACK_SIZE);
    let gpu = VkBvh::upload(&ctx, &deep, &UploadOptions::fitting(&deep)).expect("upload");
    let rays = [Ray::new(Vec3::new(-1.0, 0.1, 0.0), Vec3::X)];
    let full = TraceOptions::closest(Traversal::FullStack);
    match gpu.trace(&rays, &full) {
        Err(e @ TraceError::TooDeep { .. }) => assert!(e.to_string().contains("stackless")),
        other => panic!("expected TooDeep, got {other:?}"),
    }
    // `supports` and `prepare` say so without tracing.
    assert!(matches!(
        gpu.supports(&full),
        Err(TraceError::TooDeep { .. })
    ));
    assert!(matches!(
        Tracer::prepare(&gpu, &full),
        Err(TraceError::TooDeep { .. })
    ));
    let stackless = TraceOptions::closest(Traversal::Stackless).with_counters(true);
    gpu.supports(&stackless)
        .expect("stackless works on deep trees");
    let out = gpu
        .trace(&rays, &stackless)
        .expect("stackless works on deep trees");
    let (cpu, cpu_counters) = cpu_counted(&deep, &rays, &stackless);
    assert_eq!(out.hits, cpu);
    assert_eq!(out.counters.as_deref(), Some(&cpu_counters[..]));
    // An array larger than one storage binding is split into pages (traced above the
    // binding as below it); one over `MAX_PAGES` bindings is refused before anything is
    // allocated, naming both sizes. On a context whose bindings are capped at 64 KiB.
    let small = VkContext::with_options(&VkOptions {
        max_binding_bytes: Some(64 << 10),
        ..VkOptions::default()
    })
    .expect("the same device again");
    // Triangles a page: as many as fit the binding, in whole 768-byte steps (16
    // triangles: each page a multiple of 256 bytes).
    let fit = (64 << 10) / std::mem::size_of::<bvhtrace_core::FlatTriangle>();
    let per_page = fit / 16 * 16;
    let split = load_scene("builtin:icosphere:4", "icosphere:4")
        .expect("builtin scene")
        .bvh;
    assert!(split.triangles().len() > 2 * per_page);
    let split_rays = parity_rays(&split);
    let stackless = TraceOptions::any(Traversal::Stackless);
    let got = VkBvh::upload(&small, &split, &UploadOptions::fitting(&split))
        .expect("in pages")
        .trace(&split_rays, &stackless)
        .expect("trace");
    assert_eq!(got.hits, cpu_counted(&split, &split_rays, &stackless).0);
    let max = usize::from(bvhtrace_vk::engine::pages::MAX_PAGES);
    let n = max * per_page + 1;
    let mut huge = deep.clone();
    *huge.parts_mut().triangles = vec![bytemuck::Zeroable::zeroed(); n];
    match VkBvh::upload(&small, &huge, &UploadOptions::fitting(&huge)) {
        Err(e @ TraceError::TooLarge { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains("triangles"), "{msg}");
            assert!(msg.contains("max_storage_buffer_binding_size"), "{msg}");
            assert!(msg.contains(&(max * per_page * 48).to_string()), "{msg}");
            assert!(msg.contains(&(n as u64 * 48).to_string()), "{msg}");
        }
        other => panic!("expected TooLarge, got {other:?}"),
    }
    // Escape links that do not match the nodes are refused, saying how to make them.
    let mut unlinked = deep.clone();
    unlinked.escapes_mut().truncate(8);
    match VkBvh::upload(&ctx, &unlinked, &UploadOptions::fitting(&unlinked)) {
        Err(
            e @ TraceError::BadEscapeLinks(bvhtrace_core::flat::EscapeLinksMismatch {
                found: 8,
                ..
            }),
        ) => {
            assert!(e.to_string().contains("escape_links"), "{e}")
        }
        other => panic!("expected BadEscapeLinks, got {other:?}"),
    }
    // An empty tree is refused.
    let nothing = FlatBvh::default();
    match VkBvh::upload(&ctx, &nothing, &UploadOptions::fitting(&nothing)) {
        Err(TraceError::EmptyBvh) => {}
        other => panic!("expected EmptyBvh, got {other:?}"),
    }
    // The f64 test on a device without shaderFloat64 is refused, naming the device.
    if !ctx.features().f64 {
        let f64_opts =
            TraceOptions::closest(Traversal::Stackless).with_precision(Precision::WatertightF64);
        match gpu.trace(&rays, &f64_opts) {
            Err(e @ TraceError::PrecisionUnsupported { .. }) => {
                assert!(e.to_string().contains(&ctx.device_info().name), "{e}")
            }
            other => panic!("expected PrecisionUnsupported, got {other:?}"),
        }
    }
    // An empty batch is fine.
    let empty = gpu
        .trace(&[], &TraceOptions::new(Traversal::Stackless, Query::Any))
        .expect("empty batch");
    assert!(empty.hits.is_empty());
    // The wide walk on a BVH uploaded without its wide layout: refused, naming the fix.
    assert!(!gpu.tree().wide);
    let wide = TraceOptions::closest(Traversal::Wide);
    for err in [
        gpu.trace(&rays, &wide).expect_err("no wide layout"),
        gpu.supports(&wide).expect_err("no wide layout"),
    ] {
        assert!(
            matches!(err, TraceError::WideLayoutMissing { .. })
                && err.to_string().contains("build_wide"),
            "{err}"
        );
    }
    assert_eq!(ctx.validation_errors(), 0);
}

/// A machine whose loader finds no driver: `VkContext::new` returns an error naming the
/// cause (never panics). Runs itself in a child process with the driver list pointed at
/// nothing (`VK_ICD_FILENAMES` / `VK_DRIVER_FILES`).
#[test]
fn no_driver_is_an_error() {
    const CHILD: &str = "BVHTRACE_VK_TEST_CHILD";
    if std::env::var_os(CHILD).is_some() {
        match VkContext::new(AdapterChoice::Auto) {
            Err(e @ TraceError::NoAdapter { .. }) => {
                let msg = e.to_string();
                assert!(msg.contains("mesa-vulkan-drivers"), "{msg}");
                println!("CHILD OK: {msg}");
            }
            Err(e) => panic!("expected NoDevice, got {e}"),
            Ok(ctx) => panic!("a device without drivers: {:?}", ctx.device_info()),
        }
        return;
    }
    let exe = std::env::current_exe().expect("test binary path");
    let out = std::process::Command::new(exe)
        .args(["no_driver_is_an_error", "--exact", "--nocapture"])
        .env(CHILD, "1")
        .env("VK_ICD_FILENAMES", "/nonexistent/bvhtrace_icd.json")
        .env("VK_DRIVER_FILES", "/nonexistent/bvhtrace_icd.json")
        .output()
        .expect("run the child");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && stdout.contains("CHILD OK"),
        "child failed:\n{stdout}\n{stderr}"
    );
}

/// The context's driver tuning: the device's own by default, always with buffers; an
/// explicit one is used as given (storage aside). What the trip budget does to the answers
/// is the conformance suite's (`tight_trip_budgets_finish_on_the_cpu`).
#[test]
fn driver_tuning() {
    let Some(ctx) = context("driver tuning") else {
        return;
    };
    let own = DriverTuning {
        storage: BvhStorage::Buffers,
        ..DriverTuning::for_device(ctx.device_info().kind)
    };
    assert_eq!(*ctx.tuning(), own);
    let Some(textures) = context_with(
        "driver tuning",
        Some(DriverTuning {
            storage: BvhStorage::Textures,
            ..DriverTuning::cpu_driver(3)
        }),
    ) else {
        return;
    };
    assert_eq!(
        *textures.tuning(),
        DriverTuning {
            storage: BvhStorage::Buffers,
            ..DriverTuning::cpu_driver(3)
        },
        "the ash backend reads buffers only"
    );
}

/// `VkBvh` through the `Tracer` interface describes itself: backend, device, default walk,
/// bytes uploaded, and device timings where the device has timestamps. Its answers are the
/// conformance suite's.
#[test]
fn tracer_interface_describes_the_device() {
    let Some(ctx) = context("tracer interface") else {
        return;
    };
    let Some(SceneCase { bvh, .. }) = load_scene("builtin:degenerate", "builtin:degenerate") else {
        panic!("the built-in degenerate scene always loads");
    };
    let rays = parity_rays(&bvh);
    let vk = VkBvh::upload(&ctx, &bvh, &UploadOptions::fitting(&bvh)).expect("upload");
    let tracers: [&dyn Tracer; 1] = [&vk];
    assert_eq!(tracers[0].backend(), "vulkan");
    assert!(
        tracers[0].device_name().contains(&ctx.device_info().name),
        "{}",
        tracers[0].device_name()
    );
    assert_eq!(tracers[0].default_traversal(), Traversal::GPU_DEFAULT);
    assert_eq!(tracers[0].uploaded_bytes(), vk.stats().total_bytes());
    assert_eq!(
        vk.stats().total_bytes(),
        (std::mem::size_of_val(bvh.nodes())
            + std::mem::size_of_val(bvh.triangles())
            + std::mem::size_of_val(bvh.escapes())) as u64
    );
    // The timings it reports: the device's when it has timestamps.
    let opts = TraceOptions::closest(tracers[0].default_traversal());
    tracers[0].prepare(&opts).expect("prepare");
    let out = tracers[0].trace(&rays, &opts).expect("trace");
    assert_eq!(out.gpu_ms.is_some(), ctx.has_timestamps());
    assert_eq!(out.hits.len(), rays.len());
    assert_eq!(ctx.validation_errors(), 0, "validation errors");
}

/// `VkBvh::update` with the part to write named (the top level only after the instances
/// moved, everything after a refit), and the bytes it then holds: after a flattening refit
/// that changes the wide collapse's node count, the binary nodes and the new wide ones;
/// another shape is refused. Parity after updates, through `Tracer::update`, is the
/// conformance suite's.
#[test]
fn named_updates_and_their_bytes() {
    let Some(ctx) = context("two-level updates") else {
        return;
    };
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    let mut ib = scene
        .instanced_bvh(&bvhtrace_core::BuildOptions::default())
        .expect("two levels");
    let mut vk = VkBvh::upload(
        &ctx,
        ib.bvh(),
        &UploadOptions::fitting(ib.bvh()).with_traversal(Traversal::Wide),
    )
    .expect("upload");
    let moved: Vec<glam::Affine3A> = ib
        .instances()
        .iter()
        .enumerate()
        .map(|(k, i)| glam::Affine3A::from_rotation_x(0.2 * k as f32) * i.transform)
        .collect();
    ib.set_transforms(&moved).expect("new transforms");
    vk.engine_mut()
        .update_with(ib.bvh(), Update::TopLevel)
        .expect("top-level update");
    let mut tris = ib.mesh_bvh(1).triangles().to_vec();
    tris.sort_by_key(|t| t.prim);
    let bent: Vec<_> = tris
        .iter()
        .map(|t| t.corners().map(|p| p * glam::Vec3::new(1.2, 0.7, 1.0)))
        .collect();
    ib.refit_mesh(1, &bent).expect("refit");
    vk.engine_mut()
        .update_with(ib.bvh(), Update::Everything)
        .expect("update after refit");
    // A mesh flattened to a twentieth of its height: the wide collapse comes out with
    // another number of nodes, and the update makes new wide buffers.
    let old_bytes = vk.stats().nodes_bytes;
    let mut tris = ib.mesh_bvh(2).triangles().to_vec();
    tris.sort_by_key(|t| t.prim);
    let flat: Vec<_> = tris
        .iter()
        .map(|t| t.corners().map(|p| p * glam::Vec3::new(1.0, 0.05, 1.0)))
        .collect();
    ib.refit_mesh(2, &flat).expect("refit");
    vk.update(ib.bvh()).expect("update after flattening");
    let wide = bvhtrace_core::WideBvh::collapse(ib.bvh());
    assert_ne!(
        vk.stats().nodes_bytes,
        old_bytes,
        "the wide layout kept its size"
    );
    assert_eq!(
        vk.stats().nodes_bytes,
        (std::mem::size_of_val(ib.bvh().nodes()) + wide.byte_sizes().0) as u64
    );
    assert!(
        vk.engine_mut()
            .update_with(&one_triangle(), Update::Everything)
            .is_err()
    );
    assert_eq!(ctx.validation_errors(), 0, "validation errors");
}
