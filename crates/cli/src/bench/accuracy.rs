//! Error of traced hits against the f64 oracle: the "error" half of `bvhtrace bench`.

use bvhtrace_core::oracle::OracleHit;
use bvhtrace_core::{Hit, Query};
use serde::Serialize;

/// How wrong a configuration is on a sample of rays, against the f64 brute-force oracle.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ErrorStats {
    /// Rays compared.
    pub sample: usize,
    /// Both hit, different primitive (closest-hit queries only).
    pub wrong_prim: usize,
    /// The oracle hits, we miss.
    pub false_misses: usize,
    /// The oracle misses, we hit.
    pub false_hits: usize,
    /// Median relative error of `t` where both hit the same primitive.
    pub t_rel_median: f64,
    /// Largest relative error of `t` where both hit the same primitive.
    pub t_rel_max: f64,
}

impl ErrorStats {
    /// Wrong answers of any kind, as a fraction of the sample.
    pub fn error_rate(&self) -> f64 {
        (self.wrong_prim + self.false_misses + self.false_hits) as f64 / self.sample.max(1) as f64
    }

    /// One figure for the error-vs-time plot: the rate of wrong answers, or where there are
    /// none, the largest relative `t` error (so exact configurations sit lowest).
    pub fn headline(&self) -> f64 {
        let r = self.error_rate();
        if r > 0.0 { r } else { self.t_rel_max }
    }
}

/// Compares `ours[i]` with `oracle[i]` for every sampled ray. For any-hit queries only
/// hit/miss is compared (which triangle an any-hit query returns is unspecified).
pub fn compare(ours: &[Hit], oracle: &[OracleHit], query: Query) -> ErrorStats {
    assert_eq!(ours.len(), oracle.len());
    let mut s = ErrorStats {
        sample: ours.len(),
        ..Default::default()
    };
    let mut rel = Vec::new();
    for (h, o) in ours.iter().zip(oracle) {
        match (h.is_hit(), o.is_hit()) {
            (false, true) => s.false_misses += 1,
            (true, false) => s.false_hits += 1,
            (true, true) if query == Query::Closest => {
                if h.prim != o.prim {
                    s.wrong_prim += 1;
                } else {
                    rel.push(((h.t as f64 - o.t) / o.t).abs());
                }
            }
            _ => {}
        }
    }
    rel.sort_by(f64::total_cmp);
    s.t_rel_median = rel.get(rel.len() / 2).copied().unwrap_or(0.0);
    s.t_rel_max = rel.last().copied().unwrap_or(0.0);
    s
}

/// Root-mean-square difference of two RGB8 images, in [0, 1].
pub fn rmse(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len());
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| ((*x as f64 - *y as f64) / 255.0).powi(2))
        .sum();
    (sum / a.len().max(1) as f64).sqrt()
}

/// Root-mean-square difference of two linear RGB images (radiance, unbounded), over every
/// channel: the path tracer's error before tone mapping, which would hide its bright
/// outliers.
pub fn rmse_linear(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    assert_eq!(a.len(), b.len());
    let sum: f64 = (a.iter().flatten().zip(b.iter().flatten()))
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum();
    (sum / (3 * a.len()).max(1) as f64).sqrt()
}

/// Mean FLIP error (NVIDIA's perceptual image difference) of `test` against `reference`.
pub fn flip(reference: &[u8], test: &[u8], w: u32, h: u32) -> f64 {
    let r = nv_flip::FlipImageRgb8::with_data(w, h, reference);
    let t = nv_flip::FlipImageRgb8::with_data(w, h, test);
    let err = nv_flip::flip(r, t, nv_flip::DEFAULT_PIXELS_PER_DEGREE);
    nv_flip::FlipPool::from_image(&err).mean() as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use bvhtrace_core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal, oracle, trace_rays};
    use glam::Vec3;

    /// A unit quad in z = 0 and a 64x64 grid of +z rays over [-0.5, 1.5]^2 from z = -2:
    /// the hits, misses and `t` are known exactly.
    fn quad_and_grid() -> (Vec<[Vec3; 3]>, Vec<Ray>, usize) {
        let tris = vec![
            [
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
            ],
            [
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
            ],
        ];
        let mut rays = Vec::new();
        let mut inside = 0;
        for j in 0..64 {
            for i in 0..64 {
                // Cell centres, none exactly on the quad's border.
                let (x, y) = (
                    -0.5 + (i as f32 + 0.5) / 32.0,
                    -0.5 + (j as f32 + 0.5) / 32.0,
                );
                if (0.0..=1.0).contains(&x) && (0.0..=1.0).contains(&y) {
                    inside += 1;
                }
                rays.push(Ray::new(Vec3::new(x, y, -2.0), Vec3::Z));
            }
        }
        (tris, rays, inside)
    }

    #[test]
    fn exact_answers_give_zero_error() {
        let (tris, rays, inside) = quad_and_grid();
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
        let ours = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::Stackless)).hits;
        let o: Vec<_> = rays.iter().map(|r| oracle::closest_hit(&tris, r)).collect();
        assert_eq!(o.iter().filter(|h| h.is_hit()).count(), inside);
        assert!(o.iter().filter(|h| h.is_hit()).all(|h| h.t == 2.0));
        let s = compare(&ours, &o, Query::Closest);
        assert_eq!(
            s,
            ErrorStats {
                sample: 4096,
                ..Default::default()
            }
        );
        assert_eq!(s.error_rate(), 0.0);
    }

    #[test]
    fn each_kind_of_error_is_counted_where_it_happens() {
        let (tris, rays, inside) = quad_and_grid();
        let o: Vec<_> = rays.iter().map(|r| oracle::closest_hit(&tris, r)).collect();
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
        let mut ours = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::FullStack)).hits;
        let hit_idx: Vec<usize> = (0..ours.len()).filter(|&i| ours[i].is_hit()).collect();
        let miss_idx: Vec<usize> = (0..ours.len()).filter(|&i| !ours[i].is_hit()).collect();
        assert_eq!(hit_idx.len(), inside);
        // 7 false misses, 5 false hits, 3 wrong primitives, one t off by exactly 1/4.
        for &i in &hit_idx[..7] {
            ours[i] = Hit::miss(f32::INFINITY);
        }
        for &i in &miss_idx[..5] {
            ours[i] = Hit {
                t: 2.0,
                prim: 0,
                u: 0.0,
                v: 0.0,
            };
        }
        for &i in &hit_idx[7..10] {
            ours[i].prim ^= 1;
        }
        ours[hit_idx[10]].t = 2.5;
        let s = compare(&ours, &o, Query::Closest);
        assert_eq!((s.false_misses, s.false_hits, s.wrong_prim), (7, 5, 3));
        assert_eq!(s.t_rel_max, 0.25);
        assert_eq!(s.t_rel_median, 0.0);
        assert!((s.error_rate() - 15.0 / 4096.0).abs() < 1e-15);
        // Any-hit: only hit/miss counts.
        let a = compare(&ours, &o, Query::Any);
        assert_eq!((a.false_misses, a.false_hits, a.wrong_prim), (7, 5, 0));
    }

    #[test]
    fn image_errors() {
        let a = vec![0u8; 48];
        let mut b = a.clone();
        assert_eq!(rmse(&a, &b), 0.0);
        b.iter_mut().for_each(|x| *x = 255);
        assert!((rmse(&a, &b) - 1.0).abs() < 1e-12);
        let (w, h) = (4, 4);
        assert!(flip(&a, &a, w, h) < 1e-6);
        assert!(flip(&a, &b, w, h) > 0.5);
        // Linear: one channel of two pixels off by 3, the rest equal: sqrt(9 / 6).
        let x = [[1.0f32, 2.0, 0.5], [4.0, 0.0, 8.0]];
        let mut y = x;
        y[1][2] += 3.0;
        assert_eq!(rmse_linear(&x, &x), 0.0);
        assert!((rmse_linear(&x, &y) - 1.5f64.sqrt()).abs() < 1e-12);
    }
}
