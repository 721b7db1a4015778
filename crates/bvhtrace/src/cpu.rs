//! The CPU backend's tracer: the layout made for the CPU ([`bvhtrace_cpu`], SIMD walks
//! over 8-wide nodes) for full-stack traces (closest hits bit for bit the full stack's,
//! any hits with its verdicts); the core walks for everything else.

use std::borrow::Borrow;
use std::sync::{Arc, OnceLock};

use bvhtrace_core::{FlatBvh, InstanceTable, Precision, Ray, TraceOptions, TraceOutput, Traversal};
use bvhtrace_cpu::CpuBvh;
use bvhtrace_engine::{CpuTracer, TraceError, Tracer};
use web_time::Instant;

/// The core walks ([`CpuTracer`]) with the CPU layout beside them. A trace goes to the
/// layout when it asks for what the layout answers as the core walks do: the full stack
/// (the CPU's default walk), the watertight f32 test, no counters, no filter; one mesh or
/// two levels (any visibility mask, `TraceOptions::mask`), with or without alpha masks.
/// Closest hits are then the full stack's bit for bit; any hits agree with every backend
/// on hit or miss, the triangle reported being the layout walk's first find (which
/// triangle an any-hit query stops at depends on the walk on every backend). A batch that
/// looks coherent (`bvhtrace_cpu::coherent`: camera rays, shadow rays toward one light)
/// goes in packets, the same answers faster; others one ray at a time. The tree is
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
                let packets =
                    !fast.is_instanced() && fast.masks().is_none() && bvhtrace_cpu::coherent(rays);
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
