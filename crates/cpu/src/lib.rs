//! A CPU tracer for bvhtrace trees, made for the CPU: the binary `FlatBvh` converted
//! into 8-wide nodes with uncompressed f32 child boxes in SoA and leaves of 4-triangle
//! SoA blocks ([`layout`]), walked one ray at a time with SIMD box and triangle tests
//! (SSE on every x86-64 CPU; where the CPU has AVX2, AVX for the eight boxes and the rest
//! compiled with AVX2 enabled; a portable path elsewhere).
//!
//! # The same hits as the reference walk
//! Each SIMD lane performs the f32 operations of `bvhtrace_core::intersect`'s scalar box
//! and watertight triangle tests, in the same order (no fused operations, the same
//! min/max semantics for NaN and signed zeros), and hits are taken with the core walks'
//! rule (nearer, or as near with a lower primitive id). The closest hit is then the one
//! `bvhtrace_core::trace_ray` with `Traversal::FullStack` returns, bit for bit (primitive,
//! `t`, `u`, `v`), under the one exception every core walk documents: where f32 cannot
//! order two triangles (`oracle::f32_indeterminate`, or `t` within
//! `oracle::f32_t_error_bound`), a different visit order may rightly keep either. Any-hit
//! queries agree on hit or miss; which triangle they stop at depends on the order.
//! Rays are prepared eight at a time, and those that miss the box around the root node's
//! boxes are answered without a walk: every step of the box test is monotone, so a ray
//! that misses that box misses every box inside it. Where the CPU has AVX2, two walks take
//! turns a step at a time, so that the core overlaps their chains of dependent loads;
//! each walk is still its ray's own, with its own stack and best hit. Batches of 256 rays
//! or more through one mesh without masks walk as streams (Barringer and Akenine-Möller's
//! dynamic ray stream traversal): each node is tested against every ray that reached it,
//! and each ray's closest hit is still the one its own walk finds.
//!
//! ```
//! use bvhtrace_core::{BuildOptions, FlatBvh, Query, Ray};
//! use bvhtrace_cpu::CpuBvh;
//! use glam::Vec3;
//!
//! let tris = vec![[Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)]];
//! let flat = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
//! let bvh = CpuBvh::from_flat(&flat).unwrap();
//! let hits = bvhtrace_cpu::trace_rays(&bvh, &[Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)], Query::Closest);
//! assert_eq!((hits[0].prim, hits[0].t), (0, 5.0));
//! ```
//!
//! # Two levels and alpha masks
//! [`CpuBvh::from_flat`] takes two-level trees (instances over meshes, each mesh converted
//! once) and trees with alpha masks (`FlatBvh::masks`). At an instance the walk does what
//! the core walks do: the rays' visibility mask ([`trace_rays_with_mask`];
//! [`ALL_VISIBLE`] elsewhere) against the instance's, the ray taken into the mesh's space
//! by the core's own `FlatInstance::ray_to_object` and prepared as `PreparedRay::new`
//! prepares it, the mesh walked from the best hit so far, hits reported as the instance's
//! primitive base plus the mesh's id. A candidate that beats the best is taken only when
//! `MaskTables::accept` accepts it (the same call with the same arguments as the core
//! walks'), a function of the candidate alone, so the closest hit is still independent
//! of the order. One mesh without masks runs walks compiled apart, which carry none of
//! this. The packets ([`trace_packets`]) hold one mesh without masks: other trees are
//! traced there ray by ray.
//!
//! Not here: hit filters and counters; the core walks trace those.
//!
//! # Packets
//! [`trace_packets`] walks [`PACKET`] consecutive rays at a time together (coherent rays:
//! camera rays in 8x8 screen tiles, see [`tile_order`]), each ray's box tests the
//! single-ray walk's and its leaves tested with the single-ray triangle test: the same
//! answers as [`trace_rays`], bit for bit for closest hits (any-hit queries agree on hit
//! or miss).

// `!(a <= b)` is how NaN is rejected along with the false case, as in the core walks.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
#![warn(missing_docs)]

/// Evaluates `$body` with three consts fixed for one ray, named by the caller: `SIGNED`
/// (the box test's exit scale depends on its sign: `t_min < 0`, or along a slab),
/// `PARALLEL` (along a slab) and `KZ` (the dominant axis), so that each of the nine
/// walks is monomorphised (see `tests4::box8`).
macro_rules! for_ray_kind {
    ($parallel:expr, $signed:expr, $kz:expr, |$s:ident, $p:ident, $k:ident| $body:expr) => {
        match ($parallel, $signed, $kz) {
            (false, false, 0) => for_ray_kind!(@ $s = false, $p = false, $k = 0, $body),
            (false, false, 1) => for_ray_kind!(@ $s = false, $p = false, $k = 1, $body),
            (false, false, _) => for_ray_kind!(@ $s = false, $p = false, $k = 2, $body),
            (false, true, 0) => for_ray_kind!(@ $s = true, $p = false, $k = 0, $body),
            (false, true, 1) => for_ray_kind!(@ $s = true, $p = false, $k = 1, $body),
            (false, true, _) => for_ray_kind!(@ $s = true, $p = false, $k = 2, $body),
            (true, _, 0) => for_ray_kind!(@ $s = true, $p = true, $k = 0, $body),
            (true, _, 1) => for_ray_kind!(@ $s = true, $p = true, $k = 1, $body),
            (true, _, _) => for_ray_kind!(@ $s = true, $p = true, $k = 2, $body),
        }
    };
    (@ $s:ident = $sv:literal, $p:ident = $pv:literal, $k:ident = $kv:literal, $body:expr) => {{
        const $s: bool = $sv;
        const $p: bool = $pv;
        const $k: usize = $kv;
        $body
    }};
}

pub mod curves;
mod lanes;
pub mod layout;

mod instanced;
pub mod moving;
pub mod moving_instances;
mod packet;
mod packet_tri;
mod plan;
mod single;
mod stream;
mod tests4;
mod tiles;

use std::fmt;

use bvhtrace_core::{Hit, Query, Ray};
use rayon::prelude::*;

pub use curves::CurveCpuBvh;
pub use layout::{ConvertError, CpuBvh, Node8, Tri4};
pub use moving::MovingCpuBvh;
pub use moving_instances::MovingInstancesCpuBvh;
pub use packet::{PACKET, tile_order};
pub use tiles::Tiles;

use instanced::MeshWalk;
use lanes::{Lanes, Wide};
use single::Entry;

/// Which instruction set the walks use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Isa {
    /// Plain f32 code, on any CPU: the same answers, bit for bit.
    Portable,
    /// WebAssembly's 128-bit SIMD lanes, in a build for `wasm32` with
    /// `target-feature=+simd128` (every browser since 2021, Node 16 and later).
    Simd128,
    /// SSE2 lanes (every x86-64 CPU).
    Sse2,
    /// AVX lanes for a node's eight boxes, the SSE lanes for the triangles, all compiled
    /// with AVX2 enabled (three-operand VEX code) and the bit instructions every AVX2 CPU
    /// has (BMI1, LZCNT, POPCNT), where the CPU has them.
    Avx2,
}

impl Isa {
    /// The fastest this CPU (or this WebAssembly build) has.
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            if has!("avx2") && has!("bmi1") && has!("lzcnt") && has!("popcnt") {
                return Isa::Avx2;
            }
            Isa::Sse2
        }
        #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
        return Isa::Simd128;
        #[cfg(not(any(
            target_arch = "x86_64",
            all(target_arch = "wasm32", target_feature = "simd128")
        )))]
        Isa::Portable
    }

    /// True when this CPU can run it.
    pub fn available(self) -> bool {
        match self {
            Isa::Portable => true,
            Isa::Simd128 => Isa::detect() == Isa::Simd128,
            Isa::Sse2 | Isa::Avx2 => self <= Isa::detect() && Isa::detect() >= Isa::Sse2,
        }
    }

    /// Every instruction set this CPU can run, slowest first.
    pub fn all_available() -> Vec<Isa> {
        [Isa::Portable, Isa::Simd128, Isa::Sse2, Isa::Avx2]
            .into_iter()
            .filter(|i| i.available())
            .collect()
    }

    /// `isa`, or the fastest this CPU has when it has not that one.
    fn or_available(self) -> Isa {
        match self.available() {
            true => self,
            false => Isa::detect(),
        }
    }
}

impl fmt::Display for Isa {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(match self {
            Isa::Portable => "portable",
            Isa::Simd128 => "simd128",
            Isa::Sse2 => "sse2",
            Isa::Avx2 => "avx2",
        })
    }
}

/// Traces one ray with the fastest instruction set this CPU has (every instance visible).
pub fn trace_ray(bvh: &CpuBvh, ray: &Ray, query: Query) -> Hit {
    trace_ray_in(bvh, ray, query, &mut RayScratch::default())
}

/// The walk's stack, kept between calls of [`trace_ray_in`]: a program that asks one ray
/// at a time (a pick, a raycaster) then allocates and clears nothing per ray.
#[derive(Clone, Debug, Default)]
pub struct RayScratch {
    stack: Vec<Entry>,
}

/// [`trace_ray`] on `scratch`'s stack, grown to what `bvh` needs (and kept).
pub fn trace_ray_in(bvh: &CpuBvh, ray: &Ray, query: Query, scratch: &mut RayScratch) -> Hit {
    let mut hit = [Hit::miss(0.0)];
    let need = 2 * single::stack_size(bvh);
    if scratch.stack.len() < need {
        scratch.stack.resize(need, Entry::default());
    }
    let rays = std::slice::from_ref(ray);
    let isa = Isa::detect();
    trace_rays_on(
        bvh,
        rays,
        query,
        ALL_VISIBLE,
        isa,
        &mut hit,
        &mut scratch.stack,
    );
    hit[0]
}

/// The rays' visibility mask that sees every instance (`TraceOptions`' default).
pub const ALL_VISIBLE: u8 = 0xff;

/// Traces a batch of rays on all threads of the current rayon pool, with the fastest
/// instruction set this CPU has (every instance visible): one at a time, or as streams
/// (see the crate docs): the same closest hits and any-hit verdicts either way.
pub fn trace_rays(bvh: &CpuBvh, rays: &[Ray], query: Query) -> Vec<Hit> {
    trace_rays_with(bvh, rays, query, Isa::detect())
}

/// [`trace_rays`] with the instruction set `isa` (or the fastest this CPU has, when it
/// lacks `isa`): the answers are the same whichever runs.
pub fn trace_rays_with(bvh: &CpuBvh, rays: &[Ray], query: Query, isa: Isa) -> Vec<Hit> {
    trace_rays_with_mask(bvh, rays, query, ALL_VISIBLE, isa)
}

/// [`trace_rays_with`] with the rays' visibility mask `mask` (`TraceOptions::mask`): in a
/// two-level tree, an instance whose mask shares no bit with it is passed through, as the
/// core walks do; one mesh ignores it.
pub fn trace_rays_with_mask(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    mask: u8,
    isa: Isa,
) -> Vec<Hit> {
    let mut hits = vec![Hit::miss(0.0); rays.len()];
    let isa = isa.or_available();
    // Plain f32 lanes keep the single walks: as streams they were no faster.
    let lanes = isa != Isa::Portable;
    if lanes && bvh.is_plain() && !bvh.nodes.is_empty() && rays.len() >= STREAM_MIN {
        // Chunks of a few thousand rays: enough for the streams to share nodes, and
        // four or more per thread for a short tail.
        let threads = rayon::current_num_threads().max(1);
        let chunk = (rays.len() / (4 * threads)).clamp(STREAM_MIN, STREAM_CHUNK);
        hits.par_chunks_mut(chunk)
            .zip(rays.par_chunks(chunk))
            .for_each_init(
                || {
                    let stack = vec![Entry::default(); single::stack_size(bvh)];
                    (stream::StreamScratch::default(), stack)
                },
                |(s, stack), (h, r)| trace_stream_on(bvh, r, query, isa, h, s, stack),
            );
        return hits;
    }
    hits.par_chunks_mut(CLASS_RUN)
        .zip(rays.par_chunks(CLASS_RUN))
        .for_each(|(h, r)| trace_run(bvh, r, query, mask, isa, h));
    hits
}

/// One thread's run of at most [`CLASS_RUN`] rays into `hits`. Where rays take turns
/// (the AVX2 walks of one mesh without masks), they do so only with rays of their own
/// class in their group of eight, so rays of many classes (incoherent bounces) are walked
/// in order of class and their hits put back in the rays' order.
fn trace_run(bvh: &CpuBvh, rays: &[Ray], query: Query, mask: u8, isa: Isa, hits: &mut [Hit]) {
    let turns = isa.or_available() == Isa::Avx2 && bvh.is_plain();
    let Some(order) = turns
        .then(|| class_order(rays, query == Query::Any))
        .flatten()
    else {
        return trace_rays_into(bvh, rays, query, mask, isa, hits);
    };
    let order = &order[..rays.len()];
    let sorted: Vec<Ray> = order.iter().map(|&i| rays[usize::from(i)]).collect();
    let mut sorted_hits = vec![Hit::miss(0.0); rays.len()];
    trace_rays_into(bvh, &sorted, query, mask, isa, &mut sorted_hits);
    for (h, &i) in sorted_hits.iter().zip(order) {
        hits[usize::from(i)] = *h;
    }
}

/// The fewest rays [`trace_rays_with_mask`] walks as streams (see [`stream`]): fewer
/// share too few nodes to pay for the streams' lists.
const STREAM_MIN: usize = 256;

/// The most rays one stream takes: more share no more nodes, and their lists leave the
/// caches.
const STREAM_CHUNK: usize = 8192;

/// Traces `rays` through one mesh without masks as one stream ([`stream::trace`]) with
/// the lanes of `isa` (one this CPU has), on `s` and `stack`.
fn trace_stream_on(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    isa: Isa,
    hits: &mut [Hit],
    s: &mut stream::StreamScratch,
    stack: &mut [Entry],
) {
    match isa {
        Isa::Portable => {
            type P = lanes::Portable;
            stream::trace::<P, lanes::Pair<P>>(bvh, rays, query, hits, s, stack)
        }
        #[cfg(target_arch = "x86_64")]
        Isa::Sse2 => {
            type S = lanes::Sse;
            stream::trace::<S, lanes::Pair<S>>(bvh, rays, query, hits, s, stack)
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `isa` is one this CPU has, so it has what `Isa::Avx2` needs.
        Isa::Avx2 => unsafe { stream_avx2(bvh, rays, query, hits, s, stack) },
        #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
        Isa::Simd128 => {
            type S = lanes::Simd128;
            stream::trace::<S, lanes::Pair<S>>(bvh, rays, query, hits, s, stack)
        }
        #[allow(unreachable_patterns)]
        _ => unreachable!("or_available gives only what this target compiles"),
    }
}

/// The most rays [`class_order`] orders at once.
const CLASS_RUN: usize = 256;

/// The order (indices into `rays`, at most [`CLASS_RUN`] of them) that puts rays of one
/// class ([`single::class_guess`]) together, each class in the rays' own order; `None`
/// when most groups of eight are of one class as they are.
#[inline(always)]
fn class_order(rays: &[Ray], any: bool) -> Option<[u8; CLASS_RUN]> {
    debug_assert!(rays.len() <= CLASS_RUN);
    // Camera rays and shadow rays toward one light mostly share a class: their first
    // two groups of eight say so, for less than reading every ray.
    let classes =
        |group: &[Ray]| (group.iter()).fold(0u32, |m, r| m | 1 << single::class_guess(r, any));
    let first = rays.chunks(tests4::RAYS).take(2);
    if first.map(|g| classes(g).count_ones()).sum::<u32>() <= 2 {
        return None;
    }
    let mut class = [0u8; CLASS_RUN];
    let mut count = [0u16; single::CLASSES + 1];
    // Each class in a group has a tail walked alone, once the class's other rays are done.
    let mut tails = 0;
    for (g, group) in rays.chunks(tests4::RAYS).enumerate() {
        let mut in_group = 0u32;
        for (i, r) in group.iter().enumerate() {
            let c = single::class_guess(r, any);
            class[g * tests4::RAYS + i] = c as u8;
            count[c + 1] += 1;
            in_group |= 1 << c;
        }
        tails += in_group.count_ones() as usize;
    }
    if tails * tests4::RAYS <= rays.len() * 5 / 4 {
        return None;
    }
    for c in 1..count.len() {
        count[c] += count[c - 1];
    }
    let mut order = [0u8; CLASS_RUN];
    for (i, &c) in class[..rays.len()].iter().enumerate() {
        order[usize::from(count[usize::from(c)])] = i as u8;
        count[usize::from(c)] += 1;
    }
    Some(order)
}

/// One thread's run of rays into `hits`.
fn trace_rays_into(bvh: &CpuBvh, rays: &[Ray], query: Query, mask: u8, isa: Isa, hits: &mut [Hit]) {
    // Twice a walk's stack: two walks take turns (`single::trace_turns`).
    let mut stack = vec![Entry::default(); 2 * single::stack_size(bvh)];
    trace_rays_on(bvh, rays, query, mask, isa, hits, &mut stack);
}

/// [`trace_rays_into`] on `s`, twice a walk's stack ([`single::stack_size`]) or more.
fn trace_rays_on(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    mask: u8,
    isa: Isa,
    hits: &mut [Hit],
    s: &mut [Entry],
) {
    debug_assert!(s.len() >= 2 * single::stack_size(bvh));
    let mask = u32::from(mask);
    // One mesh without masks has walks of its own, compiled apart from the others, so
    // that the others change nothing of its code.
    let plain = bvh.is_plain();
    type P = lanes::Portable;
    type PP = lanes::Pair<P>;
    match isa.or_available() {
        Isa::Portable if plain => run::<P, PP, false>(bvh, rays, query, hits, s),
        Isa::Portable => {
            run_layered::<P, PP, instanced::Plain<P, PP>>(bvh, rays, query, mask, hits, s)
        }
        #[cfg(target_arch = "x86_64")]
        Isa::Sse2 if plain => {
            run::<lanes::Sse, lanes::Pair<lanes::Sse>, false>(bvh, rays, query, hits, s)
        }
        #[cfg(target_arch = "x86_64")]
        Isa::Sse2 => {
            type S = lanes::Sse;
            type SP = lanes::Pair<S>;
            run_layered::<S, SP, instanced::Plain<S, SP>>(bvh, rays, query, mask, hits, s)
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `or_available` returned Avx2, so the CPU has what `Isa::Avx2` needs.
        Isa::Avx2 if plain => unsafe { run_avx2(bvh, rays, query, hits, s) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx2 => unsafe { run_layered_avx2(bvh, rays, query, mask, hits, s) },
        #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
        Isa::Simd128 if plain => {
            run::<lanes::Simd128, lanes::Pair<lanes::Simd128>, false>(bvh, rays, query, hits, s)
        }
        #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
        Isa::Simd128 => {
            type S = lanes::Simd128;
            type SP = lanes::Pair<S>;
            run_layered::<S, SP, instanced::Plain<S, SP>>(bvh, rays, query, mask, hits, s)
        }
        #[allow(unreachable_patterns)]
        _ => unreachable!("or_available gives only what this target compiles"),
    }
}

/// The walks of one mesh without masks over `rays`, monomorphised for the triangle lanes
/// `L`, the box lanes `W` and the query; with `TURNS`, rays of a common kind walk in
/// pairs that take turns (`single::trace_turns`; only the AVX2 walks, where it was
/// measured).
#[inline(always)]
fn run<L: Lanes, W: Wide, const TURNS: bool>(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    match query {
        Query::Closest => run_as::<L, W, instanced::Plain<L, W>, false, false, false, TURNS>(
            bvh, rays, 0, hits, stack,
        ),
        Query::Any => run_as::<L, W, instanced::Plain<L, W>, true, false, false, TURNS>(
            bvh, rays, 0, hits, stack,
        ),
    }
}

/// The walks of two levels or masks over `rays`, monomorphised for the lanes, the mesh
/// walks of two levels `M`, the query, the levels and the masks.
#[inline(always)]
fn run_layered<L: Lanes, W: Wide, M: MeshWalk>(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    mask: u32,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    let any = query == Query::Any;
    match (any, bvh.is_instanced(), bvh.masks.is_some()) {
        (false, false, _) => {
            run_as::<L, W, M, false, false, true, false>(bvh, rays, mask, hits, stack)
        }
        (true, false, _) => {
            run_as::<L, W, M, true, false, true, false>(bvh, rays, mask, hits, stack)
        }
        (false, true, false) => {
            run_as::<L, W, M, false, true, false, false>(bvh, rays, mask, hits, stack)
        }
        (true, true, false) => {
            run_as::<L, W, M, true, true, false, false>(bvh, rays, mask, hits, stack)
        }
        (false, true, true) => {
            run_as::<L, W, M, false, true, true, false>(bvh, rays, mask, hits, stack)
        }
        (true, true, true) => {
            run_as::<L, W, M, true, true, true, false>(bvh, rays, mask, hits, stack)
        }
    }
}

/// [`run`] for one query (`ANY`), one or two levels (`TWO`), with or without masks.
#[inline(always)]
fn run_as<
    L: Lanes,
    W: Wide,
    M: MeshWalk,
    const ANY: bool,
    const TWO: bool,
    const MASKED: bool,
    const TURNS: bool,
>(
    bvh: &CpuBvh,
    rays: &[Ray],
    mask: u32,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    // Plain loops: an iterator adaptor could be compiled apart from an AVX2 caller.
    // Rays are prepared eight at a time, then walked one by one; those that miss the root
    // node's boxes altogether (most camera rays around a framed object) take no walk.
    let scene = bvh.scene_box;
    let mut start = 0;
    while start < rays.len() {
        let end = (start + tests4::RAYS).min(rays.len());
        let group = &rays[start..end];
        let mut p = tests4::Prepared::for_boxes::<W>(group);
        let enter = p.may_enter::<W>(scene.as_ref());
        if p.valid & enter == 0 {
            // No ray of the group walks: a loop of its own, apart from the walks' code.
            for (h, ray) in hits[start..end].iter_mut().zip(group) {
                *h = single::Best::start(ray).into_hit();
            }
            for i in (0..group.len()).filter(|&i| p.valid >> i & 1 == 0) {
                hits[start + i] = single::untraced(&group[i]);
            }
            start = end;
            continue;
        }
        p.shear::<W>();
        // With `TURNS`, the rays of the common kind that share a class (`single::turns_class`:
        // a dominant axis, or an octant) take turns, two or more of them; the rest are
        // walked alone.
        let mut in_turns = 0;
        if TURNS && !TWO && !MASKED && !bvh.nodes.is_empty() {
            let mut classes = [0u32; 8];
            for (i, ray) in group.iter().enumerate() {
                if (p.valid & enter) >> i & 1 != 0
                    && ray.t_min <= ray.t_max
                    && let Some(c) = single::turns_class::<ANY>(&p, ray, i)
                {
                    classes[c] |= 1 << i;
                }
            }
            // Eight octants, or three axes.
            let n = if ANY { 8 } else { 3 };
            for (c, same) in classes.into_iter().enumerate().take(n) {
                if same.count_ones() >= 2 {
                    in_turns |= same;
                    let h = &mut hits[start..end];
                    single::trace_turns::<L, W, ANY>(bvh, group, &p, same, c, stack, h);
                }
            }
        }
        for i in (0..group.len()).filter(|&i| in_turns >> i & 1 == 0) {
            hits[start + i] = if (p.valid & !enter) >> i & 1 != 0 {
                single::Best::start(&group[i]).into_hit()
            } else if TWO {
                instanced::trace::<L, W, M, ANY, MASKED>(bvh, &group[i], &p, i, mask, stack)
            } else {
                single::trace_at::<L, W, ANY, MASKED>(bvh, &group[i], &p, i, stack)
            };
        }
        start = end;
    }
}

/// [`run`] with SSE lanes for the triangles and AVX lanes for the boxes, compiled with
/// AVX2 enabled (with [`run_layered_avx2`], the only places `Avx8` is used).
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT ([`Isa::Avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
unsafe fn run_avx2(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    run::<lanes::Sse, lanes::Avx8, true>(bvh, rays, query, hits, stack)
}

/// The stream walk with the lanes of [`run_avx2`].
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT ([`Isa::Avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
unsafe fn stream_avx2(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    hits: &mut [Hit],
    s: &mut stream::StreamScratch,
    stack: &mut [Entry],
) {
    stream::trace::<lanes::Sse, lanes::Avx8>(bvh, rays, query, hits, s, stack)
}

/// [`run_layered`] with the lanes of [`run_avx2`] (and the mesh walks compiled likewise),
/// compiled with AVX2 enabled.
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT ([`Isa::Avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
#[inline(never)]
unsafe fn run_layered_avx2(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    mask: u32,
    hits: &mut [Hit],
    stack: &mut [Entry],
) {
    run_layered::<lanes::Sse, lanes::Avx8, instanced::Avx2>(bvh, rays, query, mask, hits, stack)
}

/// True when `rays` look coherent enough for [`trace_packets`] to pay over [`trace_rays`]:
/// in three of four runs of [`PACKET`] consecutive rays (64 runs sampled across the
/// batch), every ray goes within 90 degrees of the run's first. Camera rays pass in
/// row-major order (packets measured 1.2x to 1.4x faster than single rays there, 1.5x to
/// 1.8x in 8x8 tiles), and so do shadow rays toward one light from neighbouring pixels
/// (1.2x to 1.4x); rays scattered in all directions do not. The answers are the same
/// either way.
pub fn coherent(rays: &[Ray]) -> bool {
    const SAMPLES: usize = 64;
    let runs = rays.len() / PACKET;
    if runs == 0 {
        return false;
    }
    let picked = runs.min(SAMPLES);
    let one_way = (0..picked)
        .filter(|&k| {
            let run = &rays[k * runs / picked * PACKET..][..PACKET];
            let d0 = run[0].dir;
            run.iter().all(|r| {
                let d = r.dir;
                d[0] * d0[0] + d[1] * d0[1] + d[2] * d0[2] > 0.0
            })
        })
        .count();
    4 * one_way >= 3 * picked
}

/// Traces `rays` in packets of [`PACKET`] consecutive rays (the rays of one packet walked
/// together, see the crate docs), on all threads of the current rayon pool, with the
/// fastest instruction set this CPU has. Closest hits are [`trace_rays`]' to the bit;
/// any hits agree on hit or miss. Pays on coherent rays put next to each other (camera
/// rays in [`tile_order`]).
pub fn trace_packets(bvh: &CpuBvh, rays: &[Ray], query: Query) -> Vec<Hit> {
    trace_packets_with(bvh, rays, query, Isa::detect())
}

/// [`trace_packets`] with the instruction set `isa` (or the fastest this CPU has, when it
/// lacks `isa`): the answers are the same whichever runs.
pub fn trace_packets_with(bvh: &CpuBvh, rays: &[Ray], query: Query, isa: Isa) -> Vec<Hit> {
    // The packet walk holds one mesh without masks; the others go ray by ray.
    if !bvh.is_plain() {
        return trace_rays_with(bvh, rays, query, isa);
    }
    const RUN: usize = 16 * PACKET;
    let mut hits = vec![Hit::miss(0.0); rays.len()];
    hits.par_chunks_mut(RUN)
        .zip(rays.par_chunks(RUN))
        .for_each(|(h, r)| {
            let mut s = packet::Scratch::new(bvh);
            match (isa.or_available(), query) {
                (Isa::Portable, Query::Closest) => {
                    packet::run::<lanes::Portable, lanes::Pair<lanes::Portable>, false>(
                        bvh, r, h, &mut s,
                    )
                }
                (Isa::Portable, Query::Any) => {
                    packet::run::<lanes::Portable, lanes::Pair<lanes::Portable>, true>(
                        bvh, r, h, &mut s,
                    )
                }
                #[cfg(target_arch = "x86_64")]
                (Isa::Sse2, Query::Closest) => {
                    packet::run::<lanes::Sse, lanes::Pair<lanes::Sse>, false>(bvh, r, h, &mut s)
                }
                #[cfg(target_arch = "x86_64")]
                (Isa::Sse2, Query::Any) => {
                    packet::run::<lanes::Sse, lanes::Pair<lanes::Sse>, true>(bvh, r, h, &mut s)
                }
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `or_available` returned Avx2, so the CPU has what `Isa::Avx2` needs.
                (Isa::Avx2, q) => unsafe { packets_avx2(bvh, r, q, h, &mut s) },
                #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
                (Isa::Simd128, Query::Closest) => {
                    type S = lanes::Simd128;
                    packet::run::<S, lanes::Pair<S>, false>(bvh, r, h, &mut s)
                }
                #[cfg(all(target_arch = "wasm32", target_feature = "simd128"))]
                (Isa::Simd128, Query::Any) => {
                    type S = lanes::Simd128;
                    packet::run::<S, lanes::Pair<S>, true>(bvh, r, h, &mut s)
                }
                #[allow(unreachable_patterns)]
                _ => unreachable!("or_available gives only what this target compiles"),
            }
        });
    hits
}

/// The packet walk with SSE lanes for the triangles and AVX lanes for the boxes,
/// compiled with AVX2 enabled.
///
/// # Safety
/// The CPU must have AVX2, BMI1, LZCNT and POPCNT ([`Isa::Avx2`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,lzcnt,popcnt")]
unsafe fn packets_avx2(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    hits: &mut [Hit],
    s: &mut packet::Scratch,
) {
    match query {
        Query::Closest => packet::run::<lanes::Sse, lanes::Avx8, false>(bvh, rays, hits, s),
        Query::Any => packet::run::<lanes::Sse, lanes::Avx8, true>(bvh, rays, hits, s),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// Rays from one point, each direction's class given by `dirs`.
    fn rays(dirs: &[Vec3]) -> Vec<Ray> {
        dirs.iter().map(|&d| Ray::new(Vec3::ONE, d)).collect()
    }

    #[test]
    fn rays_of_one_class_keep_their_order() {
        let one = rays(&[Vec3::new(1.0, 0.5, 0.25); CLASS_RUN]);
        assert_eq!(class_order(&one, false), None);
        assert_eq!(class_order(&one, true), None);
    }

    #[test]
    fn rays_of_many_classes_are_put_together_by_class() {
        // Closest hits by dominant axis, any hits by octant, cycling from ray to ray.
        let axes = [
            Vec3::new(1.0, 0.5, 0.5),
            Vec3::new(0.5, -1.0, 0.5),
            Vec3::new(0.5, 0.5, 1.0),
        ];
        let dirs: Vec<Vec3> = (0..200)
            .map(|i| axes[i % 3] * if i % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let rs = rays(&dirs);
        for any in [false, true] {
            let order = class_order(&rs, any).expect("rays of many classes are ordered");
            let order = &order[..rs.len()];
            let mut seen = order.to_vec();
            seen.sort_unstable();
            assert!(
                seen.iter().enumerate().all(|(i, &s)| usize::from(s) == i),
                "a permutation"
            );
            let classes: Vec<usize> = order
                .iter()
                .map(|&i| single::class_guess(&rs[usize::from(i)], any))
                .collect();
            assert!(
                classes.is_sorted(),
                "classes together, in order: {classes:?}"
            );
            // Within a class, the rays' own order.
            for w in order.windows(2) {
                let c = |i: u8| single::class_guess(&rs[usize::from(i)], any);
                assert!(c(w[0]) < c(w[1]) || w[0] < w[1]);
            }
        }
    }

    #[test]
    fn rays_walked_in_order_of_class_answer_as_one_at_a_time() {
        let tris: Vec<_> = (0..64)
            .map(|i| {
                let c = Vec3::new((i % 4) as f32, (i / 4 % 4) as f32, (i / 16) as f32);
                [c, c + Vec3::X * 0.8, c + Vec3::Y * 0.8]
            })
            .collect();
        let flat = bvhtrace_core::FlatBvh::build(&tris, &Default::default()).unwrap();
        let bvh = CpuBvh::from_flat(&flat).unwrap();
        // Every direction's class from ray to ray, from points among the triangles.
        let rs: Vec<Ray> = (0..600)
            .map(|i| {
                let f = |k: u32| bvhtrace_core::surface::uniform2(i, k).0 * 2.0 - 1.0;
                let o = Vec3::new(f(0) * 2.0 + 2.0, f(1) * 2.0 + 2.0, f(2) * 2.0 + 2.0);
                Ray::new(o, Vec3::new(f(3), f(4), f(5)))
            })
            .collect();
        for q in [Query::Closest, Query::Any] {
            assert!(class_order(&rs[..CLASS_RUN], q == Query::Any).is_some());
            let mut batch = vec![Hit::miss(0.0); rs.len()];
            for (r, h) in rs.chunks(CLASS_RUN).zip(batch.chunks_mut(CLASS_RUN)) {
                trace_run(&bvh, r, q, ALL_VISIBLE, Isa::detect(), h);
            }
            let hits = batch.iter().filter(|h| h.is_hit()).count();
            assert!(hits > 50 && hits < 550, "{hits} hits: rays of both kinds");
            for (r, h) in rs.iter().zip(&batch) {
                let one = trace_ray(&bvh, r, q);
                assert_eq!(
                    (one.t.to_bits(), one.prim),
                    (h.t.to_bits(), h.prim),
                    "{q:?} {r:?}"
                );
            }
        }
    }
}
