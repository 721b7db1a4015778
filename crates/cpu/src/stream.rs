//! Rays walked as a stream (Barringer and Akenine-Möller 2014, "Dynamic ray stream
//! traversal"): the rays of a run go down the tree together, each node's eight boxes
//! tested against every ray that reached it and the rays handed on to the children they
//! hit. A ray walked alone waits on each node's memory before it can choose the next;
//! here the tests of one node for different rays do not depend on one another, and the
//! children's memory is asked for as soon as they are known, so incoherent rays, whose
//! walks are chains of cache misses, keep the CPU busy.
//!
//! Each ray's hit is the one its own walk finds: every leaf a ray's own walk could take a
//! hit from is tested for it (the box tests are [`box8`]'s, culled by the ray's own best
//! hit), and the hit rule does not depend on the order.

use bvhtrace_core::{Hit, Query, Ray};

use crate::lanes::{Lanes, Wide};
use crate::layout::{CpuBvh, LEAF, WIDTH};
use crate::single::{Best, Entry, Site, fetch, leaf_at, untraced};
use crate::tests4::{MINMAX, Prepared, RAYS, RUN_AXIS, RayAt, RayLanes, ShearLanes, box8};

/// A node or leaf and the rays that reach it: `ids[start..start + len]`.
#[derive(Clone, Copy)]
struct Frame {
    child: u32,
    start: u32,
    len: u32,
}

/// What a box test reads of a ray, in one place (a stream's rays are read in the order
/// the nodes take them): [`Prepared`]'s origin and `ninv`, and the interval.
#[derive(Clone, Copy, Default)]
#[repr(C, align(32))]
struct BoxRay {
    org: [f32; 3],
    t_min: f32,
    ninv: [f32; 3],
    t_max: f32,
}

/// A stream's memory, kept between runs: the rays prepared (in groups, and for the box
/// tests one by one), their dominant axes and best hits, the rays streamed, the ray
/// lists of the nodes waiting, and a node's hit slots per ray and lists per slot while it
/// is tested.
#[derive(Default)]
pub(crate) struct StreamScratch {
    prepared: Vec<Prepared>,
    boxes: Vec<BoxRay>,
    kz: Vec<u8>,
    best: Vec<Best>,
    streamed: Vec<u32>,
    ids: Vec<u32>,
    frames: Vec<Frame>,
    masks: Vec<u32>,
    slots: Vec<u32>,
}

/// The rays a stream takes at most (their ids, times [`WIDTH`], fit a `u32`).
pub(crate) const STREAM_MAX: usize = 1 << 24;

/// [`trace_stream`] for `query`.
#[inline(always)]
pub(crate) fn trace<L: Lanes, W: Wide>(
    bvh: &CpuBvh,
    rays: &[Ray],
    query: Query,
    hits: &mut [Hit],
    s: &mut StreamScratch,
    stack: &mut [Entry],
) {
    match query {
        Query::Closest => trace_stream::<L, W, false>(bvh, rays, hits, s, stack),
        Query::Any => trace_stream::<L, W, true>(bvh, rays, hits, s, stack),
    }
}

/// Traces `rays` (at most [`STREAM_MAX`]) through one mesh without masks as one stream,
/// their hits written to `hits`; the rays of the rare kinds (along a slab, or starting
/// behind their origin) walk alone on `stack` ([`crate::single::stack_size`] entries or
/// more).
#[inline(always)]
fn trace_stream<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    rays: &[Ray],
    hits: &mut [Hit],
    s: &mut StreamScratch,
    stack: &mut [Entry],
) {
    debug_assert!(rays.len() <= STREAM_MAX && hits.len() == rays.len());
    prepare::<L, W, ANY>(bvh, rays, hits, s, stack);
    if s.streamed.is_empty() {
        return;
    }
    s.ids.clone_from(&s.streamed);
    s.masks.resize(s.ids.len(), 0);
    s.frames.clear();
    s.frames.push(Frame {
        child: 0,
        start: 0,
        len: s.ids.len() as u32,
    });
    while let Some(f) = s.frames.pop() {
        if f.child & LEAF != 0 {
            leaf::<L, ANY>(bvh, rays, f, s);
        } else {
            node::<L, W, ANY>(bvh, f, s);
        }
    }
    for &id in &s.streamed {
        hits[id as usize] = s.best[id as usize].into_hit();
    }
}

/// Prepares `rays` in groups; answers those that need no walk, walks the rare kinds
/// alone, and lists the rest in `s.streamed`.
#[inline(always)]
fn prepare<L: Lanes, W: Wide, const ANY: bool>(
    bvh: &CpuBvh,
    rays: &[Ray],
    hits: &mut [Hit],
    s: &mut StreamScratch,
    stack: &mut [Entry],
) {
    s.prepared.clear();
    s.boxes.clear();
    s.kz.clear();
    s.best.clear();
    s.streamed.clear();
    for (g, group) in rays.chunks(RAYS).enumerate() {
        let mut p = Prepared::for_boxes::<W>(group);
        let enter = p.may_enter::<W>(bvh.scene_box.as_ref());
        p.shear::<W>();
        for (i, ray) in group.iter().enumerate() {
            let id = g * RAYS + i;
            s.best.push(Best::start(ray));
            s.boxes.push(BoxRay {
                org: [p.org[0][i], p.org[1][i], p.org[2][i]],
                t_min: ray.t_min,
                ninv: [p.ninv[0][i], p.ninv[1][i], p.ninv[2][i]],
                t_max: ray.t_max,
            });
            s.kz.push(p.kz[i] as u8);
            if p.valid >> i & 1 == 0 {
                hits[id] = untraced(ray);
            } else if bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) || enter >> i & 1 == 0 {
                hits[id] = Best::start(ray).into_hit();
            } else if p.parallel >> i & 1 != 0 || ray.t_min < 0.0 {
                hits[id] = crate::single::trace::<L, W, ANY>(bvh, ray, &p, i, stack);
            } else {
                s.streamed.push(id as u32);
            }
        }
        s.prepared.push(p);
    }
}

/// Tests the rays of frame `f` (a leaf) against its blocks.
#[inline(always)]
fn leaf<L: Lanes, const ANY: bool>(bvh: &CpuBvh, rays: &[Ray], f: Frame, s: &mut StreamScratch) {
    let (start, end) = (f.start as usize, (f.start + f.len) as usize);
    for k in start..end {
        let id = s.ids[k] as usize;
        if ANY && s.best[id].found {
            continue;
        }
        let (p, i) = (&s.prepared[id / RAYS], id % RAYS);
        let ray = &rays[id];
        let shear = ShearLanes::<L>::from_prepared(p, i, p.kz[i]);
        let at = RayAt::Lanes {
            p,
            i,
            t_min: ray.t_min,
            t_max: ray.t_max,
        };
        let t_min = L::splat(ray.t_min);
        let best = &mut s.best[id];
        leaf_at::<CpuBvh, L, ANY, false>(bvh, t_min, &shear, at, f.child, best, Site::PLAIN);
    }
    s.ids.truncate(start);
}

/// Tests the rays of frame `f` (a node) against its boxes, and pushes a frame for each
/// child some ray hits, asking for its memory, nearest last (by the entry distances
/// summed over the rays).
#[inline(always)]
fn node<L: Lanes, W: Wide, const ANY: bool>(bvh: &CpuBvh, f: Frame, s: &mut StreamScratch) {
    let StreamScratch {
        boxes,
        best,
        kz,
        ids,
        frames,
        masks,
        slots,
        ..
    } = s;
    let n = &bvh.nodes[f.child as usize];
    let (start, end) = (f.start as usize, (f.start + f.len) as usize);
    let list = &ids[start..end];
    let masks = &mut masks[..list.len()];
    let mut near = W::splat(0.0);
    let mut any = 0;
    for (&id, mask) in list.iter().zip(masks.iter_mut()) {
        let id = id as usize;
        assert!(id < best.len() && id < boxes.len() && id < kz.len());
        let b = best[id];
        let r = &boxes[id];
        let q = RayLanes::<L, W> {
            // No `array::map`: its closure would be compiled apart from an AVX2 caller.
            org: [W::splat(r.org[0]), W::splat(r.org[1]), W::splat(r.org[2])],
            ninv: [
                W::splat(r.ninv[0]),
                W::splat(r.ninv[1]),
                W::splat(r.ninv[2]),
            ],
            t_min: W::splat(r.t_min),
            t_max: W::splat(r.t_max),
            t_min4: L::splat(r.t_min),
            kz: usize::from(kz[id]),
            parallel: false,
            dir: [0.0; 3],
            t_max_s: r.t_max,
            t_min_s: r.t_min,
        };
        let culled = !ANY && b.found;
        let hit = box8::<L, W, false, false, RUN_AXIS, MINMAX>(n, &q, b.t, culled);
        near = near.add(hit.tnear);
        // A ray whose any-hit query has stopped goes no further.
        *mask = if ANY && b.found { 0 } else { hit.hit };
        any |= *mask;
    }
    // Farthest first, so that the nearest is walked first.
    let near = near.store();
    let mut order = [0usize; WIDTH];
    let mut len = 0;
    for c in 0..WIDTH {
        order[len] = c;
        len += (any >> c & 1) as usize;
    }
    for i in 1..len {
        let mut j = i;
        while j > 0 && near[order[j - 1]] < near[order[j]] {
            order.swap(j - 1, j);
            j -= 1;
        }
    }
    let rays = end - start;
    // Each ray written to every slot's list, kept by the hit ones: one pass, no
    // branch, the eight write positions in registers.
    slots.resize(WIDTH * rays, 0);
    let mut pos: [usize; WIDTH] = std::array::from_fn(|c| c * rays);
    for (&id, &m) in ids[start..end].iter().zip(masks.iter()) {
        for (c, p) in pos.iter_mut().enumerate() {
            // SAFETY: `pos[c]` starts at `c * rays` and grows by at most one per ray,
            // so it stays below `(c + 1) * rays <= slots.len()`.
            unsafe { *slots.get_unchecked_mut(*p) = id };
            *p += (m >> c & 1) as usize;
        }
    }
    ids.truncate(start);
    for &c in &order[..len] {
        fetch(bvh, n.child[c]);
        frames.push(Frame {
            child: n.child[c],
            start: ids.len() as u32,
            len: (pos[c] - c * rays) as u32,
        });
        ids.extend_from_slice(&slots[c * rays..pos[c]]);
    }
}

#[cfg(test)]
mod tests {
    use bvhtrace_core::surface::uniform2;
    use bvhtrace_core::{Hit, Query, Ray};
    use glam::Vec3;

    use crate::single::{Entry, stack_size};
    use crate::{CpuBvh, Isa, trace_ray};

    /// A grid of small triangles in a cube, tilted and shifted so that no box is flat.
    fn scene() -> CpuBvh {
        let tris: Vec<_> = (0..512)
            .map(|i| {
                let c = Vec3::new((i % 8) as f32, (i / 8 % 8) as f32, (i / 64) as f32);
                let c = c + Vec3::new(0.1, 0.2, 0.3) * ((i % 5) as f32 * 0.3);
                [
                    c,
                    c + Vec3::new(0.7, 0.1, 0.2),
                    c + Vec3::new(0.1, 0.7, -0.3),
                ]
            })
            .collect();
        let flat = bvhtrace_core::FlatBvh::build(&tris, &Default::default()).unwrap();
        CpuBvh::from_flat(&flat).unwrap()
    }

    /// Rays from points in and around the cube in every direction, and every rare kind:
    /// along an axis, starting behind their origin, empty or invalid intervals, NaN.
    fn rays(n: u32) -> Vec<Ray> {
        (0..n)
            .map(|i| {
                let f = |k: u32| uniform2(i, k).0 * 2.0 - 1.0;
                let o = Vec3::new(f(0), f(1), f(2)) * 6.0 + Vec3::splat(4.0);
                let d = Vec3::new(f(3), f(4), f(5));
                match i % 23 {
                    3 => Ray::new(o, Vec3::new(0.0, -0.0, if i % 2 == 0 { 1.0 } else { -1.0 })),
                    5 => Ray::with_interval(o, d, -2.0, f32::INFINITY),
                    7 => Ray::with_interval(o, d, 0.5, 4.0),
                    11 => Ray::with_interval(o, d, 3.0, 1.0),
                    13 => Ray::new(o, Vec3::ZERO),
                    17 => Ray::new(Vec3::new(f32::NAN, 0.0, 0.0), d),
                    19 => Ray::new(o + Vec3::splat(100.0), d.abs()),
                    _ => Ray::new(o, d),
                }
            })
            .collect()
    }

    #[test]
    fn streams_answer_as_rays_walked_alone() {
        let bvh = scene();
        let rs = rays(3000);
        let isas = Isa::all_available();
        for q in [Query::Closest, Query::Any] {
            let one: Vec<Hit> = rs.iter().map(|r| trace_ray(&bvh, r, q)).collect();
            let hits = one.iter().filter(|h| h.is_hit()).count();
            assert!(hits > 300 && hits < 2700, "{hits} hits: rays of both kinds");
            for &isa in &isas {
                let mut s = super::StreamScratch::default();
                let mut stack = vec![Entry::default(); stack_size(&bvh)];
                let mut got = vec![Hit::miss(0.0); rs.len()];
                // Two streams on one scratch: nothing is left over from the first.
                let (a, b) = rs.split_at(1000);
                let (ha, hb) = got.split_at_mut(1000);
                super::super::trace_stream_on(&bvh, a, q, isa, ha, &mut s, &mut stack);
                super::super::trace_stream_on(&bvh, b, q, isa, hb, &mut s, &mut stack);
                for ((r, g), w) in rs.iter().zip(&got).zip(&one) {
                    let bits = |h: &Hit| (h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits());
                    if q == Query::Closest || !w.is_hit() {
                        assert_eq!(bits(g), bits(w), "{isa} {q:?} {r:?}");
                    } else {
                        // Which blocker an any-hit query returns may differ; a hit it is.
                        let closest = trace_ray(&bvh, r, Query::Closest);
                        assert!(g.is_hit() && g.t >= closest.t && g.t <= r.t_max, "{r:?}");
                    }
                }
            }
        }
    }
}
