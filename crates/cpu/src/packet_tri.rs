//! The watertight triangle test with rays in lanes: one triangle's corners splatted
//! against eight rays that share the shear axes (`kx`, `ky`, `kz`), lane for lane the f32
//! operations of `bvhtrace_core::intersect::intersect_triangle` in the same order (see
//! `tests4::tri4`, the same test with triangles in lanes).
//!
//! The one liberty: the edge functions are first computed as `p.x q.y - p.y q.x`, which
//! is the reference's value but for the sign of a zero; the lanes are re-computed with the
//! reference's corner ordering and sign restoration when some lane that passes the
//! mixed-sign test has a zero edge function (the only case where the sign can reach
//! `det`, `t` or the weights). Comparisons with zero do not see the sign of a zero, so the
//! mixed-sign test is the reference's either way.

use crate::lanes::Wide;

/// Eight rays with the same shear axes, as lanes.
#[derive(Clone, Copy)]
pub(crate) struct ShearRays<W> {
    /// The origins' `kx`, `ky` and `kz` coordinates.
    pub o: [W; 3],
    /// The shear constants `sx`, `sy`, `sz` (`PreparedRay`'s).
    pub s: [W; 3],
    /// The intervals' starts.
    pub t_min: W,
}

/// `p.x q.y - p.y q.x`: the reference's edge function up to the sign of a zero.
#[inline(always)]
fn edge_fast<W: Wide>(px: W, py: W, qx: W, qy: W) -> W {
    px.mul(qy).sub(py.mul(qx))
}

/// `intersect::edge` over lanes: the corners in one fixed order, the sign restored by
/// `-(q.x p.y - q.y p.x)`.
#[inline(always)]
pub(crate) fn edge_exact<W: Wide>(px: W, py: W, qx: W, qy: W) -> W {
    let swap = px.gt(qx).or(px.eq(qx).and(py.gt(qy)));
    let (pq, qp) = (px.mul(qy), py.mul(qx));
    swap.select(qp.sub(pq).neg(), pq.sub(qp))
}

/// The test of one triangle (corners `c[corner]` as their `kx`, `ky`, `kz` coordinates)
/// against the rays of `lanes`: the lanes that hit at `t >= t_min`, and per lane `t` and
/// the weights of corners 1 and 2 (meaningful in the hit lanes only).
#[inline(always)]
pub(crate) fn tri_rays<W: Wide>(c: &[[f32; 3]; 3], r: &ShearRays<W>, lanes: u32) -> (u32, W, W, W) {
    let [sx, sy, sz] = r.s;
    let [ox, oy, oz] = r.o;
    let az = W::splat(c[0][2]).sub(oz);
    let bz = W::splat(c[1][2]).sub(oz);
    let cz = W::splat(c[2][2]).sub(oz);
    let ax = W::splat(c[0][0]).sub(ox).sub(sx.mul(az));
    let ay = W::splat(c[0][1]).sub(oy).sub(sy.mul(az));
    let bx = W::splat(c[1][0]).sub(ox).sub(sx.mul(bz));
    let by = W::splat(c[1][1]).sub(oy).sub(sy.mul(bz));
    let cx = W::splat(c[2][0]).sub(ox).sub(sx.mul(cz));
    let cy = W::splat(c[2][1]).sub(oy).sub(sy.mul(cz));
    let mut u = edge_fast(cx, cy, bx, by);
    let mut v = edge_fast(ax, ay, cx, cy);
    let mut w = edge_fast(bx, by, ax, ay);
    let zero = W::splat(0.0);
    let negative = u.lt(zero).or(v.lt(zero)).or(w.lt(zero));
    let positive = u.gt(zero).or(v.gt(zero)).or(w.gt(zero));
    let inside = !negative.and(positive).bits() & lanes;
    // Most triangles a group of rays reaches its rays miss: no distance to compute.
    if inside == 0 {
        return (0, zero, zero, zero);
    }
    if u.eq(zero).or(v.eq(zero)).or(w.eq(zero)).bits() & inside != 0 {
        u = edge_exact(cx, cy, bx, by);
        v = edge_exact(ax, ay, cx, cy);
        w = edge_exact(bx, by, ax, ay);
    }
    let det = u.add(v).add(w);
    let inside = inside & !det.eq(zero).bits();
    if inside == 0 {
        return (0, zero, zero, zero);
    }
    let t_scaled = u
        .mul(sz.mul(az))
        .add(v.mul(sz.mul(bz)))
        .add(w.mul(sz.mul(cz)));
    let inv_det = W::splat(1.0).div(det);
    let t = t_scaled.mul(inv_det);
    let ok = t.ge(r.t_min).bits() & inside;
    (ok, t, v.mul(inv_det), w.mul(inv_det))
}

#[cfg(test)]
mod tests {
    use bvhtrace_core::Ray;
    use bvhtrace_core::intersect::{PreparedRay, intersect_triangle};
    use glam::Vec3;

    use super::{ShearRays, tri_rays};
    use crate::lanes::{Pair, Portable, Wide};
    use crate::tests4::tests::{next, point, ray, value};

    /// Eight rays sharing their shear axes (`kx`, `ky`, `kz`) as lanes.
    fn lanes<W: Wide>(rays: &[PreparedRay; 8]) -> ShearRays<W> {
        let k = [rays[0].kx, rays[0].ky, rays[0].kz];
        let col = |f: &dyn Fn(&PreparedRay) -> f32| W::load(&rays.each_ref().map(f));
        ShearRays {
            o: k.map(|a| col(&|r: &PreparedRay| r.org[a])),
            s: [
                col(&|r: &PreparedRay| r.sx),
                col(&|r: &PreparedRay| r.sy),
                col(&|r: &PreparedRay| r.sz),
            ],
            t_min: col(&|r: &PreparedRay| r.t_min),
        }
    }

    /// `tri_rays` over lanes `W` equals `intersect_triangle` lane by lane, to the bit.
    fn check<W: Wide>(tri: &[Vec3; 3], rays: &[PreparedRay; 8], lanes_on: u32) -> u32 {
        let k = [rays[0].kx, rays[0].ky, rays[0].kz];
        let c = tri.map(|p| k.map(|a| p[a]));
        let (ok, t, u, v) = tri_rays::<W>(&c, &lanes::<W>(rays), lanes_on);
        let (t, u, v) = (t.store(), u.store(), v.store());
        for (j, r) in rays.iter().enumerate() {
            if lanes_on >> j & 1 == 0 {
                assert_eq!(ok >> j & 1, 0, "lane {j} is off");
                continue;
            }
            let want = intersect_triangle(r, tri[0], tri[1], tri[2]);
            assert_eq!(ok >> j & 1 != 0, want.is_some(), "{r:?} {tri:?}");
            if let Some(h) = want {
                let got = [t[j], u[j], v[j]].map(f32::to_bits);
                assert_eq!(got, [h.t, h.u, h.v].map(f32::to_bits), "{r:?} {tri:?}");
            }
        }
        ok
    }

    /// A triangle from several regimes: around a point, slivers, zero area (a point, a
    /// segment), huge and tiny, axis-aligned with exact coordinates (zero edge functions).
    fn triangle(s: &mut u64, k: u32) -> [Vec3; 3] {
        let c = point(s);
        match k % 8 {
            0 | 1 => [c, c + point(s) * 0.1, c + point(s) * 0.1],
            2 => [c, c + Vec3::X, c + Vec3::X * 2.0 + Vec3::Y * 1e-6],
            3 => [c, c, c],
            4 => [c, c + Vec3::Y, c + Vec3::Y * 3.0],
            5 => [c * 1e30, point(s) * 1e30, point(s) * 1e-30],
            6 => {
                let r = |s: &mut u64| (next(s) * 8.0).round() - 4.0;
                let q = |s: &mut u64| Vec3::new(r(s), r(s), 0.0);
                [q(s), q(s), q(s)]
            }
            _ => [c, point(s), point(s)],
        }
    }

    /// Eight rays with the same shear axes: one drawn ray, the others from origins and
    /// directions near it (or drawn freely) until their axes agree; aimed at the triangle
    /// now and then, so that many lanes hit, and at its corners and edges, where edge
    /// functions are zero.
    fn rays_for(s: &mut u64, tri: &[Vec3; 3]) -> Option<[PreparedRay; 8]> {
        let first = ray(s);
        if !first.is_valid() {
            return None;
        }
        let p0 = PreparedRay::new(&first);
        let mut out = [p0; 8];
        let mut n = 1;
        for _ in 0..200 {
            if n == 8 {
                return Some(out);
            }
            let mut r = if next(s) < 0.5 { first } else { ray(s) };
            let aim = match (next(s) * 4.0) as u32 {
                0 => Some(tri[(next(s) * 3.0) as usize % 3]),
                1 => Some(tri[0] + (tri[1] - tri[0]) * next(s)),
                2 => Some(
                    tri[0] + (tri[1] - tri[0]) * next(s) * 0.5 + (tri[2] - tri[0]) * next(s) * 0.5,
                ),
                _ => None,
            };
            if next(s) < 0.5 {
                r.origin = (Vec3::from(r.origin) + point(s) * 1e-3).to_array();
            }
            if let Some(a) = aim {
                let d = a - Vec3::from(r.origin);
                if d != Vec3::ZERO {
                    r.dir = d.to_array();
                }
            }
            if next(s) < 0.1 {
                r.t_min = -value(s).abs();
            }
            if !r.is_valid() {
                continue;
            }
            let p = PreparedRay::new(&r);
            if (p.kx, p.ky, p.kz) == (p0.kx, p0.ky, p0.kz) {
                out[n] = p;
                n += 1;
            }
        }
        None
    }

    /// Each lane of the rays-in-lanes triangle test is `intersect_triangle` of its ray:
    /// the same hits, and `t`, `u`, `v` to the bit (signed zeros included), on portable,
    /// SSE and (where the CPU has it) AVX lanes.
    #[test]
    fn ray_lanes_triangle_test_is_the_scalar_test() {
        let mut s = 0x7a11_0c0d_e5ee_d001u64;
        let (mut hits, mut groups, mut zero_hits) = (0u32, 0, 0);
        for k in 0..30_000u32 {
            let tri = triangle(&mut s, k);
            let Some(rays) = rays_for(&mut s, &tri) else {
                continue;
            };
            groups += 1;
            let lanes_on = if k % 3 == 0 {
                (next(&mut s) * 256.0) as u32 & 0xff
            } else {
                0xff
            };
            let ok = check::<Pair<Portable>>(&tri, &rays, lanes_on);
            #[cfg(target_arch = "x86_64")]
            {
                assert_eq!(check::<Pair<crate::lanes::Sse>>(&tri, &rays, lanes_on), ok);
                if std::arch::is_x86_feature_detected!("avx2") {
                    assert_eq!(check::<crate::lanes::Avx8>(&tri, &rays, lanes_on), ok);
                }
            }
            hits += ok.count_ones();
            for (j, r) in rays.iter().enumerate() {
                if ok >> j & 1 != 0 {
                    let h = intersect_triangle(r, tri[0], tri[1], tri[2]).expect("a hit");
                    zero_hits += u32::from(h.u == 0.0 || h.v == 0.0 || h.t == 0.0);
                }
            }
        }
        println!("{groups} groups, {hits} lane hits, {zero_hits} with a zero weight or t");
        assert!(groups > 15_000, "only {groups} groups");
        assert!(hits > 20_000, "only {hits} lane hits");
        assert!(
            zero_hits > 500,
            "only {zero_hits} hits with a zero weight or t"
        );
    }

    /// Signed zeros, subnormal and axis-parallel directions, `t_min < 0`: rays on one
    /// axis through a triangle's corners, edges and plane.
    #[test]
    fn ray_lanes_triangle_test_on_axis_rays() {
        let tri = [
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(0.0, 1.0, 1.0),
        ];
        let dirs = [
            [0.0, 0.0, 1.0],
            [-0.0, 0.0, 1.0],
            [0.0, -0.0, 1.0],
            [1e-40, -1e-40, 1.0],
            [-0.0, -0.0, 1.0],
        ];
        let origins = [
            [0.0, 0.0, 0.0],
            [-0.0, -0.0, 0.0],
            [0.5, 0.5, 2.0],
            [1.0, 0.0, -0.0],
            [0.25, 0.0, 3.0],
        ];
        let mut n = 0;
        for d in dirs {
            let mut rays = Vec::new();
            for o in origins {
                for t_min in [0.0, -5.0, -0.0] {
                    let r = Ray::with_interval(Vec3::from(o), Vec3::from(d), t_min, f32::INFINITY);
                    rays.push(PreparedRay::new(&r));
                }
            }
            for chunk in rays.chunks_exact(8) {
                let group: [PreparedRay; 8] = chunk.try_into().expect("eight rays");
                for tri in [tri, [tri[0], tri[2], tri[1]]] {
                    n += check::<Pair<Portable>>(&tri, &group, 0xff).count_ones();
                    #[cfg(target_arch = "x86_64")]
                    {
                        check::<Pair<crate::lanes::Sse>>(&tri, &group, 0xff);
                        if std::arch::is_x86_feature_detected!("avx2") {
                            check::<crate::lanes::Avx8>(&tri, &group, 0xff);
                        }
                    }
                }
            }
        }
        assert!(n > 20, "only {n} hits");
    }
}
