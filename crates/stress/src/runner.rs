//! Running a case on every backend, traversal and query, and judging the answers.

use std::collections::HashMap;
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

use bvhtrace_core::intersect::flush_subnormal;
use bvhtrace_core::motion::MotionInstancedBvh;
use bvhtrace_core::oracle::{self, OracleHit, PreparedRay64};
use bvhtrace_core::{
    CurveBvh, FlatBvh, FlatInstance, Hit, INVALID_RAY, InstancedBvh, MISS, MotionBvh, Precision,
    Query, Ray, TraceOptions, TraceOutput, Traversal, Triangle, brute_force,
};
use bvhtrace_engine::walks::FULL_STACK_SIZE;
use bvhtrace_engine::{CpuTracer, DriverTuning, TraceError, Tracer};
use rayon::prelude::*;
use serde::Serialize;

use crate::geom::is_zero_area;
use crate::{Case, Expect, InputInfo};

mod curves;
mod motion;

/// The rings every case runs the short stack with: one that overflows now and then, and
/// the smallest.
const SHORT_STACKS: [u32; 2] = [6, 1];

/// The walks every case runs, in table order: each of [`Traversal::ALL`], the short stack
/// with each of [`SHORT_STACKS`]. The CPU full stack has no depth limit; the GPU
/// full-stack kernel (64 entries) runs only where the tree allows. The wide walk runs on
/// the wide layout converted from the same tree.
pub fn traversals() -> Vec<Traversal> {
    Traversal::all_with_short_stacks(&SHORT_STACKS)
}

/// Opens a tracer for a case's tree, uploaded for the walks listed: what the caller gives
/// the runner for each device (the CLI builds it with the front door, `bvhtrace::Device`),
/// so that this crate opens no backend itself.
pub type OpenTracer =
    Arc<dyn Fn(&FlatBvh, &[Traversal]) -> Result<Box<dyn Tracer>, TraceError> + Send + Sync>;

/// A device backend the caller opened: the name its rows take, its adapter, its CPU-driver
/// measures, what its answers promise, and how to open tracers on it.
#[derive(Clone)]
pub struct DeviceTracers {
    /// The rows' name: the backend's (`wgpu`, `vulkan`, `ray-query`, ...).
    pub backend: String,
    /// The adapter's name.
    pub name: String,
    /// The measures in force (a bounded loop-trip budget on CPU drivers such as lavapipe).
    pub tuning: DriverTuning,
    /// Our walks: every walk and query traced and compared with the CPU twins bit for bit,
    /// and a deep tree's full-stack upload must be refused. Otherwise (the device's own ray
    /// queries, not watertight by contract) one run per query, the driver's walk, judged
    /// by the oracle and reported, never failing the run.
    pub bit_for_bit: bool,
    /// The tracer factory.
    pub open: OpenTracer,
    /// Our walk of a moving mesh on this device, where it has one (the `motion-*` cases;
    /// without it their rows are this device's note).
    pub open_motion: Option<OpenMotion>,
    /// Our walk of curves on this device, where it has one (the `curves-*` cases).
    pub open_curves: Option<OpenCurves>,
}

/// Traces rays with one query on a tree a device uploaded, each ray at its time (curves
/// have no time: the times are ignored). `Err` says why it could not.
pub type TraceTimed = Box<dyn Fn(&[Ray], &[f32], Query) -> Result<Vec<Hit>, String> + Send + Sync>;

/// A moving scene's tree, to upload.
#[derive(Clone, Debug)]
pub enum MovingTree {
    /// One moving mesh.
    Mesh(Arc<MotionBvh>),
    /// Moving instances.
    Instances(Arc<MotionInstancedBvh>),
}

/// Uploads a moving scene's tree to a device, for [`DeviceTracers::open_motion`].
pub type OpenMotion = Arc<dyn Fn(MovingTree) -> Result<TraceTimed, String> + Send + Sync>;

/// Uploads a tree of curves to a device, for [`DeviceTracers::open_curves`].
pub type OpenCurves = Arc<dyn Fn(Arc<CurveBvh>) -> Result<TraceTimed, String> + Send + Sync>;

/// Where to trace: the CPU twins, and each device backend the caller opened.
#[derive(Clone)]
pub struct Backends {
    /// Report the CPU twins' rows (they are always traced: the devices are compared with
    /// them).
    pub cpu: bool,
    /// The device backends, in the order their rows come.
    pub devices: Vec<DeviceTracers>,
}

impl std::fmt::Debug for Backends {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let devices: Vec<String> = self.devices.iter().map(DeviceTracers::label).collect();
        f.debug_struct("Backends")
            .field("cpu", &self.cpu)
            .field("devices", &devices)
            .finish()
    }
}

impl DeviceTracers {
    /// `backend (adapter)`.
    pub fn label(&self) -> String {
        format!("{} ({})", self.backend, self.name)
    }
}

impl Backends {
    /// The CPU twins only.
    pub fn cpu_only() -> Backends {
        Backends::new(true)
    }

    /// The CPU twins, their rows reported when `cpu`.
    pub fn new(cpu: bool) -> Backends {
        Backends {
            cpu,
            devices: Vec::new(),
        }
    }

    /// These backends and `device`.
    pub fn with(mut self, device: DeviceTracers) -> Backends {
        self.devices.push(device);
        self
    }

    /// The device whose rows are named `backend`.
    pub fn device(&self, backend: &str) -> Option<&DeviceTracers> {
        self.devices.iter().find(|d| d.backend == backend)
    }
}

/// Differences from a reference, split by whether f32 arithmetic could decide the ray.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Differences {
    /// The f32 test was determinate for every triangle involved: the answer is wrong.
    pub wrong: usize,
    /// Some triangle involved is f32-indeterminate for this ray (an edge within rounding,
    /// a `t` within its error bound of an interval end or of the other triangle's `t`).
    pub indeterminate: usize,
}

impl Differences {
    fn add(&mut self, indeterminate: bool) {
        if indeterminate {
            self.indeterminate += 1;
        } else {
            self.wrong += 1;
        }
    }

    /// Both kinds.
    pub fn total(&self) -> usize {
        self.wrong + self.indeterminate
    }
}

/// One surface pair and ray set of the precision-limit case, for one run.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct PrecisionRow {
    /// Translation.
    pub offset: f64,
    /// Intended gap between the surfaces.
    pub gap: f64,
    /// Rays from `offset` away (true) or from 1 unit away.
    pub far: bool,
    /// Rays whose intended (unrounded f64 geometry) answer is a hit.
    pub rays: usize,
    /// Corners of the lower surface equal to the upper's in f32.
    pub merged_corners: usize,
    /// Rays for which the f64 oracle on the f32 input hits another surface than the
    /// intended geometry: the input merged (or crossed) the surfaces.
    pub input_merged: usize,
    /// Rays for which the traversal hits another surface than the intended geometry.
    pub traced_wrong_surface: usize,
    /// Rays for which the traversal's primitive differs from the oracle's.
    pub traced_vs_oracle: Differences,
}

/// One backend x traversal x query over all of a case's rays.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RunReport {
    /// `cpu`, `cpu-layout`, or a device backend's name ([`DeviceTracers::backend`]).
    pub backend: String,
    /// A run reported beside ours and judged by the oracle, never failing the case (the
    /// device's own ray queries: [`DeviceTracers::bit_for_bit`] false).
    pub reported_only: bool,
    /// The traversal (`stackless`, `short-stack(6)`, ...).
    pub traversal: String,
    /// `closest` or `any`.
    pub query: String,
    /// `ok`, or why the run did not happen (a refused upload is expected for deep trees).
    pub status: String,
    /// Rays traced.
    pub rays: usize,
    /// Rays compared with the f64 oracle and the f32 brute force.
    pub sample: usize,
    /// Oracle hits, traversal misses.
    pub false_misses: Differences,
    /// Oracle misses, traversal hits.
    pub false_hits: Differences,
    /// Both hit, different primitives (closest-hit only).
    pub wrong_prim: Differences,
    /// Differs from the f32 brute force (closest: bit for bit; any: hit or miss): what every
    /// traversal must return exactly, short of f32-indeterminate rays.
    pub brute_mismatch: Differences,
    /// Median relative `t` error where the traversal and the oracle hit the same primitive.
    pub t_rel_median: f64,
    /// Largest relative `t` error, same.
    pub t_rel_max: f64,
    /// Same-primitive hits whose `t` error exceeds `f32_t_error_bound`.
    pub t_beyond_bound: usize,
    /// Rays with a known answer (`Prim`, `Miss`, `Invalid`).
    pub known: usize,
    /// Known answers not given.
    pub known_wrong: usize,
    /// Rays from strictly inside a closed surface.
    pub must_hit: usize,
    /// Of those, misses. `wrong`: a crack (the f32 test was determinate for every triangle
    /// the ray crosses); `indeterminate`: the origin is within f32 error of the surface
    /// (the crossing's `t` is within `f32_t_error_bound` of `t_min`), so the f32 `t` may
    /// come out negative. Goal: 0 of either.
    pub escapes: Differences,
    /// Hits whose point (`origin + t dir`) lies outside the hit triangle's box by more than
    /// `1e-4` of (its diagonal + `|t dir|`): an f32 answer for a triangle seen with no
    /// resolution (degenerate in projection, or tiny and far away).
    pub phantom_hits: usize,
    /// Outputs flagged `INVALID_RAY`.
    pub invalid_flagged: usize,
    /// Outputs with a NaN `t`, `u` or `v`.
    pub nan_outputs: usize,
    /// Outputs breaking the `Hit` contract: a hit outside `[t_min, t_max)` or on no
    /// primitive, a miss whose `t` is not `t_max` or whose `u`, `v` are not 0, `INVALID_RAY`
    /// for a valid ray or a valid answer for an invalid one.
    pub contract_violations: usize,
    /// Hits on exactly zero-area triangles.
    pub zero_area_hits: usize,
    /// GPU: rays whose hit differs from the CPU twin's, bit for bit. The CPU layout
    /// (`cpu-layout` rows): rays whose answer differs from the CPU full stack's (closest:
    /// bit for bit; any: hit or miss).
    pub parity_mismatches: Option<usize>,
    /// GPU only: rays that spent the adapter's loop-trip budget (`TRIP_LIMIT`; lavapipe
    /// silently ends longer loops) and were finished on the CPU twin.
    pub gpu_incomplete: Option<u64>,
    /// Secondary rays without the origin offset (closest-hit).
    pub secondary_plain: usize,
    /// Of those, hits on the triangle they leave.
    pub self_hits_plain: usize,
    /// Secondary rays with the origin offset.
    pub secondary_offset: usize,
    /// Of those, hits on the triangle they leave.
    pub self_hits_offset: usize,
    /// Wall time of the trace (GPU: upload of the rays, dispatch and read-back).
    pub trace_ms: f64,
    /// Precision-limit rows (that case, closest-hit only).
    pub precision: Vec<PrecisionRow>,
    /// A few failing rays, described (for bug reports).
    pub examples: Vec<String>,
}

impl RunReport {
    /// The unconditional guarantees, at any scale: no NaN output, the hit contract kept,
    /// the GPU equal to its CPU twin.
    pub fn sound(&self) -> bool {
        self.nan_outputs == 0
            && self.contract_violations == 0
            && self.parity_mismatches.unwrap_or(0) == 0
    }

    /// True when nothing that must hold failed: no escape, NaN, contract violation, wrong
    /// known answer, determinate difference from the oracle or the brute force, or GPU/CPU
    /// mismatch.
    pub fn clean(&self) -> bool {
        self.escapes.wrong == 0
            && self.nan_outputs == 0
            && self.contract_violations == 0
            && self.known_wrong == 0
            && self.false_misses.wrong == 0
            && self.false_hits.wrong == 0
            && self.wrong_prim.wrong == 0
            && self.brute_mismatch.wrong == 0
            && self.parity_mismatches.unwrap_or(0) == 0
    }
}

/// Everything measured on one case.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CaseReport {
    /// Case name.
    pub name: String,
    /// What it exercises.
    pub description: String,
    /// Triangles.
    pub triangles: usize,
    /// Rays.
    pub rays: usize,
    /// BVH nodes.
    pub nodes: usize,
    /// BVH depth (edges on the longest root-to-leaf path).
    pub depth: u32,
    /// Build and flatten time.
    pub build_ms: f64,
    /// Rays compared with the oracle.
    pub oracle_sample: usize,
    /// Time of the oracle and the f32 brute force on the sample.
    pub oracle_ms: f64,
    /// What rounding did to the input.
    pub input: InputInfo,
    /// The case's notes.
    pub notes: Vec<String>,
    /// The device backends traced, `backend (adapter)` each.
    pub devices: Vec<String>,
    /// What uploading a tree deeper than the full-stack kernel's stack did on each device
    /// of our walks, `(backend, what)` (deep trees).
    pub full_stack: Vec<(String, String)>,
    /// One entry per backend x traversal x query.
    pub runs: Vec<RunReport>,
    /// The whole case, wall time.
    pub elapsed_ms: f64,
    /// Why the case could not run at all.
    pub error: Option<String>,
    /// Why the case was skipped: its inputs are absent (the real meshes without the shared
    /// scenes folder). Not a failure.
    pub skipped: Option<String>,
    /// False beyond the guaranteed range (see `Case::guaranteed`).
    pub guaranteed: bool,
}

impl CaseReport {
    /// True when the case ran and every run is clean (see [`RunReport::clean`]; beyond the
    /// guaranteed range, [`RunReport::sound`], the CPU layout's differences from the full
    /// stack then measured only), and a deep tree's full-stack upload was refused; or when
    /// it was skipped (it has no runs).
    pub fn clean(&self) -> bool {
        self.error.is_none()
            && self.runs.iter().all(|r| {
                if r.reported_only {
                    // Reported, not guaranteed: the driver's test is its own.
                    true
                } else if self.guaranteed {
                    r.clean()
                } else if r.backend == CPU_LAYOUT_ROWS {
                    // The CPU layout visits in its own order, so it equals the full stack
                    // only where f32 orders the triangles, which beyond the guaranteed
                    // range it need not: its differences are measured there, not required.
                    r.nan_outputs == 0 && r.contract_violations == 0
                } else {
                    r.sound()
                }
            })
            && self
                .full_stack
                .iter()
                .all(|(_, s)| s.starts_with("refused"))
    }
}

/// The scene as the judging sees it. One mesh: its triangles, tested against the ray as
/// given. Two levels: primitive `prim_base + p` of an instance is its mesh's triangle `p`,
/// tested in the mesh's space against the ray as the walks transform it
/// ([`FlatInstance::ray_to_object`], the kernels' f32 arithmetic), so that the oracle, the
/// f32-indeterminacy tests and the `t` error bounds are those of the test the walk makes.
/// `t` is the world ray's parameter either way (the direction is transformed, not
/// normalised), so it is compared with the oracle's as it is.
enum Geometry<'a> {
    Flat(&'a [Triangle]),
    Instanced(Vec<Placed<'a>>),
}

/// One instance of a two-level case: how the walks enter it, and its mesh's triangles.
struct Placed<'a> {
    flat: FlatInstance,
    tris: &'a [Triangle],
}

impl<'a> Geometry<'a> {
    /// The judging view of `case`, built as `bvh` (its instances, when two levels).
    fn new(case: &'a Case, bvh: &FlatBvh) -> Geometry<'a> {
        match &case.instancing {
            None => Geometry::Flat(&case.tris),
            Some(inst) => Geometry::Instanced(
                bvh.instances()
                    .iter()
                    .zip(&inst.instances)
                    .map(|(flat, i)| Placed {
                        flat: *flat,
                        tris: inst.meshes[i.mesh as usize].as_slice(),
                    })
                    .collect(),
            ),
        }
    }

    /// The ray in an instance's space, as traced there (subnormal direction components
    /// flushed); `None` when the walks cannot enter it with this ray.
    fn object_ray(p: &Placed<'_>, ray: &Ray) -> Option<Ray> {
        as_traced(&p.flat.ray_to_object(ray))
    }

    /// Primitive `prim`'s triangle and the ray it is tested against.
    fn local(&self, prim: u32, ray: &Ray) -> Option<(Triangle, Ray)> {
        match self {
            Geometry::Flat(tris) => tris.get(prim as usize).map(|t| (*t, *ray)),
            Geometry::Instanced(placed) => {
                let k = placed
                    .partition_point(|p| p.flat.prim_base <= prim)
                    .checked_sub(1)?;
                let p = &placed[k];
                let tri = *p.tris.get((prim - p.flat.prim_base) as usize)?;
                Some((tri, Geometry::object_ray(p, ray)?))
            }
        }
    }

    /// The f64 oracle's closest hit (ties to the lower primitive id).
    fn closest(&self, ray: &Ray) -> OracleHit {
        match self {
            Geometry::Flat(tris) => oracle::closest_hit(tris, ray),
            Geometry::Instanced(placed) => {
                // The miss (or the invalid-ray answer) for this ray.
                let mut best = oracle::closest_hit(&[], ray);
                if !best.is_hit() && best.prim != MISS {
                    return best;
                }
                for p in placed {
                    let Some(r) = Geometry::object_ray(p, ray) else {
                        continue;
                    };
                    let h = oracle::closest_hit(p.tris, &r);
                    if !h.is_hit() {
                        continue;
                    }
                    let prim = p.flat.prim_base + h.prim;
                    if h.t < best.t || (h.t == best.t && best.is_hit() && prim < best.prim) {
                        best = OracleHit { prim, ..h };
                    }
                }
                best
            }
        }
    }

    /// Every primitive the f64 test accepts in the ray's interval, nearest first.
    fn all_hits(&self, ray: &Ray) -> Vec<(f64, u32)> {
        match self {
            Geometry::Flat(tris) => oracle::all_hits(tris, ray),
            Geometry::Instanced(placed) => {
                let mut hits: Vec<(f64, u32)> = placed
                    .iter()
                    .filter_map(|p| Some((p, Geometry::object_ray(p, ray)?)))
                    .flat_map(|(p, r)| {
                        oracle::all_hits(p.tris, &r)
                            .into_iter()
                            .map(|(t, q)| (t, p.flat.prim_base + q))
                    })
                    .collect();
                hits.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                hits
            }
        }
    }
}

/// Per-case data every run is judged with.
struct Judge<'a> {
    case: &'a Case,
    geo: Geometry<'a>,
    sample: Vec<usize>,
    /// `sample` position of each ray, or `usize::MAX`.
    position: Vec<usize>,
    oracle: Vec<OracleHit>,
    brute: Vec<Hit>,
    zero_area: Vec<bool>,
    /// [`as_traced`] of each ray.
    traced: Vec<Option<Ray>>,
}

/// Evenly spaced indices: all of `0..n` when it fits in `max`.
fn sample_indices(n: usize, max: usize) -> Vec<usize> {
    if n <= max {
        return (0..n).collect();
    }
    (0..max).map(|i| i * n / max).collect()
}

/// The ray the kernels actually trace: direction components below `f32::MIN_POSITIVE`
/// flushed to signed zero (see `bvhtrace_core::intersect::PreparedRay::dir`). The oracle
/// and the f32-indeterminacy tests are applied to this ray; `None` when flushing leaves
/// no direction (the answer is then only held to the contract).
fn as_traced(ray: &Ray) -> Option<Ray> {
    if !ray.is_valid() {
        return None;
    }
    let mut r = *ray;
    r.dir = r.dir.map(flush_subnormal);
    r.is_valid().then_some(r)
}

fn hit_bits(h: &Hit) -> [u32; 4] {
    [h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits()]
}

fn t64(tri: &Triangle, ray: &Ray) -> Option<f64> {
    PreparedRay64::new(ray).intersect(tri).map(|x| x.0)
}

/// True when `origin + t dir` (f64) lies outside the triangle's box by more than `1e-4` of
/// (the box diagonal + `|t dir|`).
fn phantom(tri: &Triangle, ray: &Ray, t: f32) -> bool {
    let o = glam::Vec3::from(ray.origin).as_dvec3();
    let d = glam::Vec3::from(ray.dir).as_dvec3();
    let p = o + d * t as f64;
    let [a, b, c] = tri.map(|v| v.as_dvec3());
    let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
    let outside = (lo - p).max(p - hi).max(glam::DVec3::ZERO).length();
    outside > 1e-4 * ((hi - lo).length() + (d * t as f64).length())
}

fn near_interval_end(ray: &Ray, t: f64, bound: f64) -> bool {
    (t - ray.t_min as f64).abs() <= bound
        || (ray.t_max.is_finite() && (t - ray.t_max as f64).abs() <= bound)
}

/// True when f32 may decide differently from f64 whether `tri` is accepted in the ray's
/// interval (`t` is the f64 distance, when the f64 test hits the triangle's plane inside).
fn acceptance_indeterminate(tri: &Triangle, ray: &Ray, t: Option<f64>) -> bool {
    if oracle::f32_indeterminate(tri, ray) {
        return true;
    }
    let b = oracle::f32_t_error_bound(tri, ray);
    match t {
        Some(t) => !b.is_finite() || near_interval_end(ray, t, b),
        None => !b.is_finite(),
    }
}

/// A difference from a reference answer; `true` when it is f32-indeterminate.
enum Diff {
    FalseMiss(bool),
    FalseHit(bool),
    WrongPrim(bool),
}

/// Judges a traced hit `h` against a reference answer (`ref_prim`, f64 `ref_t`): the kind
/// of difference and whether it is f32-indeterminate; `None` when they agree (any-hit
/// queries compare hit or miss only).
fn judge(
    geo: &Geometry<'_>,
    ray: &Ray,
    h: &Hit,
    ref_prim: u32,
    ref_t: f64,
    query: Query,
) -> Option<Diff> {
    let ref_hit = ref_prim < INVALID_RAY;
    match (h.is_hit(), ref_hit) {
        (false, false) => None,
        (false, true) => {
            // Every triangle f64 accepts must be one f32 may reject.
            let all = geo.all_hits(ray);
            let indet = all.is_empty()
                || all.iter().all(|&(t, p)| {
                    geo.local(p, ray)
                        .is_none_or(|(tri, r)| acceptance_indeterminate(&tri, &r, Some(t)))
                });
            Some(Diff::FalseMiss(indet))
        }
        (true, false) => {
            let Some((tri, r)) = geo.local(h.prim, ray) else {
                return Some(Diff::FalseHit(false));
            };
            Some(Diff::FalseHit(acceptance_indeterminate(
                &tri,
                &r,
                t64(&tri, &r),
            )))
        }
        (true, true) if query == Query::Closest && h.prim != ref_prim => {
            let (Some((tr, rr)), Some((th, rh))) =
                (geo.local(ref_prim, ray), geo.local(h.prim, ray))
            else {
                return Some(Diff::WrongPrim(false));
            };
            let (br, bh) = (
                oracle::f32_t_error_bound(&tr, &rr),
                oracle::f32_t_error_bound(&th, &rh),
            );
            let tie = match t64(&th, &rh) {
                Some(t) => (t - ref_t).abs() <= br + bh || near_interval_end(ray, t, bh),
                None => false,
            };
            let indet = tie
                || !br.is_finite()
                || !bh.is_finite()
                || oracle::f32_indeterminate(&tr, &rr)
                || oracle::f32_indeterminate(&th, &rh)
                || near_interval_end(ray, ref_t, br);
            Some(Diff::WrongPrim(indet))
        }
        _ => None,
    }
}

fn describe(ray: &Ray, what: &str, h: &Hit) -> String {
    format!(
        "{what}: origin {:?} dir {:?} [{:e}, {:e}) -> prim {} t {:e} (u {:e} v {:e})",
        ray.origin,
        ray.dir,
        ray.t_min,
        ray.t_max,
        prim_name(h.prim),
        h.t,
        h.u,
        h.v
    )
}

fn prim_name(p: u32) -> String {
    match p {
        MISS => "MISS".into(),
        INVALID_RAY => "INVALID_RAY".into(),
        p => p.to_string(),
    }
}

const MAX_EXAMPLES: usize = 6;

/// The first [`MAX_EXAMPLES`] descriptions of failures, in the order they were found.
#[derive(Default)]
struct Examples(Vec<String>);

impl Examples {
    /// Keeps `s` while there is room for it.
    fn push(&mut self, s: String) {
        if self.0.len() < MAX_EXAMPLES {
            self.0.push(s);
        }
    }
}

/// The verdicts on one sampled ray: against the f64 oracle and the f32 brute force.
struct SampleVerdict {
    oracle: Option<Diff>,
    brute: Option<Diff>,
    t_rel: Option<f64>,
    beyond: bool,
}

/// Whether `h` keeps the output contract for `ray`: an invalid ray's flag, a miss's
/// `t_max`, or a hit on a real prim within `[t_min, t_max)`.
fn keeps_contract(ray: &Ray, h: &Hit, prims: usize) -> bool {
    if !ray.is_valid() {
        let t = if ray.t_max.is_nan() { 0.0 } else { ray.t_max };
        h.prim == INVALID_RAY && h.t.to_bits() == t.to_bits() && h.u == 0.0 && h.v == 0.0
    } else if h.prim == MISS {
        h.t.to_bits() == ray.t_max.to_bits() && h.u == 0.0 && h.v == 0.0
    } else {
        (h.prim as usize) < prims && h.t >= ray.t_min && h.t < ray.t_max
    }
}

/// Which way a difference went, and whether f32 could not decide it.
fn diff_name(d: &Diff) -> (&'static str, bool) {
    match *d {
        Diff::FalseMiss(x) => ("false miss", x),
        Diff::FalseHit(x) => ("false hit", x),
        Diff::WrongPrim(x) => ("wrong prim", x),
    }
}

impl Judge<'_> {
    fn evaluate(
        &self,
        mut r: RunReport,
        query: Query,
        hits: &[Hit],
        cpu: Option<&[Hit]>,
    ) -> RunReport {
        let closest = query == Query::Closest;
        r.rays = hits.len();
        r.sample = self.sample.len();
        let mut examples = Examples::default();
        for (i, h) in hits.iter().enumerate().take(self.case.rays.len()) {
            self.check_output(&mut r, &mut examples, i, h);
            self.check_expectation(&mut r, &mut examples, i, h, closest);
        }
        let verdicts = self.sample_verdicts(query, hits);
        self.tally_sample(&mut r, &mut examples, &verdicts, hits);
        if let Some(c) = cpu {
            r.parity_mismatches = Some(self.parity(&mut examples, hits, c));
        }
        if closest {
            r.precision = self.precision_rows(hits);
        }
        r.examples = examples.0;
        r
    }

    /// Counts ray `i`'s output faults: NaNs, flags, contract breaks, hits on
    /// zero-area triangles and phantom hits off the triangle.
    fn check_output(&self, r: &mut RunReport, examples: &mut Examples, i: usize, h: &Hit) {
        let tris = &self.case.tris;
        let ray = &self.case.rays[i];
        if h.t.is_nan() || h.u.is_nan() || h.v.is_nan() {
            r.nan_outputs += 1;
            examples.push(describe(ray, &format!("ray {i}: NaN output"), h));
        }
        if h.prim == INVALID_RAY {
            r.invalid_flagged += 1;
        }
        // A case's curve segments are numbered after its triangles.
        let prims = tris.len() + self.case.curves.as_ref().map_or(0, |c| c.len());
        if !keeps_contract(ray, h, prims) {
            r.contract_violations += 1;
            examples.push(describe(ray, &format!("ray {i}: contract"), h));
        }
        if h.is_hit()
            && self
                .zero_area
                .get(h.prim as usize)
                .copied()
                .unwrap_or(false)
        {
            r.zero_area_hits += 1;
        }
        if h.is_hit()
            && (h.prim as usize) < tris.len()
            && h.t.is_finite()
            && self
                .geo
                .local(h.prim, ray)
                .is_some_and(|(tri, r)| phantom(&tri, &r, h.t))
        {
            r.phantom_hits += 1;
        }
    }

    /// Judges ray `i`'s output against what its case expects of it.
    fn check_expectation(
        &self,
        r: &mut RunReport,
        examples: &mut Examples,
        i: usize,
        h: &Hit,
        closest: bool,
    ) {
        let ray = &self.case.rays[i];
        let mut known = |r: &mut RunReport, ok: bool, what: &str| {
            r.known += 1;
            if !ok {
                r.known_wrong += 1;
                examples.push(describe(ray, &format!("ray {i}: {what}"), h));
            }
        };
        match self.case.expect[i] {
            Expect::MustHit => {
                r.must_hit += 1;
                if !h.is_hit() {
                    self.escape(r, examples, i, h);
                }
            }
            Expect::Prim(p) => {
                let ok = if closest { h.prim == p } else { h.is_hit() };
                known(r, ok, &format!("expected prim {p}"));
            }
            Expect::Miss => known(r, h.prim == MISS, "expected MISS"),
            Expect::Invalid => known(r, h.prim == INVALID_RAY, "expected INVALID_RAY"),
            Expect::Secondary { origin, offset } if closest => {
                let self_hit = h.prim == origin;
                if offset {
                    r.secondary_offset += 1;
                    r.self_hits_offset += self_hit as usize;
                } else {
                    r.secondary_plain += 1;
                    r.self_hits_plain += self_hit as usize;
                }
            }
            _ => {}
        }
    }

    /// Counts a must-hit ray `i` that missed, as a crack or as f32-indeterminate.
    fn escape(&self, r: &mut RunReport, examples: &mut Examples, i: usize, h: &Hit) {
        let indet = match &self.traced[i] {
            Some(tr) => matches!(
                judge(&self.geo, tr, h, 0, 0.0, Query::Any),
                Some(Diff::FalseMiss(true))
            ),
            None => true,
        };
        r.escapes.add(indet);
        let why = if indet {
            "f32-indeterminate"
        } else {
            "a crack"
        };
        examples.push(describe(
            &self.case.rays[i],
            &format!("ray {i}: escape ({why})"),
            h,
        ));
    }

    /// The sample's verdicts, one per sampled ray, in sample order.
    fn sample_verdicts(&self, query: Query, hits: &[Hit]) -> Vec<SampleVerdict> {
        self.sample
            .par_iter()
            .enumerate()
            .map(|(k, &i)| self.sample_verdict(query, k, &hits[i], i))
            .collect()
    }

    /// Judges hit `h` of ray `i` (sample position `k`) against the oracle and the
    /// brute force, with its distance's relative error when both found the same prim.
    fn sample_verdict(&self, query: Query, k: usize, h: &Hit, i: usize) -> SampleVerdict {
        let Some(ray) = &self.traced[i] else {
            return SampleVerdict {
                oracle: None,
                brute: None,
                t_rel: None,
                beyond: false,
            };
        };
        let o = &self.oracle[k];
        let geo = &self.geo;
        let oracle_diff = judge(geo, ray, h, o.prim, o.t, query);
        let brute_diff = self.brute_diff(query, ray, h, &self.brute[k]);
        let (mut t_rel, mut beyond) = (None, false);
        if query == Query::Closest && h.is_hit() && h.prim == o.prim {
            let err = (h.t as f64 - o.t).abs();
            t_rel = Some(if o.t != 0.0 { err / o.t.abs() } else { err });
            if let Some((tri, r)) = geo.local(h.prim, ray) {
                beyond = err > oracle::f32_t_error_bound(&tri, &r);
            }
        }
        SampleVerdict {
            oracle: oracle_diff,
            brute: brute_diff,
            t_rel,
            beyond,
        }
    }

    /// How `h` differs from the brute force's hit `b` on the traced `ray`, if it does.
    fn brute_diff(&self, query: Query, ray: &Ray, h: &Hit, b: &Hit) -> Option<Diff> {
        let geo = &self.geo;
        // The brute force's f64 distance, for judging a difference from it.
        let brute_t = || {
            if b.is_hit() {
                geo.local(b.prim, ray)
                    .and_then(|(tri, r)| t64(&tri, &r))
                    .unwrap_or(b.t as f64)
            } else {
                0.0
            }
        };
        if query != Query::Closest {
            return judge(geo, ray, h, b.prim, brute_t(), query);
        }
        if hit_bits(h) == hit_bits(b) {
            None
        } else if h.is_hit()
            && b.is_hit()
            && h.t.to_bits() == b.t.to_bits()
            && geo.local(h.prim, ray).is_some()
            && geo.local(h.prim, ray) == geo.local(b.prim, ray)
        {
            // Exact duplicates tie exactly: the lower index must win, f32 or
            // not (the traversal skipped it or broke the tie rule).
            Some(Diff::WrongPrim(false))
        } else {
            Some(judge(geo, ray, h, b.prim, brute_t(), query).unwrap_or(Diff::WrongPrim(false)))
        }
    }

    /// Adds the sample's verdicts to the report: differences from the oracle and the
    /// brute force, distances beyond the f32 bound, and the relative error's spread.
    fn tally_sample(
        &self,
        r: &mut RunReport,
        examples: &mut Examples,
        verdicts: &[SampleVerdict],
        hits: &[Hit],
    ) {
        let mut rel = Vec::new();
        for (k, one) in verdicts.iter().enumerate() {
            let i = self.sample[k];
            if let Some(d) = &one.oracle {
                self.tally_oracle(r, examples, k, d, &hits[i]);
            }
            if let Some(d) = &one.brute {
                self.tally_brute(r, examples, k, d, &hits[i]);
            }
            if let Some(t) = one.t_rel {
                rel.push(t);
            }
            if one.beyond {
                r.t_beyond_bound += 1;
            }
        }
        rel.sort_by(f64::total_cmp);
        r.t_rel_median = rel.get(rel.len() / 2).copied().unwrap_or(0.0);
        r.t_rel_max = rel.last().copied().unwrap_or(0.0);
    }

    /// Counts sampled hit `h` (sample position `k`) differing from the oracle by `d`.
    fn tally_oracle(
        &self,
        r: &mut RunReport,
        examples: &mut Examples,
        k: usize,
        d: &Diff,
        h: &Hit,
    ) {
        let i = self.sample[k];
        let (what, indet) = diff_name(d);
        match d {
            Diff::FalseMiss(_) => r.false_misses.add(indet),
            Diff::FalseHit(_) => r.false_hits.add(indet),
            Diff::WrongPrim(_) => r.wrong_prim.add(indet),
        }
        if !indet {
            let o = &self.oracle[k];
            examples.push(describe(
                &self.case.rays[i],
                &format!(
                    "ray {i}: {what} (oracle prim {} t {:e})",
                    prim_name(o.prim),
                    o.t
                ),
                h,
            ));
        }
    }

    /// Counts sampled hit `h` (sample position `k`) differing from the brute force by `d`.
    fn tally_brute(&self, r: &mut RunReport, examples: &mut Examples, k: usize, d: &Diff, h: &Hit) {
        let i = self.sample[k];
        let (_, indet) = diff_name(d);
        r.brute_mismatch.add(indet);
        if !indet {
            let b = &self.brute[k];
            examples.push(describe(
                &self.case.rays[i],
                &format!(
                    "ray {i}: differs from the f32 brute force (prim {} t {:e})",
                    prim_name(b.prim),
                    b.t
                ),
                h,
            ));
        }
    }

    /// The number of GPU hits that differ bit for bit from the CPU twin's.
    fn parity(&self, examples: &mut Examples, hits: &[Hit], cpu: &[Hit]) -> usize {
        let same_bits = |g: &Hit, c: &Hit| hit_bits(g) == hit_bits(c);
        self.count_unlike(
            examples,
            (hits, cpu),
            "GPU differs from the CPU twin's",
            same_bits,
        )
    }

    /// The rays whose hit in `hits` is not `alike` the reference's in `reference`, each
    /// described in `examples` as `what`, followed by the reference's answer.
    fn count_unlike(
        &self,
        examples: &mut Examples,
        (hits, reference): (&[Hit], &[Hit]),
        what: &str,
        alike: impl Fn(&Hit, &Hit) -> bool,
    ) -> usize {
        let mut n = 0;
        for (i, (g, c)) in hits.iter().zip(reference).enumerate() {
            if !alike(g, c) {
                n += 1;
                examples.push(describe(
                    &self.case.rays[i],
                    &format!(
                        "ray {i}: {what} (prim {} t {:e} u {:e} v {:e})",
                        prim_name(c.prim),
                        c.t,
                        c.u,
                        c.v
                    ),
                    g,
                ));
            }
        }
        n
    }

    fn precision_rows(&self, hits: &[Hit]) -> Vec<PrecisionRow> {
        let Some(setup) = &self.case.precision else {
            return Vec::new();
        };
        let surface = |p: u32| setup.prim_surface.get(p as usize).copied();
        let mut rows: HashMap<(u32, bool), PrecisionRow> = HashMap::new();
        for (i, probe) in setup.probes.iter().enumerate() {
            let Some(probe) = probe else { continue };
            let pair = &setup.pairs[probe.pair as usize];
            let row = rows
                .entry((probe.pair, probe.far))
                .or_insert_with(|| PrecisionRow {
                    offset: pair.offset,
                    gap: pair.gap,
                    far: probe.far,
                    merged_corners: pair.merged_corners,
                    ..Default::default()
                });
            if probe.intended == MISS {
                continue;
            }
            let k = self.position[i];
            if k == usize::MAX {
                continue;
            }
            row.rays += 1;
            let want = surface(probe.intended);
            let o = &self.oracle[k];
            let h = &hits[i];
            if surface(o.prim) != want {
                row.input_merged += 1;
            }
            if surface(h.prim) != want {
                row.traced_wrong_surface += 1;
            }
            let Some(ray) = &self.traced[i] else { continue };
            if let Some(d) = judge(&self.geo, ray, h, o.prim, o.t, Query::Closest) {
                let x = match d {
                    Diff::FalseMiss(x) | Diff::FalseHit(x) | Diff::WrongPrim(x) => x,
                };
                row.traced_vs_oracle.add(x);
            }
        }
        let mut v: Vec<PrecisionRow> = rows.into_values().collect();
        v.sort_by(|a, b| {
            b.gap
                .total_cmp(&a.gap)
                .then(a.far.cmp(&b.far))
                .then(a.offset.total_cmp(&b.offset))
        });
        v
    }
}

fn query_name(q: Query) -> &'static str {
    match q {
        Query::Closest => "closest",
        Query::Any => "any",
    }
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

/// A run's report before it is judged: status `ok`, nothing counted.
/// One row per walk and query of `backend`, saying its upload failed with `e`.
fn upload_failed(backend: &str, queries: &[Query], e: &dyn std::fmt::Display) -> Vec<RunReport> {
    let mut rows = Vec::new();
    for tr in traversals() {
        for &q in queries {
            let mut r = run_report(backend, tr, q);
            r.status = format!("upload failed: {e}");
            rows.push(r);
        }
    }
    rows
}

/// The backend name of the CPU layout's rows (`bvhtrace-cpu`).
pub const CPU_LAYOUT_ROWS: &str = "cpu-layout";

/// Any-hit answers alike: both hit (any triangle), or the same miss or invalid ray to
/// the bit.
fn same_verdict(a: &Hit, b: &Hit) -> bool {
    let hit = |h: &Hit| h.prim != MISS && h.prim != INVALID_RAY;
    if hit(a) || hit(b) {
        hit(a) && hit(b)
    } else {
        hit_bits(a) == hit_bits(b)
    }
}

/// The CPU layout's rows: the tree converted to `bvhtrace-cpu`'s layout, each query traced
/// one ray at a time and in packets, judged like every row and compared with the CPU full
/// stack's hits (`twin`): closest hits bit for bit, any hits on hit or miss (which
/// triangle an any-hit walk stops at depends on its order). A tree the layout does not
/// take gives a note instead of rows.
fn trace_cpu_layout(
    bvh: &FlatBvh,
    case: &Case,
    queries: &[Query],
    judge: &Judge<'_>,
    twin: &Hits,
) -> Result<Vec<RunReport>, String> {
    let layout =
        bvhtrace_cpu::CpuBvh::from_flat(bvh).map_err(|e| format!("{CPU_LAYOUT_ROWS}: {e}"))?;
    let mut runs = Vec::new();
    for (walk, packets) in [("single-ray", false), ("packets", true)] {
        for &q in queries {
            let t = Instant::now();
            let hits = if packets {
                bvhtrace_cpu::trace_packets(&layout, &case.rays, q)
            } else {
                bvhtrace_cpu::trace_rays(&layout, &case.rays, q)
            };
            let r = RunReport {
                traversal: walk.into(),
                trace_ms: ms(t),
                ..run_report(CPU_LAYOUT_ROWS, Traversal::FullStack, q)
            };
            let full_stack = twin.get(&(Traversal::FullStack, q)).map(Vec::as_slice);
            let mut r = match q {
                Query::Closest => judge.evaluate(r, q, &hits, full_stack),
                Query::Any => judge.evaluate(r, q, &hits, None),
            };
            if let (Query::Any, Some(f)) = (q, full_stack) {
                r.parity_mismatches = Some(
                    hits.iter()
                        .zip(f)
                        .filter(|(a, b)| !same_verdict(a, b))
                        .count(),
                );
            }
            runs.push(r);
        }
    }
    Ok(runs)
}

/// The rows of a device's own walk (its ray queries): one walk (the driver's) per query,
/// judged like every row, with no twin to equal, reported only.
fn trace_driver_walk(
    device: &DeviceTracers,
    bvh: &FlatBvh,
    case: &Case,
    queries: &[Query],
    judge: &Judge<'_>,
) -> Vec<RunReport> {
    let report = |q| RunReport {
        traversal: "driver".into(),
        reported_only: true,
        ..run_report(&device.backend, Traversal::FullStack, q)
    };
    let rq = match (device.open)(bvh, &[Traversal::FullStack]) {
        Ok(rq) => rq,
        Err(e) => {
            return queries
                .iter()
                .map(|&q| RunReport {
                    status: format!("upload failed: {e}"),
                    ..report(q)
                })
                .collect();
        }
    };
    queries
        .iter()
        .map(|&q| {
            let r = report(q);
            let opts = TraceOptions::new(Traversal::FullStack, q);
            match trace_timed(&*rq, &case.rays, &opts) {
                Ok(out) => judge.evaluate(
                    RunReport {
                        trace_ms: out.wall_ms,
                        ..r
                    },
                    q,
                    &out.hits,
                    None,
                ),
                Err(status) => RunReport { status, ..r },
            }
        })
        .collect()
}

fn run_report(backend: &str, tr: Traversal, q: Query) -> RunReport {
    RunReport {
        backend: backend.into(),
        traversal: tr.to_string(),
        query: query_name(q).into(),
        status: "ok".into(),
        ..Default::default()
    }
}

/// A row of a walk not among [`traversals`] (of moving scenes, of curves), named `walk`.
fn walk_row(backend: &str, walk: &str, q: Query) -> RunReport {
    RunReport {
        traversal: walk.into(),
        ..run_report(backend, Traversal::FullStack, q)
    }
}

/// Notes, once, that `backend` has no walk of `what`: the case's rows are the CPU twin's.
fn note_no_walk(rep: &mut CaseReport, backend: &str, what: &str) {
    let note = format!("{backend}: no walk of {what}, not traced");
    if !rep.notes.contains(&note) {
        rep.notes.push(note);
    }
}

/// Each traversal and query's hits on one backend.
type Hits = HashMap<(Traversal, Query), Vec<Hit>>;

/// Traces `rays` as `opts` says on `tracer`, timed: refused (status `refused: ...`) when
/// the tree is deeper than the backend's full stack; otherwise prepared and run once on a
/// few rays first, so that the time is the trace's, not the driver's first-use work (on
/// the CPU, there is none). `Err` is the run's status.
fn trace_timed(
    tracer: &dyn Tracer,
    rays: &[Ray],
    opts: &TraceOptions,
) -> Result<TraceOutput, String> {
    if let Err(TraceError::TooDeep { depth, max }) = tracer.supports(opts) {
        return Err(format!(
            "refused: depth {depth} > the kernel's {max}-entry stack"
        ));
    }
    let warm = &rays[..rays.len().min(64)];
    tracer
        .prepare(opts)
        .and_then(|_| tracer.trace(warm, opts))
        .map_err(|e| format!("pipeline failed: {e}"))?;
    tracer
        .trace(rays, opts)
        .map_err(|e| format!("trace failed: {e}"))
}

/// One backend's runs of `case`: every traversal and query traced on `tracer` and, when
/// `report`, judged (a device's hits against `twin`'s, the CPU twins', bit for bit) into
/// one [`RunReport`] each, labelled `backend`, in table order. Also returns the hits of
/// the runs that completed.
fn trace_all(
    tracer: &dyn Tracer,
    backend: &str,
    case: &Case,
    queries: &[Query],
    judge: &Judge<'_>,
    twin: Option<&Hits>,
    report: bool,
) -> (Vec<RunReport>, Hits) {
    let mut runs = Vec::new();
    let mut hits = Hits::new();
    let device = tracer.backend() != "cpu";
    for tr in traversals() {
        for &q in queries {
            let mut r = run_report(backend, tr, q);
            match trace_timed(tracer, &case.rays, &TraceOptions::new(tr, q)) {
                Ok(out) => {
                    r.trace_ms = out.wall_ms;
                    if device {
                        r.gpu_incomplete = Some(out.incomplete);
                    }
                    if report {
                        let cpu = twin.and_then(|t| t.get(&(tr, q))).map(Vec::as_slice);
                        runs.push(judge.evaluate(r, q, &out.hits, cpu));
                    }
                    hits.insert((tr, q), out.hits);
                }
                Err(status) => {
                    r.status = status;
                    if report {
                        runs.push(r);
                    }
                }
            }
        }
    }
    (runs, hits)
}

/// A device of our walks' rows: every walk and query, each compared with the CPU twins'
/// hits bit for bit; on a tree deeper than the full-stack kernel's stack, every walk but
/// the full stack, whose upload must be refused (`rep.full_stack` says what it did).
fn trace_device(
    device: &DeviceTracers,
    bvh: &FlatBvh,
    case: &Case,
    queries: &[Query],
    judge: &Judge<'_>,
    cpu_hits: &Hits,
    rep: &mut CaseReport,
) {
    let deep = bvh.depth() > FULL_STACK_SIZE;
    if deep {
        let what = match (device.open)(bvh, &traversals()) {
            Err(e @ TraceError::TooDeep { .. }) => format!("refused (as it must be): {e}"),
            Err(e) => format!("ERROR: the upload failed otherwise: {e}"),
            Ok(_) => format!(
                "ERROR: a tree {} deep was accepted for the {FULL_STACK_SIZE}-entry full-stack kernel",
                bvh.depth()
            ),
        };
        rep.full_stack.push((device.backend.clone(), what));
    }
    let walks: Vec<Traversal> = (traversals().into_iter())
        .filter(|t| !deep || *t != Traversal::FullStack)
        .collect();
    match (device.open)(bvh, &walks) {
        Err(e) => (rep.runs).extend(upload_failed(&device.backend, queries, &e)),
        Ok(tracer) => {
            let twin = Some(cpu_hits);
            let (runs, _) = trace_all(&*tracer, &device.backend, case, queries, judge, twin, true);
            rep.runs.extend(runs);
        }
    }
}

/// Builds the case's BVH (two levels when it has [`Case::instancing`]; an unusable
/// instance is the report's `error`, naming it), traces its rays with every traversal and
/// query on every backend (the CPU twins always, to compare the GPU with; reported when
/// `backends.cpu`; then wgpu and ash, each compared with the CPU twins bit for bit), and
/// judges every answer (see [`RunReport`]).
pub fn run_case(case: &Case, backends: &Backends) -> CaseReport {
    let start = Instant::now();
    let mut rep = CaseReport {
        name: case.name.clone(),
        description: case.description.clone(),
        triangles: case.tris.len(),
        rays: case.rays.len(),
        input: case.input.clone(),
        notes: case.notes.clone(),
        guaranteed: case.guaranteed,
        devices: backends.devices.iter().map(DeviceTracers::label).collect(),
        ..Default::default()
    };
    if let Some(curves) = &case.curves {
        curves::run(case, curves, backends, &mut rep);
        rep.elapsed_ms = ms(start);
        return rep;
    }
    if case.tris.is_empty() {
        rep.skipped = Some("skipped: no triangles (its inputs are absent; see the notes)".into());
        return rep;
    }
    let t = Instant::now();
    // Two levels when the case has instances (an unusable transform is an error naming
    // the instance, reported as the case's error), else one BVH over the triangles.
    let built = match &case.instancing {
        None => FlatBvh::build(&case.tris, &case.build).map_err(|e| e.to_string()),
        Some(inst) => InstancedBvh::build(&inst.meshes, inst.instances.clone(), &case.build)
            .map(|ib| ib.bvh().clone())
            .map_err(|e| format!("two levels: {e}")),
    };
    let mut bvh = match built {
        Ok(b) => b.with_wide(),
        Err(e) => {
            rep.error = Some(format!("build failed: {e}"));
            return rep;
        }
    };
    if let Some(m) = &case.motion {
        motion::place_at_time(&mut bvh, m);
    }
    rep.build_ms = ms(t);
    rep.nodes = bvh.nodes().len();
    rep.depth = bvh.depth();

    let t = Instant::now();
    let geo = Geometry::new(case, &bvh);
    let sample = sample_indices(case.rays.len(), case.oracle_budget.max(1));
    let traced: Vec<Option<Ray>> = case.rays.iter().map(as_traced).collect();
    let oracle: Vec<OracleHit> = sample
        .par_iter()
        .map(|&i| match &traced[i] {
            Some(r) => geo.closest(r),
            None => geo.closest(&case.rays[i]),
        })
        .collect();
    let brute: Vec<Hit> = sample
        .par_iter()
        .map(|&i| brute_force(&bvh, &case.rays[i], Precision::WatertightF32))
        .collect();
    rep.oracle_ms = ms(t);
    rep.oracle_sample = sample.len();
    let mut position = vec![usize::MAX; case.rays.len()];
    for (k, &i) in sample.iter().enumerate() {
        position[i] = k;
    }
    let judge = Judge {
        case,
        geo,
        sample,
        position,
        oracle,
        brute,
        zero_area: case.tris.iter().map(is_zero_area).collect(),
        traced,
    };
    let queries: &[Query] = if case.any_hit {
        &[Query::Closest, Query::Any]
    } else {
        &[Query::Closest]
    };

    if let Some(m) = &case.motion {
        motion::run(case, m, queries, &judge, backends, &mut rep);
        rep.elapsed_ms = ms(start);
        return rep;
    }

    // The CPU twins first (always: the GPU is compared with them), then the GPU kernels,
    // both through the one `Tracer` interface.
    let cpu = CpuTracer::new(&bvh);
    let (runs, cpu_hits) = trace_all(&cpu, "cpu", case, queries, &judge, None, backends.cpu);
    rep.runs.extend(runs);
    if backends.cpu {
        match trace_cpu_layout(&bvh, case, queries, &judge, &cpu_hits) {
            Ok(runs) => rep.runs.extend(runs),
            Err(note) => rep.notes.push(note),
        }
    }

    for device in &backends.devices {
        if device.bit_for_bit {
            trace_device(device, &bvh, case, queries, &judge, &cpu_hits, &mut rep);
        } else {
            (rep.runs).extend(trace_driver_walk(device, &bvh, case, queries, &judge));
        }
    }
    rep.elapsed_ms = ms(start);
    rep
}

/// [`run_case`] on its own thread, given up on after `timeout` (the thread is left to
/// finish on its own; the error says which case hung).
pub fn run_case_with_timeout(
    case: &Case,
    backends: &Backends,
    timeout: Duration,
) -> Result<CaseReport, String> {
    let (tx, rx) = mpsc::channel();
    let (case_owned, b) = (case.clone(), backends.clone());
    let name = case.name.clone();
    std::thread::Builder::new()
        .name(format!("stress {name}"))
        .spawn(move || {
            let _ = tx.send(run_case(&case_owned, &b));
        })
        .map_err(|e| format!("{name}: could not start a thread: {e}"))?;
    match rx.recv_timeout(timeout) {
        Ok(r) => Ok(r),
        Err(mpsc::RecvTimeoutError::Timeout) => {
            Err(format!("{name}: no result after {timeout:?} (hang?)"))
        }
        Err(mpsc::RecvTimeoutError::Disconnected) => Err(format!("{name}: the case panicked")),
    }
}

#[cfg(test)]
mod tests {
    use super::{CPU_LAYOUT_ROWS, CaseReport, RunReport};

    /// Beyond the guaranteed range the CPU layout's differences from the full stack are
    /// measured, not required; a GPU's from its CPU twin always are, and in range both.
    #[test]
    fn layout_differences_fail_only_in_the_guaranteed_range() {
        let case = |guaranteed: bool, backend: &str| CaseReport {
            guaranteed,
            runs: vec![RunReport {
                backend: backend.into(),
                parity_mismatches: Some(2),
                ..Default::default()
            }],
            ..Default::default()
        };
        assert!(case(false, CPU_LAYOUT_ROWS).clean());
        assert!(!case(true, CPU_LAYOUT_ROWS).clean());
        assert!(!case(false, "gpu").clean());
        assert!(!case(true, "gpu").clean());
        let nan = CaseReport {
            runs: vec![RunReport {
                backend: CPU_LAYOUT_ROWS.into(),
                nan_outputs: 1,
                ..Default::default()
            }],
            ..case(false, CPU_LAYOUT_ROWS)
        };
        assert!(!nan.clean());
    }
}
