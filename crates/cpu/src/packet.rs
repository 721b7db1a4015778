//! Rays in packets: up to [`PACKET`] rays (an 8x8 screen tile of camera rays, say) walked
//! together through the 8-wide tree with one stack. A node's children are tested against
//! the packet's rays eight rays at a time (rays in lanes, one child box splatted), each
//! lane the single-ray walk's box test for that ray (its own origin, inverse, interval,
//! best hit and culling slack); a child is entered with the mask of the rays that hit it,
//! and a popped child is re-tested against the rays' bests. A leaf is tested ray by ray
//! with the single-ray triangle test. Rays along a slab, invalid rays and empty intervals
//! take the single-ray walk.
//!
//! The answers are the single-ray walk's: each ray meets every node the single walk
//! enters for it (the same test, at a best hit no nearer than the single walk's at that
//! point, since the bests only fall as triangles are taken), tests its leaves with the
//! same triangle test, and keeps its hits by the same order-independent rule.

use bvhtrace_core::intersect::{BOX_CULL_SLACK, BOX_TFAR_SCALE, BOX_TFAR_SCALE_NEG};
use bvhtrace_core::{Hit, Ray};

use crate::lanes::{Lanes, Wide};
use crate::layout::{CpuBvh, LEAF, Node8, WIDTH};
use crate::single::{self, Best, Entry};
use crate::tests4::{Prepared4, ShearLanes};

/// Rays per packet: eight groups of eight lanes.
pub const PACKET: usize = 64;
/// Groups of eight rays per packet.
const GROUPS: usize = PACKET / 8;

/// A packet's rays as lanes, ray `8 g + j` in lane `j` of group `g`.
#[derive(Clone)]
struct Soa {
    /// `org[g][axis]`: the origins.
    org: [[[f32; 8]; 3]; GROUPS],
    /// `-1 / dir` (see `RayLanes::ninv`).
    ninv: [[[f32; 8]; 3]; GROUPS],
    t_min: [[f32; 8]; GROUPS],
    t_max: [[f32; 8]; GROUPS],
    /// The best hit's `t` (the ray's `t_max` until it has one).
    best_t: [[f32; 8]; GROUPS],
    /// The dominant axis (`PreparedRay::kz`) as 0.0, 1.0 or 2.0.
    kz: [[f32; 8]; GROUPS],
}

/// What a thread keeps from packet to packet.
pub(crate) struct Scratch {
    soa: Box<Soa>,
    best: [Best; PACKET],
    prep: Vec<Prepared4>,
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
        let miss = Best::start(&Ray::new(glam::Vec3::ZERO, glam::Vec3::X));
        Scratch {
            soa: Box::new(Soa {
                org: [[[0.0; 8]; 3]; GROUPS],
                ninv: [[[0.0; 8]; 3]; GROUPS],
                t_min: zero,
                t_max: zero,
                best_t: zero,
                kz: zero,
            }),
            best: [miss; PACKET],
            prep: Vec::with_capacity(PACKET / 4),
            stack: vec![PEntry::default(); single::stack_size(bvh)],
            single: vec![Entry::default(); single::stack_size(bvh)],
        }
    }
}

/// The packet's state during a walk: its rays, their bests, and which are still walked.
struct State<'a> {
    soa: &'a mut Soa,
    best: &'a mut [Best; PACKET],
    prep: &'a [Prepared4],
    /// Rays walked together and not finished (an any-hit ray finishes at its first hit).
    active: u64,
    /// Rays that have a hit.
    found: u64,
    /// The sum of the walked rays' directions: children are visited in its order.
    dir: [f32; 3],
}

/// Loads up to [`PACKET`] rays: prepares them four at a time, and returns the mask of
/// those the packet walks (the others take the single-ray walk).
#[inline(always)]
fn load<L: Lanes>(bvh: &CpuBvh, rays: &[Ray], s: &mut Scratch) -> (u64, [f32; 3]) {
    s.prep.clear();
    let mut start = 0;
    while start < rays.len() {
        let end = (start + 4).min(rays.len());
        s.prep.push(Prepared4::new::<L>(&rays[start..end]));
        start = end;
    }
    let (mut active, mut dir) = (0u64, [0.0f32; 3]);
    for (k, ray) in rays.iter().enumerate() {
        let (p, i) = (&s.prep[k / 4], k % 4);
        s.best[k] = Best::start(ray);
        let walked = p.valid >> i & 1 != 0 && p.parallel >> i & 1 == 0;
        if !walked || bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
            continue;
        }
        active |= 1 << k;
        let (g, j) = (k / 8, k % 8);
        let soa = &mut *s.soa;
        for (a, d) in dir.iter_mut().enumerate() {
            soa.org[g][a][j] = p.org[a][i];
            soa.ninv[g][a][j] = p.ninv[a][i];
            *d += p.dir[a][i];
        }
        soa.t_min[g][j] = ray.t_min;
        soa.t_max[g][j] = ray.t_max;
        soa.best_t[g][j] = ray.t_max;
        soa.kz[g][j] = p.kz[i] as f32;
    }
    (active, dir)
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

/// The rays of `mask` that hit slot `c` of `n`.
#[inline(always)]
fn child_rays<W: Wide>(n: &Node8, c: usize, soa: &Soa, mask: u64, found: u64) -> u64 {
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
    let mut out = 0u64;
    for g in 0..GROUPS {
        let m = mask >> (8 * g) & 0xff;
        if m == 0 {
            continue;
        }
        let culled = found >> (8 * g) & 0xff != 0;
        let bits = group_box::<W>(&lo, &hi, soa, g, culled) as u64;
        out |= (bits & m) << (8 * g);
    }
    out
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
    let mut used = n.used;
    while used != 0 {
        let c = used.trailing_zeros() as usize;
        used &= used - 1;
        let r = child_rays::<W>(n, c, st.soa, mask, if ANY { 0 } else { st.found });
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
        let mut key = [0.0f32; WIDTH];
        for &c in &hit[..len] {
            let mut k = 0.0;
            for a in 0..3 {
                k += (n.planes[2 * a][c] + n.planes[2 * a + 1][c]) * st.dir[a];
            }
            key[c] = k;
        }
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

/// Tests leaf `child` for each ray of `mask`, ray by ray with the single-ray test.
#[inline(always)]
fn leaf_rays<L: Lanes, const ANY: bool>(bvh: &CpuBvh, child: u32, mask: u64, st: &mut State<'_>) {
    let mut m = mask;
    while m != 0 {
        let k = m.trailing_zeros() as usize;
        m &= m - 1;
        let (p, i) = (&st.prep[k / 4], k % 4);
        let (g, j) = (k / 8, k % 8);
        let shear = ShearLanes::<L>::from4(p, i, p.kz[i]);
        let t_min = L::splat(st.soa.t_min[g][j]);
        let best = &mut st.best[k];
        let (t0, p0) = (best.t, best.prim);
        if single::leaf::<L, ANY>(bvh, t_min, &shear, child, best) {
            st.active &= !(1 << k);
        }
        if best.t.to_bits() != t0.to_bits() || best.prim != p0 {
            st.soa.best_t[g][j] = best.t;
            st.found |= 1 << k;
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
            leaf_rays::<L, ANY>(bvh, child, mask, st);
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
                mask = child_rays::<W>(n, e.slot as usize, st.soa, mask, st.found);
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
        let (active, dir) = load::<L>(bvh, group, s);
        let mut st = State {
            soa: &mut s.soa,
            best: &mut s.best,
            prep: &s.prep,
            active,
            found: 0,
            dir,
        };
        if active != 0 {
            walk::<L, W, ANY>(bvh, &mut st, &mut s.stack);
        }
        for (k, ray) in group.iter().enumerate() {
            hits[start + k] = if active >> k & 1 != 0 {
                s.best[k].into_hit()
            } else {
                single::trace::<L, W, ANY>(bvh, ray, &s.prep[k / 4], k % 4, &mut s.single)
            };
        }
        start = end;
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

    use super::{PACKET, Scratch, Soa, child_rays, load};
    use crate::CpuBvh;
    use crate::lanes::{Pair, Portable, Wide};
    use crate::layout::Node8;
    use crate::tests4::box_lane;
    use crate::tests4::tests::{next, point, ray, value};

    /// `child_rays` over lanes `W` against the scalar test of every ray of `active`.
    fn check_lanes<W: Wide>(n: &Node8, soa: &Soa, active: u64, found: u64, want: &[u64; 8]) {
        for (c, &w) in want.iter().enumerate() {
            assert_eq!(child_rays::<W>(n, c, soa, active, found), w, "slot {c}");
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
        let (mut hits, mut near_best) = (0, 0);
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
            let count = 1 + (next(&mut s) * PACKET as f32) as usize % PACKET;
            let rays: Vec<Ray> = (0..count).map(|_| ray(&mut s)).collect();
            let (active, _) = load::<Portable>(&bvh, &rays, &mut scratch);
            let mut found = 0u64;
            let mut best = [0.0f32; PACKET];
            for (k, r) in rays.iter().enumerate() {
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
                        f32::from_bits((e.to_bits() as i32 + ulps) as u32)
                    }
                    _ => value(&mut s),
                };
                found |= 1 << k;
                scratch.soa.best_t[k / 8][k % 8] = best[k];
            }
            let mut want = [0u64; 8];
            for (c, w) in want.iter_mut().enumerate() {
                for (k, r) in rays.iter().enumerate() {
                    if active >> k & 1 != 0 && box_lane(&n, &PreparedRay::new(r), c, best[k]) {
                        *w |= 1 << k;
                    }
                }
                hits += w.count_ones();
            }
            check_lanes::<Pair<Portable>>(&n, &scratch.soa, active, found, &want);
            #[cfg(target_arch = "x86_64")]
            {
                check_lanes::<Pair<crate::lanes::Sse>>(&n, &scratch.soa, active, found, &want);
                if std::arch::is_x86_feature_detected!("avx2") {
                    check_lanes::<crate::lanes::Avx8>(&n, &scratch.soa, active, found, &want);
                }
            }
        }
        assert!(hits > 7_000, "only {hits} box hits");
        println!("{hits} box hits, {near_best} bests near an entry");
        assert!(near_best > 300, "only {near_best} bests near an entry");
    }

    /// The entry distance of `r` into slot `c`'s box, where it hits it.
    fn intersect_box_entry(n: &Node8, r: &Ray, c: usize) -> Option<f32> {
        let b = n.child_box(c);
        bvhtrace_core::intersect::intersect_box(&PreparedRay::new(r), b.min, b.max, r.t_max)
    }
}
