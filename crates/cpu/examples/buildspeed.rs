//! Build times on the shared scenes: the default binned SAH (flat layout) and the CPU
//! layout's conversion, medians of RUNS: `cargo run --release -p bvhtrace-cpu --example
//! buildspeed -- [RUNS]`. `bench-build --embree` puts Embree's build beside it.

use std::time::Instant;

use bvhtrace_core::{BuildOptions, FlatBvh};
use bvhtrace_cpu::CpuBvh;

fn main() {
    let runs: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(21);
    let Some(dir) = bvhtrace_scene::shared_scenes_dir() else {
        eprintln!("no shared scenes");
        return;
    };
    for name in ["bunny_69k", "igea"] {
        let path = dir.join("glb").join(format!("{name}.glb"));
        let Ok(scene) = bvhtrace_scene::load(&path.display().to_string()) else {
            continue;
        };
        let Ok(tris) = scene.flattened_triangles() else {
            continue;
        };
        let (mut build, mut convert) = (Vec::new(), Vec::new());
        for _ in 0..runs {
            let t = Instant::now();
            let flat = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
            build.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            std::hint::black_box(CpuBvh::from_flat(&flat).expect("converts"));
            convert.push(t.elapsed().as_secs_f64() * 1e3);
        }
        build.sort_by(f64::total_cmp);
        convert.sort_by(f64::total_cmp);
        println!(
            "{name}: {} tris, build {:.1} ms, CPU layout {:.1} ms (medians of {runs})",
            tris.len(),
            build[runs / 2],
            convert[runs / 2]
        );
    }
}
