//! `bvhtrace bench-build` and `bvhtrace bench-trace`: figures as commands, not tests.

use std::time::Instant;

use crate::embree::{self, Dump};
use anyhow::{Context, Result, bail};
use bvhtrace_core::{
    BuildOptions, BuilderKind, BvhStats, FlatBvh, Query, Ray, TraceOptions, Traversal, Triangle,
    trace_rays,
};
use bvhtrace_gpu::{
    AdapterChoice, Composition, ContextOptions, GpuBvh, GpuContext, KernelKey, UploadOptions,
    VertexAttributes,
};

/// The median of `v` (the upper one for an even length).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
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
    let tris = scene.flattened_triangles()?;
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
    #[arg(long, default_value = "1024x768", value_parser = crate::render::parse_size)]
    pub size: (u32, u32),
}

/// `bvhtrace bench-build`.
pub fn bench_build(args: BenchBuildArgs) -> Result<()> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads.unwrap_or(0))
        .build()?;
    let (w, h) = args.size;
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
                let opts = TraceOptions::closest(tr);
                let counted = opts.with_counters(true);
                let c = pool
                    .install(|| trace_rays(&bvh, &rays, &counted))
                    .counters
                    .unwrap_or_default();
                let nodes = c.iter().map(|c| c.nodes as f64).sum::<f64>() / rays.len() as f64;
                let t = median(
                    (0..3)
                        .map(|_| {
                            let t = Instant::now();
                            pool.install(|| trace_rays(&bvh, &rays, &opts));
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
    /// Timed rounds (each traces every traversal once on the GPU and once on the CPU;
    /// medians are printed, and ratios are medians of the per-round ratios).
    #[arg(long, default_value_t = 7)]
    pub runs: usize,
    /// Primary rays, WxH.
    #[arg(long, default_value = "1024x768", value_parser = crate::render::parse_size)]
    pub size: (u32, u32),
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// Traversals to compare, comma-separated (`full-stack`, `stackless`, `short-stack:K`,
    /// `wide`); the first is the one the `n/full` and `GPU/full` columns divide by.
    /// Default: full-stack, stackless, short-stack 2, 4, 6 and 8, and wide.
    #[arg(long, value_delimiter = ',')]
    pub traversals: Vec<Traversal>,
    /// An `embree_trace` binary (`crates/cli/embree/embree_trace.c`): Embree 3 traces the
    /// same rays in every round, after ours (medium build, robust mode, 2 threads), and
    /// its build time and Mrays/s are printed beside ours, with each CPU walk's speed as a
    /// ratio of Embree's (`CPU/Embree`, medians of per-round ratios).
    #[arg(long)]
    pub embree: Option<std::path::PathBuf>,
    /// Also trace any-hit (occlusion) queries on the same rays.
    #[arg(long)]
    pub any_hit: bool,
    /// Instead, compare each traversal's specialised pipeline (only the bindings and code
    /// the closest-hit job reads) with the everything-on one (every module composed, the
    /// escape links uploaded, counters written): bytes uploaded per triangle, pipeline
    /// creation time, Mrays/s.
    #[arg(long)]
    pub everything_on: bool,
}

/// `bvhtrace bench-trace`.
pub fn bench_trace(args: BenchTraceArgs) -> Result<()> {
    let (w, h) = args.size;
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let ctx = GpuContext::new(AdapterChoice::from_name(args.adapter.as_deref()))?;
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
    let traversals = if args.traversals.is_empty() {
        vec![
            Traversal::FullStack,
            Traversal::Stackless,
            Traversal::ShortStack(2),
            Traversal::ShortStack(4),
            Traversal::ShortStack(6),
            Traversal::ShortStack(8),
            Traversal::Wide,
        ]
    } else {
        args.traversals.clone()
    };
    let queries: &[Query] = if args.any_hit {
        &[Query::Closest, Query::Any]
    } else {
        &[Query::Closest]
    };
    for spec in scene_specs(&args.scenes)? {
        let (tris, scene, _) = load(&spec)?;
        let t = Instant::now();
        let mut bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
        let build_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        if traversals.iter().any(|t| t.is_wide()) {
            bvh.build_wide();
        }
        let wide_ms = t.elapsed().as_secs_f64() * 1e3;
        let rays = primary_rays(&scene, w, h);
        let upload = UploadOptions {
            traversals: traversals.clone(),
            storage: None,
        };
        let gpu = GpuBvh::upload(&ctx, &bvh, &upload)?;
        let dump = match &args.embree {
            Some(_) => Some(Dump::write("trace", &tris, &rays)?),
            None => None,
        };
        println!(
            "\n{spec}: {} triangles, depth {}, {} rays ({w}x{h}); our build {build_ms:.1} ms \
             (+{wide_ms:.1} ms to the wide layout)",
            tris.len(),
            bvh.depth,
            rays.len()
        );
        println!(
            "{:16} {:8} {:>9} {:>9} {:>9} {:>7} {:>6} {:>7} {:>8} {:>8} {:>8} {:>10}",
            "traversal",
            "query",
            "GPU Mr/s",
            "GPU wall",
            "CPU Mr/s",
            "nodes",
            "tris",
            "n/full",
            "GPU/full",
            "GPU/twin",
            "GPU/CPU",
            "CPU/Embree"
        );
        let n = rays.len() as f64;
        for &q in queries {
            // Counters (and the counted pipelines) first, then one untimed trace each, so
            // that no timed run pays a pipeline's creation or first dispatch.
            let mut counts = Vec::new();
            for &tr in &traversals {
                let opts = TraceOptions::new(tr, q);
                let c = gpu
                    .trace(&rays, &opts.with_counters(true))?
                    .counters
                    .unwrap_or_default();
                let per_ray = |f: fn(&bvhtrace_core::Counters) -> u32| {
                    c.iter().map(|c| f64::from(f(c))).sum::<f64>() / n.max(1.0)
                };
                counts.push((per_ray(|c| c.nodes), per_ray(|c| c.tris)));
                gpu.trace(&rays, &opts)?;
            }
            // Rounds of every traversal on the GPU and its twin on the CPU, one after the
            // other: lavapipe and the CPU swing by 10-20% from minute to minute, so the
            // ratios are taken within each round (medians over the rounds).
            let mut gpu_ms = vec![Vec::new(); traversals.len()];
            let mut wall_ms = vec![Vec::new(); traversals.len()];
            let mut cpu_ms = vec![Vec::new(); traversals.len()];
            let (mut embree_ms, mut embree_build_ms) = (Vec::new(), Vec::new());
            for _ in 0..args.runs {
                for (i, &tr) in traversals.iter().enumerate() {
                    let opts = TraceOptions::new(tr, q);
                    let o = gpu.trace(&rays, &opts)?;
                    wall_ms[i].push(o.wall_ms);
                    gpu_ms[i].push(o.gpu_ms.unwrap_or(o.wall_ms));
                    let t = Instant::now();
                    std::hint::black_box(trace_rays(&bvh, &rays, &opts));
                    cpu_ms[i].push(t.elapsed().as_secs_f64() * 1e3);
                }
                if let (Some(exe), Some(dump), Query::Closest) = (&args.embree, &dump, q) {
                    let v = dump.run(exe, 1, &[])?;
                    embree_ms.push(embree::field(&v, "trace_ms", exe)?);
                    embree_build_ms.push(embree::field(&v, "build_ms", exe)?);
                }
            }
            let ratio = |num: &[f64], den: &[f64]| {
                median(num.iter().zip(den).map(|(a, b)| a / b).collect())
            };
            let mrays = |ms: &[f64]| n / median(ms.to_vec()) / 1e3;
            for (i, tr) in traversals.iter().enumerate() {
                let vs_embree = if embree_ms.is_empty() {
                    "-".to_string()
                } else {
                    format!("{:.2}x", ratio(&embree_ms, &cpu_ms[i]))
                };
                println!(
                    "{:16} {:8} {:>9.2} {:>9.2} {:>9.2} {:>7.1} {:>6.2} {:>6.2}x {:>7.2}x {:>7.2}x {:>7.2}x {:>10}",
                    tr.to_string(),
                    format!("{q:?}").to_lowercase(),
                    mrays(&gpu_ms[i]),
                    mrays(&wall_ms[i]),
                    mrays(&cpu_ms[i]),
                    counts[i].0,
                    counts[i].1,
                    counts[i].0 / counts[0].0,
                    ratio(&gpu_ms[0], &gpu_ms[i]),
                    ratio(&cpu_ms[i], &gpu_ms[i]),
                    ratio(&cpu_ms[0], &gpu_ms[i]),
                    vs_embree,
                );
            }
            if !embree_ms.is_empty() {
                println!(
                    "{:16} {:8} {:>9} {:>9} {:>9.2}   (Embree 3 rtcIntersect1, 2 threads; build {:.1} ms)",
                    "embree",
                    "closest",
                    "-",
                    "-",
                    mrays(&embree_ms),
                    median(embree_build_ms.clone()),
                );
            }
        }
    }
    Ok(())
}

/// One side of `bench-trace --everything-on`.
struct Side {
    name: &'static str,
    options: ContextOptions,
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
    let storage = ctx.tuning().storage;
    // A context of its own per composition, on the one device.
    let context = |options: &ContextOptions| {
        GpuContext::from_device_with(
            ctx.device().clone(),
            ctx.queue().clone(),
            ctx.adapter_info().clone(),
            options,
        )
    };
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
            Traversal::ShortStack(bvhtrace_core::traverse::DEFAULT_SHORT_STACK),
        ] {
            let plain = TraceOptions::closest(tr);
            let job = KernelKey::for_job(
                storage,
                &plain,
                VertexAttributes::NONE,
                VertexAttributes::NONE,
            );
            let all = job.with_composition(Composition::EverythingOn);
            let side = |name, composition, upload: &UploadOptions, opts, wgsl_bytes, bindings| {
                let options = ContextOptions {
                    composition,
                    ..ContextOptions::default()
                };
                anyhow::Ok(Side {
                    name,
                    options,
                    gpu: GpuBvh::upload(&context(&options)?, &bvh, upload)?,
                    opts,
                    wgsl_bytes,
                    bindings,
                    create_ms: Vec::new(),
                    gpu_ms: Vec::new(),
                    wall_ms: Vec::new(),
                })
            };
            let mut sides = [
                side(
                    "specialised",
                    Composition::Specialised,
                    &UploadOptions::for_traversal(tr).with_storage(storage),
                    plain,
                    job.source().len(),
                    job.bindings().len(),
                )?,
                side(
                    "everything-on",
                    Composition::EverythingOn,
                    &UploadOptions::all().with_storage(storage),
                    plain.with_counters(true),
                    all.source().len(),
                    all.bindings().len(),
                )?,
            ];
            // Pipeline creation (module + pipeline, nothing cached), interleaved.
            for _ in 0..args.runs {
                for s in sides.iter_mut() {
                    let fresh = context(&s.options)?;
                    let gpu = GpuBvh::upload(&fresh, &bvh, &UploadOptions::all())?;
                    let t = Instant::now();
                    gpu.prepare(&s.opts)?;
                    s.create_ms.push(t.elapsed().as_secs_f64() * 1e3);
                }
            }
            // Both pipelines compiled once more and kept; one untimed trace each.
            let mut hits = Vec::new();
            for s in sides.iter_mut() {
                s.gpu.prepare(&s.opts)?;
                hits.push(s.gpu.trace(&rays, &s.opts)?.hits);
            }
            if hits[0] != hits[1] {
                bail!("{spec} {tr}: the specialised and everything-on pipelines disagree");
            }
            for _ in 0..args.runs {
                for s in sides.iter_mut() {
                    let o = s.gpu.trace(&rays, &s.opts)?;
                    s.wall_ms.push(o.wall_ms);
                    s.gpu_ms.push(o.gpu_ms.unwrap_or(o.wall_ms));
                }
            }
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
