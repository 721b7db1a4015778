//! Scenes in time, and curves, through the front door: a moving mesh, static meshes under
//! moving instances, or triangles with curves ([`TimedScene`]), traced with rays that each
//! carry a time ([`TimedTracer`]), on the CPU or on wgpu, opened as [`crate::open`] opens a
//! static tree.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use std::sync::Arc;
//! use bvhtrace::core::motion::{MotionBvh, MotionMesh, TimeBounds};
//! use bvhtrace::core::{BuildOptions, Query, Ray};
//! use bvhtrace::glam::Vec3;
//! use bvhtrace::{Backend, OpenOptions, TimedScene};
//!
//! let tri = [Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)];
//! let moved = tri.map(|v| v + Vec3::X);
//! let mesh = MotionMesh::new(vec![vec![tri], vec![moved]])?;
//! let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), TimeBounds::Linear)?;
//! let opened = bvhtrace::open_timed(TimedScene::Moving(Arc::new(bvh)), &OpenOptions::new(Backend::Auto))?;
//! let rays = [Ray::new(Vec3::new(0.5, 0.0, 5.0), Vec3::NEG_Z)];
//! let hits = opened.tracer.trace(&rays, &[0.25], Query::Closest)?;
//! println!("{} on {}: {:?}", opened.backend, opened.device, hits[0]);
//! # Ok(()) }
//! ```

use std::fmt;
use std::sync::Arc;

use bvhtrace_core::motion::{MotionBvh, MotionInstancedBvh};
use bvhtrace_core::{CurveBvh, Hit, Query, Ray};
use bvhtrace_cpu::{ConvertError, CurveCpuBvh, MovingCpuBvh, MovingInstancesCpuBvh};
use bvhtrace_engine::TraceError;
use bvhtrace_engine::tracer::SendSync;
use bvhtrace_gpu::{GpuContext, GpuCurveBvh, GpuMotionBvh, GpuMotionInstancedBvh};

use crate::open::exceeds_a_limit;
use crate::{Backend, Device, OpenOptions};

/// A scene a [`TimedTracer`] traces: what a flat tree does not hold.
#[derive(Clone, Debug)]
pub enum TimedScene {
    /// One mesh whose triangles move between time steps.
    Moving(Arc<MotionBvh>),
    /// Static meshes placed by instances whose transforms move between time steps.
    MovingInstances(Arc<MotionInstancedBvh>),
    /// Triangles and curves, the same at every time.
    Curves(Arc<CurveBvh>),
}

impl TimedScene {
    /// What it is, for messages: `a moving mesh`, `moving instances` or `curves`.
    pub fn name(&self) -> &'static str {
        match self {
            TimedScene::Moving(_) => "a moving mesh",
            TimedScene::MovingInstances(_) => "moving instances",
            TimedScene::Curves(_) => "curves",
        }
    }
}

/// A tracer for a [`TimedScene`]: every ray carries a time.
pub trait TimedTracer: SendSync {
    /// Traces `rays[i]` at `times[i]` (clamped to the shutter `[0, 1]`; a ray whose time is
    /// NaN is not traced and answers `INVALID_RAY`; curves answer alike at every time):
    /// closest hits (the walks' hit rule, the same on every backend, bit for bit on our
    /// walks for triangles and linear curves) or any hit. `times` must hold one time per
    /// ray.
    fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, TraceError>;
}

/// A [`TimedTracer`] [`open_timed`] opened, and what was chosen and why.
pub struct OpenedTimed {
    /// The tracer.
    pub tracer: Box<dyn TimedTracer>,
    /// The backend it runs on (never [`Backend::Auto`]).
    pub backend: Backend,
    /// The device: the adapter's name and type, or `cpu`.
    pub device: String,
    /// What was not as asked, and why, as a sentence a front end prints.
    pub fallback: Option<String>,
}

impl fmt::Debug for OpenedTimed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("OpenedTimed")
            .field("backend", &self.backend)
            .field("device", &self.device)
            .field("fallback", &self.fallback)
            .finish_non_exhaustive()
    }
}

/// Opens a tracer for `scene` on the backend `opts` asks for ([`Backend::Auto`]: wgpu on
/// the best adapter, else the CPU; a scene over the device's limits goes to the CPU,
/// saying why). The CPU traces each in the CPU layout ([`MovingCpuBvh`],
/// [`MovingInstancesCpuBvh`], [`CurveCpuBvh`]); wgpu with our walks (`GpuMotionBvh`,
/// `GpuMotionInstancedBvh`, `GpuCurveBvh`). Ray queries have neither motion nor curves in
/// wgpu: [`Backend::RayQuery`] traces our walks on its device, and says so. The Vulkan backend (ash) has no kernels
/// for them and refuses.
pub fn open_timed(scene: TimedScene, opts: &OpenOptions) -> Result<OpenedTimed, TraceError> {
    Device::new(opts)?.open_timed(scene)
}

impl Device {
    /// Opens a tracer for `scene` on this device (see [`open_timed`]).
    pub fn open_timed(&self, scene: TimedScene) -> Result<OpenedTimed, TraceError> {
        let opened = |tracer, device: &Device, fallback: Option<String>| OpenedTimed {
            tracer,
            backend: device.backend(),
            device: device.name(),
            fallback: fallback.or_else(|| self.fallback().map(str::to_string)),
        };
        match self.inner.open_timed(&scene) {
            Ok((tracer, note)) => Ok(opened(tracer, self, note)),
            Err(e) if self.auto && exceeds_a_limit(&e) => {
                let why = format!(
                    "{} does not fit {} ({e}); tracing on the CPU",
                    scene.name(),
                    self.name()
                );
                let cpu = Device::cpu();
                Ok(opened(on_cpu(&scene)?, &cpu, Some(why)))
            }
            Err(e) => Err(e),
        }
    }
}

/// Times for every ray, or the error that names the mismatch.
fn check_times(rays: &[Ray], times: &[f32]) -> Result<(), TraceError> {
    if rays.len() == times.len() {
        return Ok(());
    }
    Err(TraceError::BadBuffer {
        buffer: "times",
        problem: format!("{} times for {} rays: one per ray", times.len(), rays.len()),
    })
}

/// The CPU's tracer for `scene`: its CPU layout.
pub(crate) fn on_cpu(scene: &TimedScene) -> Result<Box<dyn TimedTracer>, TraceError> {
    let refused = |e: ConvertError| TraceError::Unsupported {
        backend: Backend::Cpu.name(),
        what: format!("{} in the CPU layout: {e}", scene.name()),
    };
    Ok(match scene {
        TimedScene::Moving(b) => Box::new(CpuTimed(MovingCpuBvh::from_motion(b).map_err(refused)?)),
        TimedScene::MovingInstances(b) => Box::new(CpuTimed(
            MovingInstancesCpuBvh::from_motion(b).map_err(refused)?,
        )),
        TimedScene::Curves(b) => Box::new(CpuTimed(
            CurveCpuBvh::from_curves(b.clone()).map_err(refused)?,
        )),
    })
}

/// Our walks on wgpu for `scene`.
pub(crate) fn on_wgpu(
    ctx: &GpuContext,
    scene: &TimedScene,
) -> Result<Box<dyn TimedTracer>, TraceError> {
    Ok(match scene {
        TimedScene::Moving(b) => Box::new(WgpuTimed(GpuMotionBvh::upload(ctx, b.clone())?)),
        TimedScene::MovingInstances(b) => {
            Box::new(WgpuTimed(GpuMotionInstancedBvh::upload(ctx, b.clone())?))
        }
        TimedScene::Curves(b) => Box::new(WgpuTimed(GpuCurveBvh::upload(ctx, b.clone())?)),
    })
}

/// The error of a backend without kernels for `scene`.
pub(crate) fn unsupported(backend: Backend, scene: &TimedScene) -> TraceError {
    TraceError::Unsupported {
        backend: backend.name(),
        what: format!("{}: trace it on wgpu (our walks) or the CPU", scene.name()),
    }
}

/// Curves' `hits`, the same at every time, with the rays whose time is NaN answered as
/// invalid, as on every scene.
fn nan_times_untraced(mut hits: Vec<Hit>, rays: &[Ray], times: &[f32]) -> Vec<Hit> {
    for (h, (r, t)) in hits.iter_mut().zip(rays.iter().zip(times)) {
        if t.is_nan() {
            *h = bvhtrace_core::traverse::untraced(r);
        }
    }
    hits
}

/// A CPU tree that traces rays with times.
struct CpuTimed<T>(T);

impl TimedTracer for CpuTimed<MovingCpuBvh> {
    fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, TraceError> {
        check_times(rays, times)?;
        Ok(self.0.trace_rays(rays, times, query))
    }
}

impl TimedTracer for CpuTimed<MovingInstancesCpuBvh> {
    fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, TraceError> {
        check_times(rays, times)?;
        Ok(self.0.trace_rays(rays, times, query))
    }
}

impl TimedTracer for CpuTimed<CurveCpuBvh> {
    fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, TraceError> {
        check_times(rays, times)?;
        Ok(nan_times_untraced(
            self.0.trace_rays(rays, query),
            rays,
            times,
        ))
    }
}

/// A wgpu upload that traces rays with times.
struct WgpuTimed<T>(T);

impl TimedTracer for WgpuTimed<GpuMotionBvh> {
    fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, TraceError> {
        check_times(rays, times)?;
        self.0.trace(rays, times, query)
    }
}

impl TimedTracer for WgpuTimed<GpuMotionInstancedBvh> {
    fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, TraceError> {
        check_times(rays, times)?;
        self.0.trace(rays, times, query)
    }
}

impl TimedTracer for WgpuTimed<GpuCurveBvh> {
    fn trace(&self, rays: &[Ray], times: &[f32], query: Query) -> Result<Vec<Hit>, TraceError> {
        check_times(rays, times)?;
        Ok(nan_times_untraced(self.0.trace(rays, query)?, rays, times))
    }
}
