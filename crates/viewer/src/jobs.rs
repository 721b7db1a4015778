//! Loading a scene, building its BVH and uploading it, on a worker thread: the window keeps
//! drawing (with a progress line) while it runs, and a failure leaves the current scene as
//! it is.

use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, Sender, TryRecvError};
use std::time::Instant;

use bvhtrace_core::{BuildOptions, BvhStats, FlatBvh, Traversal, Triangle};
use bvhtrace_gpu::{FULL_STACK_SIZE, GpuBvh, GpuContext, TraceOptions, UploadOptions};
use bvhtrace_scene::Camera;
use glam::Vec3;

/// A loaded scene's triangles and what the UI shows about it.
#[derive(Debug)]
pub struct SceneData {
    /// The spec it was loaded from (a path or a `builtin:` name).
    pub spec: String,
    /// Its short name.
    pub name: String,
    /// What it is, in words.
    pub description: String,
    /// World-space triangles, in the order the BVH's `prim` indices refer to.
    pub tris: Arc<Vec<Triangle>>,
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
    /// The length of the bounds' diagonal (at least a tiny positive number).
    pub fn diagonal(&self) -> f32 {
        let d = (self.bounds.1 - self.bounds.0).length();
        if d.is_finite() && d > 0.0 { d } else { 1e-6 }
    }

    /// The scene's camera, or one that frames its bounds for this aspect ratio.
    pub fn initial_camera(&self, aspect: f32) -> Camera {
        self.camera
            .unwrap_or_else(|| Camera::frame(self.bounds.0, self.bounds.1, aspect))
    }
}

/// A built (and, when a device is there, uploaded) BVH.
pub struct BuiltBvh {
    /// The tree.
    pub bvh: Arc<FlatBvh>,
    /// Its quality figures.
    pub stats: BvhStats,
    /// The options it was built with.
    pub options: BuildOptions,
    /// Build time, milliseconds.
    pub build_ms: f64,
    /// The upload, or why there is none.
    pub gpu: Result<Arc<GpuBvh>, String>,
    /// Upload time (buffers and pipelines), milliseconds.
    pub upload_ms: f64,
}

/// Where a job's scene comes from.
pub enum Source {
    /// Load this spec (a file path or a `builtin:` name).
    Load(String),
    /// Rebuild the BVH of an already loaded scene.
    Reuse(Arc<SceneData>),
}

/// What a job does.
pub struct JobRequest {
    /// The scene.
    pub source: Source,
    /// How to build the BVH.
    pub build: BuildOptions,
    /// The traversal whose pipelines to compile ahead of the first frame.
    pub traversal: Traversal,
    /// The shared device, if there is one.
    pub gpu: Option<GpuContext>,
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

/// A job running on a worker thread.
pub struct Job {
    rx: Receiver<Msg>,
    /// When it started.
    pub started: Instant,
    /// What it is doing now, for the progress line.
    pub stage: String,
    /// What it was asked to do, in words.
    pub what: String,
}

/// The traversals an upload of a tree this deep supports: the escape-link ones always,
/// the full stack when the tree fits its stack.
pub fn upload_options(depth: u32) -> UploadOptions {
    let mut traversals = vec![
        Traversal::Stackless,
        Traversal::ShortStack(bvhtrace_core::traverse::DEFAULT_SHORT_STACK),
    ];
    if depth <= FULL_STACK_SIZE {
        traversals.push(Traversal::FullStack);
    }
    UploadOptions {
        traversals,
        storage: None,
    }
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
            stage(format!("flattening {} triangles", scene.triangle_count()));
            let tris = scene
                .flatten()
                .triangles()
                .map_err(|e| format!("{spec}: bad geometry: {e}"))?;
            let data = SceneData {
                name: scene.name.clone(),
                description: scene.description.clone(),
                bounds: scene.bounds(),
                camera: scene.camera,
                warnings: scene.warnings.clone(),
                tris: Arc::new(tris),
                load_ms: t0.elapsed().as_secs_f64() * 1e3,
                spec,
            };
            (Arc::new(data), true)
        }
    };
    stage(format!(
        "building the BVH ({}, {} triangles)",
        req.build.builder,
        scene.tris.len()
    ));
    let t1 = Instant::now();
    let bvh = FlatBvh::build(&scene.tris, &req.build)
        .map_err(|e| format!("{}: BVH build failed: {e}", scene.spec))?;
    let build_ms = t1.elapsed().as_secs_f64() * 1e3;
    let stats = BvhStats::of(&bvh);
    let t2 = Instant::now();
    let gpu = match &req.gpu {
        None => Err("no GPU device".to_string()),
        Some(ctx) => {
            stage(format!("uploading {} nodes to the GPU", bvh.nodes.len()));
            GpuBvh::upload(ctx, &bvh, &upload_options(bvh.depth))
                .and_then(|g| {
                    stage("compiling the traversal kernels".into());
                    for (query, counters) in [
                        (bvhtrace_core::Query::Closest, false),
                        (bvhtrace_core::Query::Any, false),
                    ] {
                        // A traversal this upload cannot run is reported at trace time.
                        if g.supports(req.traversal).is_ok() {
                            g.prepare(&TraceOptions {
                                traversal: req.traversal,
                                query,
                                counters,
                            })?;
                        }
                    }
                    Ok(Arc::new(g))
                })
                .map_err(|e| format!("GPU upload failed: {e}"))
        }
    };
    let upload_ms = t2.elapsed().as_secs_f64() * 1e3;
    Ok(JobOutput {
        scene,
        new_scene,
        built: BuiltBvh {
            bvh: Arc::new(bvh),
            stats,
            options: req.build,
            build_ms,
            gpu,
            upload_ms,
        },
    })
}

impl Job {
    /// Starts `req` on a new thread; `wake` is called whenever there is news (to repaint).
    pub fn spawn(req: JobRequest, what: String, wake: impl Fn() + Send + 'static) -> Job {
        let (tx, rx) = mpsc::channel();
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
        Job {
            rx,
            started: Instant::now(),
            stage: "starting".into(),
            what,
        }
    }

    /// Takes the news: `Some(result)` once the job is over.
    pub fn poll(&mut self) -> Option<Result<JobOutput, String>> {
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
