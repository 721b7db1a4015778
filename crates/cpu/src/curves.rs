//! Curves in the CPU layout: a [`CurveBvh`]'s tree (triangles and curve segments in one
//! tree) collapsed into 8-wide nodes as a triangle tree is ([`crate::layout`]), each leaf
//! its primitives eight to a node, each slot the primitive's own box. The walk is the
//! static layout's ([`crate::single`]: the eight child boxes tested together, children
//! visited nearest first); at a leaf, the primitives' boxes are tested eight at a time with
//! the same box test, and each primitive whose box the ray enters before its best hit is
//! tested with the core's own test ([`CurveBvh::test`]), segments and triangles alike.
//!
//! Each child's box is its binary node's, and a primitive's box lies inside its binary
//! leaf's, so every primitive the core walk ([`CurveBvh::trace`]) would take is tested, at
//! a best hit no nearer than the core walk's: the closest hit is the core walk's, bit for
//! bit, under the core walks' one exception (where f32 cannot order two hits, either may
//! rightly be kept). Any-hit queries agree on hit or miss.

use std::cell::OnceCell;
use std::sync::Arc;

use bvhtrace_core::{CurveBvh, CurveRay, Hit, Query, Ray};
use rayon::prelude::*;

use crate::Isa;
use crate::lanes::{self, Lanes, Wide};
use crate::layout::{
    ConvertError, LeafBoxOf, Level, Node8, WIDTH, collapse, leaf_range, place_leaves_of,
    subtree_spans,
};
use crate::plan::Plan;
use crate::single::{self, Best, Entry, Site, WalkTree, untraced};
use crate::tests4::{self, Prepared, RayAt, RayLanes, SceneBox, ShearLanes, box8};

/// Up to eight primitives of a leaf as a node: each slot's box the primitive's own, its
/// child the primitive's id, tested together with the walk's own box test ([`box8`]).
fn prim_node(bvh: &CurveBvh, prims: &[u32]) -> Node8 {
    let mut n = Node8::EMPTY;
    for (i, &prim) in prims.iter().enumerate() {
        let b = bvh.prim_box(prim);
        for a in 0..3 {
            n.planes[2 * a][i] = b.min[a];
            n.planes[2 * a + 1][i] = b.max[a];
        }
        n.child[i] = prim;
        n.used |= 1 << i;
    }
    n
}

/// A [`CurveBvh`] in the CPU layout (see the module docs), converted by
/// [`CurveCpuBvh::from_curves`].
#[derive(Clone, Debug)]
pub struct CurveCpuBvh {
    bvh: Arc<CurveBvh>,
    nodes: Vec<Node8>,
    /// Each leaf's primitives, eight to a node ([`prim_node`]).
    blocks: Vec<Node8>,
    depth: u32,
    /// A box around the root's boxes: rays that miss it take no walk.
    scene_box: Option<SceneBox>,
}

impl CurveCpuBvh {
    /// Converts `bvh`'s tree; the primitives stay `bvh`'s (shared, not copied).
    pub fn from_curves(bvh: Arc<CurveBvh>) -> Result<CurveCpuBvh, ConvertError> {
        let fnodes = bvh.nodes();
        let order = bvh.leaf_prims();
        let spans = subtree_spans(fnodes);
        // Each slot's binary leaf box: a run split off a long leaf is bounded by it.
        let leaf_box = LeafBoxOf::new(fnodes, order.len());
        let mut nodes = Vec::new();
        let mut leaves = Vec::new();
        let depth = if fnodes.is_empty() {
            0
        } else {
            let mut no_hook = |_, _, _| {};
            collapse(
                fnodes,
                &spans,
                &|t| leaf_box.get(t),
                0,
                Level::Mesh,
                &mut nodes,
                &mut leaves,
                &mut no_hook,
                Some(&Plan::new(fnodes, &spans)),
            )?
        };
        place_leaves_of(&mut nodes, &leaves, WIDTH as u32)?;
        let blocks = leaves
            .par_iter()
            .flat_map_iter(|l| {
                let prims = &order[l.first_tri as usize..(l.first_tri + l.tris) as usize];
                prims.chunks(WIDTH).map(|c| prim_node(&bvh, c))
            })
            .collect();
        Ok(CurveCpuBvh {
            scene_box: nodes.first().and_then(SceneBox::around),
            bvh,
            nodes,
            blocks,
            depth,
        })
    }

    /// The tree and primitives converted.
    pub fn curves(&self) -> &Arc<CurveBvh> {
        &self.bvh
    }

    /// Levels of wide nodes (the root's counted).
    pub fn depth(&self) -> u32 {
        self.depth
    }

    /// Bytes of wide nodes and of leaf blocks (the primitives are the core tree's).
    pub fn byte_sizes(&self) -> (usize, usize) {
        (
            std::mem::size_of_val(self.nodes.as_slice()),
            std::mem::size_of_val(self.blocks.as_slice()),
        )
    }

    /// Traces `rays` on all threads of the current rayon pool, with the fastest
    /// instruction set this CPU has: the closest hit ([`CurveBvh::trace`]'s) or any hit.
    pub fn trace_rays(&self, rays: &[Ray], query: Query) -> Vec<Hit> {
        self.trace_rays_with(rays, query, Isa::detect())
    }

    /// [`CurveCpuBvh::trace_rays`] with the instruction set `isa` (or the fastest this CPU
    /// has, when it lacks `isa`): the answers are the same whichever runs.
    pub fn trace_rays_with(&self, rays: &[Ray], query: Query, isa: Isa) -> Vec<Hit> {
        crate::moving::par_runs(rays.len(), |at, h| self.trace_run(&rays[at], query, isa, h))
    }

    /// One thread's run of rays into `hits`.
    fn trace_run(&self, rays: &[Ray], query: Query, isa: Isa, hits: &mut [Hit]) {
        let mut stack = vec![Entry::default(); (WIDTH - 1) * self.depth as usize + 4];
        let s = stack.as_mut_slice();
        type P = lanes::Portable;
        match isa.or_available() {
            Isa::Portable => run::<P, lanes::Pair<P>>(self, rays, query, hits, s),
            #[cfg(target_arch = "x86_64")]
            Isa::Sse2 => run::<lanes::Sse, lanes::Pair<lanes::Sse>>(self, rays, query, hits, s),
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `or_available` returned Avx2, so the CPU has what `Isa::Avx2` needs.
            Isa::Avx2 => unsafe { run_avx2(self, rays, query, hits, s) },
            #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
            Isa::Simd128 => {
                run::<lanes::Simd128, lanes::Pair<lanes::Simd128>>(self, rays, query, hits, s)
            }
            #[allow(unreachable_patterns)]
            _ => unreachable!("or_available gives only what this target compiles"),
        }
    }
}

/// The tree as one ray's walk reads it: the ray, made ready for the core's tests at its
/// first leaf (many rays reach none).
struct At<'a> {
    bvh: &'a CurveCpuBvh,
    src: &'a Ray,
    ray: OnceCell<CurveRay>,
}

impl WalkTree for At<'_> {
    type Node<'b>
        = &'b Node8
    where
        Self: 'b;

    #[inline(always)]
    fn node(&self, i: u32) -> &Node8 {
        &self.bvh.nodes[i as usize]
    }

    #[inline(always)]
    fn fetch(&self, c: u32) {
        #[cfg(target_arch = "x86_64")]
        {
            use crate::layout::LEAF;
            use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
            // Wrapping arithmetic, as `c` may be `EMPTY`; a prefetch never faults.
            let (at, lines) = if c & LEAF != 0 {
                let b = self.bvh.blocks.as_ptr().wrapping_add(leaf_range(c).0);
                (b.cast::<i8>(), 4)
            } else {
                (self.bvh.nodes.as_ptr().wrapping_add(c as usize).cast(), 4)
            };
            for line in 0..lines {
                // SAFETY: a prefetch only hints the cache; any address is allowed.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(at.wrapping_add(64 * line)) };
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = c;
    }

    /// Each primitive whose own box the ray enters before the best (the walk's box test,
    /// eight at a time) is tested with the core's test, in the leaf's order.
    #[inline(always)]
    fn leaf<
        L: Lanes,
        W: Wide,
        const ANY: bool,
        const MASKED: bool,
        const SIGNED: bool,
        const PARALLEL: bool,
        const KZ: usize,
        const OCT: usize,
    >(
        &self,
        q: &RayLanes<L, W>,
        _t_min: L,
        _s: &ShearLanes<L>,
        _ray: RayAt<'_>,
        child: u32,
        best: &mut Best,
        _at: Site<'_>,
    ) -> bool {
        let (first, count) = leaf_range(child);
        let ray = self.ray.get_or_init(|| self.bvh.bvh.prepare(self.src));
        // Index loops: an iterator's `next` may be compiled apart from an AVX2 caller.
        for k in first..first + count {
            let n = &self.bvh.blocks[k];
            let culled = !ANY && best.found;
            let mut hit = box8::<L, W, SIGNED, PARALLEL, KZ, OCT>(n, q, best.t, culled).hit;
            while hit != 0 {
                let i = hit.trailing_zeros() as usize;
                hit &= hit - 1;
                if self.bvh.bvh.test(n.child[i], ray, best) && ANY {
                    return true;
                }
            }
        }
        false
    }
}

/// The walks over `rays`, monomorphised for the lanes and the query.
#[inline(always)]
fn run<L: Lanes, W: Wide>(
    bvh: &CurveCpuBvh,
    rays: &[Ray],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    match query {
        Query::Closest => run_as::<L, W, false>(bvh, rays, hits, stack),
        Query::Any => run_as::<L, W, true>(bvh, rays, hits, stack),
    }
}

/// [`run`] for one query: rays prepared eight at a time for the boxes, then each walked.
#[inline(always)]
fn run_as<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CurveCpuBvh,
    rays: &[Ray],
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    // Plain loops, no closures: a closure is compiled apart from the AVX2 caller.
    let mut start = 0;
    while start < rays.len() {
        let end = (start + tests4::RAYS).min(rays.len());
        let group = &rays[start..end];
        let mut p = Prepared::for_boxes::<W>(group);
        let enter = p.may_enter::<W>(bvh.scene_box.as_ref());
        // The walk makes a triangle shear at a ray's first leaf, though curve leaves do
        // not read it.
        if p.valid & enter != 0 {
            p.shear::<W>();
        }
        for (i, ray) in group.iter().enumerate() {
            hits[start + i] = if p.valid >> i & 1 == 0 {
                untraced(ray)
            } else if enter >> i & 1 == 0 || bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
                Best::start(ray).into_hit()
            } else {
                let at = At {
                    bvh,
                    src: ray,
                    ray: OnceCell::new(),
                };
                let best = Best::start(ray);
                single::mesh::<_, L, W, ANY, false>(&at, ray, &p, i, best, 0, Site::PLAIN, stack)
                    .0
                    .into_hit()
            };
        }
        start = end;
    }
}

/// [`run`] with SSE lanes and AVX lanes for the boxes, compiled with AVX2 enabled.
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT ([`Isa::Avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
unsafe fn run_avx2(
    bvh: &CurveCpuBvh,
    rays: &[Ray],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    run::<lanes::Sse, lanes::Avx8>(bvh, rays, query, hits, stack)
}
