//! `bvhtrace render` and `bvhtrace info`.
//!
//! A render is a pipeline: the scene, its tree, the camera's rays, the trace (primary rays,
//! then the shadow or ambient-occlusion rays the shading asks for), the shading, the image.
//! Each step is one function below.

use std::path::PathBuf;

use anyhow::{Result, bail};
use bvhtrace_core::{
    BuildOptions, BuilderKind, BvhStats, Counters, FlatBvh, Hit, MaskTables, Query, Ray,
    TraceOptions, TraceOutput, TracePhases, Traversal,
};
use bvhtrace_cpu::Tiles;
use bvhtrace_gpu::{BvhStorage, KernelKey, Tracer, UploadStats};
use bvhtrace_scene::{Camera, DEFAULT_SCENE, Scene, SceneBvh};
use bvhtrace_shade::args as flags;
use glam::Vec3;
use indicatif::ProgressBar;
use serde_json::{Value, json};

use crate::backend::{self, Backend, Device};
use crate::geometry::{self, Builder, Built, TreeBuilder};
use crate::output::{AtomicFile, JsonOut, write_png};
use crate::shade::{self, Shade, View};

/// An image size flag (`--size WxH`): [`flags::parse_size`], at most 16384 a side.
pub(crate) fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = flags::parse_size(s)?;
    if w > 16384 || h > 16384 {
        return Err(format!("size must be between 1x1 and 16384x16384, got {s}"));
    }
    Ok((w, h))
}

/// The primary rays' size flag of the commands that also trace secondary rays from them.
#[derive(clap::Args, Clone, Copy)]
pub struct PrimarySize {
    /// Primary rays, WxH (the shadow and diffuse rays start at their hits).
    #[arg(
        long,
        value_name = "WxH",
        default_value = "1024x768",
        value_parser = parse_size
    )]
    pub size: (u32, u32),
}

/// The BVH build flags, shared by every command that builds one.
#[derive(clap::Args, Clone)]
pub struct BuildArgs {
    /// BVH builder: sah, sweep-sah, median, midpoint or sbvh on the CPU; gpu-ploc
    /// (clustering) or gpu-lbvh (linear BVH) built on the GPU and read back, so every
    /// backend traces it.
    #[arg(long, default_value = "sah")]
    pub builder: Builder,
    /// Bins per axis for the `sah` builder.
    #[arg(long, default_value_t = 32)]
    pub bins: usize,
    /// SAH traversal cost (intersection cost is 1); PBRT's 1/8 by default.
    #[arg(long, default_value_t = 0.125)]
    pub cost_traversal: f32,
    /// Optimise the built tree by reinsertion (Bittner et al. 2013): a lower SAH cost for
    /// a longer build.
    #[arg(long)]
    pub optimize: bool,
    /// `sbvh` only: how many references spatial splits may add, as a fraction of the
    /// triangle count (0..=16; references at most (1 + F) x triangles).
    #[arg(long, value_name = "F", default_value_t = BuildOptions::default().split_budget)]
    pub split_budget: f32,
}

impl BuildArgs {
    /// The options the flags say.
    pub fn options(&self) -> BuildOptions {
        let builder = match self.builder {
            Builder::Cpu(k) => k,
            Builder::Device(_) => BuilderKind::default(),
        };
        BuildOptions {
            builder,
            bins: self.bins,
            cost_traversal: self.cost_traversal,
            optimize: self.optimize,
            split_budget: self.split_budget,
            ..Default::default()
        }
    }

    /// The builder the flags say, a device builder on `device`.
    pub fn tree_builder(&self, device: Option<&Device>) -> Result<TreeBuilder> {
        TreeBuilder::new(self.builder, self.options(), device)
    }

    /// A command that traces on no device of its own: the device a device builder builds
    /// on (the best there is, on `adapter`), `None` for a CPU builder.
    pub fn build_device(&self, adapter: Option<&str>) -> Result<Option<Device>> {
        match self.builder {
            Builder::Cpu(_) => Ok(None),
            Builder::Device(_) => {
                let opts = backend::options(Backend::Auto, adapter, &[]);
                backend::device(&opts).map(Some)
            }
        }
    }
}

/// Scene and BVH choices shared by the commands.
#[derive(clap::Args, Clone)]
pub struct SceneArgs {
    /// A .gltf/.glb file, a .hair file or a `builtin:` name (see `bvhtrace info --list`);
    /// default: the Cornell box.
    pub scene: Option<String>,
    #[command(flatten)]
    pub build: BuildArgs,
    /// Trace one BVH over the world-space triangles, even for a scene that places meshes
    /// more than once (traced in two levels by default: a BVH per mesh, a top level over
    /// the instances).
    #[arg(long)]
    pub flatten: bool,
    /// Scene time in seconds: the glTF node animations are evaluated there (default: the
    /// scene as loaded, time 0).
    #[arg(long, allow_hyphen_values = true)]
    pub time: Option<f32>,
}

impl SceneArgs {
    fn spec(&self) -> &str {
        self.scene.as_deref().unwrap_or(DEFAULT_SCENE)
    }
}

/// Loads and builds the scene as the flags say (two levels or flattened, at `--time`; a
/// device builder on `device`); prints scene warnings.
pub fn load_and_build(args: &SceneArgs, device: Option<&Device>) -> Result<Built> {
    let builder = args.build.tree_builder(device)?;
    geometry::load_and_build(args.spec(), &builder, args.flatten, args.time)
}

/// Image size and camera.
#[derive(clap::Args, Clone)]
pub struct CameraArgs {
    /// Image size.
    #[arg(long, default_value = "1024x768", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Camera position X,Y,Z (with --target; default: the scene's camera or a framing one).
    #[arg(long, value_parser = flags::parse_vec3, requires = "target", allow_hyphen_values = true)]
    pub eye: Option<Vec3>,
    /// Point the camera looks at.
    #[arg(long, value_parser = flags::parse_vec3, requires = "eye", allow_hyphen_values = true)]
    pub target: Option<Vec3>,
    /// Vertical field of view in degrees.
    #[arg(long)]
    pub fov: Option<f32>,
}

/// `bvhtrace render`.
#[derive(clap::Args)]
pub struct RenderArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Output PNG.
    #[arg(short, long, default_value = "out.png")]
    pub output: PathBuf,
    #[command(flatten)]
    pub view: CameraArgs,
    /// Where to trace: auto (wgpu on the best Vulkan adapter, else the CPU), gpu (wgpu),
    /// vulkan (the same kernels through ash) or cpu.
    #[arg(long, default_value = "auto")]
    pub backend: Backend,
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// Where a device keeps the tree: buffers (the exact flat layout) or textures (what
    /// CPU adapters such as lavapipe trace fastest) [default: the device's choice].
    #[arg(long, value_parser = parse_storage)]
    pub storage: Option<BvhStorage>,
    /// The largest storage binding a device backend makes, in MiB, when below the
    /// device's own: a tree in buffers larger than it is split into pages of one binding
    /// each (128 is a browser's WebGPU default).
    #[arg(long, value_name = "MIB", value_parser = clap::value_parser!(u64).range(1..=1 << 20))]
    pub max_binding_mib: Option<u64>,
    /// stackless, short-stack, short-stack:K, full-stack or wide [default: the backend's
    /// fastest: full-stack on the CPU, stackless on a GPU; wide with `--layout wide`].
    #[arg(long)]
    pub traversal: Option<Traversal>,
    /// The BVH layout: `binary` (two children per node, the walks above but `wide`) or
    /// `wide` (eight children per node, compressed to 80 bytes, its one walk: the same as
    /// `--traversal wide`) [default: binary, or wide with `--traversal wide`].
    #[arg(long, value_enum)]
    pub layout: Option<Layout>,
    /// What to show.
    #[arg(long, value_enum, default_value_t = Shade::Normal)]
    pub shade: Shade,
    /// Ambient-occlusion rays per pixel.
    #[arg(long, default_value_t = 16)]
    pub ao_samples: u32,
    /// Write run statistics as JSON to this file (`-` for stdout).
    #[arg(long)]
    pub json: Option<String>,
    /// Count each primary ray's box and triangle tests (nodes_per_ray and tris_per_ray in
    /// --json). Counting costs time; the heatmap always counts.
    #[arg(long)]
    pub counters: bool,
    /// Trace the frame this many times and report the median time (the first run, which
    /// includes one-time work such as pipeline creation, is reported apart in --json).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub runs: u32,
    /// Rows per tile: each tile is one batch (keeps dispatches short).
    #[arg(long, default_value_t = 64)]
    pub tile_rows: u32,
    /// Trace masked (alpha-tested) materials as opaque. Without it their alpha cuts them,
    /// on every backend.
    #[arg(long)]
    pub opaque: bool,
    #[command(flatten)]
    pub path: PathArgs,
    #[command(flatten)]
    pub shutter: crate::motion::ShutterArgs,
    /// How the tree bounds motion (with --shutter): linear (each node's box at every time
    /// step, interpolated at the ray's time) or merged (one box over the whole shutter).
    #[arg(long, value_enum, default_value_t = crate::motion::TimeBoundsArg::Linear)]
    pub time_bounds: crate::motion::TimeBoundsArg,
}

/// The path tracer's flags of `bvhtrace render`.
#[derive(clap::Args, Clone)]
pub struct PathArgs {
    /// Samples per pixel (`--shade path`).
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    pub spp: u32,
    /// The most bounces a path takes (`--shade path`).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub max_depth: u32,
    /// Direction toward a sun, X,Y,Z (`--shade path`; default: no sun).
    #[arg(long, value_parser = bvhtrace_shade::args::parse_vec3, allow_hyphen_values = true)]
    pub sun: Option<Vec3>,
    /// The sun's irradiance on a surface facing it (`--shade path`).
    #[arg(long, default_value_t = 3.0)]
    pub sun_power: f32,
    /// The sky's constant radiance, R,G,B (`--shade path`; 0,0,0 for none; default
    /// 0.5,0.5,0.5), or with --environment the scale of the map's radiance (default 1,1,1).
    #[arg(long, value_parser = bvhtrace_shade::args::parse_vec3, allow_hyphen_values = true)]
    pub sky: Option<Vec3>,
    /// An equirectangular Radiance HDR image (`.hdr`, +Y up, its centre column toward -Z)
    /// the sky's radiance comes from, sampled by its luminance (`--shade path`).
    #[arg(long, value_name = "FILE.hdr")]
    pub environment: Option<std::path::PathBuf>,
    /// Scale of the radiance before tone mapping (`--shade path`).
    #[arg(long, default_value_t = 1.0)]
    pub exposure: f32,
    /// Also write the linear radiance as a portable float map (`.pfm`, `--shade path`).
    #[arg(long)]
    pub hdr: Option<std::path::PathBuf>,
    /// The random numbers' seed (`--shade path`).
    #[arg(long, default_value_t = 0)]
    pub seed: u32,
    /// How the device follows the paths (`--shade path`).
    #[arg(long, value_enum, default_value_t = KernelArg::Wavefront)]
    pub kernel: KernelArg,
}

/// `--kernel`: `bvhtrace_path::PathKernel`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum KernelArg {
    /// One invocation follows its pixel's path to the end.
    Megakernel,
    /// Waves of one vertex per live path, the paths in a device buffer between them.
    Wavefront,
}

impl From<KernelArg> for bvhtrace_path::PathKernel {
    fn from(k: KernelArg) -> Self {
        match k {
            KernelArg::Megakernel => bvhtrace_path::PathKernel::Megakernel,
            KernelArg::Wavefront => bvhtrace_path::PathKernel::Wavefront,
        }
    }
}

impl PathArgs {
    pub(crate) fn lighting(&self) -> Result<bvhtrace_path::Lighting> {
        let bad = |v: Vec3| !v.is_finite() || v.min_element() < 0.0;
        let sky = (self.sky).unwrap_or(match self.environment {
            Some(_) => Vec3::ONE,
            None => Vec3::splat(0.5),
        });
        if bad(sky) {
            bail!("--sky must be three finite numbers of at least 0, got {sky}");
        }
        if !(self.sun_power.is_finite() && self.sun_power >= 0.0) {
            bail!(
                "--sun-power must be a finite number of at least 0, got {}",
                self.sun_power
            );
        }
        if !(self.exposure.is_finite() && self.exposure > 0.0) {
            bail!(
                "--exposure must be a finite number above 0, got {}",
                self.exposure
            );
        }
        let sun_dir = self.sun.unwrap_or(Vec3::ZERO);
        if self.sun.is_some() && !(sun_dir.is_finite() && sun_dir.length_squared() > 0.0) {
            bail!("--sun must be a direction (finite, not zero), got {sun_dir}");
        }
        Ok(bvhtrace_path::Lighting {
            sun_dir,
            sun: if self.sun.is_some() {
                Vec3::splat(self.sun_power)
            } else {
                Vec3::ZERO
            },
            env: sky,
        })
    }

    /// The map of `--environment`, loaded and resampled; `None` without the flag.
    pub(crate) fn environment(&self) -> Result<Option<bvhtrace_path::Environment>> {
        use bvhtrace_path::environment::{DEFAULT_SIZE, Environment};
        let Some(path) = &self.environment else {
            return Ok(None);
        };
        Ok(Some(Environment::load(path, DEFAULT_SIZE)?))
    }
}

/// The camera: explicit flags, else the scene's, else framing the bounds. Rays follow the
/// convention documented in `bvhtrace_scene::camera`.
pub fn camera_for(view: &CameraArgs, scene: &Scene) -> Result<Camera> {
    let (w, h) = view.size;
    let mut cam = match (view.eye, view.target) {
        (Some(eye), Some(target)) => Camera {
            eye,
            target,
            fov_y_deg: 45.0,
        },
        _ => scene.camera_or_frame(w as f32 / h as f32),
    };
    if let Some(f) = view.fov {
        if !(f > 0.0 && f < 180.0) {
            bail!("--fov must be between 0 and 180 degrees, got {f}");
        }
        cam.fov_y_deg = f;
    }
    if cam.eye == cam.target {
        bail!("--eye and --target are the same point");
    }
    Ok(cam)
}

/// The time of one pass over a frame's rays.
#[derive(Clone, Copy, Debug, Default)]
struct Timing {
    rays: u64,
    wall_ms: f64,
    gpu_ms: Option<f64>,
    /// Where the wall time went on a device.
    phases: Option<TracePhases>,
}

/// `total` plus `next`, where every trace so far measured it (`first`: none had run):
/// `None` once one did not.
fn sum_of_every<T: std::ops::Add<Output = T>>(
    total: Option<T>,
    next: Option<T>,
    first: bool,
) -> Option<T> {
    match (total, next) {
        (Some(a), Some(b)) => Some(a + b),
        (None, Some(b)) if first => Some(b),
        _ => None,
    }
}

impl Timing {
    fn add(&mut self, n: usize, t: &TraceOutput) {
        let first = self.rays == 0;
        self.rays += n as u64;
        self.wall_ms += t.wall_ms;
        self.phases = sum_of_every(self.phases, t.phases, first);
        self.gpu_ms = sum_of_every(self.gpu_ms, t.gpu_ms, first);
    }

    fn mrays_per_s(&self) -> f64 {
        self.rays as f64 / self.wall_ms.max(1e-9) / 1e3
    }

    fn json(&self) -> Value {
        json!({
            "trace_ms": self.wall_ms,
            "gpu_ms": self.gpu_ms,
            "mrays_per_s": self.mrays_per_s(),
            "phases": self.phases_json(),
        })
    }

    /// The phases of the wall time on a device, milliseconds (`null` on the CPU).
    fn phases_json(&self) -> Value {
        self.phases.map_or(Value::Null, |p| {
            json!({ "rays_up_ms": p.upload_ms, "device_ms": p.device_ms, "hits_back_ms": p.readback_ms })
        })
    }
}

/// What one frame's trace answered: the primary hits (and counters), and the secondary
/// rays' hits with the pixel each belongs to.
struct Frame {
    hits: Vec<Hit>,
    counters: Vec<Counters>,
    secondary: Vec<Hit>,
    owner: Vec<u32>,
    timing: Timing,
}

/// How the BVH is laid out for tracing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Layout {
    /// Two children per node (`FlatBvh`): the full-stack, stackless and short-stack walks.
    Binary,
    /// Eight children per node, compressed (`WideBvh`): the wide walk.
    Wide,
}

impl RenderArgs {
    /// The walk asked for, `--layout` and `--traversal` together (`None`: the backend's
    /// default).
    pub(crate) fn walk(&self) -> Result<Option<Traversal>> {
        match (self.layout, self.traversal) {
            (Some(Layout::Wide), Some(t)) if !t.is_wide() => {
                bail!("--layout wide has one walk, wide; --traversal {t} walks the binary layout")
            }
            (Some(Layout::Binary), Some(t)) if t.is_wide() => {
                bail!("--traversal wide walks the wide layout, not --layout binary")
            }
            (Some(Layout::Wide), _) => Ok(Some(Traversal::Wide)),
            (_, t) => Ok(t),
        }
    }
}

/// What the render traces and shades with.
struct Job<'a> {
    args: &'a RenderArgs,
    traversal: Traversal,
    counters: bool,
    /// The mode, the point light and the AO rays' length.
    view: View,
}

/// `bvhtrace render`: scene, tree, rays, trace, shading, image.
pub fn render(args: RenderArgs) -> Result<()> {
    if args.shutter.shutter.is_some()
        || args
            .scene
            .scene
            .as_deref()
            .is_some_and(bvhtrace_scene::has_curves)
    {
        return crate::motion::render(&args, args.shutter.shutter);
    }
    // Fail on bad flags and output paths before any work.
    let png = AtomicFile::create(&args.output)?;
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    if args.shade == Shade::Ao && args.ao_samples == 0 {
        bail!("--ao-samples must be at least 1");
    }
    let walk = args.walk()?;
    // The device, opened once: it builds the tree (a device builder) and traces it.
    let walks: Vec<Traversal> = walk.into_iter().collect();
    let mut opts = bvhtrace::OpenOptions {
        storage: args.storage,
        max_binding_bytes: args.max_binding_mib.map(|m| m << 20),
        ..backend::options(args.backend, args.adapter.as_deref(), &walks)
    };
    let device = backend::device(&opts)?;
    // What `tune --save` measured fastest on this adapter, unless a walk or storage was
    // asked for.
    if let Some(t) = (walks.is_empty() && args.storage.is_none())
        .then(|| crate::tuned::load(&device.name()))
        .flatten()
    {
        eprintln!(
            "note: {} in {:?} storage, measured fastest here by `tune --save`",
            t.walk, t.storage
        );
        (opts.traversals, opts.storage) = (vec![t.walk], Some(t.storage));
    }
    let Built {
        scene,
        geometry: mut geo,
        load_ms,
        build_ms,
    } = load_and_build(&args.scene, Some(&device))?;
    if args.opaque {
        // Masks the scene's tree was given: dropped, so no walk cuts a candidate.
        geo.set_masks(None).map_err(anyhow::Error::msg)?;
    }
    let bvh = geo.bvh();
    let masks = bvh.masks().cloned();
    let cam = camera_for(&args.view, &scene)?;
    let opened = backend::open_on(&device, bvh, &opts).map_err(|e| match &masks {
        Some(_) => e.context("the scene has masked materials (render --opaque traces them opaque)"),
        None => e,
    })?;
    let tracer: &dyn Tracer = &*opened.tracer;
    let job = Job::new(&args, opened.traversal, &cam, bvh);
    let rays = cam.rays(args.view.size.0, args.view.size.1);
    let (frame, runs) = trace_runs(&job, tracer, &geo, &rays)?;
    let img = compose(&job, &geo, &rays, &frame);
    write_png(png, args.view.size.0, args.view.size.1, img)?;
    let report = Report {
        job: &job,
        scene: &scene,
        geo: &geo,
        bvh,
        cam: &cam,
        tracer,
        fallback: opened.fallback.as_deref(),
        choice: opened.choice.as_deref(),
        frame: &frame,
        runs: &runs,
        load_ms,
        build_ms,
        masks: masks.as_deref(),
    };
    report.print();
    if let Some(j) = json_out {
        j.write(&report.json())?;
    }
    Ok(())
}

impl<'a> Job<'a> {
    /// The job of `args`, tracing with `traversal` (the walk the front door settled on).
    fn new(args: &'a RenderArgs, traversal: Traversal, cam: &Camera, bvh: &FlatBvh) -> Job<'a> {
        Job {
            args,
            traversal,
            counters: args.counters || args.shade == Shade::Heatmap,
            view: View::hard_shadows(args.shade, cam, bvh),
        }
    }

    fn primary(&self) -> TraceOptions {
        TraceOptions::closest(self.traversal).with_counters(self.counters)
    }

    fn secondary(&self) -> TraceOptions {
        TraceOptions::new(self.traversal, Query::Any)
    }

    /// Secondary rays per pixel.
    fn secondary_per_pixel(&self) -> u64 {
        match self.args.shade {
            Shade::Diffuse => 1,
            Shade::Ao => u64::from(self.args.ao_samples),
            _ => 0,
        }
    }
}

/// Traces the frame `args.runs` times; returns the last frame and every run's timing.
fn trace_runs(
    job: &Job,
    tracer: &dyn Tracer,
    geo: &SceneBvh,
    rays: &[Ray],
) -> Result<(Frame, Vec<Timing>)> {
    let per_run = rays.len() as u64 * (1 + job.secondary_per_pixel());
    let pb = crate::output::progress_bar(
        per_run * u64::from(job.args.runs),
        "{spinner} {msg} [{bar:40}] {percent}% ({eta})",
    );
    pb.set_message(format!(
        "tracing {} on {}",
        job.args.shade_name(),
        tracer.backend()
    ));
    let mut runs = Vec::new();
    let (w, h) = job.args.view.size;
    // In 8x8 tiles: a CPU tracer walks a tile per packet, a GPU's neighbouring invocations
    // take neighbouring pixels; the answers go back in pixel order, so the image is the same.
    let tiles = Tiles::new(w, h);
    let tiled = tiles.gather(rays);
    let rays = [rays, &tiled];
    let mut frame = trace_frame(job, tracer, geo, rays, &tiles, &pb)?;
    runs.push(frame.timing);
    for _ in 1..job.args.runs {
        frame = trace_frame(job, tracer, geo, rays, &tiles, &pb)?;
        runs.push(frame.timing);
    }
    pb.finish_and_clear();
    Ok((frame, runs))
}

/// One frame: the primary rays (`[rays, tiled]`: in pixel order and in `tiles`' order),
/// then the secondary rays the shading asks for.
fn trace_frame(
    job: &Job,
    tracer: &dyn Tracer,
    geo: &SceneBvh,
    [rays, tiled]: [&[Ray]; 2],
    tiles: &Tiles,
    pb: &ProgressBar,
) -> Result<Frame> {
    let chunk = (job.args.view.size.0 * job.args.tile_rows) as usize;
    let mut timing = Timing::default();
    let primary = trace_chunked(tracer, tiled, chunk, &job.primary(), pb, &mut timing)?;
    let hits = tiles.scatter(&primary.hits);
    let (sec_rays, owner) = shade::secondary_rays(
        job.args.shade,
        &|p| geo.triangle(p).unwrap_or_default(),
        rays,
        &hits,
        job.view.light,
        job.args.ao_samples,
        job.view.ao_radius,
    );
    let (sec_tiled, place) = tiles.packets(&sec_rays, &owner);
    let idle = sec_tiled.len() - sec_rays.len();
    let secondary = trace_chunked(
        tracer,
        &sec_tiled,
        chunk * 4,
        &job.secondary(),
        pb,
        &mut timing,
    )?;
    // The idle rays that kept tiles apart are not rays of the image.
    timing.rays -= idle as u64;
    Ok(Frame {
        hits,
        counters: primary
            .counters
            .map_or_else(Vec::new, |c| tiles.scatter(&c)),
        secondary: place.iter().map(|&k| secondary.hits[k]).collect(),
        owner,
        timing,
    })
}

/// Traces rays in chunks (one batch each, so dispatches stay short) with a progress bar.
fn trace_chunked(
    tracer: &dyn Tracer,
    rays: &[Ray],
    chunk: usize,
    opts: &TraceOptions,
    pb: &ProgressBar,
    timing: &mut Timing,
) -> Result<TraceOutput> {
    let mut all = TraceOutput {
        counters: opts.counters.then(Vec::new),
        ..TraceOutput::default()
    };
    for c in rays.chunks(chunk.max(1)) {
        let t = tracer.trace(c, opts)?;
        timing.add(c.len(), &t);
        all.hits.extend(t.hits);
        if let (Some(all), Some(k)) = (all.counters.as_mut(), t.counters) {
            all.extend(k);
        }
        pb.inc(c.len() as u64);
    }
    Ok(all)
}

/// The median of the runs' timings (the lower middle one for an even count).
fn median(runs: &[Timing]) -> Timing {
    let mut sorted = runs.to_vec();
    sorted.sort_by(|a, b| a.wall_ms.total_cmp(&b.wall_ms));
    sorted[(sorted.len() - 1) / 2]
}

/// What a render reports, on the terminal and as JSON.
struct Report<'a> {
    job: &'a Job<'a>,
    scene: &'a Scene,
    geo: &'a SceneBvh,
    bvh: &'a FlatBvh,
    cam: &'a Camera,
    tracer: &'a dyn Tracer,
    /// What the front door chose instead of what was asked or preferred, and why.
    fallback: Option<&'a str>,
    /// Why the automatic choice took ray queries or our walks, on a device with both.
    choice: Option<&'a str>,
    frame: &'a Frame,
    runs: &'a [Timing],
    load_ms: f64,
    build_ms: f64,
    /// The masked materials' alpha test, when the scene has them (and not `--opaque`).
    masks: Option<&'a MaskTables>,
}

impl Report<'_> {
    /// The device pipelines the job ran, as the tracer reports them.
    fn pipelines(&self) -> Vec<KernelKey> {
        self.tracer.kernels_used()
    }

    fn print(&self) {
        let (w, h) = self.job.args.view.size;
        let t = median(self.runs);
        let runs = if self.runs.len() > 1 {
            format!(" (median of {} runs)", self.runs.len())
        } else {
            String::new()
        };
        eprintln!(
            "wrote {} ({}x{}, {} triangles, {} on {}): {} rays in {:.1} ms, {:.2} Mrays/s{runs}",
            self.job.args.output.display(),
            w,
            h,
            self.geo.triangle_count(),
            self.walk_name(),
            self.tracer.device_name(),
            t.rays,
            t.wall_ms,
            t.mrays_per_s(),
        );
        if let Some(p) = t.phases {
            let kernels = t
                .gpu_ms
                .map_or(String::new(), |g| format!(" ({g:.1} ms of kernels)"));
            eprintln!(
                "wall: rays up {:.1} ms, on the device {:.1} ms{kernels}, hits back {:.1} ms",
                p.upload_ms, p.device_ms, p.readback_ms
            );
        }
        if let Some(up) = self.masks.and(self.tracer.upload_stats()) {
            eprintln!(
                "alpha masks: cut by the kernels ({} bytes uploaded)",
                up.masks_bytes
            );
        } else if let Some(m) = self.masks {
            let (settled, sampled) = m.counts();
            let all = (settled + sampled).max(1);
            eprintln!(
                "alpha masks: {settled} candidates settled by their triangle's state or micromap, {sampled} \
                 read the texture ({:.1}% settled, over {} runs)",
                100.0 * settled as f64 / all as f64,
                self.runs.len()
            );
        }
    }

    /// The walk, or the driver's for ray queries.
    fn walk_name(&self) -> String {
        if self.tracer.device_build_ms().is_some() {
            "the driver's walk".to_string()
        } else {
            self.job.traversal.to_string()
        }
    }

    fn json(&self) -> Value {
        let (args, frame, stats) = (self.job.args, self.frame, BvhStats::of(self.bvh));
        let hits = frame.hits.iter().filter(|h| h.is_hit());
        let t_sum: f64 = hits.clone().map(|h| f64::from(h.t)).sum();
        let per_ray = |f: fn(&Counters) -> u32| {
            let c = &frame.counters;
            (!c.is_empty()).then(|| c.iter().map(|c| f64::from(f(c))).sum::<f64>() / c.len() as f64)
        };
        let mut features = vec!["closest-hit"];
        if !frame.owner.is_empty() {
            features.push("any-hit");
        }
        if self.job.counters {
            features.push("counters");
        }
        if self.job.traversal.needs_escapes() {
            features.push("escape-links");
        }
        let pipelines = self.pipelines();
        let t = median(self.runs);
        let upload = self.tracer.upload_stats();
        let mut v = json!({
            "scene": args.scene.spec(),
            "width": args.view.size.0, "height": args.view.size.1,
            "triangles": self.geo.triangle_count(),
            "nodes": stats.nodes,
            "depth": stats.depth,
            "sah_cost": stats.sah_cost,
            "sah_cost_pbrt": stats.sah_cost_pbrt,
            "load_ms": self.load_ms,
            "build_ms": self.build_ms,
            "upload_ms": upload.map_or(0.0, |u| u.upload_ms),
            "runs": self.runs.len(),
            "trace_ms": t.wall_ms,
            "gpu_ms": t.gpu_ms,
            "rays": t.rays,
            "mrays_per_s": t.mrays_per_s(),
            "first_run": self.runs[0].json(),
            "hits": hits.count(),
            "t_sum": t_sum,
            "nodes_per_ray": per_ray(|c| c.nodes),
            "tris_per_ray": per_ray(|c| c.tris),
            "backend": self.tracer.backend(),
            "adapter": self.tracer.device_name(),
            "traversal": self.walk_name(),
            "device_build_ms": self.tracer.device_build_ms(),
            "layout": if self.job.traversal.is_wide() { Layout::Wide } else { Layout::Binary },
            "default_traversal": self.tracer.default_traversal().to_string(),
            "builder": args.scene.build.builder.name(),
            "optimize": args.scene.build.optimize,
            "shade": args.shade,
            "uploaded_bytes": self.tracer.uploaded_bytes(),
            "fallback": self.fallback,
            "choice": self.choice,
            "features": features,
            "pipelines": pipelines.iter().map(pipeline_json).collect::<Vec<_>>(),
            "upload": upload.map(|s| upload_json(&s, self.geo.triangle_count())),
            "left_out": left_out(&pipelines, self.scene, self.geo, self.job.traversal),
            "camera": { "eye": self.cam.eye.to_array(), "target": self.cam.target.to_array(), "fov": self.cam.fov_y_deg },
            "time": args.scene.time,
        });
        v["phases"] = t.phases_json();
        if let Some(m) = self.masks {
            v["alpha_masks"] = match self.tracer.upload_stats() {
                // On a device the kernels cut them and count nothing.
                Some(up) => json!({ "uploaded_bytes": up.masks_bytes }),
                None => {
                    let (settled, sampled) = m.counts();
                    json!({ "settled": settled, "sampled": sampled })
                }
            };
        }
        merge(&mut v, geometry::json(self.geo, self.scene));
        v
    }
}

impl RenderArgs {
    fn shade_name(&self) -> &'static str {
        match self.shade {
            Shade::Normal => "normals",
            Shade::Depth => "depth",
            Shade::Diffuse => "diffuse",
            Shade::Ao => "ambient occlusion",
            Shade::Heatmap => "heatmap",
            Shade::Path => "path traced",
        }
    }
}

/// Shades the frame into RGB8 pixels.
fn compose(job: &Job, geo: &SceneBvh, rays: &[Ray], frame: &Frame) -> Vec<u8> {
    let pixels = shade::Pixels {
        size: job.args.view.size,
        rays,
        hits: &frame.hits,
        counters: &frame.counters,
        owner: &frame.owner,
        secondary: &frame.secondary,
        ao_samples: job.args.ao_samples,
    };
    shade::compose_rgb(&job.view, &pixels, &|p| geo.triangle(p).unwrap_or_default())
}

/// The walk, pipelines and upload of the job `info` describes, as the tracer reports
/// them: the tree opened through the front door in the storage asked for, and one probe
/// ray traced per query the job runs (closest hit, with counters for the heatmap; any
/// hit for diffuse and ambient occlusion). No pipeline and no upload without a device.
fn info_job(
    args: &InfoArgs,
    bvh: &FlatBvh,
) -> Result<(Traversal, Vec<KernelKey>, Option<UploadStats>)> {
    let walks: Vec<Traversal> = args.traversal.into_iter().collect();
    let opts = backend::options(Backend::Auto, args.adapter.as_deref(), &walks);
    let opened = bvhtrace::open(bvh, &opts.with_storage(args.storage))?;
    if let Some(why) = &opened.fallback {
        eprintln!("note: {why}");
    }
    let (tracer, traversal) = (&opened.tracer, opened.traversal);
    let probe = [Ray::new(Vec3::ZERO, Vec3::Z)];
    let counters = args.shade == Shade::Heatmap;
    tracer.trace(
        &probe,
        &TraceOptions::closest(traversal).with_counters(counters),
    )?;
    if matches!(args.shade, Shade::Diffuse | Shade::Ao) {
        tracer.trace(&probe, &TraceOptions::new(traversal, Query::Any))?;
    }
    Ok((traversal, tracer.kernels_used(), tracer.upload_stats()))
}

/// One pipeline as JSON: entry point, what it includes, its WGSL files and bindings.
fn pipeline_json(f: &KernelKey) -> Value {
    json!({
        "entry_point": f.entry_point(),
        "features": f.names(),
        "wgsl_files": f.module_set().files().iter().map(|(n, _)| *n).collect::<Vec<_>>(),
        "bindings": f.bindings().iter().map(|b| json!({
            "group": b.group,
            "binding": b.binding,
            "name": b.name,
            "bytes_per_element": b.element_bytes,
            "per": format!("{:?}", b.per).to_lowercase(),
        })).collect::<Vec<_>>(),
    })
}

/// Bytes uploaded, per buffer, in all and per triangle.
fn upload_json(s: &UploadStats, triangles: u64) -> Value {
    json!({
        "storage": format!("{:?}", s.storage).to_lowercase(),
        "nodes": s.nodes_bytes,
        "triangles": s.triangles_bytes,
        "escapes": s.escapes_bytes,
        "instances": s.instances_bytes,
        "total": s.total_bytes(),
        "bytes_per_triangle": s.total_bytes() as f64 / triangles.max(1) as f64,
    })
}

/// What the pipelines leave out, and why.
fn left_out(
    pipelines: &[KernelKey],
    scene: &Scene,
    geo: &SceneBvh,
    traversal: Traversal,
) -> Vec<String> {
    let mut v = Vec::new();
    if pipelines.is_empty() {
        return vec!["everything: traced on the CPU, nothing uploaded".into()];
    }
    if !pipelines.iter().any(|p| p.module_set().escapes()) {
        v.push(format!(
            "escape links (the {traversal} walk does not read them)"
        ));
    }
    if !pipelines.iter().any(|p| p.counters) {
        v.push("counters (asked for only by --counters or --shade heatmap)".into());
    }
    for walk in &bvhtrace_gpu::engine::walks::WALKS {
        if !pipelines
            .iter()
            .any(|p| p.module_set().walks.iter().any(|w| w == walk))
        {
            v.push(format!("the {} walk", walk.stem.replace('_', "-")));
        }
    }
    let a = &scene.attributes;
    for (has, what) in [
        (a.normals, "vertex normals"),
        (a.texcoords, "texture coordinates"),
        (a.colors, "vertex colours"),
        (a.materials, "materials"),
    ] {
        v.push(if has {
            format!("{what} (the scene has them; no GPU job reads them)")
        } else {
            format!("{what} (the scene has none)")
        });
    }
    match geo {
        SceneBvh::Flat { .. } if scene.instance_count() > 1 => v.push(format!(
            "the top level ({} placements flattened to world-space triangles on the host, \
             --flatten)",
            scene.instance_count()
        )),
        SceneBvh::Flat { .. } => {
            v.push("the top level (one placement, flattened: no instance to walk)".into())
        }
        SceneBvh::Instanced(_) => {}
    }
    v
}

/// Adds `extra`'s fields to the JSON object `v`.
fn merge(v: &mut Value, extra: Value) {
    if let (Some(o), Value::Object(e)) = (v.as_object_mut(), extra) {
        o.extend(e);
    }
}

fn parse_storage(s: &str) -> Result<BvhStorage, String> {
    match s {
        "buffers" => Ok(BvhStorage::Buffers),
        "textures" => Ok(BvhStorage::Textures),
        _ => Err(format!("expected buffers or textures, got '{s}'")),
    }
}

/// `bvhtrace info`.
#[derive(clap::Args)]
pub struct InfoArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// The traversal of the job whose GPU pipeline and upload are listed [default: the
    /// fastest on a GPU].
    #[arg(long)]
    pub traversal: Option<Traversal>,
    /// The shading mode of that job (diffuse and ao add an any-hit pipeline, heatmap
    /// counters).
    #[arg(long, value_enum, default_value_t = Shade::Normal)]
    pub shade: Shade,
    /// BVH storage of that upload: buffers (the exact flat layout) or textures (what CPU
    /// adapters such as lavapipe get).
    #[arg(long, default_value = "buffers", value_parser = parse_storage)]
    pub storage: BvhStorage,
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// List the built-in scenes and exit.
    #[arg(long)]
    pub list: bool,
    /// Print as JSON.
    #[arg(long)]
    pub json: bool,
}

/// `bvhtrace info`.
pub fn info(args: InfoArgs) -> Result<()> {
    if args.list {
        for (name, what) in bvhtrace_scene::builtin_names() {
            println!("{name:28} {what}");
        }
        return Ok(());
    }
    // A scene of curves alone has no triangles' tree to describe: its own tree instead.
    if let Some(spec) = (args.scene.scene.as_deref()).filter(|s| bvhtrace_scene::has_curves(s)) {
        let scene = crate::geometry::load_scene(spec)?;
        if scene.triangle_count() == 0 {
            return info_curves_only(&args, spec, &scene);
        }
    }
    let built = load_and_build(
        &args.scene,
        args.scene
            .build
            .build_device(args.adapter.as_deref())?
            .as_ref(),
    )?;
    let job = info_job(&args, built.geometry.bvh())?;
    if args.json {
        let v = info_json(&args, &built, &job);
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        print_info(&args, &built, &job);
    }
    Ok(())
}

/// `bvhtrace info` for a scene of curves alone: the curves and the tree `render` builds
/// over them.
fn info_curves_only(args: &InfoArgs, spec: &str, scene: &bvhtrace_scene::Scene) -> Result<()> {
    let Some(curves) = scene.curves.clone() else {
        bail!("{spec}: no triangles and no curves");
    };
    let (kind, segments, points) = (curves.kind.name(), curves.len(), curves.points.len());
    let t = std::time::Instant::now();
    let bvh = bvhtrace_core::CurveBvh::build(&[], curves, &args.scene.build.options())?;
    let build_ms = t.elapsed().as_secs_f64() * 1e3;
    let (lo, hi) = scene.bounds();
    if args.json {
        let v = json!({
            "scene": spec,
            "description": scene.description,
            "triangles": 0,
            "curves": { "kind": kind, "segments": segments, "points": points },
            "bounds": [lo.to_array(), hi.to_array()],
            "bvh": { "depth": bvh.depth(), "bytes": bvh.byte_size(), "build_ms": build_ms },
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    println!("scene       {spec} ({})", scene.description);
    println!("curves      {segments} {kind} segments, {points} points, no triangles");
    println!("bounds      {:?} .. {:?}", lo.to_array(), hi.to_array());
    println!(
        "bvh         over the segments: depth {}, {} bytes, built in {build_ms:.1} ms (render traces it on wgpu or the CPU)",
        bvh.depth(),
        bvh.byte_size()
    );
    Ok(())
}

/// `bvhtrace info --json`: what [`print_info`] prints and more (the pipelines' WGSL files,
/// the scene's camera and warnings), as one object.
fn info_json(
    args: &InfoArgs,
    built: &Built,
    (traversal, pipelines, upload): &(Traversal, Vec<KernelKey>, Option<UploadStats>),
) -> Value {
    let (scene, geo) = (&built.scene, &built.geometry);
    let bvh = geo.bvh();
    let s = BvhStats::of(bvh);
    let (lo, hi) = scene.bounds();
    let a = &scene.attributes;
    let (nb, eb, tb) = bvh.byte_sizes();
    let mut v = json!({
        "scene": args.scene.spec(),
        "name": scene.name,
        "description": scene.description,
        "synthetic": scene.synthetic,
        "meshes": scene.meshes.len(),
        "instances": scene.instance_count(),
        "triangles": geo.triangle_count(),
        "bounds": { "min": lo.to_array(), "max": hi.to_array() },
        "attributes": { "normals": a.normals, "texcoords": a.texcoords, "colors": a.colors, "materials": a.materials },
        "camera": scene.camera.map(|c| json!({"eye": c.eye.to_array(), "target": c.target.to_array(), "fov": c.fov_y_deg})),
        "builder": args.scene.build.builder.name(),
        "optimize": args.scene.build.optimize,
        "nodes": s.nodes, "leaves": s.leaves, "depth": s.depth,
        "references": s.triangles, "split_budget": args.scene.build.split_budget,
        "sah_cost": s.sah_cost, "sah_cost_pbrt": s.sah_cost_pbrt,
        "leaf_sizes": s.leaf_sizes,
        "bytes": { "nodes": nb, "escapes": eb, "triangles": tb },
        "pipelines": pipelines.iter().map(pipeline_json).collect::<Vec<_>>(),
        "upload": upload.as_ref().map(|u| upload_json(u, geo.triangle_count())),
        "left_out": left_out(pipelines, scene, geo, *traversal),
        "traversal": traversal.to_string(),
        "default_traversal": {
            "cpu": Traversal::CPU_DEFAULT.to_string(),
            "gpu": bvhtrace::DriverTuning::GPU.walk.to_string(),
            "cpu_driver": bvhtrace::DriverTuning::cpu_driver(1).walk.to_string(),
        },
        "load_ms": built.load_ms, "build_ms": built.build_ms,
        "warnings": scene.warnings,
        "time": args.scene.time,
    });
    merge(&mut v, geometry::json(geo, scene));
    v
}

/// `bvhtrace info`'s text: the scene, its tree, the job's pipelines and upload.
fn print_info(
    args: &InfoArgs,
    built: &Built,
    (traversal, pipelines, upload): &(Traversal, Vec<KernelKey>, Option<UploadStats>),
) {
    let (scene, geo) = (&built.scene, &built.geometry);
    let (lo, hi) = scene.bounds();
    let a = &scene.attributes;
    println!("scene       {} ({})", args.scene.spec(), scene.description);
    println!(
        "triangles   {} in {} meshes, {} instances{}",
        geo.triangle_count(),
        scene.meshes.len(),
        scene.instance_count(),
        if scene.synthetic { " (synthetic)" } else { "" }
    );
    if let Some(c) = &scene.curves {
        println!(
            "curves      {} {} segments, {} points (render traces them beside the triangles; the tree below is the triangles')",
            c.len(),
            c.kind.name(),
            c.points.len()
        );
    }
    println!("bounds      {:?} .. {:?}", lo.to_array(), hi.to_array());
    println!(
        "attributes  normals {} texcoords {} colors {} materials {}",
        a.normals, a.texcoords, a.colors, a.materials
    );
    print_tree(args, geo.bvh());
    for p in pipelines {
        let bindings: Vec<String> = p
            .bindings()
            .iter()
            .map(|b| format!("{}.{} {}", b.group, b.binding, b.name))
            .collect();
        println!(
            "pipeline    {} [{}]: {}",
            p.entry_point(),
            p.names().join(", "),
            bindings.join(", ")
        );
    }
    if let Some(upload) = upload {
        println!(
            "upload      {} bytes ({:?}: nodes {}, triangles {}, escapes {}) = {:.1} bytes/triangle",
            upload.total_bytes(),
            upload.storage,
            upload.nodes_bytes,
            upload.triangles_bytes,
            upload.escapes_bytes,
            upload.total_bytes() as f64 / geo.triangle_count().max(1) as f64
        );
    }
    println!(
        "traversals  default {} on the CPU, {} on a GPU, {} on a CPU driver (the fastest \
         measured on each)",
        Traversal::CPU_DEFAULT,
        bvhtrace::DriverTuning::GPU.walk,
        bvhtrace::DriverTuning::cpu_driver(1).walk,
    );
    if let SceneBvh::Instanced(i) = geo {
        let (top, meshes) = i.level_bytes();
        println!(
            "two levels  {} instances of {} meshes: top level {top} bytes, meshes {meshes} bytes",
            i.instances().len(),
            i.meshes().len()
        );
    }
    for l in left_out(pipelines, scene, geo, *traversal) {
        println!("left out    {l}");
    }
    println!(
        "timing      load {:.1} ms, build {:.1} ms",
        built.load_ms, built.build_ms
    );
}

/// `bvhtrace info`'s lines on the tree: how it was built, its shape, its SAH cost, its
/// leaves and its bytes.
fn print_tree(args: &InfoArgs, bvh: &FlatBvh) {
    let build = &args.scene.build;
    let s = BvhStats::of(bvh);
    let how = match build.builder {
        Builder::Device(_) => "built on the device".to_string(),
        Builder::Cpu(_) => format!(
            "{} bins{}",
            build.bins,
            if build.optimize {
                ", optimised by reinsertion"
            } else {
                ""
            }
        ),
    };
    println!(
        "bvh         {} ({how}): {} nodes, {} leaves, depth {}",
        build.builder, s.nodes, s.leaves, s.depth
    );
    if build.builder == Builder::Cpu(BuilderKind::Sbvh) {
        // The leaves may share triangles: how many slots the tree has for how many.
        println!(
            "references  {} for {} triangles ({:.3}x; split budget {})",
            s.triangles,
            s.primitives,
            s.triangles as f64 / s.primitives.max(1) as f64,
            build.split_budget
        );
    }
    println!(
        "sah cost    {:.3} (traversal 1, intersection 1)  {:.3} (PBRT 1/8, 1)",
        s.sah_cost, s.sah_cost_pbrt
    );
    let hist: Vec<String> = s
        .leaf_sizes
        .iter()
        .enumerate()
        .filter(|(_, n)| **n > 0)
        .map(|(k, n)| format!("{k}:{n}"))
        .collect();
    println!("leaf sizes  {}", hist.join(" "));
    let (nb, eb, tb) = bvh.byte_sizes();
    println!("gpu bytes   nodes {nb}, escapes {eb} (stackless/short-stack only), triangles {tb}");
}

/// `bvhtrace dump`.
#[derive(clap::Args)]
pub struct DumpArgs {
    /// A .gltf/.glb file, a .hair file or a `builtin:` name.
    pub scene: Option<String>,
    #[command(flatten)]
    pub view: CameraArgs,
    /// Output file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// With --shutter: the rays of every sample, each with its time, and the triangles at
    /// every time step (version 2 of the format).
    #[command(flatten)]
    pub shutter: crate::motion::ShutterArgs,
}

/// Writes the scene's triangles (world space, input order) and the camera's primary rays in
/// a flat binary form for other tracers (`crates/cli/embree/embree_trace.c`; the format is
/// [`crate::embree::dump_bytes`]'s, or with `--shutter` [`crate::embree::motion_dump_bytes`]'s:
/// the rays `render --shutter` traces, with their times).
pub fn dump(args: DumpArgs) -> Result<()> {
    let out = AtomicFile::create(&args.output)?;
    let spec = args.scene.as_deref().unwrap_or(DEFAULT_SCENE);
    let scene = crate::geometry::load_scene(spec)?;
    let cam = camera_for(&args.view, &scene)?;
    let (w, h) = args.view.size;
    let rays = cam.rays(w, h);
    let (bytes, tris, rays, steps) = match args.shutter.shutter {
        Some((open, close)) if args.shutter.instances => {
            let (meshes, instances) = scene.moving_instances(open, close)?;
            let (rays, times) = crate::motion::sample_rays(&rays, args.shutter.shutter_samples);
            let bytes = crate::embree::instanced_dump_bytes(&meshes, &instances, &rays, &times);
            let steps = instances
                .iter()
                .map(|i| i.transforms.len())
                .max()
                .unwrap_or(1);
            (bytes, scene.triangle_count(), rays.len(), steps)
        }
        Some((open, close)) => {
            let mesh = scene.motion(open, close)?;
            let (rays, times) = crate::motion::sample_rays(&rays, args.shutter.shutter_samples);
            let bytes = crate::embree::motion_dump_bytes(&mesh, &rays, &times);
            (bytes, mesh.len(), rays.len(), mesh.time_steps())
        }
        None => match &scene.curves {
            Some(curves) => {
                let tris = scene.flattened_triangles()?;
                let bytes = crate::embree::curve_dump_bytes(&tris, curves, &rays);
                eprintln!(
                    "the dump holds {} curve segments beside the triangles (version 4)",
                    curves.len()
                );
                (bytes, tris.len(), rays.len(), 1)
            }
            None => {
                let tris = scene.flattened_triangles()?;
                (
                    crate::embree::dump_bytes(&tris, &rays),
                    tris.len(),
                    rays.len(),
                    1,
                )
            }
        },
    };
    out.finish_with_bytes(&bytes)?;
    eprintln!(
        "wrote {}: {tris} triangles in {steps} time step(s), {rays} rays ({w}x{h})",
        args.output.display(),
    );
    Ok(())
}
