//! Two levels: the top level's nodes walked with the world ray as a mesh's are, and at an
//! instance leaf whose box the ray hits, the instance entered as the core walks enter it
//! (`Space::enter_instance` in `bvhtrace_core::traverse`): passed through when its
//! visibility mask shares no bit with the ray's, else the ray taken into the mesh's space
//! by the core's own `FlatInstance::ray_to_object` (the same f32 products and sums), passed
//! over when that ray is not valid, and prepared as `PreparedRay::new` prepares it. The
//! mesh is then walked from the best hit so far, its hits reporting the instance's
//! primitive base plus the mesh's id, so that `t` compares across instances (the same
//! parametrisation) and the tie rule compares global ids, as in the core walks.

use std::marker::PhantomData;

use bvhtrace_core::{Hit, Ray};

use crate::lanes::{Lanes, Wide};
use crate::layout::{CpuBvh, LEAF};
use crate::single::{self, Best, Entry, Site, order, untraced};
use crate::tests4::{MINMAX, Prepared, RayLanes, box8, still_hit};

/// How the top-level walk walks a mesh: a call, not inlined, since each of the nine
/// top-level walks (per dominant axis and ray kind) would otherwise hold the nine mesh
/// walks; the object ray's walk is chosen at each instance.
pub(crate) trait MeshWalk {
    /// The walk of `object` (the ray in the mesh's space) from `start`, from `best`, at
    /// `at`; `stack` is what the top-level walk has not used. Returns the best hit, and
    /// true when an any-hit query stopped.
    fn walk<const ANY: bool, const MASKED: bool>(
        bvh: &CpuBvh,
        object: &Ray,
        best: Best,
        start: u32,
        at: Site<'_>,
        stack: &mut [Entry],
    ) -> (Best, bool);
}

/// The mesh walks with triangle lanes `L` and box lanes `W`, compiled as the caller is.
pub(crate) struct Plain<L, W>(PhantomData<(L, W)>);

impl<L: Lanes, W: Wide> MeshWalk for Plain<L, W> {
    #[inline(never)]
    fn walk<const ANY: bool, const MASKED: bool>(
        bvh: &CpuBvh,
        object: &Ray,
        best: Best,
        start: u32,
        at: Site<'_>,
        stack: &mut [Entry],
    ) -> (Best, bool) {
        enter::<L, W, ANY, MASKED>(bvh, object, best, start, at, stack)
    }
}

/// The mesh walks with SSE triangle lanes and AVX box lanes, compiled with AVX2 enabled
/// (a walk over `Avx8` compiled without it would call each AVX operation out of line).
/// Used only by the AVX2 walks, which run where AVX2 was detected.
#[cfg(target_arch = "x86_64")]
pub(crate) struct Avx2;

#[cfg(target_arch = "x86_64")]
impl MeshWalk for Avx2 {
    #[inline(always)]
    fn walk<const ANY: bool, const MASKED: bool>(
        bvh: &CpuBvh,
        object: &Ray,
        best: Best,
        start: u32,
        at: Site<'_>,
        stack: &mut [Entry],
    ) -> (Best, bool) {
        // SAFETY: `Avx2` is named only by `run_avx2`, which runs after AVX2 was detected.
        unsafe { enter_avx2::<ANY, MASKED>(bvh, object, best, start, at, stack) }
    }
}

/// [`enter`] with AVX lanes, compiled with AVX2 enabled.
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT (`Isa::Avx2`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
#[inline(never)]
unsafe fn enter_avx2<const ANY: bool, const MASKED: bool>(
    bvh: &CpuBvh,
    object: &Ray,
    best: Best,
    start: u32,
    at: Site<'_>,
    stack: &mut [Entry],
) -> (Best, bool) {
    enter::<crate::lanes::Sse, crate::lanes::Avx8, ANY, MASKED>(bvh, object, best, start, at, stack)
}

/// The mesh walk of the object ray: nothing when it is not valid (`Ray::is_valid`, as the
/// core's `enter_instance` asks), else prepared alone and walked.
#[inline(always)]
fn enter<L: Lanes, W: Wide, const ANY: bool, const MASKED: bool>(
    bvh: &CpuBvh,
    object: &Ray,
    best: Best,
    start: u32,
    at: Site<'_>,
    stack: &mut [Entry],
) -> (Best, bool) {
    let p = Prepared::new::<W>(std::slice::from_ref(object));
    if p.valid & 1 == 0 {
        return (best, false);
    }
    single::mesh::<_, L, W, ANY, MASKED>(bvh, object, &p, 0, best, start, at, stack)
}

/// Ray `i` of a prepared group, `ray` itself, through a two-level tree, with the rays'
/// visibility mask `mask` (`TraceOptions::mask`); the stack is [`single::stack_size`]
/// entries, shared by the top level and the mesh walked.
#[inline(always)]
pub(crate) fn trace<L: Lanes, W: Wide, M: MeshWalk, const ANY: bool, const MASKED: bool>(
    bvh: &CpuBvh,
    ray: &Ray,
    p: &Prepared,
    i: usize,
    mask: u32,
    stack: &mut [Entry],
) -> Hit {
    if p.valid >> i & 1 == 0 {
        return untraced(ray);
    }
    let best = Best::start(ray);
    if bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
        return best.into_hit();
    }
    let q = RayLanes::<L, W>::from_prepared(p, ray, i);
    let signed = ray.t_min < 0.0 || q.parallel;
    let w = Top {
        bvh,
        ray,
        q: &q,
        mask,
    };
    for_ray_kind!(q.parallel, signed, q.kz, |SIGNED, PARALLEL, KZ| {
        top::<L, W, M, ANY, MASKED, SIGNED, PARALLEL, KZ>(&w, best, stack)
    })
}

/// What the top-level walk reads: the tree, the world ray and its lanes, and the rays'
/// visibility mask.
struct Top<'a, L, W> {
    bvh: &'a CpuBvh,
    ray: &'a Ray,
    q: &'a RayLanes<L, W>,
    mask: u32,
}

/// The top-level walk from node 0 (as the mesh walk, `single::mesh`, with instances for
/// leaves); `SIGNED`, `PARALLEL` and `KZ` as in [`box8`], for the world ray. Inlined only
/// where optimised (see `single::walk`).
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn top<
    L: Lanes,
    W: Wide,
    M: MeshWalk,
    const ANY: bool,
    const MASKED: bool,
    const SIGNED: bool,
    const PARALLEL: bool,
    const KZ: usize,
>(
    w: &Top<'_, L, W>,
    mut best: Best,
    stack: &mut [Entry],
) -> Hit {
    let (bvh, q) = (w.bvh, w.q);
    let mut sp = 0;
    let mut child = 0u32;
    loop {
        if child & LEAF == 0 {
            let n = &bvh.nodes[child as usize];
            let b = box8::<L, W, SIGNED, PARALLEL, KZ, MINMAX>(n, q, best.t, !ANY && best.found);
            if b.hit != 0 {
                child = order::<W, ANY>(n, &b, stack, &mut sp);
                continue;
            }
        } else {
            let inst = &bvh.instances[(child & !LEAF) as usize];
            if inst.flat.mask & w.mask != 0 {
                let object = inst.flat.ray_to_object(w.ray);
                let at = Site {
                    prim_base: inst.flat.prim_base,
                    masks: if MASKED { bvh.masks.as_deref() } else { None },
                    mask_base: inst.mask_base,
                };
                let stopped;
                (best, stopped) =
                    M::walk::<ANY, MASKED>(bvh, &object, best, inst.root, at, &mut stack[sp..]);
                if stopped {
                    return best.into_hit();
                }
            }
        }
        match pop_still_hit::<ANY>(stack, &mut sp, q.t_max_s, &best) {
            Some(c) => child = c,
            None => return best.into_hit(),
        }
    }
}

/// A top-level walk's next child: the nearest on `stack` (below `sp`) still hit against
/// `best` (an any-hit walk re-tests nothing); `None` when the stack is empty.
#[inline(always)]
pub(crate) fn pop_still_hit<const ANY: bool>(
    stack: &[Entry],
    sp: &mut usize,
    t_max: f32,
    best: &Best,
) -> Option<u32> {
    while *sp > 0 {
        *sp -= 1;
        let e = stack[*sp];
        if ANY || !best.found || still_hit(t_max, e.tnear, e.m, e.far, best.t) {
            return Some(e.child);
        }
    }
    None
}
