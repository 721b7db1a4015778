//! Loads scene specs and prints what they hold: `cargo run --release -p bvhtrace-scene
//! --example scene_info -- SPEC...` (no argument: the default scene and every builtin).

use std::time::Instant;

fn main() {
    let mut specs: Vec<String> = std::env::args().skip(1).collect();
    if specs.is_empty() {
        specs.push(bvhtrace_scene::DEFAULT_SCENE.to_string());
        specs.extend(
            [
                "builtin:spheres",
                "builtin:icosphere:3",
                "builtin:degenerate",
            ]
            .map(String::from),
        );
    }
    for spec in specs {
        let t = Instant::now();
        match bvhtrace_scene::load(&spec) {
            Ok(s) => {
                let ms = t.elapsed().as_secs_f64() * 1e3;
                let (lo, hi) = s.bounds();
                println!(
                    "{spec}: {} triangles, {} instances of {} meshes, {} materials, {:?}, camera {:?}, bounds {lo} .. {hi}, loaded in {ms:.1} ms{}",
                    s.triangle_count(),
                    s.instance_count(),
                    s.meshes.len(),
                    s.materials.len(),
                    s.attributes,
                    s.camera,
                    if s.synthetic { " (synthetic)" } else { "" },
                );
                for w in &s.warnings {
                    println!("  warning: {w}");
                }
            }
            Err(e) => println!("error: {e}"),
        }
    }
}
