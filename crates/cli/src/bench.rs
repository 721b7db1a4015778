//! `bvhtrace bench-build` and `bvhtrace bench-trace`: figures as commands, not tests.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace_core::{
    BuildOptions, BuilderKind, BvhStats, FlatBvh, Query, Ray, Traversal, Triangle, trace_batch,
    trace_batch_counted,
};
use bvhtrace_gpu::{
    AdapterChoice, Composition, GpuBvh, GpuContext, PipelineFeatures, TraceOptions, UploadOptions,
    VertexAttributes, kernel_source,
};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The scenes to use: those given, else `bunny_69k` and `igea` from the shared folder.
pub(crate) fn scene_specs(given: &[String]) -> Result<Vec<String>> {
    if !given.is_empty() {
        return Ok(given.to_vec());
    }
    let dir = bvhtrace_scene::shared_scenes_dir()
        .context("no scenes given and no shared scenes folder found (set BVHTRACE_SCENES)")?;
    Ok(["bunny_69k", "igea"]
        .iter()
        .map(|n| {
            dir.join("glb")
                .join(format!("{n}.glb"))
                .display()
                .to_string()
        })
        .collect())
}

fn load(spec: &str) -> Result<(Vec<Triangle>, bvhtrace_scene::Scene, f64)> {
    let t = Instant::now();
    let scene = bvhtrace_scene::load(spec)?;
    let tris = scene
        .flatten()
        .triangles()
        .with_context(|| format!("{spec}: bad geometry"))?;
    Ok((tris, scene, t.elapsed().as_secs_f64() * 1e3))
}

fn primary_rays(scene: &bvhtrace_scene::Scene, w: u32, h: u32) -> Vec<Ray> {
    scene.camera_or_frame(w as f32 / h as f32).rays(w, h)
}

/// `bvhtrace bench-build`.
#[derive(clap::Args)]
pub struct BenchBuildArgs {
    /// Scenes (default: bunny_69k and igea from ../shared/scenes).
    pub scenes: Vec<String>,
    /// Timed builds per configuration (the median is printed).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Primary rays for the CPU traversal figures, WxH.
    #[arg(long, default_value = "1024x768")]
    pub size: String,
}

/// `bvhtrace bench-build`.
pub fn bench_build(args: BenchBuildArgs) -> Result<()> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads.unwrap_or(0))
        .build()?;
    let (w, h) = args
        .size
        .split_once('x')
        .and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)))
        .context("--size must be WxH")?;
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let configs: Vec<(String, BuildOptions)> = BuilderKind::ALL
        .iter()
        .map(|&b| (b.name().to_string(), BuildOptions::with_builder(b)))
        .chain([4usize, 8, 16].map(|bins| {
            (
                format!("sah bins={bins}"),
                BuildOptions {
                    bins,
                    ..Default::default()
                },
            )
        }))
        .chain([BuilderKind::Sah, BuilderKind::SweepSah].map(|b| {
            (
                format!("{} ctrav=1", b.name()),
                BuildOptions {
                    cost_traversal: 1.0,
                    ..BuildOptions::with_builder(b)
                },
            )
        }))
        .collect();
    println!("threads: {}", pool.current_num_threads());
    for spec in scene_specs(&args.scenes)? {
        let (tris, scene, load_ms) = load(&spec)?;
        let rays = primary_rays(&scene, w, h);
        println!(
            "\n{spec}: {} triangles, loaded in {load_ms:.1} ms; {} primary rays ({w}x{h})",
            tris.len(),
            rays.len()
        );
        println!(
            "{:16} {:>9} {:>8} {:>8} {:>8} {:>5} | {:>22} {:>22} {:>22}",
            "builder",
            "build ms",
            "SAH(1,1)",
            "SAH pbrt",
            "nodes",
            "depth",
            "full-stack Mr/s n/ray",
            "stackless Mr/s n/ray",
            "short-stack Mr/s n/ray"
        );
        for (name, opts) in &configs {
            let runs = if opts.builder == BuilderKind::SweepSah {
                args.runs.min(3)
            } else {
                args.runs
            };
            let mut times = Vec::new();
            let mut bvh = None;
            for _ in 0..runs {
                let t = Instant::now();
                let b = pool.install(|| FlatBvh::build(&tris, opts))?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
                bvh = Some(b);
            }
            let bvh = bvh.context("no build ran")?;
            let s = BvhStats::of(&bvh);
            let mut cols = Vec::new();
            for tr in [
                Traversal::FullStack,
                Traversal::Stackless,
                Traversal::ShortStack(6),
            ] {
                let (_, c) = pool.install(|| trace_batch_counted(&bvh, &rays, tr, Query::Closest));
                let nodes = c.iter().map(|c| c.nodes as f64).sum::<f64>() / rays.len() as f64;
                let t = median(
                    (0..3)
                        .map(|_| {
                            let t = Instant::now();
                            pool.install(|| trace_batch(&bvh, &rays, tr, Query::Closest));
                            t.elapsed().as_secs_f64()
                        })
                        .collect(),
                );
                cols.push(format!(
                    "{:>13.2} {:>8.1}",
                    rays.len() as f64 / t / 1e6,
                    nodes
                ));
            }
            println!(
                "{:16} {:>9.1} {:>8.2} {:>8.3} {:>8} {:>5} | {:>22} {:>22} {:>22}",
                name,
                median(times),
                s.sah_cost,
                s.sah_cost_pbrt,
                s.nodes,
                s.depth,
                cols[0],
                cols[1],
                cols[2]
            );
        }
    }
    Ok(())
}

/// `bvhtrace bench-trace`.
#[derive(clap::Args)]
pub struct BenchTraceArgs {
    /// Scenes (default: bunny_69k and igea from ../shared/scenes).
    pub scenes: Vec<String>,
    /// Timed runs per configuration (the median is printed).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Primary rays, WxH.
    #[arg(long, default_value = "1024x768")]
    pub size: String,
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// Also trace any-hit (occlusion) queries on the same rays.
    #[arg(long)]
    pub any_hit: bool,
    /// Instead, compare each traversal's specialised pipeline (only the bindings and code
    /// the closest-hit job reads) with the everything-on one (every module composed, the
    /// parent links uploaded, counters written): bytes uploaded per triangle, pipeline
    /// creation time, Mrays/s.
    #[arg(long)]
    pub everything_on: bool,
}

/// `bvhtrace bench-trace`.
pub fn bench_trace(args: BenchTraceArgs) -> Result<()> {
    let (w, h) = args
        .size
        .split_once('x')
        .and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)))
        .context("--size must be WxH")?;
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let ctx = GpuContext::new(match &args.adapter {
        Some(n) => AdapterChoice::Named(n.clone()),
        None => AdapterChoice::Auto,
    })?;
    let info = ctx.adapter_info();
    println!(
        "adapter: {} ({:?}); CPU: {} threads",
        info.name,
        info.device_type,
        rayon::current_num_threads()
    );
    if args.everything_on {
        return compare_everything_on(&ctx, &args, w, h);
    }
    let traversals = [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(2),
        Traversal::ShortStack(4),
        Traversal::ShortStack(6),
        Traversal::ShortStack(8),
    ];
    let queries: &[Query] = if args.any_hit {
        &[Query::Closest, Query::Any]
    } else {
        &[Query::Closest]
    };
    for spec in scene_specs(&args.scenes)? {
        let (tris, scene, _) = load(&spec)?;
        let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
        let rays = primary_rays(&scene, w, h);
        let gpu = GpuBvh::upload(&ctx, &bvh, &UploadOptions::all())?;
        println!(
            "\n{spec}: {} triangles, depth {}, {} rays ({w}x{h})",
            tris.len(),
            bvh.depth,
            rays.len()
        );
        println!(
            "{:16} {:8} {:>12} {:>12} {:>10} {:>8} {:>8} {:>10} {:>9}",
            "traversal",
            "query",
            "GPU Mr/s",
            "GPU wall",
            "CPU Mr/s",
            "nodes",
            "tris",
            "vs full",
            "GPU/CPU"
        );
        for &q in queries {
            let mut full_nodes = None;
            for tr in traversals {
                let counted = gpu.trace_counted(&rays, tr, q)?;
                let c = counted.counters.unwrap_or_default();
                let nodes =
                    c.iter().map(|c| c.nodes as f64).sum::<f64>() / rays.len().max(1) as f64;
                let tris_ = c.iter().map(|c| c.tris as f64).sum::<f64>() / rays.len().max(1) as f64;
                let full = *full_nodes.get_or_insert(nodes);
                let mut gpu_ms = Vec::new();
                let mut wall_ms = Vec::new();
                for _ in 0..args.runs {
                    let o = gpu.trace(&rays, tr, q)?;
                    wall_ms.push(o.wall_ms);
                    gpu_ms.push(o.gpu_ms.unwrap_or(o.wall_ms));
                }
                let cpu_s = median(
                    (0..args.runs)
                        .map(|_| {
                            let t = Instant::now();
                            trace_batch(&bvh, &rays, tr, q);
                            t.elapsed().as_secs_f64()
                        })
                        .collect(),
                );
                let n = rays.len() as f64;
                let (g, gw) = (n / median(gpu_ms) / 1e3, n / median(wall_ms) / 1e3);
                let cpu = n / cpu_s / 1e6;
                println!(
                    "{:16} {:8} {:>12.2} {:>12.2} {:>10.2} {:>8.1} {:>8.2} {:>9.2}x {:>8.2}x",
                    tr.to_string(),
                    format!("{q:?}").to_lowercase(),
                    g,
                    gw,
                    cpu,
                    nodes,
                    tris_,
                    nodes / full,
                    g / cpu
                );
            }
        }
    }
    Ok(())
}

/// One side of `bench-trace --everything-on`.
struct Side {
    name: &'static str,
    composition: Composition,
    gpu: GpuBvh,
    opts: TraceOptions,
    wgsl_bytes: usize,
    bindings: usize,
    create_ms: Vec<f64>,
    gpu_ms: Vec<f64>,
    wall_ms: Vec<f64>,
}

/// `bvhtrace bench-trace --everything-on`: per scene and traversal, the specialised
/// closest-hit pipeline against the everything-on one, on the same rays; the two sides'
/// runs are interleaved, and their hits must be equal.
fn compare_everything_on(ctx: &GpuContext, args: &BenchTraceArgs, w: u32, h: u32) -> Result<()> {
    let storage = ctx.default_storage();
    println!(
        "storage: {storage:?}; {} runs per figure (medians)",
        args.runs
    );
    for spec in scene_specs(&args.scenes)? {
        let (tris, scene, _) = load(&spec)?;
        let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
        let rays = primary_rays(&scene, w, h);
        println!(
            "\n{spec}: {} triangles, {} nodes, {} rays ({w}x{h})",
            tris.len(),
            bvh.nodes.len(),
            rays.len()
        );
        println!(
            "{:14} {:14} {:>8} {:>9} {:>10} {:>10} {:>9} {:>9} {:>9}",
            "traversal",
            "pipeline",
            "bindings",
            "WGSL KiB",
            "upload MB",
            "bytes/tri",
            "create ms",
            "GPU Mr/s",
            "wall Mr/s"
        );
        for tr in [
            Traversal::FullStack,
            Traversal::Stackless,
            Traversal::ShortStack(6),
        ] {
            let job = PipelineFeatures::for_job(
                storage,
                tr,
                Query::Closest,
                false,
                VertexAttributes::NONE,
                VertexAttributes::NONE,
            );
            let all = job.with_composition(Composition::EverythingOn);
            let mut sides = [
                Side {
                    name: "specialised",
                    composition: Composition::Specialised,
                    gpu: GpuBvh::upload(ctx, &bvh, &job.upload_options())?,
                    opts: TraceOptions {
                        traversal: tr,
                        query: Query::Closest,
                        counters: false,
                    },
                    wgsl_bytes: job.source().len(),
                    bindings: job.bindings().len(),
                    create_ms: Vec::new(),
                    gpu_ms: Vec::new(),
                    wall_ms: Vec::new(),
                },
                Side {
                    name: "everything-on",
                    composition: Composition::EverythingOn,
                    gpu: GpuBvh::upload(ctx, &bvh, &UploadOptions::all().with_storage(storage))?,
                    opts: TraceOptions {
                        traversal: tr,
                        query: Query::Closest,
                        counters: true,
                    },
                    wgsl_bytes: kernel_source(storage).len(),
                    bindings: all.bindings().len(),
                    create_ms: Vec::new(),
                    gpu_ms: Vec::new(),
                    wall_ms: Vec::new(),
                },
            ];
            // Pipeline creation (module + pipeline, nothing cached), interleaved.
            for _ in 0..args.runs {
                for s in sides.iter_mut() {
                    ctx.set_composition(s.composition);
                    ctx.clear_pipeline_cache()?;
                    let t = Instant::now();
                    s.gpu.prepare(&s.opts)?;
                    s.create_ms.push(t.elapsed().as_secs_f64() * 1e3);
                }
            }
            // Both pipelines compiled once more and kept; one untimed trace each.
            let mut hits = Vec::new();
            for s in sides.iter_mut() {
                ctx.set_composition(s.composition);
                s.gpu.prepare(&s.opts)?;
                hits.push(s.gpu.trace_with(&rays, &s.opts)?.hits);
            }
            if hits[0] != hits[1] {
                bail!("{spec} {tr}: the specialised and everything-on pipelines disagree");
            }
            for _ in 0..args.runs {
                for s in sides.iter_mut() {
                    ctx.set_composition(s.composition);
                    let o = s.gpu.trace_with(&rays, &s.opts)?;
                    s.wall_ms.push(o.wall_ms);
                    s.gpu_ms.push(o.gpu_ms.unwrap_or(o.wall_ms));
                }
            }
            ctx.set_composition(Composition::Specialised);
            let n = rays.len() as f64;
            for s in &sides {
                let bytes = s.gpu.stats().total_bytes();
                println!(
                    "{:14} {:14} {:>8} {:>9.1} {:>10.2} {:>10.1} {:>9.1} {:>9.2} {:>9.2}",
                    tr.to_string(),
                    s.name,
                    s.bindings,
                    s.wgsl_bytes as f64 / 1024.0,
                    bytes as f64 / 1e6,
                    bytes as f64 / tris.len().max(1) as f64,
                    median(s.create_ms.clone()),
                    n / median(s.gpu_ms.clone()) / 1e3,
                    n / median(s.wall_ms.clone()) / 1e3
                );
            }
        }
    }
    Ok(())
}
