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
use bvhtrace::{Backend, CpuTracer, Device, Tracer};

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
    /// Backends to include, comma-separated (`bvhtrace render --help` lists them); the
    /// device's own ray queries, where it has them, give one row per ray kind (the
    /// driver's walk over the default builder's tree).
    #[arg(long, value_delimiter = ',', default_value = "wgpu,cpu,ray-query")]
    pub backends: Vec<Backend>,
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

/// A built tree, its median build time, and its tracer on each backend (in
/// [`open_backends`]' order; `None` where the upload was refused, said once).
struct BuiltTree {
    bvh: FlatBvh,
    build_ms: f64,
    tracers: Vec<Option<Box<dyn Tracer>>>,
}

/// The walks every configuration sweeps: each of [`Traversal::ALL`], the short stack at
/// 2, 4 and 8 entries.
fn traversals() -> Vec<Traversal> {
    (Traversal::ALL.into_iter())
        .flat_map(|t| match t {
            Traversal::ShortStack(_) => [2, 4, 8].map(Traversal::ShortStack).to_vec(),
            t => vec![t],
        })
        .collect()
}

/// A backend of the matrix: its rows' name and its device (none for the CPU walks).
struct MatrixBackend {
    name: &'static str,
    device: Option<Device>,
}

impl MatrixBackend {
    /// True for the device's own ray queries: one row per ray kind, the driver's walk.
    fn driver_walk(&self) -> bool {
        self.device
            .as_ref()
            .is_some_and(|d| !d.backend().bit_for_bit())
    }
}

/// Every backend `--backends` lists, each device opened once through the front door; one
/// that does not open is left out, saying why.
fn open_backends(args: &BenchArgs) -> Vec<MatrixBackend> {
    let mut out = Vec::new();
    for &backend in &args.backends {
        if backend == Backend::Cpu {
            out.push(MatrixBackend {
                name: backend.name(),
                device: None,
            });
            continue;
        }
        let opts = crate::backend::options(backend, args.adapter.as_deref(), &[]);
        match crate::backend::device(&opts) {
            Ok(d) => {
                eprintln!("{}: {}", d.backend(), d.name());
                out.push(MatrixBackend {
                    name: d.backend().name(),
                    device: Some(d),
                });
            }
            Err(e) => eprintln!("note: no {backend} device ({e}); leaving it out"),
        }
    }
    out
}

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

/// The sizes a run uses: primary rays, oracle sample, timed runs, the small image.
#[derive(Clone, Copy)]
struct Sizes {
    w: u32,
    h: u32,
    sample: usize,
    runs: usize,
    image: (u32, u32),
}

impl Sizes {
    fn of(args: &BenchArgs) -> Result<Sizes> {
        let quick = args.quick;
        let (w, h) = args
            .size
            .unwrap_or(if quick { (160, 120) } else { (512, 384) });
        let sizes = Sizes {
            w,
            h,
            sample: args.sample.unwrap_or(if quick { 256 } else { 2048 }),
            runs: args.runs.unwrap_or(if quick { 1 } else { 3 }),
            image: if quick { (48, 36) } else { (96, 72) },
        };
        if sizes.runs == 0 || sizes.sample == 0 {
            bail!("--runs and --sample must be at least 1");
        }
        Ok(sizes)
    }
}

/// The output files a run writes, reserved before any work: JSON, CSV, and a plot (PNG
/// and SVG) per scene.
struct Outputs {
    json: Option<JsonOut>,
    csv: Option<AtomicFile>,
    plots: Vec<(PathBuf, PathBuf)>,
    plot_files: Vec<(AtomicFile, AtomicFile)>,
}

impl Outputs {
    fn reserve(args: &BenchArgs, specs: &[String]) -> Result<Outputs> {
        let json = args.json.as_deref().map(JsonOut::create).transpose()?;
        let csv = args.csv.as_deref().map(AtomicFile::create).transpose()?;
        let plots: Vec<(PathBuf, PathBuf)> = match &args.plot {
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
        let plot_files = plots
            .iter()
            .map(|(p, s)| Ok((AtomicFile::create(p)?, AtomicFile::create(s)?)))
            .collect::<Result<_>>()?;
        Ok(Outputs {
            json,
            csv,
            plots,
            plot_files,
        })
    }
}

/// `bvhtrace bench`.
pub fn bench(args: BenchArgs) -> Result<()> {
    if args.converge.converge {
        return crate::converge::run(&args);
    }
    let sizes = Sizes::of(&args)?;
    let precisions: Vec<Precision> = if args.precisions.is_empty() {
        Precision::ALL.to_vec()
    } else {
        args.precisions
            .iter()
            .map(|s| s.parse::<Precision>().map_err(anyhow::Error::msg))
            .collect::<Result<_>>()?
    };
    let specs = crate::bench::scene_specs(&args.scenes)?;
    let mut outputs = Outputs::reserve(&args, &specs)?;
    let backends = open_backends(&args);
    eprintln!("CPU: {} threads", rayon::current_num_threads());
    let mut rows = Vec::new();
    let mut plots = std::mem::take(&mut outputs.plot_files).into_iter();
    for spec in specs {
        let scene_rows = bench_scene(&args, &spec, sizes, &precisions, &backends)?;
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
    if let Some(j) = outputs.json {
        j.write(&serde_json::to_value(&rows)?)?;
    }
    if let Some(f) = outputs.csv {
        f.finish_with_bytes(to_csv(&rows).as_bytes())?;
    }
    for (p, s) in &outputs.plots {
        eprintln!("wrote {} and {}", p.display(), s.display());
    }
    Ok(())
}

/// What every configuration of a scene is judged against: its triangles, the ray sets,
/// the oracle's answers on each kind's sample, and the oracle's small image.
struct Reference {
    tris: Vec<Triangle>,
    kinds: [(RayKind, Vec<Ray>); 3],
    samples: Vec<(Vec<usize>, Vec<OracleHit>)>,
    image_rays: Vec<Ray>,
    image: Vec<u8>,
}

impl Reference {
    /// `spec` loaded, its rays made and the oracle run on the samples.
    fn of(spec: &str, sizes: Sizes) -> Result<Reference> {
        let t0 = Instant::now();
        let scene = crate::geometry::load_scene(spec)?;
        let tris = scene.flattened_triangles()?;
        let cam = scene.camera_or_frame(sizes.w as f32 / sizes.h as f32);
        let reference = FlatBvh::build(&tris, &BuildOptions::default())?;
        let sets = ray_sets(&tris, &reference, &cam, sizes.w, sizes.h);
        let kinds = [
            (RayKind::Primary, sets.primary),
            (RayKind::Shadow, sets.shadow),
            (RayKind::Diffuse, sets.diffuse),
        ];
        let (iw, ih) = sizes.image;
        let pb = ProgressBar::new_spinner();
        pb.set_message(format!(
            "{spec}: f64 oracle on {} rays per kind and a {iw}x{ih} image",
            sizes.sample
        ));
        pb.enable_steady_tick(std::time::Duration::from_millis(200));
        let samples = kinds
            .iter()
            .map(|(_, rays)| {
                let idx = sample_indices(rays.len(), sizes.sample);
                let sampled: Vec<Ray> = idx.iter().map(|&i| rays[i]).collect();
                let o = oracle_answers(&tris, &sampled);
                (idx, o)
            })
            .collect();
        let image_rays = cam.rays(iw, ih);
        let oracle = oracle_answers(&tris, &image_rays);
        let image = normal_image(&tris, &image_rays, oracle.iter().map(|o| o.prim));
        pb.finish_and_clear();
        eprintln!(
            "{spec}: {} triangles; rays: {} primary, {} shadow, {} diffuse; setup {:.1} s",
            tris.len(),
            kinds[0].1.len(),
            kinds[1].1.len(),
            kinds[2].1.len(),
            t0.elapsed().as_secs_f64()
        );
        Ok(Reference {
            tris,
            kinds,
            samples,
            image_rays,
            image,
        })
    }
}

/// One configuration to measure: a builder, a walk, a backend, a ray kind, a precision.
#[derive(Clone, Copy)]
struct Plan {
    builder: usize,
    walk: Traversal,
    backend: usize,
    kind: RayKind,
    precision: Precision,
}

/// The configurations of one scene: sweeps around the default (SAH, stackless,
/// watertight f32): every builder on primary rays with the default walk; every walk and
/// ray kind with the default builder; the other precisions with the default builder, on
/// every ray kind, stackless and full stack (only stackless with `--quick`); `--full`
/// everything. The driver's walk of ray queries: one row per ray kind.
fn plan(
    args: &BenchArgs,
    builders: usize,
    precisions: &[Precision],
    backends: &[MatrixBackend],
) -> Vec<Plan> {
    let walks = traversals();
    let mut plan = Vec::new();
    for &precision in precisions {
        for builder in 0..builders {
            for &walk in &walks {
                for (backend, b) in backends.iter().enumerate() {
                    if b.driver_walk()
                        && (builder != 0
                            || walk != walks[0]
                            || precision != Precision::WatertightF32)
                    {
                        continue;
                    }
                    for kind in [RayKind::Primary, RayKind::Shadow, RayKind::Diffuse] {
                        let keep = if precision == Precision::WatertightF32 {
                            args.full
                                || builder == 0
                                || (walk == Traversal::Stackless && kind == RayKind::Primary)
                        } else {
                            args.full
                                || (builder == 0
                                    && (walk == Traversal::Stackless
                                        || (!args.quick && walk == Traversal::FullStack)))
                        };
                        if keep {
                            plan.push(Plan {
                                builder,
                                walk,
                                backend,
                                kind,
                                precision,
                            });
                        }
                    }
                }
            }
        }
    }
    plan
}

/// Builds `opts`' tree `runs` times (the median time kept) and opens it on every backend.
fn build_tree(
    tris: &[Triangle],
    opts: &BuildOptions,
    runs: usize,
    backends: &[MatrixBackend],
) -> Result<BuiltTree> {
    let mut times = Vec::new();
    let mut bvh = None;
    for _ in 0..runs {
        let t = Instant::now();
        bvh = Some(FlatBvh::build(tris, opts)?);
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    // The wide layout is converted from the same tree, untimed here.
    let bvh = bvh.context("no build")?.with_wide();
    let every = bvhtrace::OpenOptions {
        traversals: traversals(),
        ..Default::default()
    };
    let tracers = backends
        .iter()
        .map(|b| match &b.device {
            None => Ok(None),
            Some(d) if b.driver_walk() => Ok(Some(d.open_owned(&bvh, &Default::default())?.tracer)),
            Some(d) => Ok(Some(d.open_owned(&bvh, &every)?.tracer)),
        })
        .collect::<Result<_>>()?;
    Ok(BuiltTree {
        bvh,
        build_ms: median(times),
        tracers,
    })
}

/// Every configuration of `spec`, measured.
fn bench_scene(
    args: &BenchArgs,
    spec: &str,
    sizes: Sizes,
    precisions: &[Precision],
    backends: &[MatrixBackend],
) -> Result<Vec<Row>> {
    let reference = Reference::of(spec, sizes)?;
    let builders = builder_configs(args.full);
    let plan = plan(args, builders.len(), precisions, backends);
    let pb = ProgressBar::new(plan.len() as u64);
    pb.set_style(
        ProgressStyle::with_template("{msg:40} [{bar:30}] {pos}/{len} ({eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let mut built: Vec<Option<BuiltTree>> = (0..builders.len()).map(|_| None).collect();
    let mut rows = Vec::new();
    let mut refused = Vec::new();
    for p in plan {
        let (bname, bopts) = &builders[p.builder];
        let be = &backends[p.backend];
        pb.set_message(format!(
            "{bname} {} {} {} {}",
            p.walk,
            be.name,
            p.kind.name(),
            p.precision
        ));
        let tree = match &mut built[p.builder] {
            Some(t) => t,
            slot => slot.insert(build_tree(&reference.tris, bopts, sizes.runs, backends)?),
        };
        let cpu = CpuTracer::new(&tree.bvh);
        let tracer: &dyn Tracer = tree.tracers[p.backend].as_deref().unwrap_or(&cpu);
        let opts = TraceOptions::new(p.walk, p.kind.query()).with_precision(p.precision);
        if let Err(e) = tracer.supports(&opts) {
            // A precision the device lacks (f64 without SHADER_F64): said once.
            let note = format!("{}: {e}", be.name);
            if !refused.contains(&note) {
                pb.suspend(|| eprintln!("note: left out {note}"));
                refused.push(note);
            }
            pb.inc(1);
            continue;
        }
        let config = Config {
            builder: bname.clone(),
            bins: bopts.bins,
            traversal: match be.driver_walk() {
                true => "driver".into(),
                false => p.walk.to_string(),
            },
            backend: be.name.to_string(),
            rays: p.kind,
            precision: p.precision.name().into(),
        };
        rows.push(measure(spec, config, tracer, tree, &reference, &p, sizes)?);
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(rows)
}

/// One configuration's row: counted once, warmed up, timed `sizes.runs` times, its
/// sample judged by the oracle and, for primary rays, its small image.
fn measure(
    spec: &str,
    config: Config,
    tracer: &dyn Tracer,
    tree: &BuiltTree,
    reference: &Reference,
    p: &Plan,
    sizes: Sizes,
) -> Result<Row> {
    // The driver's build adds to ours (its input is our leaf order); it counts no box or
    // triangle tests.
    let build_ms = tree.build_ms + tracer.device_build_ms().unwrap_or(0.0);
    let counts = tracer.device_build_ms().is_none();
    let kind_idx = (reference.kinds.iter())
        .position(|k| k.0 == p.kind)
        .context("ray kind")?;
    let rays = &reference.kinds[kind_idx].1;
    let q = p.kind.query();
    // Warm-up (pipeline creation, caches: the counted pipeline here, the timed one on a few
    // rays, so that no compilation lands in the timings), then timed runs.
    let opts = TraceOptions::new(p.walk, q).with_precision(p.precision);
    let c = match counts {
        true => (tracer.trace(rays, &opts.with_counters(true))?.counters).unwrap_or_default(),
        false => Vec::new(),
    };
    tracer.trace(&rays[..rays.len().min(256)], &opts)?;
    let n = rays.len().max(1) as f64;
    // 0 (not -0: an empty sum) where the driver counted nothing.
    let per_ray = |f: fn(&bvhtrace_core::Counters) -> u32| {
        c.iter().map(|c| f64::from(f(c))).fold(0.0, |a, b| a + b) / n
    };
    let mut times = Vec::new();
    let mut hits: Vec<Hit> = Vec::new();
    for _ in 0..sizes.runs {
        let t = tracer.trace(rays, &opts)?;
        times.push(t.gpu_ms.unwrap_or(t.wall_ms));
        hits = t.hits;
    }
    let trace_ms = median(times);
    let (idx, o) = &reference.samples[kind_idx];
    let ours: Vec<Hit> = idx.iter().map(|&i| hits[i]).collect();
    let error = accuracy::compare(&ours, o, q);
    let (image_rmse, image_flip) = match p.kind {
        RayKind::Primary => {
            let closest = TraceOptions::closest(p.walk).with_precision(p.precision);
            let t = tracer.trace(&reference.image_rays, &closest)?;
            let prims = t.hits.iter().map(|h| h.prim);
            let img = normal_image(&reference.tris, &reference.image_rays, prims);
            let (iw, ih) = sizes.image;
            (
                Some(accuracy::rmse(&reference.image, &img)),
                Some(accuracy::flip(&reference.image, &img, iw, ih)),
            )
        }
        _ => (None, None),
    };
    let bytes = match tracer.upload_stats() {
        Some(u) => u.total_bytes(),
        None => {
            let (nb, eb, tb) = tree.bvh.byte_sizes();
            (nb + if p.walk.needs_escapes() { eb } else { 0 } + tb) as u64
        }
    };
    Ok(Row {
        scene: spec.to_string(),
        config,
        ray_count: rays.len(),
        build_ms,
        trace_ms,
        mrays_per_s: rays.len() as f64 / trace_ms / 1e3,
        nodes_per_ray: per_ray(|c| c.nodes),
        tris_per_ray: per_ray(|c| c.tris),
        bytes,
        error_rate: error.error_rate(),
        error,
        image_rmse,
        image_flip,
    })
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
