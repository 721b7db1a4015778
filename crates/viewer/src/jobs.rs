//! Loading a scene, building its BVH and uploading it, on a worker thread (in a browser, on
//! the page's thread between two frames): the window keeps drawing (with a progress line)
//! while it runs, and a failure leaves the current scene as it is. The finished
//! [`BuiltBvh`] holds the two tracers the viewer picks between, traces batches that may
//! finish on a later frame ([`BuiltBvh::start_trace`]), and moves an animated scene to
//! another time ([`BuiltBvh::pose`]).

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, Sender, TryRecvError};

use web_time::Instant;

use bvhtrace::{CpuTracer, Device, OpenOptions, TraceError, Tracer};
use bvhtrace_core::instance::REFIT_REBUILD_ADVISED;
use bvhtrace_core::{
    BuildOptions, BvhStats, FlatBvh, InstancedBvh, Query, Ray, TraceOptions, TraceOutput, Traversal,
};
use bvhtrace_scene::{Camera, Scene, SceneBvh};
use glam::{Affine3A, Vec3};

/// A loaded scene's triangles and what the UI shows about it.
#[derive(Debug)]
pub struct SceneData {
    /// The spec it was loaded from (a path or a `builtin:` name).
    pub spec: String,
    /// Its short name.
    pub name: String,
    /// What it is, in words.
    pub description: String,
    /// The scene as loaded (its instances posed at the time it was loaded at): what a
    /// rebuild starts from and what [`BuiltBvh::pose`] takes an animation's poses from.
    pub scene: Scene,
    /// Its animation's length, seconds (0 without animation).
    pub duration: f32,
    /// Triangles over all instances.
    pub triangles: usize,
    /// World-space bounds `(min, max)`.
    pub bounds: (Vec3, Vec3),
    /// The file's own camera, if it has one.
    pub camera: Option<Camera>,
    /// Non-fatal problems met while loading.
    pub warnings: Vec<String>,
    /// Load and flatten time, milliseconds.
    pub load_ms: f64,
}

impl SceneData {
    /// What the UI shows about `scene`, loaded from `spec` since `started`.
    fn new(spec: String, scene: Scene, started: Instant) -> SceneData {
        let mut warnings = scene.warnings.clone();
        if let Some(c) = scene.curves.as_ref().filter(|c| !c.is_empty()) {
            warnings.push(format!(
                "its {} {} curve segments are not shown: the viewer traces triangles (`bvhtrace render` traces curves)",
                c.len(),
                c.kind.name()
            ));
        }
        SceneData {
            name: scene.name.clone(),
            description: scene.description.clone(),
            bounds: scene.bounds(),
            camera: scene.camera,
            warnings,
            duration: scene.duration(),
            triangles: scene.triangle_count(),
            scene,
            load_ms: started.elapsed().as_secs_f64() * 1e3,
            spec,
        }
    }

    /// The length of the bounds' diagonal (at least a tiny positive number).
    pub fn diagonal(&self) -> f32 {
        let d = (self.bounds.1 - self.bounds.0).length();
        if d.is_finite() && d > 0.0 { d } else { 1e-6 }
    }

    /// True when the scene has an animation to play.
    pub fn animated(&self) -> bool {
        self.duration > 0.0
    }

    /// True when the scene is traced in two levels: it has more than one instance, as in
    /// `bvhtrace render` (a scene of one instance is flattened, and rebuilt at each new
    /// time when animated).
    pub fn two_level(&self) -> bool {
        self.scene.traces_in_two_levels(false)
    }

    /// `t` wrapped into the animation, `[0, duration)` (0 without animation; 0 for a time
    /// that is not finite).
    pub fn wrap_time(&self, t: f32) -> f32 {
        if self.animated() && t.is_finite() {
            let w = t.rem_euclid(self.duration);
            if w < self.duration { w } else { 0.0 }
        } else {
            0.0
        }
    }

    /// The scene's camera, or one that frames its bounds for this aspect ratio.
    pub fn initial_camera(&self, aspect: f32) -> Camera {
        self.camera
            .unwrap_or_else(|| Camera::frame(self.bounds.0, self.bounds.1, aspect))
    }
}

/// What moving an animated scene to a new time cost ([`BuiltBvh::pose`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PoseTimes {
    /// True when only the top level was rebuilt (two levels); false when the whole
    /// flattened BVH was, or deformed (skinned or morphed) meshes were refitted too.
    pub top_level: bool,
    /// Computing the poses and rebuilding the BVH (the top level, or all of a flattened
    /// one), milliseconds.
    pub rebuild_ms: f64,
    /// Writing it to the device (in place when the sizes allow, else a new upload),
    /// milliseconds; 0 without an upload.
    pub upload_ms: f64,
    /// True when the device copy was replaced by a new upload rather than updated in place.
    pub reuploaded: bool,
}

/// Whether `scene` has meshes its animation deforms (skins or morph targets).
fn deforms(scene: &Scene) -> bool {
    (scene.animation.as_ref()).is_some_and(|a| !a.skins().is_empty() || !a.morphs().is_empty())
}

/// Refits each deformed mesh (skins and morph targets) of `ib` to `scene`'s pose at `t`,
/// rebuilding it instead past [`REFIT_REBUILD_ADVISED`] (the refit's rule; a rebuild
/// changes the layout's shape): `None` without deformed meshes, else whether a mesh was
/// rebuilt.
fn pose_deformed(
    ib: &mut InstancedBvh,
    scene: &Scene,
    t: f32,
    opts: &BuildOptions,
) -> Result<Option<bool>, String> {
    let Some(a) = scene.animation.as_ref().filter(|_| deforms(scene)) else {
        return Ok(None);
    };
    let mut rebuilt = false;
    for d in a.deformed_at(Some(t)) {
        let (s, positions) = (d.instance, d.positions);
        let Some(m) = ib.instances().iter().find(|i| i.user_id as usize == s) else {
            continue;
        };
        let m = m.mesh as usize;
        let bad = |e: String| format!("the deformed mesh of instance {s} at t = {t} s: {e}");
        let mesh = (scene.instances.get(s))
            .and_then(|i| scene.meshes.get(i.mesh))
            .ok_or_else(|| bad("its mesh is gone".into()))?;
        let tris = (mesh.indices.iter())
            .map(|t| t.map(|i| positions.get(i as usize).copied()))
            .map(|[a, b, c]| Some([a?, b?, c?]))
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| bad("an index past the deformed vertices".into()))?;
        ib.refit_mesh(m, &tris).map_err(|e| bad(e.to_string()))?;
        if ib.refit_quality(m) > REFIT_REBUILD_ADVISED {
            *ib = ib
                .rebuild_mesh(m, &tris, opts)
                .map_err(|e| bad(e.to_string()))?;
            rebuilt = true;
        }
    }
    Ok(Some(rebuilt))
}

/// A built (and, when a device is there, uploaded) BVH, with the two tracers over it.
pub struct BuiltBvh {
    /// Its quality figures.
    pub stats: BvhStats,
    /// The options it was built with.
    pub options: BuildOptions,
    /// Build time, milliseconds.
    pub build_ms: f64,
    /// The traced form: its BVH (what [`BuiltBvh::cpu`] walks, the reference of "Compare
    /// with CPU") and the hits' triangles.
    pub geometry: SceneBvh,
    /// The animation time the geometry is posed at, seconds (0 without animation).
    pub time: f32,
    /// The upload (opened through the front door on eframe's device), or why there is
    /// none. A new pose is written into it in place ([`Tracer::update`]).
    pub gpu: Result<Arc<dyn Tracer>, String>,
    /// The device it is on, for a new upload when a new pose changes the tree's shape.
    pub device: Option<Device>,
    /// The walk the upload was opened for ([`upload`]).
    pub walk: Traversal,
    /// Why a GPU trace (or pipeline compile) failed: set, the CPU traces everything until
    /// [`BuiltBvh::retry_gpu`].
    pub gpu_failure: Option<String>,
    /// Upload time (buffers and pipelines), milliseconds.
    pub upload_ms: f64,
}

/// The batches the viewer traces with `traversal`: primary rays, primary rays with
/// counters (the heatmap), shadow and occlusion rays.
pub fn batch_options(traversal: Traversal) -> [TraceOptions; 3] {
    [
        TraceOptions::closest(traversal),
        TraceOptions::closest(traversal).with_counters(true),
        TraceOptions::new(traversal, Query::Any),
    ]
}

impl BuiltBvh {
    /// Why the GPU is not used: the missing upload, else the failed trace.
    pub fn gpu_problem(&self) -> Option<&str> {
        match &self.gpu {
            Err(e) => Some(e),
            Ok(_) => self.gpu_failure.as_deref(),
        }
    }

    /// The GPU's tracer, when it is uploaded, has not failed, and `prefer_cpu` is off.
    pub fn gpu_tracer(&self, prefer_cpu: bool) -> Option<&dyn Tracer> {
        match &self.gpu {
            Ok(g) if !prefer_cpu && self.gpu_failure.is_none() => Some(&**g),
            _ => None,
        }
    }

    /// The CPU walks over the tree: the fallback, and the reference of "Compare with CPU".
    pub fn cpu(&self) -> CpuTracer<&FlatBvh> {
        CpuTracer::new(self.geometry.bvh())
    }

    /// Moves the geometry to `scene`'s pose at time `t` (seconds, as given: wrap it
    /// first). Two levels: the instances get their new transforms, the top level is
    /// rebuilt ([`bvhtrace_core::InstancedBvh::set_transforms`]) and written into the
    /// upload in place ([`Tracer::update`] finds that only the top level moved). Flattened: the triangles
    /// at `t` get a new BVH, written in place when it has the uploaded shape, else
    /// uploaded anew.
    /// A failure leaves the BVH as it was (an upload that fails is kept as
    /// [`BuiltBvh::gpu_failure`]: the CPU traces the new pose).
    pub fn pose(&mut self, scene: &Scene, t: f32) -> Result<PoseTimes, String> {
        // Checked first, so that a refusal leaves the geometry as it was.
        if self.busy() {
            return Err(busy());
        }
        let t0 = Instant::now();
        let mut times = PoseTimes::default();
        match &mut self.geometry {
            SceneBvh::Instanced(ib) => {
                let all = scene.instance_transforms_at(t);
                let transforms: Vec<Affine3A> = ib
                    .instances()
                    .iter()
                    .map(|i| {
                        let m = all.get(i.user_id as usize).copied();
                        m.map_or(i.transform, Affine3A::from_mat4)
                    })
                    .collect();
                // With deformed meshes, posed on a copy: a refused mesh leaves the geometry
                // as it was (`set_transforms` alone refuses before it changes anything).
                let mut copy = deforms(scene).then(|| ib.clone());
                let posed = copy.as_mut().unwrap_or(ib);
                posed
                    .set_transforms(&transforms)
                    .map_err(|e| format!("the pose at t = {t} s: {e}"))?;
                let deformed = pose_deformed(posed, scene, t, &self.options)?;
                if let Some(c) = copy {
                    *ib = c;
                }
                times.top_level = deformed.is_none();
                times.rebuild_ms = t0.elapsed().as_secs_f64() * 1e3;
                let t1 = Instant::now();
                if let Ok(shared) = &mut self.gpu {
                    let g = Arc::get_mut(shared).ok_or_else(busy)?;
                    let written = match g.update(ib.bvh()) {
                        // A deformed mesh rebuilt: another shape, a new upload.
                        Err(TraceError::BadBuffer { .. }) if deformed == Some(true) => {
                            times.reuploaded = true;
                            upload(self.device.as_ref(), ib.bvh(), self.walk)
                                .map(|fresh| *shared = fresh)
                        }
                        other => other,
                    };
                    if let Err(e) = written {
                        self.gpu_failure = Some(format!("updating the upload failed: {e}"));
                    }
                }
                times.upload_ms = t1.elapsed().as_secs_f64() * 1e3;
            }
            SceneBvh::Flat { tris, bvh } => {
                let mut posed = scene.clone();
                posed.set_time(t);
                let new_tris = posed
                    .flattened_triangles()
                    .map_err(|e| format!("the pose at t = {t} s: {e}"))?;
                let mut new_bvh = FlatBvh::build(&new_tris, &self.options)
                    .map_err(|e| format!("the BVH at t = {t} s: {e}"))?;
                // The pose moves corners, not primitive ids: the masks still fit.
                new_bvh.set_masks(bvh.masks().cloned())?;
                if bvh.wide().is_some() {
                    new_bvh.build_wide();
                }
                times.rebuild_ms = t0.elapsed().as_secs_f64() * 1e3;
                let t1 = Instant::now();
                if let Ok(shared) = &mut self.gpu {
                    let g = Arc::get_mut(shared).ok_or_else(busy)?;
                    // A walk's depth limit is the upload's: when the updated upload no longer
                    // answers the walk, the tree is uploaded anew.
                    let walks = g.traversals();
                    let written = match g.update(&new_bvh) {
                        Ok(()) if g.traversals() == walks => Ok(()),
                        // Another shape (node or triangle count), or other walks.
                        Ok(()) | Err(TraceError::BadBuffer { .. }) => {
                            times.reuploaded = true;
                            upload(self.device.as_ref(), &new_bvh, self.walk)
                                .map(|fresh| *shared = fresh)
                        }
                        Err(e) => Err(e),
                    };
                    if let Err(e) = written {
                        self.gpu_failure = Some(format!("uploading the new BVH failed: {e}"));
                    }
                }
                times.upload_ms = t1.elapsed().as_secs_f64() * 1e3;
                *tris = new_tris;
                *bvh = new_bvh;
            }
        }
        self.stats = BvhStats::of(self.geometry.bvh());
        self.time = t;
        Ok(times)
    }

    /// Forgets a failed trace so that the next batch tries the GPU again (after the user
    /// changed the traversal, for instance). A missing upload stays missing.
    pub fn retry_gpu(&mut self) {
        self.gpu_failure = None;
    }

    /// Compiles the GPU pipelines of [`batch_options`] ahead of the first frame. A failure
    /// (a traversal the upload cannot run, say) is kept as [`BuiltBvh::gpu_failure`].
    pub fn prepare(&mut self, traversal: Traversal) {
        let Ok(g) = &self.gpu else { return };
        if let Some(e) = batch_options(traversal)
            .iter()
            .find_map(|o| g.prepare(o).err())
        {
            self.gpu_failure = Some(e.to_string());
        }
    }

    /// Traces one batch on the GPU when [`BuiltBvh::gpu_tracer`] gives one, falling back
    /// to the CPU (and remembering why) when it fails. The flag is true when the GPU traced.
    /// Not in a browser, whose GPU answers on a later frame: see
    /// [`BuiltBvh::start_trace`].
    pub fn trace(
        &mut self,
        rays: &[Ray],
        opts: &TraceOptions,
        prefer_cpu: bool,
    ) -> Result<(TraceOutput, bool), TraceError> {
        let batch = self.start_trace(rays.to_vec(), *opts, prefer_cpu, || {});
        match self.finish(&batch) {
            Some(r) => r.map(|t| (t.out, t.on_gpu)),
            None => Err(TraceError::Device {
                during: "tracing",
                message: "the batch is still on the GPU: use start_trace".into(),
            }),
        }
    }

    /// Starts tracing one batch: on the GPU when [`BuiltBvh::gpu_tracer`] gives one, else
    /// on the CPU. Natively the batch is done when this returns; in a browser the GPU's
    /// answer arrives on the event loop, which calls `wake` (to ask for a frame). Take the
    /// result with [`BuiltBvh::finish`].
    pub fn start_trace(
        &mut self,
        rays: Vec<Ray>,
        opts: TraceOptions,
        prefer_cpu: bool,
        wake: impl Fn() + 'static,
    ) -> Batch {
        let done = Rc::new(RefCell::new(None));
        let on_gpu = match &self.gpu {
            Ok(g) if !prefer_cpu && self.gpu_failure.is_none() => {
                let (g, slot) = (g.clone(), done.clone());
                let traced = async move {
                    let result = g.trace_async(&rays, &opts).await;
                    *slot.borrow_mut() = Some((rays, result));
                    wake();
                };
                run_future(traced);
                true
            }
            _ => {
                let result = self.cpu().trace(&rays, &opts);
                *done.borrow_mut() = Some((rays, result));
                false
            }
        };
        Batch { opts, on_gpu, done }
    }

    /// The rays, hits and whether the GPU traced them, once `batch` is done (`None` while
    /// it is on the GPU). A failed GPU trace is traced again on the CPU, and the failure
    /// kept in [`BuiltBvh::gpu_failure`].
    pub fn finish(&mut self, batch: &Batch) -> Option<Result<Traced, TraceError>> {
        let (rays, result) = batch.done.borrow_mut().take()?;
        Some(match result {
            Ok(out) => Ok(Traced {
                rays,
                out,
                on_gpu: batch.on_gpu,
            }),
            Err(e) if batch.on_gpu => {
                self.gpu_failure = Some(format!("GPU trace failed: {e}"));
                let out = self.cpu().trace(&rays, &batch.opts);
                out.map(|out| Traced {
                    rays,
                    out,
                    on_gpu: false,
                })
            }
            Err(e) => Err(e),
        })
    }

    /// True while a batch started on the GPU holds the upload (in a browser, until its
    /// answer arrives): a new pose waits for it.
    pub fn busy(&self) -> bool {
        self.gpu.as_ref().is_ok_and(|g| Arc::strong_count(g) > 1)
    }
}

/// A finished batch ([`BuiltBvh::finish`]).
pub struct Traced {
    /// Its rays.
    pub rays: Vec<Ray>,
    /// Their hits and times.
    pub out: TraceOutput,
    /// True when the GPU traced them.
    pub on_gpu: bool,
}

/// A batch of rays being traced ([`BuiltBvh::start_trace`]).
pub struct Batch {
    opts: TraceOptions,
    on_gpu: bool,
    done: Rc<RefCell<BatchResult>>,
}

type BatchResult = Option<(Vec<Ray>, Result<TraceOutput, TraceError>)>;

fn busy() -> String {
    "a trace is still running on the upload".to_string()
}

/// Where a job's scene comes from.
pub enum Source {
    /// Load this spec (a file path or a `builtin:` name).
    Load(String),
    /// Rebuild the BVH of an already loaded scene.
    Reuse(Arc<SceneData>),
    /// Load glTF from bytes (a file opened or dropped in a browser), named `name`.
    Bytes {
        /// The file's name, for errors and the title.
        name: String,
        /// Its contents.
        bytes: Vec<u8>,
    },
}

/// What a job does.
pub struct JobRequest {
    /// The scene.
    pub source: Source,
    /// How to build the BVH.
    pub build: BuildOptions,
    /// The traversal whose pipelines to compile ahead of the first frame.
    pub traversal: Traversal,
    /// The animation time to build the scene at, seconds (wrapped into the animation;
    /// ignored without one).
    pub time: f32,
    /// The shared device, or why there is none.
    pub gpu: Result<Device, String>,
}

/// A finished job.
pub struct JobOutput {
    /// The scene (new, or the one given back).
    pub scene: Arc<SceneData>,
    /// True when the scene was loaded by this job (the camera is then reset).
    pub new_scene: bool,
    /// Its BVH.
    pub built: BuiltBvh,
}

enum Msg {
    Stage(String),
    Done(Box<Result<JobOutput, String>>),
}

/// A job running on a worker thread (in a browser, waiting for its turn on the page).
pub struct Job {
    rx: Receiver<Msg>,
    /// In a browser: the request, its sender, and whether a frame has shown the job.
    #[cfg(target_arch = "wasm32")]
    deferred: Option<(JobRequest, Sender<Msg>, bool)>,
    /// When it started.
    pub started: Instant,
    /// What it is doing now, for the progress line.
    pub stage: String,
    /// What it was asked to do, in words.
    pub what: String,
}

/// Opens `bvh` on `device` through the front door for `walk` and the stackless walk (so
/// that every binary walk the tree allows is answered by one upload; the wide walk adds
/// its layout).
fn upload(
    device: Option<&Device>,
    bvh: &FlatBvh,
    walk: Traversal,
) -> Result<Arc<dyn Tracer>, TraceError> {
    let device = device.ok_or_else(|| TraceError::NoAdapter {
        details: ": the viewer has no wgpu device".into(),
    })?;
    let opts = OpenOptions::default()
        .with_traversal(walk)
        .with_traversal(Traversal::Stackless);
    let opened = match device.open_owned(bvh, &opts) {
        // A tree deeper than the walk's stack: the others, the walk left to the CPU.
        Err(TraceError::TooDeep { .. }) => {
            let stackless = OpenOptions::default().with_traversal(Traversal::Stackless);
            device.open_owned(bvh, &stackless)
        }
        other => other,
    };
    Ok(Arc::from(opened?.tracer))
}

/// True when `tracer` answers `walk` (a short stack of any size for a short stack).
pub fn answers(tracer: &dyn Tracer, walk: Traversal) -> bool {
    tracer.traversals().iter().any(|w| w.same_kind(&walk))
}

fn run(req: JobRequest, tx: &Sender<Msg>) -> Result<JobOutput, String> {
    let stage = |s: String| {
        let _ = tx.send(Msg::Stage(s));
    };
    let (scene, new_scene) = match req.source {
        Source::Reuse(s) => (s, false),
        Source::Load(spec) => {
            stage(format!("loading {spec}"));
            let t0 = Instant::now();
            let scene = bvhtrace_scene::load(&spec).map_err(|e| e.to_string())?;
            (Arc::new(SceneData::new(spec, scene, t0)), true)
        }
        Source::Bytes { name, bytes } => {
            stage(format!("loading {name}"));
            let t0 = Instant::now();
            let scene =
                bvhtrace_scene::load_gltf_slice(&bytes, &name, None).map_err(|e| e.to_string())?;
            (Arc::new(SceneData::new(name, scene, t0)), true)
        }
    };
    let time = scene.wrap_time(req.time);
    let t1 = Instant::now();
    stage(if scene.two_level() {
        format!(
            "building two levels ({}, {} instances, {} triangles)",
            req.build.builder,
            scene.scene.instances.len(),
            scene.triangles
        )
    } else {
        format!(
            "flattening and building the BVH ({}, {} triangles)",
            req.build.builder, scene.triangles
        )
    });
    // The scene at this time: two levels are posed always, as the CLI's `--time` does.
    let posed = (scene.animated() || scene.two_level()).then(|| {
        let mut p = scene.scene.clone();
        p.set_time(time);
        p
    });
    let geometry = posed
        .as_ref()
        .unwrap_or(&scene.scene)
        .tracing_bvh(&req.build, false)
        .map_err(|e| format!("{}: {e}", scene.spec))?;
    // The CPU twin's wide walk reads the tree's own wide layout (the upload collapses one
    // itself): built only for the wide walk.
    let mut geometry = geometry;
    if req.traversal.is_wide() {
        geometry.build_wide();
    }
    let build_ms = t1.elapsed().as_secs_f64() * 1e3;
    let bvh = geometry.bvh();
    let stats = BvhStats::of(bvh);
    let t2 = Instant::now();
    let gpu = match &req.gpu {
        Err(e) => Err(e.clone()),
        Ok(device) => {
            stage(format!("uploading {} nodes to the GPU", bvh.nodes().len()));
            upload(Some(device), bvh, req.traversal)
                .and_then(|g| {
                    stage("compiling the traversal kernels".into());
                    // Primary and shadow rays; a traversal this upload cannot run is
                    // reported at trace time.
                    let [closest, _, any] = batch_options(req.traversal);
                    for o in [closest, any] {
                        if g.supports(&o).is_ok() {
                            g.prepare(&o)?;
                        }
                    }
                    Ok(g)
                })
                .map_err(|e| format!("GPU upload failed: {e}"))
        }
    };
    let upload_ms = t2.elapsed().as_secs_f64() * 1e3;
    Ok(JobOutput {
        scene,
        new_scene,
        built: BuiltBvh {
            stats,
            options: req.build,
            build_ms,
            geometry,
            time,
            gpu,
            device: req.gpu.ok(),
            walk: req.traversal,
            gpu_failure: None,
            upload_ms,
        },
    })
}

/// Runs `work` to its end: natively at once, in a browser on the page's event loop (whose
/// GPU answers arrive there), after this returns.
pub fn run_future(work: impl std::future::Future<Output = ()> + 'static) {
    #[cfg(target_arch = "wasm32")]
    wasm_bindgen_futures::spawn_local(work);
    #[cfg(not(target_arch = "wasm32"))]
    pollster::block_on(work);
}

impl Job {
    /// Starts `req` on a new thread; `wake` is called whenever there is news (to repaint).
    /// In a browser, which has no threads here, the job runs on the page's thread at the
    /// second [`Job::poll`], after a frame has shown that it started.
    pub fn spawn(req: JobRequest, what: String, wake: impl Fn() + Send + 'static) -> Job {
        let (tx, rx) = mpsc::channel();
        #[cfg(target_arch = "wasm32")]
        let deferred = {
            wake();
            Some((req, tx, false))
        };
        #[cfg(not(target_arch = "wasm32"))]
        {
            let fallback = tx.clone();
            let started = std::thread::Builder::new()
                .name("bvhtrace-viewer job".into())
                .spawn(move || {
                    let out = run(req, &tx);
                    let _ = tx.send(Msg::Done(Box::new(out)));
                    wake();
                });
            if let Err(e) = started {
                let _ = fallback.send(Msg::Done(Box::new(Err(format!(
                    "could not start a worker thread: {e}"
                )))));
            }
        }
        Job {
            rx,
            #[cfg(target_arch = "wasm32")]
            deferred,
            started: Instant::now(),
            stage: "starting".into(),
            what,
        }
    }

    /// Takes the news: `Some(result)` once the job is over.
    pub fn poll(&mut self) -> Option<Result<JobOutput, String>> {
        #[cfg(target_arch = "wasm32")]
        if let Some((req, tx, shown)) = self.deferred.take() {
            if !shown {
                self.deferred = Some((req, tx, true));
                return None;
            }
            let out = run(req, &tx);
            let _ = tx.send(Msg::Done(Box::new(out)));
        }
        loop {
            match self.rx.try_recv() {
                Ok(Msg::Stage(s)) => self.stage = s,
                Ok(Msg::Done(out)) => return Some(*out),
                Err(TryRecvError::Empty) => return None,
                Err(TryRecvError::Disconnected) => {
                    return Some(Err(format!(
                        "{}: the worker stopped unexpectedly (while {})",
                        self.what, self.stage
                    )));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_a_gpu_the_cpu_traces_and_says_why() {
        let tris = vec![[
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ]];
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
        let mut b = BuiltBvh {
            stats: BvhStats::of(&bvh),
            options: BuildOptions::default(),
            build_ms: 0.0,
            geometry: SceneBvh::Flat { tris, bvh },
            time: 0.0,
            gpu: Err("no Vulkan adapter".into()),
            device: None,
            walk: Traversal::Stackless,
            gpu_failure: None,
            upload_ms: 0.0,
        };
        assert!(b.gpu_tracer(false).is_none());
        let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
        let [_, counted, _] = batch_options(Traversal::Stackless);
        let (out, on_gpu) = b.trace(&rays, &counted, false).expect("the CPU traces");
        assert!(!on_gpu);
        assert_eq!(out.hits[0].prim, 0);
        assert_eq!(out.counters.map(|c| c.len()), Some(1));
        // Retrying cannot conjure an upload: the reason stays.
        b.retry_gpu();
        assert_eq!(b.gpu_problem(), Some("no Vulkan adapter"));
    }
}

#[cfg(test)]
mod animation_tests {
    use super::*;
    use bvhtrace_core::Triangle;

    fn animated_spec() -> String {
        format!("{}/../../scenes/animated.gltf", env!("CARGO_MANIFEST_DIR"))
    }

    fn built(spec: &str, time: f32) -> JobOutput {
        let (tx, _rx) = mpsc::channel();
        let req = JobRequest {
            source: Source::Load(spec.to_string()),
            build: BuildOptions::default(),
            traversal: Traversal::Stackless,
            time,
            gpu: Err("no device in this test".into()),
        };
        run(req, &tx).expect("loads and builds")
    }

    /// The primary hits of the scene's camera on `b`, as (prim, world triangle) pairs.
    fn hits(scene: &SceneData, b: &mut BuiltBvh) -> Vec<(u32, Option<Triangle>)> {
        let cam = scene.initial_camera(1.5);
        let rays = cam.rays(48, 32);
        let (out, on_gpu) = b
            .trace(&rays, &TraceOptions::closest(Traversal::Stackless), false)
            .expect("traces");
        assert!(!on_gpu);
        out.hits
            .iter()
            .map(|h| {
                (
                    h.prim,
                    h.is_hit().then(|| b.geometry.triangle(h.prim)).flatten(),
                )
            })
            .collect()
    }

    /// A masked scene's tree carries its masks, so whatever traces it (the device's
    /// upload, the CPU twin) cuts the leaves: other hits than with the masks dropped.
    #[test]
    fn masked_materials_are_cut_in_the_viewer() {
        let spec = format!("{}/../../scenes/foliage.gltf", env!("CARGO_MANIFEST_DIR"));
        let JobOutput {
            scene, mut built, ..
        } = built(&spec, 0.0);
        assert!(built.geometry.bvh().masks().is_some(), "no masks attached");
        assert!(scene.warnings.iter().all(|w| !w.contains("opaque")));
        let cut = hits(&scene, &mut built);
        built.geometry.set_masks(None).expect("dropped");
        assert_ne!(hits(&scene, &mut built), cut, "the masks cut nothing");
    }

    #[test]
    fn a_pose_rebuilds_the_top_level_and_matches_a_fresh_build_at_that_time() {
        let JobOutput {
            scene, mut built, ..
        } = built(&animated_spec(), 0.0);
        assert!(scene.animated() && scene.two_level());
        assert!(built.geometry.is_two_level());
        let at0 = hits(&scene, &mut built);
        assert!(
            at0.iter().any(|(_, t)| t.is_some()),
            "the camera sees the scene"
        );

        let times = built.pose(&scene.scene, 1.0).expect("poses");
        assert!(times.top_level && !times.reuploaded);
        assert_eq!(built.time, 1.0);
        let at1 = hits(&scene, &mut built);
        assert_ne!(at0, at1, "the animation moved nothing the camera sees");

        // The same hits as the scene built from scratch at t = 1, in two levels and
        // flattened (the prims number the same triangles in both forms).
        let JobOutput {
            built: mut fresh, ..
        } = built_at(1.0);
        assert_eq!(hits(&scene, &mut fresh), at1);
        let mut posed = scene.scene.clone();
        posed.set_time(1.0);
        let tris = posed.flattened_triangles().expect("flattens");
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
        let flat = bvhtrace_core::trace_rays(
            &bvh,
            &scene.initial_camera(1.5).rays(48, 32),
            &TraceOptions::closest(Traversal::Stackless),
        );
        // Rays are walked in object space in two levels: a ray grazing an edge may pick
        // the neighbour; anything more than a few such pixels is a wrong pose.
        let hit_count = flat.hits.iter().filter(|h| h.is_hit()).count();
        let differ = at1
            .iter()
            .zip(&flat.hits)
            .filter(|((p, _), h)| *p != h.prim)
            .count();
        assert!(hit_count > 50, "{hit_count} hits");
        assert!(
            differ * 50 <= hit_count,
            "{differ} of {hit_count} hits differ from the flattened scene at t = 1"
        );
        for ((p, t), h) in at1.iter().zip(&flat.hits) {
            if h.is_hit() && *p == h.prim {
                let want = tris[*p as usize];
                let got = t.expect("a hit has a triangle");
                for (a, b) in got.iter().zip(want) {
                    assert!((*a - b).length() < 1e-4, "{a} vs {b}");
                }
            }
        }

        // Back to 0: the first image again.
        built.pose(&scene.scene, 0.0).expect("poses");
        assert_eq!(hits(&scene, &mut built), at0);
    }

    /// Deformed meshes in two levels follow their joints and weights (`scenes/skinned.gltf`:
    /// a skin; `scenes/morph.gltf`: morph targets too): posed at t = 0.75 they are
    /// refitted (not only the top level) and trace as a fresh build at that time, and back
    /// at 0 as the first build.
    #[test]
    fn a_pose_refits_deformed_meshes() {
        for file in ["skinned", "morph"] {
            let spec = format!("{}/../../scenes/{file}.gltf", env!("CARGO_MANIFEST_DIR"));
            let JobOutput {
                scene, mut built, ..
            } = built(&spec, 0.0);
            assert!(built.geometry.is_two_level(), "{file}");
            let at0 = hits(&scene, &mut built);
            let times = built.pose(&scene.scene, 0.75).expect("poses");
            assert!(
                !times.top_level,
                "{file}: the deformed meshes were not refitted"
            );
            let at1 = hits(&scene, &mut built);
            assert_ne!(at0, at1, "{file}: the pose moved nothing the camera sees");
            let JobOutput {
                built: mut fresh, ..
            } = super::animation_tests::built(&spec, 0.75);
            assert_eq!(hits(&scene, &mut fresh), at1, "{file}");
            built.pose(&scene.scene, 0.0).expect("poses");
            assert_eq!(hits(&scene, &mut built), at0, "{file}");
        }
    }

    /// A pose written into the upload in place traces as a fresh build at that time, on
    /// the device.
    #[test]
    fn a_pose_on_the_device_matches_the_cpu_at_that_time() {
        for storage in [
            bvhtrace::BvhStorage::Buffers,
            bvhtrace::BvhStorage::Textures,
        ] {
            let options = bvhtrace_gpu::ContextOptions {
                tuning: Some(bvhtrace::DriverTuning {
                    storage,
                    ..bvhtrace::DriverTuning::cpu_driver(2)
                }),
                ..Default::default()
            };
            match bvhtrace::GpuContext::new_with(bvhtrace::AdapterChoice::Auto, &options) {
                Ok(ctx) => poses_on(ctx),
                Err(e) => return eprintln!("SKIP: no device ({e})"),
            }
        }
    }

    fn poses_on(ctx: bvhtrace::GpuContext) {
        let (tx, _rx) = mpsc::channel();
        let req = JobRequest {
            source: Source::Load(animated_spec()),
            build: BuildOptions::default(),
            traversal: Traversal::Stackless,
            time: 0.0,
            gpu: Ok(Device::wgpu(ctx)),
        };
        let JobOutput {
            scene, mut built, ..
        } = run(req, &tx).expect("loads, builds and uploads");
        for t in [0.5, 1.0, 1.5] {
            built.pose(&scene.scene, t).expect("poses");
            let rays = scene.initial_camera(1.5).rays(48, 32);
            let opts = TraceOptions::closest(Traversal::Stackless);
            let (gpu, on_gpu) = built.trace(&rays, &opts, false).expect("traces");
            assert!(on_gpu, "{:?}", built.gpu_problem());
            let JobOutput { built: fresh, .. } = built_at(t);
            let cpu = fresh.cpu().trace(&rays, &opts).expect("traces");
            assert_eq!(gpu.hits, cpu.hits, "t = {t}");
        }
    }

    fn built_at(t: f32) -> JobOutput {
        built(&animated_spec(), t)
    }

    #[test]
    fn times_wrap_into_the_animation() {
        let out = built_at(5.0);
        let s = &out.scene;
        assert!((s.duration - 2.0).abs() < 1e-6);
        assert!((out.built.time - 1.0).abs() < 1e-6, "5 s wraps to 1 s");
        assert_eq!(s.wrap_time(-0.5), 1.5);
        assert_eq!(s.wrap_time(f32::NAN), 0.0);
        assert!(s.wrap_time(2.0) < 2.0);
    }

    #[test]
    fn a_scene_without_animation_stays_flattened() {
        let out = built("builtin:cornell", 3.0);
        assert!(!out.scene.animated());
        assert!(!out.built.geometry.is_two_level());
        assert_eq!(out.built.time, 0.0);
    }
}
