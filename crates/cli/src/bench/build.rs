//! `bvhtrace bench-build`: each builder configuration's build time, the quality of its
//! tree as the SAH predicts it, and what real rays cost in it, counted and timed.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use bvhtrace_core::{
    BuildOptions, BuilderKind, BvhStats, Counters, FlatBvh, Query, Ray, TraceOptions, Traversal,
    Triangle, trace_rays,
};
use indicatif::ProgressBar;

use super::{load, median, ray_sets};
use crate::embree::{self, Dump};
use crate::output::JsonOut;

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
pub fn long_about() -> String {
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
    /// An `embree_trace` binary (`crates/cli/embree/embree_trace.c`, built against Embree
    /// 3 or 4): Embree's medium build of the same triangles, with the same thread count
    /// and number of runs, is timed before and after the configurations, and each row
    /// gets its build time over Embree's (`/embree`: the mean of the two medians).
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
    /// With `--embree`: Embree's medium build, median of `runs` before the
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
pub fn run(args: BenchBuildArgs) -> Result<()> {
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
    let pb = progress_bar(specs.len() as u64 * configs.len() as u64 * per_config);
    let out = Lines { pb: &pb, to_stderr };
    let mut report = BuildReport {
        threads: pool.current_num_threads(),
        runs: args.runs,
        size: [w, h],
        count_walk: COUNT_WALK.to_string(),
        scenes: Vec::new(),
    };
    out.say(&format!("threads: {}", report.threads))?;
    let bench = Bench {
        args: &args,
        pool: &pool,
        pb: &pb,
        out: &out,
        configs: &configs,
    };
    for spec in &specs {
        report.scenes.push(bench.scene(spec)?);
    }
    pb.finish_and_clear();
    if let Some(j) = json_out {
        j.write(&serde_json::to_value(&report)?)?;
    }
    Ok(())
}

/// The progress bar of `len` steps (builds, counted traces, timed walks), on stderr.
fn progress_bar(len: u64) -> ProgressBar {
    let pb = crate::output::progress_bar(
        len,
        "{msg:56} [{bar:30}] {pos}/{len} ({elapsed}, eta {eta})",
    );
    pb.enable_steady_tick(Duration::from_millis(200));
    pb
}

/// A ray kind of [`RAY_KINDS`] with its rays.
type Kind<'a> = (&'static str, Query, &'a [Ray]);

/// What every scene of a `bench-build` run shares: the flags, the worker threads, the
/// progress bar and the lines printed around it, and the configurations.
struct Bench<'a> {
    args: &'a BenchBuildArgs,
    pool: &'a rayon::ThreadPool,
    pb: &'a ProgressBar,
    out: &'a Lines<'a>,
    configs: &'a [BuildConfig],
}

impl Bench<'_> {
    /// One scene: its rays made, every configuration built, counted and timed, the two
    /// tables printed (and Embree's builds before and after with `--embree`).
    fn scene(&self, spec: &str) -> Result<BuildScene> {
        let (w, h) = self.args.primary.size;
        self.pb.set_message(format!("{spec}: loading"));
        let (tris, scene, load_ms) = load(spec)?;
        self.pb.set_message(format!("{spec}: making rays"));
        let cam = scene.camera_or_frame(w as f32 / h as f32);
        let sets = self.pool.install(|| -> Result<_> {
            let reference = FlatBvh::build(&tris, &BuildOptions::default())
                .with_context(|| format!("{spec}: cannot build a BVH"))?;
            Ok(ray_sets(&tris, &reference, &cam, w, h))
        })?;
        let kinds: [Kind; 3] = [
            (RAY_KINDS[0].0, RAY_KINDS[0].1, &sets.primary),
            (RAY_KINDS[1].0, RAY_KINDS[1].1, &sets.shadow),
            (RAY_KINDS[2].0, RAY_KINDS[2].1, &sets.diffuse),
        ];
        let embree_dump = match &self.args.embree {
            Some(exe) => {
                self.pb
                    .set_message(format!("{spec}: writing the Embree dump"));
                let primary = &sets.primary[..sets.primary.len().min(1024)];
                let dump = Dump::write("build", &tris, primary)?;
                let (before, _) = self.embree_build(spec, &dump, exe)?;
                Some((exe, dump, before))
            }
            None => None,
        };
        let name_w = (self.configs.iter().map(|c| c.name.len()))
            .max()
            .unwrap_or(0)
            .max(18);
        self.out.say(&format!(
            "\n{spec}: {} triangles, loaded in {load_ms:.1} ms; rays: {} primary ({w}x{h}), \
             {} shadow, {} diffuse",
            tris.len(),
            sets.primary.len(),
            sets.shadow.len(),
            sets.diffuse.len()
        ))?;
        self.print_head(name_w)?;
        let mut rows = Vec::new();
        for cfg in self.configs {
            let row = self.row(spec, cfg, &tris, &kinds)?;
            self.print_row(&row, &kinds, name_w)?;
            rows.push(row);
        }
        let embree_build_ms = match &embree_dump {
            Some((exe, dump, before)) => {
                Some(self.embree_ratios(spec, exe, dump, *before, &mut rows, name_w)?)
            }
            None => None,
        };
        self.print_speeds(&rows, sets.primary.len(), name_w)?;
        Ok(BuildScene {
            scene: spec.to_string(),
            triangles: tris.len(),
            load_ms,
            configs: rows,
            embree_build_ms,
        })
    }

    /// Embree's medium build of the dump's triangles, median of `--runs`, milliseconds,
    /// and the Embree the helper runs (`Embree 4.4.0`).
    fn embree_build(
        &self,
        spec: &str,
        dump: &Dump,
        exe: &std::path::Path,
    ) -> Result<(f64, String)> {
        self.pb.set_message(format!("{spec}: Embree builds"));
        let threads = self.pool.current_num_threads();
        let v = dump.run(exe, threads, self.args.runs, &[])?;
        Ok((embree::field(&v, "build_ms", exe)?, embree::version(&v)))
    }

    /// Embree's builds after the configurations, and each row's build time over the mean
    /// of Embree's before and after (printed, and kept in the rows): the two medians.
    fn embree_ratios(
        &self,
        spec: &str,
        exe: &std::path::Path,
        dump: &Dump,
        before: f64,
        rows: &mut [BuildRow],
        name_w: usize,
    ) -> Result<[f64; 2]> {
        let (after, version) = self.embree_build(spec, dump, exe)?;
        let e = (before + after) / 2.0;
        self.out.say(&format!(
            "{version} medium build, {} threads: {before:.1} ms before, {after:.1} ms \
             after (medians of {}); build ms / Embree:",
            self.pool.current_num_threads(),
            self.args.runs
        ))?;
        for row in rows {
            row.vs_embree = Some(row.build_ms / e);
            self.out
                .say(&format!("  {:name_w$} {:.2}x", row.name, row.build_ms / e))?;
        }
        Ok([before, after])
    }

    /// The first table's two header lines.
    fn print_head(&self, name_w: usize) -> Result<()> {
        self.out.say(&format!(
            "{:name_w$} {:>9} {:>8} {:>8} {:>8} {:>5} {:>8} | {:^14} | {:^14} | {:^14}",
            "", "", "", "", "", "", "", "primary", "shadow", "diffuse"
        ))?;
        self.out.say(&format!(
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
        ))
    }

    /// One configuration's row: its tree built `--runs` times, its quality, its tests per
    /// ray of every kind, and the CPU walks' speed on the primary rays.
    fn row(
        &self,
        spec: &str,
        cfg: &BuildConfig,
        tris: &[Triangle],
        kinds: &[Kind; 3],
    ) -> Result<BuildRow> {
        let what = format!("{spec}: {}", cfg.name);
        let (bvh, times) = self.timed_builds(&what, cfg, tris)?;
        let s = BvhStats::of(&bvh);
        let tests = self.count_tests(&what, &bvh, kinds);
        let cpu = self.walk_speeds(&what, &bvh, kinds[0].2);
        Ok(BuildRow {
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
            references_per_triangle: s.triangles as f64 / s.primitives.max(1) as f64,
            tests,
            cpu,
        })
    }

    /// `cfg`'s tree over `tris`, built `--runs` times (one tree in memory at a time): the
    /// last one and every build's time, milliseconds.
    fn timed_builds(
        &self,
        what: &str,
        cfg: &BuildConfig,
        tris: &[Triangle],
    ) -> Result<(FlatBvh, Vec<f64>)> {
        let runs = self.args.runs;
        let mut times = Vec::new();
        let mut bvh = None;
        for i in 0..runs {
            self.pb
                .set_message(format!("{what}: build {}/{runs}", i + 1));
            drop(bvh.take()); // one tree in memory at a time
            let t = Instant::now();
            let b = (self.pool)
                .install(|| FlatBvh::build(tris, &cfg.opts))
                .with_context(|| format!("{what}: build failed"))?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            bvh = Some(b);
            self.pb.inc(1);
        }
        Ok((bvh.context("no build ran")?, times))
    }

    /// Box and triangle tests per ray of [`COUNT_WALK`] in `bvh`, by ray kind.
    fn count_tests(
        &self,
        what: &str,
        bvh: &FlatBvh,
        kinds: &[Kind; 3],
    ) -> BTreeMap<&'static str, RayTests> {
        let mut tests = BTreeMap::new();
        for &(kind, query, rays) in kinds {
            self.pb.set_message(format!("{what}: {kind} rays"));
            let opts = TraceOptions::new(COUNT_WALK, query).with_counters(true);
            let c = (self.pool)
                .install(|| trace_rays(bvh, rays, &opts))
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
            self.pb.inc(1);
        }
        tests
    }

    /// The speed of each of [`SPEED_WALKS`] in `bvh` on the primary rays: the median of
    /// [`SPEED_RUNS`] traces without counters, and the box tests per ray of a counted one.
    fn walk_speeds(&self, what: &str, bvh: &FlatBvh, rays: &[Ray]) -> Vec<WalkSpeed> {
        let mut cpu = Vec::new();
        for walk in SPEED_WALKS {
            self.pb.set_message(format!("{what}: {walk} speed"));
            let opts = TraceOptions::closest(walk);
            let counted = opts.with_counters(true);
            let c = (self.pool)
                .install(|| trace_rays(bvh, rays, &counted))
                .counters
                .unwrap_or_default();
            let secs = median(
                (0..SPEED_RUNS)
                    .map(|_| {
                        let t = Instant::now();
                        std::hint::black_box(self.pool.install(|| trace_rays(bvh, rays, &opts)));
                        t.elapsed().as_secs_f64()
                    })
                    .collect(),
            );
            cpu.push(WalkSpeed {
                walk: walk.to_string(),
                mrays_per_s: rays.len() as f64 / secs / 1e6,
                boxes_per_ray: per_ray(&c, |c| c.nodes).unwrap_or(0.0),
            });
            self.pb.inc(1);
        }
        cpu
    }

    /// A row of the first table.
    fn print_row(&self, row: &BuildRow, kinds: &[Kind; 3], name_w: usize) -> Result<()> {
        let test_cols: Vec<String> = kinds
            .iter()
            .map(|(k, ..)| match row.tests[k] {
                RayTests {
                    boxes_per_ray: Some(b),
                    tris_per_ray: Some(t),
                    ..
                } => format!("{b:>7.1} {t:>6.2}"),
                _ => format!("{:>7} {:>6}", "-", "-"),
            })
            .collect();
        self.out.say(&format!(
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
        ))
    }

    /// The second table: each configuration's CPU walks on the `primary` rays.
    fn print_speeds(&self, rows: &[BuildRow], primary: usize, name_w: usize) -> Result<()> {
        let (w, h) = self.args.primary.size;
        self.out.say(&format!(
            "\nCPU walks, {primary} primary rays ({w}x{h}), {} threads: Mrays/s (median of \
             {SPEED_RUNS}), box tests per ray",
            self.pool.current_num_threads()
        ))?;
        let heads = SPEED_WALKS.map(|w| format!("{w} Mr/s box/ray"));
        let col_w = heads.iter().map(String::len).max().unwrap_or(0);
        let mut head = format!("{:name_w$}", "config");
        for h in &heads {
            head += &format!(" | {h:>col_w$}");
        }
        self.out.say(&head)?;
        let mr_w = col_w - 9;
        for row in rows {
            let mut line = format!("{:name_w$}", row.name);
            for c in &row.cpu {
                line += &format!(" | {:>mr_w$.2} {:>8.1}", c.mrays_per_s, c.boxes_per_ray);
            }
            self.out.say(&line)?;
        }
        Ok(())
    }
}
