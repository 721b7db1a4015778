//! `bvhtrace bench`: error against run time for every configuration.
//!
//! Each configuration (builder, traversal, backend, ray kind, intersection precision) is
//! timed on the whole ray set and checked against the f64 brute-force oracle on an evenly
//! spaced sample of the same rays, plus a small image compared with the oracle's image.
//! By default the dimensions are swept one at a time around the default configuration
//! (SAH, stackless, watertight f32; the precisions with the default builder on every
//! traversal); `--full` runs the whole cross product.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace_core::oracle::{self, OracleHit};
use bvhtrace_core::{
    BuildOptions, BuilderKind, FlatBvh, Hit, Precision, Query, Ray, TraceOptions, Traversal,
    Triangle, trace_rays,
};
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use serde::Serialize;

use crate::accuracy::{self, ErrorStats};
use crate::bench::median;
use crate::output::{AtomicFile, JsonOut};
use crate::shade;
use bvhtrace::{Backend, CpuTracer, Tracer};

/// Which rays a configuration traces.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RayKind {
    /// Camera rays, closest hit.
    Primary,
    /// From each primary hit to a point light, any hit.
    Shadow,
    /// Cosine-weighted bounces from each primary hit, closest hit.
    Diffuse,
}

impl RayKind {
    fn query(self) -> Query {
        if self == RayKind::Shadow {
            Query::Any
        } else {
            Query::Closest
        }
    }
    fn name(self) -> &'static str {
        match self {
            RayKind::Primary => "primary",
            RayKind::Shadow => "shadow",
            RayKind::Diffuse => "diffuse",
        }
    }
}

/// `bvhtrace bench`.
#[derive(clap::Args)]
pub struct BenchArgs {
    /// Scenes (default: bunny_69k and igea from ../shared/scenes).
    pub scenes: Vec<String>,
    /// A small run that finishes in under a minute.
    #[arg(long)]
    pub quick: bool,
    /// The full cross product of all dimensions (long), instead of one-at-a-time sweeps.
    #[arg(long)]
    pub full: bool,
    /// Primary rays, WxH (default 512x384; 160x120 with --quick).
    #[arg(long, value_parser = crate::render::parse_size)]
    pub size: Option<(u32, u32)>,
    /// Rays per configuration compared with the f64 oracle (default 2048; 256 with --quick).
    #[arg(long)]
    pub sample: Option<usize>,
    /// Timed runs per configuration; the median is reported (default 3; 1 with --quick).
    #[arg(long)]
    pub runs: Option<usize>,
    /// Backends to include: gpu (wgpu), vulkan (the same kernels through ash), ray-query
    /// (the device's own ray queries, where it has them: one row per ray kind, the driver's
    /// walk over the default builder's tree), cpu.
    #[arg(long, value_delimiter = ',', default_value = "gpu,cpu,ray-query")]
    pub backends: Vec<String>,
    /// Intersection precisions (watertight-f32, moller-trumbore-f32, watertight-f64); default
    /// all three (on the GPU, f64 only where the adapter has SHADER_F64). The non-default
    /// ones are swept with the default builder on every backend and ray kind, stackless and
    /// full stack (with --quick: stackless only; with --full: everything).
    #[arg(long, value_delimiter = ',')]
    pub precisions: Vec<String>,
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// Write every row as JSON (`-` for stdout).
    #[arg(long)]
    pub json: Option<String>,
    /// Write every row as CSV.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Write the error-vs-time plot to PREFIX.png and PREFIX.svg (one per scene:
    /// PREFIX-SCENE.png when there are several).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    // `--converge` and its flags: image error against wall time (crate::converge).
    #[command(flatten)]
    pub converge: Box<crate::converge::ConvergeArgs>,
}

/// One configuration.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Config {
    pub builder: String,
    pub bins: usize,
    pub traversal: String,
    pub backend: String,
    pub rays: RayKind,
    pub precision: String,
}

/// One measured row.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub scene: String,
    #[serde(flatten)]
    pub config: Config,
    pub ray_count: usize,
    pub build_ms: f64,
    pub trace_ms: f64,
    pub mrays_per_s: f64,
    pub nodes_per_ray: f64,
    pub tris_per_ray: f64,
    pub bytes: u64,
    #[serde(flatten)]
    pub error: ErrorStats,
    pub error_rate: f64,
    /// Image error against the oracle's image (primary rays only).
    pub image_rmse: Option<f64>,
    pub image_flip: Option<f64>,
}

/// Builder variants: the four builders, then SAH with other bin counts.
fn builder_configs(full: bool) -> Vec<(String, BuildOptions)> {
    let mut v: Vec<(String, BuildOptions)> = BuilderKind::ALL
        .iter()
        .map(|&b| (b.name().to_string(), BuildOptions::with_builder(b)))
        .collect();
    let _ = full;
    for b in [4, 8, 16] {
        v.push((
            "sah".into(),
            BuildOptions {
                bins: b,
                ..Default::default()
            },
        ));
    }
    v
}

/// A built tree, its median build time, and its upload to wgpu (when there is a device).
type BuiltTree = (FlatBvh, f64, Option<Box<dyn Tracer>>);

const TRAVERSALS: [Traversal; 6] = [
    Traversal::Stackless,
    Traversal::ShortStack(2),
    Traversal::ShortStack(4),
    Traversal::ShortStack(8),
    Traversal::FullStack,
    Traversal::Wide,
];

/// Rays of every kind, generated once per scene from the reference hits so that every
/// configuration traces exactly the same rays.
pub(crate) struct RaySets {
    pub(crate) primary: Vec<Ray>,
    pub(crate) shadow: Vec<Ray>,
    pub(crate) diffuse: Vec<Ray>,
}

pub(crate) fn ray_sets(
    tris: &[Triangle],
    bvh: &FlatBvh,
    cam: &bvhtrace_scene::Camera,
    w: u32,
    h: u32,
) -> RaySets {
    let primary = cam.rays(w, h);
    let hits = trace_rays(bvh, &primary, &TraceOptions::closest(Traversal::FullStack)).hits;
    let light = shade::point_light(cam);
    let b = bvh.bounds();
    let diag = (b.max - b.min).length();
    let (shadow, _) = shade::secondary_rays(
        shade::Shade::Diffuse,
        &|p| tris[p as usize],
        &primary,
        &hits,
        light,
        1,
        diag,
    );
    let mut diffuse = Vec::new();
    for (i, (r, h)) in primary.iter().zip(&hits).enumerate() {
        if h.is_hit() {
            let p = h.surface(&tris[h.prim as usize], Vec3::from(r.dir));
            let dir = shade::cosine_dir(p.normal, i as u32, 0);
            diffuse.push(p.spawn_ray(dir, f32::INFINITY));
        }
    }
    RaySets {
        primary,
        shadow,
        diffuse,
    }
}

/// Evenly spaced sample of at most `n` indices.
fn sample_indices(len: usize, n: usize) -> Vec<usize> {
    let n = n.min(len);
    (0..n).map(|i| i * len / n.max(1)).collect()
}

fn oracle_answers(tris: &[Triangle], rays: &[Ray]) -> Vec<OracleHit> {
    rays.par_iter()
        .map(|r| oracle::closest_hit(tris, r))
        .collect()
}

/// Normal-shaded image from hits (the same mapping as `render --shade normal`).
fn normal_image(tris: &[Triangle], rays: &[Ray], prims: impl Iterator<Item = u32>) -> Vec<u8> {
    let mut img = Vec::with_capacity(rays.len() * 3);
    for (r, p) in rays.iter().zip(prims) {
        if let Some(t) = tris.get(p as usize) {
            let n = shade::facing_normal(t, Vec3::from(r.dir));
            img.extend(shade::palette::normal_colour(n));
        } else {
            img.extend(shade::BACKGROUND);
        }
    }
    img
}

/// `bvhtrace bench`.
pub fn bench(args: BenchArgs) -> Result<()> {
    if args.converge.converge {
        return crate::converge::run(&args);
    }
    let quick = args.quick;
    let (w, h) = args
        .size
        .unwrap_or(if quick { (160, 120) } else { (512, 384) });
    let sample_n = args.sample.unwrap_or(if quick { 256 } else { 2048 });
    let runs = args.runs.unwrap_or(if quick { 1 } else { 3 });
    let (iw, ih) = if quick { (48, 36) } else { (96, 72) };
    if runs == 0 || sample_n == 0 {
        bail!("--runs and --sample must be at least 1");
    }
    for b in &args.backends {
        if !matches!(b.as_str(), "gpu" | "vulkan" | "cpu" | "ray-query") {
            bail!("unknown backend '{b}' (expected gpu, vulkan, ray-query or cpu)");
        }
    }
    let precisions: Vec<Precision> = if args.precisions.is_empty() {
        Precision::ALL.to_vec()
    } else {
        args.precisions
            .iter()
            .map(|s| s.parse::<Precision>().map_err(anyhow::Error::msg))
            .collect::<Result<_>>()?
    };
    // Reserve outputs before any work.
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let csv_out = args.csv.as_deref().map(AtomicFile::create).transpose()?;
    let specs = crate::bench::scene_specs(&args.scenes)?;
    let plot_paths: Vec<(PathBuf, PathBuf)> = match &args.plot {
        None => Vec::new(),
        Some(prefix) => specs
            .iter()
            .map(|s| {
                let stem = if specs.len() == 1 {
                    prefix.display().to_string()
                } else {
                    let name = std::path::Path::new(s.split('#').next().unwrap_or(s))
                        .file_stem()
                        .map_or("scene".into(), |n| n.to_string_lossy().to_string());
                    format!("{}-{}", prefix.display(), name.replace(':', "_"))
                };
                (
                    PathBuf::from(format!("{stem}.png")),
                    PathBuf::from(format!("{stem}.svg")),
                )
            })
            .collect(),
    };
    let plot_files: Vec<(AtomicFile, AtomicFile)> = plot_paths
        .iter()
        .map(|(p, s)| Ok((AtomicFile::create(p)?, AtomicFile::create(s)?)))
        .collect::<Result<_>>()?;

    // Each device opened once, through the front door; `vulkan` runs the same kernels
    // through ash (bvhtrace-vk), BVH in storage buffers.
    let open_device = |name: &str, backend: Backend| {
        if !args.backends.iter().any(|b| b == name) {
            return None;
        }
        let opts = crate::backend::options(backend, args.adapter.as_deref(), &[]);
        match crate::backend::device(&opts) {
            Ok(d) => Some(d),
            Err(e) => {
                eprintln!("note: no {backend} device ({e}); leaving out '{name}'");
                None
            }
        }
    };
    let gpu_device = open_device("gpu", Backend::Wgpu);
    let gpu_ctx = gpu_device.as_ref().and_then(|d| d.wgpu_context());
    let vk_device = open_device("vulkan", Backend::Vulkan);
    let vk_ctx = vk_device.as_ref().and_then(|d| d.vulkan_context());
    let rq_device = open_device("ray-query", Backend::RayQuery);
    let rq_ctx = rq_device.as_ref().and_then(|d| d.wgpu_context());
    if let Some(c) = &gpu_ctx {
        eprintln!(
            "GPU: {} ({:?})",
            c.adapter_info().name,
            c.adapter_info().device_type
        );
        for p in precisions.iter().filter(|p| !c.supports_precision(**p)) {
            eprintln!("note: {p} is traced on the CPU only (the adapter has no SHADER_F64)");
        }
    }
    eprintln!("CPU: {} threads", rayon::current_num_threads());

    let mut rows = Vec::new();
    let mut plots = plot_files.into_iter();
    for spec in specs {
        let t0 = Instant::now();
        let scene = bvhtrace_scene::load(&spec)?;
        let tris = scene.flattened_triangles()?;
        let cam = scene.camera_or_frame(w as f32 / h as f32);
        let reference = FlatBvh::build(&tris, &BuildOptions::default())?;
        let sets = ray_sets(&tris, &reference, &cam, w, h);
        let kinds = [
            (RayKind::Primary, &sets.primary),
            (RayKind::Shadow, &sets.shadow),
            (RayKind::Diffuse, &sets.diffuse),
        ];
        // The oracle, once per ray kind, on the sample; and the oracle's small image.
        let pb_oracle = ProgressBar::new_spinner();
        pb_oracle.set_message(format!(
            "{spec}: f64 oracle on {sample_n} rays per kind and a {iw}x{ih} image"
        ));
        pb_oracle.enable_steady_tick(std::time::Duration::from_millis(200));
        let samples: Vec<(Vec<usize>, Vec<OracleHit>)> = kinds
            .iter()
            .map(|(_, rays)| {
                let idx = sample_indices(rays.len(), sample_n);
                let sampled: Vec<Ray> = idx.iter().map(|&i| rays[i]).collect();
                let o = oracle_answers(&tris, &sampled);
                (idx, o)
            })
            .collect();
        let img_rays = cam.rays(iw, ih);
        let img_oracle = oracle_answers(&tris, &img_rays);
        let ref_img = normal_image(&tris, &img_rays, img_oracle.iter().map(|o| o.prim));
        pb_oracle.finish_and_clear();
        eprintln!(
            "{spec}: {} triangles; rays: {} primary, {} shadow, {} diffuse; setup {:.1} s",
            tris.len(),
            sets.primary.len(),
            sets.shadow.len(),
            sets.diffuse.len(),
            t0.elapsed().as_secs_f64()
        );

        // The configurations.
        let builders = builder_configs(args.full);
        let mut plan: Vec<(usize, Traversal, &str, RayKind, Precision)> = Vec::new();
        let backends: Vec<&str> = args
            .backends
            .iter()
            .map(|s| s.as_str())
            .filter(|b| match *b {
                "gpu" => gpu_ctx.is_some(),
                "vulkan" => vk_ctx.is_some(),
                "ray-query" => rq_ctx.is_some(),
                _ => true,
            })
            .collect();
        for &p in &precisions {
            for (bi, _) in builders.iter().enumerate() {
                for &tr in &TRAVERSALS {
                    for &be in &backends {
                        if be == "gpu" && gpu_ctx.as_ref().is_some_and(|c| !c.supports_precision(p))
                        {
                            continue;
                        }
                        // The driver's own walk and triangle test: one row per ray kind,
                        // over the default builder's leaf order.
                        if be == "ray-query"
                            && (bi != 0 || tr != TRAVERSALS[0] || p != Precision::WatertightF32)
                        {
                            continue;
                        }
                        if be == "vulkan"
                            && p == Precision::WatertightF64
                            && vk_ctx.as_ref().is_some_and(|c| !c.features().f64)
                        {
                            continue;
                        }
                        for (kind, _) in &kinds {
                            // Sweeps around the default (SAH, stackless, watertight f32):
                            // every builder on primary rays with the default traversal;
                            // every traversal and ray kind with the default builder; the
                            // other precisions with the default builder, on every ray kind,
                            // stackless and full stack (only stackless with --quick).
                            let keep = if p == Precision::WatertightF32 {
                                args.full
                                    || bi == 0
                                    || (tr == Traversal::Stackless && *kind == RayKind::Primary)
                            } else {
                                args.full
                                    || (bi == 0
                                        && (tr == Traversal::Stackless
                                            || (!quick && tr == Traversal::FullStack)))
                            };
                            if keep {
                                plan.push((bi, tr, be, *kind, p));
                            }
                        }
                    }
                }
            }
        }
        let pb = ProgressBar::new(plan.len() as u64);
        pb.set_style(
            ProgressStyle::with_template("{msg:40} [{bar:30}] {pos}/{len} ({eta})")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        let mut built: Vec<Option<BuiltTree>> = (0..builders.len()).map(|_| None).collect();
        let mut scene_rows = Vec::new();
        for (bi, tr, be, kind, prec) in plan {
            let (bname, bopts) = &builders[bi];
            pb.set_message(format!("{bname} {tr} {be} {} {prec}", kind.name()));
            if built[bi].is_none() {
                let mut times = Vec::new();
                let mut bvh = None;
                for _ in 0..runs {
                    let t = Instant::now();
                    bvh = Some(FlatBvh::build(&tris, bopts)?);
                    times.push(t.elapsed().as_secs_f64() * 1e3);
                }
                // The wide layout is converted from the same tree, untimed here.
                let bvh = bvh.context("no build")?.with_wide();
                let every = bvhtrace::OpenOptions {
                    traversals: TRAVERSALS.to_vec(),
                    ..Default::default()
                };
                let gpu = match gpu_ctx {
                    Some(c) => Some(bvhtrace::open_on_wgpu(c, &bvh, &every)?.tracer),
                    None => None,
                };
                built[bi] = Some((bvh, median(times), gpu));
            }
            let Some((bvh, build_ms, gpu)) = built[bi].as_ref() else {
                continue;
            };
            let cpu = CpuTracer::new(bvh);
            let vk = match (be, &vk_ctx) {
                ("vulkan", Some(c)) => {
                    let every = bvhtrace::OpenOptions {
                        traversals: TRAVERSALS.to_vec(),
                        ..Default::default()
                    };
                    Some(bvhtrace::open_on_vulkan(c, bvh, &every)?.tracer)
                }
                _ => None,
            };
            let rq = match (be, rq_ctx) {
                ("ray-query", Some(c)) => {
                    Some(bvhtrace::open_on_ray_query(c, bvh, &Default::default())?.tracer)
                }
                _ => None,
            };
            let tracer: &dyn Tracer = match (be, gpu, &vk, &rq) {
                ("gpu", Some(g), _, _) => &**g,
                ("vulkan", _, Some(v), _) => &**v,
                ("ray-query", _, _, Some(r)) => &**r,
                _ => &cpu,
            };
            // The driver's build adds to ours (its input is our leaf order); it counts no
            // box or triangle tests.
            let build_ms = build_ms + tracer.device_build_ms().unwrap_or(0.0);
            let counts = tracer.device_build_ms().is_none();
            let (kind_idx, rays) = kinds
                .iter()
                .enumerate()
                .find(|(_, k)| k.0 == kind)
                .map(|(i, k)| (i, k.1))
                .context("ray kind")?;
            let q = kind.query();
            // Warm-up (pipeline creation, caches: the counted pipeline here, the timed
            // one on a few rays, so that no compilation lands in the timings), then timed
            // runs.
            let opts = TraceOptions::new(tr, q).with_precision(prec);
            let c = if counts {
                tracer
                    .trace(rays, &opts.with_counters(true))?
                    .counters
                    .unwrap_or_default()
            } else {
                Vec::new()
            };
            tracer.trace(&rays[..rays.len().min(256)], &opts)?;
            let n = rays.len().max(1) as f64;
            // 0 (not -0: an empty sum) where the driver counted nothing.
            let per_ray = |f: fn(&bvhtrace_core::Counters) -> u32| {
                c.iter().map(|c| f64::from(f(c))).fold(0.0, |a, b| a + b) / n
            };
            let (nodes, tris_per) = (per_ray(|c| c.nodes), per_ray(|c| c.tris));
            let mut times = Vec::new();
            let mut hits: Vec<Hit> = Vec::new();
            for _ in 0..runs {
                let t = tracer.trace(rays, &opts)?;
                times.push(t.gpu_ms.unwrap_or(t.wall_ms));
                hits = t.hits;
            }
            let trace_ms = median(times);
            let (idx, o) = &samples[kind_idx];
            let ours: Vec<Hit> = idx.iter().map(|&i| hits[i]).collect();
            let error = accuracy::compare(&ours, o, q);
            let (image_rmse, image_flip) = if kind == RayKind::Primary {
                let t = tracer.trace(&img_rays, &TraceOptions::closest(tr).with_precision(prec))?;
                let img = normal_image(&tris, &img_rays, t.hits.iter().map(|h| h.prim));
                (
                    Some(accuracy::rmse(&ref_img, &img)),
                    Some(accuracy::flip(&ref_img, &img, iw, ih)),
                )
            } else {
                (None, None)
            };
            let bytes = match tracer.upload_stats() {
                Some(u) => u.total_bytes(),
                None => {
                    let (nb, eb, tb) = bvh.byte_sizes();
                    (nb + if tr.needs_escapes() { eb } else { 0 } + tb) as u64
                }
            };
            scene_rows.push(Row {
                scene: spec.clone(),
                config: Config {
                    builder: bname.clone(),
                    bins: bopts.bins,
                    traversal: if counts {
                        tr.to_string()
                    } else {
                        "driver".into()
                    },
                    backend: be.to_string(),
                    rays: kind,
                    precision: prec.name().into(),
                },
                ray_count: rays.len(),
                build_ms,
                trace_ms,
                mrays_per_s: rays.len() as f64 / trace_ms / 1e3,
                nodes_per_ray: nodes,
                tris_per_ray: tris_per,
                bytes,
                error_rate: error.error_rate(),
                error,
                image_rmse,
                image_flip,
            });
            pb.inc(1);
        }
        pb.finish_and_clear();
        print_table(&scene_rows, args.json.as_deref() == Some("-"));
        if let Some((png, svg)) = plots.next() {
            // The file name, not the path: the plots are committed.
            let title = std::path::Path::new(&spec)
                .file_name()
                .map_or(spec.clone(), |n| n.to_string_lossy().into_owned());
            crate::plot::error_vs_time(&title, &scene_rows, png, svg)?;
        }
        rows.extend(scene_rows);
    }
    if let Some(j) = json_out {
        j.write(&serde_json::to_value(&rows)?)?;
    }
    if let Some(f) = csv_out {
        f.finish_with_bytes(to_csv(&rows).as_bytes())?;
    }
    for (p, s) in &plot_paths {
        eprintln!("wrote {} and {}", p.display(), s.display());
    }
    Ok(())
}

fn fmt_err(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else {
        format!("{x:.1e}")
    }
}

fn print_table(rows: &[Row], to_stderr: bool) {
    let mut out = String::new();
    out += &format!(
        "\n{:9} {:5} {:15} {:4} {:8} {:19} {:>8} {:>9} {:>8} {:>6} {:>5} {:>9} | {:>6} {:>5} {:>5} {:>5} {:>8} {:>8} {:>8} {:>8}",
        "builder",
        "bins",
        "traversal",
        "bknd",
        "rays",
        "precision",
        "build ms",
        "trace ms",
        "Mrays/s",
        "nodes",
        "tris",
        "bytes",
        "sample",
        "wrong",
        "fmiss",
        "fhit",
        "t med",
        "t max",
        "img rmse",
        "img FLIP"
    );
    out.push('\n');
    for r in rows {
        out += &format!(
            "{:9} {:5} {:15} {:4} {:8} {:19} {:>8.1} {:>9.2} {:>8.2} {:>6.1} {:>5.2} {:>9} | {:>6} {:>5} {:>5} {:>5} {:>8} {:>8} {:>8} {:>8}",
            r.config.builder,
            r.config.bins,
            r.config.traversal,
            r.config.backend,
            r.config.rays.name(),
            r.config.precision,
            r.build_ms,
            r.trace_ms,
            r.mrays_per_s,
            r.nodes_per_ray,
            r.tris_per_ray,
            r.bytes,
            r.error.sample,
            r.error.wrong_prim,
            r.error.false_misses,
            r.error.false_hits,
            fmt_err(r.error.t_rel_median),
            fmt_err(r.error.t_rel_max),
            r.image_rmse.map_or("-".into(), fmt_err),
            r.image_flip.map_or("-".into(), fmt_err),
        );
        out.push('\n');
    }
    if to_stderr {
        eprint!("{out}");
    } else {
        print!("{out}");
    }
}

fn to_csv(rows: &[Row]) -> String {
    let mut s = String::from(
        "scene,builder,bins,traversal,backend,rays,precision,ray_count,build_ms,trace_ms,mrays_per_s,nodes_per_ray,tris_per_ray,bytes,sample,wrong_prim,false_misses,false_hits,t_rel_median,t_rel_max,error_rate,image_rmse,image_flip\n",
    );
    for r in rows {
        let c = &r.config;
        s += &format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            r.scene,
            c.builder,
            c.bins,
            c.traversal,
            c.backend,
            c.rays.name(),
            c.precision,
            r.ray_count,
            r.build_ms,
            r.trace_ms,
            r.mrays_per_s,
            r.nodes_per_ray,
            r.tris_per_ray,
            r.bytes,
            r.error.sample,
            r.error.wrong_prim,
            r.error.false_misses,
            r.error.false_hits,
            r.error.t_rel_median,
            r.error.t_rel_max,
            r.error_rate,
            r.image_rmse.map_or(String::new(), |x| x.to_string()),
            r.image_flip.map_or(String::new(), |x| x.to_string())
        );
    }
    s
}
