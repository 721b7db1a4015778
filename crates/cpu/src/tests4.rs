//! The box and triangle tests over four lanes: lane for lane the f32 operations of
//! `bvhtrace_core::intersect::{intersect_box, intersect_triangle}`, in the same order.

use bvhtrace_core::intersect::{BOX_CULL_SLACK, BOX_TFAR_SCALE, BOX_TFAR_SCALE_NEG, PreparedRay};

use crate::lanes::Lanes;
use crate::layout::{Node4, Tri4};

/// A prepared ray, splatted into lanes once per ray.
#[derive(Clone, Copy)]
pub(crate) struct RayLanes<L> {
    /// The scalar preparation (axes, flags, interval).
    pub r: PreparedRay,
    pub org: [L; 3],
    pub inv: [L; 3],
    pub t_min: L,
    pub t_max: L,
    /// `sx`, `sy`, `sz` of the watertight test.
    pub shear: [L; 3],
    /// Per axis, the index in [`Node4::planes`] of the plane the ray meets first (`lo`
    /// for a positive component); the other is `near ^ 1`.
    pub near: [usize; 3],
}

impl<L: Lanes> RayLanes<L> {
    #[inline(always)]
    pub fn new(r: PreparedRay) -> Self {
        RayLanes {
            r,
            org: [0, 1, 2].map(|a| L::splat(r.org[a])),
            inv: [0, 1, 2].map(|a| L::splat(r.inv_dir[a])),
            t_min: L::splat(r.t_min),
            t_max: L::splat(r.t_max),
            shear: [L::splat(r.sx), L::splat(r.sy), L::splat(r.sz)],
            near: [0, 1, 2].map(|a| 2 * a + usize::from(r.inv_dir[a] < 0.0)),
        }
    }
}

/// A node's four box tests: the hit slots (used ones only), and per lane the entry
/// distance, the culling slack's magnitude `m` and the slabs' exit distance before the
/// interval's end is applied (what [`still_hit`] re-tests a popped child with).
///
/// A ray along no slab takes each axis's entry from the plane its direction faces first
/// (`lo` for a positive component): since `lo <= hi`, rounding keeps
/// `(lo - o) * inv <= (hi - o) * inv` for a positive `inv` (the reverse for a negative
/// one), so that plane's distance is the scalar test's `fmin(t0, t1)` and the other its
/// `fmax` (to the bit, but for the sign of a zero that an underflow gives, which no
/// comparison sees): two operations fewer per axis, and no lane select.
#[inline(always)]
pub(crate) fn box4<L: Lanes>(n: &Node4, q: &RayLanes<L>, t_best: f32) -> (u32, L, L, L) {
    let r = &q.r;
    let (near, far) = if r.parallel {
        parallel_slabs(n, q)
    } else {
        let plane = |a: usize, p: usize| L::load(&n.planes[p]).sub(q.org[a]).mul(q.inv[a]);
        (
            [0, 1, 2].map(|a| plane(a, q.near[a])),
            [0, 1, 2].map(|a| plane(a, q.near[a] ^ 1)),
        )
    };
    let tnear = near[0].max(near[1]).max(near[2].max(q.t_min));
    let m = match r.kz {
        0 => near[0].abs().max(far[0].abs()),
        1 => near[1].abs().max(far[1].abs()),
        _ => near[2].abs().max(far[2].abs()),
    };
    let limit = L::splat(t_best)
        .add(L::splat(BOX_CULL_SLACK).mul(m))
        .min(q.t_max);
    let slabs = far[0].min(far[1]).min(far[2]);
    let tfar = far[0].min(far[1]).min(far[2].min(limit));
    let scale = tfar
        .lt(L::splat(0.0))
        .select(L::splat(BOX_TFAR_SCALE_NEG), L::splat(BOX_TFAR_SCALE));
    let hit = tnear.le(tfar.mul(scale)).bits() & n.used;
    (hit, tnear, m, slabs)
}

/// The per-axis `fmin(t0, t1)` and `fmax(t0, t1)` of the scalar test's general path, for
/// rays along some slab: inside the slab for every t, or for none.
#[inline(never)]
fn parallel_slabs<L: Lanes>(n: &Node4, q: &RayLanes<L>) -> ([L; 3], [L; 3]) {
    let r = &q.r;
    let mut near = [L::splat(0.0); 3];
    let mut far = near;
    for a in 0..3 {
        let (lo, hi) = (L::load(&n.planes[2 * a]), L::load(&n.planes[2 * a + 1]));
        let (mut t0, mut t1) = (
            lo.sub(q.org[a]).mul(q.inv[a]),
            hi.sub(q.org[a]).mul(q.inv[a]),
        );
        if r.dir[a] == 0.0 {
            let o = q.org[a];
            let inside = lo.le(o).and(o.le(hi));
            t0 = inside.select(L::splat(f32::NEG_INFINITY), L::splat(f32::INFINITY));
            t1 = L::splat(f32::INFINITY);
        }
        near[a] = t0.min(t1);
        far[a] = t0.max(t1);
    }
    (near, far)
}

/// The box test of a child [`box4`] hit, repeated against a nearer best hit from its
/// entry distance, slack magnitude and slab exit: the same answer as the full test
/// (`min` over finite values is associative, and a signed zero compares as zero).
#[inline(always)]
pub(crate) fn still_hit(r: &PreparedRay, tnear: f32, m: f32, far: f32, t_best: f32) -> bool {
    let fmin = |a: f32, b: f32| if a < b { a } else { b };
    let limit = fmin(t_best + BOX_CULL_SLACK * m, r.t_max);
    let tfar = fmin(far, limit);
    let tfar = tfar
        * if tfar < 0.0 {
            BOX_TFAR_SCALE_NEG
        } else {
            BOX_TFAR_SCALE
        };
    tnear <= tfar
}

/// The scalar box test of slot `i` of `n` (what [`box4`]'s lane `i` must equal).
#[cfg(test)]
fn box_lane(n: &Node4, r: &PreparedRay, i: usize, t_best: f32) -> bool {
    let b = n.child_box(i);
    let (lo, hi) = (b.min, b.max);
    bvhtrace_core::intersect::intersect_box(r, lo, hi, t_best).is_some()
}

/// The edge function of `intersect::edge` over lanes: the corners taken in one fixed
/// order, the sign restored (`-(q.x p.y - q.y p.x)` is not `p.x q.y - p.y q.x` for a zero).
#[inline(always)]
fn edge<L: Lanes>(px: L, py: L, qx: L, qy: L) -> L {
    let swap = px.gt(qx).or(px.eq(qx).and(py.gt(qy)));
    let (pq, qp) = (px.mul(qy), py.mul(qx));
    swap.select(qp.sub(pq).neg(), pq.sub(qp))
}

/// The watertight test on a block's four triangles: the lanes that hit at `t >= t_min`,
/// and per lane `t` and the weights of corners 1 and 2.
#[inline(always)]
pub(crate) fn tri4<L: Lanes>(b: &Tri4, q: &RayLanes<L>) -> (u32, L, L, L) {
    let r = &q.r;
    let (kx, ky, kz) = (r.kx, r.ky, r.kz);
    let [sx, sy, sz] = q.shear;
    let rel = |c: usize, a: usize| L::load(&b.v[c][a]).sub(q.org[a]);
    let (az, bz, cz) = (rel(0, kz), rel(1, kz), rel(2, kz));
    let ax = rel(0, kx).sub(sx.mul(az));
    let ay = rel(0, ky).sub(sy.mul(az));
    let bx = rel(1, kx).sub(sx.mul(bz));
    let by = rel(1, ky).sub(sy.mul(bz));
    let cx = rel(2, kx).sub(sx.mul(cz));
    let cy = rel(2, ky).sub(sy.mul(cz));
    let u = edge(cx, cy, bx, by);
    let v = edge(ax, ay, cx, cy);
    let w = edge(bx, by, ax, ay);
    let zero = L::splat(0.0);
    let negative = u.lt(zero).or(v.lt(zero)).or(w.lt(zero));
    let positive = u.gt(zero).or(v.gt(zero)).or(w.gt(zero));
    let det = u.add(v).add(w);
    let t_scaled = u
        .mul(sz.mul(az))
        .add(v.mul(sz.mul(bz)))
        .add(w.mul(sz.mul(cz)));
    let inv_det = L::splat(1.0).div(det);
    let t = t_scaled.mul(inv_det);
    let mixed = negative.and(positive).bits();
    let ok = t.ge(q.t_min).bits() & !mixed & !det.eq(zero).bits();
    (ok, t, v.mul(inv_det), w.mul(inv_det))
}

#[cfg(test)]
mod tests {
    use bvhtrace_core::intersect::{PreparedRay, intersect_triangle};
    use bvhtrace_core::{Aabb, Ray};
    use glam::Vec3;

    use super::{RayLanes, box_lane, box4, still_hit, tri4};
    use crate::lanes::{Lanes, Portable};
    use crate::layout::{Node4, Tri4};

    fn next(s: &mut u64) -> f32 {
        *s ^= *s << 13;
        *s ^= *s >> 7;
        *s ^= *s << 17;
        (*s >> 40) as f32 / (1u64 << 24) as f32
    }

    /// A value from several regimes: ordinary, tiny, huge, exact small ones and zeros.
    fn value(s: &mut u64) -> f32 {
        let x = next(s) * 2.0 - 1.0;
        match (next(s) * 6.0) as u32 {
            0 => x * 1e-3,
            1 => x * 1e6,
            2 => 0.0,
            3 => (x * 4.0).round() * 0.5,
            _ => x * 10.0,
        }
    }

    fn point(s: &mut u64) -> Vec3 {
        Vec3::new(value(s), value(s), value(s))
    }

    fn ray(s: &mut u64) -> Ray {
        let mut d = point(s);
        // Axis-parallel with signed zeros, and subnormal components, now and then.
        match (next(s) * 5.0) as u32 {
            0 => d = Vec3::new(-0.0, if next(s) < 0.5 { 1.0 } else { -1.0 }, 0.0),
            1 => d.x = 1e-40,
            _ => {}
        }
        if d == Vec3::ZERO {
            d = Vec3::Z;
        }
        let t_min = if next(s) < 0.2 { -value(s).abs() } else { 0.0 };
        let t_max = if next(s) < 0.3 {
            value(s).abs()
        } else {
            f32::INFINITY
        };
        Ray::with_interval(point(s), d, t_min, t_max)
    }

    /// Each lane of the four-box test is the scalar box test of its box, on both lane
    /// types, including the parallel path and a finite running best.
    #[test]
    fn box_lanes_are_the_scalar_test() {
        let mut s = 0x1234_5678_9abc_def1u64;
        let (mut hits, mut culled) = (0, 0);
        for _ in 0..20_000 {
            let mut n = Node4::EMPTY;
            for i in 0..4 {
                let (a, b) = (point(&mut s), point(&mut s));
                let bx = Aabb {
                    min: a.min(b),
                    max: a.max(b),
                };
                for ax in 0..3 {
                    n.planes[2 * ax][i] = bx.min[ax];
                    n.planes[2 * ax + 1][i] = bx.max[ax];
                }
            }
            n.used = if next(&mut s) < 0.2 { 0b0111 } else { 0b1111 };
            let ray = ray(&mut s);
            if !ray.is_valid() {
                continue;
            }
            let r = PreparedRay::new(&ray);
            let t_best = if next(&mut s) < 0.5 {
                ray.t_max
            } else {
                value(&mut s)
            };
            let want = (0..4)
                .filter(|&i| n.used >> i & 1 != 0 && box_lane(&n, &r, i, t_best))
                .fold(0, |m, i| m | 1 << i);
            let (got, tnear, m, far) = box4(&n, &RayLanes::<Portable>::new(r), t_best);
            assert_eq!(got, want, "{ray:?} {n:?} t_best {t_best}");
            // A popped child re-tested against a nearer best: the full test's answer, for
            // bests a few ulps around its entry, where the culling slack decides.
            let (tnear, m, far) = (tnear.store(), m.store(), far.store());
            for i in (0..4).filter(|i| want >> i & 1 != 0) {
                let ulps = (next(&mut s) * 400.0) as i32 - 300;
                let nearer = f32::from_bits((tnear[i].to_bits() as i32 + ulps) as u32);
                if nearer.is_finite() {
                    let full = box_lane(&n, &r, i, nearer);
                    assert_eq!(
                        still_hit(&r, tnear[i], m[i], far[i], nearer),
                        full,
                        "{ray:?} lane {i} best {nearer}"
                    );
                    culled += u32::from(!full);
                }
            }
            #[cfg(target_arch = "x86_64")]
            {
                let (sse, ..) = box4(&n, &RayLanes::<crate::lanes::Sse>::new(r), t_best);
                assert_eq!(sse, want, "{ray:?}");
            }
            hits += want.count_ones();
        }
        assert!(hits > 5_000, "only {hits} box hits");
        assert!(culled > 300, "only {culled} re-tests culled");
    }

    /// Each lane of the four-triangle test is `intersect_triangle` of its triangle: the
    /// same hits, and `t`, `u`, `v` to the bit (signed zeros included).
    #[test]
    fn triangle_lanes_are_the_scalar_test() {
        let mut s = 0x0fed_cba9_8765_4321u64;
        let mut hits = 0;
        for k in 0..40_000 {
            let mut b = Tri4 {
                v: [[[0.0; 4]; 3]; 3],
                prim: [0; 4],
            };
            let mut tris = [[Vec3::ZERO; 3]; 4];
            for (lane, t) in tris.iter_mut().enumerate() {
                let c = point(&mut s);
                *t = match k % 5 {
                    // Small triangles around a point the ray is aimed at, and slivers.
                    0 | 1 => [c, c + point(&mut s) * 0.1, c + point(&mut s) * 0.1],
                    2 => [c, c + Vec3::X, c + Vec3::X * 2.0 + Vec3::Y * 1e-6],
                    _ => [c, point(&mut s), point(&mut s)],
                };
                for (ci, corner) in t.iter().enumerate() {
                    for a in 0..3 {
                        b.v[ci][a][lane] = corner[a];
                    }
                }
            }
            let mut ray = ray(&mut s);
            if k % 2 == 0 {
                // Aim at a lane's triangle, so that many lanes hit.
                let t = tris[k % 4];
                let aim =
                    t[0] + (t[1] - t[0]) * next(&mut s) * 0.5 + (t[2] - t[0]) * next(&mut s) * 0.5;
                let d = aim - Vec3::from(ray.origin);
                if d != Vec3::ZERO {
                    ray.dir = d.to_array();
                }
            }
            if !ray.is_valid() {
                continue;
            }
            let r = PreparedRay::new(&ray);
            let (mask, t, u, v) = tri4(&b, &RayLanes::<Portable>::new(r));
            let (t, u, v) = (t.store(), u.store(), v.store());
            for (lane, tri) in tris.iter().enumerate() {
                let want = intersect_triangle(&r, tri[0], tri[1], tri[2]);
                assert_eq!(mask >> lane & 1 != 0, want.is_some(), "{ray:?} {tri:?}");
                if let Some(h) = want {
                    let got = [t[lane], u[lane], v[lane]].map(f32::to_bits);
                    assert_eq!(got, [h.t, h.u, h.v].map(f32::to_bits), "{ray:?} {tri:?}");
                    hits += 1;
                }
            }
            #[cfg(target_arch = "x86_64")]
            {
                let (m2, t2, u2, v2) = tri4(&b, &RayLanes::<crate::lanes::Sse>::new(r));
                assert_eq!(m2, mask);
                for lane in 0..4 {
                    if mask >> lane & 1 != 0 {
                        let a = [t[lane], u[lane], v[lane]].map(f32::to_bits);
                        let b = [t2.store()[lane], u2.store()[lane], v2.store()[lane]];
                        assert_eq!(a, b.map(f32::to_bits));
                    }
                }
            }
        }
        assert!(hits > 10_000, "only {hits} triangle hits");
    }
}
