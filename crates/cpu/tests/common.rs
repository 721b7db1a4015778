//! Generators and comparisons shared by the tests (after the core tests' own).
#![allow(dead_code)]

use bvhtrace_core::{
    BuildOptions, BuilderKind, FlatBvh, Hit, Query, Ray, TraceOptions, Traversal, Triangle, oracle,
};
use bvhtrace_cpu::{CpuBvh, Isa};
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

/// An ordinary triangle, a sliver, a zero-area one, or one far from the origin.
pub fn triangle() -> impl Strategy<Value = Triangle> {
    prop_oneof![
        6 => (point(), point(), point()).prop_map(|(a, b, c)| [a, b, c]),
        1 => (point(), point()).prop_map(|(a, b)| [a, b, b]),
        1 => (point(), point()).prop_map(|(a, b)| [a, b, (a + b) * 0.5]),
        1 => point().prop_map(|a| [a, a, a]),
        1 => (point(), point()).prop_map(|(a, b)| [a, b, a + (b - a) * 1e-6 + Vec3::new(0.0, 1e-6, 0.0)]),
        1 => (point(), point(), point()).prop_map(|(a, b, c)| {
            let o = Vec3::new(1e7, -3e6, 5e5);
            [a + o, b + o, c + o]
        }),
    ]
}

/// Small random soups, exact duplicates included.
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

/// xorshift64 from `seed` (not 0): uniform in [0, 1).
pub fn xorshift(seed: u64) -> impl FnMut() -> f32 {
    let mut s = seed;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Rays aimed at random points of the soup from around it, from inside its box, along
/// the axes (signed zeros in the other components), with subnormal components, and with
/// intervals that start behind the origin or end early.
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
        let origin = match i % 5 {
            0 => lo + Vec3::new(rnd(), rnd(), rnd()) * ext,
            _ => lo + Vec3::new(rnd(), rnd(), rnd()) * ext * 3.0 - ext,
        };
        let mut dir = target - origin;
        match i % 7 {
            5 => {
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
        let (t_min, t_max) = match i % 11 {
            3 => (-1.0, f32::INFINITY),
            7 => (0.0, 0.5 + rnd()),
            _ => (0.0, f32::INFINITY),
        };
        out.push(Ray::with_interval(origin, dir, t_min, t_max));
    }
    out
}

/// A closed UV sphere of `n` x `2n` quads, radius `r`, centre `c`.
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

/// The same hit bit for bit: primitive, `t`, `u` and `v`.
pub fn same(a: &Hit, b: &Hit) -> bool {
    a.prim == b.prim
        && a.t.to_bits() == b.t.to_bits()
        && a.u.to_bits() == b.u.to_bits()
        && a.v.to_bits() == b.v.to_bits()
}

/// The core walks' documented exception: the f32 test is indeterminate for a triangle
/// involved, or the two `t` lie within their triangles' f32 error bounds.
pub fn f32_departure(tris: &[Triangle], ray: &Ray, a: &Hit, b: &Hit) -> bool {
    let tri = |p: u32| tris.get(p as usize);
    let terr = |p: u32| tri(p).map_or(0.0, |t| oracle::f32_t_error_bound(t, ray));
    [a.prim, b.prim]
        .iter()
        .any(|&p| tri(p).is_some_and(|t| oracle::f32_indeterminate(t, ray)))
        || (a.t as f64 - b.t as f64).abs() <= terr(a.prim) + terr(b.prim)
}

/// What the reference walk (full stack) answers.
pub fn reference(flat: &FlatBvh, rays: &[Ray], q: Query) -> Vec<Hit> {
    bvhtrace_core::trace_rays(flat, rays, &TraceOptions::new(Traversal::FullStack, q)).hits
}

/// Every instruction set's single-ray answers: closest hits equal to the bit; any-hit
/// queries the same verdict (which blocker is returned may differ: streams and single
/// walks visit the leaves in other orders), each hit inside its ray's interval.
pub fn every_isa(bvh: &CpuBvh, rays: &[Ray], q: Query) -> Vec<Hit> {
    let isas = Isa::all_available();
    let first = bvhtrace_cpu::trace_rays_with(bvh, rays, q, isas[0]);
    for &isa in &isas[1..] {
        let h = bvhtrace_cpu::trace_rays_with(bvh, rays, q, isa);
        for (i, (a, b)) in first.iter().zip(&h).enumerate() {
            let r = &rays[i];
            let agree = match q {
                Query::Closest => same(a, b),
                Query::Any => {
                    a.is_hit() == b.is_hit()
                        && (!b.is_hit() || (b.t >= r.t_min && b.t <= r.t_max))
                        && (b.is_hit() || same(a, b))
                }
            };
            assert!(
                agree,
                "{isa} differs from {} on ray {i} {r:?}: {b:?} vs {a:?}",
                isas[0],
            );
        }
    }
    first
}

/// A scene for the tests: triangles, their tree, primary rays and shadow rays.
pub type SceneRays = (Vec<Triangle>, FlatBvh, Vec<Ray>, Vec<Ray>);

/// A shared scene's triangles, its primary rays (`w` x `h`, row by row) and shadow rays
/// from their hits toward a light beside the camera; `None` without the shared scenes.
pub fn scene_rays(name: &str, w: u32, h: u32) -> Option<SceneRays> {
    let dir = bvhtrace_scene::shared_scenes_dir()?;
    let path = dir.join("glb").join(format!("{name}.glb"));
    if !path.is_file() {
        return None;
    }
    let scene = bvhtrace_scene::load(&path.display().to_string()).ok()?;
    let tris = scene.flattened_triangles().ok()?;
    let flat = FlatBvh::build(&tris, &bvhtrace_core::BuildOptions::default()).ok()?;
    let cam = scene.camera_or_frame(w as f32 / h as f32);
    let primary = cam.rays(w, h);
    let (_, right, up) = cam.basis();
    let light = cam.eye + (right * 0.25 + up * 0.2) * (cam.target - cam.eye).length();
    let hits = reference(&flat, &primary, Query::Closest);
    let shadow = primary
        .iter()
        .zip(&hits)
        .filter(|(_, h)| h.is_hit())
        .map(|(r, h)| {
            h.surface(&tris[h.prim as usize], Vec3::from(r.dir))
                .ray_toward(light)
        })
        .collect();
    Some((tris, flat, primary, shadow))
}

/// Triangles in the planes `x = 3^(i - 40)`, one per leaf (a chain built by the midpoint
/// builder), and rays from just beside the planes in all directions: hits at or behind
/// the origin that f32 rounds to a small positive `t`.
pub fn planes_at_origins() -> (FlatBvh, Vec<Ray>) {
    let xs: Vec<f32> = (0..90).map(|i| 3f64.powi(i - 40) as f32).collect();
    let tris: Vec<Triangle> = xs
        .iter()
        .map(|&x| {
            [
                Vec3::new(x, -1.0, -1.0),
                Vec3::new(x, 1.0, -1.0),
                Vec3::new(x, 0.0, 1.5),
            ]
        })
        .collect();
    let opts = BuildOptions {
        builder: BuilderKind::Midpoint,
        max_depth: 1000,
        max_leaf_size: 1,
        ..Default::default()
    };
    let flat = FlatBvh::build(&tris, &opts).expect("built");
    let mut next = xorshift(19);
    let rays = (0..3000)
        .map(|_| {
            let i = (next() * 89.0) as usize;
            let o = Vec3::new(xs[i] * (1.1 + 0.8 * next()), next() - 0.5, next() - 0.6);
            Ray::new(o, Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5))
        })
        .collect();
    (flat, rays)
}

/// Fails naming the first ray whose hit differs from `want`'s to the bit.
pub fn assert_same_hits(rays: &[Ray], got: &[Hit], want: &[Hit]) {
    let differ: Vec<usize> = (0..rays.len())
        .filter(|&i| !same(&got[i], &want[i]))
        .collect();
    if let Some(&i) = differ.first() {
        panic!(
            "{} of {} rays differ, e.g. ray {:?}: {:?} vs {:?}",
            differ.len(),
            rays.len(),
            rays[i],
            got[i],
            want[i]
        );
    }
}
