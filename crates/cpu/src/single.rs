//! One ray at a time through the 8-wide layout: the eight child boxes tested together, hit
//! children visited nearest first, popped children re-tested against the best hit, and a
//! leaf's triangles tested four at a time.

use std::borrow::Borrow;

use bvhtrace_core::masks::MaskTables;
use bvhtrace_core::{Aabb, Hit, Ray};

use crate::lanes::{Lanes, Wide};
use crate::layout::{CpuBvh, EMPTY, LEAF, Node8, Tri4, WIDTH, leaf_range};
use crate::tests4::{
    BoxHits, MINMAX, Prepared, RayAt, RayLanes, ShearLanes, box8, near_ends, octant, still_hit,
    tri4,
};

// The core walks' best hit and hit rule, and their answer for a ray not traced: one rule
// for every walk.
pub(crate) use bvhtrace_core::traverse::{Best, untraced};

/// What a walk reads of a tree: its nodes, and how a leaf is tested. The converted
/// layout lends its own nodes; a moving tree ([`crate::moving`]) gives each interpolated
/// at the ray's time; a tree of curves ([`crate::curves`]) tests its leaves with the core's
/// curve test, so that one walk serves all three.
pub(crate) trait WalkTree {
    /// A node as the walk tests it.
    type Node<'a>: Borrow<Node8>
    where
        Self: 'a;
    /// Node `i`.
    fn node(&self, i: u32) -> Self::Node<'_>;
    /// Asks for the memory of child `c` (a node, or a leaf's first block) ahead of its
    /// visit.
    fn fetch(&self, c: u32);
    /// Tests leaf `child`'s primitives as [`leaf_at`] does (`q` the ray's lanes, and the
    /// walk's kind as [`box8`] takes it); true when an any-hit query can stop.
    #[allow(clippy::too_many_arguments)]
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
        t_min: L,
        s: &ShearLanes<L>,
        ray: RayAt<'_>,
        child: u32,
        best: &mut Best,
        at: Site<'_>,
    ) -> bool;
}

/// A tree whose leaves are 4-triangle blocks ([`leaf_at`]'s): its blocks and their lanes'
/// binary leaf boxes.
pub(crate) trait BlockTree: WalkTree {
    /// A block as the walk tests it.
    type Block<'a>: Borrow<Tri4>
    where
        Self: 'a;
    /// Block `b`.
    fn block(&self, b: usize) -> Self::Block<'_>;
    /// Block `block`'s lane `i`'s binary leaf box (see [`crate::layout::LeafBoxes`]).
    fn leaf_box(&self, block: usize, i: usize) -> Aabb;
}

/// [`WalkTree::leaf`] for a [`BlockTree`]: [`leaf_at`].
macro_rules! block_leaf {
    () => {
        #[inline(always)]
        fn leaf<
            L: crate::lanes::Lanes,
            W: crate::lanes::Wide,
            const ANY: bool,
            const MASKED: bool,
            const SIGNED: bool,
            const PARALLEL: bool,
            const KZ: usize,
            const OCT: usize,
        >(
            &self,
            _q: &crate::tests4::RayLanes<L, W>,
            t_min: L,
            s: &crate::tests4::ShearLanes<L>,
            ray: crate::tests4::RayAt<'_>,
            child: u32,
            best: &mut crate::single::Best,
            at: crate::single::Site<'_>,
        ) -> bool {
            crate::single::leaf_at::<Self, L, ANY, MASKED>(self, t_min, s, ray, child, best, at)
        }
    };
}
pub(crate) use block_leaf;

impl WalkTree for CpuBvh {
    type Node<'a> = &'a Node8;

    #[inline(always)]
    fn node(&self, i: u32) -> &Node8 {
        &self.nodes[i as usize]
    }

    #[inline(always)]
    fn fetch(&self, c: u32) {
        fetch(self, c)
    }

    block_leaf!();
}

impl BlockTree for CpuBvh {
    type Block<'a> = &'a Tri4;

    #[inline(always)]
    fn block(&self, b: usize) -> &Tri4 {
        &self.blocks[b]
    }

    #[inline(always)]
    fn leaf_box(&self, block: usize, i: usize) -> Aabb {
        CpuBvh::leaf_box(self, block, i)
    }
}

/// A child waiting on the stack: its reference, and what [`still_hit`] needs. An any-hit
/// walk re-tests nothing at a pop and keeps only references, four to an entry (see
/// [`refs`]).
#[derive(Clone, Copy, Debug, Default)]
#[repr(C)]
pub(crate) struct Entry {
    pub child: u32,
    pub tnear: f32,
    pub m: f32,
    pub far: f32,
}

/// `stack` as child references, four to an entry: an any-hit walk's stack.
#[inline(always)]
fn refs(stack: &mut [Entry]) -> &mut [u32] {
    // SAFETY: `Entry` is `repr(C)` with four 4-byte fields and no padding, so `stack` is
    // `4 * len` initialised u32s, aligned for u32; every bit pattern is a valid u32, f32
    // and `Entry`; the slice borrows `stack` mutably for its lifetime.
    unsafe { std::slice::from_raw_parts_mut(stack.as_mut_ptr().cast::<u32>(), 4 * stack.len()) }
}

/// Puts `EMPTY` in an any-hit walk's bottom slot, where popping it ends the walk (see
/// `Walk::any_next`).
#[inline(always)]
fn mark_bottom(stack: &mut [Entry]) {
    if let Some(bottom) = refs(stack).first_mut() {
        *bottom = EMPTY;
    }
}

/// Asks for the memory of child `c` of `bvh` (a node, or a leaf's first block) ahead of
/// its visit, with no branch on which: in turns, the other walk's step runs before it.
#[inline(always)]
pub(crate) fn fetch(bvh: &CpuBvh, c: u32) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // Pointers computed with wrapping arithmetic: `c` may be `EMPTY`, and either may
        // lie outside its array; a prefetch reads nothing and never faults.
        let node = bvh.nodes.as_ptr().wrapping_add(c as usize).cast::<i8>();
        let block = bvh
            .blocks
            .as_ptr()
            .wrapping_add(leaf_range(c).0)
            .cast::<i8>();
        let at = if c & LEAF != 0 { block } else { node };
        // Four lines: a node, or a block at any 16-byte offset.
        const { assert!(size_of::<Node8>() <= 256 && size_of::<crate::layout::Tri4>() <= 192) };
        for line in 0..4 {
            // SAFETY: a prefetch only hints the cache; any address is allowed.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(at.wrapping_add(64 * line)) };
        }
    }
    // Other targets have no prefetch to ask for.
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (bvh, c);
}

/// Where a leaf's triangles are tested (the core walks' `Site`): the primitive base of
/// the instance walked (0 in one level), and the alpha masks with the instance's base in
/// them (`MaskTables::base`), read only by the masked walks.
#[derive(Clone, Copy)]
pub(crate) struct Site<'a> {
    pub prim_base: u32,
    pub masks: Option<&'a MaskTables>,
    pub mask_base: u32,
}

impl Site<'_> {
    /// One mesh without masks.
    pub const PLAIN: Site<'static> = Site {
        prim_base: 0,
        masks: None,
        mask_base: 0,
    };
}

/// Tests a leaf's blocks (`t_min` the ray's, splatted) in one mesh without masks. Returns
/// true when an any-hit query can stop.
#[inline(always)]
pub(crate) fn leaf<L: Lanes, const ANY: bool>(
    bvh: &CpuBvh,
    t_min: L,
    s: &ShearLanes<L>,
    ray: RayAt<'_>,
    child: u32,
    best: &mut Best,
) -> bool {
    leaf_at::<_, L, ANY, false>(bvh, t_min, s, ray, child, best, Site::PLAIN)
}

/// [`leaf`] at `at`: hits report `at.prim_base` plus the block's id, and with `MASKED` a
/// candidate that beats the best is taken only when the masks accept it (the core walks'
/// call, with the mesh's own id), which is a function of the candidate alone, so the hit
/// rule stays independent of the order. With `ray`, a hit within f32 error of an end of
/// the interval is taken only when the ray hits its binary leaf's box, as the binary walk
/// requires (see [`crate::layout::LeafBoxes`]).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn leaf_at<T: BlockTree, L: Lanes, const ANY: bool, const MASKED: bool>(
    bvh: &T,
    t_min: L,
    s: &ShearLanes<L>,
    ray: RayAt<'_>,
    child: u32,
    best: &mut Best,
    at: Site<'_>,
) -> bool {
    let (first, count) = leaf_range(child);
    // An index loop: an iterator's `next` may be compiled apart from an AVX2 caller.
    for k in 0..count {
        let block = bvh.block(first + k);
        let b = block.borrow();
        let (mut ok, t, u, v) = tri4::<L, ANY>(b, t_min, s);
        // Only lanes at or before the best can be taken; the rule settles the ties.
        ok &= t.le(L::splat(best.t)).bits();
        if ok == 0 {
            continue;
        }
        // An any-hit walk takes one hit and stops: its few hits are judged one by one,
        // which costs less than all four lanes.
        let near = if ANY {
            u32::MAX
        } else {
            near_ends(b, s, t, t_min, ray.t_max())
        };
        let (t, u, v) = (t.store(), u.store(), v.store());
        while ok != 0 {
            let i = ok.trailing_zeros() as usize;
            ok &= ok - 1;
            if near >> i & 1 != 0
                && (!ANY || ray.near_end(t[i], b, i))
                && !in_leaf_box(bvh, first + k, i, &ray, best.t)
            {
                continue;
            }
            let prim = at.prim_base.wrapping_add(b.prim[i]);
            if MASKED {
                if !best.beats(t[i], prim)
                    || at
                        .masks
                        .is_some_and(|m| !m.accept(at.mask_base, b.prim[i], u[i], v[i]))
                {
                    continue;
                }
                *best = Best {
                    t: t[i],
                    prim,
                    u: u[i],
                    v: v[i],
                    found: true,
                };
                if ANY {
                    return true;
                }
            } else if best.offer(t[i], prim, u[i], v[i]) && ANY {
                return true;
            }
        }
    }
    false
}

/// The binary walk's test of block `block`'s lane `i`'s own leaf box, at the best so far
/// (see [`crate::layout::LeafBoxes`]).
#[cold]
#[inline(never)]
pub(crate) fn in_leaf_box<T: BlockTree>(
    bvh: &T,
    block: usize,
    i: usize,
    ray: &RayAt<'_>,
    t_best: f32,
) -> bool {
    let b = bvh.leaf_box(block, i);
    bvhtrace_core::intersect::intersect_box(&ray.prepared(), b.min, b.max, t_best).is_some()
}

/// Orders a node's hit children nearest first: pushes all but the nearest (farthest
/// first, so the nearer pop sooner) onto `stack` above `sp`, and returns the nearest. An
/// any-hit walk re-tests nothing at a pop, so its entries carry no slack or exit.
#[inline(always)]
pub(crate) fn order<W: Wide, const ANY: bool>(
    n: &Node8,
    b: &BoxHits<W>,
    stack: &mut [Entry],
    sp: &mut usize,
) -> u32 {
    let mut hit = b.hit;
    if hit & (hit - 1) == 0 {
        return n.child[hit.trailing_zeros() as usize];
    }
    if ANY {
        // An any-hit walk visits every hit child unless it stops, and most shadow rays
        // find nothing to stop at: the order is not worth a sort.
        let first = hit.trailing_zeros() as usize;
        hit &= hit - 1;
        while hit != 0 {
            let i = hit.trailing_zeros() as usize;
            hit &= hit - 1;
            stack[*sp] = Entry {
                child: n.child[i],
                ..Entry::default()
            };
            *sp += 1;
        }
        return n.child[first];
    }
    // Only a node with two or more hit children needs the distances.
    let tnear = b.tnear.store();
    let (m, far) = if ANY {
        ([0.0; 8], [0.0; 8])
    } else {
        (b.m().store(), b.far.store())
    };
    let mut push = |i: usize| {
        stack[*sp] = Entry {
            child: n.child[i],
            tnear: tnear[i],
            m: m[i],
            far: far[i],
        };
        *sp += 1;
    };
    let a = hit.trailing_zeros() as usize;
    hit &= hit - 1;
    let b = hit.trailing_zeros() as usize;
    hit &= hit - 1;
    if hit == 0 {
        let (near, far_one) = if tnear[b] < tnear[a] { (b, a) } else { (a, b) };
        push(far_one);
        return n.child[near];
    }
    // Three to eight: an insertion sort by entry distance, farthest first.
    let mut lanes = [a, b, 0, 0, 0, 0, 0, 0];
    let mut len = 2;
    while hit != 0 {
        lanes[len] = hit.trailing_zeros() as usize;
        hit &= hit - 1;
        len += 1;
    }
    for i in 1..len {
        let mut j = i;
        while j > 0 && tnear[lanes[j - 1]] < tnear[lanes[j]] {
            lanes.swap(j - 1, j);
            j -= 1;
        }
    }
    for &l in &lanes[..len - 1] {
        push(l);
    }
    n.child[lanes[len - 1]]
}

/// Stack entries a walk over `bvh` can hold at once: at most `WIDTH - 1` per level (a
/// node pushes all its hit children but one), and a margin. An any-hit walk's references,
/// four to an entry, fit with room to spare for its bottom slot and a node's eight
/// written at once (see [`Walk::any_next`]).
pub(crate) fn stack_size(bvh: &CpuBvh) -> usize {
    (WIDTH - 1) * bvh.depth as usize + 4
}

/// Ray `i` of a prepared group, `ray` itself: its walk (closest hit, or any hit with
/// `ANY`) in one mesh without masks, with a stack of [`stack_size`] entries reused across
/// rays.
#[inline(always)]
pub(crate) fn trace<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    ray: &Ray,
    p: &Prepared,
    i: usize,
    stack: &mut [Entry],
) -> Hit {
    trace_at::<L, W, ANY, false>(bvh, ray, p, i, stack)
}

/// [`trace`] in one mesh, with the tree's alpha masks when `MASKED`.
#[inline(always)]
pub(crate) fn trace_at<L: Lanes, W: Wide, const ANY: bool, const MASKED: bool>(
    bvh: &CpuBvh,
    ray: &Ray,
    p: &Prepared,
    i: usize,
    stack: &mut [Entry],
) -> Hit {
    if p.valid >> i & 1 == 0 {
        return untraced(ray);
    }
    let best = Best::start(ray);
    if bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
        return best.into_hit();
    }
    let at = Site {
        masks: if MASKED { bvh.masks.as_deref() } else { None },
        ..Site::PLAIN
    };
    mesh::<_, L, W, ANY, MASKED>(bvh, ray, p, i, best, 0, at, stack)
        .0
        .into_hit()
}

/// The class of ray `i` of `p` (`ray` itself) whose rays take turns in [`trace_turns`],
/// when it is of the common kind (`t_min >= 0`, no zero direction component): its
/// dominant axis for closest hits, its [`octant`] for any hits (whose box test never
/// reads the axis, and reads each slab's entry from one plane by the octant). The other
/// kinds are rare and walk alone.
#[inline(always)]
pub(crate) fn turns_class<const ANY: bool>(p: &Prepared, ray: &Ray, i: usize) -> Option<usize> {
    let plain = p.parallel >> i & 1 == 0 && ray.t_min >= 0.0;
    plain.then(|| {
        if ANY {
            octant([p.dir[0][i], p.dir[1][i], p.dir[2][i]])
        } else {
            p.kz[i]
        }
    })
}

/// The number of classes [`class_guess`] gives.
pub(crate) const CLASSES: usize = 9;

/// [`class_guess`]'s class for the rare kinds, which walk alone.
const RARE: usize = CLASSES - 1;

/// [`turns_class`] of `ray` read from the ray itself, before it is prepared (its
/// direction not flushed), so that rays can be put in order of class ahead of their
/// groups: closest hits by dominant axis, any hits by octant; [`RARE`] for the rare
/// kinds. A guess that differs costs only a turn.
#[inline(always)]
pub(crate) fn class_guess(ray: &Ray, any: bool) -> usize {
    let d = ray.dir;
    if !(ray.t_min >= 0.0) || d.contains(&0.0) {
        return RARE;
    }
    if any {
        return octant(d);
    }
    let a = d.map(f32::abs);
    if a[0] >= a[1] && a[0] >= a[2] {
        0
    } else if a[1] >= a[2] {
        1
    } else {
        2
    }
}

/// The rays of `group` in `rays` (bits, two or more; each valid, with `t_min <= t_max`,
/// all of [`turns_class`] `class`), prepared in `p`, through one mesh without masks,
/// their hits written to `hits`, with a stack of twice [`stack_size`] entries: two walks
/// take turns a step at a time, each taking the next ray when its own ends, so that the
/// CPU overlaps one ray's chain of dependent loads and tests with the other's. Each ray's
/// walk is its own, so the hits are those of [`trace`].
#[inline(always)]
pub(crate) fn trace_turns<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    group: &[Ray],
    p: &Prepared,
    rays: u32,
    class: usize,
    stack: &mut [Entry],
    hits: &mut [Hit],
) {
    debug_assert!(!bvh.nodes.is_empty() && rays.count_ones() >= 2);
    debug_assert!(stack.len() >= 2 * stack_size(bvh));
    if ANY {
        any_turns::<L, W>(bvh, group, p, rays, class, stack, hits)
    } else {
        closest_turns::<L, W>(bvh, group, p, rays, class, stack, hits)
    }
}

/// [`trace_turns`] for closest hits, of dominant axis `kz`.
#[inline(always)]
fn closest_turns<L: Lanes, W: Wide>(
    bvh: &CpuBvh,
    group: &[Ray],
    p: &Prepared,
    rays: u32,
    kz: usize,
    stack: &mut [Entry],
    hits: &mut [Hit],
) {
    const M: usize = MINMAX;
    match kz {
        0 => walk_turns::<L, W, false, 0, M>(bvh, group, p, rays, stack, hits),
        1 => walk_turns::<L, W, false, 1, M>(bvh, group, p, rays, stack, hits),
        _ => walk_turns::<L, W, false, 2, M>(bvh, group, p, rays, stack, hits),
    }
}

/// [`trace_turns`] for any hits, of octant `oct`.
#[inline(always)]
fn any_turns<L: Lanes, W: Wide>(
    bvh: &CpuBvh,
    group: &[Ray],
    p: &Prepared,
    rays: u32,
    oct: usize,
    stack: &mut [Entry],
    hits: &mut [Hit],
) {
    match oct {
        0 => walk_turns::<L, W, true, 0, 0>(bvh, group, p, rays, stack, hits),
        1 => walk_turns::<L, W, true, 0, 1>(bvh, group, p, rays, stack, hits),
        2 => walk_turns::<L, W, true, 0, 2>(bvh, group, p, rays, stack, hits),
        3 => walk_turns::<L, W, true, 0, 3>(bvh, group, p, rays, stack, hits),
        4 => walk_turns::<L, W, true, 0, 4>(bvh, group, p, rays, stack, hits),
        5 => walk_turns::<L, W, true, 0, 5>(bvh, group, p, rays, stack, hits),
        6 => walk_turns::<L, W, true, 0, 6>(bvh, group, p, rays, stack, hits),
        _ => walk_turns::<L, W, true, 0, 7>(bvh, group, p, rays, stack, hits),
    }
}

/// The walks of [`trace_turns`], of dominant axis `KZ` or octant `OCT` (see [`box8`]).
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn walk_turns<L: Lanes, W: Wide, const ANY: bool, const KZ: usize, const OCT: usize>(
    bvh: &CpuBvh,
    group: &[Ray],
    p: &Prepared,
    mut rays: u32,
    stack: &mut [Entry],
    hits: &mut [Hit],
) {
    let at = Site::PLAIN;
    let (sa, sb) = stack.split_at_mut(stack.len() / 2);
    let (i, j) = (next(&mut rays), next(&mut rays));
    let mut qa = RayLanes::<L, W>::from_prepared(p, &group[i], i);
    let mut qb = RayLanes::<L, W>::from_prepared(p, &group[j], j);
    let (ri, rj) = (&group[i], &group[j]);
    let mut a = Walk::<L>::new(p, i, [ri.t_min, ri.t_max], Best::start(ri), 0, sa);
    let mut b = Walk::<L>::new(p, j, [rj.t_min, rj.t_max], Best::start(rj), 0, sb);
    // Both walks in turns while there are rays to start, then the one left to its end.
    let last = loop {
        if !turn::<L, W, ANY, KZ, OCT>(bvh, group, p, (&mut a, &mut qa), &mut rays, hits) {
            break (b, qb);
        }
        if !turn::<L, W, ANY, KZ, OCT>(bvh, group, p, (&mut b, &mut qb), &mut rays, hits) {
            break (a, qa);
        }
    };
    let (mut last, q) = last;
    while last
        .step::<_, W, ANY, false, false, false, KZ, OCT>(bvh, &q, at)
        .is_none()
    {}
    hits[last.i] = last.best.into_hit();
}

/// One step of walk `w` (its ray's lanes `q`) of [`walk_turns`]; a walk that ends stores
/// its hit and starts the next ray of `rays`. Returns false when it ended with no ray left.
#[inline(always)]
fn turn<L: Lanes, W: Wide, const ANY: bool, const KZ: usize, const OCT: usize>(
    bvh: &CpuBvh,
    group: &[Ray],
    p: &Prepared,
    (w, q): (&mut Walk<'_, L>, &mut RayLanes<L, W>),
    rays: &mut u32,
    hits: &mut [Hit],
) -> bool {
    if w.step::<_, W, ANY, false, false, false, KZ, OCT>(bvh, q, Site::PLAIN)
        .is_some()
    {
        hits[w.i] = w.best.into_hit();
        if *rays == 0 {
            return false;
        }
        let i = next(rays);
        *q = RayLanes::from_prepared(p, &group[i], i);
        w.restart(i, &group[i]);
    }
    true
}

/// The lowest ray left, taken off `rays`.
#[inline(always)]
fn next(rays: &mut u32) -> usize {
    let i = rays.trailing_zeros() as usize;
    *rays &= rays.wrapping_sub(1);
    i
}

/// mesh whose walk starts at `start` (a node, or a leaf), from the best hit `best`, at
/// `at`. Returns the best hit, and true when an any-hit query stopped.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn mesh<T: WalkTree, L: Lanes, W: Wide, const ANY: bool, const MASKED: bool>(
    bvh: &T,
    ray: &Ray,
    p: &Prepared,
    i: usize,
    best: Best,
    start: u32,
    at: Site<'_>,
    stack: &mut [Entry],
) -> (Best, bool) {
    let q = RayLanes::<L, W>::from_prepared(p, ray, i);
    // One walk per dominant axis, for rays along a slab, and for rays that start behind
    // their origin (see `box8`): most rays are none of the last two.
    let signed = ray.t_min < 0.0 || q.parallel;
    for_ray_kind!(q.parallel, signed, q.kz, |SIGNED, PARALLEL, KZ| {
        walk::<T, L, W, ANY, MASKED, SIGNED, PARALLEL, KZ>(bvh, p, i, &q, best, start, at, stack)
    })
}

/// The walk from `start` (see [`mesh`]); `SIGNED`, `PARALLEL` and `KZ` as in [`box8`].
#[allow(clippy::too_many_arguments)]
// Inlined only where optimised: an unoptimised build keeps the locals of every inlined
// walk apart, and the nine walks of a caller made frames of megabytes (a thread's stack
// overflowed).
#[cfg_attr(not(debug_assertions), inline(always))]
#[cfg_attr(debug_assertions, inline(never))]
fn walk<
    T: WalkTree,
    L: Lanes,
    W: Wide,
    const ANY: bool,
    const MASKED: bool,
    const SIGNED: bool,
    const PARALLEL: bool,
    const KZ: usize,
>(
    bvh: &T,
    p: &Prepared,
    i: usize,
    q: &RayLanes<L, W>,
    best: Best,
    start: u32,
    at: Site<'_>,
    stack: &mut [Entry],
) -> (Best, bool) {
    let mut w = Walk::<L>::new(p, i, [q.t_min_s, q.t_max_s], best, start, stack);
    loop {
        if let Some(stopped) = w.step::<_, W, ANY, MASKED, SIGNED, PARALLEL, KZ, MINMAX>(bvh, q, at)
        {
            return (w.best, stopped);
        }
    }
}

/// A walk under way: one ray's state between [`Walk::step`]s, so that two walks can take
/// turns (see [`trace_turns`]). The ray's lanes are passed to each step, not kept here, so
/// that they can stay in registers.
pub(crate) struct Walk<'a, L> {
    p: &'a Prepared,
    i: usize,
    ray: RayAt<'a>,
    /// Made at the ray's first leaf.
    shear: Option<ShearLanes<L>>,
    /// The best hit so far.
    pub best: Best,
    /// The node or leaf to visit next.
    child: u32,
    /// Entries on the stack (an any-hit walk's references above its bottom slot).
    sp: usize,
    stack: &'a mut [Entry],
}

impl<'a, L: Lanes> Walk<'a, L> {
    /// The walk of ray `i` of `p` (interval `t_min..=t_max`) from `start`, from `best`.
    #[inline(always)]
    pub fn new(
        p: &'a Prepared,
        i: usize,
        [t_min, t_max]: [f32; 2],
        best: Best,
        start: u32,
        stack: &'a mut [Entry],
    ) -> Self {
        mark_bottom(stack);
        Walk {
            p,
            i,
            ray: RayAt::Lanes { p, i, t_min, t_max },
            shear: None,
            best,
            child: start,
            sp: 0,
            stack,
        }
    }

    /// Starts the walk of ray `i` of the same group (`ray` itself) from the root, in this
    /// walk's stack.
    #[inline(always)]
    pub fn restart(&mut self, i: usize, ray: &Ray) {
        self.i = i;
        self.ray = RayAt::Lanes {
            p: self.p,
            i,
            t_min: ray.t_min,
            t_max: ray.t_max,
        };
        self.shear = None;
        self.best = Best::start(ray);
        self.child = 0;
        self.sp = 0;
        mark_bottom(self.stack);
    }

    /// Visits the next node (and goes on to its nearest hit child) or leaf (and pops the
    /// next child still hit against the best so far). Returns `Some` when the walk is
    /// over: true when an any-hit query stopped.
    #[inline(always)]
    pub fn step<
        T: WalkTree,
        W: Wide,
        const ANY: bool,
        const MASKED: bool,
        const SIGNED: bool,
        const PARALLEL: bool,
        const KZ: usize,
        const OCT: usize,
    >(
        &mut self,
        bvh: &T,
        q: &RayLanes<L, W>,
        at: Site<'_>,
    ) -> Option<bool> {
        if self.child & LEAF == 0 {
            let node = bvh.node(self.child);
            let n = node.borrow();
            // An any-hit walk stops at its first hit, so its best is always `t_max`.
            let culled = !ANY && self.best.found;
            let b = box8::<L, W, SIGNED, PARALLEL, KZ, OCT>(n, q, self.best.t, culled);
            if ANY {
                self.child = self.any_next::<W>(n, b.hit);
                bvh.fetch(self.child);
                return (self.child == EMPTY).then_some(false);
            }
            if b.hit != 0 {
                self.child = order::<W, ANY>(n, &b, self.stack, &mut self.sp);
                return None;
            }
        } else {
            let (p, i) = (self.p, self.i);
            let shear = self.shear.get_or_insert_with(|| {
                ShearLanes::from_prepared(p, i, if OCT == MINMAX { KZ } else { p.kz[i] })
            });
            if bvh.leaf::<L, W, ANY, MASKED, SIGNED, PARALLEL, KZ, OCT>(
                q,
                q.t_min4,
                shear,
                self.ray,
                self.child,
                &mut self.best,
                at,
            ) {
                return Some(true);
            }
        }
        if ANY {
            self.child = self.any_pop();
            bvh.fetch(self.child);
            return (self.child == EMPTY).then_some(false);
        }
        loop {
            if self.sp == 0 {
                return Some(false);
            }
            self.sp -= 1;
            let e = self.stack[self.sp];
            if !self.best.found || still_hit(q.t_max_s, e.tnear, e.m, e.far, self.best.t) {
                self.child = e.child;
                return None;
            }
        }
    }

    /// An any-hit walk's next child after node `n` whose hit slots are `hit` (0 after a
    /// leaf): all the hit children pushed at once in slot order and the last taken back,
    /// or the stack's top when none was hit; [`EMPTY`] when the stack is empty. An
    /// any-hit walk visits every hit child unless it stops, so it keeps no order, and no
    /// branch depends on how many children were hit (a branch that often mispredicts).
    /// Its stack is references (see [`refs`]): slot 0 holds [`EMPTY`], the entries
    /// follow.
    #[inline(always)]
    fn any_next<W: Wide>(&mut self, n: &Node8, hit: u32) -> u32 {
        let refs = refs(self.stack);
        let above = &mut refs[1 + self.sp..1 + self.sp + WIDTH];
        W::compress(hit, &n.child, above.try_into().expect("eight slots"));
        let top = refs[self.sp];
        let last = n.child[31 - (hit | 1).leading_zeros() as usize];
        // `sp` wraps past zero only when the walk ends.
        self.sp = (self.sp + hit.count_ones() as usize).wrapping_sub(1);
        if hit != 0 { last } else { top }
    }

    /// An any-hit walk's next child after a leaf: the stack's top, or [`EMPTY`] when the
    /// stack is empty (see [`Walk::any_next`]).
    #[inline(always)]
    fn any_pop(&mut self) -> u32 {
        let top = refs(self.stack)[self.sp];
        self.sp = self.sp.wrapping_sub(1);
        top
    }
}
