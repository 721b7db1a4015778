//! The device's path tracer against its CPU twin: the same paths, summed to the same bits
//! on a device that rounds as IEEE 754 says (lavapipe), over every walk, with the sun, the
//! sky and the emissive triangles all lighting; no pixel is NaN.

mod support;

use bvhtrace_core::{BuildOptions, Traversal};
use bvhtrace_gpu::{AdapterChoice, GpuContext, GpuError};
use bvhtrace_path::{
    Accumulation, CpuPathTracer, Environment, GpuPathTracer, Lighting, PathKernel, PathParams,
    PathScene, PathStats, PathWalk,
};
use glam::Vec3;

struct Case {
    spec: &'static str,
    size: (u32, u32),
    samples: u32,
    lighting: Lighting,
    /// An equirectangular `.hdr` the sky comes from (`None`: the constant sky).
    environment: Option<&'static str>,
}

/// The scene of `case`, flattened with its masks, its shading data and parameters.
fn setup(
    case: &Case,
    wide: bool,
) -> (
    Vec<bvhtrace_core::Triangle>,
    bvhtrace_core::FlatBvh,
    PathScene,
    PathParams,
) {
    let scene = bvhtrace_scene::load(case.spec).unwrap_or_else(|e| panic!("{e}"));
    // Flattened, with the scene's alpha masks on the tree.
    let traced = scene
        .tracing_bvh(&BuildOptions::default(), true)
        .expect("build");
    let bvhtrace_scene::SceneBvh::Flat { tris, mut bvh } = traced else {
        panic!("flattened");
    };
    if wide {
        bvh.build_wide();
    }
    let mut shading = PathScene::new(&scene, &tris).expect("shading");
    if let Some(path) = case.environment {
        let map = Environment::load(std::path::Path::new(path), 64).expect("the sky");
        shading.set_environment(Some(map));
        assert!(shading.environment.is_some(), "{path}: a black map");
    }
    let camera = scene.camera_or_frame(case.size.0 as f32 / case.size.1 as f32);
    let params = PathParams::new(&camera, case.size, &case.lighting, 6, &shading);
    (tris, bvh, shading, params)
}

/// The device's sums and counts for `case` walked by `walk`.
fn both_device(
    ctx: &GpuContext,
    case: &Case,
    walk: PathWalk,
) -> (Accumulation, PathStats, PathParams) {
    let (_, bvh, shading, params) = setup(case, false);
    device_sums(ctx, case, (&bvh, &shading), params, (walk, None))
}

/// The device's sums for `case`, walked by `walk`, in waves of at most `waves` paths
/// (`None`: the single kernel).
fn device_sums(
    ctx: &GpuContext,
    case: &Case,
    (bvh, shading): (&bvhtrace_core::FlatBvh, &PathScene),
    params: PathParams,
    (walk, waves): (PathWalk, Option<u32>),
) -> (Accumulation, PathStats, PathParams) {
    let kernel = match waves {
        Some(_) => PathKernel::Wavefront,
        None => PathKernel::Megakernel,
    };
    let mut gpu = GpuPathTracer::with_kernel(ctx, bvh, shading, walk, kernel).expect("tracer");
    assert_eq!(gpu.kernel(), kernel);
    if let Some(n) = waves {
        gpu.set_max_wave_paths(n);
    }
    gpu.restart(params);
    gpu.add_samples(case.samples).expect("samples");
    let (device, stats) = gpu.read().expect("read");
    assert_eq!(stats.incomplete, 0, "{}: rays given up", case.spec);
    assert_eq!(stats.not_finite, 0, "{}: samples not finite", case.spec);
    (device, stats, params)
}

/// The device's sums and the twin's, for `walk`, and the pixels that differ.
fn both(ctx: &GpuContext, case: &Case, walk: PathWalk) -> (Accumulation, Accumulation, usize) {
    both_in(ctx, case, (walk, None))
}

/// [`both`] in waves of at most `waves` paths (`None`: the single kernel).
fn both_in(
    ctx: &GpuContext,
    case: &Case,
    (walk, waves): (PathWalk, Option<u32>),
) -> (Accumulation, Accumulation, usize) {
    let wide = matches!(walk, PathWalk::Walk(t) if t.is_wide());
    let (tris, bvh, shading, params) = setup(case, wide);
    let (device, stats, _) = device_sums(ctx, case, (&bvh, &shading), params, (walk, waves));

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
            environment: None,
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
            environment: None,
        },
        // The sky from an environment map (its sun among it), sampled by luminance.
        Case {
            spec: "../../scenes/foliage.gltf",
            size: (40, 30),
            samples: 2,
            lighting: Lighting {
                sun: Vec3::ZERO,
                env: Vec3::ONE,
                ..Lighting::default()
            },
            environment: Some("../../scenes/sky.hdr"),
        },
    ]
}

#[test]
fn the_device_traces_the_twins_paths_bit_for_bit_on_every_walk() {
    let Some(ctx) = support::context("path tracer twin") else {
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

/// The wavefront kernel follows the same paths as the single kernel and the twin, to the
/// same bits: in runs of at most 500 paths (twelve rows of the 40 x 30 frame: three runs,
/// the last one short),
/// on a stack walk and the stackless one.
#[test]
fn the_waves_trace_the_twins_paths_bit_for_bit() {
    let Some(ctx) = support::context("path tracer waves") else {
        return;
    };
    for case in cases() {
        for t in [Traversal::FullStack, Traversal::Stackless] {
            let (device, twin, differ) = both_in(&ctx, &case, (PathWalk::Walk(t), Some(500)));
            assert_eq!(device.samples(), case.samples);
            assert!(bvhtrace_path::mean_luminance(&twin) > 0.01, "{}", case.spec);
            assert_eq!(
                differ,
                0,
                "{} {}: waves differ from the twin",
                case.spec,
                t.name()
            );
        }
    }
}

/// The rule for the device's ray queries (docs/design.md, "The path tracer"): their hits
/// are the driver's, so the paths are ours wherever the hits agree; at 8 samples over the
/// Cornell box and the alpha-masked foliage, the mean radiance is within 0.1% of our
/// walk's, the RMSE under 1% of the mean, and most pixels are the same bits.
#[test]
fn ray_queries_trace_the_same_image_under_the_rule() {
    let required = std::env::var("BVHTRACE_REQUIRE_RAY_QUERIES").is_ok_and(|v| v == "1");
    let options = bvhtrace_gpu::ContextOptions {
        ray_queries: true,
        ..Default::default()
    };
    let ctx = match GpuContext::new_with(AdapterChoice::Auto, &options) {
        Ok(ctx) if ctx.has_ray_queries() => ctx,
        Ok(_) | Err(GpuError::NoAdapter { .. }) if !required => {
            eprintln!("SKIP ray-query path tracing: no device with ray queries");
            return;
        }
        Ok(_) => panic!("no ray queries with BVHTRACE_REQUIRE_RAY_QUERIES=1"),
        Err(e) => panic!("cannot open a GPU: {e}"),
    };
    for mut case in cases() {
        case.samples = 8;
        let (walk, _, _) = both_device(&ctx, &case, PathWalk::Walk(Traversal::Stackless));
        let (rq, _, _) = both_device(&ctx, &case, PathWalk::RayQueries);
        let (a, b) = (walk.linear(), rq.linear());
        let n = (a.len() * 3) as f64;
        let mean = |v: &[[f32; 3]]| v.iter().flatten().map(|&x| f64::from(x)).sum::<f64>() / n;
        let (ma, mb) = (mean(&a), mean(&b));
        let se: f64 = (a.iter().flatten().zip(b.iter().flatten()))
            .map(|(x, y)| f64::from(x - y).powi(2))
            .sum();
        let rmse = (se / n).sqrt();
        let same = a.iter().zip(&b).filter(|(x, y)| x == y).count();
        println!(
            "{}: ray queries' mean {mb:.5} against the walk's {ma:.5}, RMSE {rmse:.5}, {same} of {} pixels the same bits",
            case.spec,
            a.len()
        );
        assert!(
            (mb - ma).abs() <= 1e-3 * ma,
            "{}: means {ma} and {mb}",
            case.spec
        );
        assert!(rmse <= 1e-2 * ma, "{}: RMSE {rmse}", case.spec);
        assert!(same * 4 >= a.len(), "{}: {same} pixels the same", case.spec);
    }
}

/// Two levels (instances over meshes): the kernel's surfaces are the library's
/// `bvh_hit_surface` through the instances, the twin's `hits::instance_surface`; the
/// instances number the flattened scene's triangles, so the shading data is the same.
#[test]
fn two_levels_trace_the_twins_paths_bit_for_bit() {
    let Some(ctx) = support::context("path tracer over two levels") else {
        return;
    };
    for spec in ["builtin:spheres", "../../scenes/animated.gltf"] {
        let scene = bvhtrace_scene::load(spec).unwrap_or_else(|e| panic!("{e}"));
        let traced = scene
            .tracing_bvh(&BuildOptions::default(), false)
            .expect("build");
        let bvhtrace_scene::SceneBvh::Instanced(mut ib) = traced else {
            panic!("{spec}: not two levels");
        };
        let tris = scene.flattened_triangles().expect("triangles");
        for (p, t) in tris.iter().enumerate() {
            let w = ib.world_triangle(p as u32).expect("the instances hold it");
            let close =
                (0..3).all(|k| w[k].abs_diff_eq(t[k], 1e-4 * (1.0 + t[k].abs().max_element())));
            assert!(close, "{spec}: primitive {p} is not the flattened scene's");
        }
        let shading = PathScene::new(&scene, &tris).expect("shading");
        let camera = scene.camera_or_frame(4.0 / 3.0);
        let lighting = Lighting {
            sun_dir: Vec3::new(0.3, 1.0, 0.5),
            sun: Vec3::splat(3.0),
            env: Vec3::splat(0.4),
        };
        let params = PathParams::new(&camera, (40, 30), &lighting, 6, &shading);
        for walk in [Traversal::Stackless, Traversal::Wide] {
            if walk.is_wide() {
                ib.build_wide();
            }
            let mut gpu = GpuPathTracer::new(&ctx, ib.bvh(), &shading, walk).expect("tracer");
            gpu.restart(params);
            gpu.add_samples(2).expect("samples");
            let (device, stats) = gpu.read().expect("read");
            let twin = CpuPathTracer::instanced(&ib, &shading, walk).expect("twin");
            let mut sums = Accumulation::default();
            let mut twin_stats = PathStats::default();
            for s in 0..2 {
                twin_stats = twin_stats
                    + twin.add_sample(
                        &PathParams {
                            sample: s,
                            ..params
                        },
                        &mut sums,
                    );
            }
            let differ = (device.sums.iter().zip(&sums.sums))
                .filter(|(a, b)| a.map(f32::to_bits) != b.map(f32::to_bits))
                .count();
            println!(
                "{spec} in two levels, {}: {differ} of {} pixels differ",
                walk.name(),
                sums.sums.len()
            );
            assert_eq!(
                differ,
                0,
                "{spec} {}: pixels differ from the twin",
                walk.name()
            );
            assert_eq!(stats, twin_stats, "{spec}: the counts");
            assert!(bvhtrace_path::mean_luminance(&sums) > 0.01);
        }
    }
}

/// The tree in buffers split over bindings (a context whose bindings hold half the
/// Cornell box's nodes): the traversal library reads each array through its pages, and
/// the device still follows the twin's paths to the bit.
#[test]
fn a_tree_split_over_bindings_traces_the_twins_paths() {
    use bvhtrace_gpu::{BvhStorage, ContextOptions, DriverTuning};
    let Some(plain) = support::context("path tracer in pages") else {
        return;
    };
    let case = &cases()[0];
    let (_, bvh, _, _) = setup(case, false);
    let options = ContextOptions {
        tuning: Some(DriverTuning {
            storage: BvhStorage::Buffers,
            ..*plain.tuning()
        }),
        max_binding_bytes: Some(two_pages(&bvh)),
        ..ContextOptions::default()
    };
    let ctx = GpuContext::new_with(AdapterChoice::Auto, &options).expect("the same adapter");
    // The stackless walk reads the most arrays: nodes, escape links and triangles.
    let t = Traversal::Stackless;
    let up = bvhtrace_gpu::GpuBvh::upload(&ctx, &bvh, &Default::default()).expect("upload");
    assert!(!up.library_shape(t).pages.is_one(), "{:?}", up.tree());
    let (device, _, differ) = both(&ctx, case, PathWalk::Walk(t));
    assert_eq!(device.samples(), case.samples);
    assert_eq!(differ, 0, "{} {} in pages", case.spec, t.name());
}

/// A binding size that splits `bvh`'s nodes (and escape links) into two pages: a split
/// kernel compiles several times slower than a whole one on lavapipe, the more so the
/// more pages.
fn two_pages(bvh: &bvhtrace_core::FlatBvh) -> u64 {
    (std::mem::size_of_val(bvh.nodes()) as u64).next_power_of_two() / 2
}
