//! Emissive triangles light their front only (the side their corners wind about, the side
//! light sampling counts): the Cornell box's light, just below the ceiling and facing
//! down, seen from below is its emission; seen from the gap above it, it is dark.

use bvhtrace_core::{BuildOptions, Traversal};
use bvhtrace_path::{Accumulation, CpuPathTracer, Lighting, PathParams, PathScene};
use bvhtrace_scene::{Camera, SceneBvh};
use glam::Vec3;

/// The mean luminance of the Cornell box's light seen from `eye` toward `target`
/// (no sky, no sun: the scene's own light alone), 4 samples on the CPU twin.
fn light_seen(eye: Vec3, target: Vec3) -> f64 {
    let scene = bvhtrace_scene::load("builtin:cornell").expect("cornell");
    let SceneBvh::Flat { tris, bvh } = scene
        .tracing_bvh(&BuildOptions::default(), true)
        .expect("build")
    else {
        panic!("flattened");
    };
    let shading = PathScene::new(&scene, &tris).expect("shading");
    let camera = Camera {
        eye,
        target,
        fov_y_deg: 10.0,
    };
    let dark = Lighting {
        sun: Vec3::ZERO,
        env: Vec3::ZERO,
        ..Lighting::default()
    };
    let params = PathParams::new(&camera, (8, 8), &dark, 4, &shading);
    let twin = CpuPathTracer::new(&bvh, &tris, &shading, Traversal::FullStack).expect("twin");
    let mut sums = Accumulation::default();
    for sample in 0..4 {
        twin.add_sample(&PathParams { sample, ..params }, &mut sums);
    }
    bvhtrace_path::mean_luminance(&sums)
}

#[test]
fn an_emissive_triangle_lights_its_front_only() {
    // The light: y = 1.98, 0.5 wide, facing -Y; the ceiling at y = 2.
    let front = light_seen(Vec3::new(0.0, 1.0, 0.0), Vec3::new(0.0, 1.98, 0.0));
    let back = light_seen(Vec3::new(0.0, 1.995, 0.0), Vec3::new(0.0, 1.0, 0.0));
    println!("the light from below: {front:.3}; from above: {back:.5}");
    assert!(front > 5.0, "the light's front is dim: {front}");
    assert!(back < 0.05, "the light's back glows: {back}");
}
