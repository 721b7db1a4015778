//! `bvhtrace info` and `render --json` list what each GPU pipeline includes (features,
//! bindings) and the bytes uploaded, and leave out what the job does not read.

mod common;

use common::{json, render, run, scratch};
use serde_json::Value;

fn names(pipeline: &Value) -> Vec<String> {
    pipeline["bindings"]
        .as_array()
        .expect("bindings")
        .iter()
        .map(|b| b["name"].as_str().expect("name").to_string())
        .collect()
}

/// `info --json` on the Cornell box; `None` (SKIP) without a device, where the job's
/// pipelines and upload are not known: nothing was uploaded.
fn info(args: &[&str]) -> Option<Value> {
    let mut a = vec!["info", "builtin:cornell", "--json"];
    a.extend_from_slice(args);
    let out = run(&a);
    assert!(out.status.success());
    let v = json(&out);
    if v["upload"].is_null() {
        assert!(v["pipelines"].as_array().unwrap().is_empty(), "{v}");
        eprintln!("SKIP: no Vulkan adapter, so no upload or pipeline to list");
        return None;
    }
    Some(v)
}

#[test]
fn info_lists_the_pipeline_and_exact_upload() {
    // Full stack, normal shading: no escapes, no counters, no attributes, one pipeline.
    let Some(v) = info(&["--traversal", "full-stack"]) else {
        return;
    };
    let (nodes, tris) = (
        v["nodes"].as_u64().unwrap(),
        v["triangles"].as_u64().unwrap(),
    );
    let p = v["pipelines"].as_array().unwrap();
    assert_eq!(p.len(), 1);
    assert_eq!(p[0]["entry_point"], "bvh_trace_full_stack_main");
    assert_eq!(
        names(&p[0]),
        ["bvh_nodes", "bvh_triangles", "rays", "hits"],
        "{v}"
    );
    let u = &v["upload"];
    assert_eq!(u["escapes"], 0);
    assert_eq!(u["total"].as_u64().unwrap(), nodes * 32 + tris * 48);
    let per_tri = u["bytes_per_triangle"].as_f64().unwrap();
    assert!((per_tri - (nodes * 32 + tris * 48) as f64 / tris as f64).abs() < 1e-9);
    let left: Vec<&str> = v["left_out"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l.as_str().unwrap())
        .collect();
    assert!(
        left.iter().any(|l| l.starts_with("escape links")),
        "{left:?}"
    );
    assert!(left.iter().any(|l| l.starts_with("counters")), "{left:?}");

    // Stackless heatmap: escapes and counters come in.
    let Some(v) = info(&["--traversal", "stackless", "--shade", "heatmap"]) else {
        return;
    };
    let p = &v["pipelines"][0];
    assert_eq!(p["entry_point"], "bvh_trace_short_stack_counted");
    let n = names(p);
    assert!(n.contains(&"bvh_escapes".to_string()) && n.contains(&"counters".to_string()));
    assert_eq!(
        v["upload"]["escapes"].as_u64().unwrap(),
        4 * bvhtrace_core::flat::escape_links_len(nodes as usize) as u64
    );

    // AO: a second, any-hit pipeline without counters.
    let Some(v) = info(&["--shade", "ao", "--storage", "textures"]) else {
        return;
    };
    let p = v["pipelines"].as_array().unwrap();
    assert_eq!(p.len(), 2);
    assert!(
        p[1]["features"]
            .as_array()
            .unwrap()
            .contains(&"any-hit".into())
    );
    assert!(!names(&p[1]).contains(&"counters".to_string()));
    assert!(names(&p[1]).contains(&"bvh_node_texels".to_string()));
}

#[test]
fn attributes_a_scene_has_but_no_job_reads_are_left_out() {
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/cornell.gltf");
    let out = run(&["info", scene, "--json", "--shade", "diffuse"]);
    assert!(out.status.success());
    let v = json(&out);
    assert_eq!(
        v["attributes"]["normals"], true,
        "the committed Cornell box has NORMAL"
    );
    if v["upload"].is_null() {
        eprintln!("SKIP: no Vulkan adapter, so no pipeline to leave anything out of");
        return;
    }
    for p in v["pipelines"].as_array().unwrap() {
        assert!(!names(p).iter().any(|n| n.contains("normal")), "{p}");
    }
    let left = v["left_out"].to_string();
    assert!(
        left.contains("vertex normals (the scene has them"),
        "{left}"
    );
    assert!(left.contains("materials (the scene has them"), "{left}");
}

#[test]
fn render_json_lists_the_pipelines_and_bytes_uploaded() {
    let dir = scratch("pipeline-json");
    let png = dir.join("o.png");
    let out = render(
        "builtin:cornell",
        &png,
        &[
            "--size",
            "48x32",
            "--traversal",
            "full-stack",
            "--shade",
            "diffuse",
        ],
    );
    assert!(out.status.success());
    let v = json(&out);
    if v["backend"] != "wgpu" {
        eprintln!("SKIP: no GPU, the render ran on the CPU");
        assert!(v["pipelines"].as_array().unwrap().is_empty());
        return;
    }
    let u = &v["upload"];
    assert_eq!(u["total"], v["uploaded_bytes"]);
    assert_eq!(u["escapes"], 0, "the full stack does not read escapes");
    let p = v["pipelines"].as_array().unwrap();
    assert_eq!(p.len(), 2, "closest hit and the shadow rays' any hit");
    // --json alone counts nothing: both kernels are the uncounted ones.
    assert!(!names(&p[0]).contains(&"counters".to_string()));
    assert!(!names(&p[1]).contains(&"counters".to_string()));
    assert!(v["nodes_per_ray"].is_null(), "{}", v["nodes_per_ray"]);
    for q in p {
        assert!(
            !names(q)
                .iter()
                .any(|n| n.contains("escape") || n.contains("normal"))
        );
    }
}

/// Counters only when asked for: `--json` on a positions-only scene with normal shading
/// runs the uncounted kernel and lists no counters; `--counters` and the heatmap count.
/// `--runs N` reports N runs, the median and the first run apart.
#[test]
fn render_json_counts_only_when_asked() {
    let dir = scratch("pipeline-counters");
    let png = dir.join("o.png");
    let render = |extra: &[&str]| {
        let out = render(
            "builtin:icosphere:2",
            &png,
            &[&["--size", "40x30"], extra].concat(),
        );
        assert!(out.status.success());
        json(&out)
    };
    let counted = |v: &Value| {
        v["features"]
            .as_array()
            .unwrap()
            .iter()
            .any(|f| f == "counters")
    };
    for backend in ["cpu", "auto"] {
        let plain = render(&["--backend", backend, "--shade", "normal", "--runs", "3"]);
        assert!(!counted(&plain), "{backend}: {}", plain["features"]);
        assert!(plain["nodes_per_ray"].is_null());
        assert_eq!(plain["runs"], 3);
        assert!(plain["first_run"]["mrays_per_s"].as_f64().unwrap() > 0.0);
        assert!(plain["mrays_per_s"].as_f64().unwrap() > 0.0);
        for p in plain["pipelines"].as_array().unwrap() {
            assert!(!names(p).contains(&"counters".to_string()), "{p}");
        }
        for extra in [
            &["--counters", "--shade", "normal"][..],
            &["--shade", "heatmap"][..],
        ] {
            let mut a = vec!["--backend", backend];
            a.extend_from_slice(extra);
            let v = render(&a);
            assert!(counted(&v), "{backend} {extra:?}: {}", v["features"]);
            assert!(v["nodes_per_ray"].as_f64().unwrap() > 0.0);
            assert_eq!(plain["hits"], v["hits"], "counting changed the hits");
        }
        // The default walk is the backend's fastest, and the JSON says which it is.
        assert_eq!(plain["traversal"], plain["default_traversal"]);
    }
}
