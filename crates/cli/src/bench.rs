//! `bvhtrace bench-build` and `bvhtrace bench-trace`: figures as commands, not tests.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use crate::bench_matrix::ray_sets;
use crate::embree::{self, Dump};
use crate::output::JsonOut;
use anyhow::{Context, Result, bail};
use bvhtrace_core::{
    BuildOptions, BuilderKind, BvhStats, Counters, FlatBvh, Query, Ray, TraceOptions, Traversal,
    Triangle, trace_rays,
};
use bvhtrace_gpu::{
    Composition, ContextOptions, GpuBvh, GpuContext, KernelKey, Tracer, UploadOptions,
    VertexAttributes,
};
use indicatif::{ProgressBar, ProgressStyle};

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
    let dir = crate::geometry::shared_scenes_dir()
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
    let scene = crate::geometry::load_scene(spec)?;
    let tris = scene.flattened_triangles()?;
    Ok((tris, scene, t.elapsed().as_secs_f64() * 1e3))
}

fn primary_rays(scene: &bvhtrace_scene::Scene, w: u32, h: u32) -> Vec<Ray> {
    scene.camera_or_frame(w as f32 / h as f32).rays(w, h)
}

/// The walk whose box and triangle tests `bench-build` counts on every ray kind.
const COUNT_WALK: Traversal = Traversal::FullStack;

/// The ray kinds `bench-build` counts tests on, with their queries: the rays `bvhtrace
/// cost` and `bvhtrace bench` trace ([`ray_sets`]).
const RAY_KINDS: [(&str, Query); 3] = [
    ("primary", Query::Closest),
    ("shadow", Query::Any),
    ("diffuse", Query::Closest),
];

/// The walks timed on primary rays (the second table).
const SPEED_WALKS: [Traversal; 3] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(6),
];

/// Timed traces per walk in the second table (the median is printed).
const SPEED_RUNS: usize = 3;

/// `bench-build --help`: what is built, what is traced, what each column means.
pub fn build_long_about() -> String {
    [
        "Benchmark the builders: for each scene and builder configuration, the build time,",
        "the tree's quality as the SAH predicts it, and what real rays cost in it, counted.",
        "",
        "Configurations (--builders): every builder with its default options (binned sah,",
        "sweep-sah, median, midpoint, sbvh with split budget 0.3); sah:ctrav=1 (traversal",
        "cost 1, the objective tinybvh's figures use); sah+optimize, median+optimize and",
        "midpoint+optimize (the built tree then optimised by reinsertion, Bittner et al.",
        "2013); sbvh:budget=1 (up to one extra reference per triangle). The +optimize rows",
        "take the longest (seconds per build at 10^5 triangles): --builders picks fewer.",
        "",
        "Rays, made once per scene and the same for every configuration (those `bvhtrace",
        "cost` and `bvhtrace bench` trace): primary rays (closest hit, --size, from the",
        "scene's camera or a framing one), shadow rays (any hit, from each primary hit",
        "toward a point light near the eye) and diffuse rays (closest hit, one",
        "cosine-distributed bounce from each primary hit).",
        "",
        "First table, one row per configuration:",
        "  build ms   median wall time of --runs builds, flat layout included",
        "  SAH(1,1)   SAH cost, traversal 1 and intersection 1, over the root's area:",
        "             tinybvh's SAHCost convention (interior: area; leaf: area x triangles)",
        "  SAH pbrt   the same with PBRT's costs (traversal 1/8, intersection 1); lower is",
        "             better in both, and the two reward slightly different trees",
        "  nodes      nodes, interior and leaves",
        "  depth      longest root-to-leaf path, in edges",
        "  refs/tri   triangle references per distinct triangle: 1, but for an SBVH, whose",
        "             spatial splits may put a triangle in several leaves",
        "  box, tri   box tests and triangle tests per ray of the CPU full-stack walk,",
        "             counted on the primary, shadow and diffuse rays",
        "",
        "Second table, primary rays on the CPU: Mrays/s (median of 3 traces, counters off)",
        "and box tests per ray of the full-stack, stackless and short-stack(6) walks.",
        "",
        "--json writes every figure (each build's time too); with --json - the tables go to",
        "stderr. A progress bar shows on stderr when it is a terminal.",
    ]
    .join("\n")
}

/// One `bench-build` configuration: the options a builder runs with, named as `--builders`
/// takes it.
#[derive(Clone, Debug)]
pub struct BuildConfig {
    /// The name in the tables and the JSON (`BUILDER[+optimize][:KEY=VALUE]...`).
    pub name: String,
    /// The options.
    pub opts: BuildOptions,
}

impl BuildConfig {
    /// The default list: every builder of [`BuilderKind::ALL`] with default options, each
    /// followed by its variants (`sah:ctrav=1`, `+optimize` for sah, median and midpoint,
    /// `sbvh:budget=1`).
    pub fn defaults() -> Vec<BuildConfig> {
        let mut v = Vec::new();
        for b in BuilderKind::ALL {
            let base = BuildOptions::with_builder(b);
            v.push(BuildConfig {
                name: b.name().to_string(),
                opts: base,
            });
            match b {
                BuilderKind::Sah => v.push(BuildConfig {
                    name: "sah:ctrav=1".into(),
                    opts: BuildOptions {
                        cost_traversal: 1.0,
                        ..base
                    },
                }),
                BuilderKind::Sbvh => v.push(BuildConfig {
                    name: "sbvh:budget=1".into(),
                    opts: BuildOptions {
                        split_budget: 1.0,
                        ..base
                    },
                }),
                _ => {}
            }
            if matches!(
                b,
                BuilderKind::Sah | BuilderKind::Median | BuilderKind::Midpoint
            ) {
                v.push(BuildConfig {
                    name: format!("{}+optimize", b.name()),
                    opts: BuildOptions {
                        optimize: true,
                        ..base
                    },
                });
            }
        }
        v
    }
}

impl std::str::FromStr for BuildConfig {
    type Err = String;

    /// `BUILDER[+optimize][:KEY=VALUE]...`, keys `ctrav` (traversal cost), `bins`,
    /// `budget` (SBVH split budget) and `leaf` (max leaf size); checked as a build checks.
    fn from_str(s: &str) -> Result<Self, String> {
        let s = s.trim();
        let mut parts = s.split(':');
        let head = parts.next().unwrap_or_default();
        let (builder, optimize) = match head.strip_suffix("+optimize") {
            Some(b) => (b, true),
            None => (head, false),
        };
        let mut opts = BuildOptions {
            optimize,
            ..BuildOptions::with_builder(builder.parse()?)
        };
        for p in parts {
            let (k, v) = p
                .split_once('=')
                .ok_or_else(|| format!("'{p}' in '{s}': expected KEY=VALUE"))?;
            let bad = |e: &dyn std::fmt::Display| format!("'{p}' in '{s}': {e}");
            match k {
                "ctrav" => opts.cost_traversal = v.parse().map_err(|e| bad(&e))?,
                "bins" => opts.bins = v.parse().map_err(|e| bad(&e))?,
                "budget" => opts.split_budget = v.parse().map_err(|e| bad(&e))?,
                "leaf" => opts.max_leaf_size = v.parse().map_err(|e| bad(&e))?,
                _ => {
                    return Err(format!(
                        "unknown key '{k}' in '{s}' (expected ctrav, bins, budget or leaf)"
                    ));
                }
            }
        }
        opts.validate().map_err(|e| format!("'{s}': {e}"))?;
        Ok(BuildConfig {
            name: s.to_string(),
            opts,
        })
    }
}

/// `bvhtrace bench-build`.
#[derive(clap::Args)]
pub struct BenchBuildArgs {
    /// Scenes: .gltf/.glb files or `builtin:` names (default: bunny_69k and igea from
    /// ../shared/scenes; when that folder is absent, a note and nothing else).
    pub scenes: Vec<String>,
    /// Timed builds per configuration (the median is printed).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    #[command(flatten)]
    pub primary: crate::render::PrimarySize,
    /// Configurations, comma-separated: BUILDER[+optimize][:KEY=VALUE]..., BUILDER one of
    /// sah, sweep-sah, median, midpoint, sbvh; keys ctrav (traversal cost, PBRT's 0.125 by
    /// default), bins, budget (SBVH split budget), leaf (max leaf size); e.g.
    /// `sah,sah:ctrav=1,sweep-sah:ctrav=1,sah+optimize,sbvh:budget=0.5`. Default: every
    /// builder, sah:ctrav=1, sah+optimize, median+optimize, midpoint+optimize,
    /// sbvh:budget=1.
    #[arg(long, value_name = "CONFIG,...", value_delimiter = ',')]
    pub builders: Vec<BuildConfig>,
    /// Write every figure as JSON (`-` for stdout; the tables then go to stderr).
    #[arg(long, value_name = "FILE|-")]
    pub json: Option<String>,
    /// An `embree_trace` binary (`crates/cli/embree/embree_trace.c`): Embree 3's medium
    /// build of the same triangles, with the same thread count and number of runs, is timed
    /// before and after the configurations, and each row gets its build time over
    /// Embree's (`/embree`: the mean of the two medians).
    #[arg(long, value_name = "BIN")]
    pub embree: Option<std::path::PathBuf>,
}

/// `bench-build --json`: the whole document.
#[derive(serde::Serialize)]
struct BuildReport {
    /// Worker threads.
    threads: usize,
    /// Timed builds per configuration.
    runs: usize,
    /// Primary rays, [w, h].
    size: [u32; 2],
    /// The walk the `tests` figures count.
    count_walk: String,
    /// One entry per scene, in the order given.
    scenes: Vec<BuildScene>,
}

/// One scene's figures.
#[derive(serde::Serialize)]
struct BuildScene {
    /// The scene as given.
    scene: String,
    /// Triangles after flattening the scene.
    triangles: usize,
    /// Load time, milliseconds.
    load_ms: f64,
    /// One entry per configuration, in order.
    configs: Vec<BuildRow>,
    /// With `--embree`: Embree 3's medium build, median of `runs` before the
    /// configurations and after them, milliseconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    embree_build_ms: Option<[f64; 2]>,
}

/// One configuration's figures on one scene.
#[derive(serde::Serialize)]
struct BuildRow {
    /// As `--builders` names it.
    name: String,
    /// The builder.
    builder: &'static str,
    /// The options built with.
    options: OptionsJson,
    /// Median build time, milliseconds.
    build_ms: f64,
    /// With `--embree`: `build_ms` over Embree's (the mean of its two medians).
    #[serde(skip_serializing_if = "Option::is_none")]
    vs_embree: Option<f64>,
    /// Every timed build, milliseconds, in run order.
    build_ms_runs: Vec<f64>,
    /// SAH cost, traversal 1 and intersection 1 (`BvhStats::sah_cost`).
    sah_cost: f64,
    /// SAH cost, traversal 1/8 and intersection 1 (`BvhStats::sah_cost_pbrt`).
    sah_cost_pbrt: f64,
    /// Nodes, interior and leaves.
    nodes: usize,
    /// Leaves.
    leaves: usize,
    /// Longest root-to-leaf path, in edges.
    depth: u32,
    /// Triangle references in the leaves.
    references: usize,
    /// Distinct triangles among them.
    primitives: usize,
    /// `references / primitives`.
    references_per_triangle: f64,
    /// Box and triangle tests per ray of `count_walk`, by ray kind.
    tests: BTreeMap<&'static str, RayTests>,
    /// CPU speed on primary rays, by walk.
    cpu: Vec<WalkSpeed>,
}

/// [`BuildOptions`] as JSON.
#[derive(serde::Serialize)]
struct OptionsJson {
    bins: usize,
    cost_traversal: f32,
    cost_intersection: f32,
    max_leaf_size: usize,
    max_depth: usize,
    optimize: bool,
    split_budget: f32,
}

impl From<&BuildOptions> for OptionsJson {
    fn from(o: &BuildOptions) -> Self {
        OptionsJson {
            bins: o.bins,
            cost_traversal: o.cost_traversal,
            cost_intersection: o.cost_intersection,
            max_leaf_size: o.max_leaf_size,
            max_depth: o.max_depth,
            optimize: o.optimize,
            split_budget: o.split_budget,
        }
    }
}

/// Counted work on one ray kind.
#[derive(serde::Serialize, Clone, Copy)]
struct RayTests {
    /// The query (`closest` or `any`).
    query: &'static str,
    /// Rays traced.
    ray_count: usize,
    /// Box tests per ray (null without rays).
    boxes_per_ray: Option<f64>,
    /// Triangle tests per ray (null without rays).
    tris_per_ray: Option<f64>,
}

/// One walk's speed on the primary rays.
#[derive(serde::Serialize)]
struct WalkSpeed {
    /// The walk.
    walk: String,
    /// Median of the timed traces, counters off.
    mrays_per_s: f64,
    /// Box tests per ray.
    boxes_per_ray: f64,
}

/// Prints lines around a progress bar, to stdout or (when JSON takes stdout) stderr.
struct Lines<'a> {
    pb: &'a ProgressBar,
    to_stderr: bool,
}

impl Lines<'_> {
    fn say(&self, s: &str) -> Result<()> {
        use std::io::Write;
        let s = s.trim_end();
        self.pb
            .suspend(|| {
                if self.to_stderr {
                    writeln!(std::io::stderr(), "{s}")
                } else {
                    writeln!(std::io::stdout(), "{s}")
                }
            })
            .context("cannot write the table")
    }
}

/// The default scenes that exist, with a note for each one missing; none (and a note)
/// without the shared folder.
fn default_build_scenes() -> Vec<String> {
    let Some(dir) = crate::geometry::shared_scenes_dir() else {
        eprintln!(
            "bench-build: no scenes given and no shared scenes folder (../shared/scenes; \
             set BVHTRACE_SCENES) found: nothing to benchmark"
        );
        return Vec::new();
    };
    ["bunny_69k", "igea"]
        .iter()
        .map(|n| dir.join("glb").join(format!("{n}.glb")))
        .filter(|p| {
            let ok = p.is_file();
            if !ok {
                eprintln!("bench-build: {} not found, skipped", p.display());
            }
            ok
        })
        .map(|p| p.display().to_string())
        .collect()
}

/// Milliseconds with three significant digits or more (tiny scenes build in microseconds).
fn fmt_ms(ms: f64) -> String {
    match ms {
        x if x < 1.0 => format!("{x:.3}"),
        x if x < 10.0 => format!("{x:.2}"),
        x => format!("{x:.1}"),
    }
}

/// Mean of `f` over the counters, `None` when there are none.
fn per_ray(c: &[Counters], f: fn(&Counters) -> u32) -> Option<f64> {
    (!c.is_empty()).then(|| c.iter().map(|c| f64::from(f(c))).sum::<f64>() / c.len() as f64)
}

/// `bvhtrace bench-build`.
pub fn bench_build(args: BenchBuildArgs) -> Result<()> {
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let (w, h) = args.primary.size;
    // Reserve the JSON destination before any work, so a bad path fails at once.
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let to_stderr = matches!(json_out, Some(JsonOut::Stdout));
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads.unwrap_or(0))
        .build()?;
    let configs = if args.builders.is_empty() {
        BuildConfig::defaults()
    } else {
        args.builders.clone()
    };
    let specs = if args.scenes.is_empty() {
        default_build_scenes()
    } else {
        args.scenes.clone()
    };
    let per_config = (args.runs + RAY_KINDS.len() + SPEED_WALKS.len()) as u64;
    let pb = ProgressBar::new(specs.len() as u64 * configs.len() as u64 * per_config);
    pb.set_style(
        ProgressStyle::with_template("{msg:56} [{bar:30}] {pos}/{len} ({elapsed}, eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.enable_steady_tick(Duration::from_millis(200));
    let out = Lines { pb: &pb, to_stderr };
    let mut report = BuildReport {
        threads: pool.current_num_threads(),
        runs: args.runs,
        size: [w, h],
        count_walk: COUNT_WALK.to_string(),
        scenes: Vec::new(),
    };
    out.say(&format!("threads: {}", report.threads))?;
    for spec in &specs {
        pb.set_message(format!("{spec}: loading"));
        let (tris, scene, load_ms) = load(spec)?;
        pb.set_message(format!("{spec}: making rays"));
        let cam = scene.camera_or_frame(w as f32 / h as f32);
        let sets = pool.install(|| -> Result<_> {
            let reference = FlatBvh::build(&tris, &BuildOptions::default())
                .with_context(|| format!("{spec}: cannot build a BVH"))?;
            Ok(ray_sets(&tris, &reference, &cam, w, h))
        })?;
        let kinds: [(&'static str, Query, &[Ray]); 3] = [
            (RAY_KINDS[0].0, RAY_KINDS[0].1, &sets.primary),
            (RAY_KINDS[1].0, RAY_KINDS[1].1, &sets.shadow),
            (RAY_KINDS[2].0, RAY_KINDS[2].1, &sets.diffuse),
        ];
        let threads = pool.current_num_threads();
        let embree_build = |dump: &Dump, exe: &std::path::Path| -> Result<f64> {
            pb.set_message(format!("{spec}: Embree builds"));
            let v = dump.run(exe, threads, args.runs, &[])?;
            embree::field(&v, "build_ms", exe)
        };
        let embree_dump = match &args.embree {
            Some(exe) => {
                pb.set_message(format!("{spec}: writing the Embree dump"));
                let dump = Dump::write(
                    "build",
                    &tris,
                    &sets.primary[..sets.primary.len().min(1024)],
                )?;
                let before = embree_build(&dump, exe)?;
                Some((exe, dump, before))
            }
            None => None,
        };
        let name_w = configs
            .iter()
            .map(|c| c.name.len())
            .max()
            .unwrap_or(0)
            .max(18);
        out.say(&format!(
            "\n{spec}: {} triangles, loaded in {load_ms:.1} ms; rays: {} primary ({w}x{h}), \
             {} shadow, {} diffuse",
            tris.len(),
            sets.primary.len(),
            sets.shadow.len(),
            sets.diffuse.len()
        ))?;
        out.say(&format!(
            "{:name_w$} {:>9} {:>8} {:>8} {:>8} {:>5} {:>8} | {:^14} | {:^14} | {:^14}",
            "", "", "", "", "", "", "", "primary", "shadow", "diffuse"
        ))?;
        out.say(&format!(
            "{:name_w$} {:>9} {:>8} {:>8} {:>8} {:>5} {:>8} | {:>7} {:>6} | {:>7} {:>6} | {:>7} {:>6}",
            "config",
            "build ms",
            "SAH(1,1)",
            "SAH pbrt",
            "nodes",
            "depth",
            "refs/tri",
            "box",
            "tri",
            "box",
            "tri",
            "box",
            "tri"
        ))?;
        let mut rows = Vec::new();
        for cfg in &configs {
            let what = format!("{spec}: {}", cfg.name);
            let mut times = Vec::new();
            let mut bvh = None;
            for i in 0..args.runs {
                pb.set_message(format!("{what}: build {}/{}", i + 1, args.runs));
                drop(bvh.take()); // one tree in memory at a time
                let t = Instant::now();
                let b = pool
                    .install(|| FlatBvh::build(&tris, &cfg.opts))
                    .with_context(|| format!("{what}: build failed"))?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
                bvh = Some(b);
                pb.inc(1);
            }
            let bvh = bvh.context("no build ran")?;
            let s = BvhStats::of(&bvh);
            let mut tests = BTreeMap::new();
            for (kind, query, rays) in kinds {
                pb.set_message(format!("{what}: {kind} rays"));
                let opts = TraceOptions::new(COUNT_WALK, query).with_counters(true);
                let c = pool
                    .install(|| trace_rays(&bvh, rays, &opts))
                    .counters
                    .unwrap_or_default();
                tests.insert(
                    kind,
                    RayTests {
                        query: if query == Query::Any {
                            "any"
                        } else {
                            "closest"
                        },
                        ray_count: rays.len(),
                        boxes_per_ray: per_ray(&c, |c| c.nodes),
                        tris_per_ray: per_ray(&c, |c| c.tris),
                    },
                );
                pb.inc(1);
            }
            let mut cpu = Vec::new();
            for walk in SPEED_WALKS {
                pb.set_message(format!("{what}: {walk} speed"));
                let rays = &sets.primary;
                let opts = TraceOptions::closest(walk);
                let counted = opts.with_counters(true);
                let c = pool
                    .install(|| trace_rays(&bvh, rays, &counted))
                    .counters
                    .unwrap_or_default();
                let secs = median(
                    (0..SPEED_RUNS)
                        .map(|_| {
                            let t = Instant::now();
                            std::hint::black_box(pool.install(|| trace_rays(&bvh, rays, &opts)));
                            t.elapsed().as_secs_f64()
                        })
                        .collect(),
                );
                cpu.push(WalkSpeed {
                    walk: walk.to_string(),
                    mrays_per_s: rays.len() as f64 / secs / 1e6,
                    boxes_per_ray: per_ray(&c, |c| c.nodes).unwrap_or(0.0),
                });
                pb.inc(1);
            }
            let refs_per_tri = s.triangles as f64 / s.primitives.max(1) as f64;
            let test_cols: Vec<String> = kinds
                .iter()
                .map(|(k, ..)| match tests[k] {
                    RayTests {
                        boxes_per_ray: Some(b),
                        tris_per_ray: Some(t),
                        ..
                    } => format!("{b:>7.1} {t:>6.2}"),
                    _ => format!("{:>7} {:>6}", "-", "-"),
                })
                .collect();
            let row = BuildRow {
                name: cfg.name.clone(),
                builder: cfg.opts.builder.name(),
                options: OptionsJson::from(&cfg.opts),
                build_ms: median(times.clone()),
                vs_embree: None,
                build_ms_runs: times,
                sah_cost: s.sah_cost,
                sah_cost_pbrt: s.sah_cost_pbrt,
                nodes: s.nodes,
                leaves: s.leaves,
                depth: s.depth,
                references: s.triangles,
                primitives: s.primitives,
                references_per_triangle: refs_per_tri,
                tests,
                cpu,
            };
            out.say(&format!(
                "{:name_w$} {:>9} {:>8.2} {:>8.3} {:>8} {:>5} {:>8.3} | {} | {} | {}",
                row.name,
                fmt_ms(row.build_ms),
                row.sah_cost,
                row.sah_cost_pbrt,
                row.nodes,
                row.depth,
                row.references_per_triangle,
                test_cols[0],
                test_cols[1],
                test_cols[2]
            ))?;
            rows.push(row);
        }
        let embree_build_ms = match &embree_dump {
            Some((exe, dump, before)) => {
                let after = embree_build(dump, exe)?;
                let e = (before + after) / 2.0;
                out.say(&format!(
                    "Embree 3 medium build, {threads} threads: {before:.1} ms before, {after:.1} ms \
                     after (medians of {}); build ms / Embree:",
                    args.runs
                ))?;
                for row in &mut rows {
                    row.vs_embree = Some(row.build_ms / e);
                    out.say(&format!("  {:name_w$} {:.2}x", row.name, row.build_ms / e))?;
                }
                Some([*before, after])
            }
            None => None,
        };
        out.say(&format!(
            "\nCPU walks, {} primary rays ({w}x{h}), {} threads: Mrays/s (median of {SPEED_RUNS}), \
             box tests per ray",
            sets.primary.len(),
            report.threads
        ))?;
        let heads = SPEED_WALKS.map(|w| format!("{w} Mr/s box/ray"));
        let col_w = heads.iter().map(String::len).max().unwrap_or(0);
        let mut head = format!("{:name_w$}", "config");
        for h in &heads {
            head += &format!(" | {h:>col_w$}");
        }
        out.say(&head)?;
        let mr_w = col_w - 9;
        for row in &rows {
            let mut line = format!("{:name_w$}", row.name);
            for c in &row.cpu {
                line += &format!(" | {:>mr_w$.2} {:>8.1}", c.mrays_per_s, c.boxes_per_ray);
            }
            out.say(&line)?;
        }
        report.scenes.push(BuildScene {
            scene: spec.clone(),
            triangles: tris.len(),
            load_ms,
            configs: rows,
            embree_build_ms,
        });
    }
    pb.finish_and_clear();
    if let Some(j) = json_out {
        j.write(&serde_json::to_value(&report)?)?;
    }
    Ok(())
}

/// The CPU layout's rows of `bench-trace`'s table: one per instruction set, its Mrays/s
/// over `n` rays (medians of `ms`) and its speed against Embree's (`embree_ms`, the same
/// rounds), the GPU columns empty.
fn print_cpu_layout_rows(
    isas: &[bvhtrace_cpu::Isa],
    q: Query,
    ms: &[Vec<f64>],
    embree_ms: &[f64],
    n: f64,
) {
    for (isa, ms) in isas.iter().zip(ms) {
        let vs_embree = if embree_ms.is_empty() {
            "-".to_string()
        } else {
            let ratios = embree_ms.iter().zip(ms).map(|(a, b)| a / b).collect();
            format!("{:.2}x", median(ratios))
        };
        println!(
            "{:16} {:8} {:>9} {:>9} {:>9.2} {:>7} {:>6} {:>7} {:>8} {:>8} {:>8} {:>10}",
            format!("cpu8 {isa}"),
            format!("{q:?}").to_lowercase(),
            "-",
            "-",
            n / median(ms.clone()) / 1e3,
            "-",
            "-",
            "-",
            "-",
            "-",
            "-",
            vs_embree,
        );
    }
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
    /// Only the CPU paths, without a device: the core walks (`--traversals`, default
    /// full-stack and wide) and the CPU layout (`bvhtrace-cpu`, each instruction set the
    /// CPU has) on primary (closest-hit) and shadow (any-hit) rays, beside Embree 3's
    /// default and robust modes with `--embree`, and each path's differences from the
    /// full stack's answers.
    #[arg(long)]
    pub cpu_only: bool,
}

/// `bvhtrace bench-trace`.
pub fn bench_trace(args: BenchTraceArgs) -> Result<()> {
    let (w, h) = args.size;
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    if args.cpu_only {
        return crate::bench_cpu::bench_trace_cpu(&args);
    }
    // The automatic choice's device: wgpu, with its ray queries when it has them (they are
    // measured beside our walks whichever the choice would trace with).
    let device = crate::backend::device(&crate::backend::options(
        crate::backend::Backend::Auto,
        args.adapter.as_deref(),
        &[],
    ))?;
    let ctx = device
        .wgpu_context()
        .context("bench-trace measures the wgpu backend, and there is no Vulkan adapter")?;
    let info = ctx.adapter_info();
    println!(
        "adapter: {} ({:?}); CPU: {} threads",
        info.name,
        info.device_type,
        rayon::current_num_threads()
    );
    if args.everything_on {
        return compare_everything_on(ctx, &args, w, h);
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
        // The CPU layout (`bvhtrace-cpu`), timed beside the walks on each instruction set.
        let cpu_layout = bvhtrace_cpu::CpuBvh::from_flat(&bvh)?;
        let isas = bvhtrace_cpu::Isa::all_available();
        let rays = primary_rays(&scene, w, h);
        let upload = bvhtrace::OpenOptions {
            traversals: traversals.clone(),
            ..Default::default()
        };
        let gpu = bvhtrace::Device::wgpu(ctx.clone())
            .open_owned(&bvh, &upload)?
            .tracer;
        // The device's ray queries on the same rays, when it has them.
        let rq = match ctx.has_ray_queries() {
            true => Some(
                bvhtrace::Device::ray_query(ctx.clone())?
                    .open_owned(&bvh, &upload)?
                    .tracer,
            ),
            false => None,
        };
        let dump = match &args.embree {
            Some(_) => Some(Dump::write("trace", &tris, &rays)?),
            None => None,
        };
        println!(
            "\n{spec}: {} triangles, depth {}, {} rays ({w}x{h}); our build {build_ms:.1} ms \
             (+{wide_ms:.1} ms to the wide layout)",
            tris.len(),
            bvh.depth(),
            rays.len()
        );
        if let Some(build) = rq.as_ref().and_then(|t| t.device_build_ms()) {
            println!(
                "ray queries: the driver's build {build:.1} ms (a BLAS over the triangles in \
                 our leaf order, a TLAS), beside our build {build_ms:.1} ms"
            );
        }
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
            let mut cpu_layout_ms = vec![Vec::new(); isas.len()];
            let (mut embree_ms, mut embree_build_ms) = (Vec::new(), Vec::new());
            let mut rq_ms = Vec::new();
            if let Some(rq) = &rq {
                rq.trace(&rays, &TraceOptions::new(traversals[0], q))?;
            }
            for _ in 0..args.runs {
                if let Some(rq) = &rq {
                    rq_ms.push(
                        rq.trace(&rays, &TraceOptions::new(traversals[0], q))?
                            .wall_ms,
                    );
                }
                for (i, &tr) in traversals.iter().enumerate() {
                    let opts = TraceOptions::new(tr, q);
                    let o = gpu.trace(&rays, &opts)?;
                    wall_ms[i].push(o.wall_ms);
                    gpu_ms[i].push(o.gpu_ms.unwrap_or(o.wall_ms));
                    let t = Instant::now();
                    std::hint::black_box(trace_rays(&bvh, &rays, &opts));
                    cpu_ms[i].push(t.elapsed().as_secs_f64() * 1e3);
                }
                for (i, &isa) in isas.iter().enumerate() {
                    let t = Instant::now();
                    std::hint::black_box(bvhtrace_cpu::trace_rays_with(&cpu_layout, &rays, q, isa));
                    cpu_layout_ms[i].push(t.elapsed().as_secs_f64() * 1e3);
                }
                if let (Some(exe), Some(dump), Query::Closest) = (&args.embree, &dump, q) {
                    let v = dump.run(exe, 2, 1, &[])?;
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
            print_cpu_layout_rows(&isas, q, &cpu_layout_ms, &embree_ms, n);
            if !rq_ms.is_empty() {
                // Wall time only (the driver's walk has no timestamps of ours); ratios
                // against the first walk's wall time and its CPU twin's.
                println!(
                    "{:16} {:8} {:>9} {:>9.2} {:>9} {:>7} {:>6} {:>7} {:>7.2}x {:>8} {:>7.2}x {:>10}",
                    "ray-query",
                    format!("{q:?}").to_lowercase(),
                    "-",
                    mrays(&rq_ms),
                    "-",
                    "-",
                    "-",
                    "-",
                    ratio(&wall_ms[0], &rq_ms),
                    "-",
                    ratio(&cpu_ms[0], &rq_ms),
                    "-",
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
            bvh.nodes().len(),
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
