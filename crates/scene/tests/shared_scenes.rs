//! Every published scene in the shared folder loads with the triangle count SOURCES.md
//! gives; the glTF originals match their flattened GLB twins; igea loads fast.

mod common;

use std::path::Path;
use std::time::Instant;

use bvhtrace_scene::{Scene, load, load_gltf_file};

/// `(relative path, triangles)` for every row of SOURCES.md's two tables.
fn sources(dir: &Path) -> Vec<(String, usize)> {
    let text = std::fs::read_to_string(dir.join("SOURCES.md")).expect("SOURCES.md");
    text.lines()
        .filter_map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let file = cells.get(1)?.strip_prefix('`')?.strip_suffix('`')?;
            let n: usize = cells.get(2)?.parse().ok()?;
            Some((file.to_string(), n))
        })
        .collect()
}

fn total_area(s: &Scene) -> f64 {
    s.flatten()
        .triangles()
        .expect("valid triangles")
        .iter()
        .map(|[a, b, c]| {
            (b.as_dvec3() - a.as_dvec3())
                .cross(c.as_dvec3() - a.as_dvec3())
                .length()
                * 0.5
        })
        .sum()
}

#[test]
fn every_shared_scene_loads_with_its_triangle_count() {
    let Some(dir) = common::shared("every_shared_scene_loads_with_its_triangle_count") else {
        return;
    };
    let rows = sources(&dir);
    let glbs: Vec<_> = std::fs::read_dir(dir.join("glb"))
        .expect("glb folder")
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "glb"))
        .collect();
    assert!(glbs.len() >= 20, "expected the 20 shared GLB files");
    for p in &glbs {
        let rel = format!(
            "glb/{}",
            p.file_name().and_then(|s| s.to_str()).unwrap_or_default()
        );
        let expect = rows.iter().find(|(f, _)| *f == rel).map(|r| r.1);
        let s = load_gltf_file(p).unwrap_or_else(|e| panic!("{e}"));
        s.check_invariants()
            .unwrap_or_else(|e| panic!("{rel}: {e}"));
        s.flatten()
            .triangles()
            .unwrap_or_else(|e| panic!("{rel}: {e}"));
        assert_eq!(Some(s.triangle_count()), expect, "{rel}");
        println!("{rel}: {} triangles", s.triangle_count());
    }
    let gltfs: Vec<&(String, usize)> = rows
        .iter()
        .filter(|(f, _)| f.starts_with("gltf/"))
        .collect();
    assert_eq!(gltfs.len(), 8, "SOURCES.md lists eight glTF files");
    for (rel, n) in gltfs {
        let s = load(dir.join(rel).to_str().expect("utf-8 path")).unwrap_or_else(|e| panic!("{e}"));
        s.check_invariants()
            .unwrap_or_else(|e| panic!("{rel}: {e}"));
        s.flatten()
            .triangles()
            .unwrap_or_else(|e| panic!("{rel}: {e}"));
        assert_eq!(s.triangle_count(), *n, "{rel}");
        assert!(s.attributes.normals, "{rel} has normals");
        println!(
            "{rel}: {} triangles, {} instances, warnings {:?}",
            n,
            s.instance_count(),
            s.warnings
        );
    }
}

/// Missing image files are one warning; the masked materials whose textures they were,
/// one more.
#[test]
fn missing_textures_are_one_warning() {
    let Some(dir) = common::shared("missing_textures_are_one_warning") else {
        return;
    };
    let s = load_gltf_file(&dir.join("gltf/FlightHelmet/FlightHelmet.gltf")).expect("loads");
    let count = |what: &str| s.warnings.iter().filter(|w| w.contains(what)).count();
    assert_eq!(count("image file(s) are missing"), 1, "{:?}", s.warnings);
    assert_eq!(count("masked material(s)"), 1, "{:?}", s.warnings);
    assert_eq!(count("image"), 2, "{:?}", s.warnings);
    assert!(s.attributes.texcoords && s.attributes.materials);
    assert!(s.meshes.len() > 1, "several meshes");
}

/// The glTF originals, node transforms applied, are the GLB files' triangles.
#[test]
fn gltf_originals_match_their_glb_twins() {
    let Some(dir) = common::shared("gltf_originals_match_their_glb_twins") else {
        return;
    };
    let pairs = [
        ("gltf/Box/Box.gltf", "glb/khronos_box.glb"),
        ("gltf/teapot.gltf", "glb/teapot_9k_gltf.glb"),
        ("gltf/chinesedragon.gltf", "glb/chinese_dragon.glb"),
        (
            "gltf/DamagedHelmet/DamagedHelmet.gltf",
            "glb/damaged_helmet.glb",
        ),
        (
            "gltf/FlightHelmet/FlightHelmet.gltf",
            "glb/flight_helmet.glb",
        ),
        ("gltf/drone/scene.gltf", "glb/drone.glb"),
        ("gltf/balloon/scene.gltf", "glb/balloon.glb"),
        ("gltf/smallpine/scene.gltf", "glb/smallpine.glb"),
    ];
    for (g, b) in pairs {
        let sg = load_gltf_file(&dir.join(g)).expect("gltf loads");
        let sb = load_gltf_file(&dir.join(b)).expect("glb loads");
        assert_eq!(sg.triangle_count(), sb.triangle_count(), "{g}");
        let ((lg, hg), (lb, hb)) = (sg.bounds(), sb.bounds());
        let ext = (hb - lb).max_element();
        assert!(
            lg.abs_diff_eq(lb, ext * 1e-4) && hg.abs_diff_eq(hb, ext * 1e-4),
            "{g}: bounds {lg}..{hg} vs {lb}..{hb}"
        );
        let (ag, ab) = (total_area(&sg), total_area(&sb));
        assert!((ag - ab).abs() <= ab * 1e-4, "{g}: area {ag} vs {ab}");
    }
}

#[test]
fn igea_loads_fast() {
    let Some(dir) = common::shared("igea_loads_fast") else {
        return;
    };
    let path = dir.join("glb/igea.glb");
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t = Instant::now();
        let s = load_gltf_file(&path).expect("igea loads");
        best = best.min(t.elapsed().as_secs_f64());
        assert_eq!(s.triangle_count(), 268_686);
    }
    let t = Instant::now();
    let flat = load_gltf_file(&path).expect("igea loads").flatten();
    let with_flatten = t.elapsed().as_secs_f64();
    assert_eq!(flat.len(), 268_686);
    println!(
        "igea.glb (4.8 MB, 268,686 triangles): load {:.1} ms (best of 5), load + flatten {:.1} ms{}",
        best * 1e3,
        with_flatten * 1e3,
        if cfg!(debug_assertions) {
            " [debug build: run with --release for the real figure]"
        } else {
            ""
        }
    );
    if !cfg!(debug_assertions) {
        assert!(best < 0.5, "igea took {best} s to load");
    }
}

#[test]
fn grid_of_igea_is_instanced_and_large() {
    let Some(dir) = common::shared("grid_of_igea_is_instanced_and_large") else {
        return;
    };
    // Only from the folder named: the library looks in no other.
    assert!(
        load("builtin:grid:igea:3x3").is_err(),
        "igea is not in the repository"
    );
    let opts = bvhtrace_scene::LoadOptions::with_meshes(Some(dir.clone()));
    let s = bvhtrace_scene::load_with("builtin:grid:igea:3x3", &opts).expect("grid loads");
    assert!(s.synthetic && s.description.contains("synthetic"));
    assert_eq!(s.meshes.len(), 1);
    assert_eq!(s.instance_count(), 9);
    assert_eq!(s.triangle_count(), 9 * 268_686);
    assert!(s.triangle_count() > 2_000_000);
    let flat = s.flatten();
    assert_eq!(flat.len(), s.triangle_count());
    // The copies do not all sit on top of each other.
    let (lo, hi) = s.bounds();
    let one = load_gltf_file(&dir.join("glb/igea.glb")).expect("igea");
    let (l1, h1) = one.bounds();
    assert!((hi - lo).x > 2.5 * (h1 - l1).x);
}
