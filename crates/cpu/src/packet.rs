//! Rays in packets: up to [`PACKET`] rays (an 8x8 screen tile of camera rays, say) walked
//! together through the 8-wide tree with one stack. The rays are loaded eight at a time
//! into lanes. At a node the eight children are first tested together against bounds over
//! the packet's rays (a conservative cull, [`Frustum`]), then each kept child's box is
//! tested against the packet's rays eight rays at a time (rays in lanes, the box
//! splatted), each lane the single-ray walk's box test for that ray (its own origin,
//! inverse, interval, best hit and culling slack); a child is entered with the mask of
//! the rays that hit it, and a popped child is re-tested against the rays' bests. A leaf's
//! triangles are tested one at a time against eight rays that share their shear axes
//! (`packet_tri`), other rays ray by ray with the single-ray test. Rays along a slab,
//! invalid rays and empty intervals take the single-ray walk.
//!
//! The answers are the single-ray walk's: each ray meets every node the single walk
//! enters for it (the same test, at a best hit no nearer than the single walk's at that
//! point, since the bests only fall as triangles are taken; the bounds only drop children
//! no ray hits), tests its leaves with the same triangle test lane for lane, and keeps its
//! hits by the same order-independent rule.

use bvhtrace_core::intersect::{BOX_CULL_SLACK, BOX_TFAR_SCALE, BOX_TFAR_SCALE_NEG};
use bvhtrace_core::{Hit, MISS, Ray};

use crate::lanes::{Lanes, Wide};
use crate::layout::{CpuBvh, LEAF, Node8, WIDTH, leaf_range};
use crate::packet_tri::{ShearRays, tri_rays};
use crate::single::{self, Best, Entry};
use crate::tests4::{Prepared, RayAt, ShearLanes, near_end, row, shear_lanes, sheared_axes};

/// Rays per packet: eight groups of eight lanes.
pub const PACKET: usize = 64;
/// Groups of eight rays per packet.
const GROUPS: usize = PACKET / 8;

/// Where a full packet's lane `8 g + j` takes its ray from: a full packet is taken to be
/// an 8x8 tile (rays row by row, as [`tile_order`] lists them), and each group is a 4x2
/// block of it, which a small box or triangle covers more fully than a row of eight.
/// The answers do not depend on it; partial packets keep the rays' order.
const TILE_LANES: [u8; PACKET] = {
    let mut t = [0u8; PACKET];
    let mut k = 0;
    while k < PACKET {
        let (g, j) = (k / 8, k % 8);
        let (x, y) = ((g % 2) * 4 + j % 4, (g / 2) * 2 + j / 4);
        t[k] = (y * 8 + x) as u8;
        k += 1;
    }
    t
};

/// Lane `k`'s ray in a partial packet: its own.
const SAME_LANES: [u8; PACKET] = {
    let mut t = [0u8; PACKET];
    let mut k = 0;
    while k < PACKET {
        t[k] = k as u8;
        k += 1;
    }
    t
};

/// Where a packet of `len` rays takes lane `k`'s ray from (see [`TILE_LANES`]).
#[inline(always)]
fn lane_order(len: usize) -> &'static [u8; PACKET] {
    if len == PACKET {
        &TILE_LANES
    } else {
        &SAME_LANES
    }
}

/// A packet's rays as lanes, ray `8 g + j` in lane `j` of group `g`.
#[derive(Clone)]
struct Soa {
    /// `org[g][axis]`: the origins.
    org: [[[f32; 8]; 3]; GROUPS],
    /// The directions, `dir[g][axis]`.
    dir: [[[f32; 8]; 3]; GROUPS],
    /// `-1 / dir` (see `RayLanes::ninv`).
    ninv: [[[f32; 8]; 3]; GROUPS],
    t_min: [[f32; 8]; GROUPS],
    t_max: [[f32; 8]; GROUPS],
    /// The best hit's `t` (the ray's `t_max` until it has one).
    best_t: [[f32; 8]; GROUPS],
    /// The best hit's primitive ([`MISS`] until it has one) and weights, as bits.
    best_prim: [[f32; 8]; GROUPS],
    best_u: [[f32; 8]; GROUPS],
    best_v: [[f32; 8]; GROUPS],
    /// The dominant axis (`PreparedRay::kz`) as 0.0, 1.0 or 2.0.
    kz: [[f32; 8]; GROUPS],
    /// The shear constants `sx`, `sy`, `sz` (`PreparedRay`'s).
    shear: [[[f32; 8]; 3]; GROUPS],
    /// Each group's shear axes `kx`, `ky`, `kz` (those of its first walked ray).
    axes: [[usize; 3]; GROUPS],
    /// Bit `k`: ray `k`'s `kx` and `ky` are swapped (`dir[kz] < 0`).
    swap: u64,
    /// The walked rays whose shear axes are their group's: their leaves are tested with
    /// rays in lanes, the others' ray by ray.
    lanes: u64,
}

/// Bounds over a packet's walked rays for a conservative cull of a node's eight children
/// at once (children in lanes): per axis the origins' range and the range of `-1 / dir`,
/// the smallest `t_min` and the largest `t_max`.
///
/// Why it never culls a box a ray's own test hits: f32 subtraction and multiplication are
/// monotone in each operand (rounding is), so over the rays' origins `o` and inverses `n`
/// the ray's `(o - plane) * n` is at least the smallest of the products at the range's
/// corners and at most the largest. Where every ray's `n` has one sign on an axis, the
/// near plane is the same for all of them, and the bound needs the products at one end of
/// the origins' range; where the signs differ the axis bounds nothing (`-inf`, `+inf`).
/// So the entry (a max of per-axis entries and `t_min`) is at least the bound's entry,
/// the exit (a min of per-axis exits and a limit never above `t_max`) at most the bound's
/// exit, and the exit scaling is monotone: a box the bound misses, every ray misses.
#[derive(Clone, Copy, Default)]
struct Frustum {
    /// The origin coordinate that gives the smallest distance to the near plane.
    o_near: [f32; 3],
    /// The origin coordinate that gives the largest distance to the far plane.
    o_far: [f32; 3],
    /// The smallest `-1 / dir`.
    n_lo: [f32; 3],
    /// The largest `-1 / dir`.
    n_hi: [f32; 3],
    /// The near plane's index in `Node8::planes` (`2 a` or `2 a + 1`).
    near: [usize; 3],
    /// `-inf` on an axis where the signs differ (the entry bound dropped), else `+inf`.
    cap_near: [f32; 3],
    /// `+inf` on an axis where the signs differ, else `-inf`.
    cap_far: [f32; 3],
    /// The smallest `t_min`.
    t_min: f32,
    /// The largest `t_max`.
    t_max: f32,
    /// Every walked ray has the same origin (then `o_near`) and, per axis, the direction
    /// sign of every other: [`child_rays`] then takes each slab's distances from the
    /// origin's distances to the near and far planes, computed once per box.
    common: bool,
}

/// What a thread keeps from packet to packet.
pub(crate) struct Scratch {
    soa: Box<Soa>,
    stack: Vec<PEntry>,
    single: Vec<Entry>,
}

/// A child waiting on the stack: where its box is (for the re-test) and its rays.
#[derive(Clone, Copy, Default)]
struct PEntry {
    mask: u64,
    parent: u32,
    slot: u32,
}

impl Scratch {
    /// Room for walks over `bvh`.
    pub fn new(bvh: &CpuBvh) -> Scratch {
        let zero = [[0.0f32; 8]; GROUPS];
        Scratch {
            soa: Box::new(Soa {
                org: [[[0.0; 8]; 3]; GROUPS],
                dir: [[[0.0; 8]; 3]; GROUPS],
                ninv: [[[0.0; 8]; 3]; GROUPS],
                t_min: zero,
                t_max: zero,
                best_t: zero,
                best_prim: zero,
                best_u: zero,
                best_v: zero,
                kz: zero,
                shear: [[[0.0; 8]; 3]; GROUPS],
                axes: [[0, 1, 2]; GROUPS],
                swap: 0,
                lanes: 0,
            }),
            stack: vec![PEntry::default(); single::stack_size(bvh)],
            single: vec![Entry::default(); single::stack_size(bvh)],
        }
    }
}

/// The packet's state during a walk: its rays, their bests, and which are still walked.
struct State<'a> {
    soa: &'a mut Soa,
    /// The packet's rays, in the caller's order (see [`lane_order`]).
    rays: &'a [Ray],
    /// Rays walked together and not finished (an any-hit ray finishes at its first hit).
    active: u64,
    /// Rays that have a hit.
    found: u64,
    /// The sum of the walked rays' directions: children are visited in its order.
    dir: [f32; 3],
    /// Bounds over the walked rays for culling a node's children at once.
    frustum: Frustum,
}

/// Loads up to [`PACKET`] rays into the packet's lanes ([`gather`], then [`prepare`]);
/// returns the mask of those the packet walks, the sum of their directions and their
/// bounds.
#[cfg(test)]
fn load<W: Wide>(bvh: &CpuBvh, rays: &[Ray], soa: &mut Soa) -> (u64, [f32; 3], Frustum) {
    let (active, dir, f) = gather::<W>(bvh, rays, soa);
    prepare::<W>(rays.len(), active, soa);
    (active, dir, f)
}

/// The first pass over up to [`PACKET`] rays, eight at a time: their rows transposed into
/// the packet's lanes (origin, direction, interval), which of them the packet walks (the
/// others take the single-ray walk: invalid rays, rays along a slab, empty intervals),
/// the sum of their directions and their bounds. Enough to tell a packet whose rays all
/// miss the root's boxes, which then needs nothing more.
///
/// The bounds' range of `-1 / dir` on an axis where every walked ray has one sign comes
/// from the directions' range: `-1 / d` is increasing in `d` on each side of 0, and so
/// is its correctly rounded value, so the smallest and largest are `-1 / d_lo` and
/// `-1 / d_hi`, the per-ray values' own extremes to the bit. Where the signs differ the
/// axis bounds nothing and the range is not used.
#[inline(always)]
fn gather<W: Wide>(bvh: &CpuBvh, rays: &[Ray], soa: &mut Soa) -> (u64, [f32; 3], Frustum) {
    // The bounds over the walked rays' rows (origin, `t_min`, direction, `t_max`), field
    // by field, and the sum of the rows.
    if bvh.nodes.is_empty() {
        return (0, [0.0; 3], Frustum::default());
    }
    let inf = W::splat(f32::INFINITY);
    let mut b = RowBounds {
        lo: inf,
        hi: inf.neg(),
        sum: W::splat(0.0),
    };
    let mut active = 0u64;
    if let Ok(full) = <&[Ray; PACKET]>::try_from(rays) {
        // Full packets (tiles) apart: their rows need no clamping.
        for g in 0..GROUPS {
            active |= (gather_group::<W>(full_rows(full, g), g, 7, soa, &mut b) as u64) << (8 * g);
        }
    } else {
        let mut g = 0;
        while 8 * g < rays.len() {
            let last = rays.len().min(8 * g + 8) - 8 * g - 1;
            let rows = group_rows(rays, g);
            active |= (gather_group::<W>(rows, g, last, soa, &mut b) as u64) << (8 * g);
            g += 1;
        }
    }
    let (lo, hi, sum) = (b.lo.store(), b.hi.store(), b.sum.store());
    let (t_lo, t_hi) = (lo[3], hi[7]);
    let mut f = Frustum {
        t_min: t_lo,
        t_max: t_hi,
        common: true,
        ..Frustum::default()
    };
    let mut dir = [0.0f32; 3];
    for a in 0..3 {
        dir[a] = sum[4 + a];
        let (dl, dh) = (lo[4 + a], hi[4 + a]);
        // `d > 0`, so `n < 0` (the rays move up the axis): the lower plane is the near
        // one, and the largest origin gives the smallest distance to it.
        let up = dl > 0.0;
        let mixed = !(up || dh < 0.0);
        (f.n_lo[a], f.n_hi[a]) = if mixed {
            (-1.0, 1.0)
        } else {
            (-1.0 / dl, -1.0 / dh)
        };
        f.near[a] = 2 * a + usize::from(!up);
        let (ol, oh) = (lo[a], hi[a]);
        (f.o_near[a], f.o_far[a]) = if up { (oh, ol) } else { (ol, oh) };
        f.cap_near[a] = if mixed {
            f32::NEG_INFINITY
        } else {
            f32::INFINITY
        };
        f.cap_far[a] = if mixed {
            f32::INFINITY
        } else {
            f32::NEG_INFINITY
        };
        f.common &= !mixed && ol == oh;
    }
    (active, dir, f)
}

/// Bounds over rays' rows (`[ox, oy, oz, t_min, dx, dy, dz, t_max]`), field by field:
/// the smallest and largest of each, and their sum.
struct RowBounds<W> {
    lo: W,
    hi: W,
    sum: W,
}

/// One group of [`gather`]: the rows `rows` of group `g` (lanes after `last` repeat the
/// last ray) into the lanes, their walked rays' rows into the bounds; returns the mask of
/// the walked rays.
#[inline(always)]
fn gather_group<W: Wide>(
    rows: [&[f32; 8]; 8],
    g: usize,
    last: usize,
    soa: &mut Soa,
    b: &mut RowBounds<W>,
) -> u32 {
    let inf = W::splat(f32::INFINITY);
    let [ox, oy, oz, t_min, dx, dy, dz, t_max] = W::columns(rows);
    let (o, d) = ([ox, oy, oz], [dx, dy, dz]);
    // Valid (`Ray::is_valid`: finite origin and direction, no NaN bound), no component
    // zero or subnormal (not along a slab), and a non-empty interval.
    let mut walk = t_min.le(t_max);
    for a in 0..3 {
        walk = walk
            .and(o[a].abs().lt(inf))
            .and(d[a].abs().lt(inf))
            .and(d[a].abs().ge(W::splat(f32::MIN_POSITIVE)));
    }
    let walked = walk.bits() & ((2u32 << last) - 1);
    for a in 0..3 {
        soa.org[g][a] = o[a].store();
        soa.dir[g][a] = d[a].store();
    }
    soa.t_min[g] = t_min.store();
    soa.t_max[g] = t_max.store();
    // Rows, not columns: three accumulators instead of fifteen.
    if walked == 0xff {
        // Every lane walks (nearly every group of camera rays): pairwise, so that no
        // long chain of dependent operations forms.
        // No `array::map` over AVX lanes: its closure would be compiled apart from the
        // AVX2 caller.
        let r = [
            W::load(rows[0]),
            W::load(rows[1]),
            W::load(rows[2]),
            W::load(rows[3]),
            W::load(rows[4]),
            W::load(rows[5]),
            W::load(rows[6]),
            W::load(rows[7]),
        ];
        let (lo, hi, sum) = (
            (r[0].min(r[1]).min(r[2].min(r[3]))).min(r[4].min(r[5]).min(r[6].min(r[7]))),
            (r[0].max(r[1]).max(r[2].max(r[3]))).max(r[4].max(r[5]).max(r[6].max(r[7]))),
            (r[0].add(r[1]).add(r[2].add(r[3]))).add(r[4].add(r[5]).add(r[6].add(r[7]))),
        );
        b.lo = lo.min(b.lo);
        b.hi = hi.max(b.hi);
        b.sum = b.sum.add(sum);
    } else {
        for (j, r) in rows.iter().enumerate() {
            if walked >> j & 1 != 0 {
                let r = W::load(r);
                b.lo = r.min(b.lo);
                b.hi = r.max(b.hi);
                b.sum = b.sum.add(r);
            }
        }
    }
    walked
}

/// Group `g`'s rows of a full packet: [`TILE_LANES`] for it, a 4x2 block of the 8x8 tile
/// at row `2 (g / 2)` and column `4 (g % 2)`.
#[inline(always)]
fn full_rows(full: &[Ray; PACKET], g: usize) -> [&[f32; 8]; 8] {
    let b = (g & 7) / 2 * 16 + (g & 1) * 4;
    [
        row(&full[b]),
        row(&full[b + 1]),
        row(&full[b + 2]),
        row(&full[b + 3]),
        row(&full[b + 8]),
        row(&full[b + 9]),
        row(&full[b + 10]),
        row(&full[b + 11]),
    ]
}

/// The rows of group `g`'s rays, lane `j` from the ray [`lane_order`] gives it; missing
/// lanes of a partial group repeat its last ray (they are not walked).
#[inline(always)]
fn group_rows(rays: &[Ray], g: usize) -> [&[f32; 8]; 8] {
    if let Ok(full) = <&[Ray; PACKET]>::try_from(rays) {
        return full_rows(full, g);
    }
    let (base, order) = (8 * g, lane_order(rays.len()));
    let last = rays.len().min(base + 8) - base - 1;
    // No `array::map` with AVX lanes here: its closure is compiled apart from the AVX2
    // caller, and the AVX operations in it stay out-of-line calls.
    let at = |j: usize| row(&rays[order[base + if j < last { j } else { last }] as usize]);
    [at(0), at(1), at(2), at(3), at(4), at(5), at(6), at(7)]
}

/// The second pass, for a packet that walks: per group `-1 / dir`, the shear constants
/// and dominant axes, the bests at the start, and the group's shear axes (see [`Soa`]).
///
/// The values are `PreparedRay::new`'s to the bit for the walked rays (the operations of
/// `Prepared::new`; a walked ray has no zero or subnormal direction component, so its
/// flushed direction is its direction and `safe_inverse` is `1 / dir`).
#[inline(always)]
fn prepare<W: Wide>(len: usize, active: u64, soa: &mut Soa) {
    let (mut swap_all, mut lanes_all) = (0u64, 0u64);
    let mut g = 0;
    while 8 * g < len {
        let d = [
            W::load(&soa.dir[g][0]),
            W::load(&soa.dir[g][1]),
            W::load(&soa.dir[g][2]),
        ];
        let minus_one = W::splat(-1.0);
        let (kz, swap, shear) = shear_lanes(d);
        for a in 0..3 {
            soa.ninv[g][a] = minus_one.div(d[a]).store();
            soa.shear[g][a] = shear[a].store();
        }
        soa.best_t[g] = soa.t_max[g];
        soa.best_prim[g] = [f32::from_bits(MISS); 8];
        soa.best_u[g] = [0.0; 8];
        soa.best_v[g] = [0.0; 8];
        soa.kz[g] = kz.store();
        let walked = (active >> (8 * g) & 0xff) as u32;
        if walked != 0 {
            // The group's shear axes are its first walked ray's; the rays that share
            // them are tested with rays in lanes.
            let j = walked.trailing_zeros() as usize;
            let (k, s) = (soa.kz[g][j], swap >> j & 1);
            soa.axes[g] = sheared_axes(k as usize, s != 0);
            let same = kz_lanes::<W>(&soa.kz[g], k) & !(swap ^ s.wrapping_neg()) & walked;
            lanes_all |= (same as u64) << (8 * g);
        }
        swap_all |= (swap as u64) << (8 * g);
        g += 1;
    }
    soa.swap = swap_all;
    soa.lanes = lanes_all;
}

/// The lanes of `kz` equal to `k`.
#[inline(always)]
fn kz_lanes<W: Wide>(kz: &[f32; 8], k: f32) -> u32 {
    W::load(kz).eq(W::splat(k)).bits()
}

/// The children of `n` that some ray of the packet may hit, from the packet's bounds (see
/// [`Frustum`]): a superset of the slots any walked ray's own test hits.
#[inline(always)]
fn frustum_hits<W: Wide>(n: &Node8, f: &Frustum) -> u32 {
    let mut tnear = W::splat(f.t_min);
    let mut tfar = W::splat(f.t_max);
    for a in 0..3 {
        let (lo, hi) = (W::splat(f.n_lo[a]), W::splat(f.n_hi[a]));
        // The near plane's index is `2 a` or `2 a + 1`, the far one's the other.
        let near = W::splat(f.o_near[a]).sub(W::load(&n.planes[f.near[a]]));
        let far = W::splat(f.o_far[a]).sub(W::load(&n.planes[f.near[a] ^ 1]));
        let near = near.mul(lo).min(near.mul(hi)).min(W::splat(f.cap_near[a]));
        let far = far.mul(lo).max(far.mul(hi)).max(W::splat(f.cap_far[a]));
        tnear = tnear.max(near);
        tfar = tfar.min(far);
    }
    let scale = tfar
        .lt(W::splat(0.0))
        .select(W::splat(BOX_TFAR_SCALE_NEG), W::splat(BOX_TFAR_SCALE));
    // Culled only where the entry bound is after the exit bound (NaN culls nothing).
    !tnear.gt(tfar.mul(scale)).bits() & n.used
}

/// The box test of group `g`'s eight rays against one box (`lo`, `hi` splatted): lane
/// for lane `box8`'s test for that ray, with the culling slack where the ray has a hit
/// (`culled`; without one its best is its `t_max`, where the slack changes nothing) and
/// the exit scale chosen by sign (`box8`'s `SIGNED` test, which serves every ray).
#[inline(always)]
fn group_box<W: Wide>(lo: &[W; 3], hi: &[W; 3], soa: &Soa, g: usize, culled: bool) -> u32 {
    let (mut near, mut far) = ([W::splat(0.0); 3], [W::splat(0.0); 3]);
    for a in 0..3 {
        let (o, ninv) = (W::load(&soa.org[g][a]), W::load(&soa.ninv[g][a]));
        let t0 = o.sub(lo[a]).mul(ninv);
        let t1 = o.sub(hi[a]).mul(ninv);
        near[a] = t0.min(t1);
        far[a] = t0.max(t1);
    }
    group_slabs::<W>(near, far, soa, g, culled)
}

/// The rest of [`group_box`] from the per-axis entries `near` and exits `far`.
#[inline(always)]
fn group_slabs<W: Wide>(near: [W; 3], far: [W; 3], soa: &Soa, g: usize, culled: bool) -> u32 {
    let tnear = near[0]
        .max(near[1])
        .max(near[2].max(W::load(&soa.t_min[g])));
    let t_max = W::load(&soa.t_max[g]);
    let limit = if culled {
        let kz = W::load(&soa.kz[g]);
        let (x, xy) = (kz.lt(W::splat(0.5)), kz.lt(W::splat(1.5)));
        let near_kz = x.select(near[0], xy.select(near[1], near[2]));
        let far_kz = x.select(far[0], xy.select(far[1], far[2]));
        let m = near_kz.abs().max(far_kz.abs());
        W::load(&soa.best_t[g])
            .add(W::splat(BOX_CULL_SLACK).mul(m))
            .min(t_max)
    } else {
        t_max
    };
    let tfar = far[0].min(far[1]).min(far[2].min(limit));
    let scale = tfar
        .lt(W::splat(0.0))
        .select(W::splat(BOX_TFAR_SCALE_NEG), W::splat(BOX_TFAR_SCALE));
    tnear.le(tfar.mul(scale)).bits()
}

/// The rays of `mask` that hit slot `c` of `n`: `groups` are the groups `mask` has rays
/// in and `found` those with a hit ([`groups_of`]), `f` the packet's bounds.
#[inline(always)]
fn child_rays<W: Wide>(
    n: &Node8,
    c: usize,
    soa: &Soa,
    (mask, groups): (u64, u32),
    found: u32,
    f: &Frustum,
) -> u64 {
    let mut out = 0u64;
    if f.common {
        // One origin `o` and one sign per axis (camera rays in a tile, mostly): per axis
        // the ray's `fmin(t0, t1)` is `(o - p) * -inv` at the near plane `p` (the lower
        // plane for a positive direction), `fmax` at the far one, to the bit but for the
        // sign of a zero, since the conversion keeps every lower plane at or below its
        // upper one; `o - p` is the same for every ray.
        let (mut dn, mut df) = ([W::splat(0.0); 3], [W::splat(0.0); 3]);
        for a in 0..3 {
            let near = f.near[a];
            dn[a] = W::splat(f.o_near[a] - n.planes[near][c]);
            df[a] = W::splat(f.o_near[a] - n.planes[near ^ 1][c]);
        }
        let mut gs = groups;
        while gs != 0 {
            let g = gs.trailing_zeros() as usize;
            gs &= gs - 1;
            let (m, culled) = (mask >> (8 * g) & 0xff, found >> g & 1 != 0);
            let mut near = [W::splat(0.0); 3];
            let mut far = near;
            for a in 0..3 {
                let ninv = W::load(&soa.ninv[g][a]);
                near[a] = dn[a].mul(ninv);
                far[a] = df[a].mul(ninv);
            }
            let bits = group_slabs::<W>(near, far, soa, g, culled) as u64;
            out |= (bits & m) << (8 * g);
        }
        return out;
    }
    let lo = [
        W::splat(n.planes[0][c]),
        W::splat(n.planes[2][c]),
        W::splat(n.planes[4][c]),
    ];
    let hi = [
        W::splat(n.planes[1][c]),
        W::splat(n.planes[3][c]),
        W::splat(n.planes[5][c]),
    ];
    let mut gs = groups;
    while gs != 0 {
        let g = gs.trailing_zeros() as usize;
        gs &= gs - 1;
        let (m, culled) = (mask >> (8 * g) & 0xff, found >> g & 1 != 0);
        let bits = group_box::<W>(&lo, &hi, soa, g, culled) as u64;
        out |= (bits & m) << (8 * g);
    }
    out
}

/// Bit `g` set when group `g` has a ray in `mask`.
#[inline(always)]
fn groups_of(mask: u64) -> u32 {
    // Each byte's bits gathered into its lowest, then the lowest bits of the eight bytes
    // into the top byte by one multiplication (no two partial products overlap).
    let x = mask | mask >> 4;
    let x = x | x >> 2;
    let x = (x | x >> 1) & 0x0101_0101_0101_0101;
    (x.wrapping_mul(0x0102_0408_1020_4080) >> 56) as u32
}

/// Tests node `node`'s children against the rays of `mask`; pushes the hit children but
/// one (a closest-hit walk the farther first along the packet's direction), and returns
/// the one to visit with its rays, or `None`.
#[inline(always)]
fn visit<W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    node: u32,
    mask: u64,
    st: &State<'_>,
    stack: &mut [PEntry],
    sp: &mut usize,
) -> Option<(u32, u64)> {
    let n = &bvh.nodes[node as usize];
    let mut rays = [0u64; WIDTH];
    let mut hit = [0usize; WIDTH];
    let mut len = 0;
    let mut used = frustum_hits::<W>(n, &st.frustum);
    let groups = (mask, groups_of(mask));
    let found = if ANY { 0 } else { groups_of(st.found) };
    while used != 0 {
        let c = used.trailing_zeros() as usize;
        used &= used - 1;
        let r = child_rays::<W>(n, c, st.soa, groups, found, &st.frustum);
        if r != 0 {
            rays[c] = r;
            hit[len] = c;
            len += 1;
        }
    }
    if len == 0 {
        return None;
    }
    if !ANY && len > 1 {
        // Nearest last: an insertion sort by the box centre along the packet's direction.
        // Every slot's key at once (twice the centre: the order is the same).
        let mut k = W::splat(0.0);
        for a in 0..3 {
            let centre = W::load(&n.planes[2 * a]).add(W::load(&n.planes[2 * a + 1]));
            k = k.add(centre.mul(W::splat(st.dir[a])));
        }
        let key = k.store();
        for i in 1..len {
            let mut j = i;
            while j > 0 && key[hit[j - 1]] < key[hit[j]] {
                hit.swap(j - 1, j);
                j -= 1;
            }
        }
    }
    for &c in &hit[..len - 1] {
        stack[*sp] = PEntry {
            mask: rays[c],
            parent: node,
            slot: c as u32,
        };
        *sp += 1;
    }
    let c = hit[len - 1];
    Some((n.child[c], rays[c]))
}

/// Groups with fewer rays than this in a leaf test them ray by ray: one ray's test of a
/// block (four triangles in lanes) costs about what one triangle against eight rays does.
const LANE_MIN: u32 = 2;

/// Tests leaf `child` for the rays of `mask`: eight rays at a time in lanes where a group
/// has enough rays sharing its shear axes, the others ray by ray with the single-ray test.
#[inline(always)]
fn leaf_rays<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    child: u32,
    mask: u64,
    st: &mut State<'_>,
) {
    let mut lanes = 0u64;
    let in_lanes = mask & st.soa.lanes;
    let mut gs = groups_of(in_lanes);
    while gs != 0 {
        let g = gs.trailing_zeros() as usize;
        gs &= gs - 1;
        let m = in_lanes >> (8 * g) & 0xff;
        if m.count_ones() >= LANE_MIN {
            lanes |= m << (8 * g);
            group_leaf::<W, ANY>(bvh, child, g, m as u32, st);
        }
    }
    let mut m = mask & !lanes;
    while m != 0 {
        let k = m.trailing_zeros() as usize;
        m &= m - 1;
        let (g, j) = (k / 8, k % 8);
        let soa = &mut *st.soa;
        let [kx, ky, kz] = sheared_axes(soa.kz[g][j] as usize, soa.swap >> k & 1 != 0);
        let shear = ShearLanes {
            kx,
            ky,
            kz,
            s: [
                L::splat(soa.shear[g][0][j]),
                L::splat(soa.shear[g][1][j]),
                L::splat(soa.shear[g][2][j]),
            ],
            o: [
                L::splat(soa.org[g][kx][j]),
                L::splat(soa.org[g][ky][j]),
                L::splat(soa.org[g][kz][j]),
            ],
        };
        let t_min = L::splat(soa.t_min[g][j]);
        let mut best = soa.best(g, j, st.found >> k & 1 != 0);
        let ray = RayAt::Ray(&st.rays[lane_order(st.rays.len())[k] as usize]);
        if single::leaf::<L, ANY>(bvh, t_min, &shear, ray, child, &mut best) {
            st.active &= !(1 << k);
        }
        if best.found {
            soa.set_best(g, j, &best);
            st.found |= 1 << k;
        }
    }
}

impl Soa {
    /// Lane `j` of group `g`'s best hit (`found`: it has one).
    #[inline(always)]
    fn best(&self, g: usize, j: usize, found: bool) -> Best {
        Best {
            t: self.best_t[g][j],
            prim: self.best_prim[g][j].to_bits(),
            u: self.best_u[g][j],
            v: self.best_v[g][j],
            found,
        }
    }

    /// Sets lane `j` of group `g`'s best hit.
    #[inline(always)]
    fn set_best(&mut self, g: usize, j: usize, b: &Best) {
        self.best_t[g][j] = b.t;
        self.best_prim[g][j] = f32::from_bits(b.prim);
        self.best_u[g][j] = b.u;
        self.best_v[g][j] = b.v;
    }
}

/// Tests leaf `child` for the rays `m` of group `g` (which share the group's shear axes),
/// triangle by triangle with the rays in lanes ([`tri_rays`]), taking hits by the hit rule
/// lane by lane.
#[inline(always)]
fn group_leaf<W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    child: u32,
    g: usize,
    mut m: u32,
    st: &mut State<'_>,
) {
    let soa = &mut *st.soa;
    let [kx, ky, kz] = soa.axes[g];
    let r = ShearRays {
        o: [
            W::load(&soa.org[g][kx]),
            W::load(&soa.org[g][ky]),
            W::load(&soa.org[g][kz]),
        ],
        s: [
            W::load(&soa.shear[g][0]),
            W::load(&soa.shear[g][1]),
            W::load(&soa.shear[g][2]),
        ],
        t_min: W::load(&soa.t_min[g]),
    };
    let (first, count) = leaf_range(child);
    for (n, b) in bvh.blocks[first..first + count].iter().enumerate() {
        // A hit of the lane before was refused by its leaf box (see below).
        let mut refused = false;
        for i in 0..4 {
            // A short block's free lanes repeat its last triangle (and a split builder
            // may put one triangle twice in a leaf): nothing new to find, unless the
            // repeat comes from another binary leaf, whose box may take a hit the one
            // before refused.
            if i > 0 && b.prim[i] == b.prim[i - 1] && !refused {
                continue;
            }
            refused = false;
            let c = [
                [b.v[0][kx][i], b.v[0][ky][i], b.v[0][kz][i]],
                [b.v[1][kx][i], b.v[1][ky][i], b.v[1][kz][i]],
                [b.v[2][kx][i], b.v[2][ky][i], b.v[2][kz][i]],
            ];
            let (ok, t, u, v) = tri_rays::<W>(&c, &r, m);
            // Only lanes at or before the best can be taken; the rule settles the ties.
            let mut ok = ok & t.le(W::load(&soa.best_t[g])).bits();
            if ok == 0 {
                continue;
            }
            let (t, u, v) = (t.store(), u.store(), v.store());
            while ok != 0 {
                let j = ok.trailing_zeros() as usize;
                ok &= ok - 1;
                let k = 8 * g + j;
                let mut best = soa.best(g, j, st.found >> k & 1 != 0);
                // A hit near an end of the interval is taken only where the binary walk
                // would test the triangle (see `LeafBoxes`); an any-hit ray's one hit
                // is always checked.
                let zs = [c[0][2], c[1][2], c[2][2]];
                let (oz, sz) = (soa.org[g][kz][j], soa.shear[g][2][j]);
                if (ANY || near_end(t[j], soa.t_min[g][j], soa.t_max[g][j], zs, oz, sz))
                    && !single::in_leaf_box(
                        bvh,
                        first + n,
                        i,
                        &RayAt::Ray(&st.rays[lane_order(st.rays.len())[k] as usize]),
                        best.t,
                    )
                {
                    refused = true;
                    continue;
                }
                if best.offer(t[j], b.prim[i], u[j], v[j]) {
                    soa.set_best(g, j, &best);
                    st.found |= 1 << k;
                    if ANY {
                        st.active &= !(1 << k);
                        m &= !(1 << j);
                    }
                }
            }
            if ANY && m == 0 {
                return;
            }
        }
    }
}

/// The packet walk from the root over the rays of `st.active`.
#[inline(always)]
fn walk<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    st: &mut State<'_>,
    stack: &mut [PEntry],
) {
    let mut sp = 0;
    let (mut child, mut mask) = (0u32, st.active);
    loop {
        if child & LEAF == 0 {
            if let Some(next) = visit::<W, ANY>(bvh, child, mask, st, stack, &mut sp) {
                (child, mask) = next;
                continue;
            }
        } else {
            leaf_rays::<L, W, ANY>(bvh, child, mask, st);
        }
        // Pop the next child that some ray still hits, against the rays' bests.
        loop {
            if sp == 0 || st.active == 0 {
                return;
            }
            sp -= 1;
            let e = stack[sp];
            let n = &bvh.nodes[e.parent as usize];
            mask = e.mask & st.active;
            if !ANY && mask & st.found != 0 {
                let (c, groups) = (e.slot as usize, (mask, groups_of(mask)));
                let found = groups_of(st.found);
                mask = child_rays::<W>(n, c, st.soa, groups, found, &st.frustum);
            }
            if mask != 0 {
                child = n.child[e.slot as usize];
                break;
            }
        }
    }
}

/// Traces `rays` in packets of [`PACKET`] consecutive rays into `hits`.
#[inline(always)]
pub(crate) fn run<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    rays: &[Ray],
    hits: &mut [Hit],
    s: &mut Scratch,
) {
    let mut start = 0;
    while start < rays.len() {
        let end = (start + PACKET).min(rays.len());
        let group = &rays[start..end];
        let (active, dir, frustum) = gather::<W>(bvh, group, &mut s.soa);
        let all = u64::MAX >> (PACKET - group.len());
        if active == all && frustum_hits::<W>(&bvh.nodes[0], &frustum) == 0 {
            // Every ray walks, and the bounds miss every box of the root: all miss (camera
            // rays past a framed object, tile by tile).
            for (h, r) in hits[start..end].iter_mut().zip(group) {
                *h = Hit::miss(r.t_max);
            }
            start = end;
            continue;
        }
        prepare::<W>(group.len(), active, &mut s.soa);
        let mut st = State {
            soa: &mut s.soa,
            rays: group,
            active,
            found: 0,
            dir,
            frustum,
        };
        if active != 0 {
            walk::<L, W, ANY>(bvh, &mut st, &mut s.stack);
        }
        store_hits::<L, W, ANY>(
            bvh,
            group,
            active,
            &s.soa,
            &mut hits[start..end],
            &mut s.single,
        );
        start = end;
    }
}

/// A best as the row `t`, `prim` (as bits), `u`, `v`: the layout of `Hit`, so that the
/// row is stored as one.
#[inline(always)]
fn hit_of(row: &[f32; 4]) -> Hit {
    const { assert!(size_of::<Hit>() == size_of::<[f32; 4]>()) };
    // SAFETY: `Hit` is `repr(C)` with four 4-byte fields (`t: f32`, `prim: u32`, `u`, `v`:
    // f32) and no padding (size checked above), and every bit pattern is a valid `u32`.
    unsafe { std::mem::transmute::<[f32; 4], Hit>(*row) }
}

/// Writes the packet's answers: the walked rays' bests (a miss at `t_max` is what the SoA
/// holds for a ray without a hit), eight at a time, then the single-ray walk's for the
/// others.
#[inline(always)]
fn store_hits<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    rays: &[Ray],
    active: u64,
    soa: &Soa,
    out: &mut [Hit],
    stack: &mut [Entry],
) {
    let order = lane_order(rays.len());
    let mut g = 0;
    while 8 * g < rays.len() {
        let h = W::rows4([
            W::load(&soa.best_t[g]),
            W::load(&soa.best_prim[g]),
            W::load(&soa.best_u[g]),
            W::load(&soa.best_v[g]),
        ]);
        let lanes = (rays.len() - 8 * g).min(8);
        for (j, row) in h.iter().enumerate().take(lanes) {
            out[order[8 * g + j] as usize] = hit_of(row);
        }
        g += 1;
    }
    let mut rest = !active & (u64::MAX >> (PACKET - rays.len()));
    while rest != 0 {
        let k = rest.trailing_zeros() as usize;
        rest &= rest - 1;
        let r = order[k] as usize;
        let p = Prepared::new::<W>(std::slice::from_ref(&rays[r]));
        out[r] = single::trace::<L, W, ANY>(bvh, &rays[r], &p, 0, stack);
    }
}

/// The order of a `width` x `height` image's pixels (row by row) in 8x8 tiles: tiles row
/// by row, each tile's pixels row by row (tiles at the right and bottom edges are cut).
/// `rays[tile_order(w, h)[k]]` put in that order make packets of one tile each when `w`
/// and `h` are multiples of 8.
pub fn tile_order(width: u32, height: u32) -> Vec<u32> {
    let mut out = Vec::with_capacity(width as usize * height as usize);
    for ty in (0..height).step_by(8) {
        for tx in (0..width).step_by(8) {
            for y in ty..(ty + 8).min(height) {
                for x in tx..(tx + 8).min(width) {
                    out.push(y * width + x);
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use bvhtrace_core::intersect::PreparedRay;
    use bvhtrace_core::{BuildOptions, FlatBvh, Ray};
    use glam::Vec3;

    use super::{
        PACKET, Scratch, Soa, child_rays, frustum_hits, group_rows, groups_of, lane_order, load,
    };
    use crate::CpuBvh;
    use crate::lanes::{Pair, Portable, Wide};
    use crate::layout::Node8;
    use crate::tests4::box_lane;
    use crate::tests4::tests::{next, point, ray, value};

    /// `child_rays` over lanes `W` against the scalar test of every ray of `active`, and
    /// the packet's bounds keeping every slot some ray hits.
    fn check_lanes<W: Wide>(
        n: &Node8,
        soa: &Soa,
        f: &super::Frustum,
        (active, found): (u64, u64),
        want: &[u64; 8],
    ) {
        let kept = frustum_hits::<W>(n, f);
        // The general test, and the one for a common origin and signs where they hold.
        let general = super::Frustum {
            common: false,
            ..*f
        };
        let (groups, found) = ((active, groups_of(active)), groups_of(found));
        for (c, &w) in want.iter().enumerate() {
            assert_eq!(
                child_rays::<W>(n, c, soa, groups, found, &general),
                w,
                "slot {c}"
            );
            assert_eq!(
                child_rays::<W>(n, c, soa, groups, found, f),
                w,
                "slot {c}, {}",
                f.common
            );
            assert!(
                w == 0 || kept >> c & 1 != 0,
                "slot {c} culled by the bounds"
            );
        }
    }

    /// `groups_of` marks exactly the bytes with a bit set.
    #[test]
    fn groups_of_marks_the_groups_with_rays() {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..20_000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            // Sparse masks too: some bytes empty, some with one bit.
            let mask = s & (s >> 7).rotate_left(13) & (s >> 3).rotate_left(29);
            let want = (0..8)
                .filter(|g| mask >> (8 * g) & 0xff != 0)
                .fold(0, |w, g| w | 1 << g);
            assert_eq!(groups_of(mask), want, "{mask:#018x}");
        }
        assert_eq!(groups_of(0), 0);
        assert_eq!(groups_of(u64::MAX), 0xff);
        assert_eq!(groups_of(1 << 63 | 1), 0x81);
    }

    /// Each group's rows are the rays `lane_order` gives its lanes, full packets and
    /// partial ones (whose missing lanes repeat the last ray).
    #[test]
    fn group_rows_follow_the_lane_order() {
        for len in 1..=PACKET {
            let rays: Vec<Ray> = (0..len)
                .map(|k| Ray::new(Vec3::splat(k as f32), Vec3::X))
                .collect();
            let order = lane_order(len);
            for g in 0..len.div_ceil(8) {
                let rows = group_rows(&rays, g);
                for (j, r) in rows.iter().enumerate() {
                    let k = (8 * g + j).min(len - 1);
                    assert_eq!(r[0], order[k] as f32, "{len} rays, group {g}, lane {j}");
                }
            }
        }
    }

    /// Each lane of the packet's box test is `intersect_box` of its ray at its best hit:
    /// random boxes and rays (the generators of the lane tests), bests at the ray's
    /// `t_max`, anywhere, or a few hundred ulps around the box's entry where the culling
    /// slack decides; portable, SSE and (where the CPU has it) AVX lanes.
    #[test]
    fn packet_box_lanes_are_the_scalar_test() {
        let tri = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let bvh =
            CpuBvh::from_flat(&FlatBvh::build(&[tri], &BuildOptions::default()).unwrap()).unwrap();
        let mut scratch = Scratch::new(&bvh);
        let mut s = 0x5eed_1234_abcd_0077u64;
        let (mut hits, mut near_best, mut culled, mut commons) = (0, 0, 0, 0);
        for _ in 0..1500 {
            let mut n = Node8::EMPTY;
            for i in 0..8 {
                let (a, b) = (point(&mut s), point(&mut s));
                for ax in 0..3 {
                    n.planes[2 * ax][i] = a[ax].min(b[ax]);
                    n.planes[2 * ax + 1][i] = a[ax].max(b[ax]);
                }
            }
            n.used = 0xff;
            // Full packets (lanes permuted) a third of the time, else 1 to 64 rays.
            let count = if next(&mut s) < 0.33 {
                PACKET
            } else {
                1 + (next(&mut s) * PACKET as f32) as usize % PACKET
            };
            let mut rays: Vec<Ray> = (0..count).map(|_| ray(&mut s)).collect();
            if next(&mut s) < 0.5 {
                // Coherent rays now and then: the bounds then cull some slots.
                let (o, mut d) = (rays[0].origin, Vec3::from(rays[0].dir));
                let m = d.abs().max_element();
                // Clear of the axes' planes, with a spread too small to change a sign:
                // one sign per axis for every ray (the box test for one origin and signs).
                let clear = next(&mut s) < 0.6 && m.is_finite() && m > 1e-30;
                if clear {
                    d = d.signum() * d.abs().max(Vec3::splat(0.3 * m));
                }
                for r in &mut rays {
                    r.origin = o;
                    let spread = if clear {
                        Vec3::new(next(&mut s), next(&mut s), next(&mut s)) * 2.0 - 1.0
                    } else {
                        point(&mut s)
                    };
                    r.dir = (d + spread * 0.01 * d.length()).to_array();
                }
            }
            let (active, _, frustum) = load::<Pair<Portable>>(&bvh, &rays, &mut scratch.soa);
            commons += u32::from(frustum.common);
            let order = lane_order(count);
            let mut found = 0u64;
            let mut best = [0.0f32; PACKET];
            for k in 0..count {
                let r = &rays[order[k] as usize];
                best[k] = r.t_max;
                if active >> k & 1 == 0 {
                    continue;
                }
                let entry = intersect_box_entry(&n, r, (next(&mut s) * 8.0) as usize % 8);
                best[k] = match ((next(&mut s) * 3.0) as u32, entry) {
                    (0, _) => continue,
                    (1, Some(e)) if e.is_finite() => {
                        near_best += 1;
                        let ulps = (next(&mut s) * 400.0) as i32 - 300;
                        f32::from_bits((e.to_bits() as i32).wrapping_add(ulps) as u32)
                    }
                    _ => value(&mut s),
                };
                found |= 1 << k;
                scratch.soa.best_t[k / 8][k % 8] = best[k];
            }
            let mut want = [0u64; 8];
            for (c, w) in want.iter_mut().enumerate() {
                for k in 0..count {
                    let r = &rays[order[k] as usize];
                    if active >> k & 1 != 0 && box_lane(&n, &PreparedRay::new(r), c, best[k]) {
                        *w |= 1 << k;
                    }
                }
                hits += w.count_ones();
            }
            let (soa, m) = (&scratch.soa, (active, found));
            check_lanes::<Pair<Portable>>(&n, soa, &frustum, m, &want);
            #[cfg(target_arch = "x86_64")]
            {
                check_lanes::<Pair<crate::lanes::Sse>>(&n, soa, &frustum, m, &want);
                if std::arch::is_x86_feature_detected!("avx2") {
                    check_lanes::<crate::lanes::Avx8>(&n, soa, &frustum, m, &want);
                }
            }
            culled += (frustum_hits::<Pair<Portable>>(&n, &frustum) ^ 0xff).count_ones();
        }
        assert!(hits > 7_000, "only {hits} box hits");
        println!(
            "{hits} box hits, {near_best} bests near an entry, {culled} slots culled, \
             {commons} packets with one origin and signs"
        );
        assert!(culled > 500, "only {culled} slots culled by the bounds");
        assert!(near_best > 300, "only {near_best} bests near an entry");
        assert!(
            commons > 300,
            "only {commons} packets with one origin and signs"
        );
    }

    /// The entry distance of `r` into slot `c`'s box, where it hits it.
    fn intersect_box_entry(n: &Node8, r: &Ray, c: usize) -> Option<f32> {
        let b = n.child_box(c);
        bvhtrace_core::intersect::intersect_box(&PreparedRay::new(r), b.min, b.max, r.t_max)
    }
}
