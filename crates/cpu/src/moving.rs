//! Moving meshes in the CPU layout: a [`MotionBvh`] collapsed into 8-wide nodes as a
//! static tree is ([`crate::layout`]), with every node's child boxes and every block's
//! corners kept at each time step. A ray's walk interpolates them at its time as the core's
//! moving walk does (`lerp_box` for boxes, `lerp_point` for corners: the same f32
//! operations, lane by lane) and tests them with the static walk's SIMD box and triangle
//! tests. Each child's interpolated box is its binary node's, so the closest hit is
//! `MotionBvh::trace`'s, bit for bit, under the static layout's one exception (see the
//! crate docs); any-hit queries agree on hit or miss.
//!
//! With [`TimeBounds::Merged`] the nodes keep their boxes over the whole shutter, as the
//! core tree does, and only the corners move.

use bvhtrace_core::motion::{MotionBvh, TimeBounds, lerp_box, time_segment};
use bvhtrace_core::{Aabb, FlatTriangle, Hit, Query, Ray};
use rayon::prelude::*;

use crate::Isa;
use crate::lanes::{self, Lanes, Wide};
use crate::layout::{
    BLOCK, ConvertError, Level, Node8, PendingLeaf, Src, Tri4, WIDTH, collapse, leaf_of_triangles,
    place_leaves, subtree_spans,
};
use crate::plan::Plan;
use crate::single::{self, Best, BlockTree, Entry, Site, WalkTree, untraced};
use crate::tests4::{self, Prepared, SceneBox};

/// A node's eight child boxes at one time step, plane by plane (as [`Node8::planes`]).
type Planes = [[f32; WIDTH]; 6];

/// A [`MotionBvh`] in the CPU layout (see the module docs), converted by
/// [`MovingCpuBvh::from_motion`].
#[derive(Clone, Debug)]
pub struct MovingCpuBvh {
    /// The nodes: children, and their boxes over the whole shutter.
    pub(crate) nodes: Vec<Node8>,
    /// Node `i`'s child boxes at step `k`: `step_planes[i * steps + k]` (linear bounds).
    step_planes: Vec<Planes>,
    /// Block `b` at step `k`: `blocks[b * steps + k]`.
    blocks: Vec<Tri4>,
    /// Each block lane's binary leaf, an index into `leaf_boxes` by step.
    lane_leaf: Vec<[u32; BLOCK]>,
    /// Binary node `i`'s box at step `k`: `leaf_boxes[i * steps + k]` (linear bounds), or
    /// over the shutter: `leaf_boxes[i]` (merged).
    leaf_boxes: Vec<Aabb>,
    pub(crate) steps: usize,
    pub(crate) bounds: TimeBounds,
    pub(crate) depth: u32,
    triangles: usize,
    /// A box around the root's boxes at every time: rays that miss it take no walk.
    pub(crate) scene_box: Option<SceneBox>,
}

impl MovingCpuBvh {
    /// Converts `m`. The blocks are written in parallel on the current rayon pool.
    pub fn from_motion(m: &MotionBvh) -> Result<MovingCpuBvh, ConvertError> {
        let tree = MovingTree {
            nodes: m.nodes(),
            step_boxes: m.step_boxes(),
            steps: m.time_steps(),
            bounds: m.time_bounds(),
        };
        MovingCpuBvh::convert(&tree, Level::Mesh, m.triangles(), m.triangle_count())
    }

    /// Converts `tree` at `level`: a mesh over `count` triangles (`tris`, every step's in
    /// turn), or a top level whose leaves are instance leaves (no triangles).
    pub(crate) fn convert(
        tree: &MovingTree<'_>,
        level: Level,
        tris: &[FlatTriangle],
        count: usize,
    ) -> Result<MovingCpuBvh, ConvertError> {
        let (fnodes, steps, bounds, step_boxes) =
            (tree.nodes, tree.steps, tree.bounds, tree.step_boxes);
        let spans = subtree_spans(fnodes);
        let leaf_of = leaf_of_triangles(fnodes, count, |i, _| i, 0);
        let mut nodes = Vec::new();
        let mut leaves = Vec::new();
        // Each slot's binary node: a run split off a long leaf stands for the leaf.
        let mut origin: Vec<[u32; WIDTH]> = Vec::new();
        let mut on_slot = |node: u32, slot: usize, src: Src| {
            let node = node as usize;
            if origin.len() <= node {
                origin.resize(node + 1, [0; WIDTH]);
            }
            origin[node][slot] = match src {
                Src::Node(i) => i,
                Src::Run(first, _) => leaf_of[first as usize],
            };
        };
        let depth = if fnodes.is_empty() {
            0
        } else {
            let root = 0;
            collapse(
                fnodes,
                &spans,
                &|t| fnodes[leaf_of[t] as usize].aabb(),
                root,
                level,
                &mut nodes,
                &mut leaves,
                &mut on_slot,
                (level == Level::Mesh)
                    .then(|| Plan::new(fnodes, &spans))
                    .as_ref(),
            )?
        };
        origin.resize(nodes.len(), [0; WIDTH]);
        let box_at = |i: u32, k: usize| step_boxes[i as usize * steps + k].aabb();
        let step_planes = match bounds {
            TimeBounds::Merged => Vec::new(),
            TimeBounds::Linear => (nodes.iter().zip(&origin))
                .flat_map(|(n, o)| (0..steps).map(move |k| (n, o, k)))
                .map(|(n, o, k)| {
                    let mut planes = [[0.0; WIDTH]; 6];
                    for slot in (0..WIDTH).filter(|&s| n.used >> s & 1 != 0) {
                        let b = box_at(o[slot], k);
                        for a in 0..3 {
                            planes[2 * a][slot] = b.min[a];
                            planes[2 * a + 1][slot] = b.max[a];
                        }
                    }
                    planes
                })
                .collect(),
        };
        let leaf_boxes = match bounds {
            TimeBounds::Merged => fnodes.iter().map(|n| n.aabb()).collect(),
            TimeBounds::Linear => step_boxes.iter().map(|b| b.aabb()).collect(),
        };
        let scene_box = match bounds {
            TimeBounds::Merged => nodes.first().and_then(SceneBox::around),
            TimeBounds::Linear => {
                around_steps(nodes.first(), &step_planes[..steps.min(step_planes.len())])
            }
        };
        let (blocks, lane_leaf) = write_blocks(&mut nodes, &leaves, tris, count, steps, &leaf_of)?;
        Ok(MovingCpuBvh {
            nodes,
            step_planes,
            blocks,
            lane_leaf,
            leaf_boxes,
            steps,
            bounds,
            depth,
            triangles: count,
            scene_box,
        })
    }

    /// Number of time steps.
    pub fn time_steps(&self) -> usize {
        self.steps
    }

    /// How the nodes bound time (the converted tree's).
    pub fn time_bounds(&self) -> TimeBounds {
        self.bounds
    }

    /// Levels of nodes on the longest root-to-leaf path.
    pub fn depth(&self) -> u32 {
        self.depth
    }

    /// Triangles of the tree it was converted from.
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// Bytes of the nodes with their step boxes, and of the blocks at every step with
    /// their leaf boxes.
    pub fn byte_sizes(&self) -> (usize, usize) {
        use std::mem::size_of_val;
        (
            size_of_val(self.nodes.as_slice()) + size_of_val(self.step_planes.as_slice()),
            size_of_val(self.blocks.as_slice())
                + size_of_val(self.lane_leaf.as_slice())
                + size_of_val(self.leaf_boxes.as_slice()),
        )
    }

    /// Traces `rays[i]` at `times[i]` (clamped to `[0, 1]`; a NaN time is an invalid ray)
    /// on all threads of the current rayon pool, with the fastest instruction set this CPU
    /// has: the closest hit (`MotionBvh::trace`'s) or any hit.
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace_rays(&self, rays: &[Ray], times: &[f32], query: Query) -> Vec<Hit> {
        self.trace_rays_with(rays, times, query, Isa::detect())
    }

    /// [`MovingCpuBvh::trace_rays`] with the instruction set `isa` (or the fastest this CPU
    /// has, when it lacks `isa`): the answers are the same whichever runs.
    ///
    /// # Panics
    /// When the two slices differ in length.
    pub fn trace_rays_with(&self, rays: &[Ray], times: &[f32], query: Query, isa: Isa) -> Vec<Hit> {
        in_runs(rays, times, |r, t, h| self.trace_run(r, t, query, isa, h))
    }

    /// One thread's run of rays into `hits`.
    fn trace_run(&self, rays: &[Ray], times: &[f32], query: Query, isa: Isa, hits: &mut [Hit]) {
        let mut stack = vec![Entry::default(); (WIDTH - 1) * self.depth as usize + 4];
        let s = stack.as_mut_slice();
        type P = lanes::Portable;
        type PP = lanes::Pair<P>;
        match isa.or_available() {
            Isa::Portable => run::<P, PP>(self, rays, times, query, hits, s),
            #[cfg(target_arch = "x86_64")]
            Isa::Sse2 => {
                run::<lanes::Sse, lanes::Pair<lanes::Sse>>(self, rays, times, query, hits, s)
            }
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `or_available` returned Avx2, so the CPU has what `Isa::Avx2` needs.
            Isa::Avx2 => unsafe { run_avx2(self, rays, times, query, hits, s) },
            #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
            Isa::Simd128 => run::<lanes::Simd128, lanes::Pair<lanes::Simd128>>(
                self, rays, times, query, hits, s,
            ),
            #[allow(unreachable_patterns)]
            _ => unreachable!("or_available gives only what this target compiles"),
        }
    }
}

/// A box around `root`'s boxes at every step (`steps`, its planes at each) and at every
/// time between: an interpolated plane lies within the rounding of its two steps' range
/// (`(1 - f) + f` is at most an ulp from 1) less the slack of `2^-20` of the magnitude,
/// so the steps' box widened by `2^-18` of the largest magnitude on each axis holds it.
fn around_steps(root: Option<&Node8>, steps: &[Planes]) -> Option<SceneBox> {
    let mut union = *root?;
    for (k, planes) in steps.iter().enumerate() {
        for slot in 0..WIDTH {
            for a in 0..3 {
                let (lo, hi) = (planes[2 * a][slot], planes[2 * a + 1][slot]);
                let u = &mut union.planes;
                if k == 0 {
                    (u[2 * a][slot], u[2 * a + 1][slot]) = (lo, hi);
                } else {
                    u[2 * a][slot] = u[2 * a][slot].min(lo);
                    u[2 * a + 1][slot] = u[2 * a + 1][slot].max(hi);
                }
            }
        }
    }
    let mut b = SceneBox::around(&union)?;
    for a in 0..3 {
        let slack = b.lo[a].abs().max(b.hi[a].abs()) * (1.0 / (1 << 18) as f32);
        (b.lo[a], b.hi[a]) = (b.lo[a] - slack, b.hi[a] + slack);
    }
    Some(b)
}

/// `run(rays, times, hits)` over runs of the rays in parallel ([`par_runs`]).
///
/// # Panics
/// When the two slices differ in length.
pub(crate) fn in_runs(
    rays: &[Ray],
    times: &[f32],
    run: impl Fn(&[Ray], &[f32], &mut [Hit]) + Sync,
) -> Vec<Hit> {
    assert_eq!(rays.len(), times.len(), "one time per ray");
    par_runs(rays.len(), |at, h| run(&rays[at.clone()], &times[at], h))
}

/// The answers for `n` rays, `run(range, hits)` filling those of each run of 256 rays in
/// parallel on the current rayon pool, each run a thread's (one stack allocated per run).
pub(crate) fn par_runs(
    n: usize,
    run: impl Fn(std::ops::Range<usize>, &mut [Hit]) + Sync,
) -> Vec<Hit> {
    const RUN: usize = 256;
    let mut hits = vec![Hit::miss(0.0); n];
    hits.par_chunks_mut(RUN)
        .enumerate()
        .for_each(|(k, h)| run(k * RUN..k * RUN + h.len(), h));
    hits
}

/// Allocates every leaf's blocks in leaf order, sets the leaf references, and writes each
/// block at every step (in parallel), with its lanes' binary leaves.
fn write_blocks(
    nodes: &mut [Node8],
    leaves: &[PendingLeaf],
    tris: &[FlatTriangle],
    count: usize,
    steps: usize,
    leaf_of: &[u32],
) -> Result<(Vec<Tri4>, Vec<[u32; BLOCK]>), ConvertError> {
    let total = place_leaves(nodes, leaves)?;
    // One block per leaf's run of four, in the same order: (first triangle, triangles).
    let mut runs = Vec::with_capacity(total);
    for l in leaves {
        for b in 0..l.tris.div_ceil(BLOCK as u32) {
            let first = l.first_tri + b * BLOCK as u32;
            runs.push((
                first as usize,
                (l.tris - b * BLOCK as u32).min(BLOCK as u32) as usize,
            ));
        }
    }
    let blocks: Vec<Tri4> = runs
        .par_iter()
        .with_min_len(1024)
        .flat_map_iter(|&(first, n)| {
            (0..steps).map(move |k| Tri4::of(&tris[k * count + first..][..n]))
        })
        .collect();
    let lane_leaf = runs
        .iter()
        .map(|&(first, n)| std::array::from_fn(|lane| leaf_of[first + lane.min(n - 1)]))
        .collect();
    Ok((blocks, lane_leaf))
}

/// `(1 - f) a + f b` per plane, widened by `2^-20` of the largest magnitude of the two
/// boxes on the axis: `lerp_box`'s operations in its order, lane by lane (glam's `max`
/// is `if a > b { a } else { b }`, as here).
#[inline(always)]
fn lerp_planes(a: &Planes, b: &Planes, f: f32) -> Planes {
    let g = 1.0 - f;
    let max = |x: f32, y: f32| if x > y { x } else { y };
    let mut out = [[0.0; WIDTH]; 6];
    for axis in 0..3 {
        let (lo, hi) = (2 * axis, 2 * axis + 1);
        for l in 0..WIDTH {
            let scale = max(
                max(a[lo][l].abs(), a[hi][l].abs()),
                max(b[lo][l].abs(), b[hi][l].abs()),
            );
            let slack = scale * (1.0 / (1 << 20) as f32);
            out[lo][l] = g * a[lo][l] + f * b[lo][l] - slack;
            out[hi][l] = g * a[hi][l] + f * b[hi][l] + slack;
        }
    }
    out
}

/// Block `a` moved `f` of the way to `b`, corner by corner: `lerp_point`'s operations,
/// `((1 - f) a + f b).clamp(a.min(b), a.max(b))` with glam's `min`, `max` and `clamp`.
#[inline(always)]
fn lerp_block(a: &Tri4, b: &Tri4, f: f32) -> Tri4 {
    let g = 1.0 - f;
    let mut out = *a;
    for c in 0..3 {
        for axis in 0..3 {
            for l in 0..BLOCK {
                let (x, y) = (a.v[c][axis][l], b.v[c][axis][l]);
                let lo = if x < y { x } else { y };
                let hi = if x > y { x } else { y };
                let p = g * x + f * y;
                let p = if p > lo { p } else { lo };
                out.v[c][axis][l] = if p < hi { p } else { hi };
            }
        }
    }
    out
}

/// A binary moving tree to convert: its nodes, their boxes at every step, and how they
/// bound time.
pub(crate) struct MovingTree<'a> {
    pub nodes: &'a [bvhtrace_core::FlatNode],
    pub step_boxes: &'a [bvhtrace_core::motion::MotionBox],
    pub steps: usize,
    pub bounds: TimeBounds,
}

/// The tree at one ray's time: segment `s` (steps `s` and `s + 1`), fraction `f`.
#[derive(Clone, Copy)]
pub(crate) struct At<'a, const LINEAR: bool> {
    pub bvh: &'a MovingCpuBvh,
    pub s: usize,
    pub f: f32,
}

impl<const LINEAR: bool> BlockTree for At<'_, LINEAR> {
    type Block<'b>
        = Tri4
    where
        Self: 'b;

    #[inline(always)]
    fn block(&self, b: usize) -> Tri4 {
        let at = &self.bvh.blocks[b * self.bvh.steps + self.s..][..2];
        lerp_block(&at[0], &at[1], self.f)
    }

    #[inline(always)]
    fn leaf_box(&self, block: usize, i: usize) -> Aabb {
        let leaf = self.bvh.lane_leaf[block][i] as usize;
        if !LINEAR {
            return self.bvh.leaf_boxes[leaf];
        }
        let at = leaf * self.bvh.steps + self.s;
        lerp_box(
            &self.bvh.leaf_boxes[at],
            &self.bvh.leaf_boxes[at + 1],
            self.f,
        )
    }
}

impl<const LINEAR: bool> WalkTree for At<'_, LINEAR> {
    type Node<'b>
        = Node8
    where
        Self: 'b;

    single::block_leaf!();

    #[inline(always)]
    fn node(&self, i: u32) -> Node8 {
        let n = &self.bvh.nodes[i as usize];
        if !LINEAR {
            return *n;
        }
        let at = i as usize * self.bvh.steps + self.s;
        let steps = &self.bvh.step_planes[at..at + 2];
        Node8 {
            planes: lerp_planes(&steps[0], &steps[1], self.f),
            ..*n
        }
    }

    #[inline(always)]
    fn fetch(&self, c: u32) {
        #[cfg(target_arch = "x86_64")]
        {
            use crate::layout::{LEAF, leaf_range};
            use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
            let steps = self.bvh.steps;
            // The two steps the walk will read: planes, or blocks. Wrapping arithmetic, as
            // `c` may be `EMPTY`; a prefetch reads nothing and never faults.
            let (at, lines) = if c & LEAF != 0 {
                let b = leaf_range(c).0 * steps + self.s;
                (self.bvh.blocks.as_ptr().wrapping_add(b).cast::<i8>(), 5)
            } else if LINEAR {
                let p = c as usize * steps + self.s;
                (
                    self.bvh.step_planes.as_ptr().wrapping_add(p).cast::<i8>(),
                    6,
                )
            } else {
                (
                    self.bvh
                        .nodes
                        .as_ptr()
                        .wrapping_add(c as usize)
                        .cast::<i8>(),
                    4,
                )
            };
            for line in 0..lines {
                // SAFETY: a prefetch only hints the cache; any address is allowed.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(at.wrapping_add(64 * line)) };
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = c;
    }
}

/// The walks over `rays` at `times`, monomorphised for the lanes and the query.
#[inline(always)]
fn run<L: Lanes, W: Wide>(
    bvh: &MovingCpuBvh,
    rays: &[Ray],
    times: &[f32],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    let linear = bvh.bounds == TimeBounds::Linear;
    match (query, linear) {
        (Query::Closest, true) => run_as::<L, W, false, true>(bvh, rays, times, hits, stack),
        (Query::Closest, false) => run_as::<L, W, false, false>(bvh, rays, times, hits, stack),
        (Query::Any, true) => run_as::<L, W, true, true>(bvh, rays, times, hits, stack),
        (Query::Any, false) => run_as::<L, W, true, false>(bvh, rays, times, hits, stack),
    }
}

/// [`run`] for one query and one kind of bounds: rays prepared eight at a time, then each
/// walked at its time.
#[inline(always)]
fn run_as<L: Lanes, W: Wide, const ANY: bool, const LINEAR: bool>(
    bvh: &MovingCpuBvh,
    rays: &[Ray],
    times: &[f32],
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    // Plain loops, no closures: a closure is compiled apart from the AVX2 caller (as
    // `moving_instances::run_as`' twin of this loop).
    let mut start = 0;
    while start < rays.len() {
        let end = (start + tests4::RAYS).min(rays.len());
        let group = &rays[start..end];
        let mut p = Prepared::for_boxes::<W>(group);
        let enter = p.may_enter::<W>(bvh.scene_box.as_ref());
        if p.valid & enter != 0 {
            p.shear::<W>();
        }
        for (i, ray) in group.iter().enumerate() {
            let time = times[start + i];
            hits[start + i] = if p.valid >> i & 1 == 0 || time.is_nan() {
                untraced(ray)
            } else if enter >> i & 1 == 0 || bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
                Best::start(ray).into_hit()
            } else {
                let (s, f) = time_segment(time, bvh.steps);
                let at = At::<LINEAR> { bvh, s, f };
                let best = Best::start(ray);
                single::mesh::<_, L, W, ANY, false>(&at, ray, &p, i, best, 0, Site::PLAIN, stack)
                    .0
                    .into_hit()
            };
        }
        start = end;
    }
}

/// [`run`] with SSE lanes for the triangles and AVX lanes for the boxes, compiled with
/// AVX2 enabled.
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT ([`Isa::Avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
unsafe fn run_avx2(
    bvh: &MovingCpuBvh,
    rays: &[Ray],
    times: &[f32],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    run::<lanes::Sse, lanes::Avx8>(bvh, rays, times, query, hits, stack)
}
