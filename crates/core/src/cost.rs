//! A GPU cost model that needs no GPU: the CPU walks (which do what the kernels do, step
//! for step) run over a batch of rays grouped as a GPU runs them, and each walk's loop
//! trips and loads are tallied per warp.
//!
//! # Assumptions
//! * **Warps of 32 lanes, one ray per lane, in batch order**: the kernels give invocation
//!   `i` ray `i`, so a warp holds 32 consecutive rays (for an image in row order, 32
//!   neighbouring pixels of a row).
//! * **Lock step**: a warp runs until its slowest lane is done, so it costs the largest
//!   trip count of its lanes ([`WarpCost::trips_per_warp`]). Lane utilisation is the mean
//!   trip count over that maximum: the share of lane-trips doing work.
//! * **Every load goes to memory**: bytes per ray add up the nodes (32 bytes per binary
//!   box tested, 80 per wide node tested, 4 per escape link followed) and triangles (48
//!   per triangle tested) a ray loads, with no cache and no coalescing. On a real GPU the
//!   upper levels of the tree stay in cache, so this ranks walks by the traffic they
//!   cause rather than predicting bandwidth.
//! * One trip is one pass through a walk's loop: a node visited (binary walks), or a
//!   child taken or a group popped (the wide walk). Trips differ in cost (a full-stack
//!   trip tests two boxes, a stackless one one, a wide one up to eight); the trip count is
//!   what divergence multiplies.
//! * **Work**: a lane's loop trips plus [`BOX_TEST_TRIPS`] per box it tests, the warp's
//!   the slowest lane's ([`WarpCost::work_per_warp`]): the model's estimate of a warp's
//!   time, which ranks walks of different trip costs. Trips alone rank the wide walk
//!   first; on the one real GPU measured it is second, behind the full stack.

use rayon::prelude::*;

use crate::flat::FlatBvh;
use crate::ray::Ray;
use crate::traverse::{TraceOptions, WalkCost, trace_ray_cost};

/// Lanes per warp.
pub const WARP: usize = 32;

/// What a box test costs beside a loop trip, in trips: the one weight of
/// [`WarpCost::work_per_warp`], fitted to an NVIDIA H200's primary rays (bunny_69k and
/// igea, 1024x768: the stackless and wide walks' dispatch rates against the full stack's,
/// four ratios; docs/benchmarks.md). With it the model ranks the walks as that GPU did
/// (full stack, wide, stackless) within 8-14% of each ratio; with trips alone it put the
/// wide walk first, at 0.60-0.63x the full stack's time where the GPU took 1.23-1.27x.
pub const BOX_TEST_TRIPS: f64 = 0.65;

/// What one walk costs a batch of rays on the model GPU (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WarpCost {
    /// Rays traced.
    pub rays: usize,
    /// Warps of [`WARP`] rays (the last one may be short).
    pub warps: usize,
    /// Mean over warps of the slowest lane's loop trips.
    pub trips_per_warp: f64,
    /// Mean over warps of the slowest lane's work: its loop trips plus [`BOX_TEST_TRIPS`]
    /// per box test (the model's time per warp, in trips).
    pub work_per_warp: f64,
    /// Mean trips per ray.
    pub trips_per_ray: f64,
    /// Lane-trips doing work over lane-trips spent: `sum(trips) / (lanes * max trips)`
    /// over all warps.
    pub lane_utilisation: f64,
    /// Bytes of nodes (and escape links) loaded per ray.
    pub node_bytes_per_ray: f64,
    /// Bytes of triangles loaded per ray.
    pub triangle_bytes_per_ray: f64,
    /// Box tests per ray.
    pub nodes_per_ray: f64,
    /// Triangle tests per ray.
    pub tris_per_ray: f64,
}

impl WarpCost {
    /// Bytes of nodes and triangles loaded per ray.
    pub fn bytes_per_ray(&self) -> f64 {
        self.node_bytes_per_ray + self.triangle_bytes_per_ray
    }
}

/// Runs `opts`' walk over `rays` on the CPU and tallies it in warps of [`WARP`]
/// consecutive rays. The wide walk needs `bvh.wide()` ([`FlatBvh::build_wide`]).
pub fn warp_cost(bvh: &FlatBvh, rays: &[Ray], opts: &TraceOptions) -> WarpCost {
    let per_warp: Vec<(u64, f64, WalkTotals)> = rays
        .par_chunks(WARP)
        .map_init(Vec::new, |stack, warp| {
            let mut totals = WalkTotals::default();
            let (mut slowest, mut most_work) = (0u64, 0f64);
            for ray in warp {
                let (_, c) = trace_ray_cost(bvh, ray, opts, stack);
                slowest = slowest.max(u64::from(c.trips));
                let work = f64::from(c.trips) + BOX_TEST_TRIPS * f64::from(c.nodes);
                most_work = most_work.max(work);
                totals.add(&c);
            }
            (slowest, most_work, totals)
        })
        .collect();
    let n = rays.len().max(1) as f64;
    let warps = per_warp.len();
    let mut all = WalkTotals::default();
    let (mut slowest_sum, mut lane_trips_spent, mut work_sum) = (0u64, 0u64, 0f64);
    for (slowest, work, t) in &per_warp {
        slowest_sum += slowest;
        work_sum += work;
        lane_trips_spent += slowest * WARP as u64;
        all.merge(t);
    }
    WarpCost {
        rays: rays.len(),
        warps,
        trips_per_warp: slowest_sum as f64 / warps.max(1) as f64,
        work_per_warp: work_sum / warps.max(1) as f64,
        trips_per_ray: all.trips as f64 / n,
        lane_utilisation: if lane_trips_spent == 0 {
            1.0
        } else {
            all.trips as f64 / lane_trips_spent as f64
        },
        node_bytes_per_ray: all.node_bytes as f64 / n,
        triangle_bytes_per_ray: all.triangle_bytes as f64 / n,
        nodes_per_ray: all.nodes as f64 / n,
        tris_per_ray: all.tris as f64 / n,
    }
}

/// Sums of [`WalkCost`] over many rays, in 64 bits.
#[derive(Clone, Copy, Debug, Default)]
struct WalkTotals {
    nodes: u64,
    tris: u64,
    trips: u64,
    node_bytes: u64,
    triangle_bytes: u64,
}

impl WalkTotals {
    fn add(&mut self, c: &WalkCost) {
        self.nodes += u64::from(c.nodes);
        self.tris += u64::from(c.tris);
        self.trips += u64::from(c.trips);
        self.node_bytes += u64::from(c.node_bytes);
        self.triangle_bytes += u64::from(c.triangle_bytes());
    }

    fn merge(&mut self, o: &WalkTotals) {
        self.nodes += o.nodes;
        self.tris += o.tris;
        self.trips += o.trips;
        self.node_bytes += o.node_bytes;
        self.triangle_bytes += o.triangle_bytes;
    }
}
