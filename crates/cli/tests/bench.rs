//! `bvhtrace bench` end to end on a small closed mesh.

mod common;

use std::path::Path;
use std::process::Output;

use common::*;

#[test]
fn bench_quick_writes_every_output_and_watertight_never_leaks() {
    let dir = scratch("bench");
    let csv = dir.join("b.csv");
    let plot = dir.join("plot");
    let out = run(&[
        "bench",
        "builtin:icosphere:3",
        "--quick",
        "--backends",
        "cpu",
        "--json",
        "-",
        "--csv",
        csv.to_str().unwrap(),
        "--plot",
        plot.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).expect("JSON rows");
    // 7 builders on primary rays + 5 traversals x 3 ray kinds, minus the shared one.
    assert!(rows.len() >= 7 + 15 - 1, "{} rows", rows.len());
    for r in &rows {
        assert!(r["trace_ms"].as_f64().unwrap() > 0.0);
        assert!(r["sample"].as_u64().unwrap() > 0);
        if r["precision"] != "moller-trumbore-f32" {
            assert_eq!(
                r["false_misses"], 0,
                "watertight leaked on a closed mesh: {r}"
            );
        }
    }
    // The precision axis: every precision is measured (Möller–Trumbore's false misses are
    // counted, whatever they are), on every ray kind.
    for p in ["watertight-f32", "moller-trumbore-f32", "watertight-f64"] {
        let n = rows.iter().filter(|r| r["precision"] == p).count();
        assert!(n >= 3, "{n} rows for {p}");
        assert!(
            rows.iter()
                .filter(|r| r["precision"] == p)
                .all(|r| r["false_misses"].is_u64())
        );
    }
    let text = std::fs::read_to_string(&csv).unwrap();
    assert_eq!(text.lines().count(), rows.len() + 1);
    assert!(text.starts_with("scene,builder,bins,traversal,backend,rays,precision"));
    for ext in ["png", "svg"] {
        let p = dir.join(format!("plot.{ext}"));
        assert!(
            std::fs::metadata(&p)
                .map(|m| m.len() > 1000)
                .unwrap_or(false),
            "{}",
            p.display()
        );
    }
}

#[test]
fn bench_rejects_an_unknown_precision() {
    let out = run(&[
        "bench",
        "builtin:icosphere:1",
        "--quick",
        "--backends",
        "cpu",
        "--precisions",
        "f16",
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown precision 'f16'"), "{err}");
}

#[test]
fn bench_refit_reports_refit_rebuild_and_top_level_times() {
    let out = run(&[
        "bench-refit",
        "builtin:icosphere:4",
        "--instances",
        "builtin:grid:icosphere:4x3",
        "--runs",
        "1",
        "--json",
        "-",
    ]);
    assert!(out.status.success());
    // Only the JSON on standard output (the table goes to standard error).
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON alone");
    assert!(String::from_utf8_lossy(&out.stderr).contains("refit ms"));
    let rows = v["refit"].as_array().expect("refit rows");
    assert_eq!(rows.len(), 5);
    for r in rows {
        assert!(r["refit_ms"].as_f64().unwrap() > 0.0);
        assert!(r["rebuild_ms"].as_f64().unwrap() > 0.0);
        // A refitted tree is never better than the tree built for the same vertices by
        // much, and the largest deformation makes it worse.
        assert!(r["sah_ratio"].as_f64().unwrap() > 0.9, "{r}");
    }
    let last = rows.last().unwrap();
    assert!(last["sah_ratio"].as_f64().unwrap() > rows[0]["sah_ratio"].as_f64().unwrap());
    assert_eq!(v["instances"], 12);
    assert_eq!(v["meshes"], 1);
    assert!(v["top_rebuild_ms"].as_f64().unwrap() > 0.0);
    assert!(v["gpu_refit"].is_null(), "the GPU refit only with --gpu");
}

#[test]
fn bench_refit_gpu_reports_the_device_refit() {
    let out = run(&[
        "bench-refit",
        "builtin:icosphere:4",
        "--instances",
        "builtin:grid:icosphere:2x2",
        "--runs",
        "1",
        "--gpu",
        "--json",
        "-",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    if err.contains("no Vulkan adapter") {
        eprintln!("SKIP bench-refit --gpu: {err}");
        return;
    }
    assert!(out.status.success(), "{err}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON alone");
    let g = &v["gpu_refit"];
    assert!(g["refit_ms"].as_f64().unwrap() > 0.0, "{g}");
    assert!(g["with_upload_ms"].as_f64().unwrap() > 0.0, "{g}");
    // The check, the corners, the leaves and at least one level of interior nodes.
    assert!(g["dispatches"].as_u64().unwrap() >= 4, "{g}");
    assert!(err.contains("GPU refit ("), "{err}");
}

/// `bench builtin:cornell --converge --quick` at 48x36, 1, 4 and 16 spp against a 64-spp
/// reference kept in `cache`, JSON on stdout, with `extra` flags.
fn quick_converge(cache: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "bench",
        "builtin:cornell",
        "--converge",
        "--quick",
        "--size",
        "48x36",
        "--spp",
        "1,4,16",
        "--reference-spp",
        "64",
        "--reference-cache",
        cache.to_str().unwrap(),
        "--json",
        "-",
    ];
    args.extend_from_slice(extra);
    run(&args)
}

#[test]
fn bench_converge_quick_errors_fall_as_samples_grow() {
    let dir = scratch("converge");
    let csv = dir.join("c.csv");
    let cache = dir.join("references");
    let converge = |extra: &[&str]| quick_converge(&cache, extra);
    let out = converge(&["--backends", "cpu", "--csv", csv.to_str().unwrap()]);
    assert!(out.status.success());
    let points: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).expect("JSON");
    // 2 builders x 2 walks x 1 backend x 3 shading kinds (ao, diffuse, path) x 3 levels.
    assert_eq!(points.len(), 36);
    for curve in points.chunks(3) {
        let spp: Vec<u64> = curve.iter().map(|p| p["spp"].as_u64().unwrap()).collect();
        assert_eq!(spp, [1, 4, 16]);
        for metric in ["flip", "rmse"] {
            let e: Vec<f64> = curve.iter().map(|p| p[metric].as_f64().unwrap()).collect();
            assert!(e[0] > e[1] && e[1] > e[2], "{metric} {e:?}: {}", curve[0]);
        }
        for p in curve {
            let (build, image) = (
                p["build_ms"].as_f64().unwrap(),
                p["image_ms"].as_f64().unwrap(),
            );
            assert!(image > 0.0 && (p["wall_ms"].as_f64().unwrap() - build - image).abs() < 1e-9);
        }
    }
    let text = std::fs::read_to_string(&csv).unwrap();
    assert_eq!(text.lines().count(), points.len() + 1);
    assert!(text.starts_with("scene,shade,builder,traversal,backend"));
    assert!(
        text.lines()
            .next()
            .unwrap()
            .ends_with(",max_depth,readback_ms,reference_cached")
    );
    check_path_rows(&points, &cache, &out, false);

    // Again, the path tracer alone, on the device too: its reference is read back from the
    // cache, and gives the CPU twin's images the same errors as the first time.
    let again = converge(&["--backends", "wgpu,cpu", "--shades", "path"]);
    assert_ok(&again);
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&again.stdout).expect("JSON");
    check_path_rows(&rows, &cache, &again, true);
    let first: Vec<&serde_json::Value> = points.iter().filter(|p| p["shade"] == "path").collect();
    let cpu: Vec<&serde_json::Value> = rows.iter().filter(|p| p["backend"] == "cpu").collect();
    assert_eq!(cpu.len(), first.len());
    for (a, b) in first.iter().zip(&cpu) {
        assert_eq!(
            (&a["flip"], &a["rmse"]),
            (&b["flip"], &b["rmse"]),
            "{a}\n{b}"
        );
    }
    let err = String::from_utf8_lossy(&again.stderr);
    let device: Vec<&serde_json::Value> = rows.iter().filter(|p| p["backend"] == "wgpu").collect();
    if device.is_empty() {
        eprintln!("SKIP the path tracer on the device: {err}");
    } else if err.contains("llvmpipe") {
        // lavapipe sums exactly as the twin does: the same images, the same errors.
        assert_eq!(device.len(), cpu.len());
        for (d, c) in device.iter().zip(&cpu) {
            assert_eq!(
                (&d["flip"], &d["rmse"]),
                (&c["flip"], &c["rmse"]),
                "{d}\n{c}"
            );
        }
    }
}

/// The path tracer's rows of a `--converge` run: one progressive image per configuration,
/// its errors falling as its samples grow, its reference cached in `cache` (one file) and
/// read from there when `reused`.
fn check_path_rows(points: &[serde_json::Value], cache: &Path, out: &Output, reused: bool) {
    let path: Vec<&serde_json::Value> = points.iter().filter(|p| p["shade"] == "path").collect();
    // 2 builders x 2 walks x each backend x 3 levels.
    assert!(
        !path.is_empty() && path.len().is_multiple_of(12),
        "{} path rows",
        path.len()
    );
    for curve in path.chunks(3) {
        let spp: Vec<u64> = curve.iter().map(|p| p["spp"].as_u64().unwrap()).collect();
        assert_eq!(spp, [1, 4, 16]);
        for metric in ["flip", "rmse"] {
            let e: Vec<f64> = curve.iter().map(|p| p[metric].as_f64().unwrap()).collect();
            assert!(e[0] > e[1] && e[1] > e[2], "{metric} {e:?}: {}", curve[0]);
        }
        // One image growing: its time and rays grow with it.
        for w in curve.windows(2) {
            assert!(
                w[1]["image_ms"].as_f64() > w[0]["image_ms"].as_f64(),
                "{}",
                w[1]
            );
            assert!(w[1]["rays"].as_u64() > w[0]["rays"].as_u64(), "{}", w[1]);
        }
        for p in curve {
            assert_eq!(p["first_sample"], 0);
            assert_eq!(p["max_depth"], 8);
            assert_eq!(p["reference_cached"], reused, "{p}");
            assert!(p["readback_ms"].as_f64().unwrap() >= 0.0, "{p}");
        }
    }
    for p in points.iter().filter(|p| p["shade"] != "path") {
        assert!(
            p["max_depth"].is_null() && p["reference_cached"].is_null(),
            "{p}"
        );
    }
    let files: Vec<_> = std::fs::read_dir(cache)
        .expect("the cache folder")
        .collect();
    assert_eq!(files.len(), 1, "{files:?}");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        err.contains("path reference (48x36, 64 spp) read from"),
        reused,
        "{err}"
    );
}

/// `bench` and `bench --converge` measure the device's ray queries beside our walks where
/// it has them (Mesa 25's lavapipe; `.ci/run` sets BVHTRACE_REQUIRE_RAY_QUERIES=1 there).
#[test]
fn bench_and_converge_measure_ray_queries() {
    let required = std::env::var("BVHTRACE_REQUIRE_RAY_QUERIES").is_ok_and(|v| v == "1");
    let out = run(&[
        "bench",
        "builtin:icosphere:3",
        "--quick",
        "--backends",
        "ray-query,cpu",
        "--precisions",
        "watertight-f32",
        "--json",
        "-",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    if err.contains("no ray-query device") {
        assert!(
            !required,
            "no ray queries with BVHTRACE_REQUIRE_RAY_QUERIES=1: {err}"
        );
        eprintln!("SKIP ray-query rows: {err}");
        return;
    }
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).expect("JSON rows");
    let rq: Vec<&serde_json::Value> = rows
        .iter()
        .filter(|r| r["backend"] == "ray-query")
        .collect();
    // One row per ray kind: the driver's walk, over the default builder's tree.
    assert_eq!(rq.len(), 3, "{rq:?}\n{err}");
    for r in &rq {
        assert_eq!(r["traversal"], "driver", "{r}");
        assert!(r["trace_ms"].as_f64().unwrap() > 0.0 && r["sample"].as_u64().unwrap() > 0);
        assert!(r["wrong_prim"].is_u64(), "{r}");
    }

    let cache = scratch("converge-ray-queries");
    let out = quick_converge(&cache, &["--backends", "ray-query,cpu"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let points: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).expect("JSON");
    let rq: Vec<&serde_json::Value> = points
        .iter()
        .filter(|p| p["backend"] == "ray-query")
        .collect();
    // 2 builders x the driver's walk x 3 shading kinds (the path tracer's kernel over ray
    // queries among them) x 3 levels.
    assert_eq!(rq.len(), 18, "{} ray-query points", rq.len());
    for curve in rq.chunks(3) {
        assert_eq!(curve[0]["traversal"], "driver");
        let flip: Vec<f64> = curve.iter().map(|p| p["flip"].as_f64().unwrap()).collect();
        assert!(flip[0] > flip[2], "{flip:?}");
    }
}

/// The rows of `bench-trace --cpu-only`'s first table of ray kind `kind` in `text` (the
/// lines below its head, up to the next blank line or table).
fn cpu_table_rows<'a>(text: &'a str, kind: &str) -> Vec<&'a str> {
    let table = (text.split(&format!("{kind} (")).nth(1))
        .unwrap_or_else(|| panic!("no {kind} table:\n{text}"));
    (table.lines().skip(2))
        .take_while(|l| !l.is_empty() && !l.contains(" ("))
        .collect()
}

/// `bench-trace --cpu-only` traces diffuse-bounce rays beside primary and shadow rays, every
/// path with the full stack's answers, and sweeps thread counts; a count of 0, or a sweep
/// or Embree 4's helper without `--cpu-only`, is refused.
#[test]
fn bench_trace_cpu_only_sweeps_threads_over_every_ray_kind() {
    let out = run(&[
        "bench-trace",
        "--cpu-only",
        "--runs",
        "1",
        "--size",
        "64x48",
        "--threads",
        "1,2",
        "builtin:icosphere:2",
    ]);
    assert_ok(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    for kind in ["primary", "shadow", "diffuse"] {
        let rows = cpu_table_rows(&text, kind);
        assert!(rows.len() >= 3, "{kind}: {rows:?}");
        for row in rows {
            let differ = row.split_whitespace().last().unwrap_or_default();
            assert!(differ == "0" || differ == "-", "{kind}: {row}");
        }
    }
    let sweep = (text.split("thread sweep").nth(1)).unwrap_or_else(|| panic!("no sweep:\n{text}"));
    let lines: Vec<&str> = sweep.lines().filter(|l| l.contains(" diffuse ")).collect();
    assert!(!lines.is_empty(), "{sweep}");
    for l in lines {
        assert!(l.contains("1: ") && l.contains("2: "), "{l}");
    }
    for (flags, says) in [
        (&["--cpu-only", "--threads", "0"][..], "--threads"),
        (&["--threads", "2"], "--threads"),
        (&["--embree4", "embree4_trace"], "--embree4"),
        (&["--cpu-only", "--rays", "shadow"], "--rays"),
    ] {
        let mut args = vec!["bench-trace", "--runs", "1"];
        args.extend_from_slice(flags);
        let out = run(&args);
        assert!(!out.status.success(), "{flags:?} succeeded");
        assert!(
            String::from_utf8_lossy(&out.stderr).contains(says),
            "{flags:?}"
        );
    }
}

#[test]
fn bench_trace_cpu_only_times_the_scene_as_the_front_door_traces_it() {
    // The foliage places its meshes several times and cuts its leaves with alpha masks:
    // the CPU layout over that tree gets its own rows, checked against the full stack over
    // the same tree; one mesh without masks (the icosphere) gets none.
    let foliage = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/foliage.gltf");
    for (scene, rows_expected) in [(foliage, 1), ("builtin:icosphere:2", 0)] {
        let out = run(&[
            "bench-trace",
            "--cpu-only",
            "--runs",
            "1",
            "--size",
            "64x48",
            scene,
        ]);
        assert_ok(&out);
        let text = String::from_utf8_lossy(&out.stdout);
        assert_eq!(
            text.contains("as traced (two-level masked)"),
            rows_expected > 0,
            "{text}"
        );
        for kind in ["primary", "shadow", "diffuse"] {
            let rows: Vec<&str> = (cpu_table_rows(&text, kind).into_iter())
                .filter(|l| l.contains(" two-level masked "))
                .collect();
            // One row per instruction set this CPU has.
            assert_eq!(rows.len().min(1), rows_expected, "{kind}:\n{text}");
            for row in rows {
                let differ = row.split_whitespace().last().unwrap_or_default();
                assert_eq!(differ, "0", "{kind}: {row}");
            }
        }
    }
}

/// `tune --json` times every walk the device opens in each storage it offers, names the
/// fastest among them, and the device's default beside it (the stackless walk in textures
/// on lavapipe, no faster than the fastest); the CPU is not a device to tune.
#[test]
fn tune_times_every_walk_beside_the_devices_default() {
    let out = run(&["tune", "--json", "--runs", "1", "--size", "32x24"]);
    if !out.status.success() && String::from_utf8_lossy(&out.stderr).contains("Vulkan") {
        eprintln!("SKIP tune: no device");
        return;
    }
    assert!(out.status.success());
    let v = json(&out);
    let rows = v["measured"].as_array().expect("rows");
    let walks: std::collections::BTreeSet<&str> =
        rows.iter().filter_map(|r| r["walk"].as_str()).collect();
    assert_eq!(walks.len(), 4, "{walks:?}");
    assert!(rows.contains(&v["fastest"]), "{}", v["fastest"]);
    assert!(
        rows.iter()
            .all(|r| r["mrays_per_s"].as_f64().unwrap() > 0.0)
    );
    let over = v["default_over_fastest"]
        .as_f64()
        .expect("the default was timed");
    assert!(over >= 1.0, "{over}");
    let refused = run(&["tune", "--backend", "cpu"]);
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--backend gpu or vulkan"));
}

/// `tune --save` records the fastest walk and storage for the adapter in the cache
/// (`$XDG_CACHE_HOME/bvhtrace/tuned.json`), and `render` on that adapter takes them when no
/// walk or storage is asked for, saying so; one asked for wins.
#[test]
fn tune_save_is_what_render_takes_on_that_adapter() {
    let dir = scratch("tuned");
    let with_cache = |args: &[&str]| {
        let out = bvhtrace()
            .env("XDG_CACHE_HOME", &dir)
            .args(args)
            .output()
            .expect("bvhtrace runs");
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        out
    };
    let probe = run(&["tune", "--json", "--runs", "1", "--size", "8x6"]);
    if !probe.status.success() {
        eprintln!("SKIP tune --save: no device");
        return;
    }
    let tuned = json(&with_cache(&[
        "tune", "--save", "--json", "--runs", "1", "--size", "32x24",
    ]));
    let cache: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("bvhtrace/tuned.json")).expect("saved"))
            .expect("JSON");
    let entry = &cache["adapters"][tuned["device"].as_str().expect("device")];
    // The cache spells a short stack as `--traversal` takes it, reports as `short-stack(K)`.
    let saved = entry["walk"].as_str().expect("walk");
    let saved = match saved.strip_prefix("short-stack:") {
        Some(k) => format!("short-stack({k})"),
        None => saved.to_string(),
    };
    assert_eq!(tuned["fastest"]["walk"], saved.as_str(), "{cache}");
    let png = dir.join("r.png");
    let p = png.to_str().unwrap();
    let out = with_cache(&["render", "--size", "32x24", "-o", p, "--json", "-"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("tune --save"));
    assert_eq!(json(&out)["traversal"], saved.as_str());
    let other = if saved == "wide" {
        "full-stack"
    } else {
        "wide"
    };
    let out = with_cache(&[
        "render",
        "--size",
        "32x24",
        "--traversal",
        other,
        "-o",
        p,
        "--json",
        "-",
    ]);
    assert!(!String::from_utf8_lossy(&out.stderr).contains("tune --save"));
    assert_eq!(json(&out)["traversal"], other);
}

/// `bench-trace --rays shadow` traces the shadow rays `bvhtrace cost` models on the device:
/// fewer rays than pixels (only primary hits cast one), many more box tests each.
#[test]
fn bench_trace_traces_the_ray_kind_asked_for() {
    let counts = |kind: &str| {
        let out = run(&[
            "bench-trace",
            "--runs",
            "1",
            "--size",
            "64x48",
            "--traversals",
            "full-stack",
            "--any-hit",
            "--rays",
            kind,
            "builtin:icosphere:3",
        ]);
        if !out.status.success() && String::from_utf8_lossy(&out.stderr).contains("adapter") {
            return None;
        }
        assert_ok(&out);
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        let rays: usize = (text.lines())
            .find_map(|l| l.split(" triangles, depth ").nth(1))
            .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
            .unwrap_or_else(|| panic!("no ray count:\n{text}"));
        Some((rays, text))
    };
    let Some((primary, p)) = counts("primary") else {
        return eprintln!("SKIP: no adapter");
    };
    let (shadow, s) = counts("shadow").expect("the same adapter");
    assert_eq!(primary, 64 * 48, "{p}");
    assert!(shadow > 0 && shadow < primary, "{s}");
    assert!(s.contains(" shadow rays (from 64x48)"), "{s}");
}
