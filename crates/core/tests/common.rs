//! Shared generators for the core tests.
#![allow(dead_code)]

use bvhtrace_core::{BuildOptions, FlatBvh, Hit, Ray, Traversal, Triangle, oracle};
use glam::Vec3;
use proptest::prelude::*;

/// A coordinate drawn from several regimes, so soups mix ordinary, tiny and huge values.
pub fn coord() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => -10.0f32..10.0,
        1 => -1e-3f32..1e-3,
        1 => -1e6f32..1e6,
        1 => Just(0.0f32),
        1 => prop::sample::select(vec![-1.0f32, 1.0, 0.5, 2.0, -0.25]),
    ]
}

pub fn point() -> impl Strategy<Value = Vec3> {
    (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z))
}

/// A triangle that may be ordinary, a sliver, zero-area (repeated corner or collinear),
/// or an exact copy of another's corners.
pub fn triangle() -> impl Strategy<Value = Triangle> {
    prop_oneof![
        6 => (point(), point(), point()).prop_map(|(a, b, c)| [a, b, c]),
        1 => (point(), point()).prop_map(|(a, b)| [a, b, b]),
        1 => (point(), point()).prop_map(|(a, b)| [a, b, (a + b) * 0.5]),
        1 => point().prop_map(|a| [a, a, a]),
        1 => (point(), point()).prop_map(|(a, b)| [a, b, a + (b - a) * 1e-6 + Vec3::new(0.0, 1e-6, 0.0)]),
    ]
}

/// Small random soups, duplicates included.
pub fn soup() -> impl Strategy<Value = Vec<Triangle>> {
    prop::collection::vec(triangle(), 1..200).prop_flat_map(|v| {
        let n = v.len();
        prop::collection::vec(0..n, 0..n / 4 + 1).prop_map(move |dups| {
            let mut out = v.clone();
            out.extend(dups.iter().map(|&d| v[d]));
            out
        })
    })
}

/// A small deterministic generator (xorshift64 from `seed`, which must not be 0): each
/// call gives the next value, uniform in [0, 1).
pub fn xorshift(seed: u64) -> impl FnMut() -> f32 {
    let mut s = seed;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// `FlatBvh::build` on a thread pool of `threads` threads.
pub fn build_on_threads(tris: &[Triangle], opts: &BuildOptions, threads: usize) -> FlatBvh {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(|| FlatBvh::build(tris, opts).unwrap())
}

/// Rays aimed at random points of the soup, plus axis-parallel ones with signed zeros.
pub fn rays_for(tris: &[Triangle], seed: u64, n: usize) -> Vec<Ray> {
    let mut rnd = xorshift(seed | 1);
    let (lo, hi) = tris.iter().flatten().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(l, h), p| (l.min(*p), h.max(*p)),
    );
    let ext = (hi - lo).max(Vec3::splat(1e-6));
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let t = &tris[i % tris.len()];
        let (a, b) = (rnd(), rnd());
        let target = t[0] + (t[1] - t[0]) * a * (1.0 - b) + (t[2] - t[0]) * b;
        let origin = lo + Vec3::new(rnd(), rnd(), rnd()) * ext * 3.0 - ext;
        let mut dir = target - origin;
        match i % 7 {
            5 => {
                // Axis-parallel, with a signed zero in the other components.
                let axis = i % 3;
                let mut d = [0.0f32, -0.0, 0.0];
                d[axis] = if rnd() < 0.5 { 1.0 } else { -1.0 };
                dir = Vec3::from(d);
            }
            6 => dir.x = 1e-30,
            _ => {}
        }
        if dir == Vec3::ZERO {
            dir = Vec3::X;
        }
        out.push(Ray::new(origin, dir));
    }
    out
}

/// A closed UV sphere of `n` x `2n` quads (two triangles each), radius `r`, centre `c`.
pub fn uv_sphere(n: usize, r: f32, c: Vec3) -> Vec<Triangle> {
    let p = |i: usize, j: usize| {
        let (th, ph) = (
            std::f32::consts::PI * i as f32 / n as f32,
            std::f32::consts::PI * j as f32 / n as f32,
        );
        c + Vec3::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin()) * r
    };
    let mut t = Vec::new();
    for i in 0..n {
        for j in 0..2 * n {
            let (a, b, c, d) = (p(i, j), p(i + 1, j), p(i + 1, j + 1), p(i, j + 1));
            t.push([a, b, c]);
            t.push([a, c, d]);
        }
    }
    t
}

/// The documented f32 exception to "every traversal and every tree returns the same
/// closest hit": two
/// answers `a` and `b` may differ only where the f32 test is indeterminate for a triangle
/// involved, or where their `t` lie within the f32 `t` error bounds of their triangles
/// (see `intersect::BOX_CULL_SLACK`: the box test's slack covers the rounding of the
/// watertight test's `T` and `det`, not the error of its edge functions).
pub fn f32_departure(tris: &[Triangle], ray: &Ray, a: &Hit, b: &Hit) -> bool {
    let tri = |p: u32| tris.get(p as usize);
    let terr = |p: u32| tri(p).map_or(0.0, |t| oracle::f32_t_error_bound(t, ray));
    [a.prim, b.prim]
        .iter()
        .any(|&p| tri(p).is_some_and(|t| oracle::f32_indeterminate(t, ray)))
        || (a.t as f64 - b.t as f64).abs() <= terr(a.prim) + terr(b.prim)
}

/// Every walk, short stacks of one and eight entries among them.
pub const WALKS: [Traversal; 5] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(1),
    Traversal::ShortStack(8),
    Traversal::Wide,
];

/// The same hit bit for bit: primitive, `t`, `u` and `v`.
pub fn same(a: &Hit, b: &Hit) -> bool {
    a.prim == b.prim && a.t.to_bits() == b.t.to_bits() && a.u == b.u && a.v == b.v
}
