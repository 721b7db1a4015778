//! `bvhtrace cost` end to end: the GPU cost model on small built-in scenes.

mod common;

use common::*;
use serde_json::Value;

/// The walks `cost` runs by default, as its JSON names them.
const WALKS: [&str; 4] = ["full-stack", "stackless", "short-stack(8)", "wide"];
/// The ray kinds, in the order the rows come.
const KINDS: [&str; 3] = ["primary", "shadow", "diffuse"];

/// `x` as a number, or a panic naming the field and the row.
fn num(row: &Value, field: &str) -> f64 {
    row[field]
        .as_f64()
        .unwrap_or_else(|| panic!("{field} is not a number in {row}"))
}

/// Equal up to rounding of sums in 64-bit floats.
fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
}

/// `a >= b`, up to the same rounding.
fn at_least(a: f64, b: f64) -> bool {
    a >= b || close(a, b)
}

#[test]
fn cost_json_has_every_walk_and_consistent_figures() {
    let out = run(&[
        "cost",
        "builtin:cornell",
        "builtin:icosphere:3",
        "--size",
        "64x48",
        "--json",
        "-",
    ]);
    assert!(out.status.success());
    // With `--json -` the table goes to stderr, so stdout is pure JSON.
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("trips/warp"),
        "no table on stderr:\n{stderr}"
    );
    let doc = json(&out);
    assert_eq!(doc["warp"], 32);
    assert!(doc["assumptions"].as_str().unwrap().contains("lock step"));
    let scenes = doc["scenes"].as_array().expect("scenes");
    assert_eq!(scenes.len(), 2);
    for s in scenes {
        let name = s["scene"].as_str().unwrap();
        assert!(s["triangles"].as_u64().unwrap() > 0, "{name}");
        let (binary, wide) = (
            num(s, "binary_bytes_per_triangle"),
            num(s, "wide_bytes_per_triangle"),
        );
        // At least the 48-byte triangle itself; the wide layout's fewer, fatter nodes
        // take less room than the binary tree's.
        assert!(binary > 48.0 && wide > 48.0, "{name}: {binary} {wide}");
        assert!(
            wide < binary,
            "{name}: wide {wide} >= binary {binary} B/triangle"
        );

        let rows = s["rows"].as_array().expect("rows");
        assert_eq!(rows.len(), KINDS.len() * WALKS.len(), "{name}");
        for kind in KINDS {
            for walk in WALKS {
                let n = rows
                    .iter()
                    .filter(|r| r["rays"] == kind && r["walk"] == walk)
                    .count();
                assert_eq!(n, 1, "{name}: {n} rows for {kind} {walk}");
            }
        }
        for r in rows {
            let rays = r["ray_count"].as_u64().unwrap();
            let warps = r["warps"].as_u64().unwrap();
            if r["rays"] == "primary" {
                assert_eq!(rays, 64 * 48, "{r}");
            }
            assert!(rays > 0, "{name}: no rays in {r}");
            assert_eq!(warps, rays.div_ceil(32), "{r}");
            let lanes = num(r, "lane_utilisation");
            assert!(lanes > 0.0 && lanes <= 1.0, "{r}");
            let (per_warp, per_ray) = (num(r, "trips_per_warp"), num(r, "trips_per_ray"));
            assert!(per_ray > 0.0, "{r}");
            // The slowest lane of a warp makes at least its warp's mean trips; a short
            // last warp can tip the means over, so only whole warps are held to it.
            if rays % 32 == 0 {
                assert!(at_least(per_warp, per_ray), "{r}");
                // A lane's work is its trips and 0.65 trips a box test, the slowest lane's
                // at least the mean lane's.
                let work = num(r, "work_per_warp");
                assert!(
                    at_least(work, per_ray + 0.65 * num(r, "nodes_per_ray")),
                    "{r}"
                );
                assert!(at_least(work, per_warp), "{r}");
            }
            // Utilisation is work over lane-trips spent: the two means say the same.
            let spent = 32.0 * per_warp * warps as f64;
            assert!(
                close(lanes, per_ray * rays as f64 / spent),
                "utilisation does not match the trip counts: {r}"
            );
            let (node_b, tri_b) = (
                num(r, "node_bytes_per_ray"),
                num(r, "triangle_bytes_per_ray"),
            );
            assert!(node_b > 0.0, "{r}");
            assert!(close(num(r, "bytes_per_ray"), node_b + tri_b), "{r}");
            // Every walk loads 48 bytes per triangle tested.
            assert!(close(tri_b, 48.0 * num(r, "tris_per_ray")), "{r}");
            let nodes = num(r, "nodes_per_ray");
            match r["walk"].as_str().unwrap() {
                // No escape links: exactly one 32-byte node per box tested.
                "full-stack" => {
                    assert!(close(node_b, 32.0 * nodes), "{r}");
                    assert!(close(num(r, "trips_per_warp_ratio"), 1.0), "{r}");
                    assert!(close(num(r, "bytes_per_ray_ratio"), 1.0), "{r}");
                }
                // Escape links on top of the boxes.
                "stackless" | "short-stack(8)" => assert!(at_least(node_b, 32.0 * nodes), "{r}"),
                // One 80-byte node holds up to eight boxes.
                "wide" => assert!(at_least(node_b, 80.0 * nodes / 8.0), "{r}"),
                w => panic!("unexpected walk {w}"),
            }
        }
    }
}

#[test]
fn cost_walks_option_orders_the_ratios() {
    let out = run(&[
        "cost",
        "builtin:cornell",
        "--size",
        "32x16",
        "--walks",
        "wide,full-stack",
        "--json",
        "-",
    ]);
    assert!(out.status.success());
    let doc = json(&out);
    let rows = doc["scenes"][0]["rows"].as_array().expect("rows");
    assert_eq!(rows.len(), 2 * KINDS.len());
    for pair in rows.chunks(2) {
        assert_eq!(pair[0]["walk"], "wide");
        assert_eq!(pair[1]["walk"], "full-stack");
        // The first walk listed is the one the ratios divide by.
        assert!(close(num(&pair[0], "bytes_per_ray_ratio"), 1.0));
        let want = num(&pair[1], "trips_per_warp") / num(&pair[0], "trips_per_warp");
        assert!(
            close(num(&pair[1], "trips_per_warp_ratio"), want),
            "{pair:?}"
        );
        let want = num(&pair[1], "work_per_warp") / num(&pair[0], "work_per_warp");
        assert!(
            close(num(&pair[1], "work_per_warp_ratio"), want),
            "{pair:?}"
        );
    }
}

#[test]
fn cost_bad_inputs_fail_with_a_message_naming_them() {
    let missing = scratch("cost").join("no-such-scene.glb");
    let missing = missing.to_str().unwrap();
    let out = run(&["cost", missing, "--size", "8x8"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(missing), "{err}");
    assert!(!err.contains("panicked"), "{err}");

    let out = run(&["cost", "builtin:cornell", "--size", "64by48"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("64by48"), "{err}");
    assert!(!err.contains("panicked"), "{err}");

    let out = run(&["cost", "builtin:cornell", "--walks", "full-stack,sideways"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("sideways"), "{err}");
}
