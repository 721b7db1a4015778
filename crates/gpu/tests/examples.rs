//! The examples run (on lavapipe in CI) and draw what they should: each example binary is
//! run on `builtin:cornell` at its default size, and its PNG is checked against an image
//! made on the CPU from `bvhtrace_core::trace_rays`.
//!
//! * `user_device`: byte for byte. The test recomputes the image with the example's own
//!   shading functions (both examples are compiled into this test as modules, for their
//!   functions and constants), from the CPU walk's hits, which the kernels reproduce bit
//!   for bit.
//! * `own_shader`: its shader makes its camera rays itself, in WGSL, so they may differ from
//!   `Camera::rays` in the last bit, and a ray grazing a triangle edge may then hit the
//!   neighbour. So each pixel is compared with the CPU's colour for the same pixel within
//!   2 levels per channel, and at most 0.5% of the pixels (edges) may differ more; the
//!   number of hit (non-background) pixels must match the CPU's hits within the same 0.5%.
//!
//! Without a Vulkan adapter the examples say so and the tests print SKIP. The example
//! binaries are built by `cargo test` (examples are built with the tests); when they are
//! missing (a filtered run such as `cargo test --test examples`), the test builds them.

// Both examples are compiled in below, each with its own copy of `examples/common`.
#![allow(clippy::duplicate_mod)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;

use bvhtrace_core::surface::{geometric_normal, hash};
use bvhtrace_core::{BuildOptions, FlatBvh, Query, TraceOptions, Traversal, trace_rays};
use bvhtrace_shade::palette;
use glam::Vec3;

#[path = "../examples/user_device.rs"]
#[allow(dead_code)]
mod user_device;

#[path = "../examples/own_shader.rs"]
#[allow(dead_code)]
mod own_shader;

const SCENE: &str = "builtin:cornell";

/// Serialises the build of missing examples between the tests of this file.
static BUILD: Mutex<()> = Mutex::new(());

/// The path of example `name` in this test's target directory: the test binary is
/// `target/<profile>/deps/examples-<hash>`, the examples `target/<profile>/examples/<name>`.
/// Builds the examples (same profile) when it is missing.
fn example(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    let deps = exe.parent().expect("deps folder");
    let profile_dir = deps.parent().expect("profile folder");
    let bin = profile_dir
        .join("examples")
        .join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    let _guard = BUILD.lock().unwrap_or_else(|e| e.into_inner());
    if !bin.exists() {
        // `target/debug` is the `dev` profile; any other folder is its profile's name.
        let profile = match profile_dir.file_name().and_then(|n| n.to_str()) {
            Some("debug") => "dev".to_string(),
            Some(p) => p.to_string(),
            None => panic!("unexpected test path {}", exe.display()),
        };
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| env!("CARGO").to_string());
        eprintln!(
            "{} is missing: building the examples ({profile})",
            bin.display()
        );
        let status = Command::new(cargo)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .args([
                "build",
                "-p",
                "bvhtrace-gpu",
                "--examples",
                "--profile",
                &profile,
            ])
            .status()
            .expect("running cargo");
        assert!(
            status.success() && bin.exists(),
            "could not build {}: run `cargo test -p bvhtrace-gpu{}`, which builds the examples",
            bin.display(),
            if profile == "release" {
                " --release"
            } else {
                ""
            }
        );
    }
    bin
}

/// Runs example `name` on [`SCENE`], writing `<name>.png` under the target's temporary
/// folder. Returns the image path and the example's output, or `None` (after printing
/// SKIP) when there is no Vulkan adapter.
fn run_example(name: &str) -> Option<(PathBuf, String)> {
    run_example_with(name, &[])
}

/// [`run_example`] with `extra` arguments (named in the image's file name).
fn run_example_with(name: &str, extra: &[&str]) -> Option<(PathBuf, String)> {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("examples");
    std::fs::create_dir_all(&dir).expect("temporary folder");
    let png = dir.join(format!("{name}{}.png", extra.concat()));
    let _ = std::fs::remove_file(&png);
    let out = Command::new(example(name))
        .arg(SCENE)
        .args(extra)
        .arg("-o")
        .arg(&png)
        .output()
        .expect("running the example");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() {
        if stderr.contains("no Vulkan adapter") {
            eprintln!("SKIP {name}: {stderr}");
            return None;
        }
        panic!("{name} failed ({}):\n{stdout}\n{stderr}", out.status);
    }
    assert!(png.exists(), "{name} wrote no {}:\n{stdout}", png.display());
    Some((png, stdout))
}

/// The PNG as RGB, checked for its size and for holding more than one colour.
fn load(png: &Path, width: u32, height: u32) -> image::RgbImage {
    let img = image::open(png).expect("a PNG").to_rgb8();
    assert_eq!(img.dimensions(), (width, height), "{}", png.display());
    let first = img.get_pixel(0, 0);
    assert!(
        img.pixels().any(|p| p != first),
        "{} is a single colour",
        png.display()
    );
    img
}

#[test]
fn user_device_draws_the_cpu_image_with_shadows() {
    let Some((png, stdout)) = run_example("user_device") else {
        return;
    };
    let (w, h) = (user_device::WIDTH, user_device::HEIGHT);
    let img = load(&png, w, h);

    // The example's steps, with the CPU walk in place of the GPU.
    let scene = bvhtrace_scene::load(SCENE).expect("scene");
    let tris = scene.flatten().triangles().expect("triangles");
    let albedo = user_device::albedos(&scene);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let camera = scene.camera_or_frame(w as f32 / h as f32);
    let rays = camera.rays(w, h);
    let hits = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::Stackless)).hits;
    let light = bvhtrace_shade::point_light(&camera);
    let (shadow, owners) = user_device::shadow_rays(&tris, &rays, &hits, light);
    let any = TraceOptions::new(Traversal::Stackless, Query::Any);
    let blocked = trace_rays(&bvh, &shadow, &any).hits;
    let mut in_shadow = vec![false; rays.len()];
    for (&pixel, b) in owners.iter().zip(&blocked) {
        in_shadow[pixel] = b.is_hit();
    }
    let expected = user_device::shade(&tris, &albedo, &rays, &hits, light, &in_shadow);

    // The scene has a background, lit surfaces and shadows on surfaces facing the light.
    let hit_count = hits.iter().filter(|h| h.is_hit()).count();
    let shadowed = in_shadow.iter().filter(|&&s| s).count();
    assert!(hit_count > 0 && hit_count < rays.len(), "{hit_count} hits");
    assert!(shadowed > 100, "{shadowed} pixels in shadow");
    assert!(shadow.len() - shadowed > 100, "lit pixels");
    assert!(
        stdout.contains(&format!("{hit_count} hits"))
            && stdout.contains(&format!("{shadowed} in shadow")),
        "the example counted other hits than the CPU ({hit_count} hits, {shadowed} in shadow):\n{stdout}"
    );

    let differing = img
        .pixels()
        .zip(expected.pixels())
        .filter(|(a, b)| a != b)
        .count();
    assert_eq!(
        differing,
        0,
        "{differing} pixels of {} differ from the CPU image",
        png.display()
    );
}

/// The colour `own_shader`'s WGSL writes for a pixel whose ray `dir` hits triangle `prim`
/// with unit normal `n`: the triangle's hash colour, shaded by `|n . dir|`.
fn own_shader_colour(prim: u32, n: Vec3, dir: Vec3) -> [u8; 3] {
    let h = hash(prim);
    let bytes = Vec3::new(
        (h & 255) as f32,
        ((h >> 8) & 255) as f32,
        ((h >> 16) & 255) as f32,
    );
    let c = (Vec3::splat(0.35) + 0.65 * bytes / 255.0) * (0.3 + 0.7 * n.dot(dir).abs());
    c.to_array().map(palette::to8)
}

#[test]
fn own_shader_draws_the_cpu_hits() {
    check_own_shader(&[]);
}

/// The same shader over a two-level upload: the library composed for it walks the
/// instances, and the image is the one-mesh CPU image (the primitive ids number the
/// triangles alike).
#[test]
fn own_shader_draws_the_cpu_hits_on_two_levels() {
    check_own_shader(&["--two-level"]);
}

/// Runs `own_shader` with `extra` and compares its image with the CPU's.
fn check_own_shader(extra: &[&str]) {
    let Some((png, stdout)) = run_example_with("own_shader", extra) else {
        return;
    };
    check_own_shader_image(&png, &stdout, extra.contains(&"--two-level"));
}

/// The Mesa 22 lavapipe ICD, which has no ray queries: `$BVHTRACE_MESA22_ICD`, else the
/// system's when the tests run on another driver through `VK_ICD_FILENAMES`.
fn mesa22_icd() -> Option<PathBuf> {
    let named = std::env::var_os("BVHTRACE_MESA22_ICD").map(PathBuf::from);
    let system = std::env::var_os("VK_ICD_FILENAMES")
        .map(|_| PathBuf::from("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json"));
    named.or(system).filter(|p| p.exists())
}

/// Write your shader once: `own_shader --ray-queries` on a device with ray queries (Mesa
/// 25's lavapipe) composes its library over them, on one without (Mesa 22's, through
/// [`mesa22_icd`]) over our walk; both images are the CPU's under the same tolerance, and
/// each other's.
#[test]
fn own_shader_draws_the_same_image_with_ray_queries_and_with_our_walk() {
    let required = std::env::var("BVHTRACE_REQUIRE_RAY_QUERIES").is_ok_and(|v| v == "1");
    for level in [&[][..], &["--two-level"][..]] {
        let args: Vec<&str> = [&["--ray-queries"][..], level].concat();
        let Some((rq_png, rq_out)) = run_example_with("own_shader", &args) else {
            return;
        };
        if !rq_out.contains("the device's ray queries") {
            assert!(
                !required,
                "no ray queries with BVHTRACE_REQUIRE_RAY_QUERIES=1:\n{rq_out}"
            );
            eprintln!("SKIP own_shader on ray queries: the device has none:\n{rq_out}");
            return;
        }
        check_own_shader_image(&rq_png, &rq_out, !level.is_empty());
        let Some(icd) = mesa22_icd() else {
            assert!(
                !required,
                "no Mesa 22 ICD to compare with (BVHTRACE_MESA22_ICD)"
            );
            eprintln!("SKIP own_shader on Mesa 22: no ICD found (BVHTRACE_MESA22_ICD)");
            return;
        };
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("examples");
        let walk_png = dir.join(format!("own_shader-mesa22{}.png", level.concat()));
        let out = Command::new(example("own_shader"))
            .arg(SCENE)
            .args(&args)
            .arg("-o")
            .arg(&walk_png)
            .env("VK_ICD_FILENAMES", &icd)
            .output()
            .expect("running the example");
        let walk_out = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "own_shader on {}: {walk_out}\n{}",
            icd.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(walk_out.contains("stackless walk"), "{walk_out}");
        check_own_shader_image(&walk_png, &walk_out, !level.is_empty());
        let (w, h) = (own_shader::WIDTH, own_shader::HEIGHT);
        let (a, b) = (load(&rq_png, w, h), load(&walk_png, w, h));
        let differing = a
            .pixels()
            .zip(b.pixels())
            .filter(|(p, q)| p.0.iter().zip(q.0).any(|(&x, y)| x.abs_diff(y) > 2))
            .count();
        let allowed = (w * h) as usize / 200;
        println!("own_shader {args:?}: ray queries and our walk differ in {differing} pixels");
        assert!(
            differing <= allowed,
            "{differing} pixels differ between ray queries and our walk (allowed {allowed})"
        );
    }
}

/// Compares `own_shader`'s image at `png` with the CPU's.
fn check_own_shader_image(png: &Path, stdout: &str, two_level: bool) {
    assert_eq!(stdout.contains("two levels"), two_level, "{stdout}");
    let (w, h) = (own_shader::WIDTH, own_shader::HEIGHT);
    let img = load(png, w, h);
    assert!(stdout.contains("incomplete: 0 pixels"), "{stdout}");

    let scene = bvhtrace_scene::load(SCENE).expect("scene");
    let tris = scene.flatten().triangles().expect("triangles");
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let rays = scene.camera_or_frame(w as f32 / h as f32).rays(w, h);
    let hits = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::Stackless)).hits;
    // Both examples draw misses in the same colour.
    let background = image::Rgb(user_device::BACKGROUND);

    let mut differing = 0;
    let mut drawn = 0;
    for ((p, ray), hit) in img.pixels().zip(&rays).zip(&hits) {
        let expected = if hit.is_hit() {
            let n = geometric_normal(&tris[hit.prim as usize]);
            image::Rgb(own_shader_colour(hit.prim, n, Vec3::from(ray.dir)))
        } else {
            background
        };
        if p.0.iter().zip(expected.0).any(|(&a, b)| a.abs_diff(b) > 2) {
            differing += 1;
        }
        drawn += usize::from(*p != background);
    }
    let cpu_hits = hits.iter().filter(|h| h.is_hit()).count();
    let allowed = rays.len() / 200;
    println!(
        "own_shader: {differing} pixels off the CPU's colours, {drawn} drawn, {cpu_hits} CPU hits"
    );
    assert!(
        differing <= allowed,
        "{differing} pixels of {} differ from the CPU's colours (allowed: {allowed})",
        png.display()
    );
    assert!(
        drawn.abs_diff(cpu_hits) <= allowed,
        "{drawn} pixels drawn, {cpu_hits} CPU hits"
    );
    assert!(cpu_hits > 0 && cpu_hits < rays.len(), "{cpu_hits} hits");
}
