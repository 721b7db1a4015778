//! Build times on the shared scenes: the default binned SAH (flat layout) and the CPU
//! layout's conversion, medians of RUNS: `cargo run --release -p bvhtrace-cpu --example
//! buildspeed -- [RUNS]`. `bench-build --embree` puts Embree's build beside it. The hashes
//! show whether a change to the builder or the conversion changed the tree or the layout.

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
        let (mut tree_hash, mut layout_hash) = (0, 0);
        for run in 0..runs {
            let t = Instant::now();
            let flat = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
            build.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            let cpu = std::hint::black_box(CpuBvh::from_flat(&flat).expect("converts"));
            convert.push(t.elapsed().as_secs_f64() * 1e3);
            if run == 0 {
                (tree_hash, layout_hash) = (hash_of(&flat), layout_hash_of(&cpu));
            }
        }
        build.sort_by(f64::total_cmp);
        convert.sort_by(f64::total_cmp);
        println!(
            "{name}: {} tris, build {:.1} ms, CPU layout {:.1} ms (medians of {runs}), tree {tree_hash:016x}, layout {layout_hash:016x}",
            tris.len(),
            build[runs / 2],
            convert[runs / 2]
        );
    }
}

/// A hash of the CPU layout's nodes, blocks and every block's leaf boxes.
fn layout_hash_of(cpu: &CpuBvh) -> u64 {
    use std::hash::{DefaultHasher, Hasher};
    let mut h = DefaultHasher::new();
    for n in cpu.nodes() {
        h.write(format!("{n:?}").as_bytes());
    }
    for (b, block) in cpu.blocks().iter().enumerate() {
        h.write(format!("{block:?}").as_bytes());
        for lane in 0..4 {
            h.write(format!("{:?}", cpu.leaf_box(b, lane)).as_bytes());
        }
    }
    h.finish()
}

/// A hash of the tree's nodes and triangle order: a change to the builder that should
/// give the same tree shows the same hash.
fn hash_of(flat: &FlatBvh) -> u64 {
    use std::hash::{DefaultHasher, Hasher};
    let mut h = DefaultHasher::new();
    h.write(bytemuck::cast_slice(flat.nodes()));
    h.write(bytemuck::cast_slice(flat.triangles()));
    h.finish()
}
