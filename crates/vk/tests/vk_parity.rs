//! The ash backend alone against the CPU twin, ray by ray and bit for bit (hits and
//! counters), on the built-in scenes with every walk; object lifetime and error behaviour.
//! The comparisons with the other backends on every parity scene are the workspace's
//! conformance suite (`tests/conformance.rs`): this crate's tests need no wgpu. Runs on
//! lavapipe in CI; prints SKIP and passes only when there is no Vulkan loader or device at
//! all.

use bvhtrace_core::{FlatBvh, Precision, Query, Ray, Traversal, trace_rays};
use bvhtrace_vk::kernels::{
    BvhStorage, CpuTracer, FULL_STACK_SIZE, plan_dispatches, rays_per_dispatch,
};
use bvhtrace_vk::{
    AdapterChoice, DriverTuning, TraceError, TraceOptions, Tracer, VkBvh, VkContext, VkOptions,
};
use glam::Vec3;

#[path = "../../../tests/support/mod.rs"]
mod support;
use support::{
    SceneCase, cpu_counted, deep_tree, differ, differences, load_instanced_scene, load_scene,
    one_triangle, parity_rays,
};

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

/// The built-in scenes: degenerate triangles, the Cornell box (also at 1e-4 scale), and
/// spheres in two levels.
fn scenes() -> Vec<SceneCase> {
    [
        load_scene("builtin:degenerate", "builtin:degenerate"),
        load_scene("builtin:cornell", "builtin:cornell"),
        load_scene("builtin:cornell#scale=1e-4", "builtin:cornell#scale=1e-4"),
        load_instanced_scene("builtin:spheres", "builtin:spheres"),
    ]
    .into_iter()
    .map(|s| s.expect("the built-in scenes always load"))
    .collect()
}

#[test]
fn ash_equals_the_cpu_bit_for_bit() {
    let Some(ctx) = context("ash parity") else {
        return;
    };
    let mut failures = Vec::new();
    for SceneCase { name, bvh, .. } in scenes() {
        // With its wide layout: the ash upload takes it, the CPU twin walks it.
        let bvh = bvh.with_wide();
        let rays = parity_rays(&bvh);
        let vk = VkBvh::upload(&ctx, &bvh).expect("ash upload");
        for traversal in [
            Traversal::FullStack,
            Traversal::Stackless,
            Traversal::ShortStack(4),
            Traversal::Wide,
        ] {
            for query in [Query::Closest, Query::Any] {
                let label = format!("{name} {traversal} {query:?}");
                let opts = TraceOptions::new(traversal, query);
                let (cpu_hits, cpu_counters) = cpu_counted(&bvh, &rays, &opts);
                let counted = vk.trace(&rays, &opts.with_counters(true)).expect("trace");
                let plain = vk.trace(&rays, &opts).expect("trace");
                assert!(plain.counters.is_none());
                assert_eq!(counted.gpu_ms.is_some(), ctx.has_timestamps());
                let counters = counted.counters.as_deref().expect("counters asked for");
                failures.extend(differences(
                    &format!("{label} on ash"),
                    &rays,
                    (&counted.hits, counters),
                    &plain.hits,
                    (&cpu_hits, &cpu_counters),
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert_eq!(ctx.validation_errors(), 0, "validation errors");
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
        let gpu = VkBvh::upload(&ctx, &bvh).unwrap_or_else(|e| panic!("iteration {i}: {e}"));
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
    let gpu = VkBvh::upload(&ctx, &deep).expect("upload");
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
    // An array larger than one storage binding is refused before anything is allocated,
    // naming both sizes (only tried where the limit is small enough to allocate here).
    let limit = ctx.limits().max_storage_buffer_binding_size;
    if limit <= 256 << 20 {
        let n = (limit / std::mem::size_of::<bvhtrace_core::FlatTriangle>() as u64 + 1) as usize;
        let mut huge = deep.clone();
        *huge.parts_mut().triangles = vec![bytemuck::Zeroable::zeroed(); n];
        match VkBvh::upload(&ctx, &huge) {
            Err(e @ TraceError::TooLarge { .. }) => {
                let msg = e.to_string();
                assert!(msg.contains("triangles"), "{msg}");
                assert!(msg.contains(&limit.to_string()), "{msg}");
                assert!(msg.contains(&(n as u64 * 48).to_string()), "{msg}");
            }
            other => panic!("expected TooLarge, got {other:?}"),
        }
    } else {
        eprintln!("SKIP the too-large upload: maxStorageBufferRange is {limit} bytes");
    }
    // Escape links that do not match the nodes are refused, saying how to make them.
    let mut unlinked = deep.clone();
    unlinked.escapes_mut().truncate(8);
    match VkBvh::upload(&ctx, &unlinked) {
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
    match VkBvh::upload(&ctx, &nothing) {
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
    assert!(!gpu.has_wide());
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

/// A batch larger than one dispatch (more rays than one storage binding holds, and more
/// workgroups than one grid dimension allows) is split as `plan_dispatches` says; every
/// ray is answered as the CPU answers it.
#[test]
fn batches_larger_than_a_dispatch_are_split() {
    let Some(ctx) = context("split batches") else {
        return;
    };
    let bvh = one_triangle();
    let n = rays_per_dispatch(ctx.limits()) as usize + 1000;
    let plan = plan_dispatches(n as u64, ctx.limits());
    assert!(plan.len() >= 2, "{plan:?}");
    let rays: Vec<Ray> = (0..n)
        .map(|i| {
            let x = (i % 2048) as f32 / 1024.0 - 1.0;
            let y = ((i / 2048) % 2048) as f32 / 1024.0 - 1.0;
            Ray::new(Vec3::new(x, y, 5.0), Vec3::NEG_Z)
        })
        .collect();
    let opts = TraceOptions::closest(Traversal::Stackless);
    let out = VkBvh::upload(&ctx, &bvh)
        .expect("upload")
        .trace(&rays, &opts)
        .expect("trace");
    let cpu = trace_rays(&bvh, &rays, &opts).hits;
    let bad = differ(&out.hits, &cpu);
    assert!(
        bad.is_empty(),
        "{} of {n} rays differ (plan {plan:?}); first {:?}",
        bad.len(),
        bad.first()
    );
    assert!(cpu.iter().any(|h| h.prim == 0) && cpu.iter().any(|h| h.prim != 0));
    assert_eq!(ctx.validation_errors(), 0);
}

/// The context's driver tuning: the device's own by default, always with buffers; an
/// explicit one is used as given (storage aside). A tiny trip budget leaves rays
/// incomplete, and they are finished on the CPU with the same answers and counters.
#[test]
fn driver_tuning_and_incomplete_rays() {
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
    drop(textures);

    let Some(SceneCase { name, bvh, .. }) = load_scene("builtin:cornell", "builtin:cornell") else {
        panic!("the built-in Cornell box always loads");
    };
    let rays = parity_rays(&bvh);
    let tight = DriverTuning {
        trip_limit: 4,
        ..DriverTuning::cpu_driver(2)
    };
    for tuning in [DriverTuning::GPU, tight] {
        let Some(ctx) = context_with("driver tuning", Some(tuning)) else {
            return;
        };
        let vk = VkBvh::upload(&ctx, &bvh).expect("upload");
        for traversal in [Traversal::FullStack, Traversal::ShortStack(4)] {
            let opts = TraceOptions::closest(traversal).with_counters(true);
            let out = vk.trace(&rays, &opts).expect("trace");
            let (cpu, cpu_counters) = cpu_counted(&bvh, &rays, &opts);
            let label = format!("{name} {traversal} {tuning:?}");
            assert!(differ(&out.hits, &cpu).is_empty(), "{label}: hits differ");
            assert!(
                differ(out.counters.as_deref().expect("counters"), &cpu_counters).is_empty(),
                "{label}: counters differ"
            );
            if tuning.finishes_on_cpu() {
                assert!(
                    out.incomplete > 0,
                    "{label}: a 4-trip budget finishes no ray"
                );
            } else {
                assert_eq!(out.incomplete, 0, "{label}");
            }
        }
        assert_eq!(ctx.validation_errors(), 0, "validation errors");
    }
}

/// `VkBvh` through the `Tracer` interface gives what the CPU tracer gives, and describes
/// itself.
#[test]
fn tracer_interface_matches_the_cpu() {
    let Some(ctx) = context("tracer interface") else {
        return;
    };
    let Some(SceneCase { bvh, .. }) = load_scene("builtin:degenerate", "builtin:degenerate") else {
        panic!("the built-in degenerate scene always loads");
    };
    let rays = parity_rays(&bvh);
    let vk = VkBvh::upload(&ctx, &bvh).expect("upload");
    let cpu = CpuTracer::new(&bvh);
    let tracers: [&dyn Tracer; 2] = [&vk, &cpu];
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
    for query in [Query::Closest, Query::Any] {
        let opts = TraceOptions::new(tracers[0].default_traversal(), query).with_counters(true);
        tracers[0].prepare(&opts).expect("prepare");
        let [a, c] = tracers.map(|t| t.trace(&rays, &opts).expect("trace"));
        assert!(
            differ(&a.hits, &c.hits).is_empty(),
            "{query:?}: hits differ"
        );
        assert_eq!(a.counters, c.counters, "{query:?}: counters differ");
    }
    assert_eq!(ctx.validation_errors(), 0, "validation errors");
}

/// A two-level upload updated in place after the instances moved and after a refit traces
/// as the CPU twin of the changed BVH does, bit for bit, the wide layout (collapsed again
/// by the update) too; another shape is refused.
#[test]
fn two_level_updates_in_place_match_the_cpu() {
    let Some(ctx) = context("two-level updates") else {
        return;
    };
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    let mut ib = scene
        .instanced_bvh(&bvhtrace_core::BuildOptions::default())
        .expect("two levels");
    let mut vk = VkBvh::upload(&ctx, &ib.bvh().clone().with_wide()).expect("upload");
    let rays = parity_rays(ib.bvh());
    let check = |vk: &VkBvh, bvh: &FlatBvh, what: &str| {
        let bvh = &bvh.clone().with_wide();
        for traversal in [Traversal::Stackless, Traversal::FullStack, Traversal::Wide] {
            let opts = TraceOptions::closest(traversal);
            let cpu = trace_rays(bvh, &rays, &opts).hits;
            let got = vk.trace(&rays, &opts).expect("trace").hits;
            assert!(differ(&cpu, &got).is_empty(), "{what} {traversal}");
        }
    };
    let moved: Vec<glam::Affine3A> = ib
        .instances()
        .iter()
        .enumerate()
        .map(|(k, i)| glam::Affine3A::from_rotation_x(0.2 * k as f32) * i.transform)
        .collect();
    ib.set_transforms(&moved).expect("new transforms");
    vk.update(ib.bvh()).expect("top-level update");
    check(&vk, ib.bvh(), "after new transforms");
    let mut tris = ib.mesh_bvh(1).triangles().to_vec();
    tris.sort_by_key(|t| t.prim);
    let bent: Vec<_> = tris
        .iter()
        .map(|t| t.corners().map(|p| p * glam::Vec3::new(1.2, 0.7, 1.0)))
        .collect();
    ib.refit_mesh(1, &bent).expect("refit");
    vk.update(ib.bvh()).expect("update after refit");
    check(&vk, ib.bvh(), "after a refit");
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
    check(&vk, ib.bvh(), "after flattening");
    assert!(vk.update(&one_triangle()).is_err());
    assert_eq!(ctx.validation_errors(), 0, "validation errors");
}
