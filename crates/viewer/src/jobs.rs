//! Loading a scene, building its BVH and uploading it, on a worker thread: the window keeps
//! drawing (with a progress line) while it runs, and a failure leaves the current scene as
//! it is. The finished [`BuiltBvh`] holds the two tracers the viewer picks between.

use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, Sender, TryRecvError};
use std::time::Instant;

use bvhtrace_core::{
    BuildOptions, BvhStats, FlatBvh, Query, Ray, TraceOptions, TraceOutput, Traversal, Triangle,
};
use bvhtrace_gpu::kernels::check_depth;
use bvhtrace_gpu::{CpuTracer, GpuBvh, GpuContext, TraceError, Tracer, UploadOptions};
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

/// A built (and, when a device is there, uploaded) BVH, with the two tracers over it.
pub struct BuiltBvh {
    /// Its quality figures.
    pub stats: BvhStats,
    /// The options it was built with.
    pub options: BuildOptions,
    /// Build time, milliseconds.
    pub build_ms: f64,
    /// The CPU walks over the tree: the fallback, and the reference of "Compare with CPU".
    pub cpu: CpuTracer,
    /// The upload, or why there is none.
    pub gpu: Result<Box<dyn Tracer>, String>,
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
            Ok(g) if !prefer_cpu && self.gpu_failure.is_none() => Some(g.as_ref()),
            _ => None,
        }
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
    pub fn trace(
        &mut self,
        rays: &[Ray],
        opts: &TraceOptions,
        prefer_cpu: bool,
    ) -> Result<(TraceOutput, bool), TraceError> {
        if let Some(g) = self.gpu_tracer(prefer_cpu) {
            match g.trace(rays, opts) {
                Ok(out) => return Ok((out, true)),
                Err(e) => self.gpu_failure = Some(format!("GPU trace failed: {e}")),
            }
        }
        Ok((self.cpu.trace(rays, opts)?, false))
    }
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
    /// The shared device, or why there is none.
    pub gpu: Result<GpuContext, String>,
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
    if check_depth(Traversal::FullStack, depth).is_ok() {
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
        Err(e) => Err(e.clone()),
        Ok(ctx) => {
            stage(format!("uploading {} nodes to the GPU", bvh.nodes.len()));
            GpuBvh::upload(ctx, &bvh, &upload_options(bvh.depth))
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
                    Ok(Box::new(g) as Box<dyn Tracer>)
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
            cpu: CpuTracer::new(Arc::new(bvh)),
            gpu,
            gpu_failure: None,
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
            cpu: CpuTracer::new(Arc::new(bvh)),
            gpu: Err("no Vulkan adapter".into()),
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
