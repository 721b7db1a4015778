//! Curves in the tree: the walk finds what testing every segment finds, any-hit agrees
//! with closest-hit, and degenerate strands (zero length, radius 0 or huge, tiny scales,
//! axis-parallel rays, rays from inside) give finite answers inside the ray's interval.

use bvhtrace_core::{BuildOptions, CurveBvh, CurveKind, Curves, Hit, Query, Ray, Triangle};
use glam::{Vec3, Vec4};

/// SplitMix64, for repeatable scenes.
struct Rng(u64);

impl Rng {
    fn f32(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
    fn vec(&mut self) -> Vec3 {
        Vec3::new(self.f32(), self.f32(), self.f32()) * 2.0 - 1.0
    }
}

/// `strands` random strands of `kind`, five segments each, in the cube `[-1, 1]^3`.
fn random_curves(kind: CurveKind, strands: usize, rng: &mut Rng) -> Curves {
    let (mut points, mut segments) = (Vec::new(), Vec::new());
    for _ in 0..strands {
        let mut p = rng.vec();
        let first = points.len() as u32;
        let n = 5 * kind.degree() + 1;
        for _ in 0..n {
            points.push(p.extend(0.01 + 0.05 * rng.f32()));
            p += rng.vec() * 0.2;
        }
        let step = if kind == CurveKind::RoundBSpline {
            1
        } else {
            kind.degree()
        };
        let count = if kind == CurveKind::RoundBSpline {
            n - 3
        } else {
            5
        };
        segments.extend((0..count).map(|i| first + (i * step) as u32));
    }
    Curves {
        kind,
        points,
        segments,
    }
}

fn random_rays(n: usize, rng: &mut Rng) -> Vec<Ray> {
    (0..n)
        .map(|_| {
            let o = rng.vec() * 3.0;
            let target = rng.vec() * 0.8;
            Ray::with_interval(o, target - o, 0.0, f32::INFINITY)
        })
        .collect()
}

fn one_segment(curves: &Curves, s: usize) -> CurveBvh {
    let first = curves.segments[s] as usize;
    let d = curves.kind.degree();
    let single = Curves {
        kind: curves.kind,
        points: curves.points[first..=first + d].to_vec(),
        segments: vec![0],
    };
    CurveBvh::build(&[], single, &BuildOptions::default()).unwrap()
}

/// Every hit is finite, inside the ray's interval, with `u` in `[0, 1]` and a unit normal.
fn check_hit(bvh: &CurveBvh, ray: &Ray, h: &Hit, what: &str) {
    if !h.is_hit() {
        return;
    }
    assert!(
        h.t >= ray.t_min && h.t <= ray.t_max,
        "{what}: {h:?} outside {ray:?}"
    );
    assert!((0.0..=1.0).contains(&h.u), "{what}: {h:?}");
    let n = bvh.normal(h, ray);
    assert!(
        (n.length() - 1.0).abs() < 1e-3,
        "{what}: normal {n} of {h:?}"
    );
}

#[test]
fn the_walk_finds_what_every_segment_finds() {
    let mut rng = Rng(7);
    for kind in CurveKind::ALL {
        // Strands with linear neighbours cut each other; one segment alone is not the
        // same surface, so the linear kinds are compared strand-free (one segment each).
        let mut curves = random_curves(kind, 40, &mut rng);
        if kind.degree() == 1 {
            curves.segments = curves.segments.iter().step_by(2).copied().collect();
        }
        let tris: Vec<Triangle> = (0..20).map(|_| [rng.vec(), rng.vec(), rng.vec()]).collect();
        let bvh = CurveBvh::build(&tris, curves.clone(), &BuildOptions::default()).unwrap();
        let singles: Vec<CurveBvh> = (0..curves.len()).map(|s| one_segment(&curves, s)).collect();
        let tri_bvh = CurveBvh::build(
            &tris,
            Curves {
                segments: vec![],
                ..curves.clone()
            },
            &BuildOptions::default(),
        )
        .unwrap();
        let mut hits = 0;
        for ray in random_rays(2000, &mut rng) {
            let (got, _) = bvh.trace(&ray, Query::Closest);
            check_hit(&bvh, &ray, &got, kind.name());
            // The nearest of the triangles' tree and each segment alone (a lower id wins
            // a tie).
            let mut want = tri_bvh.trace(&ray, Query::Closest).0;
            for (s, single) in singles.iter().enumerate() {
                let h = single.trace(&ray, Query::Closest).0;
                let prim = (tris.len() + s) as u32;
                if h.is_hit()
                    && (!want.is_hit() || h.t < want.t || (h.t == want.t && prim < want.prim))
                {
                    want = Hit { prim, ..h };
                }
            }
            assert_eq!((got.prim, got.t), (want.prim, want.t), "{kind:?} {ray:?}");
            let (any, _) = bvh.trace(&ray, Query::Any);
            assert_eq!(any.is_hit(), got.is_hit(), "{kind:?} any-hit {ray:?}");
            hits += got.is_hit() as usize;
        }
        assert!(hits > 200, "{kind:?}: only {hits} hits");
    }
}

/// A strand of `kind` through `pts` (xyz, radius), one or more segments.
fn strand(kind: CurveKind, pts: &[Vec4]) -> Curves {
    let d = kind.degree();
    let count = if kind == CurveKind::RoundBSpline {
        pts.len() - 3
    } else {
        (pts.len() - 1) / d
    };
    let step = if kind == CurveKind::RoundBSpline {
        1
    } else {
        d
    };
    Curves {
        kind,
        points: pts.to_vec(),
        segments: (0..count).map(|i| (i * step) as u32).collect(),
    }
}

/// Rays from around `c` at `scale`, axis-parallel ones among them, and from `c` itself.
fn rays_around(c: Vec3, scale: f32, rng: &mut Rng) -> Vec<Ray> {
    let mut rays = random_rays(300, rng);
    for r in &mut rays {
        r.origin = (Vec3::from(r.origin) * scale + c).to_array();
    }
    for axis in [Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X] {
        for k in 0..5 {
            let o = c - axis * 3.0 * scale + rng.vec() * 0.01 * scale * k as f32;
            rays.push(Ray::with_interval(o, axis, 0.0, f32::INFINITY));
        }
        rays.push(Ray::with_interval(c, axis, 0.0, f32::INFINITY));
    }
    rays
}

#[test]
fn degenerate_strands_give_finite_answers() {
    let mut rng = Rng(11);
    let p = |x: f32, y: f32, z: f32, r: f32| Vec4::new(x, y, z, r);
    for kind in CurveKind::ALL {
        let n = if kind.degree() == 1 { 3 } else { 4 };
        let cases: Vec<(&str, Vec<Vec4>, f32)> = vec![
            ("zero length", vec![p(0.5, 0.5, 0.5, 0.1); n], 1.0),
            (
                "radius 0",
                (0..n).map(|i| p(i as f32 * 0.3, 0.0, 0.1, 0.0)).collect(),
                1.0,
            ),
            (
                "huge radius",
                (0..n).map(|i| p(i as f32, 0.0, 0.0, 1e6)).collect(),
                1e6,
            ),
            (
                "tiny",
                (0..n)
                    .map(|i| p(i as f32 * 1e-20, 1e-20, 0.0, 3e-21))
                    .collect(),
                1e-20,
            ),
            (
                "far away",
                (0..n).map(|i| p(1e7 + i as f32, 1e7, 1e7, 0.5)).collect(),
                1.0,
            ),
            (
                "doubles back",
                (0..n).map(|i| p((i % 2) as f32, 0.0, 0.0, 0.2)).collect(),
                1.0,
            ),
        ];
        for (what, pts, scale) in cases {
            let c = strand(kind, &pts);
            let center = pts.iter().fold(Vec3::ZERO, |a, q| a + q.truncate()) / pts.len() as f32;
            let bvh = CurveBvh::build(&[], c, &BuildOptions::default()).unwrap();
            let name = format!("{kind:?} {what}");
            let mut hits = 0;
            for ray in rays_around(center, scale, &mut rng) {
                for q in [Query::Closest, Query::Any] {
                    let (h, _) = bvh.trace(&ray, q);
                    assert!(!h.t.is_nan(), "{name}: {h:?} for {ray:?}");
                    check_hit(&bvh, &ray, &h, &name);
                    hits += h.is_hit() as usize;
                }
            }
            // Strands with a radius and a length are hit (so the checks above ran); a round
            // cubic's tube is open at its ends, so a short one much wider than it is long
            // is a thin band, rarely hit.
            let band = what == "huge radius" && kind.degree() == 3;
            let visible = !matches!(what, "zero length" | "radius 0") && !band;
            assert!(!visible || hits > 20, "{name}: {hits} hits");
        }
    }
}

#[test]
fn a_round_tube_is_hit_from_inside_and_the_interval_is_kept() {
    let pts = [-1.5f32, -0.5, 0.5, 1.5].map(|x| Vec4::new(x, 0.0, 0.0, 0.5));
    for kind in CurveKind::ALL {
        if kind == CurveKind::FlatLinear {
            continue;
        }
        let c = strand(kind, if kind.degree() == 1 { &pts[1..3] } else { &pts });
        let bvh = CurveBvh::build(&[], c, &BuildOptions::default()).unwrap();
        // From the axis, straight up: the wall at 0.5.
        let up = Ray::with_interval(Vec3::ZERO, Vec3::Y, 0.0, f32::INFINITY);
        let (h, _) = bvh.trace(&up, Query::Closest);
        assert!((h.t - 0.5).abs() < 1e-4, "{kind:?}: {h:?}");
        // From outside: the near wall, unless the interval starts past it.
        let down = Ray::with_interval(Vec3::new(0.0, 2.0, 0.0), -Vec3::Y, 0.0, f32::INFINITY);
        let (h, _) = bvh.trace(&down, Query::Closest);
        assert!((h.t - 1.5).abs() < 1e-4, "{kind:?}: {h:?}");
        let past = Ray { t_min: 2.0, ..down };
        let (h, _) = bvh.trace(&past, Query::Closest);
        assert!((h.t - 2.5).abs() < 1e-4, "{kind:?}: {h:?}");
        let short = Ray { t_max: 1.4, ..down };
        assert!(!bvh.trace(&short, Query::Any).0.is_hit(), "{kind:?}");
    }
}
