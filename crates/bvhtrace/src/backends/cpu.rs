//! The CPU backend: the core walks, with the layout made for the CPU ([`bvhtrace_cpu`],
//! SIMD walks over 8-wide nodes) for full-stack traces (closest hits bit for bit the full
//! stack's, any hits with its verdicts); the core walks for everything else.

use std::any::Any;
use std::borrow::Borrow;
use std::sync::{Arc, OnceLock};

use bvhtrace_core::{
    FlatBvh, InstanceTable, Precision, Ray, TraceOptions, TraceOutput, Traversal, Triangle,
};
use bvhtrace_cpu::CpuBvh;
use bvhtrace_engine::builder::{GpuBuildOptions, GpuBuildTimes};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::{CpuTracer, DriverTuning, TraceError, Tracer};
use web_time::Instant;

use super::interface::{DeviceInterface, OpenResult, TimedOpen, Tree, no_device_builder};
use crate::open::check_walks;
use crate::{Backend, OpenOptions, Opened, TimedScene};

/// The CPU: nothing to open.
struct CpuDevice;

/// The CPU backend's device.
pub(crate) fn device() -> Arc<dyn DeviceInterface> {
    Arc::new(CpuDevice)
}

impl DeviceInterface for CpuDevice {
    fn backend(&self) -> Backend {
        Backend::Cpu
    }

    fn name(&self) -> String {
        "cpu".to_string()
    }

    fn tuning(&self) -> Option<DriverTuning> {
        None
    }

    fn limits(&self) -> Option<DeviceLimits> {
        None
    }

    fn applies_rust_filters(&self) -> bool {
        true
    }

    fn open_timed(&self, scene: &TimedScene) -> Result<TimedOpen, TraceError> {
        Ok((crate::timed::on_cpu(scene)?, None))
    }

    fn open<'t, 'a>(
        &self,
        tree: Tree<'t, 'a>,
        opts: &OpenOptions,
        _auto: bool,
    ) -> OpenResult<'t, 'a> {
        // No other backend takes over from the CPU: nothing to give back.
        open(tree, opts, None).map_err(|e| (e, None))
    }

    fn build_bvh(
        &self,
        _: &[Triangle],
        _: &GpuBuildOptions,
    ) -> Result<(FlatBvh, GpuBuildTimes), TraceError> {
        Err(no_device_builder(Backend::Cpu))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// The CPU walks on `tree` (kept as given: traced in place) with `opts`' filter and the CPU
/// layout beside them ([`FastCpuTracer`]); `why` is the fallback that led here.
pub(crate) fn open<'a>(
    tree: Tree<'_, 'a>,
    opts: &OpenOptions,
    why: Option<String>,
) -> Result<Opened<'a>, TraceError> {
    let walks = match opts.traversals.is_empty() {
        true => vec![Traversal::CPU_DEFAULT],
        false => opts.traversals.clone(),
    };
    let walks_on = CpuTracer::new(tree.keep());
    let tracer: Box<dyn Tracer + 'a> = match &opts.filter {
        Some(f) => Box::new(FastCpuTracer::new(walks_on.with_filter(f.0.clone()))),
        None => Box::new(FastCpuTracer::new(walks_on)),
    };
    check_walks(&*tracer, &walks)?;
    Ok(Opened {
        device: tracer.device_name(),
        tracer,
        backend: Backend::Cpu,
        storage: None,
        traversal: walks[0],
        fallback: why,
        choice: None,
    })
}

/// The core walks ([`CpuTracer`]) with the CPU layout beside them. A trace goes to the
/// layout when it asks for what the layout answers as the core walks do: the full stack
/// (the CPU's default walk), the watertight f32 test, no counters, no filter; one mesh or
/// two levels (any visibility mask, `TraceOptions::mask`), with or without alpha masks.
/// Closest hits are then the full stack's bit for bit; any hits agree with every backend
/// on hit or miss, the triangle reported being the layout walk's first find (which
/// triangle an any-hit query stops at depends on the walk on every backend). A batch that
/// looks coherent (`bvhtrace_cpu::coherent`: camera rays, shadow rays toward one light)
/// goes in packets, the same answers faster; others one ray at a time. A packet is 64
/// consecutive rays: camera rays put in 8x8 tiles ([`crate::tile_order`], as `bvhtrace
/// render` traces them) walk 1.3-1.5x faster than the same rays row by row, whose
/// packets are 64x1 strips. The tree is
/// converted on the first trace the layout takes (or the first question about it), not
/// before.
pub struct FastCpuTracer<B> {
    walks: CpuTracer<B>,
    layout: OnceLock<Option<Arc<CpuBvh>>>,
    /// The two-level tree's instance table every output shares (`None` for one mesh).
    instances: OnceLock<Option<Arc<InstanceTable>>>,
}

impl<B: Borrow<FlatBvh>> FastCpuTracer<B> {
    /// `walks`, with the CPU layout beside them for the traces it takes.
    pub fn new(walks: CpuTracer<B>) -> Self {
        FastCpuTracer {
            walks,
            layout: OnceLock::new(),
            instances: OnceLock::new(),
        }
    }

    /// The tree in the CPU layout; `None` when a filter is on or the layout refuses the
    /// tree (one edited by hand past its arrays).
    fn layout(&self) -> Option<&Arc<CpuBvh>> {
        self.layout
            .get_or_init(|| {
                if self.walks.has_filter() {
                    return None;
                }
                CpuBvh::from_flat(self.walks.bvh()).ok().map(Arc::new)
            })
            .as_ref()
    }

    /// True when the layout traces with `opts`.
    pub fn takes(&self, opts: &TraceOptions) -> bool {
        opts.traversal == Traversal::FullStack
            && opts.precision == Precision::WatertightF32
            && !opts.counters
            && self.layout().is_some()
    }

    /// True when the tree is in the CPU layout too (converting it on the first call).
    pub fn has_layout(&self) -> bool {
        self.layout().is_some()
    }
}

impl<B: Borrow<FlatBvh> + Send + Sync> Tracer for FastCpuTracer<B> {
    fn backend(&self) -> &'static str {
        self.walks.backend()
    }

    fn device_name(&self) -> String {
        match self.layout() {
            Some(_) => format!(
                "{}, full-stack traces in the CPU layout ({})",
                self.walks.device_name(),
                bvhtrace_cpu::Isa::detect()
            ),
            None => self.walks.device_name(),
        }
    }

    fn default_traversal(&self) -> Traversal {
        self.walks.default_traversal()
    }

    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.walks.supports(opts)
    }

    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        match self.layout() {
            Some(fast) if self.takes(opts) => {
                let start = Instant::now();
                let isa = bvhtrace_cpu::Isa::detect();
                // Packets hold one mesh without masks (and its rays see no instance mask).
                let packets = fast.is_plain() && bvhtrace_cpu::coherent(rays);
                let hits = if packets {
                    bvhtrace_cpu::trace_packets_with(fast, rays, opts.query, isa)
                } else {
                    bvhtrace_cpu::trace_rays_with_mask(fast, rays, opts.query, opts.mask, isa)
                };
                Ok(TraceOutput {
                    hits,
                    counters: None,
                    gpu_ms: None,
                    wall_ms: start.elapsed().as_secs_f64() * 1e3,
                    incomplete: 0,
                    instances: self
                        .instances
                        .get_or_init(|| InstanceTable::of(self.walks.bvh()))
                        .clone(),
                    phases: None,
                })
            }
            _ => self.walks.trace(rays, opts),
        }
    }

    fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        self.walks.update(bvh)?;
        // Converted again when next asked for, from the updated tree.
        self.layout = OnceLock::new();
        self.instances = OnceLock::new();
        Ok(())
    }
}
