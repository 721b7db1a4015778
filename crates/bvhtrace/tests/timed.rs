//! Scenes in time and curves through the front door (`open_timed`): every backend that
//! opens answers as the core walks do, a backend without kernels for them refuses by name,
//! and bad times are refused. Without a Vulkan adapter the device cases print SKIP.

use std::sync::Arc;

use bvhtrace::core::curves::{CurveKind, Curves};
use bvhtrace::core::motion::{MotionBvh, MotionInstancedBvh, MotionMesh, MovingInstance};
use bvhtrace::core::{BuildOptions, CurveBvh, Hit, Query, Ray, TimeBounds, Triangle};
use bvhtrace::glam::{Mat4, Vec3, Vec4};
use bvhtrace::{Backend, OpenOptions, TimedScene, TraceError, open_timed};

/// A closed octahedron of radius 1 at `c`.
fn octahedron(c: Vec3) -> Vec<Triangle> {
    let (x, y, z) = (Vec3::X, Vec3::Y, Vec3::Z);
    let mut out = Vec::new();
    for sx in [x, -x] {
        for sy in [y, -y] {
            for sz in [z, -z] {
                out.push([c + sx, c + sy, c + sz]);
            }
        }
    }
    out
}

/// 24 x 24 rays toward -z over [-2, 4] x [-2, 2], and a time for each (the shutter's
/// ends, between, outside, and every 37th NaN).
fn rays_and_times() -> (Vec<Ray>, Vec<f32>) {
    let n = 24;
    let rays = (0..n * n)
        .map(|k| {
            let (i, j) = ((k % n) as f32, (k / n) as f32);
            Ray::new(
                Vec3::new(-2.0 + 6.0 * i / n as f32, -2.0 + 4.0 * j / n as f32, 5.0),
                Vec3::NEG_Z,
            )
        })
        .collect();
    let times = (0..n * n)
        .map(|k| match k % 37 {
            0 => f32::NAN,
            1 => 0.0,
            2 => 1.0,
            3 => -0.5,
            _ => (k % 11) as f32 / 10.0,
        })
        .collect();
    (rays, times)
}

/// The three scenes, and the core walks' answers on `rays` at `times` for each query.
fn scenes(rays: &[Ray], times: &[f32]) -> Vec<(TimedScene, [Vec<Hit>; 2])> {
    let opts = BuildOptions::default();
    let still = octahedron(Vec3::ZERO);
    let moved: Vec<Triangle> = octahedron(Vec3::new(2.0, 0.5, 0.0));
    let mesh = MotionMesh::new(vec![still.clone(), moved]).expect("finite");
    let moving = Arc::new(MotionBvh::build(&mesh, &opts, TimeBounds::Linear).expect("built"));
    let instances = vec![MovingInstance {
        mesh: 0,
        transforms: vec![
            Mat4::IDENTITY,
            Mat4::from_translation(Vec3::new(1.0, 0.0, 0.0)),
            Mat4::from_translation(Vec3::new(2.0, 0.5, 0.0)) * Mat4::from_rotation_z(0.5),
        ],
    }];
    let placed = Arc::new(
        MotionInstancedBvh::build(&[still], instances, &opts, TimeBounds::Linear).expect("built"),
    );
    let points = (0..8)
        .map(|i| Vec4::new(-1.5 + 0.8 * i as f32, 0.3 * (i % 2) as f32, 0.0, 0.15))
        .collect();
    let curves = Curves {
        kind: CurveKind::RoundLinear,
        points,
        segments: (0..7).collect(),
    };
    let hair = Arc::new(
        CurveBvh::build(&octahedron(Vec3::new(0.0, 0.0, -3.0)), curves, &opts).expect("built"),
    );
    let answers = |trace: &dyn Fn(Query) -> Vec<Hit>| [trace(Query::Closest), trace(Query::Any)];
    vec![
        (
            TimedScene::Moving(moving.clone()),
            answers(&|q| moving.trace_rays(rays, times, q)),
        ),
        (
            TimedScene::MovingInstances(placed.clone()),
            answers(&|q| placed.trace_rays(rays, times, q)),
        ),
        (
            TimedScene::Curves(hair.clone()),
            answers(&|q| {
                let mut h = hair.trace_rays(rays, q);
                for (h, (r, t)) in h.iter_mut().zip(rays.iter().zip(times)) {
                    if t.is_nan() {
                        *h = bvhtrace::core::traverse::untraced(r);
                    }
                }
                h
            }),
        ),
    ]
}

fn same(a: &Hit, b: &Hit) -> bool {
    a.prim == b.prim
        && a.t.to_bits() == b.t.to_bits()
        && a.u.to_bits() == b.u.to_bits()
        && a.v.to_bits() == b.v.to_bits()
}

fn no_device(e: &TraceError) -> bool {
    matches!(
        e,
        TraceError::NoAdapter { .. } | TraceError::AdapterNotFound { .. }
    )
}

#[test]
fn every_backend_answers_as_the_core_walks() {
    let (rays, times) = rays_and_times();
    let mut opened_on = Vec::new();
    for backend in [Backend::Cpu, Backend::Wgpu, Backend::Auto] {
        for (scene, [closest, any]) in scenes(&rays, &times) {
            let name = scene.name();
            let opened = match open_timed(scene, &OpenOptions::new(backend)) {
                Ok(o) => o,
                Err(e) if no_device(&e) => {
                    eprintln!("SKIP {backend}: {e}");
                    continue;
                }
                Err(e) => panic!("{backend}, {name}: {e}"),
            };
            opened_on.push(opened.backend);
            let got = opened
                .tracer
                .trace(&rays, &times, Query::Closest)
                .expect("traced");
            let hits = got.iter().filter(|h| h.is_hit()).count();
            assert!(hits > 20, "{backend}, {name}: {hits} hits");
            for i in 0..rays.len() {
                assert!(
                    same(&got[i], &closest[i]),
                    "{backend} ({}), {name}: ray {i} at {}: {:?}, the core walk {:?}",
                    opened.backend,
                    times[i],
                    got[i],
                    closest[i]
                );
            }
            let got = opened
                .tracer
                .trace(&rays, &times, Query::Any)
                .expect("traced");
            for i in 0..rays.len() {
                assert_eq!(
                    got[i].is_hit(),
                    any[i].is_hit(),
                    "{backend}, {name}: any, ray {i}"
                );
                assert_eq!(
                    got[i].prim == bvhtrace::core::ray::INVALID_RAY,
                    times[i].is_nan()
                );
            }
        }
    }
    assert!(opened_on.contains(&Backend::Cpu));
}

#[test]
fn bad_times_and_backends_without_kernels_are_refused() {
    let (rays, times) = rays_and_times();
    for (scene, _) in scenes(&rays, &times) {
        let opened = open_timed(scene.clone(), &OpenOptions::new(Backend::Cpu)).expect("the CPU");
        match opened.tracer.trace(&rays, &times[1..], Query::Closest) {
            Err(TraceError::BadBuffer {
                buffer: "times",
                problem,
            }) => {
                assert!(problem.contains("575 times for 576 rays"), "{problem}")
            }
            other => panic!("{}: {other:?}", scene.name()),
        }
        match open_timed(scene.clone(), &OpenOptions::new(Backend::Vulkan)) {
            Err(TraceError::Unsupported { backend, what }) => {
                assert_eq!(backend, "vulkan");
                assert!(what.starts_with(scene.name()), "{what}");
            }
            Err(e) if no_device(&e) => eprintln!("SKIP vulkan: {e}"),
            other => panic!("{}: {other:?}", scene.name()),
        }
    }
}

#[test]
fn ray_queries_trace_our_walks_and_say_so() {
    let (rays, times) = rays_and_times();
    let (scene, [closest, _]) = scenes(&rays, &times).swap_remove(0);
    let opened = match open_timed(scene, &OpenOptions::new(Backend::RayQuery)) {
        Ok(o) => o,
        Err(e) => return eprintln!("SKIP ray queries: {e}"),
    };
    let note = opened.fallback.as_deref().unwrap_or_default();
    assert!(note.contains("no motion blur or curves"), "{note:?}");
    let got = opened
        .tracer
        .trace(&rays, &times, Query::Closest)
        .expect("traced");
    assert!(got.iter().zip(&closest).all(|(a, b)| same(a, b)));
}
