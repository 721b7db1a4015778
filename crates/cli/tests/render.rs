//! The render command as a user meets it: every shading mode gives the same image on the GPU
//! and the CPU, bad paths fail early and cleanly, --help works everywhere.

mod common;

use common::*;

#[test]
fn every_shading_mode_gives_the_same_image_on_gpu_and_cpu() {
    let dir = scratch("modes");
    for mode in ["normal", "depth", "diffuse", "ao", "heatmap"] {
        let mut images = Vec::new();
        for backend in ["auto", "cpu"] {
            let png = dir.join(format!("{mode}-{backend}.png"));
            let out = render(
                "builtin:cornell",
                &png,
                &[
                    "--size",
                    "160x120",
                    "--shade",
                    mode,
                    "--ao-samples",
                    "4",
                    // One walk on both: the heatmap's counts depend on it.
                    "--traversal",
                    "stackless",
                    "--backend",
                    backend,
                ],
            );
            assert!(out.status.success(), "{mode} on {backend}");
            let stats = json(&out);
            if backend == "auto" && stats["backend"] != "wgpu" {
                eprintln!(
                    "SKIP: no Vulkan adapter (install mesa-vulkan-drivers); GPU images not compared"
                );
                return;
            }
            assert_eq!(stats["width"], 160);
            let img = image::open(&png).expect("a PNG was written").to_rgb8();
            assert_eq!(img.dimensions(), (160, 120));
            images.push(img);
        }
        let (g, c) = (&images[0], &images[1]);
        let differ = g.pixels().zip(c.pixels()).filter(|(a, b)| a != b).count();
        assert_eq!(
            differ, 0,
            "{mode}: {differ} pixels differ between GPU and CPU"
        );
        // Not blank: the scene is visible.
        let distinct: std::collections::HashSet<_> = c.pixels().map(|p| p.0).collect();
        assert!(distinct.len() > 3, "{mode}: image looks blank");
    }
}

#[test]
fn json_has_the_keys_scripts_depend_on() {
    let dir = scratch("json");
    let png = dir.join("o.png");
    let out = run(&[
        "render",
        "--size",
        "64x48",
        "--backend",
        "cpu",
        "--counters",
        "-o",
        png.to_str().unwrap(),
        "--json",
        "-",
    ]);
    assert!(out.status.success());
    let v = json(&out);
    for key in [
        "triangles",
        "nodes",
        "sah_cost",
        "sah_cost_pbrt",
        "load_ms",
        "build_ms",
        "upload_ms",
        "trace_ms",
        "rays",
        "mrays_per_s",
        "hits",
        "t_sum",
        "nodes_per_ray",
        "tris_per_ray",
        "backend",
        "adapter",
        "traversal",
        "builder",
        "uploaded_bytes",
        "features",
        "runs",
        "first_run",
        "default_traversal",
    ] {
        assert!(!v[key].is_null(), "missing key {key}");
    }
    assert_eq!(v["rays"], 64 * 48);
    assert!(v["hits"].as_u64().unwrap() > 0);
}

#[test]
fn an_unwritable_output_fails_before_any_work_and_leaves_nothing() {
    let dir = scratch("unwritable");
    let bad = dir.join("no/such/folder/out.png");
    let t = std::time::Instant::now();
    let out = run(&[
        "render",
        "builtin:grid:icosphere:30x30",
        "--backend",
        "cpu",
        "-o",
        bad.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("out.png") && err.contains("cannot write"),
        "{err}"
    );
    assert!(
        t.elapsed().as_secs() < 5,
        "failed only after doing the work"
    );
    // A render that fails after the file was reserved leaves no partial file behind.
    let png = dir.join("o.png");
    let out = run(&[
        "render",
        "/nonexistent/scene.glb",
        "-o",
        png.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/scene.glb"), "{err}");
    assert_eq!(
        std::fs::read_dir(&dir).unwrap().count(),
        0,
        "left files behind"
    );
}

#[test]
fn bad_flags_and_scenes_get_clear_errors() {
    let dir = scratch("flags");
    let png = dir.join("o.png");
    let p = png.to_str().unwrap();
    for (args, needle) in [
        (vec!["render", "--size", "0x10", "-o", p], "size"),
        (
            vec!["render", "--eye", "1,2", "--target", "0,0,0", "-o", p],
            "three",
        ),
        (
            vec!["render", "--traversal", "sideways", "-o", p],
            "unknown traversal",
        ),
        (vec!["render", "--builder", "magic", "-o", p], "gpu-ploc"),
        (
            vec!["render", "--builder", "gpu-ploc", "--optimize", "-o", p],
            "--optimize",
        ),
        (vec!["render", "builtin:nope", "-o", p], "builtin:nope"),
        (
            vec!["render", "--fov", "200", "--backend", "cpu", "-o", p],
            "fov",
        ),
    ] {
        let out = run(&args);
        assert!(!out.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}

#[test]
fn every_subcommand_has_help() {
    for sub in [
        "render",
        "info",
        "dump",
        "bench-build",
        "bench-trace",
        "bench-refit",
    ] {
        let out = run(&[sub, "--help"]);
        assert!(out.status.success(), "{sub} --help");
        assert!(
            String::from_utf8_lossy(&out.stdout).contains("Usage"),
            "{sub}"
        );
    }
}

#[test]
fn info_reports_the_scene() {
    let out = run(&["info", "builtin:cornell", "--json"]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["triangles"], 36);
    assert!(v["sah_cost"].as_f64().unwrap() > 1.0);
    assert!(v["nodes"].as_u64().unwrap() <= 71);
}

#[test]
fn optimize_lowers_the_sah_cost_and_keeps_the_image() {
    let info = |extra: &[&str]| {
        let mut a = vec![
            "info",
            "builtin:spheres",
            "--flatten",
            "--builder",
            "median",
            "--json",
        ];
        a.extend_from_slice(extra);
        let out = run(&a);
        assert!(out.status.success(), "{a:?}");
        json(&out)
    };
    let (plain, opt) = (info(&[]), info(&["--optimize"]));
    assert_eq!(opt["optimize"], true);
    assert_eq!(plain["nodes"], opt["nodes"]);
    assert!(opt["sah_cost"].as_f64().unwrap() < plain["sah_cost"].as_f64().unwrap());
    // Hits do not depend on the tree's shape: the same image, shadows included.
    let args = [
        "builtin:spheres",
        "--builder",
        "median",
        "--shade",
        "diffuse",
    ];
    let (_, img) = render_json("unoptimised", &args);
    let (v, img_opt) = render_json("optimised", &[&args[..], &["--optimize"]].concat());
    assert_eq!(v["optimize"], true);
    assert!(img == img_opt, "--optimize changed the image");
}

#[test]
fn device_builders_keep_the_image_in_one_and_two_levels() {
    // The device builds on the device it traces on: none on the CPU backend.
    let out = run(&["info", "--builder", "gpu-ploc"]);
    if !out.status.success() && String::from_utf8_lossy(&out.stderr).contains("mesa-vulkan") {
        return eprintln!("SKIP: no Vulkan adapter");
    }
    let png = scratch("device build on the cpu").join("o.png");
    let png = png.to_str().unwrap();
    let cpu = run(&[
        "render",
        "--backend",
        "cpu",
        "--builder",
        "gpu-ploc",
        "-o",
        png,
    ]);
    let err = String::from_utf8_lossy(&cpu.stderr);
    assert!(
        !cpu.status.success() && err.contains("cpu") && err.contains("no device to build on"),
        "{err}"
    );
    for scene in [&["builtin:spheres"][..], &["builtin:spheres", "--flatten"]] {
        let args = [scene, &["--shade", "diffuse"]].concat();
        let (sah, img) = render_json("device builds sah", &args);
        for builder in ["gpu-ploc", "gpu-lbvh"] {
            let (v, got) = render_json_on(
                "wgpu",
                &format!("device builds {builder}"),
                &[&args[..], &["--builder", builder]].concat(),
            );
            assert_eq!(v["builder"], builder);
            assert_eq!(v["form"], sah["form"]);
            assert_eq!(v["triangles"], sah["triangles"]);
            assert_ne!(
                v["sah_cost"], sah["sah_cost"],
                "{builder}: a tree of its own"
            );
            assert!(img == got, "{builder} {scene:?}: another image");
        }
    }
}

#[test]
fn sbvh_builds_within_its_budget_and_keeps_the_image() {
    let info = |extra: &[&str]| {
        let mut a = vec!["info", "builtin:degenerate", "--builder", "sbvh", "--json"];
        a.extend_from_slice(extra);
        let out = run(&a);
        assert!(out.status.success(), "{a:?}");
        json(&out)
    };
    let (plain, none) = (info(&[]), info(&["--split-budget", "0"]));
    let (tris, refs) = (
        plain["triangles"].as_u64().unwrap(),
        plain["references"].as_u64().unwrap(),
    );
    assert_eq!(plain["builder"], "sbvh");
    assert!(
        refs > tris && refs as f64 <= 1.3 * tris as f64,
        "{refs} references, {tris} triangles"
    );
    assert_eq!(none["references"], none["triangles"]);
    let bad = run(&["info", "--builder", "sbvh", "--split-budget=-1"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("split_budget"));
    // Leaves sharing triangles hit what one reference per triangle hits: the same image.
    let args = ["builtin:spheres", "--flatten", "--shade", "normal"];
    let (_, img) = render_json("sah", &args);
    let (_, img_sbvh) = render_json("sbvh", &[&args[..], &["--builder", "sbvh"]].concat());
    assert!(img == img_sbvh, "--builder sbvh changed the image");
}

/// Renders `args` on the CPU at 96x72 with JSON on stdout; returns the JSON and the PNG.
fn render_json(name: &str, args: &[&str]) -> (serde_json::Value, Vec<u8>) {
    render_json_on("cpu", name, args)
}

/// [`render_json`] on `backend`.
fn render_json_on(backend: &str, name: &str, args: &[&str]) -> (serde_json::Value, Vec<u8>) {
    let dir = scratch(name);
    let png = dir.join("o.png");
    let mut all = vec!["render", "--size", "96x72", "--backend", backend, "-o"];
    all.push(png.to_str().unwrap());
    all.extend_from_slice(&["--json", "-"]);
    all.extend_from_slice(args);
    let out = run(&all);
    assert!(out.status.success(), "{args:?}");
    (json(&out), std::fs::read(&png).expect("png written"))
}

#[test]
fn scenes_with_several_placements_trace_in_two_levels_and_flattened_alike() {
    let (two, img_two) = render_json("two-level", &["builtin:spheres"]);
    let (flat, img_flat) = render_json("flattened", &["builtin:spheres", "--flatten"]);
    assert_eq!(two["form"], "two-level");
    assert_eq!(flat["form"], "flattened");
    for v in [&two, &flat] {
        assert_eq!(v["instances"], 9);
        assert_eq!(v["meshes"], 5);
        assert_eq!(v["triangles"], 35_328);
    }
    assert!(two["top_level_bytes"].as_u64().unwrap() > 0);
    assert!(two["mesh_bytes"].as_u64().unwrap() > 0);
    // The same primitives are hit (same ids in both forms); `t` agrees to f32 rounding.
    assert_eq!(two["hits"], flat["hits"]);
    let (a, b) = (
        two["t_sum"].as_f64().unwrap(),
        flat["t_sum"].as_f64().unwrap(),
    );
    assert!((a - b).abs() <= 1e-5 * a.abs(), "t_sum {a} vs {b}");
    // The same image but where rounding moved a normal's colour by one step.
    let decode = |b: &[u8]| image::load_from_memory(b).expect("a PNG").to_rgb8();
    let (x, y) = (decode(&img_two), decode(&img_flat));
    let far = x
        .pixels()
        .zip(y.pixels())
        .filter(|(p, q)| p.0.iter().zip(q.0).any(|(a, b)| a.abs_diff(b) > 1))
        .count();
    assert!(
        far * 200 <= 96 * 72,
        "{far} pixels differ by more than one step"
    );
    // One placement traces flattened: no top level to walk.
    let (one, _) = render_json("one-placement", &["builtin:cornell"]);
    assert_eq!(one["form"], "flattened");
}

#[test]
fn animated_scenes_render_at_the_time_asked_for() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/animated.gltf");
    let (a, img_a) = render_json("time-0", &[scene, "--time", "0"]);
    let (b, img_b) = render_json("time-1", &[scene, "--time", "1.3"]);
    let (_, img_c) = render_json("time-0-again", &[scene, "--time", "0"]);
    assert_eq!(a["time"], 0.0);
    assert_eq!(b["time"], 1.3f32 as f64);
    assert_ne!(
        img_a, img_b,
        "the scene did not move between t = 0 and t = 1.3"
    );
    assert_eq!(img_a, img_c, "the same time gave another image");
    let out = run(&[
        "render",
        scene,
        "--backend",
        "cpu",
        "--time",
        "nan",
        "-o",
        "/tmp/x.png",
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--time"));
}

/// Deforming glTF scenes change with `--time`, and the GPU renders each pose as the CPU
/// does: `scenes/skinned.gltf` (a tube on two joints) and `scenes/morph.gltf` (the tube
/// swelling by a morph target before it is skinned, and a sphere morphing beside it).
#[test]
fn deforming_scenes_move_with_time_alike_on_gpu_and_cpu() {
    for (file, triangles) in [("skinned", 420), ("morph", 612)] {
        let scene = format!("{}/../../scenes/{file}.gltf", env!("CARGO_MANIFEST_DIR"));
        let (a, img_a) = render_json(&format!("{file}-0"), &[&scene, "--time", "0"]);
        let (b, img_b) = render_json(&format!("{file}-1"), &[&scene, "--time", "1"]);
        assert_eq!(a["triangles"], triangles, "{file}");
        assert_eq!(a["form"], "two-level", "{file}");
        assert_ne!(
            img_a, img_b,
            "{file}: nothing moved between t = 0 and t = 1"
        );
        assert_ne!(a["t_sum"], b["t_sum"], "{file}");
        for (t, cpu) in [("0", &img_a), ("1", &img_b)] {
            let dir = scratch(&format!("{file}-gpu-{t}"));
            let png = dir.join("o.png");
            let out = render(
                &scene,
                &png,
                &["--time", t, "--size", "96x72", "--backend", "gpu"],
            );
            let err = String::from_utf8_lossy(&out.stderr);
            if err.contains("no Vulkan adapter") {
                eprintln!("SKIP {file} GPU render: {err}");
                return;
            }
            assert!(out.status.success(), "{err}");
            assert!(
                std::fs::read(&png).expect("png") == *cpu,
                "{file} at t = {t}: GPU != CPU"
            );
        }
    }
}

/// `--layout wide` renders what the binary layout renders, byte for byte, on every backend,
/// in one level or two, and says so in the JSON; a binary walk with it is a clear error.
#[test]
fn the_wide_layout_renders_the_same_image() {
    let dir = scratch("layouts");
    let render = |scene: &str, backend: &str, layout: &str| {
        let png = dir.join(format!(
            "{}-{backend}-{layout}.png",
            scene.replace(':', "_")
        ));
        let out = common::render(
            scene,
            &png,
            &["--size", "96x72", "--backend", backend, "--layout", layout],
        );
        assert!(out.status.success(), "{scene} {backend} {layout}");
        (json(&out), std::fs::read(&png).expect("png written"))
    };
    for scene in ["builtin:cornell", "builtin:spheres"] {
        let (binary, img_binary) = render(scene, "cpu", "binary");
        assert_eq!(binary["layout"], "binary", "{scene}");
        // `auto` is wgpu when there is an adapter, the CPU (saying so) when there is none.
        for backend in ["cpu", "auto", "vulkan"] {
            let (wide, img_wide) = render(scene, backend, "wide");
            if backend == "auto" && wide["backend"] == "cpu" {
                // No adapter at all: `--backend vulkan` would be an error.
                eprintln!("SKIP: no Vulkan adapter; the wide kernel not compared");
                break;
            }
            assert_eq!(wide["layout"], "wide", "{scene} on {backend}");
            assert_eq!(wide["traversal"], "wide");
            assert_eq!(wide["hits"], binary["hits"], "{scene} on {backend}");
            assert!(
                img_wide == img_binary,
                "{scene} on {backend}: the images differ"
            );
            if backend != "cpu" {
                assert!(wide["uploaded_bytes"].as_u64().unwrap() > 0, "{backend}");
            }
        }
    }
    let out = run(&["render", "--layout", "wide", "--traversal", "stackless"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--layout wide") && err.contains("stackless"),
        "{err}"
    );
}

/// A masked scene (`scenes/foliage.gltf`): its leaves, fence and gate are cut by their
/// textures (on the CPU the JSON counts the candidates settled and sampled); `--opaque`
/// traces them whole (another image); the kernels, through wgpu and through ash, cut
/// them as the CPU does: the same hits and the same image, byte for byte.
#[test]
fn masked_materials_are_cut_alike_on_every_backend() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/foliage.gltf");
    let (cut, img_cut) = render_json("foliage-cut", &[scene, "--shade", "diffuse"]);
    let (whole, img_whole) =
        render_json("foliage-whole", &[scene, "--shade", "diffuse", "--opaque"]);
    assert_eq!(cut["backend"], "cpu");
    let masks = &cut["alpha_masks"];
    let (settled, sampled) = (masks["settled"].as_u64(), masks["sampled"].as_u64());
    assert!(sampled.is_some_and(|s| s > 100), "{masks}");
    assert!(settled.is_some_and(|s| s > 10), "{masks}");
    assert!(whole["alpha_masks"].is_null());
    assert_ne!(img_cut, img_whole, "the masks cut nothing");
    let hits = |v: &serde_json::Value| v["hits"].as_u64().expect("hits");
    assert!(hits(&cut) <= hits(&whole), "a cut scene stops more rays");
    assert_ne!(cut["t_sum"], whole["t_sum"]);
    for backend in ["gpu", "vulkan"] {
        let dir = scratch(&format!("foliage-{backend}"));
        let png = dir.join("o.png");
        let out = run(&[
            "render",
            scene,
            "--size",
            "96x72",
            "--backend",
            backend,
            "--shade",
            "diffuse",
            "-o",
            png.to_str().unwrap(),
            "--json",
            "-",
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        if err.contains("no Vulkan adapter") || err.contains("libvulkan") {
            return eprintln!("SKIP the device renders: {err}");
        }
        assert!(out.status.success(), "{backend}: {err}");
        let v = json(&out);
        assert_ne!(v["backend"], "cpu", "{backend}");
        assert!(
            v["alpha_masks"]["uploaded_bytes"]
                .as_u64()
                .is_some_and(|b| b > 0),
            "{v}"
        );
        assert_eq!(v["hits"], cut["hits"], "{backend}");
        assert_eq!(v["t_sum"], cut["t_sum"], "{backend}");
        let img = std::fs::read(&png).expect("png written");
        assert!(
            img == img_cut,
            "{backend}: the image differs from the CPU's"
        );
    }
}

/// `--shutter`: a scene that does not move renders as without a shutter, pixel for pixel;
/// a moving one blurs between its poses at the shutter's ends, alike on the device and
/// the CPU; flags the blurred render cannot honour are refused, naming them.
#[test]
fn blurred_renders_over_the_shutter() {
    let still = ["builtin:cornell", "--ao-samples", "4"];
    for mode in ["normal", "diffuse", "ao"] {
        let (_, sharp) = render_json(
            &format!("still-{mode}"),
            &[&still[..], &["--shade", mode]].concat(),
        );
        let blur = [
            &still[..],
            &[
                "--shade",
                mode,
                "--shutter",
                "0,1",
                "--shutter-samples",
                "1",
            ],
        ];
        let (j, blurred) = render_json(&format!("still-blur-{mode}"), &blur.concat());
        assert_eq!(j["time_steps"], 2);
        assert_eq!(
            sharp, blurred,
            "{mode}: a still scene changed under the shutter"
        );
    }
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/skinned.gltf");
    let (_, open) = render_json("blur-open", &[scene, "--time", "0.2"]);
    let (_, close) = render_json("blur-close", &[scene, "--time", "0.6"]);
    for bounds in ["linear", "merged"] {
        let args = [scene, "--shutter", "0.2,0.6", "--time-bounds", bounds];
        let (j, blurred) = render_json(&format!("blur-{bounds}"), &args);
        assert_eq!(j["time_bounds"], bounds);
        assert!(j["time_steps"].as_u64().unwrap() > 2, "{j}");
        assert_eq!(j["rays"], 96 * 72 * 8);
        assert!(
            blurred != open && blurred != close,
            "the blur is one of its ends"
        );
        let diffuse = [&args[..], &["--shade", "diffuse"]].concat();
        let (_, cpu) = render_json(&format!("blur-cpu-{bounds}"), &diffuse);
        let (g, gpu) = render_json_on("gpu", &format!("blur-gpu-{bounds}"), &diffuse);
        assert_eq!(g["backend"], "wgpu");
        assert!(cpu == gpu, "{bounds}: the device's blur is not the CPU's");
    }
    // Moving instances in two levels: the moving builtin's two copies.
    let two = [
        "builtin:moving:icosphere",
        "--shutter",
        "0,1",
        "--shade",
        "diffuse",
    ];
    let (j, instanced) = render_json("blur-instances", &[&two[..], &["--instances"]].concat());
    let (_, flattened) = render_json("blur-flattened", &two);
    assert_eq!(
        (j["levels"].as_u64(), j["time_steps"].as_u64()),
        (Some(2), Some(5))
    );
    // On the device and on the CPU twin: the same image.
    let (g, gpu_instanced) = render_json_on(
        "gpu",
        "blur-instances-gpu",
        &[&two[..], &["--instances"]].concat(),
    );
    assert_eq!(
        (j["backend"].as_str(), g["backend"].as_str()),
        (Some("cpu"), Some("wgpu"))
    );
    assert!(
        gpu_instanced == instanced,
        "the device's moving instances are not the CPU's"
    );
    // The same surfaces, rounded apart (each instance walked in its own space): a few
    // silhouette pixels may differ.
    let pixels = |png: &[u8]| image::load_from_memory(png).unwrap().to_rgb8().into_raw();
    let (a, b) = (pixels(&instanced), pixels(&flattened));
    let differ = a
        .iter()
        .zip(&b)
        .filter(|(x, y)| x.abs_diff(**y) > 8)
        .count();
    assert!(
        differ * 200 < a.len(),
        "{differ} of {} channels differ from the flattened blur",
        a.len()
    );
    for bad in [
        &["--backend", "vulkan"][..],
        &["--backend", "vulkan", "--instances"],
        &["--backend", "auto", "--shade", "heatmap"],
        &["--shade", "path"],
        &["--time", "0.3"],
        &["--traversal", "stackless"],
    ] {
        let mut args = vec![
            "render",
            scene,
            "--shutter",
            "0.2,0.6",
            "-o",
            "/tmp/never.png",
        ];
        args.extend(bad);
        let out = run(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("--shutter"),
            "{bad:?}: {err}"
        );
    }
    for shutter in ["0.6,0.2", "nan,1", "0.5", "0.5,0.5"] {
        let out = run(&[
            "render",
            scene,
            "--shutter",
            shutter,
            "-o",
            "/tmp/never.png",
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("OPEN,CLOSE"),
            "{shutter}: {err}"
        );
    }
    assert!(!std::path::Path::new("/tmp/never.png").exists());
}

/// Scenes with curves render through the tree of curves on the CPU twin and on wgpu (the
/// same hits and image for linear curves), a `.hair` file renders and `info` describes
/// it, `dump` writes version 4, and flags a scene with curves cannot honour are refused
/// by name.
#[test]
fn hair_renders_with_curves() {
    let hair = ["builtin:hair:round-linear:400", "--shade", "diffuse"];
    let (cpu, cpu_png) = render_json("hair-cpu", &hair);
    let (gpu, gpu_png) = render_json_on("gpu", "hair-gpu", &hair);
    assert_eq!(cpu["curves"]["segments"], 400 * 9);
    assert_eq!(gpu["backend"], "wgpu");
    assert!(cpu["hits"].as_u64().unwrap() > 1000, "{cpu}");
    assert_eq!(
        (cpu["hits"].as_u64(), cpu["t_sum"].as_f64()),
        (gpu["hits"].as_u64(), gpu["t_sum"].as_f64())
    );
    assert!(cpu_png == gpu_png, "the device's hair is not the CPU's");
    // A .hair file: its strands alone, framed by the camera.
    let dir = scratch("hair-strands");
    let file = dir.join("strands.hair");
    let scene = bvhtrace_scene::load("builtin:hair:round-linear:50").unwrap();
    std::fs::write(
        &file,
        bvhtrace_scene::hair_file_bytes(scene.curves.as_ref().unwrap()),
    )
    .unwrap();
    let (j, _) = render_json("hair-file", &[file.to_str().unwrap()]);
    assert_eq!(
        (j["triangles"].as_u64(), j["curves"]["segments"].as_u64()),
        (Some(0), Some(450))
    );
    assert!(j["hits"].as_u64().unwrap() > 0, "{j}");
    let info = run(&["info", file.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(
        info.status.success() && text.contains("450 round-linear segments"),
        "{text}"
    );
    let dump = dir.join("hair.bin");
    assert!(
        run(&[
            "dump",
            "builtin:hair:flat-linear:20",
            "-o",
            dump.to_str().unwrap()
        ])
        .status
        .success()
    );
    let bytes = std::fs::read(&dump).unwrap();
    assert_eq!((&bytes[..4], bytes[4]), (&b"BVHD"[..], 4));
    let never = dir.join("never.png");
    for bad in [
        ["--shade", "path"],
        ["--backend", "vulkan"],
        ["--time", "0.5"],
    ] {
        let mut args = vec![
            "render",
            "builtin:hair:round-linear:10",
            "-o",
            never.to_str().unwrap(),
        ];
        args.extend(bad);
        let out = run(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(bad[0]),
            "{bad:?}: {err}"
        );
    }
    assert!(!never.exists(), "a refused render wrote its image");
    // The commands that trace triangles alone refuse curves rather than time without them.
    for cmd in [
        &["cost", "builtin:hair:round-linear:10"][..],
        &["bench", "--quick", "builtin:hair:round-linear:10"],
        &["bench-build", "builtin:hair:round-linear:10"],
    ] {
        let out = run(cmd);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success()
                && err.contains("90 round-linear curve segments would be left out"),
            "{cmd:?}: {err}"
        );
    }
}
