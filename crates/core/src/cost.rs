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
//!   child taken or a group popped (the wide walk). Trips differ in cost (a wide trip
//!   tests eight boxes); the trip count is what divergence multiplies.

use rayon::prelude::*;

use crate::flat::FlatBvh;
use crate::ray::Ray;
use crate::traverse::{TraceOptions, WalkCost, trace_ray_cost};

/// Lanes per warp.
pub const WARP: usize = 32;

/// What one walk costs a batch of rays on the model GPU (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WarpCost {
    /// Rays traced.
    pub rays: usize,
    /// Warps of [`WARP`] rays (the last one may be short).
    pub warps: usize,
    /// Mean over warps of the slowest lane's loop trips.
    pub trips_per_warp: f64,
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
    let per_warp: Vec<(u64, u64, usize, WalkTotals)> = rays
        .par_chunks(WARP)
        .map_init(Vec::new, |stack, warp| {
            let mut totals = WalkTotals::default();
            let mut slowest = 0u64;
            for ray in warp {
                let (_, c) = trace_ray_cost(bvh, ray, opts, stack);
                slowest = slowest.max(u64::from(c.trips));
                totals.add(&c);
            }
            (slowest, totals.trips, warp.len(), totals)
        })
        .collect();
    let n = rays.len().max(1) as f64;
    let warps = per_warp.len();
    let mut all = WalkTotals::default();
    let (mut slowest_sum, mut lane_trips_spent) = (0u64, 0u64);
    for (slowest, _, _, t) in &per_warp {
        slowest_sum += slowest;
        lane_trips_spent += slowest * WARP as u64;
        all.merge(t);
    }
    WarpCost {
        rays: rays.len(),
        warps,
        trips_per_warp: slowest_sum as f64 / warps.max(1) as f64,
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
