//! The BVHs built on the device against the CPU's binned SAH build, on the same cores.
//!
//! ```text
//! cargo run --release -p bvhtrace-gpu --example gpu_build -- [SCENE...] [--runs N] [--radius R]
//! ```
//!
//! SCENE is any `bvhtrace_scene::load` spec (flattened to world triangles); the default is
//! `bunny_69k` and `igea` from the shared scenes. For each: each device builder
//! (`GpuContext::build_bvh`: upload, dispatches, read back) and the CPU's binned SAH
//! build (`FlatBvh::build`, all cores), `N` times each (default 5), interleaved; median
//! milliseconds and Mtris/s, the SAH cost of each tree (`BvhStats`: traversal and
//! intersection cost 1, then PBRT's 1/8 and 1, the builders' own rule) and its ratio to
//! the CPU tree's. The first device build, which
//! compiles the pipelines, is not counted. `--radius` sets the clustering's search radius.

use std::time::Instant;

use bvhtrace_core::{BuildOptions, BvhStats, FlatBvh};
use bvhtrace_gpu::{AdapterChoice, GpuBuildOptions, GpuBuilderKind, GpuContext};
use bvhtrace_scene::shared_scenes_dir;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut specs = Vec::new();
    let mut runs = 5usize;
    let mut radius = GpuBuildOptions::default().radius;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--runs" => runs = args.next().ok_or("--runs needs N")?.parse()?,
            "--radius" => radius = args.next().ok_or("--radius needs R")?.parse()?,
            "-h" | "--help" => {
                println!("gpu_build [SCENE...] [--runs N] [--radius R]");
                return Ok(());
            }
            s => specs.push(s.to_string()),
        }
    }
    if runs == 0 {
        return Err("--runs must be at least 1".into());
    }
    if specs.is_empty() {
        let dir = shared_scenes_dir().ok_or("no SCENE given and no shared scenes folder")?;
        for f in ["bunny_69k.glb", "igea.glb"] {
            specs.push(dir.join("glb").join(f).to_string_lossy().into_owned());
        }
    }
    let ctx = GpuContext::new(AdapterChoice::Auto)?;
    println!(
        "adapter: {} ({:?}); CPU: {} threads",
        ctx.adapter_info().name,
        ctx.adapter_info().device_type,
        rayon::current_num_threads()
    );
    println!(
        "{:28} {:>10} {:>9} {:>10} {:>9} {:>9} {:>9} {:>7} {:>9} {:>7}",
        "scene",
        "triangles",
        "builder",
        "ms",
        "(build)",
        "Mtris/s",
        "SAH",
        "xCPU",
        "SAH 1/8",
        "xCPU"
    );
    for spec in &specs {
        let opts = bvhtrace_scene::LoadOptions::with_meshes(bvhtrace_scene::shared_scenes_dir());
        let tris = bvhtrace_scene::load_with(spec, &opts)?.flattened_triangles()?;
        let name = std::path::Path::new(spec)
            .file_name()
            .map_or(spec.clone(), |f| f.to_string_lossy().into_owned());
        let n = tris.len() as f64;
        let mut cpu = Vec::new();
        let mut sah = None;
        for _ in 0..runs {
            let t = Instant::now();
            sah = Some(FlatBvh::build(&tris, &BuildOptions::default())?);
            cpu.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let cpu_stats = BvhStats::of(&sah.ok_or("no run")?);
        let (cpu_sah, cpu_pbrt) = (cpu_stats.sah_cost, cpu_stats.sah_cost_pbrt);
        let c = median(cpu);
        println!(
            "{:28} {:>10} {:>9} {:>10.1} {:>9} {:>9.2} {:>9.2} {:>7.3} {:>9.2} {:>7.3}",
            name,
            tris.len(),
            "cpu-sah",
            c,
            "",
            n / c / 1e3,
            cpu_sah,
            1.0,
            cpu_pbrt,
            1.0
        );
        for kind in GpuBuilderKind::ALL {
            let opts = GpuBuildOptions {
                radius,
                ..GpuBuildOptions::with_builder(kind)
            };
            let (_, first) = ctx.build_bvh(&tris, &opts)?;
            let (mut device, mut dispatch) = (Vec::new(), Vec::new());
            let mut tree = None;
            for _ in 0..runs {
                let t = Instant::now();
                let (bvh, times) = ctx.build_bvh(&tris, &opts)?;
                device.push(t.elapsed().as_secs_f64() * 1e3);
                dispatch.push(times.build_ms);
                tree = Some(bvh);
            }
            let d = median(device);
            let stats = BvhStats::of(&tree.ok_or("no run")?);
            let (s, p) = (stats.sah_cost, stats.sah_cost_pbrt);
            println!(
                "{:28} {:>10} {:>9} {:>10.1} {:>9.1} {:>9.2} {:>9.2} {:>7.3} {:>9.2} {:>7.3}",
                name,
                tris.len(),
                kind.name(),
                d,
                median(dispatch),
                n / d / 1e3,
                s,
                s / cpu_sah,
                p,
                p / cpu_pbrt
            );
            let parts: Vec<String> = first
                .stages_ms
                .iter()
                .map(|(step, ms)| format!("{step} {ms:.1}"))
                .collect();
            if !parts.is_empty() {
                println!("  device steps, ms: {}", parts.join(", "));
            }
            if first.iterations > 0 {
                println!("  {} iterations", first.iterations);
            }
        }
    }
    Ok(())
}
