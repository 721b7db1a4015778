//! The CPU backend's tracer: the layout made for the CPU ([`bvhtrace_cpu`], SIMD walks
//! over 8-wide nodes) for the closest hits it answers as the full-stack walk does, bit for
//! bit; the core walks for everything else.

use std::borrow::Borrow;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, Precision, Query, Ray, TraceOptions, TraceOutput, Traversal};
use bvhtrace_cpu::CpuBvh;
use bvhtrace_kernels::{CpuTracer, TraceError, Tracer};
use web_time::Instant;

/// The core walks ([`CpuTracer`]) with the CPU layout beside them. A trace goes to the
/// layout when it asks for what the layout answers identically: closest hits with the
/// full stack (the CPU's default walk), the watertight f32 test, no counters, no filter.
/// Any-hit queries stay on the core walks, whose choice of hit is the kernels' twin; so do
/// two-level and alpha-masked trees, which the layout does not take.
pub struct FastCpuTracer<'a> {
    walks: Box<dyn Tracer + 'a>,
    fast: Option<Arc<CpuBvh>>,
    filtered: bool,
}

impl<'a> FastCpuTracer<'a> {
    /// `walks` over `bvh`, with the layout converted from `bvh` when it takes the tree;
    /// `filtered` when `walks` passes candidates through a filter (the layout cannot).
    pub fn new<B>(walks: CpuTracer<B>, filtered: bool) -> Self
    where
        B: Borrow<FlatBvh> + Send + Sync + 'a,
    {
        let fast = CpuBvh::from_flat(walks.bvh()).ok().map(Arc::new);
        FastCpuTracer {
            walks: Box::new(walks),
            fast,
            filtered,
        }
    }

    /// True when the layout traces with `opts`.
    pub fn takes(&self, opts: &TraceOptions) -> bool {
        self.fast.is_some()
            && !self.filtered
            && opts.traversal == Traversal::FullStack
            && opts.query == Query::Closest
            && opts.precision == Precision::WatertightF32
            && !opts.counters
    }

    /// True when the tree is in the CPU layout too.
    pub fn has_layout(&self) -> bool {
        self.fast.is_some()
    }
}

impl Tracer for FastCpuTracer<'_> {
    fn backend(&self) -> &'static str {
        self.walks.backend()
    }

    fn device_name(&self) -> String {
        match self.fast {
            Some(_) => format!(
                "{}, closest hits in the CPU layout ({})",
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
        match &self.fast {
            Some(fast) if self.takes(opts) => {
                let start = Instant::now();
                let hits = bvhtrace_cpu::trace_rays(fast, rays, opts.query);
                Ok(TraceOutput {
                    hits,
                    counters: None,
                    gpu_ms: None,
                    wall_ms: start.elapsed().as_secs_f64() * 1e3,
                    incomplete: 0,
                    instances: None,
                })
            }
            _ => self.walks.trace(rays, opts),
        }
    }

    fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        self.walks.update(bvh)?;
        self.fast = CpuBvh::from_flat(bvh).ok().map(Arc::new);
        Ok(())
    }
}
