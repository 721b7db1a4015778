//! Never a NaN pixel: every scene of the repository and a hostile one (NaN and
//! out-of-range factors, infinite and huge emission, zero-area and sliver triangles, an
//! emissive triangle of no area, the camera inside a closed block) path traced on the CPU
//! twin, and the hostile one on the device too: no pixel is NaN or infinite, no sample was
//! dropped as not finite.

mod support;

use bvhtrace_core::{BuildOptions, Traversal};
use bvhtrace_path::{Accumulation, CpuPathTracer, Lighting, PathParams, PathScene, PathStats};
use bvhtrace_scene::{Camera, Material, Mesh, Scene, SceneBvh};
use glam::{Vec3, Vec4};

/// `scene` path traced at 24x18, 2 samples, by the twin walking `walk`: the sums and the
/// counts.
fn twin(
    scene: &Scene,
    camera: &Camera,
    lighting: &Lighting,
    walk: Traversal,
) -> (Accumulation, PathStats) {
    let traced = scene
        .tracing_bvh(&BuildOptions::default(), true)
        .expect("build");
    let SceneBvh::Flat { tris, bvh } = traced else {
        panic!("flattened");
    };
    let shading = PathScene::new(scene, &tris).expect("shading");
    let params = PathParams::new(camera, (24, 18), lighting, 8, &shading);
    let cpu = CpuPathTracer::new(&bvh, &tris, &shading, walk).expect("twin");
    let mut sums = Accumulation::default();
    let mut stats = PathStats::default();
    for sample in 0..2 {
        stats = stats + cpu.add_sample(&PathParams { sample, ..params }, &mut sums);
    }
    (sums, stats)
}

fn lit() -> Lighting {
    Lighting {
        sun_dir: Vec3::new(0.2, 1.0, 0.4),
        sun: Vec3::splat(4.0),
        env: Vec3::splat(0.6),
    }
}

/// A scene whose inputs try to make NaN.
fn hostile() -> Scene {
    let mut scene = bvhtrace_scene::load("builtin:degenerate").expect("degenerate");
    let nan = f32::NAN;
    let bad = |name: &str, c: Vec4, metallic: f32, roughness: f32, emissive: Vec3| Material {
        metallic,
        roughness,
        ..Material::opaque(name, c).with_emissive(emissive)
    };
    scene.materials = vec![
        bad("nan", Vec4::splat(nan), nan, nan, Vec3::splat(nan)),
        bad(
            "inf",
            Vec4::splat(f32::INFINITY),
            -3.0,
            0.0,
            Vec3::splat(f32::INFINITY),
        ),
        bad("huge", Vec4::splat(1e30), 2.0, -1.0, Vec3::splat(1e30)),
        bad("mirror", Vec4::ONE, 1.0, 0.0, Vec3::ZERO),
    ];
    // A zero-area emissive triangle, and every triangle given one of the materials.
    let mesh: &mut Mesh = &mut scene.meshes[0];
    let p = mesh.positions[0];
    let base = mesh.positions.len() as u32;
    mesh.positions.extend([p, p, p]);
    if !mesh.normals.is_empty() {
        mesh.normals.extend([Vec3::Y; 3]);
    }
    if !mesh.texcoords.is_empty() {
        mesh.texcoords.extend([glam::Vec2::ZERO; 3]);
    }
    if !mesh.colors.is_empty() {
        mesh.colors.extend([Vec4::ONE; 3]);
    }
    mesh.indices.push([base, base + 1, base + 2]);
    mesh.materials = (0..mesh.indices.len() as u32).map(|i| i % 4).collect();
    scene.attributes.materials = true;
    scene
}

#[test]
fn no_scene_makes_a_nan_pixel() {
    let mut specs: Vec<String> = ["builtin:cornell", "builtin:spheres", "builtin:icosphere:3"]
        .map(String::from)
        .to_vec();
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes");
    for e in std::fs::read_dir(dir).expect("scenes/").flatten() {
        let path = e.path();
        if matches!(
            path.extension().and_then(|x| x.to_str()),
            Some("gltf" | "glb")
        ) {
            specs.push(path.to_string_lossy().into_owned());
        }
    }
    let mut scenes: Vec<(String, Scene)> = specs
        .iter()
        .map(|s| {
            (
                s.clone(),
                bvhtrace_scene::load(s).unwrap_or_else(|e| panic!("{e}")),
            )
        })
        .collect();
    scenes.push(("hostile".into(), hostile()));
    assert!(scenes.len() >= 9, "{} scenes", scenes.len());
    for (name, scene) in &scenes {
        let camera = scene.camera_or_frame(24.0 / 18.0);
        let (sums, stats) = twin(scene, &camera, &lit(), Traversal::FullStack);
        println!("{name}: {stats:?}");
        assert_eq!(sums.not_finite_pixels(), 0, "{name}");
        assert_eq!(stats.not_finite, 0, "{name}: samples dropped");
        assert!(bvhtrace_path::mean_luminance(&sums) > 0.0, "{name}: black");
    }
    // The camera inside the Cornell box's closed tall block, the sun outside.
    let cornell = &scenes[0].1;
    let inside = Camera {
        eye: Vec3::new(-0.35, 0.6, -0.3),
        target: Vec3::new(0.0, 0.6, 1.0),
        fov_y_deg: 60.0,
    };
    let (sums, stats) = twin(cornell, &inside, &lit(), Traversal::FullStack);
    assert_eq!((sums.not_finite_pixels(), stats.not_finite), (0, 0));
}

#[test]
fn the_device_makes_no_nan_pixel_from_the_hostile_scene_and_agrees_with_the_twin() {
    let Some(ctx) = support::context("the hostile scene on the device") else {
        return;
    };
    let scene = hostile();
    let traced = scene
        .tracing_bvh(&BuildOptions::default(), true)
        .expect("build");
    let SceneBvh::Flat { tris, bvh } = traced else {
        panic!("flattened");
    };
    let shading = PathScene::new(&scene, &tris).expect("shading");
    let camera = scene.camera_or_frame(24.0 / 18.0);
    let params = PathParams::new(&camera, (24, 18), &lit(), 8, &shading);
    let mut gpu = bvhtrace_path::GpuPathTracer::new(&ctx, &bvh, &shading, Traversal::Stackless)
        .expect("tracer");
    gpu.restart(params);
    gpu.add_samples(2).expect("samples");
    let (device, stats) = gpu.read().expect("read");
    assert_eq!(device.not_finite_pixels(), 0);
    assert_eq!((stats.not_finite, stats.incomplete), (0, 0));
    // The same walk: among coincident duplicates, which one is the closest hit is the
    // walk's order.
    let (sums, _) = twin(&scene, &camera, &lit(), Traversal::Stackless);
    let differ = (device.sums.iter().zip(&sums.sums))
        .filter(|(a, b)| a.map(f32::to_bits) != b.map(f32::to_bits))
        .count();
    assert_eq!(differ, 0, "pixels differ from the twin");
}
