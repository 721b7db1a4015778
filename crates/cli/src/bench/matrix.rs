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
    Triangle,
};
use glam::Vec3;
use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::Serialize;

use super::accuracy::{self, ErrorStats};
use super::plot::{one_two_five, pareto, plot_error, write_png_and_svg};
use super::{BenchArgs, BenchBackend, median, open_backends, ray_sets, scene_specs};
use crate::output::{AtomicFile, JsonOut};
use crate::shade;
use bvhtrace::{CpuTracer, Tracer};
use plotters::prelude::*;

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
/// [`open_backends`]' order; `None` for the CPU walks, a [`CpuTracer`] on the tree).
struct BuiltTree {
    bvh: FlatBvh,
    build_ms: f64,
    tracers: Vec<Option<Box<dyn Tracer>>>,
}

/// The walks every configuration sweeps: each of [`Traversal::ALL`], the short stack at
/// 2, 4 and 8 entries.
fn traversals() -> Vec<Traversal> {
    Traversal::all_with_short_stacks(&[2, 4, 8])
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

/// `bvhtrace bench` (without `--converge`).
pub fn run(args: &BenchArgs) -> Result<()> {
    let sizes = Sizes::of(args)?;
    let precisions: Vec<Precision> = if args.precisions.is_empty() {
        Precision::ALL.to_vec()
    } else {
        args.precisions
            .iter()
            .map(|s| s.parse::<Precision>().map_err(anyhow::Error::msg))
            .collect::<Result<_>>()?
    };
    let specs = scene_specs(&args.scenes)?;
    let mut outputs = Outputs::reserve(args, &specs)?;
    let backends = open_backends(&args.backends, args.adapter.as_deref());
    eprintln!("CPU: {} threads", rayon::current_num_threads());
    let mut rows = Vec::new();
    let mut plots = std::mem::take(&mut outputs.plot_files).into_iter();
    for spec in specs {
        let scene_rows = bench_scene(args, &spec, sizes, &precisions, &backends)?;
        print_table(&scene_rows, args.json.as_deref() == Some("-"));
        if let Some((png, svg)) = plots.next() {
            // The file name, not the path: the plots are committed.
            let title = std::path::Path::new(&spec)
                .file_name()
                .map_or(spec.clone(), |n| n.to_string_lossy().into_owned());
            error_vs_time(&title, &scene_rows, png, svg)?;
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
        let scene = crate::geometry::load_triangle_scene(spec)?;
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
    backends: &[BenchBackend],
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
    backends: &[BenchBackend],
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
            _ if b.is_cpu() => Ok(None),
            d if b.driver_walk() => Ok(Some(d.open_owned(&bvh, &Default::default())?.tracer)),
            d => Ok(Some(d.open_owned(&bvh, &every)?.tracer)),
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
    backends: &[BenchBackend],
) -> Result<Vec<Row>> {
    let reference = Reference::of(spec, sizes)?;
    let builders = builder_configs(args.full);
    let plan = plan(args, builders.len(), precisions, backends);
    let pb =
        crate::output::progress_bar(plan.len() as u64, "{msg:40} [{bar:30}] {pos}/{len} ({eta})");
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

/// An error as the table shows it: `0`, or one decimal and the exponent.
fn fmt_err(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else {
        format!("{x:.1e}")
    }
}

/// A row's value in one column: the CSV writes it in full, the table as it reads best.
enum Cell {
    /// A name.
    Text(String),
    /// A count.
    Count(u64),
    /// A measure, with this many decimals in the table.
    Fixed(f64, usize),
    /// An error ([`fmt_err`] in the table); where the row has none, `-` in the table and
    /// nothing in the CSV.
    Error(Option<f64>),
}

impl Cell {
    fn csv(&self) -> String {
        match self {
            Cell::Text(s) => s.clone(),
            Cell::Count(n) => n.to_string(),
            Cell::Fixed(x, _) | Cell::Error(Some(x)) => x.to_string(),
            Cell::Error(None) => String::new(),
        }
    }

    fn table(&self) -> String {
        match self {
            Cell::Text(s) => s.clone(),
            Cell::Count(n) => n.to_string(),
            Cell::Fixed(x, decimals) => format!("{x:.decimals$}"),
            Cell::Error(x) => x.map_or("-".into(), fmt_err),
        }
    }
}

/// One column of the matrix's outputs: the table and the CSV are both written from
/// [`COLUMNS`], so a column is added in one place.
struct Column {
    /// The CSV's header.
    csv: &'static str,
    /// The table's header and width; `None` for a column of the CSV only.
    table: Option<(&'static str, usize)>,
    /// Left-aligned in the table (names); figures are right-aligned.
    left: bool,
    /// A `|` before it in the table: where the error columns start.
    bar: bool,
    /// The row's value.
    value: fn(&Row) -> Cell,
}

impl Column {
    /// A name, left-aligned in the table.
    const fn name(
        csv: &'static str,
        head: &'static str,
        width: usize,
        value: fn(&Row) -> Cell,
    ) -> Column {
        Column {
            csv,
            table: Some((head, width)),
            left: true,
            bar: false,
            value,
        }
    }

    /// A figure, right-aligned in the table.
    const fn figure(
        csv: &'static str,
        head: &'static str,
        width: usize,
        value: fn(&Row) -> Cell,
    ) -> Column {
        Column {
            left: false,
            ..Column::name(csv, head, width, value)
        }
    }

    /// A column of the CSV only.
    const fn csv_only(csv: &'static str, value: fn(&Row) -> Cell) -> Column {
        Column {
            table: None,
            ..Column::name(csv, "", 0, value)
        }
    }

    /// The same column, after a `|` in the table.
    const fn after_bar(self) -> Column {
        Column { bar: true, ..self }
    }
}

/// The columns of the table and the CSV, in order. The CSV's headers and values are what
/// users parse: keep them.
const COLUMNS: [Column; 23] = [
    Column::csv_only("scene", |r| Cell::Text(r.scene.clone())),
    Column::name("builder", "builder", 9, |r| {
        Cell::Text(r.config.builder.clone())
    }),
    Column::figure("bins", "bins", 5, |r| Cell::Count(r.config.bins as u64)),
    Column::name("traversal", "traversal", 15, |r| {
        Cell::Text(r.config.traversal.clone())
    }),
    Column::name("backend", "bknd", 4, |r| {
        Cell::Text(r.config.backend.clone())
    }),
    Column::name("rays", "rays", 8, |r| {
        Cell::Text(r.config.rays.name().into())
    }),
    Column::name("precision", "precision", 19, |r| {
        Cell::Text(r.config.precision.clone())
    }),
    Column::csv_only("ray_count", |r| Cell::Count(r.ray_count as u64)),
    Column::figure("build_ms", "build ms", 8, |r| Cell::Fixed(r.build_ms, 1)),
    Column::figure("trace_ms", "trace ms", 9, |r| Cell::Fixed(r.trace_ms, 2)),
    Column::figure("mrays_per_s", "Mrays/s", 8, |r| {
        Cell::Fixed(r.mrays_per_s, 2)
    }),
    Column::figure("nodes_per_ray", "nodes", 6, |r| {
        Cell::Fixed(r.nodes_per_ray, 1)
    }),
    Column::figure("tris_per_ray", "tris", 5, |r| {
        Cell::Fixed(r.tris_per_ray, 2)
    }),
    Column::figure("bytes", "bytes", 9, |r| Cell::Count(r.bytes)),
    Column::figure("sample", "sample", 6, |r| {
        Cell::Count(r.error.sample as u64)
    })
    .after_bar(),
    Column::figure("wrong_prim", "wrong", 5, |r| {
        Cell::Count(r.error.wrong_prim as u64)
    }),
    Column::figure("false_misses", "fmiss", 5, |r| {
        Cell::Count(r.error.false_misses as u64)
    }),
    Column::figure("false_hits", "fhit", 5, |r| {
        Cell::Count(r.error.false_hits as u64)
    }),
    Column::figure("t_rel_median", "t med", 8, |r| {
        Cell::Error(Some(r.error.t_rel_median))
    }),
    Column::figure("t_rel_max", "t max", 8, |r| {
        Cell::Error(Some(r.error.t_rel_max))
    }),
    Column::csv_only("error_rate", |r| Cell::Error(Some(r.error_rate))),
    Column::figure("image_rmse", "img rmse", 8, |r| Cell::Error(r.image_rmse)),
    Column::figure("image_flip", "img FLIP", 8, |r| Cell::Error(r.image_flip)),
];

/// One line of the table: `text` of each of its columns, padded to the column's width.
fn table_line(text: impl Fn(&Column) -> String) -> String {
    let mut line = String::new();
    let shown = COLUMNS.iter().filter_map(|c| Some((c, c.table?.1)));
    for (i, (c, width)) in shown.enumerate() {
        if i > 0 {
            line += if c.bar { " | " } else { " " };
        }
        let t = text(c);
        line += &match c.left {
            true => format!("{t:width$}"),
            false => format!("{t:>width$}"),
        };
    }
    line
}

/// Prints the table of `rows`, to stderr when the JSON takes stdout.
fn print_table(rows: &[Row], to_stderr: bool) {
    let head = table_line(|c| c.table.map_or("", |t| t.0).to_string());
    let mut out = format!("\n{head}\n");
    for r in rows {
        out += &table_line(|c| (c.value)(r).table());
        out.push('\n');
    }
    if to_stderr {
        eprint!("{out}");
    } else {
        print!("{out}");
    }
}

/// The CSV of `rows`: a header line, then a line per row.
fn to_csv(rows: &[Row]) -> String {
    let line = |cell: &dyn Fn(&Column) -> String| {
        let cells: Vec<String> = COLUMNS.iter().map(cell).collect();
        cells.join(",") + "\n"
    };
    let mut s = line(&|c| c.csv.to_string());
    for r in rows {
        s += &line(&|c| (c.value)(r).csv());
    }
    s
}

/// Where exact configurations (error 0) are drawn on the log axis.
const FLOOR: f64 = 1e-9;

/// The plot's label of a row: builder (with its bins when not 32), walk, backend, precision.
fn label(r: &Row) -> String {
    let c = &r.config;
    let b = if c.builder == "sah" && c.bins != 32 {
        format!("sah{}", c.bins)
    } else {
        c.builder.clone()
    };
    format!(
        "{b}/{}/{}/{}",
        c.traversal,
        c.backend,
        match c.precision.as_str() {
            "watertight-f32" => "wt",
            "moller-trumbore-f32" => "mt",
            "watertight-f64" => "wt64",
            other => other,
        }
    )
}

/// The error-vs-time plot of one scene's rows: error against trace time per ray, log-log,
/// with the Pareto front of each ray kind.
fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    rows: &[Row],
    text: bool,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(plot_error)?;
    // x: nanoseconds per ray; y: the headline error.
    let pts: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| {
            (
                1e6 * r.trace_ms / r.ray_count.max(1) as f64,
                r.error.headline().max(FLOOR),
            )
        })
        .collect();
    let (xmin, xmax) = pts
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let ymax = pts.iter().fold(FLOOR * 10.0, |a, p| a.max(p.1));
    let mut chart = ChartBuilder::on(&root);
    chart.margin(20);
    if text {
        chart
            .caption(title, ("sans-serif", 20))
            .x_label_area_size(40)
            .y_label_area_size(70);
    }
    let mut chart = chart
        .build_cartesian_2d(
            (xmin * 0.8..xmax * 1.25)
                .log_scale()
                .with_key_points(one_two_five(xmin * 0.8, xmax * 1.25)),
            (FLOOR * 0.5..ymax * 2.0).log_scale(),
        )
        .map_err(plot_error)?;
    if text {
        chart
            .configure_mesh()
            .x_desc("trace time per ray (ns, median)")
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_desc("error vs f64 oracle (wrong-answer rate; else max rel. t error; floor = exact)")
            .draw()
            .map_err(plot_error)?;
    }
    let colour = |k: RayKind| match k {
        RayKind::Primary => BLUE,
        RayKind::Shadow => GREEN,
        RayKind::Diffuse => RED,
    };
    for (r, p) in rows.iter().zip(&pts) {
        let c = colour(r.config.rays);
        if r.config.backend != "cpu" {
            chart
                .draw_series(std::iter::once(TriangleMarker::new(*p, 6, c.filled())))
                .map_err(plot_error)?;
        } else {
            chart
                .draw_series(std::iter::once(Circle::new(*p, 4, c.filled())))
                .map_err(plot_error)?;
        }
    }
    // One Pareto front per ray kind: the kinds are different workloads.
    for kind in [RayKind::Primary, RayKind::Shadow, RayKind::Diffuse] {
        let ids: Vec<usize> = (0..rows.len())
            .filter(|&i| rows[i].config.rays == kind)
            .collect();
        let sub: Vec<(f64, f64)> = ids.iter().map(|&i| pts[i]).collect();
        let mut front: Vec<usize> = pareto(&sub).into_iter().map(|k| ids[k]).collect();
        front.sort_by(|&a, &b| pts[a].0.total_cmp(&pts[b].0));
        chart
            .draw_series(LineSeries::new(
                front.iter().map(|&i| pts[i]),
                colour(kind).stroke_width(2),
            ))
            .map_err(plot_error)?;
        if text {
            for &i in &front {
                chart
                    .draw_series(std::iter::once(Text::new(
                        format!(" {}", label(&rows[i])),
                        pts[i],
                        ("sans-serif", 12).into_font(),
                    )))
                    .map_err(plot_error)?;
            }
        }
    }
    if text {
        chart
            .draw_series(std::iter::once(Text::new(
                "exact (0 wrong, 0 t error)".to_string(),
                (xmin * 0.85, FLOOR * 0.75),
                ("sans-serif", 12).into_font(),
            )))
            .map_err(plot_error)?;
        chart
            .draw_series(std::iter::once(Text::new(
                "blue primary, green shadow, red diffuse; triangles GPU, circles CPU; lines = Pareto fronts, labelled".to_string(),
                (xmin * 0.85, ymax * 1.6),
                ("sans-serif", 12).into_font(),
            )))
            .map_err(plot_error)?;
    }
    root.present().map_err(plot_error)?;
    Ok(())
}

/// Writes the plot for one scene's rows as PNG and SVG.
fn error_vs_time(title: &str, rows: &[Row], png: AtomicFile, svg: AtomicFile) -> Result<()> {
    if rows.is_empty() {
        return Ok(());
    }
    write_png_and_svg(
        (1100, 750),
        png,
        svg,
        |area, text| draw(area, title, rows, text),
        |area| draw(area, title, rows, true),
    )
}
