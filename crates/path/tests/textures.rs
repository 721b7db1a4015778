//! Textured materials: base colour, metallic-roughness and emissive textures read at each
//! hit (and at each light sample), on the device as on the twin, bit for bit; the
//! textures change the image.

mod support;

use bvhtrace_core::{BuildOptions, Traversal};
use bvhtrace_gpu::GpuContext;
use bvhtrace_path::{Accumulation, CpuPathTracer, GpuPathTracer, Lighting, PathParams, PathScene};
use bvhtrace_scene::{Scene, SceneBvh};
use glam::Vec3;

/// The Cornell box with a texture in each slot (`builtin:cornell-textured`).
fn textured_cornell() -> Scene {
    bvhtrace_scene::load("builtin:cornell-textured").expect("cornell-textured")
}

fn render(
    ctx: Option<&GpuContext>,
    scene: &Scene,
    walk: Traversal,
    samples: u32,
) -> (Accumulation, Option<Accumulation>) {
    let traced = scene
        .tracing_bvh(&BuildOptions::default(), true)
        .expect("build");
    let SceneBvh::Flat { tris, mut bvh } = traced else {
        panic!("flattened");
    };
    if walk.is_wide() {
        bvh.build_wide();
    }
    let shading = PathScene::new(scene, &tris).expect("shading");
    let camera = scene.camera_or_frame(4.0 / 3.0);
    let params = PathParams::new(&camera, (48, 36), &Lighting::default(), 6, &shading);
    let twin = CpuPathTracer::new(&bvh, &tris, &shading, walk).expect("twin");
    let mut sums = Accumulation::default();
    for sample in 0..samples {
        twin.add_sample(&PathParams { sample, ..params }, &mut sums);
    }
    let device = ctx.map(|ctx| {
        let mut gpu = GpuPathTracer::new(ctx, &bvh, &shading, walk).expect("tracer");
        gpu.restart(params);
        gpu.add_samples(samples).expect("samples");
        let (device, stats) = gpu.read().expect("read");
        assert_eq!((stats.incomplete, stats.not_finite), (0, 0));
        device
    });
    (sums, device)
}

#[test]
fn textures_shade_on_the_device_as_on_the_twin() {
    let ctx = support::context("textures on the device");
    let scene = textured_cornell();
    let shading =
        PathScene::new(&scene, &scene.flattened_triangles().expect("tris")).expect("shading");
    assert_eq!(shading.materials[0].base_tex, 0);
    assert_eq!(shading.materials[3].emissive_tex, 2);
    for walk in [Traversal::Stackless, Traversal::Wide] {
        let (twin, device) = render(ctx.as_ref(), &scene, walk, 3);
        assert_eq!(twin.not_finite_pixels(), 0);
        if let Some(device) = device {
            let differ = (device.sums.iter().zip(&twin.sums))
                .filter(|(a, b)| a.map(f32::to_bits) != b.map(f32::to_bits))
                .count();
            println!(
                "textured Cornell, {}: {differ} of {} pixels differ",
                walk.name(),
                twin.sums.len()
            );
            assert_eq!(differ, 0, "{}: pixels differ from the twin", walk.name());
        }
    }
    // The textures matter: the plain box's image is another.
    let plain = bvhtrace_scene::load("builtin:cornell").expect("cornell");
    let (a, _) = render(None, &scene, Traversal::FullStack, 2);
    let (b, _) = render(None, &plain, Traversal::FullStack, 2);
    let changed = (a.linear().iter().zip(b.linear().iter()))
        .filter(|(x, y)| (Vec3::from(**x) - Vec3::from(**y)).abs().max_element() > 0.05)
        .count();
    assert!(
        changed > a.sums.len() / 4,
        "{changed} pixels changed by the textures"
    );
}
