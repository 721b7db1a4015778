//! The eframe application: the traced image in the central panel, the controls in the side
//! panel, scene jobs, progressive accumulation, animation playback, the CPU comparison and
//! screenshot runs.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use bvhtrace_core::{
    BuildOptions, BuilderKind, Query, Ray, TraceOptions, TraceOutput, Traversal,
    traverse::DEFAULT_SHORT_STACK,
};
use bvhtrace_gpu::{GpuContext, Tracer};
use bvhtrace_scene::Camera;
use eframe::egui::{self, Color32, RichText};
use eframe::egui_wgpu::RenderState;
use eframe::wgpu;

use crate::camera;
use crate::cli::Args;
use crate::display::Display;
use crate::jobs::{
    Batch, BuiltBvh, Job, JobOutput, JobRequest, PoseTimes, SceneData, Source, Traced,
};
use crate::path_mode::{PathMode, SumsSlot};
use crate::shade::{self, Accumulation, Comparison, Shade, View};

/// How a screenshot run ended: `Ok(message)` or `Err(message)`; `None` while it runs (or
/// when the window was closed before it finished).
pub type Outcome = Arc<Mutex<Option<Result<String, String>>>>;

/// Files to open, oldest first: a name, and the bytes or why they could not be read.
pub type Inbox = Arc<Mutex<Vec<(String, Result<Vec<u8>, String>)>>>;

/// What a front end shares with the app ([`ViewerApp::new`]).
#[derive(Clone, Default)]
pub struct Shared {
    /// How a screenshot run ended.
    pub outcome: Outcome,
    /// glTF files read by the page (a drop, its file picker, a URL) for the app to open; a
    /// file here when the app starts is opened instead of the command line's scene.
    pub inbox: Inbox,
    /// A screenshot run's images where there is no file system to write them to (in a
    /// browser): set when the run ends well.
    pub shot: Arc<Mutex<Option<ShotImages>>>,
}

/// A screenshot run's images, in memory.
#[derive(Clone, Debug)]
pub struct ShotImages {
    /// The window, as a PNG file's bytes.
    pub window_png: Vec<u8>,
    /// The traced image alone, RGBA8, `size[0]` by `size[1]`.
    pub traced_rgba: Vec<u8>,
    /// The traced image's size, pixels.
    pub size: [u32; 2],
    /// The camera it was traced with.
    pub camera: Camera,
    /// True when the GPU traced every ray of the last frame.
    pub on_gpu: bool,
    /// The animation time of the traced image, seconds (in a browser, a frame behind the
    /// latest pose while an animation plays).
    pub time: f32,
    /// Samples per pixel of a path-traced image (0 in the other modes).
    pub samples: u32,
}

/// The largest traced image side, pixels.
const MAX_SIDE: u32 = 4096;

/// The tracing time per frame that automatic samples per frame aim at, milliseconds.
pub const FRAME_BUDGET_MS: f64 = 80.0;

/// How far a `--screenshot` run's animation advances per frame, seconds.
pub const SCREENSHOT_STEP_S: f32 = 1.0 / 30.0;

/// Animation playback: the time shown, whether it advances, and what the last new pose
/// cost.
#[derive(Clone, Debug, Default)]
struct Playback {
    /// The time shown, seconds (wrapped into the scene's animation).
    time: f32,
    /// The time advances every frame.
    playing: bool,
    /// Advance this much per frame instead of the frame's wall-clock time (screenshot
    /// runs, so that their image does not depend on the machine's speed).
    fixed_step: Option<f32>,
    /// The time the next scene opened starts at (`--time` for the first one, then 0).
    start_time: f32,
    /// What the last new pose cost.
    last: Option<PoseTimes>,
    /// New poses since the scene was opened.
    poses: u64,
}

/// What the user chose in the side panel.
#[derive(Clone, Debug, PartialEq)]
struct Settings {
    builder: BuilderKind,
    /// The walk, one of [`Traversal::ALL`] (a short stack's size is `short_stack`).
    traversal: Traversal,
    short_stack: u32,
    shade: Shade,
    heatmap: bool,
    samples_per_frame: u32,
    /// Pick the samples per frame from the measured speed to keep frames near
    /// [`FRAME_BUDGET_MS`].
    auto_samples: bool,
    max_samples: u32,
    render_scale: f32,
    prefer_cpu: bool,
}

impl Settings {
    fn traversal(&self) -> Traversal {
        match self.traversal {
            Traversal::ShortStack(_) => Traversal::ShortStack(self.short_stack.clamp(1, 32)),
            t => t,
        }
    }

    fn build_options(&self) -> BuildOptions {
        BuildOptions {
            builder: self.builder,
            ..Default::default()
        }
    }
}

/// Everything the primary pass depends on: when it changes, accumulation restarts.
#[derive(Clone, Debug, PartialEq)]
struct PassKey {
    camera: Camera,
    size: [u32; 2],
    shade: Shade,
    heatmap: bool,
    traversal: Traversal,
    prefer_cpu: bool,
    /// The BVH: a new build or pose is a new generation, posed at `time` seconds.
    generation: u64,
    time: f32,
}

/// Timing of the last frame that traced something.
#[derive(Clone, Debug, Default)]
struct FrameStats {
    rays: u64,
    trace_ms: f64,
    gpu_ms: Option<f64>,
    on_gpu: bool,
    frame_ms: f32,
}

impl FrameStats {
    /// Counts a traced batch of `n` rays.
    fn add(&mut self, n: usize, t: &TraceOutput, on_gpu: bool) {
        self.rays += n as u64;
        self.trace_ms += t.wall_ms;
        self.on_gpu &= on_gpu;
        self.gpu_ms = match (self.gpu_ms, t.gpu_ms) {
            (Some(a), Some(b)) => Some(a + b),
            _ => None,
        };
    }
}

/// What a batch in flight traces.
enum Work {
    /// The primary pass for this key.
    Primary(PassKey),
    /// This many secondary samples per pixel.
    Samples(u32),
}

/// A batch being traced, and what it is for.
struct InFlight {
    work: Work,
    batch: Batch,
}

/// The last comparison with the CPU twin.
struct CompareView {
    result: Comparison,
    gpu_image: bool,
    traversal: Traversal,
    cpu_ms: f64,
    display: Display,
    open: bool,
}

/// A screenshot run in progress.
struct Shot {
    path: PathBuf,
    frames: u32,
    frames_done: u32,
    requested_at: Option<u32>,
    image: Arc<Mutex<Option<Arc<egui::ColorImage>>>>,
    /// In the path mode, the sums read back with the screenshot (its one readback).
    sums: Option<SumsSlot>,
}

/// The viewer.
pub struct ViewerApp {
    /// eframe's device wrapped for the tracer, or why it cannot trace.
    gpu: Result<GpuContext, String>,
    render_state: Option<RenderState>,
    adapter_line: String,
    /// The device is a CPU driver (lavapipe): its timestamps do not time the kernels.
    cpu_adapter: bool,
    scene: Option<Arc<SceneData>>,
    built: Option<BuiltBvh>,
    /// The batch being traced (in a browser it may finish on a later frame).
    in_flight: Option<InFlight>,
    generation: u64,
    job: Option<Job>,
    error: Option<String>,
    settings: Settings,
    cam: Camera,
    pending_camera: Option<Camera>,
    fly_speed: f32,
    accum: Option<Accumulation>,
    key: Option<PassKey>,
    view: Option<View>,
    primary_on_gpu: bool,
    /// Secondary rays traced per millisecond, smoothed (for automatic samples per frame).
    secondary_rate: Option<f64>,
    /// Samples the last frame added.
    last_k: u32,
    image: Vec<u8>,
    display: Display,
    stats: FrameStats,
    compare: Option<CompareView>,
    open_text: String,
    flags_text: String,
    flags_error: Option<String>,
    last_aspect: f32,
    fov_override: Option<f32>,
    /// A new scene was installed: set its camera on the next central-panel layout.
    reset_camera: bool,
    shot: Option<Shot>,
    compare_pending: bool,
    image_rect: egui::Rect,
    shared: Shared,
    /// When the app started, and how long after it the first traced image was shown.
    started: web_time::Instant,
    first_image_ms: Option<f64>,
    playback: Playback,
    /// The path mode's tracer, made when the mode is first shown for a scene and pose.
    path: Option<PathMode>,
    /// One being made (its kernel compiling: in a browser, across frames), and for what.
    path_pending: Option<((u64, f32), PathSlot)>,
    /// The path mode's environment map (`--environment`), loaded once.
    environment: Option<std::sync::Arc<bvhtrace_path::Environment>>,
}

/// Where a path tracer being made lands.
type PathSlot = std::rc::Rc<std::cell::RefCell<Option<Result<PathMode, String>>>>;

impl ViewerApp {
    /// Creates the app from eframe's creation context: wraps eframe's wgpu device (the one
    /// that draws the window) in a [`GpuContext`] for the traversal, and starts loading the
    /// scene named on the command line. A device the tracer cannot use (see
    /// [`GpuContext::from_device`]) is reported on stderr and in the side panel, and the
    /// CPU traces instead.
    pub fn new(cc: &eframe::CreationContext<'_>, args: &Args, shared: Shared) -> ViewerApp {
        let render_state = cc.wgpu_render_state.clone();
        let (gpu, adapter_line, cpu_adapter) = match &render_state {
            Some(rs) => {
                let info = rs.adapter.get_info();
                let line = format!("{} ({:?}, {:?})", info.name, info.device_type, info.backend);
                let cpu = info.device_type == wgpu::DeviceType::Cpu;
                let ctx = GpuContext::from_device(rs.device.clone(), rs.queue.clone(), info)
                    .map_err(|e| {
                        let e = format!("the GPU cannot trace: {e}");
                        eprintln!("error: {e} (tracing on the CPU instead)");
                        e
                    });
                (ctx, line, cpu)
            }
            None => (Err("no wgpu device".to_string()), "none".to_string(), true),
        };
        let traversal = args.traversal;
        let k = match traversal {
            Traversal::ShortStack(k) => k,
            _ => DEFAULT_SHORT_STACK,
        };
        let settings = Settings {
            builder: args.builder,
            traversal,
            short_stack: k,
            // `--shade heatmap` is the heatmap switch over the default surface mode.
            shade: if args.shade == Shade::Heatmap {
                Shade::default()
            } else {
                args.shade
            },
            heatmap: args.heatmap || args.shade == Shade::Heatmap,
            samples_per_frame: if cpu_adapter { 2 } else { 8 },
            auto_samples: true,
            max_samples: 256,
            render_scale: args.scale.unwrap_or(if cpu_adapter { 0.5 } else { 1.0 }),
            prefer_cpu: args.cpu,
        };
        let pending_camera = match (args.eye, args.target) {
            (Some(eye), Some(target)) => Some(Camera {
                eye,
                target,
                fov_y_deg: args.fov.unwrap_or(45.0),
            }),
            _ => None,
        };
        let spec = args
            .scene
            .clone()
            .unwrap_or_else(|| bvhtrace_scene::DEFAULT_SCENE.to_string());
        let mut app = ViewerApp {
            gpu,
            render_state,
            adapter_line,
            cpu_adapter,
            scene: None,
            built: None,
            in_flight: None,
            generation: 0,
            job: None,
            error: None,
            settings,
            cam: Camera::frame(glam::Vec3::splat(-1.0), glam::Vec3::splat(1.0), 1.0),
            pending_camera,
            fly_speed: 1.0,
            accum: None,
            key: None,
            view: None,
            primary_on_gpu: false,
            secondary_rate: None,
            last_k: 0,
            image: Vec::new(),
            display: Display::default(),
            stats: FrameStats::default(),
            compare: None,
            open_text: spec.clone(),
            flags_text: String::new(),
            flags_error: None,
            last_aspect: args.size.0 as f32 / args.size.1 as f32,
            fov_override: args.fov,
            reset_camera: false,
            shot: args.screenshot.clone().map(|path| Shot {
                path,
                frames: args.frames,
                frames_done: 0,
                requested_at: None,
                image: Arc::new(Mutex::new(None)),
                sums: None,
            }),
            compare_pending: args.compare,
            image_rect: egui::Rect::from_min_size(egui::Pos2::ZERO, egui::vec2(800.0, 600.0)),
            shared,
            started: web_time::Instant::now(),
            first_image_ms: None,
            path: None,
            path_pending: None,
            environment: None,
            playback: Playback {
                time: args.time,
                playing: args.play,
                fixed_step: args.screenshot.is_some().then_some(SCREENSHOT_STEP_S),
                start_time: args.time,
                last: None,
                poses: 0,
            },
        };
        if let Some(path) = &args.environment {
            use bvhtrace_path::environment::{DEFAULT_SIZE, Environment};
            match Environment::load(path, DEFAULT_SIZE) {
                Ok(e) => app.environment = Some(std::sync::Arc::new(e)),
                Err(e) => {
                    eprintln!("error: {e}");
                    app.error = Some(e.to_string());
                }
            }
        }
        if !app.open_from_inbox(&cc.egui_ctx) {
            app.start_job(&cc.egui_ctx, Source::Load(spec));
        }
        app
    }
}

fn axis(i: &egui::InputState, plus: egui::Key, minus: egui::Key) -> f32 {
    f32::from(u8::from(i.key_down(plus))) - f32::from(u8::from(i.key_down(minus)))
}

impl ViewerApp {
    /// Starts loading a scene or rebuilding the current one's BVH on a worker thread. A job
    /// already running is abandoned (its result is dropped).
    fn start_job(&mut self, ctx: &egui::Context, source: Source) {
        let (what, time) = match &source {
            Source::Load(s) => (format!("opening {s}"), self.playback.start_time),
            Source::Bytes { name, .. } => (format!("opening {name}"), self.playback.start_time),
            Source::Reuse(s) => (
                format!("rebuilding the BVH of {}", s.name),
                self.playback.time,
            ),
        };
        let wake = ctx.clone();
        self.job = Some(Job::spawn(
            JobRequest {
                source,
                build: self.settings.build_options(),
                traversal: self.settings.traversal(),
                time,
                gpu: self.gpu.clone().map(bvhtrace::Device::wgpu),
            },
            what,
            move || wake.request_repaint(),
        ));
    }

    /// Opens a scene spec typed, dropped or given on the command line.
    fn open(&mut self, ctx: &egui::Context, spec: &str) {
        let spec = spec.trim();
        if spec.is_empty() {
            self.error = Some("type a .gltf/.glb path or a builtin: name first".into());
            return;
        }
        self.start_job(ctx, Source::Load(spec.to_string()));
    }

    fn poll_job(&mut self) {
        let Some(job) = &mut self.job else { return };
        let Some(result) = job.poll() else { return };
        self.job = None;
        match result {
            Ok(out) => self.install(out),
            Err(e) => self.error = Some(e),
        }
    }

    fn install(&mut self, out: JobOutput) {
        let JobOutput {
            scene,
            new_scene,
            built,
        } = out;
        if new_scene {
            // The camera is set in `central`, once the image's aspect ratio is known.
            self.reset_camera = true;
            self.fly_speed = 0.5 * scene.diagonal();
            self.open_text = scene.spec.clone();
            self.compare = None;
            self.error = None;
            self.playback.time = built.time;
            self.playback.start_time = 0.0;
            self.playback.last = None;
            self.playback.poses = 0;
        }
        self.built = Some(built);
        self.in_flight = None;
        self.scene = Some(scene);
        self.generation += 1;
    }

    /// Advances the animation's time by one frame while it plays (a no-op for a scene
    /// without animation), and asks for the next frame.
    fn advance_time(&mut self, ctx: &egui::Context) {
        let Some(scene) = &self.scene else { return };
        if !scene.animated() || !self.playback.playing {
            return;
        }
        let dt = self
            .playback
            .fixed_step
            .unwrap_or_else(|| ctx.input(|i| i.stable_dt.clamp(0.0, 0.1)));
        self.playback.time = scene.wrap_time(self.playback.time + dt);
        ctx.request_repaint();
    }

    /// Moves the BVH to the shown time when it is posed at another (after the time
    /// advanced, the slider moved, or a rebuild finished): the top level rebuilt and
    /// updated in place on the device for two levels, the whole BVH for a flattened scene.
    /// The next [`ViewerApp::step`] re-traces.
    fn pose(&mut self) {
        let (Some(scene), Some(built)) = (&self.scene, &mut self.built) else {
            return;
        };
        // A batch still on the GPU (in a browser) holds the upload: pose after it.
        if !scene.animated() || built.time == self.playback.time || self.in_flight.is_some() {
            return;
        }
        match built.pose(&scene.scene, self.playback.time) {
            Ok(times) => {
                self.playback.last = Some(times);
                self.playback.poses += 1;
                self.generation += 1;
            }
            Err(e) => {
                self.error = Some(e);
                self.playback.playing = false;
                // Do not retry this time every frame.
                self.playback.time = built.time;
            }
        }
    }

    /// Frames the whole scene (the `F` key).
    fn frame_scene(&mut self) {
        if let Some(s) = &self.scene {
            let fov = self.cam.fov_y_deg;
            self.cam = Camera::frame(s.bounds.0, s.bounds.1, self.last_aspect);
            self.cam.fov_y_deg = fov;
            // Keep the framing valid for a different field of view: move back along the view.
            let scale = (camera_half_tan(bvhtrace_scene::camera::FRAME_FOV_Y_DEG)
                / camera_half_tan(fov))
            .clamp(0.05, 50.0);
            self.cam.eye = self.cam.target + (self.cam.eye - self.cam.target) * scale;
        }
    }

    /// Traces what this frame needs: the primary pass when anything it depends on changed,
    /// then one batch of secondary samples while the view accumulates. Natively each batch
    /// finishes when started; in a browser a batch on the GPU finishes on a later frame,
    /// which takes its result and starts the next. Returns true when the image changed.
    fn step(&mut self, ctx: &egui::Context, size: [u32; 2]) -> bool {
        let key = PassKey {
            camera: self.cam,
            size,
            shade: self.settings.shade,
            heatmap: self.settings.heatmap,
            traversal: self.settings.traversal(),
            prefer_cpu: self.settings.prefer_cpu,
            generation: self.generation,
            time: self.built.as_ref().map_or(0.0, |b| b.time),
        };
        let mut stats = FrameStats {
            on_gpu: true,
            gpu_ms: Some(0.0),
            frame_ms: self.stats.frame_ms,
            ..Default::default()
        };
        let (mut changed, mut sampled) = (false, false);
        loop {
            if let Some(flight) = self.in_flight.take() {
                let Some(built) = &mut self.built else { break };
                let Some(result) = built.finish(&flight.batch) else {
                    // Still on the GPU: its answer asks for the frame that takes it.
                    self.in_flight = Some(flight);
                    break;
                };
                let Traced { rays, out, on_gpu } = match result {
                    Ok(r) => r,
                    Err(e) => {
                        self.error = Some(format!("tracing failed: {e}"));
                        break;
                    }
                };
                stats.add(rays.len(), &out, on_gpu);
                changed |= match flight.work {
                    Work::Primary(done) => self.primary_done(done, rays, out, on_gpu),
                    Work::Samples(k) if self.key.as_ref() == Some(&key) => {
                        self.samples_done(&rays, &out, k)
                    }
                    Work::Samples(_) => false,
                };
            }
            let Some(work) = self.next_work(&key, sampled) else {
                break;
            };
            sampled |= matches!(work, Work::Samples(_));
            self.start(ctx, work, &key);
        }
        if changed && let (Some(acc), Some(view)) = (&self.accum, &self.view) {
            self.image = acc.compose(view);
            self.stats = stats;
            self.first_image_ms
                .get_or_insert_with(|| self.started.elapsed().as_secs_f64() * 1e3);
        }
        changed
    }

    /// What to trace next, if anything: the primary pass when `key` is not the shown
    /// one, else a batch of samples (one per frame) while the view accumulates.
    fn next_work(&mut self, key: &PassKey, sampled: bool) -> Option<Work> {
        let s = &self.settings;
        self.built.as_ref()?;
        if self.key.as_ref() != Some(key) {
            return Some(Work::Primary(key.clone()));
        }
        let (acc, view) = (self.accum.as_ref()?, self.view.as_ref()?);
        if sampled || !view.accumulates() || acc.samples >= s.max_samples || acc.hit_count() == 0 {
            return None;
        }
        let wanted = match (s.auto_samples, self.secondary_rate) {
            (true, Some(rays_per_ms)) => {
                (FRAME_BUDGET_MS * rays_per_ms / acc.hit_count() as f64).floor() as u32
            }
            (true, None) => 1,
            (false, _) => s.samples_per_frame,
        };
        Some(Work::Samples(
            wanted.clamp(1, 64).min(s.max_samples - acc.samples),
        ))
    }

    /// Starts tracing `work`'s rays.
    fn start(&mut self, ctx: &egui::Context, work: Work, key: &PassKey) {
        let Some(built) = &mut self.built else { return };
        let (rays, opts) =
            match &work {
                Work::Primary(_) => {
                    if self.key.as_ref().is_some_and(|k| {
                        k.traversal != key.traversal || k.prefer_cpu != key.prefer_cpu
                    }) {
                        self.secondary_rate = None;
                    }
                    if self
                        .key
                        .as_ref()
                        .is_some_and(|k| k.traversal != key.traversal)
                    {
                        built.retry_gpu();
                        built.prepare(key.traversal);
                    }
                    let rays = key.camera.rays(key.size[0], key.size[1]);
                    // In 8x8 tiles, one packet each on the CPU tracer; back in pixel
                    // order in `primary_done`.
                    let rays = bvhtrace::Tiles::new(key.size[0], key.size[1]).gather(&rays);
                    let opts = TraceOptions::closest(key.traversal).with_counters(key.heatmap);
                    (rays, opts)
                }
                Work::Samples(k) => {
                    let (Some(acc), Some(view)) = (&mut self.accum, &self.view) else {
                        return;
                    };
                    let rays = acc.secondary_rays(view, *k);
                    (rays, TraceOptions::new(key.traversal, Query::Any))
                }
            };
        let wake = ctx.clone();
        let batch = built.start_trace(rays, opts, key.prefer_cpu, move || wake.request_repaint());
        self.in_flight = Some(InFlight { work, batch });
    }

    /// Shows a finished primary pass: a new accumulation over its hits. A pass for a view
    /// that changed while it was traced is dropped.
    fn primary_done(&mut self, key: PassKey, rays: Vec<Ray>, t: TraceOutput, on_gpu: bool) -> bool {
        let Some(built) = &self.built else {
            return false;
        };
        if key.generation != self.generation {
            return false;
        }
        self.primary_on_gpu = on_gpu;
        // Traced in tiles (see `start`): back in pixel order.
        let tiles = bvhtrace::Tiles::new(key.size[0], key.size[1]);
        self.accum = Some(Accumulation::new(
            key.size[0],
            key.size[1],
            tiles.scatter(&rays),
            tiles.scatter(&t.hits),
            t.counters.map_or_else(Vec::new, |c| tiles.scatter(&c)),
            |p| built.geometry.triangle(p),
        ));
        let mode = if key.heatmap {
            Shade::Heatmap
        } else {
            key.shade
        };
        let diagonal = self.scene.as_ref().map_or(1.0, |s| s.diagonal());
        self.view = Some(View::for_camera(mode, &key.camera, diagonal));
        self.key = Some(key);
        true
    }

    /// Adds a finished batch of `k` samples per pixel to the accumulation.
    fn samples_done(&mut self, rays: &[Ray], t: &TraceOutput, k: u32) -> bool {
        let (Some(acc), Some(view)) = (&mut self.accum, &self.view) else {
            return false;
        };
        let rate = rays.len() as f64 / t.wall_ms.max(1e-3);
        self.secondary_rate = Some(match self.secondary_rate {
            Some(r) => 0.5 * r + 0.5 * rate,
            None => rate,
        });
        self.last_k = k;
        acc.accumulate(view, rays, &t.hits, k);
        true
    }

    /// True while more frames would add samples.
    fn accumulating(&self) -> bool {
        match (&self.accum, &self.view) {
            (Some(a), Some(v)) => {
                v.accumulates() && a.samples < self.settings.max_samples && a.hit_count() > 0
            }
            _ => false,
        }
    }

    /// Traces the displayed image's primary rays with the CPU twin and compares hits.
    fn compare_with_cpu(&mut self, ctx: &egui::Context) {
        let (Some(acc), Some(built), Some(key)) = (&self.accum, &self.built, &self.key) else {
            return;
        };
        let t = match built
            .cpu()
            .trace(&acc.rays, &TraceOptions::closest(key.traversal))
        {
            Ok(t) => t,
            Err(e) => {
                self.error = Some(format!("the CPU comparison failed: {e}"));
                return;
            }
        };
        let (result, img) = shade::compare_hits(&acc.hits, &t.hits, &self.image);
        let mut display = Display::default();
        display.set(
            ctx,
            self.render_state.as_ref(),
            "bvhtrace difference",
            [acc.width, acc.height],
            &img,
        );
        self.compare = Some(CompareView {
            result,
            gpu_image: self.primary_on_gpu,
            traversal: key.traversal,
            cpu_ms: t.wall_ms,
            display,
            open: true,
        });
    }

    /// Writes the screenshot to `path`; in a browser, keeps it and the traced image in
    /// [`Shared::shot`] instead.
    fn save_shot(
        &self,
        path: &std::path::Path,
        img: &egui::ColorImage,
        sums: Option<Result<bvhtrace_path::Accumulation, String>>,
    ) -> Result<(), String> {
        if cfg!(not(target_arch = "wasm32")) {
            sums.transpose()?;
            return crate::png::write_png_atomic(path, img);
        }
        let size = self.accum.as_ref().map_or([0, 0], |a| [a.width, a.height]);
        let mut images = ShotImages {
            window_png: crate::png::encode_png(img)?,
            traced_rgba: self.image.clone(),
            size,
            camera: self.key.as_ref().map_or(self.cam, |k| k.camera),
            on_gpu: self.stats.on_gpu,
            time: self.key.as_ref().map_or(0.0, |k| k.time),
            samples: 0,
        };
        // The path mode's image is its sums, tone mapped as `bvhtrace render` maps them.
        if let (Some(sums), Some((camera, _))) = (
            sums.transpose()?,
            self.path.as_ref().and_then(PathMode::view),
        ) {
            images.traced_rgba = (sums.to_srgb8(1.0).chunks_exact(3))
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            images.size = [sums.width, sums.height];
            images.samples = sums.samples();
            images.camera = camera;
            images.on_gpu = true;
        }
        if let Ok(mut s) = self.shared.shot.lock() {
            *s = Some(images);
        }
        Ok(())
    }

    fn finish_shot(&mut self, ctx: &egui::Context, result: Result<String, String>) {
        if let Ok(mut o) = self.shared.outcome.lock() {
            *o = Some(result);
        }
        self.shot = None;
        ctx.send_viewport_cmd(egui::ViewportCommand::Close);
    }

    /// Advances a `--screenshot` run: counts frames once the scene is shown, asks for the
    /// screenshot, saves it and closes the window.
    fn screenshot_step(&mut self, ctx: &egui::Context) {
        let path_mode = self.settings.shade == Shade::Path;
        let Some(shot) = &mut self.shot else { return };
        ctx.request_repaint();
        if self.job.is_some() {
            return;
        }
        if self.scene.is_none() {
            let e = self
                .error
                .clone()
                .unwrap_or_else(|| "no scene loaded".into());
            self.finish_shot(ctx, Err(e));
            return;
        }
        match shot.requested_at {
            None => {
                let shown = match &self.path {
                    Some(p) if self.settings.shade == Shade::Path => p.samples() > 0,
                    _ => self.display.id().is_some(),
                };
                if shown {
                    shot.frames_done += 1;
                }
                if shot.frames_done >= shot.frames {
                    shot.requested_at = Some(shot.frames_done);
                    // A page has no file system: it hands the sums to its caller.
                    if path_mode && cfg!(target_arch = "wasm32") {
                        shot.sums = self.path.as_ref().map(PathMode::read_sums);
                    }
                    let slot = shot.image.clone();
                    let wake = ctx.clone();
                    ctx.request_screenshot(move |img| {
                        if let Ok(mut s) = slot.lock() {
                            *s = Some(img);
                        }
                        wake.request_repaint();
                    });
                }
            }
            Some(at) => {
                let sums_ready = (shot.sums.as_ref()).is_none_or(|s| s.borrow().is_some());
                let taken = match sums_ready {
                    true => shot.image.lock().ok().and_then(|mut g| g.take()),
                    false => None,
                };
                if let Some(img) = taken {
                    let path = shot.path.clone();
                    let [w, h] = img.size;
                    let why = self.built.as_ref().and_then(|b| b.gpu_problem());
                    let path_mode = self.settings.shade == Shade::Path;
                    let backend = match (self.stats.on_gpu || path_mode, why) {
                        (true, _) if path_mode => "GPU, path traced with no readback".to_string(),
                        (true, _) => "GPU".to_string(),
                        (false, Some(why)) => format!("CPU ({why})"),
                        (false, None) => "CPU".to_string(),
                    };
                    let samples = match &self.path {
                        Some(p) if self.settings.shade == Shade::Path => p.samples(),
                        _ => self.accum.as_ref().map_or(0, |a| a.samples),
                    };
                    let animation = match (&self.scene, &self.built) {
                        (Some(s), Some(b)) if s.animated() => format!(
                            "; animation at t = {:.4} s, {} new poses ({}){}",
                            b.time,
                            self.playback.poses,
                            if b.geometry.is_two_level() {
                                "top level rebuilt and updated in place"
                            } else {
                                "flattened BVH rebuilt"
                            },
                            if self.playback.playing {
                                ", playing"
                            } else {
                                ""
                            }
                        ),
                        _ => String::new(),
                    };
                    let frames = shot.frames;
                    let first = self.first_image_ms.unwrap_or(f64::NAN);
                    let sums = shot.sums.take().and_then(|s| s.borrow_mut().take());
                    let samples = match &sums {
                        Some(Ok(s)) => s.samples(),
                        _ => samples,
                    };
                    let rate = match (&self.path, path_mode) {
                        (Some(p), true) => p
                            .samples_per_second()
                            .map_or(String::new(), |r| format!(" at {r:.1} samples/s")),
                        _ => String::new(),
                    };
                    let r = self.save_shot(&path, &img, sums).map(|()| {
                        format!(
                            "wrote {} ({w}x{h}; {frames} frames, traced on the {backend}, \
                             {samples} accumulated samples per pixel{rate}{animation}; first image \
                             {first:.0} ms after the start)",
                            path.display(),
                        )
                    });
                    self.finish_shot(ctx, r);
                } else {
                    shot.frames_done += 1;
                    if shot.frames_done > at + 300 {
                        self.finish_shot(
                            ctx,
                            Err("the screenshot never arrived from the renderer".into()),
                        );
                    }
                }
            }
        }
    }
}

fn camera_half_tan(fov_deg: f32) -> f32 {
    (fov_deg.clamp(1.0, 179.0).to_radians() * 0.5).tan()
}

fn fmt_count(n: usize) -> String {
    let s = n.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

fn vec3_editor(ui: &mut egui::Ui, label: &str, v: &mut glam::Vec3, speed: f32) -> bool {
    let mut changed = false;
    ui.horizontal(|ui| {
        ui.label(label);
        for c in [&mut v.x, &mut v.y, &mut v.z] {
            changed |= ui
                .add(egui::DragValue::new(c).speed(speed).max_decimals(4))
                .changed();
        }
    });
    changed
}

/// Paints the heatmap's colour ramp with its end values.
fn heatmap_legend(ui: &mut egui::Ui, max: u32) {
    let width = ui.available_width().min(260.0);
    let (rect, _) = ui.allocate_exact_size(egui::vec2(width, 14.0), egui::Sense::hover());
    let steps = 64;
    for k in 0..steps {
        let x0 = rect.left() + rect.width() * k as f32 / steps as f32;
        let x1 = rect.left() + rect.width() * (k + 1) as f32 / steps as f32;
        let [r, g, b] = bvhtrace_shade::palette::heat_ramp((k as f32 + 0.5) / steps as f32);
        ui.painter().rect_filled(
            egui::Rect::from_min_max(
                egui::pos2(x0, rect.top()),
                egui::pos2(x1 + 0.5, rect.bottom()),
            ),
            0.0,
            Color32::from_rgb(r, g, b),
        );
    }
    ui.horizontal(|ui| {
        ui.set_width(width);
        ui.label("0");
        ui.with_layout(egui::Layout::right_to_left(egui::Align::Center), |ui| {
            ui.label(max.to_string());
        });
    });
    ui.label(RichText::new("box tests (nodes visited) per primary ray").small());
}

impl ViewerApp {
    fn side_panel(&mut self, ui: &mut egui::Ui) {
        let ctx = ui.ctx().clone();
        ui.spacing_mut().item_spacing.y = 3.0;
        ui.spacing_mut().interact_size.y = 18.0;
        ui.label(RichText::new("bvhtrace viewer").strong().size(16.0));
        if let Some(job) = &self.job {
            ui.horizontal(|ui| {
                ui.spinner();
                ui.label(format!(
                    "{} ({:.1} s)",
                    job.stage,
                    job.started.elapsed().as_secs_f32()
                ));
            });
        }
        egui::CollapsingHeader::new("Scene")
            .default_open(true)
            .show(ui, |ui| self.scene_section(ui, &ctx));
        if self.scene.as_ref().is_some_and(|s| s.animated()) {
            egui::CollapsingHeader::new("Animation")
                .default_open(true)
                .show(ui, |ui| self.animation_section(ui));
        }
        egui::CollapsingHeader::new("BVH and tracing")
            .default_open(true)
            .show(ui, |ui| self.tracing_section(ui, &ctx));
        egui::CollapsingHeader::new("Shading")
            .default_open(true)
            .show(ui, |ui| self.shading_section(ui));
        egui::CollapsingHeader::new("Performance")
            .default_open(true)
            .show(ui, |ui| self.performance_section(ui, &ctx));
        egui::CollapsingHeader::new("Camera")
            .default_open(true)
            .show(ui, |ui| self.camera_section(ui));
    }

    fn scene_section(&mut self, ui: &mut egui::Ui, ctx: &egui::Context) {
        ui.horizontal(|ui| {
            let edit = ui
                .add(
                    egui::TextEdit::singleline(&mut self.open_text)
                        .hint_text("file.glb or builtin:NAME")
                        .desired_width(170.0),
                )
                .on_hover_text(
                    "a .gltf/.glb path or a builtin: scene; you can also drop a file on the window",
                );
            let enter = edit.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter));
            if ui.button("Open").clicked() || enter {
                let spec = self.open_text.clone();
                self.open(ctx, &spec);
            }
            ui.menu_button("Built-in", |ui| {
                egui::ScrollArea::vertical()
                    .max_height(300.0)
                    .show(ui, |ui| {
                        for (name, what) in bvhtrace_scene::builtin_names() {
                            if ui.button(*name).on_hover_text(*what).clicked() {
                                let spec = format!("builtin:{name}");
                                self.open_text = spec.clone();
                                // Names with placeholders (icosphere:N) go to the text field
                                // to be filled in; the others open at once.
                                if !name.chars().any(|c| c.is_ascii_uppercase()) {
                                    self.open(ctx, &spec);
                                }
                                ui.close();
                            }
                        }
                    });
            });
        });
        let Some(scene) = &self.scene else {
            ui.label("no scene loaded");
            return;
        };
        ui.label(RichText::new(&scene.name).strong())
            .on_hover_text(&scene.spec);
        if !scene.description.is_empty() {
            ui.label(RichText::new(&scene.description).small());
        }
        if let Some(b) = &self.built {
            let st = &b.stats;
            egui::Grid::new("stats").num_columns(2).show(ui, |ui| {
                ui.label("triangles");
                if b.geometry.is_two_level() {
                    ui.label(format!(
                        "{} in meshes, {} placed",
                        fmt_count(st.triangles),
                        fmt_count(scene.triangles)
                    ));
                } else {
                    ui.label(fmt_count(st.triangles));
                }
                ui.end_row();
                ui.label("nodes");
                ui.label(format!(
                    "{} ({} leaves)",
                    fmt_count(st.nodes),
                    fmt_count(st.leaves)
                ));
                ui.end_row();
                ui.label("depth");
                ui.label(st.depth.to_string());
                ui.end_row();
                ui.label("SAH cost")
                    .on_hover_text("traversal 1, intersection 1 (tinybvh's convention)");
                ui.label(format!("{:.3}", st.sah_cost));
                ui.end_row();
                ui.label("SAH cost (PBRT)")
                    .on_hover_text("traversal 1/8, intersection 1");
                ui.label(format!("{:.3}", st.sah_cost_pbrt));
                ui.end_row();
                ui.label("times");
                ui.label(format!(
                    "load {:.0} ms, build {:.0} ms, upload {:.0} ms",
                    scene.load_ms, b.build_ms, b.upload_ms
                ));
                ui.end_row();
            });
        }
        if !scene.warnings.is_empty() {
            ui.label(
                RichText::new(format!("{} loader warnings", scene.warnings.len()))
                    .color(Color32::YELLOW),
            )
            .on_hover_text(scene.warnings.join("\n"));
        }
    }

    fn animation_section(&mut self, ui: &mut egui::Ui) {
        let Some(scene) = &self.scene else { return };
        let duration = scene.duration;
        let pb = &mut self.playback;
        ui.horizontal(|ui| {
            let label = if pb.playing { "Pause" } else { "Play" };
            if ui
                .button(label)
                .on_hover_text("play or pause the glTF node animation (Space)")
                .clicked()
            {
                pb.playing = !pb.playing;
            }
            let slider = egui::Slider::new(&mut pb.time, 0.0..=duration)
                .text("time")
                .suffix(" s")
                .fixed_decimals(2);
            if ui.add(slider).changed() {
                pb.time = scene.wrap_time(pb.time);
                ui.ctx().request_repaint();
            }
        });
        let Some(b) = &self.built else { return };
        match &b.geometry {
            bvhtrace_scene::SceneBvh::Instanced(ib) => {
                ui.label(format!(
                    "two levels: {} instances over {} meshes",
                    ib.instances().len(),
                    ib.meshes().len()
                ))
                .on_hover_text(
                    "each new time rebuilds the top level and updates it on the GPU in place",
                );
            }
            bvhtrace_scene::SceneBvh::Flat { .. } => {
                ui.label("one instance, flattened").on_hover_text(
                    "each new time rebuilds the whole BVH (written in place when its size is \
                     unchanged, else uploaded anew)",
                );
            }
        }
        if let Some(t) = &self.playback.last {
            let what = if t.top_level {
                "top-level rebuild"
            } else {
                "BVH rebuild"
            };
            let upload = if b.gpu.is_err() {
                "no GPU copy".to_string()
            } else if t.reuploaded {
                format!("new upload {:.2} ms", t.upload_ms)
            } else {
                format!("GPU update {:.2} ms", t.upload_ms)
            };
            ui.label(format!("{what} {:.2} ms · {upload}", t.rebuild_ms));
            ui.label(
                RichText::new(format!("{} new poses since opening", self.playback.poses)).small(),
            );
        }
    }

    fn tracing_section(&mut self, ui: &mut egui::Ui, ctx: &egui::Context) {
        let busy = self.job.is_some();
        let before = self.settings.builder;
        ui.add_enabled_ui(!busy && self.scene.is_some(), |ui| {
            egui::ComboBox::from_label("builder")
                .selected_text(self.settings.builder.name())
                .show_ui(ui, |ui| {
                    for b in BuilderKind::ALL {
                        ui.selectable_value(&mut self.settings.builder, b, b.name());
                    }
                });
        });
        if self.settings.builder != before
            && let Some(scene) = self.scene.clone()
        {
            self.start_job(ctx, Source::Reuse(scene));
        }
        egui::ComboBox::from_label("traversal")
            .selected_text(self.settings.traversal().name())
            .show_ui(ui, |ui| {
                for walk in Traversal::ALL {
                    let chosen = self.settings.traversal.same_kind(&walk);
                    if ui.selectable_label(chosen, walk.name()).clicked() {
                        self.settings.traversal = walk;
                    }
                }
            });
        // A walk the upload, made for another, does not answer (the wide layout, the
        // escape links) gets a new one; one made for this walk that does not answer it
        // (a tree too deep for its stack) leaves the walk to the CPU.
        let walk = self.settings.traversal();
        if !busy
            && self.built.as_ref().is_some_and(|b| {
                !b.walk.same_kind(&walk)
                    && b.gpu
                        .as_ref()
                        .is_ok_and(|g| !crate::jobs::answers(&**g, walk))
            })
            && let Some(scene) = self.scene.clone()
        {
            self.start_job(ctx, Source::Reuse(scene));
        }
        if matches!(self.settings.traversal, Traversal::ShortStack(_)) {
            ui.add(
                egui::Slider::new(&mut self.settings.short_stack, 1..=32)
                    .text("short-stack entries"),
            );
        }
        ui.horizontal(|ui| {
            ui.label("trace on");
            ui.radio_value(&mut self.settings.prefer_cpu, false, "GPU");
            ui.radio_value(&mut self.settings.prefer_cpu, true, "CPU twin");
        });
        ui.label(RichText::new(format!("device: {}", self.adapter_line)).small());
        if let Ok(ctx) = &self.gpu {
            for line in ctx.left_out() {
                ui.label(RichText::new(format!("left out: {line}")).small().weak());
            }
        }
        if let Some(b) = &self.built {
            if let Some(u) = b.gpu.as_ref().ok().and_then(|g| g.upload_stats()) {
                ui.label(
                    RichText::new(format!(
                        "BVH on the GPU as {:?}, {:.1} MiB",
                        u.storage,
                        u.total_bytes() as f64 / (1024.0 * 1024.0)
                    ))
                    .small(),
                );
            }
            if let Some(p) = b.gpu_problem() {
                ui.label(
                    RichText::new(format!("{p}: tracing on the CPU instead"))
                        .color(Color32::from_rgb(255, 170, 60)),
                );
                if b.gpu.is_ok() && ui.button("Retry the GPU").clicked() {
                    if let Some(b) = &mut self.built {
                        b.retry_gpu();
                    }
                    self.key = None;
                }
            }
        } else if let Err(e) = &self.gpu {
            ui.label(RichText::new(e).color(Color32::from_rgb(255, 170, 60)));
        }
        ui.separator();
        let can_compare = self.accum.is_some() && self.job.is_none();
        if ui
            .add_enabled(can_compare, egui::Button::new("Compare with CPU"))
            .on_hover_text(
                "trace the displayed image's primary rays with the CPU twin of the traversal \
                 and show where the hits differ",
            )
            .clicked()
        {
            self.compare_with_cpu(ctx);
        }
        if let Some(c) = &mut self.compare {
            let r = &c.result;
            let color = if r.prim_mismatches == 0 {
                Color32::from_rgb(120, 220, 120)
            } else {
                Color32::from_rgb(255, 90, 90)
            };
            ui.label(
                RichText::new(format!(
                    "{} of {} rays hit a different triangle; {} differ in t only",
                    fmt_count(r.prim_mismatches),
                    fmt_count(r.rays),
                    fmt_count(r.t_mismatches)
                ))
                .color(color),
            );
            if !c.open && ui.button("Show the difference image").clicked() {
                c.open = true;
            }
        }
    }

    fn shading_section(&mut self, ui: &mut egui::Ui) {
        egui::ComboBox::from_label("shading")
            .selected_text(self.settings.shade.label())
            .show_ui(ui, |ui| {
                for s in Shade::SURFACE {
                    ui.selectable_value(&mut self.settings.shade, s, s.label());
                }
                if self.gpu.is_ok() {
                    ui.selectable_value(&mut self.settings.shade, Shade::Path, Shade::Path.label());
                }
            });
        if self.settings.shade == Shade::Path {
            ui.add(
                egui::Slider::new(&mut self.settings.samples_per_frame, 1..=64)
                    .text("samples / frame"),
            );
            ui.add(
                egui::Slider::new(&mut self.settings.max_samples, 1..=65536)
                    .logarithmic(true)
                    .text("max samples"),
            );
            if let Some(p) = &self.path {
                let rate = p
                    .samples_per_second()
                    .map_or(String::new(), |r| format!(", {r:.1} / s"));
                ui.label(format!(
                    "{} samples{rate}, on the GPU, no readback",
                    p.samples()
                ));
            }
        }
        ui.checkbox(&mut self.settings.heatmap, "heatmap (box tests per pixel)");
        if self.settings.heatmap {
            let max = self.accum.as_ref().map_or(1, Accumulation::max_nodes);
            heatmap_legend(ui, max);
        }
        if self.settings.shade.accumulates() && !self.settings.heatmap {
            ui.horizontal(|ui| {
                ui.checkbox(&mut self.settings.auto_samples, "auto")
                    .on_hover_text(format!(
                        "as many samples per frame as fit in about {FRAME_BUDGET_MS} ms"
                    ));
                if self.settings.auto_samples {
                    ui.label(format!("{} samples / frame", self.last_k.max(1)));
                } else {
                    ui.add(
                        egui::Slider::new(&mut self.settings.samples_per_frame, 1..=64)
                            .text("samples / frame"),
                    );
                }
            });
            ui.add(
                egui::Slider::new(&mut self.settings.max_samples, 1..=4096)
                    .logarithmic(true)
                    .text("max samples"),
            );
            if let Some(a) = &self.accum {
                ui.add(
                    egui::ProgressBar::new(
                        a.samples as f32 / self.settings.max_samples.max(1) as f32,
                    )
                    .desired_width(260.0)
                    .text(format!(
                        "{} / {} samples",
                        a.samples, self.settings.max_samples
                    )),
                );
            }
        }
        ui.add(
            egui::Slider::new(&mut self.settings.render_scale, 0.1..=2.0)
                .text("render scale")
                .fixed_decimals(2),
        )
        .on_hover_text("traced pixels per window pixel");
    }

    fn camera_section(&mut self, ui: &mut egui::Ui) {
        let speed = self.scene.as_ref().map_or(0.01, |s| s.diagonal() * 0.002);
        vec3_editor(ui, "eye   ", &mut self.cam.eye, speed);
        vec3_editor(ui, "target", &mut self.cam.target, speed);
        ui.horizontal(|ui| {
            ui.label("fov");
            ui.add(
                egui::DragValue::new(&mut self.cam.fov_y_deg)
                    .range(1.0..=179.0)
                    .speed(0.2)
                    .suffix("°"),
            );
            if ui.button("Frame (F)").clicked() {
                self.frame_scene();
            }
            if ui.button("Scene camera").clicked()
                && let Some(s) = &self.scene
            {
                self.cam = s.initial_camera(self.last_aspect);
            }
        });
        let flags = camera::render_flags(&self.cam);
        ui.label("as `bvhtrace render` flags:");
        ui.add(egui::Label::new(RichText::new(&flags).monospace().size(11.0)).wrap());
        ui.horizontal(|ui| {
            if ui.button("Copy").clicked() {
                ui.ctx().copy_text(flags.clone());
            }
            let edit = ui.add(
                egui::TextEdit::singleline(&mut self.flags_text)
                    .hint_text("paste flags")
                    .desired_width(180.0),
            );
            let enter = edit.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter));
            if ui.button("Apply").clicked() || enter {
                match camera::parse_render_flags(&self.flags_text, self.cam.fov_y_deg) {
                    Ok(c) => {
                        self.cam = c;
                        self.flags_error = None;
                    }
                    Err(e) => self.flags_error = Some(e),
                }
            }
        });
        if let Some(e) = &self.flags_error {
            ui.label(RichText::new(e).color(Color32::from_rgb(255, 90, 90)));
        }
        ui.add(
            egui::Slider::new(&mut self.fly_speed, 1e-3..=1e4)
                .logarithmic(true)
                .text("fly speed / s"),
        );
        ui.label(
            RichText::new(
                "drag: orbit (left), pan (right/middle) · wheel: zoom\n\
                 W/A/S/D, Q/E: fly (Shift: faster) · F: frame the scene",
            )
            .small(),
        );
    }

    fn performance_section(&mut self, ui: &mut egui::Ui, ctx: &egui::Context) {
        let frame_ms = ctx.input(|i| i.unstable_dt) * 1e3;
        self.stats.frame_ms = if self.stats.frame_ms == 0.0 {
            frame_ms
        } else {
            self.stats.frame_ms * 0.9 + frame_ms * 0.1
        };
        let s = &self.stats;
        egui::Grid::new("perf").num_columns(2).show(ui, |ui| {
            ui.label("frame");
            ui.label(format!("{:.1} ms", s.frame_ms));
            ui.end_row();
            ui.label("image");
            let [w, h] = self.display.size();
            ui.label(format!("{w}x{h} px"));
            ui.end_row();
            ui.label("last trace");
            ui.label(format!(
                "{} rays in {:.1} ms on the {}",
                fmt_count(s.rays as usize),
                s.trace_ms,
                if s.on_gpu { "GPU" } else { "CPU" }
            ));
            ui.end_row();
            ui.label("Mrays/s");
            ui.label(format!("{:.2}", s.rays as f64 / s.trace_ms.max(1e-9) / 1e3));
            ui.end_row();
            if let Some(g) = s.gpu_ms
                && s.on_gpu
                && !self.cpu_adapter
            {
                ui.label("GPU timestamps")
                    .on_hover_text("the compute passes' own time, from timestamp queries");
                ui.label(format!(
                    "{g:.1} ms ({:.2} Mrays/s)",
                    s.rays as f64 / g.max(1e-9) / 1e3
                ));
                ui.end_row();
            }
        });
    }

    fn central(&mut self, ui: &mut egui::Ui) {
        let rect = ui.available_rect_before_wrap();
        self.image_rect = rect;
        let resp = ui.allocate_rect(rect, egui::Sense::click_and_drag());
        let ctx = ui.ctx().clone();
        let ppp = ctx.pixels_per_point();
        if rect.width() >= 1.0 && rect.height() >= 1.0 {
            self.last_aspect = rect.width() / rect.height();
        }
        if self.reset_camera
            && let Some(scene) = &self.scene
        {
            self.reset_camera = false;
            self.cam = self.pending_camera.take().unwrap_or_else(|| {
                let mut c = scene.initial_camera(self.last_aspect);
                if let Some(f) = self.fov_override.take() {
                    c.fov_y_deg = f;
                }
                c
            });
        }
        self.steer(&ctx, &resp, rect);
        let scale = self.settings.render_scale.clamp(0.1, 2.0);
        let px = |v: f32| ((v * ppp * scale).round() as u32).clamp(1, MAX_SIDE);
        let size = [px(rect.width()), px(rect.height())];
        self.pose();
        let path_mode = self.settings.shade == Shade::Path;
        if path_mode {
            self.path_frame(size);
        } else if self.step(&ctx, size) {
            self.display.set(
                &ctx,
                self.render_state.as_ref(),
                "bvhtrace image",
                [size[0], size[1]],
                &self.image,
            );
        }
        let painter = ui.painter_at(rect);
        let [r, g, b] = shade::BACKGROUND;
        painter.rect_filled(rect, 0.0, Color32::from_rgb(r, g, b));
        let shown = match (path_mode, &mut self.path, &self.render_state) {
            (true, Some(p), Some(rs)) => p.texture_id(rs).ok(),
            (true, _, _) => None,
            (false, _, _) => self.display.id(),
        };
        if let Some(id) = shown {
            let uv = egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0));
            painter.image(id, rect, uv, Color32::WHITE);
        }
        let galley = painter.layout_no_wrap(
            self.caption(),
            egui::FontId::proportional(13.0),
            Color32::from_gray(230),
        );
        let pos = rect.left_top() + egui::vec2(8.0, 6.0);
        painter.rect_filled(
            egui::Rect::from_min_size(
                pos - egui::vec2(4.0, 2.0),
                galley.size() + egui::vec2(8.0, 4.0),
            ),
            3.0,
            Color32::from_black_alpha(150),
        );
        painter.galley(pos, galley, Color32::WHITE);
        if ctx.input(|i| !i.raw.hovered_files.is_empty()) {
            painter.rect_filled(rect, 0.0, Color32::from_black_alpha(140));
            painter.text(
                rect.center(),
                egui::Align2::CENTER_CENTER,
                "drop a .gltf/.glb file to open it",
                egui::FontId::proportional(22.0),
                Color32::WHITE,
            );
        }
        let path_running = path_mode
            && (self.path.as_ref()).is_some_and(|p| p.samples() < self.settings.max_samples);
        if self.accumulating() || self.job.is_some() || path_running {
            ctx.request_repaint();
        }
    }

    /// A frame of the path mode: its tracer made for the scene's current pose when there
    /// is none for it, then samples added and shown, all on the device.
    fn path_frame(&mut self, size: [u32; 2]) {
        let (Some(data), Ok(gpu)) = (&self.scene, &self.gpu) else {
            if let Err(e) = &self.gpu {
                self.error = Some(format!("the path mode traces on the GPU: {e}"));
                self.settings.shade = Shade::Normal;
            }
            return;
        };
        let time = self.built.as_ref().map_or(0.0, |b| b.time);
        let made_for = (self.generation, time);
        let pending_for = self.path_pending.as_ref().map(|(m, _)| *m);
        if self.path.as_ref().map(PathMode::made_for) != Some(made_for)
            && pending_for != Some(made_for)
        {
            let mut scene = data.scene.clone();
            if data.animated() {
                scene.set_time(time);
            }
            let slot = PathSlot::default();
            let (gpu, traversal, into) = (gpu.clone(), self.settings.traversal(), slot.clone());
            let environment = self.environment.clone();
            let made = async move {
                let env = environment.as_deref().cloned();
                let mode = PathMode::new(&gpu, (&scene, env), traversal, made_for).await;
                *into.borrow_mut() = Some(mode);
            };
            crate::jobs::run_future(made);
            self.path_pending = Some((made_for, slot));
        }
        if let Some((_, slot)) = &self.path_pending {
            let made = slot.borrow_mut().take();
            match made {
                Some(Ok(p)) => {
                    self.path = Some(p);
                    self.path_pending = None;
                }
                Some(Err(e)) => {
                    self.path_pending = None;
                    self.error = Some(format!("path mode: {e}"));
                    self.settings.shade = Shade::Normal;
                    return;
                }
                // Still compiling: the frame shows what there was.
                None => return,
            }
        }
        let (k, max) = (
            self.settings.samples_per_frame.max(1),
            self.settings.max_samples,
        );
        let Some(path) = &mut self.path else { return };
        match path.advance(&self.cam, size, k, max) {
            Ok(_) => {
                self.first_image_ms
                    .get_or_insert_with(|| self.started.elapsed().as_secs_f64() * 1e3);
            }
            Err(e) => {
                self.error = Some(format!("path tracing failed: {e}"));
                self.settings.shade = Shade::Normal;
            }
        }
    }

    /// Moves the camera as the image's pointer input (`resp`, over `rect`) and the keys
    /// ask: drag to orbit (primary button) or pan (the others), scroll to zoom, WASD/QE to
    /// fly (shift: faster), F to frame the scene; space plays or pauses an animation.
    fn steer(&mut self, ctx: &egui::Context, resp: &egui::Response, rect: egui::Rect) {
        let Some(scene) = &self.scene else {
            return;
        };
        let diag = scene.diagonal();
        let d = resp.drag_delta();
        if d != egui::Vec2::ZERO {
            if resp.dragged_by(egui::PointerButton::Primary) {
                camera::orbit(&mut self.cam, -d.x * 0.008, d.y * 0.008);
            } else if resp.dragged_by(egui::PointerButton::Secondary)
                || resp.dragged_by(egui::PointerButton::Middle)
            {
                camera::pan(&mut self.cam, d.x, d.y, rect.height());
            }
        }
        if resp.hovered() {
            let scroll = ctx.input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                camera::zoom(&mut self.cam, scroll / 60.0, camera::MIN_DISTANCE * diag);
            }
        }
        if ctx.egui_wants_keyboard_input() {
            return;
        }
        let (f, r, u, fast, frame, dt, play) = ctx.input(|i| {
            use egui::Key;
            (
                axis(i, Key::W, Key::S),
                axis(i, Key::D, Key::A),
                axis(i, Key::E, Key::Q),
                i.modifiers.shift,
                i.key_pressed(Key::F),
                i.stable_dt.clamp(0.0, 0.1),
                i.key_pressed(Key::Space),
            )
        });
        if play && scene.animated() {
            self.playback.playing = !self.playback.playing;
            ctx.request_repaint();
        }
        if f != 0.0 || r != 0.0 || u != 0.0 {
            let step = self.fly_speed * dt * if fast { 4.0 } else { 1.0 };
            camera::fly(&mut self.cam, f * step, r * step, u * step);
            ctx.request_repaint();
        }
        if frame {
            self.frame_scene();
        }
    }

    /// The line over the image: the job under way, the scene, the walk, where it traces,
    /// the samples accumulated and the animation's time.
    fn caption(&self) -> String {
        if self.settings.shade == Shade::Path
            && let (Some(scene), Some(p)) = (&self.scene, &self.path)
        {
            let rate = p
                .samples_per_second()
                .map_or(String::new(), |r| format!(" ({r:.1} / s)"));
            return format!(
                "{}  ·  path traced on the GPU  ·  {} samples{rate}",
                scene.name,
                p.samples()
            );
        }
        let mut caption = match (&self.scene, &self.job) {
            (_, Some(job)) => format!("{}…", job.stage),
            (None, None) => "no scene".to_string(),
            (Some(_), None) => String::new(),
        };
        let (Some(scene), Some(key)) = (&self.scene, &self.key) else {
            return caption;
        };
        if !caption.is_empty() {
            caption.push_str("  ·  ");
        }
        let gpu_failed = self
            .built
            .as_ref()
            .is_some_and(|b| b.gpu_problem().is_some() && !self.settings.prefer_cpu);
        caption.push_str(&format!(
            "{}  ·  {}  ·  {}",
            scene.name,
            key.traversal,
            match (self.stats.on_gpu, gpu_failed) {
                (true, _) => "GPU",
                (false, true) => "CPU (the GPU is not available: see the panel)",
                (false, false) => "CPU",
            }
        ));
        if let (Some(a), Some(v)) = (&self.accum, &self.view)
            && v.accumulates()
        {
            caption.push_str(&format!("  ·  {} samples", a.samples));
        }
        if scene.animated() {
            caption.push_str(&format!(
                "  ·  t = {:.2} s{}",
                self.playback.time,
                if self.playback.playing {
                    ""
                } else {
                    " (paused)"
                }
            ));
        }
        caption
    }

    fn windows(&mut self, ctx: &egui::Context) {
        if let Some(err) = self.error.clone() {
            let mut open = true;
            egui::Window::new("Error")
                .collapsible(false)
                .resizable(false)
                .anchor(egui::Align2::CENTER_TOP, egui::vec2(0.0, 40.0))
                .open(&mut open)
                .show(ctx, |ui| {
                    ui.label(RichText::new(err).color(Color32::from_rgb(255, 120, 120)));
                    if self.scene.is_some() {
                        ui.label("The current scene stays loaded.");
                    }
                });
            if !open {
                self.error = None;
            }
        }
        if let Some(c) = &mut self.compare
            && c.open
        {
            let mut open = true;
            egui::Window::new("GPU vs CPU twin")
                .open(&mut open)
                .default_width(420.0)
                .pivot(egui::Align2::RIGHT_TOP)
                .default_pos(self.image_rect.right_top() + egui::vec2(-12.0, 30.0))
                .show(ctx, |ui| {
                    let r = &c.result;
                    ui.label(format!(
                        "{} traversal, {} rays, CPU trace {:.1} ms{}",
                        c.traversal,
                        fmt_count(r.rays),
                        c.cpu_ms,
                        if c.gpu_image {
                            ""
                        } else {
                            " (the image was traced on the CPU: both sides are the CPU)"
                        }
                    ));
                    ui.label(format!(
                        "different triangle: {} · same triangle, different t: {} (max relative {:.2e})",
                        fmt_count(r.prim_mismatches),
                        fmt_count(r.t_mismatches),
                        r.max_rel_t
                    ));
                    ui.label(
                        RichText::new("red: different triangle · yellow: different t · grey: equal")
                            .small(),
                    );
                    if let Some(id) = c.display.id() {
                        let [w, h] = c.display.size();
                        let width = ui.available_width().max(100.0);
                        let size = egui::vec2(width, width * h as f32 / w.max(1) as f32);
                        ui.image(egui::load::SizedTexture::new(id, size));
                    }
                });
            c.open = open;
        }
    }

    /// Opens a dropped file (natively by its path; in a browser its bytes are read on the
    /// event loop, then go through [`Shared::inbox`]) and whatever the inbox holds.
    fn handle_drops(&mut self, ctx: &egui::Context) {
        let dropped = ctx.input(|i| i.raw.dropped_files.first().cloned());
        if let Some(file) = dropped {
            #[cfg(not(target_arch = "wasm32"))]
            {
                let spec = file.path().to_string_lossy().into_owned();
                self.open_text = spec.clone();
                self.open(ctx, &spec);
            }
            #[cfg(target_arch = "wasm32")]
            {
                let (inbox, wake) = (self.shared.inbox.clone(), ctx.clone());
                wasm_bindgen_futures::spawn_local(async move {
                    let name = file.path().display().to_string();
                    let bytes = file.bytes_async().await;
                    if let Ok(mut q) = inbox.lock() {
                        q.push((name, bytes));
                    }
                    wake.request_repaint();
                });
            }
        }
        self.open_from_inbox(ctx);
    }

    /// Opens the oldest file in [`Shared::inbox`] (or shows why it could not be read);
    /// false when the inbox is empty.
    fn open_from_inbox(&mut self, ctx: &egui::Context) -> bool {
        let first = self.shared.inbox.lock().ok().and_then(|mut q| {
            let any = !q.is_empty();
            any.then(|| q.remove(0))
        });
        match first {
            Some((name, Ok(bytes))) => {
                self.open_text = name.clone();
                self.start_job(ctx, Source::Bytes { name, bytes });
            }
            Some((name, Err(e))) => self.error = Some(format!("{name}: {e}")),
            None => return false,
        }
        true
    }
}

impl eframe::App for ViewerApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let ctx = ui.ctx().clone();
        self.poll_job();
        self.handle_drops(&ctx);
        self.advance_time(&ctx);
        egui::Panel::left("controls")
            .resizable(true)
            .default_size(330.0)
            .size_range(220.0..=700.0)
            .show(ui, |ui| {
                egui::ScrollArea::vertical()
                    .auto_shrink([false, false])
                    .show(ui, |ui| self.side_panel(ui));
            });
        egui::CentralPanel::no_frame().show(ui, |ui| self.central(ui));
        if self.compare_pending && self.accum.is_some() && self.job.is_none() {
            self.compare_pending = false;
            self.compare_with_cpu(&ctx);
        }
        self.windows(&ctx);
        self.screenshot_step(&ctx);
    }

    fn clear_color(&self, _visuals: &egui::Visuals) -> [f32; 4] {
        let [r, g, b] = shade::BACKGROUND;
        Color32::from_rgb(r, g, b).to_normalized_gamma_f32()
    }
}
