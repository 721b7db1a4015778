//! `bvhtrace bench --converge`: image error against wall time, as a renderer sees it.
//!
//! For each scene, shading kind (ambient occlusion, one-bounce diffuse) and configuration
//! (builder x walk x backend), images are rendered at increasing samples per pixel, and
//! each image gets a wall time (the configuration's BVH build, plus everything the image
//! takes: camera rays, traces, secondary rays, shading) and an error (mean FLIP and RMSE)
//! against a reference rendered once per scene and shading kind with many more samples, on
//! the CPU full-stack walk over the default builder's tree. The question answered: which
//! configuration reaches a given image error first, build included.
//!
//! Samples: pixel `p`'s sample `s` is `shade::cosine_dir(normal, p, s)`, a hash of `(p, s)`.
//! The levels take consecutive, disjoint ranges of `s` from 0 (1 spp: sample 0; 2 spp:
//! samples 1..3; 4 spp: 3..7, ...) and the reference takes `REFERENCE_FIRST_SAMPLE..`,
//! so no two images share a sample and each level's error is that of an independent
//! estimate. Every configuration renders the same samples: the walks answer the same
//! hits, so at a given spp every configuration's image is the same and only time differs.
//!
//! The path tracer (`path`, [`path`]) is measured as a progressive renderer is used: one
//! image's sums grow sample by sample (seed 0, as `render --shade path`), and at each level
//! the clock stops, the sums are read back (the device waited for first), the error is
//! measured (FLIP of the tone-mapped image, RMSE of the linear radiance) and the clock goes
//! on. Its levels are therefore one image at growing spp, not independent estimates. Its
//! reference is the CPU twin's (seed 1: no sample in common), kept on disk between runs.

use std::borrow::Cow;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace::{CpuTracer, Tracer};
use bvhtrace_core::traverse::DEFAULT_SHORT_STACK;
use bvhtrace_core::{
    BuildOptions, BuilderKind, FlatBvh, Hit, Query, Ray, TraceOptions, Traversal, Triangle,
};
use bvhtrace_scene::Camera;
use glam::Vec3;
use indicatif::ProgressBar;
use plotters::prelude::*;
use serde::Serialize;

use super::accuracy;
use super::plot::{one_two_five, plot_error, write_png_and_svg};
use super::{BenchArgs, BenchBackend, ConvergeArgs, ShadeKind, median, open_backends, scene_specs};
use crate::output::{AtomicFile, JsonOut};
use crate::shade::{self, Shade, palette};

mod path;

use path::{PathFrame, PathReference, PathSettings};

impl ShadeKind {
    fn name(self) -> &'static str {
        match self {
            ShadeKind::Ao => "ao",
            ShadeKind::Diffuse => "diffuse",
            ShadeKind::Path => "path",
        }
    }

    /// The table's default error levels, (FLIP, RMSE): where a 69k-triangle mesh filling
    /// a 256x192 image crosses them between 1 and 32 spp. The diffuse images are far less
    /// noisy (the point light's direct term has no noise), so their levels are lower. The
    /// path tracer's errors depend on the lighting far more than on the mesh (256x192 at
    /// 64 spp: FLIP 0.054 in the Cornell box, 0.016 in the foliage, 0.004 on the sky-lit
    /// bunny), so its levels span more than a decade: each of those crosses one or more.
    fn default_levels(self) -> (Vec<f64>, Vec<f64>) {
        match self {
            ShadeKind::Ao => (vec![0.05, 0.03, 0.02], vec![0.1, 0.05, 0.025]),
            ShadeKind::Diffuse => (vec![0.01, 0.007, 0.005], vec![0.01, 0.005, 0.0025]),
            ShadeKind::Path => (vec![0.1, 0.02, 0.006], vec![0.3, 0.03, 0.01]),
        }
    }
}

/// The first sample index of the reference images; the levels use `0..` and may add up to
/// this many samples, so they never share one with the reference. `cosine_dir` hashes
/// `9781 p + 6271 s`: indices below 9781 never collide.
const REFERENCE_FIRST_SAMPLE: u32 = 4096;
/// The most samples the reference may take (`REFERENCE_FIRST_SAMPLE + this < 9781`).
const MAX_REFERENCE_SPP: u32 = 4096;
/// Radiance of the sky a bounce ray that escapes sees (diffuse).
const SKY: f32 = 0.4;
/// The fraction of light surfaces reflect (diffuse).
const ALBEDO: f32 = 0.5;
/// Rays per trace call: bounds the ray and hit buffers of one call.
const CHUNK: usize = 1 << 18;

/// One measured image.
#[derive(Clone, Debug, Serialize)]
pub struct Point {
    /// The scene as given.
    pub scene: String,
    /// Ambient occlusion, one-bounce diffuse or the path tracer.
    pub shade: ShadeKind,
    /// The builder's name.
    pub builder: String,
    /// The walk, as `--traversals` names it.
    pub traversal: String,
    /// `gpu` (wgpu), `vulkan` (ash) or `cpu`.
    pub backend: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Samples per pixel of this image.
    pub spp: u32,
    /// The image's first sample index (its samples are `first_sample..first_sample + spp`;
    /// 0 for `path`, whose levels are one image growing).
    pub first_sample: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    /// The BVH build (median of `--runs`), with the wide conversion for the wide walk.
    pub build_ms: f64,
    /// The upload to the device (0 on the CPU; for `path` the kernel's compilation too);
    /// not in `wall_ms`.
    pub upload_ms: f64,
    /// The image: camera rays, every trace, secondary rays, shading (median of `--runs`);
    /// for `path` every sample from the first to this level's last, the device waited for.
    pub image_ms: f64,
    /// `build_ms + image_ms`.
    pub wall_ms: f64,
    /// Rays traced for the image.
    pub rays: u64,
    /// Mean FLIP against the reference (for `path` of the tone-mapped sRGB images).
    pub flip: f64,
    /// RMSE against the reference (RGB8 channels in [0, 1]; for `path` of the linear
    /// radiance).
    pub rmse: f64,
    /// `path`: the most bounces of a path (`null` for the other kinds).
    pub max_depth: Option<u32>,
    /// `path`: reading the sums back to measure the error (a copy on the CPU; median of
    /// `--runs`); not in `image_ms` or `wall_ms`.
    pub readback_ms: Option<f64>,
    /// `path`: whether the reference was read from `--reference-cache` rather than rendered.
    pub reference_cached: Option<bool>,
}

/// The error of an image against the reference.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageError {
    /// Mean FLIP (NVIDIA's perceptual difference, 0 = identical).
    pub flip: f64,
    /// Root-mean-square difference of the RGB8 channels, in [0, 1].
    pub rmse: f64,
}

/// Mean FLIP and RMSE of the RGB8 image `test` against `reference` (both `w` x `h`).
pub fn image_error(reference: &[u8], test: &[u8], w: u32, h: u32) -> ImageError {
    ImageError {
        flip: accuracy::flip(reference, test, w, h),
        rmse: accuracy::rmse(reference, test),
    }
}

/// The wall time at which a curve of `(time, error)` points (in the order measured, spp
/// increasing) first reaches `level`: interpolated in log-log between the last point above
/// the level and the first at or below it; the first point's time when that one is already
/// at or below; `None` when no point reaches it.
pub fn time_to_reach(points: &[(f64, f64)], level: f64) -> Option<f64> {
    let i = points.iter().position(|p| p.1 <= level)?;
    let (t1, e1) = points[i];
    if i == 0 {
        return Some(t1);
    }
    let (t0, e0) = points[i - 1];
    // A zero error or time has no logarithm: the measured point is all we know.
    if !(e1 > 0.0 && level > 0.0 && t0 > 0.0 && t1 > 0.0) {
        return Some(t1);
    }
    let f = (level.ln() - e0.ln()) / (e1.ln() - e0.ln());
    Some((t0.ln() + f * (t1.ln() - t0.ln())).exp())
}

/// The configurations and sizes a run measures.
struct Plan {
    size: (u32, u32),
    flip_levels: Vec<f64>,
    rmse_levels: Vec<f64>,
    levels: Vec<u32>,
    reference_spp: u32,
    builders: Vec<BuilderKind>,
    walks: Vec<Traversal>,
    shades: Vec<ShadeKind>,
    runs: usize,
    /// The path tracer's lights and depth.
    path: PathSettings,
    /// Where the path tracer's references are kept.
    reference_cache: PathBuf,
}

impl Plan {
    fn new(args: &BenchArgs) -> Result<Plan> {
        let c = &args.converge;
        let quick = args.quick;
        if args.full || args.sample.is_some() || !args.precisions.is_empty() {
            bail!("--full, --sample and --precisions do not apply to --converge");
        }
        let levels = if c.spp.is_empty() {
            let top = if quick { 16 } else { 64 };
            std::iter::successors(Some(1u32), |s| Some(s * 2))
                .take_while(|&s| s <= top)
                .collect()
        } else {
            c.spp.clone()
        };
        if levels.first() == Some(&0) || levels.windows(2).any(|w| w[1] <= w[0]) {
            bail!("--spp must be increasing and at least 1, got {levels:?}");
        }
        if levels.iter().map(|&s| u64::from(s)).sum::<u64>() > u64::from(REFERENCE_FIRST_SAMPLE) {
            bail!("--spp levels add up to more than {REFERENCE_FIRST_SAMPLE} samples");
        }
        let reference_spp = c.reference_spp.unwrap_or(if quick { 128 } else { 1024 });
        if !(1..=MAX_REFERENCE_SPP).contains(&reference_spp) {
            bail!("--reference-spp must be 1..={MAX_REFERENCE_SPP}, got {reference_spp}");
        }
        let runs = args.runs.unwrap_or(1);
        if runs == 0 {
            bail!("--runs must be at least 1");
        }
        let builders = match (c.builders.is_empty(), quick) {
            (false, _) => c.builders.clone(),
            // The default and the quickest to build: the two ends of build time.
            (true, true) => vec![BuilderKind::default(), BuilderKind::Median],
            (true, false) => BuilderKind::ALL.to_vec(),
        };
        let walks = match (c.traversals.is_empty(), quick) {
            (false, _) => c.traversals.clone(),
            // The reference walk and the GPU default.
            (true, true) => Traversal::ALL[..2].to_vec(),
            (true, false) => Traversal::ALL.to_vec(),
        };
        let shades = if c.shades.is_empty() {
            vec![ShadeKind::Ao, ShadeKind::Diffuse, ShadeKind::Path]
        } else {
            c.shades.clone()
        };
        let reference_cache = (c.reference_cache.clone()).unwrap_or_else(path::default_cache_dir);
        if reference_cache.exists() && !reference_cache.is_dir() {
            bail!(
                "--reference-cache {}: not a folder",
                reference_cache.display()
            );
        }
        for l in c.flip_levels.iter().chain(&c.rmse_levels) {
            if !(*l > 0.0 && l.is_finite()) {
                bail!("error levels must be positive, got {l}");
            }
        }
        Ok(Plan {
            flip_levels: c.flip_levels.clone(),
            rmse_levels: c.rmse_levels.clone(),
            size: args
                .size
                .unwrap_or(if quick { (96, 72) } else { (256, 192) }),
            levels,
            reference_spp,
            builders,
            walks,
            shades,
            runs,
            path: PathSettings::from_args(c)?,
            reference_cache,
        })
    }

    /// True when the path tracer is among the shading kinds.
    fn has_path(&self) -> bool {
        self.shades.contains(&ShadeKind::Path)
    }

    /// The table's error levels for `kind`, (FLIP, RMSE): the flags', else the defaults.
    fn error_levels(&self, kind: ShadeKind) -> (Vec<f64>, Vec<f64>) {
        let (f, r) = kind.default_levels();
        (
            if self.flip_levels.is_empty() {
                f
            } else {
                self.flip_levels.clone()
            },
            if self.rmse_levels.is_empty() {
                r
            } else {
                self.rmse_levels.clone()
            },
        )
    }

    /// Each level's samples: consecutive disjoint ranges from 0.
    fn sample_ranges(&self) -> Vec<Range<u32>> {
        let mut first = 0;
        self.levels
            .iter()
            .map(|&n| {
                let r = first..first + n;
                first += n;
                r
            })
            .collect()
    }
}

/// The walk's name as `--traversals` takes it.
fn walk_name(t: Traversal) -> String {
    match t {
        Traversal::ShortStack(k) if k == DEFAULT_SHORT_STACK => "short-stack".into(),
        Traversal::ShortStack(k) => format!("short-stack:{k}"),
        t => t.name().into(),
    }
}

/// What every image of a scene shares.
struct View<'a> {
    tris: &'a [Triangle],
    cam: Camera,
    w: u32,
    h: u32,
    light: Vec3,
    ao_radius: f32,
}

/// Traces `rays` in chunks of [`CHUNK`].
fn trace(tracer: &dyn Tracer, rays: &[Ray], opts: &TraceOptions) -> Result<Vec<Hit>> {
    let mut hits = Vec::with_capacity(rays.len());
    for c in rays.chunks(CHUNK) {
        hits.extend(tracer.trace(c, opts)?.hits);
    }
    Ok(hits)
}

/// One-time work a renderer does once, not per image, done untimed: the ray buffers
/// grown to their largest ([`CHUNK`] rays) with rays that miss the scene, for both
/// queries (the pipelines are compiled by `Tracer::prepare`).
fn warm_up(tracer: &dyn Tracer, walk: Traversal, bvh: &FlatBvh) -> Result<()> {
    let b = bvh.bounds();
    let away = b.max + (b.max - b.min).max(Vec3::ONE);
    let rays = vec![Ray::new(away, Vec3::ONE); CHUNK];
    for opts in [
        TraceOptions::closest(walk),
        TraceOptions::new(walk, Query::Any),
    ] {
        tracer.trace(&rays, &opts)?;
    }
    Ok(())
}

/// Renders one image with the samples `samples`: RGB8 pixels and the rays traced.
fn render(
    view: &View,
    tracer: &dyn Tracer,
    walk: Traversal,
    kind: ShadeKind,
    samples: Range<u32>,
) -> Result<(Vec<u8>, u64)> {
    let tri = |p: u32| view.tris.get(p as usize).copied().unwrap_or_default();
    let closest = TraceOptions::closest(walk);
    let any = TraceOptions::new(walk, Query::Any);
    let spp = samples.len().max(1) as f32;
    let rays = view.cam.rays(view.w, view.h);
    let hits = trace(tracer, &rays, &closest)?;
    let mut traced = rays.len() as u64;
    let mut img = Vec::with_capacity(rays.len() * 3);
    match kind {
        ShadeKind::Ao => {
            let (ao, owner) = shade::secondary_rays_from(
                Shade::Ao,
                &tri,
                &rays,
                &hits,
                view.light,
                samples,
                view.ao_radius,
            );
            let occl = trace(tracer, &ao, &any)?;
            traced += ao.len() as u64;
            let mut blocked = vec![0u32; rays.len()];
            for (o, h) in owner.iter().zip(&occl) {
                blocked[*o as usize] += u32::from(h.is_hit());
            }
            for (h, b) in hits.iter().zip(&blocked) {
                img.extend(if h.is_hit() {
                    palette::ao_grey(1.0 - *b as f32 / spp)
                } else {
                    shade::BACKGROUND
                });
            }
        }
        ShadeKind::Diffuse => {
            let light = view.light;
            // Shadow rays from the primary hits, and the bounces (AO rays of unbounded
            // length are exactly cosine-weighted bounce rays).
            let (shadow, s_owner) =
                shade::secondary_rays_from(Shade::Diffuse, &tri, &rays, &hits, light, 0..1, 0.0);
            let (bounce, b_owner) = shade::secondary_rays_from(
                Shade::Ao,
                &tri,
                &rays,
                &hits,
                light,
                samples,
                f32::INFINITY,
            );
            let b_hits = trace(tracer, &bounce, &closest)?;
            let (b_shadow, bs_owner) = shade::secondary_rays_from(
                Shade::Diffuse,
                &tri,
                &bounce,
                &b_hits,
                light,
                0..1,
                0.0,
            );
            // Both kinds of shadow ray in one any-hit trace.
            let all_shadow: Vec<Ray> = shadow.iter().chain(&b_shadow).copied().collect();
            let occl = trace(tracer, &all_shadow, &any)?;
            traced += (bounce.len() + all_shadow.len()) as u64;
            let (occl_primary, occl_bounce) = occl.split_at(shadow.len());
            // What each bounce ray brings back: the sky, or the light a surface reflects.
            let mut incoming: Vec<f32> = b_hits
                .iter()
                .map(|h| if h.is_hit() { 0.0 } else { SKY })
                .collect();
            for (b, o) in bs_owner.iter().zip(occl_bounce) {
                let (b, bh) = (*b as usize, &b_hits[*b as usize]);
                if !o.is_hit() {
                    let dir = Vec3::from(bounce[b].dir);
                    incoming[b] = ALBEDO * shade::lambert(&tri(bh.prim), bh, dir, light);
                }
            }
            let mut lit = vec![0f32; rays.len()];
            for (p, o) in s_owner.iter().zip(occl_primary) {
                let p = *p as usize;
                if !o.is_hit() {
                    lit[p] =
                        shade::lambert(&tri(hits[p].prim), &hits[p], rays[p].dir.into(), light);
                }
            }
            for (p, l) in b_owner.iter().zip(&incoming) {
                lit[*p as usize] += ALBEDO * l / spp;
            }
            for (h, l) in hits.iter().zip(&lit) {
                img.extend(if h.is_hit() {
                    palette::diffuse_colour(*l)
                } else {
                    shade::BACKGROUND
                });
            }
        }
        ShadeKind::Path => bail!("the path tracer's images are its own (path::progressive)"),
    }
    Ok((img, traced))
}

/// Opens a tracer for `bvh` and `walk` on `backend`'s device through the front door; the
/// tracer and the upload's time.
fn upload<'a>(
    backend: &BenchBackend,
    bvh: &'a FlatBvh,
    walk: Traversal,
) -> Result<(Box<dyn Tracer + 'a>, f64)> {
    let t = Instant::now();
    let opts = bvhtrace::OpenOptions::default().with_traversal(walk);
    let tracer = crate::backend::open_on(&backend.device, bvh, &opts)?.tracer;
    Ok((tracer, t.elapsed().as_secs_f64() * 1e3))
}

/// A plot's two files, reserved, and their paths: PNG, SVG.
type PlotFiles = (AtomicFile, AtomicFile, PathBuf, PathBuf);

/// Reserves the plots `--plot PREFIX` asks for: one per scene and shading kind,
/// `PREFIX-SCENE-SHADE.png` and `.svg`, in the order they are drawn.
fn reserve_plots(prefix: Option<&Path>, specs: &[String], plan: &Plan) -> Result<Vec<PlotFiles>> {
    let mut plot_files = Vec::new();
    if let Some(prefix) = prefix {
        for spec in specs {
            for kind in &plan.shades {
                let stem = format!("{}-{}-{}", prefix.display(), scene_stem(spec), kind.name());
                let (png, svg) = (
                    PathBuf::from(format!("{stem}.png")),
                    PathBuf::from(format!("{stem}.svg")),
                );
                plot_files.push((
                    AtomicFile::create(&png)?,
                    AtomicFile::create(&svg)?,
                    png,
                    svg,
                ));
            }
        }
    }
    Ok(plot_files)
}

/// `bvhtrace bench --converge`.
pub fn run(args: &BenchArgs) -> Result<()> {
    let plan = Plan::new(args)?;
    let specs = scene_specs(&args.scenes)?;
    // Reserve every output before any work, so a bad path fails at once.
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let csv_out = args.csv.as_deref().map(AtomicFile::create).transpose()?;
    let mut plots = reserve_plots(args.plot.as_deref(), &specs, &plan)?.into_iter();
    let backends = open_backends(&args.backends, args.adapter.as_deref());
    if backends.is_empty() {
        bail!("no backend left to measure");
    }
    if plan.has_path() {
        for b in backends.iter().filter(|b| !path::runs_on(b)) {
            eprintln!(
                "note: the path tracer runs on wgpu and the CPU: {} measures the other kinds only",
                b.name
            );
        }
    }
    eprintln!("CPU: {} threads", rayon::current_num_threads());
    let to_stderr = args.json.as_deref() == Some("-");
    let mut points = Vec::new();
    let mut written = Vec::new();
    for spec in &specs {
        let scene_points = measure_scene(spec, &args.converge, &plan, &backends)?;
        for &kind in &plan.shades {
            let these: Vec<&Point> = scene_points.iter().filter(|p| p.shade == kind).collect();
            let curves = curves(&these);
            let levels = plan.error_levels(kind);
            print_table(spec, kind, &plan, &levels, &curves, to_stderr);
            if let Some((png, svg, png_path, svg_path)) = plots.next() {
                plot(&plot_title(spec, kind, &plan), &curves, &levels, png, svg)?;
                written.push((png_path, svg_path));
            }
        }
        points.extend(scene_points);
    }
    if let Some(j) = json_out {
        j.write(&serde_json::to_value(&points)?)?;
    }
    if let Some(f) = csv_out {
        f.finish_with_bytes(to_csv(&points).as_bytes())?;
    }
    for (p, s) in &written {
        eprintln!("wrote {} and {}", p.display(), s.display());
    }
    Ok(())
}

/// The title of a scene's plot for one shading kind.
fn plot_title(spec: &str, kind: ShadeKind, plan: &Plan) -> String {
    let (w, h) = plan.size;
    let depth = format!("path traced, {} bounces at most", plan.path.max_depth);
    format!(
        "{} - {} ({w}x{h}; reference {} spp, {})",
        Path::new(spec)
            .file_name()
            .map_or(spec.to_string(), |n| n.to_string_lossy().into_owned()),
        match kind {
            ShadeKind::Ao => "ambient occlusion",
            ShadeKind::Diffuse => "one-bounce diffuse",
            ShadeKind::Path => &depth,
        },
        plan.reference_spp,
        match kind {
            ShadeKind::Path => "CPU twin",
            _ => "CPU full stack",
        },
    )
}

/// What the images of one scene share: the scene as given, what they show, the reference
/// image of each traced shading kind (ao, diffuse; in `plan.shades`' order), the path
/// tracer's frame and reference when it is measured, each level's samples, and the
/// progress bar of the scene's configurations.
struct SceneRun<'a> {
    spec: &'a str,
    view: View<'a>,
    references: Vec<(ShadeKind, Vec<u8>)>,
    path: Option<(PathFrame<'a>, PathReference)>,
    plan: &'a Plan,
    ranges: Vec<Range<u32>>,
    pb: ProgressBar,
}

/// A tree a configuration traces: the builder's, converted for the walk where it is wide,
/// with its build time (the conversion included).
struct Tree<'a> {
    builder: BuilderKind,
    walk: Traversal,
    bvh: &'a FlatBvh,
    build_ms: f64,
}

/// Every image of `spec`, measured: its references first, then each builder's tree on
/// each walk and backend.
fn measure_scene(
    spec: &str,
    args: &ConvergeArgs,
    plan: &Plan,
    backends: &[BenchBackend],
) -> Result<Vec<Point>> {
    let scene = crate::geometry::load_triangle_scene(spec)
        .with_context(|| format!("{spec}: cannot load the scene"))?;
    let tris = scene
        .flattened_triangles()
        .with_context(|| format!("{spec}: cannot flatten the scene"))?;
    let (w, h) = plan.size;
    let cam = camera(args, &scene, (w, h))?;
    let reference_bvh = FlatBvh::build(&tris, &BuildOptions::default())
        .with_context(|| format!("{spec}: the reference build failed"))?;
    let view = View {
        tris: &tris,
        light: shade::point_light(&cam),
        ao_radius: shade::ao_radius(&reference_bvh),
        cam,
        w,
        h,
    };
    let references = references(spec, &view, &reference_bvh, plan)?;
    let path = match plan.has_path() {
        true => Some(path_reference(spec, &scene, &view, &reference_bvh, plan)?),
        false => None,
    };
    let configs = plan.builders.len() * plan.walks.len() * backends.len();
    let pb = crate::output::progress_bar(
        (configs * plan.shades.len() * plan.levels.len()) as u64,
        "{msg:40} [{bar:30}] {pos}/{len} ({eta})",
    );
    let run = SceneRun {
        spec,
        view,
        references,
        path,
        plan,
        ranges: plan.sample_ranges(),
        pb,
    };
    let mut points = Vec::new();
    for &builder in &plan.builders {
        run.pb.set_message(format!("building {builder}"));
        let (binary, binary_ms) = timed_build(&tris, builder, plan.runs)
            .with_context(|| format!("{spec}: the {builder} build failed"))?;
        for &walk in &plan.walks {
            let (bvh, build_ms) = for_walk(&binary, binary_ms, walk, plan.runs)?;
            let tree = Tree {
                builder,
                walk,
                bvh: &bvh,
                build_ms,
            };
            for backend in backends {
                points.extend(run.measure(&tree, backend)?);
                points.extend(run.measure_path(&tree, backend)?);
            }
        }
    }
    run.pb.finish_and_clear();
    Ok(points)
}

/// The reference images of `spec`, once per traced shading kind (ao, diffuse): CPU full
/// stack, default builder, `plan.reference_spp` samples from [`REFERENCE_FIRST_SAMPLE`].
fn references(
    spec: &str,
    view: &View,
    bvh: &FlatBvh,
    plan: &Plan,
) -> Result<Vec<(ShadeKind, Vec<u8>)>> {
    let (w, h) = (view.w, view.h);
    let cpu = CpuTracer::new(bvh);
    let mut references = Vec::new();
    for &kind in plan.shades.iter().filter(|&&k| k != ShadeKind::Path) {
        let sp = ProgressBar::new_spinner();
        sp.set_message(format!(
            "{spec}: {} reference, {w}x{h} at {} spp on the CPU",
            kind.name(),
            plan.reference_spp
        ));
        sp.enable_steady_tick(std::time::Duration::from_millis(200));
        let t = Instant::now();
        let samples = REFERENCE_FIRST_SAMPLE..REFERENCE_FIRST_SAMPLE + plan.reference_spp;
        let (img, _) = render(view, &cpu, Traversal::FullStack, kind, samples)?;
        sp.finish_and_clear();
        eprintln!(
            "{spec}: {} triangles; {} reference ({w}x{h}, {} spp) in {:.1} s",
            view.tris.len(),
            kind.name(),
            plan.reference_spp,
            t.elapsed().as_secs_f64()
        );
        references.push((kind, img));
    }
    Ok(references)
}

/// The path tracer's frame of `spec` and its reference: the CPU twin at
/// `plan.reference_spp` samples over the default builder's tree `bvh`, read from
/// `plan.reference_cache` when an earlier run left it there.
fn path_reference<'a>(
    spec: &str,
    scene: &bvhtrace_scene::Scene,
    view: &View<'a>,
    bvh: &FlatBvh,
    plan: &Plan,
) -> Result<(PathFrame<'a>, PathReference)> {
    let size = (view.w, view.h);
    let frame = PathFrame::new(scene, view.tris, bvh, &view.cam, size, &plan.path)
        .with_context(|| format!("{spec}: the path tracer cannot shade this scene"))?;
    let stem = scene_stem(spec);
    let cache = &plan.reference_cache;
    let reference = path::reference(spec, &stem, &frame, bvh, plan.reference_spp, cache)?;
    Ok((frame, reference))
}

/// `builder`'s tree over `tris`, built `runs` times: the last build and the median time.
fn timed_build(tris: &[Triangle], builder: BuilderKind, runs: usize) -> Result<(FlatBvh, f64)> {
    let opts = BuildOptions::with_builder(builder);
    let mut times = Vec::new();
    let mut built = None;
    for _ in 0..runs {
        let t = Instant::now();
        built = Some(FlatBvh::build(tris, &opts)?);
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok((built.context("no build")?, median(times)))
}

/// The tree `walk` traces and its build time: the binary one for a binary walk; for the
/// wide walk the binary one converted, the conversion (median of `runs`) added to the time.
fn for_walk(
    binary: &FlatBvh,
    binary_ms: f64,
    walk: Traversal,
    runs: usize,
) -> Result<(Cow<'_, FlatBvh>, f64)> {
    if !walk.is_wide() {
        return Ok((Cow::Borrowed(binary), binary_ms));
    }
    let mut times = Vec::new();
    let mut wide = None;
    for _ in 0..runs {
        let mut b = binary.clone();
        let t = Instant::now();
        b.build_wide();
        times.push(t.elapsed().as_secs_f64() * 1e3);
        wide = Some(b);
    }
    let wide = wide.context("no wide conversion")?;
    Ok((Cow::Owned(wide), binary_ms + median(times)))
}

impl SceneRun<'_> {
    /// The images of `tree` on `backend`: every shading kind at every level. None where the
    /// backend cannot trace the walk (said once), and for the driver's walk under any walk
    /// but the first: it walks its own structure, one curve per builder (the triangles in
    /// that builder's leaf order).
    fn measure(&self, tree: &Tree, backend: &BenchBackend) -> Result<Vec<Point>> {
        let (plan, walk) = (self.plan, tree.walk);
        let images = (self.references.len() * plan.levels.len()) as u64;
        if images == 0 {
            return Ok(Vec::new());
        }
        if backend.driver_walk() && walk != plan.walks[0] {
            self.pb.inc(images);
            return Ok(Vec::new());
        }
        let walk_label = match backend.driver_walk() {
            true => "driver".to_string(),
            false => walk_name(walk),
        };
        let label = format!("{}/{walk_label}/{}", tree.builder, backend.name);
        self.pb.set_message(label.clone());
        let (tracer, upload_ms) = upload(backend, tree.bvh, walk)
            .with_context(|| format!("{}: {label}: upload failed", self.spec))?;
        let checks = [
            TraceOptions::closest(walk),
            TraceOptions::new(walk, Query::Any),
        ];
        if let Some(e) = checks.iter().find_map(|o| tracer.prepare(o).err()) {
            self.pb.suspend(|| eprintln!("note: {label} left out: {e}"));
            self.pb.inc(images);
            return Ok(Vec::new());
        }
        warm_up(&*tracer, walk, tree.bvh)?;
        let mut points = Vec::new();
        for (kind, reference) in &self.references {
            let kind = *kind;
            // First use of the shading's code paths and caches, untimed.
            render(&self.view, &*tracer, walk, kind, self.ranges[0].clone())?;
            for (spp, samples) in plan.levels.iter().zip(&self.ranges) {
                let (img, rays, image_ms) = self.timed_image(&*tracer, walk, kind, samples)?;
                let (w, h) = (self.view.w, self.view.h);
                let err = image_error(reference, &img, w, h);
                points.push(Point {
                    scene: self.spec.to_string(),
                    shade: kind,
                    builder: tree.builder.name().into(),
                    traversal: walk_label.clone(),
                    backend: backend.name.into(),
                    width: w,
                    height: h,
                    spp: *spp,
                    first_sample: samples.start,
                    reference_spp: plan.reference_spp,
                    build_ms: tree.build_ms,
                    upload_ms,
                    image_ms,
                    wall_ms: tree.build_ms + image_ms,
                    rays,
                    flip: err.flip,
                    rmse: err.rmse,
                    max_depth: None,
                    readback_ms: None,
                    reference_cached: None,
                });
                self.pb.inc(1);
            }
        }
        Ok(points)
    }

    /// One image with `samples`, rendered `plan.runs` times: the last image, its rays
    /// traced, and the median time.
    fn timed_image(
        &self,
        tracer: &dyn Tracer,
        walk: Traversal,
        kind: ShadeKind,
        samples: &Range<u32>,
    ) -> Result<(Vec<u8>, u64, f64)> {
        let mut times = Vec::new();
        let mut image = None;
        for _ in 0..self.plan.runs {
            let t = Instant::now();
            let out = render(&self.view, tracer, walk, kind, samples.clone())?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            image = Some(out);
        }
        let (img, rays) = image.context("no image")?;
        Ok((img, rays, median(times)))
    }

    /// The path tracer's image of `tree` on `backend`, grown to every level and measured
    /// at each. None where the path tracer is not measured or the backend does not run it
    /// (said once by [`run`]), and for the driver's walk under any walk but the first (as
    /// [`SceneRun::measure`]).
    fn measure_path(&self, tree: &Tree, backend: &BenchBackend) -> Result<Vec<Point>> {
        let Some((frame, reference)) = &self.path else {
            return Ok(Vec::new());
        };
        let (plan, walk) = (self.plan, tree.walk);
        if !path::runs_on(backend) || (backend.driver_walk() && walk != plan.walks[0]) {
            self.pb.inc(plan.levels.len() as u64);
            return Ok(Vec::new());
        }
        let walk_label = match backend.driver_walk() {
            true => "driver".to_string(),
            false => walk_name(walk),
        };
        let label = format!("{}/{walk_label}/{}", tree.builder, backend.name);
        self.pb.set_message(format!("path {label}"));
        let bvh = frame.tree(tree.bvh)?;
        let (mut engine, upload_ms) = match path::open(backend, &bvh, frame, walk) {
            Ok(opened) => opened,
            Err(e) => {
                self.pb
                    .suspend(|| eprintln!("note: path {label} left out: {e:#}"));
                self.pb.inc(plan.levels.len() as u64);
                return Ok(Vec::new());
            }
        };
        let levels = path::progressive(&mut engine, frame, &plan.levels, plan.runs)
            .with_context(|| format!("{}: path {label}: tracing failed", self.spec))?;
        let (w, h) = (self.view.w, self.view.h);
        let mut points = Vec::new();
        for (spp, level) in plan.levels.iter().zip(levels) {
            points.push(Point {
                scene: self.spec.to_string(),
                shade: ShadeKind::Path,
                builder: tree.builder.name().into(),
                traversal: walk_label.clone(),
                backend: backend.name.into(),
                width: w,
                height: h,
                spp: *spp,
                first_sample: 0,
                reference_spp: plan.reference_spp,
                build_ms: tree.build_ms,
                upload_ms,
                image_ms: level.image_ms,
                wall_ms: tree.build_ms + level.image_ms,
                rays: level.rays,
                flip: accuracy::flip(&reference.srgb, &level.image.to_srgb8(1.0), w, h),
                rmse: accuracy::rmse_linear(&reference.linear, &level.image.linear()),
                max_depth: Some(plan.path.max_depth),
                readback_ms: Some(level.readback_ms),
                reference_cached: Some(reference.cached),
            });
            self.pb.inc(1);
        }
        Ok(points)
    }
}

/// The files name stem of a scene: its file stem, `:` made `_`.
fn scene_stem(spec: &str) -> String {
    Path::new(spec.split('#').next().unwrap_or(spec))
        .file_stem()
        .map_or("scene".into(), |n| n.to_string_lossy().replace(':', "_"))
}

/// The camera: `--eye`/`--target`/`--fov`, else the scene's, else a framing one.
fn camera(args: &ConvergeArgs, scene: &bvhtrace_scene::Scene, size: (u32, u32)) -> Result<Camera> {
    let view = crate::render::CameraArgs {
        size,
        eye: args.eye,
        target: args.target,
        fov: args.fov,
    };
    crate::render::camera_for(&view, scene)
}

/// One configuration's points, in the order measured.
struct Curve<'a> {
    label: String,
    builder: String,
    traversal: String,
    backend: String,
    build_ms: f64,
    points: Vec<&'a Point>,
}

impl Curve<'_> {
    fn flip(&self) -> Vec<(f64, f64)> {
        self.points.iter().map(|p| (p.wall_ms, p.flip)).collect()
    }
    fn rmse(&self) -> Vec<(f64, f64)> {
        self.points.iter().map(|p| (p.wall_ms, p.rmse)).collect()
    }
}

/// Groups one scene and shading kind's points by configuration, in the order measured.
fn curves<'a>(points: &[&'a Point]) -> Vec<Curve<'a>> {
    let mut out: Vec<Curve<'a>> = Vec::new();
    for p in points {
        let label = format!("{}/{}/{}", p.builder, p.traversal, p.backend);
        match out.iter_mut().find(|c| c.label == label) {
            Some(c) => c.points.push(p),
            None => out.push(Curve {
                label,
                builder: p.builder.clone(),
                traversal: p.traversal.clone(),
                backend: p.backend.clone(),
                build_ms: p.build_ms,
                points: vec![p],
            }),
        }
    }
    out
}

fn fmt_ms(t: Option<f64>) -> String {
    t.map_or("-".into(), |t| format!("{t:.1}"))
}

fn print_table(
    spec: &str,
    kind: ShadeKind,
    plan: &Plan,
    (flip_levels, rmse_levels): &(Vec<f64>, Vec<f64>),
    curves: &[Curve],
    to_stderr: bool,
) {
    let mut out = format!(
        "\n{spec}: {}, {}x{}, spp {:?}, reference {} spp; wall ms to reach each error (build + image, log-log interpolated)\n",
        kind.name(),
        plan.size.0,
        plan.size.1,
        plan.levels,
        plan.reference_spp
    );
    let heads: Vec<String> = flip_levels
        .iter()
        .map(|l| format!("FLIP {l}"))
        .chain(rmse_levels.iter().map(|l| format!("RMSE {l}")))
        .collect();
    out += &format!("{:32} {:>9}", "builder/traversal/backend", "build ms");
    for hd in &heads {
        out += &format!(" {hd:>11}");
    }
    out.push('\n');
    let mut best: Vec<Option<(f64, &str)>> = vec![None; heads.len()];
    for c in curves {
        out += &format!("{:32} {:>9.1}", c.label, c.build_ms);
        let (flip, rmse) = (c.flip(), c.rmse());
        let times = flip_levels
            .iter()
            .map(|&l| time_to_reach(&flip, l))
            .chain(rmse_levels.iter().map(|&l| time_to_reach(&rmse, l)));
        for (k, t) in times.enumerate() {
            out += &format!(" {:>11}", fmt_ms(t));
            if let Some(t) = t
                && best[k].is_none_or(|b| t < b.0)
            {
                best[k] = Some((t, &c.label));
            }
        }
        out.push('\n');
    }
    for (hd, b) in heads.iter().zip(&best) {
        if let Some((t, label)) = b {
            out += &format!("first to {hd}: {label} ({t:.1} ms)\n");
        }
    }
    if to_stderr {
        eprint!("{out}");
    } else {
        print!("{out}");
    }
}

fn to_csv(points: &[Point]) -> String {
    let mut s = String::from(
        "scene,shade,builder,traversal,backend,width,height,spp,first_sample,reference_spp,build_ms,upload_ms,image_ms,wall_ms,rays,flip,rmse,max_depth,readback_ms,reference_cached\n",
    );
    // The path tracer's own columns are empty on the other kinds' rows.
    fn opt<T: std::fmt::Display>(v: Option<T>) -> String {
        v.map_or(String::new(), |v| v.to_string())
    }
    for p in points {
        s += &format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            p.scene,
            p.shade.name(),
            p.builder,
            p.traversal,
            p.backend,
            p.width,
            p.height,
            p.spp,
            p.first_sample,
            p.reference_spp,
            p.build_ms,
            p.upload_ms,
            p.image_ms,
            p.wall_ms,
            p.rays,
            p.flip,
            p.rmse,
            opt(p.max_depth),
            opt(p.readback_ms),
            opt(p.reference_cached),
        );
    }
    s
}

/// Writes the plot of one scene and shading kind: FLIP (left) and RMSE (right) against
/// wall time, log-log, one curve per configuration.
fn plot(
    title: &str,
    curves: &[Curve],
    levels: &(Vec<f64>, Vec<f64>),
    png: AtomicFile,
    svg: AtomicFile,
) -> Result<()> {
    if curves.is_empty() {
        return Ok(());
    }
    write_png_and_svg(
        (1400, 700),
        png,
        svg,
        |area, text| draw(area, title, curves, levels, text),
        |area| draw(area, title, curves, levels, true),
    )
}

/// The distinct values, in the order first seen.
fn distinct<'a>(values: impl Iterator<Item = &'a str>) -> Vec<String> {
    let mut v: Vec<String> = Vec::new();
    for x in values {
        if !v.iter().any(|y| y == x) {
            v.push(x.to_string());
        }
    }
    v
}

/// The `i`th builder's colour: matplotlib's "tab10", readable on white (then again).
fn builder_colour(i: usize) -> RGBColor {
    const TAB10: [(u8, u8, u8); 10] = [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ];
    let (r, g, b) = TAB10[i % TAB10.len()];
    RGBColor(r, g, b)
}

/// How the curves are told apart: colour by builder, marker by walk, line by backend (solid
/// cpu, dashed wgpu, dotted the others), so that 40 curves stay readable with a legend of
/// a dozen entries.
struct Styles {
    builders: Vec<String>,
    walks: Vec<String>,
    backends: Vec<String>,
}

impl Styles {
    fn of(curves: &[Curve]) -> Styles {
        Styles {
            builders: distinct(curves.iter().map(|c| c.builder.as_str())),
            walks: distinct(curves.iter().map(|c| c.traversal.as_str())),
            backends: distinct(curves.iter().map(|c| c.backend.as_str())),
        }
    }

    /// The curve's builder's colour.
    fn colour(&self, c: &Curve) -> RGBColor {
        builder_colour(position(&self.builders, &c.builder))
    }

    /// The curve's walk's marker, 0 to 3: filled circle, triangle, cross, hollow circle.
    fn marker(&self, c: &Curve) -> usize {
        position(&self.walks, &c.traversal) % 4
    }
}

/// Where `x` is in `v` (0 when it is not).
fn position(v: &[String], x: &str) -> usize {
    v.iter().position(|y| y == x).unwrap_or(0)
}

/// A backend's line, from what answers its rays: solid (`None`) for the CPU walks, else
/// the dashes' on and off lengths (long for our WGSL walks, short for the rest).
fn dash(backend: &str) -> Option<(u32, u32)> {
    use bvhtrace::Kernels;
    match backend.parse::<bvhtrace::Backend>().map(|b| b.kernels()) {
        Ok(Kernels::Cpu) => None,
        Ok(Kernels::Wgsl) => Some((8, 5)),
        _ => Some((2, 4)),
    }
}

/// One panel of the plot: the error it shows, its axis title and the table's levels.
struct Panel<'a> {
    name: &'static str,
    pick: fn(&Point) -> f64,
    levels: &'a [f64],
}

/// The plot of one scene and shading kind on `root`: FLIP and RMSE panels side by side;
/// without `text` (a PNG with no font), no title, axis labels or legend.
fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    curves: &[Curve],
    (flip_levels, rmse_levels): &(Vec<f64>, Vec<f64>),
    text: bool,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(plot_error)?;
    let root = if text {
        root.titled(title, ("sans-serif", 20)).map_err(plot_error)?
    } else {
        root
    };
    let panels = root.split_evenly((1, 2));
    let styles = Styles::of(curves);
    let all = curves.iter().flat_map(|c| c.points.iter());
    let (tmin, tmax) = all.fold((f64::MAX, f64::MIN), |(a, b), p| {
        (a.min(p.wall_ms), b.max(p.wall_ms))
    });
    let times = (tmin.max(1e-3) * 0.8, tmax.max(1e-3) * 1.25);
    // The path tracer's RMSE is of the linear radiance, the others' of the RGB8 image.
    let path = (curves.iter().flat_map(|c| &c.points)).any(|p| p.shade == ShadeKind::Path);
    let metrics = [
        Panel {
            name: "mean FLIP against the reference",
            pick: |p| p.flip,
            levels: flip_levels,
        },
        Panel {
            name: match path {
                true => "RMSE of the linear radiance against the reference",
                false => "RMSE against the reference",
            },
            pick: |p| p.rmse,
            levels: rmse_levels,
        },
    ];
    for (pi, (area, panel)) in panels.iter().zip(metrics).enumerate() {
        draw_panel(area, &panel, curves, &styles, times, text, pi == 0 && text)?;
    }
    root.present().map_err(plot_error)?;
    Ok(())
}

/// One panel on `area`: `panel`'s error of every curve against wall time (`tmin..tmax`),
/// log-log, with the table's levels as thin grey lines, and the legend where `legend`.
fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    panel: &Panel,
    curves: &[Curve],
    styles: &Styles,
    (tmin, tmax): (f64, f64),
    text: bool,
    legend: bool,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let (pick, levels) = (panel.pick, panel.levels);
    // Identical images (error 0) would have no place on a log axis.
    let positive = (curves.iter().flat_map(|c| c.points.iter()))
        .map(|p| pick(p))
        .filter(|e| *e > 0.0);
    let (emin, emax) = positive.fold((f64::MAX, f64::MIN), |(a, b), e| (a.min(e), b.max(e)));
    let (emin, emax) = if emin <= emax {
        (emin * 0.7, emax * 1.4)
    } else {
        (1e-4, 1.0)
    };
    let mut chart = ChartBuilder::on(area);
    chart.margin(15);
    if text {
        chart.x_label_area_size(40).y_label_area_size(60);
    }
    let mut chart = chart
        .build_cartesian_2d(
            (tmin..tmax)
                .log_scale()
                .with_key_points(one_two_five(tmin, tmax)),
            (emin..emax).log_scale().with_key_points({
                // The 1-2-5 marks and the table's levels.
                let mut k = one_two_five(emin, emax);
                k.extend(levels.iter().filter(|l| (emin..emax).contains(*l)));
                k.sort_by(f64::total_cmp);
                k.dedup();
                k
            }),
        )
        .map_err(plot_error)?;
    if text {
        chart
            .configure_mesh()
            .x_desc("wall time: build + image (ms)")
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_desc(panel.name.to_string())
            .y_label_formatter(&|y| format!("{y}"))
            .draw()
            .map_err(plot_error)?;
    }
    // The table's levels, as thin grey lines.
    for &l in levels.iter().filter(|l| (emin..emax).contains(*l)) {
        chart
            .draw_series(LineSeries::new(
                [(tmin, l), (tmax, l)],
                RGBColor(170, 170, 170).stroke_width(1),
            ))
            .map_err(plot_error)?;
    }
    for c in curves {
        let pts: Vec<(f64, f64)> = c
            .points
            .iter()
            .map(|p| (p.wall_ms, pick(p).max(emin)))
            .collect();
        draw_curve(&mut chart, c, &pts, styles)?;
    }
    if legend {
        draw_legend(&mut chart, styles)?;
    }
    Ok(())
}

/// One curve at `pts`: its backend's line in its builder's colour, its walk's marker at
/// each point.
fn draw_curve<'a, DB, CT>(
    chart: &mut ChartContext<'a, DB, CT>,
    c: &Curve,
    pts: &[(f64, f64)],
    styles: &Styles,
) -> Result<()>
where
    DB: DrawingBackend + 'a,
    DB::ErrorType: 'static,
    CT: CoordTranslate<From = (f64, f64)>,
{
    let col = styles.colour(c);
    let style = col.stroke_width(if dash(&c.backend).is_none() { 2 } else { 1 });
    match dash(&c.backend) {
        None => chart
            .draw_series(LineSeries::new(pts.to_vec(), style))
            .map(|_| ()),
        Some((on, off)) => chart
            .draw_series(DashedLineSeries::new(pts.to_vec(), on, off, style))
            .map(|_| ()),
    }
    .map_err(plot_error)?;
    let (fill, line) = (col.filled(), col.stroke_width(1));
    let at = pts.iter().copied();
    match styles.marker(c) {
        0 => chart.draw_series(at.map(|p| Circle::new(p, 3, fill))),
        1 => chart.draw_series(at.map(|p| TriangleMarker::new(p, 4, fill))),
        2 => chart.draw_series(at.map(|p| Cross::new(p, 4, line))),
        _ => chart.draw_series(at.map(|p| Circle::new(p, 4, line))),
    }
    .map_err(plot_error)?;
    Ok(())
}

/// The legend, with entries of their own: builders (colour), walks (marker), backends
/// (line).
fn draw_legend<'a, DB, CT>(chart: &mut ChartContext<'a, DB, CT>, styles: &Styles) -> Result<()>
where
    DB: DrawingBackend + 'a,
    DB::ErrorType: 'static,
    CT: CoordTranslate<From = (f64, f64)>,
{
    for (i, b) in styles.builders.iter().enumerate() {
        let col = builder_colour(i);
        chart
            .draw_series(std::iter::empty::<PathElement<(f64, f64)>>())
            .map_err(plot_error)?
            .label(format!("builder {b}"))
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], col.stroke_width(3)));
    }
    for (i, wk) in styles.walks.iter().enumerate() {
        let entry = chart
            .draw_series(std::iter::empty::<PathElement<(f64, f64)>>())
            .map_err(plot_error)?
            .label(format!("walk {wk}"));
        let (fill, line) = (BLACK.filled(), BLACK.stroke_width(1));
        match i % 4 {
            0 => entry.legend(move |(x, y)| Circle::new((x + 9, y), 3, fill)),
            1 => entry.legend(move |(x, y)| TriangleMarker::new((x + 9, y), 4, fill)),
            2 => entry.legend(move |(x, y)| Cross::new((x + 9, y), 4, line)),
            _ => entry.legend(move |(x, y)| Circle::new((x + 9, y), 4, line)),
        };
    }
    for be in &styles.backends {
        let entry = chart
            .draw_series(std::iter::empty::<PathElement<(f64, f64)>>())
            .map_err(plot_error)?
            .label(format!("backend {be}"));
        match dash(be) {
            None => entry
                .legend(|(x, y)| PathElement::new([(x, y), (x + 18, y)], BLACK.stroke_width(2))),
            Some((on, off)) => entry.legend(move |(x, y)| {
                plotters::element::DashedPathElement::new(
                    [(x, y), (x + 18, y)],
                    on,
                    off,
                    BLACK.stroke_width(1),
                )
            }),
        };
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerLeft)
        .label_font(("sans-serif", 12))
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grey(w: u32, h: u32, v: u8) -> Vec<u8> {
        vec![v; (w * h * 3) as usize]
    }

    #[test]
    fn identical_images_have_no_error() {
        let (w, h) = (16, 12);
        let mut a = grey(w, h, 40);
        // Some structure, so that FLIP's edge and point detectors see something.
        for (i, x) in a.iter_mut().enumerate() {
            *x = (i * 37 % 251) as u8;
        }
        let e = image_error(&a, &a, w, h);
        assert_eq!(e.rmse, 0.0);
        assert!(e.flip.abs() < 1e-6, "{}", e.flip);
    }

    #[test]
    fn a_constant_difference_gives_that_rmse() {
        let (w, h) = (8, 8);
        let e = image_error(&grey(w, h, 100), &grey(w, h, 151), w, h);
        assert!((e.rmse - 51.0 / 255.0).abs() < 1e-12, "{}", e.rmse);
        let mut half = grey(w, h, 0);
        let n = half.len();
        half[n / 2..].fill(255);
        // Half the channels off by 1: sqrt(1/2).
        let e = image_error(&grey(w, h, 0), &half, w, h);
        assert!((e.rmse - 0.5f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn flip_of_black_against_white_is_its_documented_value_and_grows_with_the_difference() {
        let (w, h) = (8, 8);
        // FLIP's colour pipeline on flat images (no edges, no points): HyAB(black, white)
        // = 100, compressed to 100^0.7 = 25.12; the largest difference (green against
        // blue, Hunt-adjusted) to 203.1^0.7 = 41.1; 25.12 is above 0.4 of that, so it maps
        // to 0.95 + (25.12 - 0.4 * 41.1) / (0.6 * 41.1) * 0.05 = 0.9676.
        let e = image_error(&grey(w, h, 0), &grey(w, h, 255), w, h);
        assert!((e.flip - 0.9676).abs() < 0.01, "{}", e.flip);
        let mut last = 0.0;
        for d in [8u8, 16, 32, 64, 127] {
            let f = image_error(&grey(w, h, 128), &grey(w, h, 128 + d), w, h).flip;
            assert!(
                f > last,
                "FLIP {f} for a difference of {d}, {last} for less"
            );
            last = f;
        }
    }

    #[test]
    fn time_to_reach_interpolates_in_log_log() {
        // Error halves as time doubles: e = 1 / t.
        let curve = [(1.0, 1.0), (2.0, 0.5), (4.0, 0.25), (8.0, 0.125)];
        // Exactly on a point.
        assert_eq!(time_to_reach(&curve, 0.5), Some(2.0));
        // Between points, on the line through them: e = 1/t gives t = 1/e.
        let t = time_to_reach(&curve, 0.3).unwrap();
        assert!((t - 1.0 / 0.3).abs() < 1e-9, "{t}");
        // Already there at the first point: its time.
        assert_eq!(time_to_reach(&curve, 2.0), Some(1.0));
        // Never reached.
        assert_eq!(time_to_reach(&curve, 0.1), None);
        // The first crossing counts, even when noise lifts a later point again.
        let noisy = [(10.0, 0.4), (20.0, 0.1), (40.0, 0.2), (80.0, 0.05)];
        let t = time_to_reach(&noisy, 0.2).unwrap();
        assert!((t - 10.0 * 2f64.powf(0.5)).abs() < 1e-9, "{t}");
        // An identical image (error 0) is reached at its own time.
        assert_eq!(time_to_reach(&[(1.0, 0.3), (2.0, 0.0)], 0.1), Some(2.0));
        assert_eq!(time_to_reach(&[], 0.1), None);
    }

    #[test]
    fn levels_take_disjoint_sample_ranges_below_the_reference() {
        let plan = Plan {
            size: (4, 4),
            flip_levels: vec![],
            rmse_levels: vec![],
            levels: vec![1, 2, 4, 8],
            reference_spp: 16,
            builders: vec![],
            walks: vec![],
            shades: vec![],
            runs: 1,
            path: PathSettings::from_args(&ConvergeArgs::default()).unwrap(),
            reference_cache: PathBuf::new(),
        };
        assert_eq!(plan.sample_ranges(), vec![0..1, 1..3, 3..7, 7..15]);
    }

    #[test]
    fn more_samples_give_less_error_on_a_scene_with_occlusion() {
        let scene = bvhtrace_scene::load("builtin:cornell").unwrap();
        let tris = scene.flattened_triangles().unwrap();
        let (w, h) = (32, 24);
        let cam = scene.camera_or_frame(w as f32 / h as f32);
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
        let view = View {
            tris: &tris,
            light: shade::point_light(&cam),
            ao_radius: shade::ao_radius(&bvh),
            cam,
            w,
            h,
        };
        let cpu = CpuTracer::new(&bvh);
        for kind in [ShadeKind::Ao, ShadeKind::Diffuse] {
            let r = REFERENCE_FIRST_SAMPLE..REFERENCE_FIRST_SAMPLE + 256;
            let (reference, _) = render(&view, &cpu, Traversal::FullStack, kind, r).unwrap();
            let e = |s: Range<u32>| {
                let (img, _) = render(&view, &cpu, Traversal::Stackless, kind, s).unwrap();
                image_error(&reference, &img, w, h).rmse
            };
            let (e1, e16) = (e(0..1), e(1..17));
            assert!(e16 < 0.6 * e1, "{kind:?}: rmse {e1} at 1 spp, {e16} at 16");
        }
    }
}
