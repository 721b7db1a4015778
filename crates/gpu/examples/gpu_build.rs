//! The BVH built on the device against the CPU's binned SAH build, on the same cores.
//!
//! ```text
//! cargo run --release -p bvhtrace-gpu --example gpu_build -- [SCENE...] [--runs N]
//! ```
//!
//! SCENE is any `bvhtrace_scene::load` spec (flattened to world triangles); the default is
//! `bunny_69k` and `igea` from the shared scenes. For each: the device's linear BVH
//! (`GpuContext::build_lbvh`: upload, dispatches, read back) and the CPU's binned SAH
//! build (`FlatBvh::build`, all cores), `N` times each (default 5), interleaved; median
//! milliseconds and Mtris/s, and the SAH cost of both trees (`BvhStats`, traversal and
//! intersection cost 1). The first device build, which compiles the pipelines, is not
//! counted.

use std::time::Instant;

use bvhtrace_core::{BuildOptions, BvhStats, FlatBvh};
use bvhtrace_gpu::{AdapterChoice, GpuContext};
use bvhtrace_scene::shared_scenes_dir;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut specs = Vec::new();
    let mut runs = 5usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--runs" => runs = args.next().ok_or("--runs needs N")?.parse()?,
            "-h" | "--help" => {
                println!("gpu_build [SCENE...] [--runs N]");
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
        "{:28} {:>10} {:>10} {:>9} {:>9} {:>9} {:>10} {:>9} {:>9}",
        "scene",
        "triangles",
        "device ms",
        "(build)",
        "Mtris/s",
        "SAH",
        "CPU SAH ms",
        "Mtris/s",
        "SAH"
    );
    for spec in &specs {
        let tris = bvhtrace_scene::load(spec)?.flattened_triangles()?;
        ctx.build_lbvh(&tris)?;
        let (mut device, mut dispatch, mut cpu) = (Vec::new(), Vec::new(), Vec::new());
        let (mut lbvh, mut sah) = (None, None);
        for _ in 0..runs {
            let t = Instant::now();
            let (bvh, times) = ctx.build_lbvh(&tris)?;
            device.push(t.elapsed().as_secs_f64() * 1e3);
            dispatch.push(times.build_ms);
            lbvh = Some(bvh);
            let t = Instant::now();
            sah = Some(FlatBvh::build(&tris, &BuildOptions::default())?);
            cpu.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let n = tris.len() as f64;
        if let Some(stages) = ctx.build_lbvh(&tris)?.1.stages_ms {
            let parts: Vec<String> = bvhtrace_gpu::GpuBuildTimes::STAGES
                .iter()
                .zip(stages)
                .map(|(name, ms)| format!("{name} {ms:.1}"))
                .collect();
            println!("  device steps, ms: {}", parts.join(", "));
        }
        let (lbvh, sah) = (lbvh.ok_or("no run")?, sah.ok_or("no run")?);
        let (d, c) = (median(device), median(cpu));
        let name = std::path::Path::new(spec)
            .file_name()
            .map_or(spec.clone(), |f| f.to_string_lossy().into_owned());
        println!(
            "{:28} {:>10} {:>10.1} {:>9.1} {:>9.2} {:>9.2} {:>10.1} {:>9.2} {:>9.2}",
            name,
            tris.len(),
            d,
            median(dispatch),
            n / d / 1e3,
            BvhStats::of(&lbvh).sah_cost,
            c,
            n / c / 1e3,
            BvhStats::of(&sah).sah_cost,
        );
    }
    Ok(())
}
