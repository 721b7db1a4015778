//! `bvhtrace bench-build` end to end: every configuration's quality and counted work on a
//! small built-in scene.

mod common;

use bvhtrace_core::BuilderKind;
use common::*;
use serde_json::Value;

/// The ray kinds every row counts tests on.
const KINDS: [&str; 3] = ["primary", "shadow", "diffuse"];

/// `field` of `v` as a number, or a panic naming it.
fn num(v: &Value, field: &str) -> f64 {
    v[field]
        .as_f64()
        .unwrap_or_else(|| panic!("{field} is not a number in {v}"))
}

/// The rows of the only scene in a `bench-build --json -` document.
fn rows(doc: &Value) -> &Vec<Value> {
    let scenes = doc["scenes"].as_array().expect("scenes");
    assert_eq!(scenes.len(), 1);
    scenes[0]["configs"].as_array().expect("configs")
}

/// The row named `name`.
fn row<'a>(rows: &'a [Value], name: &str) -> &'a Value {
    rows.iter()
        .find(|r| r["name"] == name)
        .unwrap_or_else(|| panic!("no row {name}"))
}

#[test]
fn bench_build_reports_quality_and_counted_work_for_every_configuration() {
    let out = run(&[
        "bench-build",
        "builtin:cornell",
        "--runs",
        "1",
        "--size",
        "32x24",
        "--json",
        "-",
    ]);
    assert!(out.status.success());
    // With `--json -` the tables go to stderr, so stdout is pure JSON.
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("SAH(1,1)"), "no table on stderr:\n{stderr}");
    let doc = json(&out);
    assert_eq!(doc["runs"], 1);
    assert_eq!(doc["count_walk"], "full-stack");
    let rows = rows(&doc);

    // The default list: every builder with default options, and the variants.
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    for b in BuilderKind::ALL {
        assert!(
            names.contains(&b.name()),
            "{} missing from {names:?}",
            b.name()
        );
    }
    for v in [
        "sah:ctrav=1",
        "sah+optimize",
        "median+optimize",
        "midpoint+optimize",
        "sbvh:budget=1",
    ] {
        assert!(names.contains(&v), "{v} missing from {names:?}");
    }
    assert_eq!(row(rows, "sah:ctrav=1")["options"]["cost_traversal"], 1.0);
    assert_eq!(row(rows, "sah+optimize")["options"]["optimize"], true);
    assert_eq!(row(rows, "sbvh:budget=1")["options"]["split_budget"], 1.0);

    for r in rows {
        let name = r["name"].as_str().unwrap();
        for f in ["sah_cost", "sah_cost_pbrt", "build_ms"] {
            let x = num(r, f);
            assert!(x.is_finite() && x >= 0.0, "{name}: {f} = {x}");
        }
        // The SAH cost counts the root and at least one triangle test.
        assert!(num(r, "sah_cost") >= 1.0, "{name}");
        assert!(num(r, "sah_cost_pbrt") >= 1.0, "{name}");
        assert!(r["nodes"].as_u64().unwrap() >= 1, "{name}");
        assert!(num(r, "references_per_triangle") >= 1.0, "{name}");
        assert_eq!(r["primitives"], 36, "{name}: cornell has 36 triangles");
        for k in KINDS {
            let t = &r["tests"][k];
            assert!(t["ray_count"].as_u64().unwrap() > 0, "{name} {k}: no rays");
            for f in ["boxes_per_ray", "tris_per_ray"] {
                let x = num(t, f);
                assert!(x.is_finite() && x > 0.0, "{name} {k}: {f} = {x}");
            }
        }
        let cpu = r["cpu"].as_array().expect("cpu");
        assert_eq!(cpu.len(), 3, "{name}");
        for c in cpu {
            assert!(num(c, "mrays_per_s") > 0.0, "{name}: {c}");
            assert!(num(c, "boxes_per_ray") > 0.0, "{name}: {c}");
        }
        // The full-stack speed row counted the same rays as the primary tests.
        assert_eq!(
            cpu[0]["boxes_per_ray"], r["tests"]["primary"]["boxes_per_ray"],
            "{name}"
        );
    }

    // The exact sweep finds splits at least as good as the median's, in both conventions.
    let (sweep, med) = (row(rows, "sweep-sah"), row(rows, "median"));
    for f in ["sah_cost", "sah_cost_pbrt"] {
        assert!(
            num(sweep, f) <= num(med, f),
            "{f}: sweep-sah {} > median {}",
            num(sweep, f),
            num(med, f)
        );
    }
}

#[test]
fn bench_build_runs_the_configurations_asked_for() {
    let out = run(&[
        "bench-build",
        "builtin:icosphere:2",
        "--runs",
        "2",
        "--size",
        "16x12",
        "--builders",
        "sah:bins=8,sweep-sah:ctrav=1,median+optimize",
        "--json",
        "-",
    ]);
    assert!(out.status.success());
    let doc = json(&out);
    let rows = rows(&doc);
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        ["sah:bins=8", "sweep-sah:ctrav=1", "median+optimize"]
    );
    assert_eq!(rows[0]["options"]["bins"], 8);
    assert_eq!(rows[1]["builder"], "sweep-sah");
    assert_eq!(rows[1]["options"]["cost_traversal"], 1.0);
    assert_eq!(rows[2]["builder"], "median");
    assert_eq!(rows[2]["options"]["optimize"], true);
    for r in rows {
        assert_eq!(r["build_ms_runs"].as_array().unwrap().len(), 2);
    }

    for (bad, needle) in [
        ("nope", "unknown builder"),
        ("sah:foo=1", "unknown key"),
        ("sah:bins=1", "bins"),
        ("sah:ctrav", "KEY=VALUE"),
    ] {
        let out = run(&["bench-build", "builtin:cornell", "--builders", bad]);
        assert!(!out.status.success(), "--builders {bad} should fail");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "--builders {bad}: {err}");
    }
}
