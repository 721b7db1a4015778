//! `--backend vulkan` (the kernels on raw Vulkan through ash) as a user meets it: the same
//! images as the CPU, and the same bench measurements of accuracy and work per ray.

mod common;

use common::*;

/// True (after printing SKIP) when the Vulkan run failed because there is no Vulkan here.
fn no_vulkan(out: &std::process::Output) -> bool {
    let err = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() && err.contains("mesa-vulkan-drivers") {
        eprintln!("SKIP: no Vulkan device: {err}");
        return true;
    }
    false
}

#[test]
fn render_vulkan_gives_the_cpu_image() {
    let dir = scratch("vk-render");
    for mode in ["normal", "heatmap", "ao"] {
        let mut images = Vec::new();
        for backend in ["vulkan", "cpu"] {
            let png = dir.join(format!("{mode}-{backend}.png"));
            let out = render(
                "builtin:cornell",
                &png,
                &[
                    "--size",
                    "96x72",
                    "--shade",
                    mode,
                    "--ao-samples",
                    "2",
                    "--traversal",
                    "short-stack:4",
                    "--backend",
                    backend,
                ],
            );
            if backend == "vulkan" && no_vulkan(&out) {
                return;
            }
            assert!(
                out.status.success(),
                "{mode} on {backend}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            assert_eq!(json(&out)["backend"], backend);
            images.push(image::open(&png).expect("a PNG").to_rgb8());
        }
        let differ = images[0]
            .pixels()
            .zip(images[1].pixels())
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!(differ, 0, "{mode}: {differ} pixels differ, vulkan vs cpu");
    }
}

#[test]
fn bench_vulkan_measures_what_the_cpu_measures() {
    let out = bvhtrace()
        .args([
            "bench",
            "builtin:icosphere:2",
            "--quick",
            "--backends",
            "vulkan,cpu",
            "--precisions",
            "watertight-f32,moller-trumbore-f32",
            "--json",
            "-",
        ])
        .output()
        .expect("bvhtrace runs");
    assert_ok(&out);
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).expect("JSON rows");
    let vk: Vec<_> = rows.iter().filter(|r| r["backend"] == "vulkan").collect();
    if vk.is_empty() {
        eprintln!(
            "SKIP: no vulkan rows (no Vulkan device?): {}",
            String::from_utf8_lossy(&out.stderr)
        );
        return;
    }
    let key = |r: &serde_json::Value| {
        ["builder", "bins", "traversal", "rays", "precision"].map(|k| r[k].to_string())
    };
    for r in &vk {
        let cpu = rows
            .iter()
            .find(|c| c["backend"] == "cpu" && key(c) == key(r))
            .unwrap_or_else(|| panic!("no cpu row for {r}"));
        for field in [
            "wrong_prim",
            "false_misses",
            "false_hits",
            "nodes_per_ray",
            "tris_per_ray",
        ] {
            assert_eq!(r[field], cpu[field], "{field}: vulkan {r} vs cpu {cpu}");
        }
        assert!(r["trace_ms"].as_f64().unwrap() > 0.0);
    }
}

/// `--backend vulkan` with a device builder builds through ash, on the device it traces
/// on: the same tree as the wgpu build, the same image.
#[test]
fn device_builders_build_through_ash_on_vulkan() {
    let dir = scratch("vk-device-build");
    for builder in ["gpu-ploc", "gpu-lbvh"] {
        let mut runs = Vec::new();
        for backend in ["vulkan", "wgpu"] {
            let png = dir.join(format!("{builder}-{backend}.png"));
            let out = render(
                "builtin:spheres",
                &png,
                &[
                    "--size",
                    "96x72",
                    "--flatten",
                    "--builder",
                    builder,
                    "--backend",
                    backend,
                ],
            );
            if backend == "vulkan" && no_vulkan(&out) {
                return;
            }
            assert!(
                out.status.success(),
                "{builder} on {backend}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            let v = json(&out);
            assert_eq!(v["builder"], builder);
            let png = image::open(&png).expect("a PNG").to_rgb8();
            runs.push((v["sah_cost"].clone(), v["nodes"].clone(), png));
        }
        assert_eq!(
            runs[0].0, runs[1].0,
            "{builder}: SAH cost, ash vs wgpu build"
        );
        assert_eq!(runs[0].1, runs[1].1, "{builder}: nodes, ash vs wgpu build");
        assert!(runs[0].2 == runs[1].2, "{builder}: another image");
    }
}
