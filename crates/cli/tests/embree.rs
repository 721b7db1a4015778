//! The bunny hit count against an independent tracer (Embree 3, robust mode) on exactly the
//! same rays (written by `bvhtrace dump`): the CPU walks, the GPU walks, and the device's
//! ray queries where it has them. Skips, saying so, without a C compiler and Embree
//! (`apt-get install libembree-dev`) or without the shared scenes.

mod common;

use std::process::Command;

use common::*;

#[test]
fn bunny_hits_match_embree() {
    let Some(shared) = shared() else {
        eprintln!("SKIP: ../shared/scenes is absent");
        return;
    };
    if !std::path::Path::new("/usr/include/embree3/rtcore.h").exists() {
        eprintln!("SKIP: Embree 3 headers not found (apt-get install libembree-dev)");
        return;
    }
    let dir = scratch("embree");
    let exe = dir.join("embree_trace");
    let src = concat!(env!("CARGO_MANIFEST_DIR"), "/embree/embree_trace.c");
    let cc = Command::new("cc")
        .args(["-O2", src, "-lembree3", "-lpthread", "-lm", "-o"])
        .arg(&exe)
        .status();
    if !matches!(cc, Ok(s) if s.success()) {
        eprintln!("SKIP: could not compile {src} against Embree");
        return;
    }
    let bunny = shared.join("glb/bunny_69k.glb");
    let cam = [
        "--eye",
        "0.0540025,0.160756,0.200872",
        "--target",
        "-0.0168405,0.110154,-0.001537",
        "--fov",
        "50",
    ];
    let dump = dir.join("bunny.bin");
    let mut args = vec![
        "dump",
        bunny.to_str().unwrap(),
        "-o",
        dump.to_str().unwrap(),
    ];
    args.extend(cam);
    assert!(run(&args).status.success());
    let out = Command::new(&exe)
        .arg(&dump)
        .args(["2", "1"])
        .output()
        .expect("embree_trace runs");
    assert_ok(&out);
    let embree: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("embree: {embree}");
    assert_eq!(embree["rays"], 1024 * 768);
    let theirs = embree["hits"].as_f64().unwrap();
    // The device's ray queries too, where it has them (Mesa 25's lavapipe); `.ci/run`
    // sets BVHTRACE_REQUIRE_RAY_QUERIES=1 when it installed such a driver.
    let require_rq = std::env::var("BVHTRACE_REQUIRE_RAY_QUERIES").is_ok_and(|v| v == "1");
    // The tree built on the device too, traced by our walks on wgpu and on ash.
    for (backend, builder) in [
        ("cpu", "sah"),
        ("wgpu", "sah"),
        ("ray-query", "sah"),
        ("wgpu", "gpu-ploc"),
        ("vulkan", "gpu-ploc"),
    ] {
        let png = dir.join(format!("{backend}-{builder}.png"));
        let mut args = vec!["--backend", backend, "--builder", builder];
        args.extend(cam);
        let r = render(bunny.to_str().unwrap(), &png, &args);
        let stderr = String::from_utf8_lossy(&r.stderr);
        if backend == "ray-query" && !require_rq && stderr.contains("EXPERIMENTAL_RAY_QUERY") {
            eprintln!("SKIP ray-query: {}", stderr.trim());
            continue;
        }
        assert!(r.status.success(), "{backend} {builder}: {stderr}");
        let ours = json(&r);
        assert_eq!(ours["builder"], builder);
        let hits = ours["hits"].as_f64().unwrap();
        eprintln!(
            "{backend} {builder} ({}): {hits} hits, embree {theirs}",
            ours["adapter"]
        );
        assert!(
            (hits - theirs).abs() <= 1e-4 * theirs,
            "{backend} {builder}: {hits} hits vs Embree's {theirs}"
        );
        let (ts, tt) = (
            ours["t_sum"].as_f64().unwrap(),
            embree["t_sum"].as_f64().unwrap(),
        );
        assert!(
            (ts - tt).abs() <= 1e-4 * tt,
            "{backend} {builder}: t_sum {ts} vs {tt}"
        );
    }
}
