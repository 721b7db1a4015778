//! Traversal speed on the GPU against the CPU twins, on primary rays.
//!
//! ```text
//! cargo run --release -p bvhtrace-gpu --example gpu_bench -- [SCENE...] [--size WxH] [--runs N]
//! ```
//!
//! SCENE is any `bvhtrace_scene::load` spec; the default is `bunny_69k` and `igea` from the
//! shared scenes. For each scene: a camera framing the mesh, W x H primary rays (default
//! 1024x768), closest hit, each traversal traced `N` times (default 5) on the GPU with the
//! BVH in textures and in buffers (`--storage textures|buffers|both`; median Mrays/s of the
//! timestamp-query times and of the wall times) and on the CPU (`trace_rays`, all cores),
//! interleaved; nodes and triangles tested per ray, and whether every GPU hit and counter
//! equals the CPU twin's. `--traversals full-stack,stackless,short-stack:6,wide` picks them
//! (`wide` uploads the wide layout too, in the same storage); `--best` reports the best run
//! instead of the median (steadier on a shared machine). `--in-flight N` sets the
//! submissions a trace keeps in flight (`DriverTuning::in_flight`; the device's default
//! otherwise).

use std::time::Instant;

use bvhtrace_core::{BuildOptions, FlatBvh, Query, TraceOptions, Traversal, trace_rays};
use bvhtrace_gpu::{
    AdapterChoice, BvhStorage, ContextOptions, DriverTuning, GpuBvh, GpuContext, Tracer,
    UploadOptions,
};
use bvhtrace_scene::{Camera, shared_scenes_dir};

/// The median time, or the best (smallest) with `--best`: on a shared machine the best of
/// several interleaved runs is the one least disturbed by neighbours.
fn pick(mut v: Vec<f64>, best: bool) -> f64 {
    v.sort_by(f64::total_cmp);
    if best { v[0] } else { v[v.len() / 2] }
}

fn load_avg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

/// What the command line asks for.
struct Options {
    /// The scenes, as `bvhtrace_scene::load` takes them.
    specs: Vec<String>,
    /// Primary rays, `w` x `h`.
    w: u32,
    h: u32,
    /// Timed runs per traversal.
    runs: usize,
    /// The best run instead of the median.
    best: bool,
    /// The walks timed.
    traversals: Vec<Traversal>,
    /// Where the BVH is uploaded: each is a column pair.
    storages: Vec<BvhStorage>,
    /// `DriverTuning::in_flight`, when given.
    in_flight: Option<u32>,
}

impl Options {
    fn parse() -> Result<Options, Box<dyn std::error::Error>> {
        let mut o = Options {
            specs: Vec::new(),
            w: 1024,
            h: 768,
            runs: 5,
            best: false,
            traversals: vec![
                Traversal::FullStack,
                Traversal::Stackless,
                Traversal::ShortStack(2),
                Traversal::ShortStack(6),
                Traversal::ShortStack(12),
            ],
            storages: vec![BvhStorage::Textures, BvhStorage::Buffers],
            in_flight: None,
        };
        let mut args = std::env::args().skip(1);
        while let Some(a) = args.next() {
            match a.as_str() {
                "--size" => {
                    let v = args.next().ok_or("--size needs WxH")?;
                    let (a, b) = v.split_once('x').ok_or("--size needs WxH")?;
                    (o.w, o.h) = (a.parse()?, b.parse()?);
                }
                "--runs" => o.runs = args.next().ok_or("--runs needs N")?.parse()?,
                "--best" => o.best = true,
                "--in-flight" => {
                    o.in_flight = Some(args.next().ok_or("--in-flight needs N")?.parse()?)
                }
                "--storage" => {
                    o.storages = match args.next().as_deref() {
                        Some("buffers") => vec![BvhStorage::Buffers],
                        Some("textures") => vec![BvhStorage::Textures],
                        Some("both") => vec![BvhStorage::Textures, BvhStorage::Buffers],
                        _ => return Err("--storage needs buffers, textures or both".into()),
                    }
                }
                "--traversals" => {
                    o.traversals = args
                        .next()
                        .ok_or("--traversals needs a list")?
                        .split(',')
                        .map(|t| t.parse::<Traversal>())
                        .collect::<Result<Vec<_>, _>>()?;
                }
                _ => o.specs.push(a),
            }
        }
        if o.specs.is_empty() {
            let dir =
                shared_scenes_dir().ok_or("no shared scenes folder; name scenes explicitly")?;
            for f in ["bunny_69k.glb", "igea.glb"] {
                o.specs
                    .push(dir.join("glb").join(f).to_string_lossy().into_owned());
            }
        }
        Ok(o)
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let o = Options::parse()?;
    let mut ctx = GpuContext::new(AdapterChoice::Auto)?;
    if let Some(in_flight) = o.in_flight {
        let tuning = DriverTuning {
            in_flight,
            ..*ctx.tuning()
        };
        let options = ContextOptions {
            tuning: Some(tuning),
            ..Default::default()
        };
        ctx = GpuContext::new_with(AdapterChoice::Auto, &options)?;
    }
    println!(
        "device: {} ({:?}, {}); CPU threads: {}; load average at start: {}",
        ctx.adapter_info().name,
        ctx.adapter_info().device_type,
        ctx.adapter_info().driver_info,
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        load_avg()
    );
    for spec in &o.specs {
        bench_scene(&ctx, &o, spec)?;
    }
    println!("\nload average at end: {}", load_avg());
    Ok(())
}

/// One scene: its tree uploaded in each storage, the table's head, a row per traversal.
fn bench_scene(
    ctx: &GpuContext,
    o: &Options,
    spec: &str,
) -> Result<(), Box<dyn std::error::Error>> {
    let (w, h) = (o.w, o.h);
    let opts = bvhtrace_scene::LoadOptions::with_meshes(bvhtrace_scene::shared_scenes_dir());
    let scene = bvhtrace_scene::load_with(spec, &opts)?;
    let tris = scene.flatten().triangles()?;
    let mut bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
    let wide = o.traversals.iter().any(|t| t.is_wide());
    if wide {
        bvh.build_wide();
    }
    let b = bvh.bounds();
    let rays = Camera::frame(b.min, b.max, w as f32 / h as f32).rays(w, h);
    let upload = |st| {
        let opts = UploadOptions::all().with_storage(st);
        if wide {
            opts.with_traversal(Traversal::Wide)
        } else {
            opts
        }
    };
    let gpus = (o.storages.iter())
        .map(|&st| GpuBvh::upload(ctx, &bvh, &upload(st)))
        .collect::<Result<Vec<_>, _>>()?;
    let name = std::path::Path::new(spec)
        .file_stem()
        .map_or(spec.to_string(), |s| s.to_string_lossy().into_owned());
    println!(
        "\n{name}: {} triangles, {} nodes, depth {}; {}x{} primary rays",
        bvh.triangles().len(),
        bvh.nodes().len(),
        bvh.depth(),
        w,
        h,
    );
    for g in &gpus {
        println!(
            "  upload ({:?}): {:.1} MB in {:.1} ms",
            g.tree().storage,
            g.stats().total_bytes() as f64 / 1e6,
            g.stats().upload_ms
        );
    }
    print!("{:<16}", "traversal");
    for g in &gpus {
        let s = format!("{:?}", g.tree().storage).to_lowercase();
        print!(" {:>13} {:>13}", format!("{s} GPU"), format!("{s} wall"));
    }
    println!(
        " {:>10} {:>8} {:>8} {:>8}",
        "CPU", "nodes/r", "tris/r", "GPU=CPU"
    );
    for &traversal in &o.traversals {
        bench_walk(o, &bvh, &rays, &gpus, traversal)?;
    }
    Ok(())
}

/// One traversal's row: checked against the CPU twin (hits and counters), then timed
/// `o.runs` times on every upload and on the CPU, interleaved.
fn bench_walk(
    o: &Options,
    bvh: &FlatBvh,
    rays: &[bvhtrace_core::Ray],
    gpus: &[GpuBvh],
    traversal: Traversal,
) -> Result<(), Box<dyn std::error::Error>> {
    let n = rays.len() as f64;
    let mrays = |ms: f64| n / ms / 1e3;
    let q = Query::Closest;
    let opts = TraceOptions::new(traversal, q);
    let counted_opts = opts.with_counters(true);
    let cpu = trace_rays(bvh, rays, &counted_opts);
    let (cpu_hits, cpu_counters) = (cpu.hits, cpu.counters.unwrap_or_default());
    let mut same = true;
    for gpu in gpus {
        // Warm-up (pipeline creation, lavapipe's first-dispatch cost) and checks.
        let counted = gpu.trace(rays, &counted_opts)?;
        same &= counted.hits == cpu_hits && counted.counters.as_deref() == Some(&cpu_counters[..]);
        gpu.trace(rays, &opts)?;
    }
    let nodes = cpu_counters.iter().map(|c| u64::from(c.nodes)).sum::<u64>() as f64 / n;
    let tris_per = cpu_counters.iter().map(|c| u64::from(c.tris)).sum::<u64>() as f64 / n;
    let mut g = vec![Vec::new(); gpus.len()];
    let mut wall = vec![Vec::new(); gpus.len()];
    let mut cpu = Vec::new();
    // Interleaved, so that a noisy neighbour hurts every column alike.
    for _ in 0..o.runs {
        for (i, gpu) in gpus.iter().enumerate() {
            let out = gpu.trace(rays, &opts)?;
            g[i].push(out.gpu_ms.unwrap_or(f64::NAN));
            wall[i].push(out.wall_ms);
        }
        let t = Instant::now();
        std::hint::black_box(trace_rays(bvh, rays, &opts));
        cpu.push(t.elapsed().as_secs_f64() * 1e3);
    }
    print!("{:<16}", traversal.to_string());
    for i in 0..gpus.len() {
        print!(
            " {:>13.2} {:>13.2}",
            mrays(pick(g[i].clone(), o.best)),
            mrays(pick(wall[i].clone(), o.best))
        );
    }
    println!(
        " {:>10.2} {:>8.1} {:>8.2} {:>8}",
        mrays(pick(cpu, o.best)),
        nodes,
        tris_per,
        if same { "yes" } else { "NO" }
    );
    Ok(())
}
