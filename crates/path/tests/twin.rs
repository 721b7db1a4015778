//! The device's path tracer against its CPU twin: the same paths, summed to the same bits
//! on a device that rounds as IEEE 754 says (lavapipe), over every walk, with the sun, the
//! sky and the emissive triangles all lighting; no pixel is NaN.

use bvhtrace_core::{BuildOptions, Traversal};
use bvhtrace_gpu::{AdapterChoice, GpuContext, GpuError};
use bvhtrace_path::{
    Accumulation, CpuPathTracer, GpuPathTracer, Lighting, PathParams, PathScene, PathStats,
    PathWalk,
};
use glam::Vec3;

fn context(what: &str) -> Option<GpuContext> {
    match GpuContext::new(AdapterChoice::Auto) {
        Ok(ctx) => Some(ctx),
        Err(e @ GpuError::NoAdapter { .. }) => {
            eprintln!("SKIP {what}: {e}");
            None
        }
        Err(e) => panic!("cannot open a GPU: {e}"),
    }
}

struct Case {
    spec: &'static str,
    size: (u32, u32),
    samples: u32,
    lighting: Lighting,
}

/// The device's sums and the twin's, for `walk`, and the pixels that differ.
fn both(ctx: &GpuContext, case: &Case, walk: PathWalk) -> (Accumulation, Accumulation, usize) {
    let scene = bvhtrace_scene::load(case.spec).unwrap_or_else(|e| panic!("{e}"));
    // Flattened, with the scene's alpha masks on the tree.
    let traced = scene
        .tracing_bvh(&BuildOptions::default(), true)
        .expect("build");
    let bvhtrace_scene::SceneBvh::Flat { tris, mut bvh } = traced else {
        panic!("flattened");
    };
    if matches!(walk, PathWalk::Walk(t) if t.is_wide()) {
        bvh.build_wide();
    }
    let shading = PathScene::new(&scene, &tris).expect("shading");
    let camera = scene.camera_or_frame(case.size.0 as f32 / case.size.1 as f32);
    let params = PathParams::new(&camera, case.size, &case.lighting, 6, &shading);

    let mut gpu = GpuPathTracer::with_walk(ctx, &bvh, &shading, walk).expect("tracer");
    gpu.restart(params);
    gpu.add_samples(case.samples).expect("samples");
    let (device, stats) = gpu.read().expect("read");
    assert_eq!(stats.incomplete, 0, "{}: rays given up", case.spec);
    assert_eq!(stats.not_finite, 0, "{}: samples not finite", case.spec);

    let traversal = match walk {
        PathWalk::Walk(t) => t,
        PathWalk::RayQueries => Traversal::FullStack,
    };
    let cpu = CpuPathTracer::new(&bvh, &tris, &shading, traversal).expect("twin");
    let mut twin = Accumulation::default();
    let mut twin_stats = PathStats::default();
    for s in 0..case.samples {
        let p = PathParams {
            sample: s,
            ..params
        };
        twin_stats = twin_stats + cpu.add_sample(&p, &mut twin);
    }
    // The same rays, counted on both sides.
    assert_eq!(twin_stats, stats, "{}: the twin's counts", case.spec);
    assert!(stats.rays > u64::from(case.samples) * twin.sums.len() as u64);
    let differ = (device.sums.iter().zip(&twin.sums))
        .filter(|(a, b)| a.map(f32::to_bits) != b.map(f32::to_bits))
        .count();
    (device, twin, differ)
}

fn cases() -> Vec<Case> {
    vec![
        // Lit by its ceiling light alone (a closed room: the sky does not reach in).
        Case {
            spec: "builtin:cornell",
            size: (40, 30),
            samples: 3,
            lighting: Lighting::default(),
        },
        // Sun and sky over alpha-masked leaves: shadow rays cut by the masks.
        Case {
            spec: "../../scenes/foliage.gltf",
            size: (40, 30),
            samples: 2,
            lighting: Lighting {
                sun_dir: Vec3::new(0.3, 1.0, 0.5),
                sun: Vec3::splat(3.0),
                env: Vec3::new(0.3, 0.4, 0.6),
            },
        },
    ]
}

#[test]
fn the_device_traces_the_twins_paths_bit_for_bit_on_every_walk() {
    let Some(ctx) = context("path tracer twin") else {
        return;
    };
    for case in cases() {
        for t in Traversal::all_with_short_stacks(&[4]) {
            let (device, twin, differ) = both(&ctx, &case, PathWalk::Walk(t));
            assert_eq!(device.samples(), case.samples);
            assert_eq!(device.not_finite_pixels(), 0, "{}", case.spec);
            let lum = bvhtrace_path::mean_luminance(&twin);
            assert!(lum > 0.01, "{}: a dark image ({lum})", case.spec);
            println!(
                "{} {}: {} pixels, {differ} differ from the twin; mean luminance {lum:.4}",
                case.spec,
                t.name(),
                device.sums.len()
            );
            assert_eq!(
                differ,
                0,
                "{} {}: pixels differ from the twin",
                case.spec,
                t.name()
            );
        }
    }
}
