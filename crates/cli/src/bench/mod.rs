//! The benchmarks: figures as commands, not tests. `bvhtrace bench` measures error against
//! run time for every configuration ([`matrix`]) or, with `--converge`, image error against
//! wall time ([`converge`]); `bench-build` the builders ([`build`]); `bench-trace` the walks
//! on a device beside the CPU ([`trace`]) or, with `--cpu-only`, every CPU path
//! ([`trace_cpu`]); `bench-refit` what moving things costs ([`refit`]); `tune` each walk
//! and storage on one device beside its default ([`tune`]).
//!
//! This module holds what they share (the scenes, the rays, the backends opened once, the
//! median) and the arguments of the two commands with more than one mode; `main` chooses
//! the mode, so that this module imports none of them and no mode imports another.
//! [`accuracy`] and [`plot`] are helpers of the matrix and of converge that import nothing
//! from the benchmarks.

mod accuracy;
pub mod build;
pub mod converge;
pub mod matrix;
mod plot;
pub mod refit;
pub mod trace;
pub mod trace_cpu;
pub mod tune;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace::{Backend, Device};
use bvhtrace_core::{BuilderKind, FlatBvh, Ray, TraceOptions, Traversal, Triangle, trace_rays};
use glam::Vec3;
use serde::Serialize;

use crate::shade;

/// The median of `v` (the upper one for an even length).
fn median(mut v: Vec<f64>) -> f64 {
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

/// `spec` loaded: its triangles flattened, the scene, and the load time in milliseconds.
fn load(spec: &str) -> Result<(Vec<Triangle>, bvhtrace_scene::Scene, f64)> {
    let t = Instant::now();
    let scene = crate::geometry::load_triangle_scene(spec)?;
    let tris = scene.flattened_triangles()?;
    Ok((tris, scene, t.elapsed().as_secs_f64() * 1e3))
}

/// The `w` x `h` primary rays of the scene's camera, or of a camera framing it.
fn primary_rays(scene: &bvhtrace_scene::Scene, w: u32, h: u32) -> Vec<Ray> {
    scene.camera_or_frame(w as f32 / h as f32).rays(w, h)
}

/// The kind of rays `bench-trace --rays` traces.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RayKind {
    /// The camera's rays.
    Primary,
    /// From each primary hit to a point light near the eye.
    Shadow,
    /// One cosine-distributed bounce from each primary hit.
    Diffuse,
}

/// Rays of every kind, generated once per scene from the reference hits so that every
/// configuration traces exactly the same rays.
pub(crate) struct RaySets {
    /// The camera's rays, `w` x `h`, closest hit.
    pub(crate) primary: Vec<Ray>,
    /// From each primary hit to the point light near the eye, any hit.
    pub(crate) shadow: Vec<Ray>,
    /// One cosine-distributed bounce from each primary hit, closest hit.
    pub(crate) diffuse: Vec<Ray>,
}

/// The rays of every kind for `cam` at `w` x `h` over `tris`, their hits found in `bvh`.
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

/// A backend `--backends` names, opened once per run through the front door: the name its
/// rows carry and its device.
struct BenchBackend {
    /// The backend opened's name (`Backend::name`).
    name: &'static str,
    /// The device, for every tree of the run.
    device: Device,
}

impl BenchBackend {
    /// True for the CPU walks.
    fn is_cpu(&self) -> bool {
        self.device.backend() == Backend::Cpu
    }

    /// True for the device's own ray queries: the driver's walk over its own structure,
    /// measured once per builder and ray kind rather than per walk.
    fn driver_walk(&self) -> bool {
        !self.device.backend().bit_for_bit()
    }
}

/// Every backend of `backends`, in its order, each device opened once through the front
/// door on `adapter` (said on stderr, the CPU walks aside); one that does not open is left
/// out, saying why.
fn open_backends(backends: &[Backend], adapter: Option<&str>) -> Vec<BenchBackend> {
    let mut out = Vec::new();
    for &backend in backends {
        let opts = crate::backend::options(backend, adapter, &[]);
        match crate::backend::device(&opts) {
            Ok(device) => {
                let name = device.backend().name();
                let opened = BenchBackend { name, device };
                if !opened.is_cpu() {
                    eprintln!("{}: {}", opened.device.backend(), opened.device.name());
                }
                out.push(opened);
            }
            Err(e) => eprintln!("note: no {backend} device ({e}); leaving it out"),
        }
    }
    out
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
    // `--converge` and its flags: image error against wall time (`converge`).
    #[command(flatten)]
    pub converge: Box<ConvergeArgs>,
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
    /// Which rays the device walks trace: the camera's (`primary`), from each primary hit
    /// to a light near the eye (`shadow`: trace them with `--any-hit`), or one diffuse
    /// bounce from each primary hit (`diffuse`): the ray kinds `bvhtrace cost` models. Not
    /// with `--cpu-only` (which traces all three) or `--embree`.
    #[arg(long, value_enum, default_value_t = RayKind::Primary)]
    pub rays: RayKind,
    /// Instead, compare each traversal's specialised pipeline (only the bindings and code
    /// the closest-hit job reads) with the everything-on one (every module composed, the
    /// escape links uploaded, counters written): bytes uploaded per triangle, pipeline
    /// creation time, Mrays/s.
    #[arg(long)]
    pub everything_on: bool,
    /// Only the CPU paths, without a device: the core walks (`--traversals`, default
    /// full-stack and wide) and the CPU layout (`bvhtrace-cpu`, each instruction set the
    /// CPU has) on primary (closest-hit), shadow (any-hit) and diffuse-bounce (closest-hit,
    /// incoherent) rays, beside Embree 3's default and robust modes with `--embree`, and
    /// each path's differences from the full stack's answers. A scene traced in two levels
    /// or with alpha masks also gets the CPU layout over that tree (rows `two-level`,
    /// `masked`), checked against the full stack over the same tree.
    #[arg(long)]
    pub cpu_only: bool,
    /// With `--cpu-only`: an `embree_trace` built against Embree 4
    /// (`crates/cli/embree/embree_trace.c` with `-DBVHTRACE_EMBREE4`), traced in every round
    /// after Embree 3's: its fast and robust rows, and each path's ratio to its fast mode.
    #[arg(long)]
    pub embree4: Option<std::path::PathBuf>,
    /// With `--cpu-only`: thread counts to sweep, comma-separated (ours and Embree's
    /// alike); the tables are printed for each, then each path's rate per count and its
    /// scaling efficiency (rate over the count times the first count's rate per thread).
    /// Default: the machine's threads.
    #[arg(long, value_delimiter = ',')]
    pub threads: Vec<usize>,
}

impl BenchTraceArgs {
    /// The flags' own errors, before any work.
    pub fn check(&self) -> Result<()> {
        if self.runs == 0 {
            bail!("--runs must be at least 1");
        }
        if self.threads.contains(&0) {
            bail!("--threads counts must be at least 1");
        }
        if !self.threads.is_empty() && !self.cpu_only {
            bail!("--threads sweeps the CPU paths: it goes with --cpu-only");
        }
        if self.embree4.is_some() && !self.cpu_only {
            bail!("--embree4 times the CPU paths' rays: it goes with --cpu-only");
        }
        if self.rays != RayKind::Primary && (self.cpu_only || self.embree.is_some()) {
            bail!("--rays picks the device walks' rays: not with --cpu-only or --embree");
        }
        Ok(())
    }
}

/// The flags `bench` takes for `--converge` (flattened into [`BenchArgs`]).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ConvergeArgs {
    /// Image error against wall time instead of hit error: for each shading kind (ao,
    /// diffuse with one bounce, path) and configuration (builder x walk x backend), images
    /// at increasing samples per pixel, each timed from the BVH build to the last pixel and
    /// compared (mean FLIP, RMSE) with a reference of --reference-spp samples (CPU
    /// full-stack walk, default builder; for `path` the path tracer's CPU twin, cached in
    /// --reference-cache). Uses the scenes, --quick, --size (image size, default 256x192;
    /// 96x72 with --quick), --backends, --adapter, --runs (median image time; default 1),
    /// --json, --csv and --plot (PREFIX-SCENE-SHADE.png/.svg).
    #[arg(long)]
    pub converge: bool,
    /// Builders for --converge (default every builder; with --quick sah and median).
    #[arg(long, value_delimiter = ',', requires = "converge")]
    pub builders: Vec<BuilderKind>,
    /// Walks for --converge (default full-stack, stackless, short-stack, wide; with
    /// --quick full-stack and stackless).
    #[arg(long, value_delimiter = ',', requires = "converge")]
    pub traversals: Vec<Traversal>,
    /// Shading kinds for --converge (default all three: ao, diffuse, path).
    #[arg(long, value_delimiter = ',', value_enum, requires = "converge")]
    pub shades: Vec<ShadeKind>,
    /// Samples per pixel of the measured images, increasing (default 1,2,4,...,64; with
    /// --quick 1,2,4,8,16); they may add up to at most 4096.
    #[arg(long, value_delimiter = ',', requires = "converge")]
    pub spp: Vec<u32>,
    /// Samples per pixel of the reference images (default 1024; 128 with --quick; at
    /// most 4096).
    #[arg(long, requires = "converge")]
    pub reference_spp: Option<u32>,
    /// Where the path tracer's references are kept between runs, one file per scene
    /// content, size, camera, lighting, --max-depth, --reference-spp and tracer version
    /// (default: `target/bvhtrace-cache/converge` when the binary runs from a cargo
    /// `target` folder, else `bvhtrace-cache/converge` in the system's temporary folder).
    /// The run says which file it read or wrote; delete one to render it again.
    #[arg(long, requires = "converge")]
    pub reference_cache: Option<PathBuf>,
    /// The most bounces of a path, 1 to 64 (--converge's `path` kind; default 8, as
    /// `render --shade path`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=64), requires = "converge")]
    pub max_depth: Option<u32>,
    /// Direction toward a sun of irradiance 3, X,Y,Z (--converge's `path` kind; default:
    /// no sun).
    #[arg(long, value_parser = bvhtrace_shade::args::parse_vec3, requires = "converge", allow_hyphen_values = true)]
    pub sun: Option<Vec3>,
    /// The sky's constant radiance, R,G,B (--converge's `path` kind; 0,0,0 for none;
    /// default 0.5,0.5,0.5).
    #[arg(long, value_parser = bvhtrace_shade::args::parse_vec3, requires = "converge", allow_hyphen_values = true)]
    pub sky: Option<Vec3>,
    /// Camera position X,Y,Z for --converge (with --target; default: the scene's camera or
    /// a framing one).
    #[arg(long, value_parser = bvhtrace_shade::args::parse_vec3, requires_all = ["converge", "target"], allow_hyphen_values = true)]
    pub eye: Option<Vec3>,
    /// The point the --converge camera looks at (with --eye).
    #[arg(long, value_parser = bvhtrace_shade::args::parse_vec3, requires_all = ["converge", "eye"], allow_hyphen_values = true)]
    pub target: Option<Vec3>,
    /// Vertical field of view of the --converge camera, in degrees.
    #[arg(long, requires = "converge")]
    pub fov: Option<f32>,
    /// Mean FLIP levels of the --converge table, every shading kind (default: ao 0.05,
    /// 0.03, 0.02; diffuse 0.01, 0.007, 0.005; path 0.1, 0.02, 0.006).
    #[arg(long, value_delimiter = ',', requires = "converge")]
    pub flip_levels: Vec<f64>,
    /// RMSE levels of the --converge table, every shading kind (default: ao 0.1, 0.05,
    /// 0.025; diffuse 0.01, 0.005, 0.0025; path, of the linear radiance: 0.3, 0.03, 0.01).
    #[arg(long, value_delimiter = ',', requires = "converge")]
    pub rmse_levels: Vec<f64>,
}

/// What an image shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ShadeKind {
    /// Ambient occlusion: `spp` any-hit rays per pixel, as `render --shade ao`.
    Ao,
    /// The point light of `render --shade diffuse` (one shadow ray), plus one bounce:
    /// `spp` cosine-weighted closest-hit rays per pixel that see the sky or a surface lit
    /// by the same light (a shadow ray from there).
    Diffuse,
    /// The progressive path tracer of `render --shade path` (its materials, lights and
    /// bounces): one image's sums grown sample by sample, its error read at each level.
    Path,
}
