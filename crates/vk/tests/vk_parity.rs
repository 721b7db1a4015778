//! The ash backend against the wgpu backend and the CPU twin, ray by ray and bit for bit
//! (hits and counters), on the scenes of `tests/gpu_parity.rs`; object lifetime and error
//! behaviour. Runs on lavapipe in CI; prints SKIP and passes only when there is no Vulkan
//! loader or device at all.

use bvhtrace_core::{
    BuildOptions, BuilderKind, FlatBvh, Query, Ray, Traversal, trace_batch_counted,
};
use bvhtrace_gpu::{AdapterChoice, BvhStorage, GpuBvh, GpuContext, UploadOptions};
use bvhtrace_scene::{Camera, shared_scenes_dir};
use bvhtrace_vk::{VkBvh, VkContext, VkError, VkOptions};
use glam::Vec3;

/// A context with validation on (when the layer is installed), or `None` (SKIP) when this
/// machine has no Vulkan at all.
fn context(test: &str) -> Option<VkContext> {
    match VkContext::with_options(&VkOptions {
        adapter: None,
        validation: true,
    }) {
        Ok(ctx) => {
            eprintln!(
                "ash: {:?}, validation {}",
                ctx.device_info(),
                ctx.validation_enabled()
            );
            Some(ctx)
        }
        Err(e @ (VkError::LoaderMissing(_) | VkError::NoDevice { .. })) => {
            eprintln!("SKIP {test}: {e}");
            None
        }
        Err(e) => panic!("cannot open a Vulkan device: {e}"),
    }
}

fn load(spec: &str) -> Option<(String, FlatBvh)> {
    let scene = match bvhtrace_scene::load(spec) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("SKIP scene {spec}: {e}");
            return None;
        }
    };
    let tris = scene
        .flatten()
        .triangles()
        .unwrap_or_else(|e| panic!("{spec}: {e}"));
    let bvh =
        FlatBvh::build(&tris, &BuildOptions::default()).unwrap_or_else(|e| panic!("{spec}: {e}"));
    Some((spec.to_string(), bvh))
}

/// The scenes of `tests/gpu_parity.rs`: shared meshes when present (a small one, the
/// bunny, the bunny at 1e-3 scale), the degenerate builtin, the Cornell box, and the
/// Cornell box at 1e-4 scale (a tiny-scale scene that is always there).
fn scenes() -> Vec<(String, FlatBvh)> {
    let mut out = Vec::new();
    match shared_scenes_dir().map(|d| d.join("glb")) {
        Some(dir) => {
            let p = |f: &str| dir.join(f).to_string_lossy().into_owned();
            out.extend(load(&p("suzanne_968.glb")));
            out.extend(load(&p("bunny_69k.glb")));
            out.extend(load(&format!("{}#scale=1e-3", p("bunny_69k.glb"))));
        }
        None => eprintln!("SKIP the shared .glb scenes: no shared/scenes folder found"),
    }
    out.extend(load("builtin:degenerate"));
    out.extend(load("builtin:cornell"));
    out.extend(load("builtin:cornell#scale=1e-4"));
    out
}

/// SplitMix64.
struct Rng(u64);

impl Rng {
    fn f32(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
    fn unit(&mut self) -> Vec3 {
        loop {
            let v = Vec3::new(self.f32(), self.f32(), self.f32()) * 2.0 - Vec3::ONE;
            if v.length_squared() > 1e-4 && v.length_squared() <= 1.0 {
                return v.normalize();
            }
        }
    }
}

/// 128x96 primary rays, random rays from inside the bounds (full and finite intervals),
/// axis-parallel rays with signed zeros, and invalid rays.
fn rays(bvh: &FlatBvh) -> Vec<Ray> {
    let b = bvh.bounds();
    let (lo, hi) = (b.min, b.max);
    let size = hi - lo;
    let mut rays = Camera::frame(lo, hi, 128.0 / 96.0).rays(128, 96);
    let mut rng = Rng(7);
    for i in 0..3072 {
        let o = lo + size * Vec3::new(rng.f32(), rng.f32(), rng.f32());
        let d = rng.unit();
        rays.push(if i % 3 == 0 {
            Ray::with_interval(o, d, 1e-4 * size.length(), size.length() * rng.f32())
        } else {
            Ray::new(o, d)
        });
    }
    for axis in 0..3 {
        for zero in [0.0f32, -0.0] {
            for i in 0..8 {
                let mut d = Vec3::splat(zero);
                d[axis] = if i % 2 == 0 { 1.0 } else { -1.0 };
                let mut o = lo + size * ((i as f32 + 0.5) / 8.0);
                o[axis] = if d[axis] > 0.0 {
                    lo[axis] - size[axis]
                } else {
                    hi[axis] + size[axis]
                };
                rays.push(Ray::new(o, d));
            }
        }
    }
    let eye = hi + size;
    let d = ((lo + hi) * 0.5 - eye).normalize();
    rays.extend([
        Ray::new(Vec3::new(f32::NAN, 0.0, 0.0), d),
        Ray::new(eye, Vec3::ZERO),
        Ray::with_interval(eye, d, 1.0, 0.5),
        Ray::with_interval(eye, d, f32::NEG_INFINITY, f32::INFINITY),
    ]);
    rays
}

/// Indices where two Pod slices differ bytewise.
fn differ<T: bytemuck::Pod>(a: &[T], b: &[T]) -> Vec<usize> {
    assert_eq!(a.len(), b.len());
    (0..a.len())
        .filter(|&i| bytemuck::bytes_of(&a[i]) != bytemuck::bytes_of(&b[i]))
        .collect()
}

#[test]
fn ash_equals_wgpu_and_cpu_bit_for_bit() {
    let Some(ctx) = context("ash parity") else {
        return;
    };
    let wgpu = GpuContext::new(AdapterChoice::Auto).expect("wgpu opens the same Vulkan device");
    let traversals = [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(4),
    ];
    let mut failures = Vec::new();
    let mut checked = 0;
    for (name, bvh) in scenes() {
        let rays = rays(&bvh);
        let vk = VkBvh::upload(&ctx, &bvh).expect("ash upload");
        let wg = GpuBvh::upload(
            &wgpu,
            &bvh,
            &UploadOptions::all().with_storage(BvhStorage::Buffers),
        )
        .expect("wgpu upload");
        eprintln!(
            "{name}: {} nodes, depth {}, {} rays",
            bvh.nodes.len(),
            bvh.depth,
            rays.len()
        );
        for traversal in traversals {
            for query in [Query::Closest, Query::Any] {
                let label = format!("{name} {traversal} {query:?}");
                let (cpu_hits, cpu_counters) = trace_batch_counted(&bvh, &rays, traversal, query);
                let counted = vk.trace(&rays, traversal, query, true).expect("ash trace");
                let plain = vk.trace(&rays, traversal, query, false).expect("ash trace");
                let w = wg
                    .trace_counted(&rays, traversal, query)
                    .expect("wgpu trace");
                let vc = counted.counters.as_deref().expect("counters asked for");
                let wc = w.counters.as_deref().expect("counters asked for");
                assert!(plain.counters.is_none());
                assert_eq!(counted.gpu_ns.is_some(), ctx.has_timestamps());
                let checks = [
                    ("hits vs cpu", differ(&counted.hits, &cpu_hits)),
                    ("uncounted hits vs cpu", differ(&plain.hits, &cpu_hits)),
                    ("hits vs wgpu", differ(&counted.hits, &w.hits)),
                    ("counters vs cpu", differ(vc, &cpu_counters)),
                    ("counters vs wgpu", differ(vc, wc)),
                ];
                for (what, bad) in checks {
                    if let Some(&i) = bad.first() {
                        failures.push(format!(
                            "{label}: {what}: {} rays differ; first {i}: ray {:?}, ash {:?} {:?}, \
                             wgpu {:?} {:?}, cpu {:?} {:?}",
                            bad.len(),
                            rays[i],
                            counted.hits[i],
                            vc[i],
                            w.hits[i],
                            wc[i],
                            cpu_hits[i],
                            cpu_counters[i]
                        ));
                    }
                }
                checked += 1;
            }
        }
    }
    assert!(
        checked >= 4 * 6,
        "too few configurations checked: {checked}"
    );
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
    let tris = vec![[
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ]];
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let rays = [
        Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z),
        Ray::new(Vec3::new(3.0, 0.0, 5.0), Vec3::NEG_Z),
    ];
    assert_eq!(first.validation_errors(), 0);
    drop(first);
    for i in 0..20 {
        let ctx = VkContext::with_options(&VkOptions {
            adapter: None,
            validation: true,
        })
        .unwrap_or_else(|e| panic!("iteration {i}: {e}"));
        let gpu = VkBvh::upload(&ctx, &bvh).unwrap_or_else(|e| panic!("iteration {i}: {e}"));
        let out = gpu
            .trace(&rays, Traversal::ShortStack(4), Query::Closest, i % 2 == 0)
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
}

#[test]
fn errors_are_errors_not_panics() {
    let Some(ctx) = context("errors") else { return };
    // An unknown adapter names itself and lists what there is.
    match VkContext::new(Some("no-such-gpu-xyz")) {
        Err(e @ VkError::AdapterNotFound { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains("no-such-gpu-xyz"), "{msg}");
            assert!(msg.contains(&ctx.device_info().name), "{msg}");
        }
        other => panic!("expected AdapterNotFound, got {other:?}"),
    }
    // The device's own name (any case) finds it.
    let name = ctx.device_info().name.to_uppercase();
    let again = VkContext::new(Some(&name)).expect("found by name");
    assert_eq!(again.device_info().name, ctx.device_info().name);

    // A tree deeper than the full-stack kernel's stack is refused for that traversal only.
    let tris: Vec<[Vec3; 3]> = (0..120)
        .map(|i| {
            let p = Vec3::new(2f32.powi(i - 60), 0.0, 0.0);
            [
                p + Vec3::new(0.0, -1.0, -1.0),
                p + Vec3::new(0.0, 1.0, -1.0),
                p + Vec3::new(0.0, 0.0, 1.0),
            ]
        })
        .collect();
    let deep = FlatBvh::build(
        &tris,
        &BuildOptions {
            builder: BuilderKind::Midpoint,
            max_depth: 1000,
            max_leaf_size: 1,
            ..Default::default()
        },
    )
    .expect("build");
    assert!(deep.depth > bvhtrace_gpu::FULL_STACK_SIZE);
    let gpu = VkBvh::upload(&ctx, &deep).expect("upload");
    let rays = [Ray::new(Vec3::new(-1.0, 0.1, 0.0), Vec3::X)];
    match gpu.trace(&rays, Traversal::FullStack, Query::Closest, false) {
        Err(e @ VkError::TooDeep { .. }) => assert!(e.to_string().contains("stackless")),
        other => panic!("expected TooDeep, got {other:?}"),
    }
    let out = gpu
        .trace(&rays, Traversal::Stackless, Query::Closest, true)
        .expect("stackless works on deep trees");
    let (cpu, cpu_counters) =
        trace_batch_counted(&deep, &rays, Traversal::Stackless, Query::Closest);
    assert_eq!(out.hits, cpu);
    assert_eq!(out.counters.as_deref(), Some(&cpu_counters[..]));
    // An empty batch is fine.
    let empty = gpu
        .trace(&[], Traversal::Stackless, Query::Any, false)
        .expect("empty batch");
    assert!(empty.hits.is_empty());
    assert_eq!(ctx.validation_errors(), 0);
}
