//! One interface over the GPU kernels and the CPU twin: the viewer asks for a batch and
//! gets hits back, from the GPU when it can, else from the CPU with the reason kept for
//! the UI.

use std::sync::Arc;
use std::time::Instant;

use bvhtrace_core::{
    Counters, FlatBvh, Hit, Query, Ray, Traversal, trace_batch, trace_batch_counted,
};
use bvhtrace_gpu::{GpuBvh, TraceOptions};

/// The answer to one batch.
#[derive(Clone, Debug, Default)]
pub struct Traced {
    /// One hit per ray.
    pub hits: Vec<Hit>,
    /// One entry per ray when counters were asked for.
    pub counters: Option<Vec<Counters>>,
    /// Wall time (for the GPU: ray upload, dispatch and readback), milliseconds.
    pub wall_ms: f64,
    /// Kernel time from GPU timestamps, when there are any.
    pub gpu_ms: Option<f64>,
    /// True when the GPU traced the batch.
    pub on_gpu: bool,
}

/// Where the rays of one scene are traced.
pub struct Tracer {
    /// The BVH (the CPU twin traverses it; the GPU has an uploaded copy).
    pub bvh: Arc<FlatBvh>,
    /// The uploaded BVH, when there is a device and the upload worked.
    pub gpu: Option<Arc<GpuBvh>>,
    /// Why the GPU is not used: no device, a failed upload, or a failed trace. Set, the
    /// CPU traces everything until [`Tracer::retry_gpu`].
    pub gpu_problem: Option<String>,
    /// The user's choice to trace on the CPU even with a working GPU.
    pub prefer_cpu: bool,
}

impl Tracer {
    /// A tracer over `bvh`, with its GPU upload (or the reason there is none).
    pub fn new(bvh: Arc<FlatBvh>, gpu: Result<Arc<GpuBvh>, String>) -> Tracer {
        let (gpu, gpu_problem) = match gpu {
            Ok(g) => (Some(g), None),
            Err(e) => (None, Some(e)),
        };
        Tracer {
            bvh,
            gpu,
            gpu_problem,
            prefer_cpu: false,
        }
    }

    /// True when the next batch goes to the GPU.
    pub fn uses_gpu(&self) -> bool {
        self.gpu.is_some() && self.gpu_problem.is_none() && !self.prefer_cpu
    }

    /// Forgets a failed trace so that the next batch tries the GPU again (after the user
    /// changed the traversal, for instance). A missing upload stays missing.
    pub fn retry_gpu(&mut self) {
        if self.gpu.is_some() {
            self.gpu_problem = None;
        }
    }

    /// Compiles the GPU pipelines this traversal needs for the viewer's batches, so that
    /// the first frame does not pay for them. Errors are kept as the GPU problem.
    pub fn prepare(&mut self, traversal: Traversal) {
        let Some(g) = &self.gpu else { return };
        for (query, counters) in [
            (Query::Closest, false),
            (Query::Closest, true),
            (Query::Any, false),
        ] {
            if let Err(e) = g.prepare(&TraceOptions {
                traversal,
                query,
                counters,
            }) {
                self.gpu_problem = Some(format!("{e}"));
                return;
            }
        }
    }

    /// Traces one batch: on the GPU when [`Tracer::uses_gpu`], falling back to the CPU
    /// twin (and remembering why) when the GPU fails.
    pub fn trace(
        &mut self,
        rays: &[Ray],
        traversal: Traversal,
        query: Query,
        counters: bool,
    ) -> Traced {
        if self.uses_gpu()
            && let Some(g) = &self.gpu
        {
            match g.trace_with(
                rays,
                &TraceOptions {
                    traversal,
                    query,
                    counters,
                },
            ) {
                Ok(out) => {
                    return Traced {
                        hits: out.hits,
                        counters: out.counters,
                        wall_ms: out.wall_ms,
                        gpu_ms: out.gpu_ms,
                        on_gpu: true,
                    };
                }
                Err(e) => self.gpu_problem = Some(format!("GPU trace failed: {e}")),
            }
        }
        cpu_trace(&self.bvh, rays, traversal, query, counters)
    }
}

/// Traces a batch with the CPU twin (rayon over rays).
pub fn cpu_trace(
    bvh: &FlatBvh,
    rays: &[Ray],
    traversal: Traversal,
    query: Query,
    counters: bool,
) -> Traced {
    let start = Instant::now();
    let (hits, c) = if counters {
        let (h, c) = trace_batch_counted(bvh, rays, traversal, query);
        (h, Some(c))
    } else {
        (trace_batch(bvh, rays, traversal, query), None)
    };
    Traced {
        hits,
        counters: c,
        wall_ms: start.elapsed().as_secs_f64() * 1e3,
        gpu_ms: None,
        on_gpu: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bvhtrace_core::BuildOptions;
    use glam::Vec3;

    #[test]
    fn without_a_gpu_the_cpu_traces_and_says_why() {
        let tris = vec![[
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ]];
        let bvh = Arc::new(FlatBvh::build(&tris, &BuildOptions::default()).expect("builds"));
        let mut t = Tracer::new(bvh, Err("no Vulkan adapter".into()));
        assert!(!t.uses_gpu());
        let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
        let out = t.trace(&rays, Traversal::Stackless, Query::Closest, true);
        assert!(!out.on_gpu);
        assert_eq!(out.hits[0].prim, 0);
        assert_eq!(out.counters.map(|c| c.len()), Some(1));
        // Retrying cannot conjure an upload: the reason stays.
        t.retry_gpu();
        assert_eq!(t.gpu_problem.as_deref(), Some("no Vulkan adapter"));
    }
}
