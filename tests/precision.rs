//! Intersection precision (`bvhtrace_core::Precision`): watertight f32, Möller–Trumbore
//! f32, watertight f64.
//!
//! * On closed icospheres (the `builtin:icosphere:N` scene, shared vertices), rays from
//!   inside aimed exactly at every vertex and at points on every edge: the watertight tests
//!   (f32 and f64) let none escape; Möller–Trumbore's escapes are counted and, at a large
//!   offset, are not zero (its leaks are measured, not assumed).
//! * Every traversal returns the same closest hit as the brute-force loop with the same
//!   test, for every precision, and the default precision is exactly what options
//!   without one (`TraceOptions::new`) trace with (on well-conditioned scenes: where f32
//!   is indeterminate, see `f32_departure` in `tests/conformance.rs`).
//! * On the GPU (lavapipe in CI), each precision's kernels equal their CPU twin bit for bit
//!   (hits and counters) on two small scenes; f64 where the adapter has `SHADER_F64`.

use bvhtrace_core::{
    BuildOptions, FlatBvh, Hit, Precision, Query, TraceOptions, Traversal, Triangle, brute_force,
    trace_rays,
};
use bvhtrace_gpu::{AdapterChoice, GpuBvh, GpuContext, GpuError, Tracer, UploadOptions};
use glam::Vec3;

#[path = "support/rays.rs"]
mod support_rays;
use support_rays::edge_rays;

const TRAVERSALS: [Traversal; 4] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(1),
    Traversal::ShortStack(6),
];

fn triangles(spec: &str) -> Vec<Triangle> {
    bvhtrace_scene::load(spec)
        .unwrap_or_else(|e| panic!("{spec}: {e}"))
        .flatten()
        .triangles()
        .unwrap_or_else(|e| panic!("{spec}: {e}"))
}

fn centre(tris: &[Triangle]) -> Vec3 {
    let (lo, hi) = tris.iter().flatten().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(l, h), p| (l.min(*p), h.max(*p)),
    );
    (lo + hi) * 0.5
}

/// Escapes (misses) of edge/vertex rays from two inside points, per traversal.
fn escapes(spec: &str, precision: Precision) -> Vec<(Traversal, usize, usize)> {
    let tris = triangles(spec);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let c = centre(&tris);
    let size = (tris[0][0] - c).length();
    let mut rays = edge_rays(&tris, c);
    rays.extend(edge_rays(&tris, c + Vec3::new(0.3, -0.2, 0.1) * size));
    TRAVERSALS
        .iter()
        .map(|&tr| {
            let hits = trace_rays(
                &bvh,
                &rays,
                &TraceOptions::closest(tr).with_precision(precision),
            )
            .hits;
            assert!(
                hits.iter()
                    .all(|h| !h.t.is_nan() && !h.u.is_nan() && !h.v.is_nan())
            );
            (tr, hits.iter().filter(|h| !h.is_hit()).count(), rays.len())
        })
        .collect()
}

const CLOSED: [&str; 4] = [
    "builtin:icosphere:3",
    "builtin:icosphere:3#offset=1000,-500,250",
    "builtin:icosphere:3#offset=100000,-50000,25000",
    "builtin:icosphere:2#scale=1e-2#offset=30,10,-20",
];

#[test]
fn watertight_tests_never_leak_and_moller_trumbore_leaks_are_counted() {
    let mut mt_total = 0;
    for spec in CLOSED {
        for p in Precision::ALL {
            for (tr, n, of) in escapes(spec, p) {
                eprintln!(
                    "{spec:48} {:20} {tr:16} {n:6} of {of} rays escaped",
                    p.name()
                );
                if p.is_watertight() {
                    assert_eq!(n, 0, "{spec} {p} {tr}: {n} of {of} rays escaped");
                } else {
                    mt_total += n;
                }
            }
        }
    }
    // Measured: Möller–Trumbore lets edge and vertex rays through once the mesh is far from
    // the origin (its `s = org - v0` and edge vectors lose the bits that decide).
    assert!(
        mt_total > 0,
        "Möller–Trumbore never leaked on these closed meshes"
    );
}

#[test]
fn every_traversal_equals_brute_force_for_every_precision() {
    for spec in [
        "builtin:icosphere:3#offset=1000,-500,250",
        "builtin:cornell",
    ] {
        let tris = triangles(spec);
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
        let c = centre(&tris);
        let mut rays = edge_rays(&tris, c);
        let scene = bvhtrace_scene::load(spec).unwrap();
        rays.extend(scene.camera_or_frame(1.0).rays(48, 48));
        for p in Precision::ALL {
            let brute: Vec<Hit> = rays.iter().map(|r| brute_force(&bvh, r, p)).collect();
            for tr in TRAVERSALS {
                let hits =
                    trace_rays(&bvh, &rays, &TraceOptions::closest(tr).with_precision(p)).hits;
                let diff = hits
                    .iter()
                    .zip(&brute)
                    .filter(|(a, b)| a.prim != b.prim || a.t.to_bits() != b.t.to_bits())
                    .count();
                assert_eq!(
                    diff, 0,
                    "{spec} {p} {tr}: {diff} rays differ from brute force"
                );
            }
        }
        // The default precision is what options without one trace with, bit for bit.
        for tr in TRAVERSALS {
            let a = trace_rays(&bvh, &rays, &TraceOptions::closest(tr)).hits;
            let b = trace_rays(
                &bvh,
                &rays,
                &TraceOptions::closest(tr).with_precision(Precision::default()),
            )
            .hits;
            assert!(a.iter().zip(&b).all(|(x, y)| x.prim == y.prim
                && x.t.to_bits() == y.t.to_bits()
                && x.u.to_bits() == y.u.to_bits()
                && x.v.to_bits() == y.v.to_bits()));
        }
    }
}

#[test]
fn gpu_equals_cpu_twin_for_every_precision() {
    let ctx = match GpuContext::new(AdapterChoice::Auto) {
        Ok(c) => c,
        Err(e @ GpuError::NoAdapter { .. }) => {
            eprintln!("SKIP gpu precision parity: {e}");
            return;
        }
        Err(e) => panic!("cannot open a GPU: {e}"),
    };
    let has_f64 = ctx
        .device()
        .features()
        .contains(bvhtrace_gpu::wgpu::Features::SHADER_F64);
    eprintln!("GPU: {} (SHADER_F64: {has_f64})", ctx.adapter_info().name);
    assert_eq!(
        ctx.supports_precision(Precision::WatertightF64),
        has_f64,
        "supports_precision agrees with the device's features"
    );
    let mut checked = 0;
    for spec in [
        "builtin:icosphere:3#offset=100000,-50000,25000",
        "builtin:cornell",
    ] {
        let tris = triangles(spec);
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
        let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).unwrap();
        let mut rays = edge_rays(&tris, centre(&tris));
        let scene = bvhtrace_scene::load(spec).unwrap();
        rays.extend(scene.camera_or_frame(1.0).rays(64, 64));
        for p in Precision::ALL {
            if !ctx.supports_precision(p) {
                let err = gpu
                    .trace(
                        &rays,
                        &TraceOptions::closest(Traversal::FullStack).with_precision(p),
                    )
                    .expect_err("an unsupported precision is refused");
                assert!(matches!(err, GpuError::PrecisionUnsupported { .. }));
                eprintln!("{p}: not supported here ({err})");
                continue;
            }
            for tr in [
                Traversal::FullStack,
                Traversal::Stackless,
                Traversal::ShortStack(2),
            ] {
                for q in [Query::Closest, Query::Any] {
                    let opts = TraceOptions::new(tr, q)
                        .with_precision(p)
                        .with_counters(true);
                    let cpu = trace_rays(&bvh, &rays, &opts);
                    let cpu_c = cpu.counters.expect("CPU counters");
                    let cpu = cpu.hits;
                    let out = gpu
                        .trace(&rays, &opts)
                        .unwrap_or_else(|e| panic!("{spec} {p} {tr}: {e}"));
                    let gpu_c = out.counters.expect("counters");
                    for (i, (a, b)) in out.hits.iter().zip(&cpu).enumerate() {
                        assert!(
                            a.prim == b.prim
                                && a.t.to_bits() == b.t.to_bits()
                                && a.u.to_bits() == b.u.to_bits()
                                && a.v.to_bits() == b.v.to_bits()
                                && gpu_c[i] == cpu_c[i],
                            "{spec} {p} {tr} {q:?} ray {i} {:?}: GPU {a:?} {:?} vs CPU {b:?} {:?}",
                            rays[i],
                            gpu_c[i],
                            cpu_c[i]
                        );
                    }
                    checked += 1;
                }
            }
        }
    }
    assert!(checked >= 12, "checked {checked} configurations");
}

/// A device created without `SHADER_F64` (as an application may hand us one): f64 kernels
/// are refused with a clear error, before any shader is compiled; the f32 ones still run.
#[test]
fn f64_without_shader_f64_is_a_clear_error() {
    use bvhtrace_gpu::wgpu;
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    let instance = wgpu::Instance::new(desc);
    let Some(adapter) = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN))
        .into_iter()
        .next()
    else {
        eprintln!("SKIP: no Vulkan adapter");
        return;
    };
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("no f64"),
        required_features: wgpu::Features::empty(),
        required_limits: adapter.limits(),
        ..Default::default()
    }))
    .expect("device");
    let ctx = GpuContext::from_device(device, queue, adapter.get_info())
        .expect("a device with the adapter's limits is accepted");
    assert!(!ctx.supports_precision(Precision::WatertightF64));
    assert!(ctx.supports_precision(Precision::MollerTrumboreF32));
    let tris = triangles("builtin:icosphere:1");
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all()).unwrap();
    let rays = edge_rays(&tris, centre(&tris));
    let opts = TraceOptions::closest(Traversal::Stackless);
    let err = gpu
        .trace(&rays, &opts.with_precision(Precision::WatertightF64))
        .expect_err("f64 refused");
    let msg = err.to_string();
    assert!(
        matches!(err, GpuError::PrecisionUnsupported { .. }) && msg.contains("SHADER_F64"),
        "{msg}"
    );
    let ok = gpu
        .trace(&rays, &opts.with_precision(Precision::MollerTrumboreF32))
        .expect("f32 runs");
    assert_eq!(ok.hits.len(), rays.len());
}
