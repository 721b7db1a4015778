//! `bvhtrace stress` end to end: a quick case through the binary, its JSON, and its errors.
//! (The guarantees themselves are tested case by case in `crates/stress/tests/stress.rs`.)

mod common;

use common::{bvhtrace, run, scratch};

#[test]
fn stress_runs_a_case_and_writes_json() {
    let dir = scratch("stress");
    let json = dir.join("stress.json");
    let out = run(&[
        "stress",
        "--quick",
        "--case",
        "extreme-rays",
        "--json",
        json.to_str().expect("utf-8 path"),
    ]);
    assert!(out.status.success());
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(table.contains("extreme-rays"), "{table}");
    assert!(table.contains("all cases clean"), "{table}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json written")).expect("json");
    assert_eq!(v["clean"], serde_json::Value::Bool(true));
    let cases = v["cases"].as_array().expect("cases");
    assert_eq!(cases.len(), 1);
    assert_eq!(cases[0]["name"], "extreme-rays");
    // Every run of the case: no NaN, the contract kept.
    for r in cases[0]["runs"].as_array().expect("runs") {
        assert_eq!(r["nan_outputs"], 0, "{r}");
        assert_eq!(r["contract_violations"], 0, "{r}");
    }
}

#[test]
fn stress_runs_with_optimised_trees() {
    let dir = scratch("stress-optimize");
    let json = dir.join("stress.json");
    let out = run(&[
        "stress",
        "--quick",
        "--backends",
        "cpu",
        "--case",
        "watertight",
        "--optimize",
        "--json",
        json.to_str().expect("utf-8 path"),
    ]);
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{table}");
    assert!(table.contains("optimised trees"), "{table}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json written")).expect("json");
    assert_eq!(v["optimize"], true);
    assert_eq!(v["clean"], true);
}

#[test]
fn stress_errors_name_the_cause() {
    let out = run(&["stress", "--case", "no-such-case"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no-such-case"), "{err}");

    let out = run(&["stress", "--quick", "--json", "/nonexistent-dir/x.json"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent-dir/x.json"), "{err}");
}

/// A case whose inputs are absent (the real meshes, without the shared scenes folder) is
/// skipped, says so, and is not a failure.
#[test]
fn stress_skips_a_case_without_its_inputs() {
    let absent = scratch("stress-no-scenes").join("absent");
    let out = bvhtrace()
        .env("BVHTRACE_SCENES", &absent)
        .args(["stress", "--quick", "--case", "watertight-real"])
        .output()
        .expect("bvhtrace runs");
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{table}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(table.contains("watertight-real"), "{table}");
    assert!(table.contains("skipped"), "{table}");
    assert!(table.contains("1 skipped: watertight-real"), "{table}");
}
