//! Motion blur: the moving-mesh BVH against the static walks at the shutter's ends, against
//! the f32 brute force and the f64 oracle at every time, closed moving meshes at every
//! time, and the stress cases (a triangle that flips, no motion, huge motion, bad times).

mod common;

use bvhtrace_core::motion::{
    MotionBvh, MotionError, MotionInstancedBvh, MotionMesh, MovingInstance, TimeBounds,
};
use bvhtrace_core::traverse::Best;
use bvhtrace_core::*;
use common::{rays_for, soup, uv_sphere, xorshift};
use glam::{Mat3, Mat4, Vec3};
use proptest::prelude::*;

#[path = "../../../tests/support/rays.rs"]
mod support_rays;
use support_rays::edge_rays;

const BOUNDS: [TimeBounds; 2] = [TimeBounds::Linear, TimeBounds::Merged];

/// The closest (or any) hit among `tris` by the walks' f32 test and hit rule, every
/// triangle tested.
fn brute(tris: &[Triangle], ray: &Ray, query: Query) -> Hit {
    if !ray.is_valid() {
        return traverse::untraced(ray);
    }
    let r = intersect::PreparedRay::new(ray);
    let mut best = Best::start(ray);
    for (i, t) in tris.iter().enumerate() {
        if let Some(h) = intersect::intersect_triangle(&r, t[0], t[1], t[2])
            && best.offer(h.t, i as u32, h.u, h.v)
            && query == Query::Any
        {
            break;
        }
    }
    best.into_hit()
}

/// `tris` moved by `m` about `pivot` and by `shift`.
fn moved(tris: &[Triangle], m: Mat3, pivot: Vec3, shift: Vec3) -> Vec<Triangle> {
    tris.iter()
        .map(|t| t.map(|p| m * (p - pivot) + pivot + shift))
        .collect()
}

/// A soup at three steps: still, turned and shifted, turned back further.
fn three_steps(tris: &[Triangle]) -> MotionMesh {
    let c = tris.iter().flatten().copied().sum::<Vec3>() / (3 * tris.len()) as f32;
    MotionMesh::new(vec![
        tris.to_vec(),
        moved(
            tris,
            Mat3::from_rotation_y(0.4),
            c,
            Vec3::new(0.5, 0.0, -0.2),
        ),
        moved(
            tris,
            Mat3::from_rotation_x(-0.3),
            c,
            Vec3::new(0.1, 0.7, 0.0),
        ),
    ])
    .unwrap()
}

#[test]
fn the_shutters_ends_are_the_static_meshes_bit_for_bit() {
    let tris = uv_sphere(12, 1.0, Vec3::ZERO);
    let mesh = three_steps(&tris);
    for bounds in BOUNDS {
        let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), bounds).unwrap();
        for (time, step) in [(0.0, 0), (0.5, 1), (1.0, 2)] {
            let fixed = mesh.step(step);
            let flat = FlatBvh::build(fixed, &BuildOptions::default()).unwrap();
            let rays = rays_for(fixed, 7 + step as u64, 2000);
            for query in [Query::Closest, Query::Any] {
                let opts = TraceOptions::new(Traversal::FullStack, query);
                let want = trace_rays(&flat, &rays, &opts).hits;
                let got = bvh.trace_rays(&rays, &vec![time; rays.len()], query);
                for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                    match query {
                        Query::Closest => assert_eq!(g, w, "{bounds:?} t={time} ray {i}"),
                        Query::Any => assert_eq!(g.is_hit(), w.is_hit(), "{bounds:?} ray {i}"),
                    }
                }
            }
        }
    }
}

#[test]
fn every_time_answers_as_the_brute_force_and_the_oracle() {
    let tris = uv_sphere(10, 1.0, Vec3::new(0.2, -0.1, 0.3));
    let mesh = three_steps(&tris);
    let mut rnd = xorshift(99);
    let (mut hits, mut tested) = (0, 0);
    for bounds in BOUNDS {
        let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), bounds).unwrap();
        for (i, ray) in rays_for(mesh.step(1), 3, 1500).iter().enumerate() {
            let time = rnd();
            let at = mesh.at(time);
            for query in [Query::Closest, Query::Any] {
                let (got, _) = bvh.trace(ray, time, query);
                let want = brute(&at, ray, query);
                match query {
                    Query::Closest => assert_eq!(got, want, "{bounds:?} ray {i} at {time}"),
                    Query::Any => assert_eq!(got.is_hit(), want.is_hit(), "ray {i}"),
                }
            }
            let (got, _) = bvh.trace(ray, time, Query::Closest);
            let oracle = oracle::closest_hit(&at, ray);
            assert!(
                got.prim == oracle.prim
                    || oracle::agreement(&at, ray, &got, &oracle_hit(&oracle), false).agrees(),
                "{bounds:?} ray {i} at {time}: {got:?} vs the oracle's {oracle:?}"
            );
            hits += got.is_hit() as usize;
            tested += 1;
        }
    }
    assert!(
        hits > tested / 4,
        "{hits} of {tested} rays hit: the rays miss the mesh"
    );
}

fn oracle_hit(o: &oracle::OracleHit) -> Hit {
    Hit {
        t: o.t as f32,
        prim: o.prim,
        u: o.u as f32,
        v: o.v as f32,
    }
}

#[test]
fn no_ray_escapes_a_closed_moving_mesh_at_any_time() {
    let c0 = Vec3::new(0.3, -0.2, 0.1);
    let sphere = uv_sphere(8, 1.0, c0);
    let shifts = [
        Vec3::ZERO,
        Vec3::new(2.0, 0.5, -1.0),
        Vec3::new(2.5, -0.5, 0.0),
    ];
    let steps = [0.0f32, 0.35, 0.7]
        .iter()
        .zip(shifts)
        .map(|(&a, s)| moved(&sphere, Mat3::from_rotation_z(a) * (1.0 + a), c0, s))
        .collect();
    let mesh = MotionMesh::new(steps).unwrap();
    for bounds in BOUNDS {
        let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), bounds).unwrap();
        for time in [0.0, 0.1, 0.25, 0.5, 0.5001, 0.8, 0.999, 1.0] {
            let (s, f) = motion::time_segment(time, 3);
            let centre = c0 + shifts[s].lerp(shifts[s + 1], f);
            let at = mesh.at(time);
            let rays = edge_rays(&at, centre);
            let hits = bvh.trace_rays(&rays, &vec![time; rays.len()], Query::Closest);
            let escaped = hits.iter().filter(|h| !h.is_hit()).count();
            assert_eq!(
                escaped, 0,
                "{bounds:?}: {escaped} rays escaped at time {time}"
            );
        }
    }
}

#[test]
fn linear_bounds_test_fewer_boxes_than_merged_ones() {
    // Strands of a grass field swaying: each triangle moves far against its size.
    let mut rnd = xorshift(5);
    let blades: Vec<Triangle> = (0..4000)
        .map(|_| {
            let p = Vec3::new(rnd() * 20.0, 0.0, rnd() * 20.0);
            [
                p,
                p + Vec3::new(0.05, 0.0, 0.0),
                p + Vec3::new(0.02, 1.0, 0.0),
            ]
        })
        .collect();
    let swayed = blades
        .iter()
        .map(|t| [t[0], t[1], t[2] + Vec3::new(0.8, -0.2, 0.3)])
        .collect();
    let mesh = MotionMesh::new(vec![blades, swayed]).unwrap();
    let rays = rays_for(mesh.step(0), 11, 3000);
    let mut nodes = Vec::new();
    for bounds in BOUNDS {
        let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), bounds).unwrap();
        let mut rnd = xorshift(17);
        let mut sum = 0u64;
        for r in &rays {
            sum += bvh.trace(r, rnd(), Query::Closest).1.nodes as u64;
        }
        nodes.push(sum);
    }
    eprintln!("boxes tested: linear {}, merged {}", nodes[0], nodes[1]);
    assert!(
        nodes[0] * 10 < nodes[1] * 9,
        "linear bounds tested {} boxes, merged {}",
        nodes[0],
        nodes[1]
    );
}

#[test]
fn a_triangle_that_flips_is_hit_from_either_side_and_missed_when_flat() {
    // Corners 1 and 2 trade places: at mid-shutter the triangle is a segment.
    let a = [
        Vec3::ZERO,
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ];
    let b = [a[0], a[2], a[1]];
    let mesh = MotionMesh::new(vec![vec![a], vec![b]]).unwrap();
    let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), TimeBounds::Linear).unwrap();
    let ray = Ray::new(Vec3::new(0.2, 0.3, 1.0), Vec3::new(0.0, 0.0, -1.0));
    for time in [0.0, 0.25, 0.75, 1.0] {
        let (h, _) = bvh.trace(&ray, time, Query::Closest);
        assert_eq!((h.prim, h.t), (0, 1.0), "time {time}");
    }
    // At 0.5 both moving corners are at (0.5, 0.5, 0): no area, no hit off its line.
    assert!(!bvh.trace(&ray, 0.5, Query::Closest).0.is_hit());
}

#[test]
fn huge_and_zero_motion_answer_as_the_brute_force() {
    let tris = uv_sphere(6, 1.0, Vec3::ZERO);
    for shift in [
        Vec3::ZERO,
        Vec3::new(1e7, -3e6, 0.0),
        Vec3::new(0.0, 1e-30, 0.0),
    ] {
        let far = moved(&tris, Mat3::IDENTITY, Vec3::ZERO, shift);
        let mesh = MotionMesh::new(vec![tris.clone(), far]).unwrap();
        let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), TimeBounds::Linear).unwrap();
        for time in [0.0, 1e-7, 0.3, 0.5, 1.0 - 1e-7, 1.0] {
            let at = mesh.at(time);
            for ray in rays_for(&at, 21, 300) {
                let got = bvh.trace(&ray, time, Query::Closest).0;
                assert_eq!(got, brute(&at, &ray, Query::Closest), "{shift} at {time}");
            }
        }
    }
}

#[test]
fn times_outside_the_shutter_are_clamped_and_nan_is_invalid() {
    let a = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let b = a.map(|p| p + Vec3::new(5.0, 0.0, 0.0));
    let mesh = MotionMesh::new(vec![vec![a], vec![b]]).unwrap();
    let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), TimeBounds::Linear).unwrap();
    let at = |x: f32| Ray::new(Vec3::new(x + 0.2, 0.2, 1.0), Vec3::new(0.0, 0.0, -1.0));
    assert!(bvh.trace(&at(0.0), -3.0, Query::Closest).0.is_hit());
    assert!(!bvh.trace(&at(5.0), -3.0, Query::Closest).0.is_hit());
    assert!(bvh.trace(&at(5.0), 7.0, Query::Closest).0.is_hit());
    assert!(
        bvh.trace(&at(5.0), f32::INFINITY, Query::Closest)
            .0
            .is_hit()
    );
    assert_eq!(
        bvh.trace(&at(0.0), f32::NAN, Query::Any).0.prim,
        INVALID_RAY
    );
}

#[test]
fn bad_motion_meshes_are_refused_naming_the_step() {
    let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
    assert_eq!(
        MotionMesh::new(vec![vec![t]]),
        Err(MotionError::TooFewSteps(1))
    );
    let e = MotionMesh::new(vec![vec![t, t], vec![t]]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "time step 1 has 1 triangles, time step 0 has 2"
    );
    let nan = [Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0), Vec3::Y];
    let e = MotionMesh::new(vec![vec![t], vec![t], vec![nan]]).unwrap_err();
    assert!(
        e.to_string()
            .starts_with("time step 2: triangle 0: corner 1"),
        "{e}"
    );
    let many = vec![vec![t]; motion::MAX_TIME_STEPS + 1];
    assert!(MotionMesh::new(many).is_err());
    let empty = MotionMesh::new(vec![vec![], vec![]]).unwrap();
    assert!(MotionBvh::build(&empty, &BuildOptions::default(), TimeBounds::Linear).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]
    /// Random soups (slivers, degenerate and duplicate triangles, mixed scales) moving
    /// between two random poses: every walk answer is the brute force's at its time, under
    /// the static walks' exception.
    #[test]
    fn moving_soups_answer_as_the_brute_force(
        a in soup(), seed in 1u64..1000, shift in common::point(), turn in -3.0f32..3.0
    ) {
        let c = a[0][0];
        let b = moved(&a, Mat3::from_rotation_y(turn), c, shift);
        let mesh = MotionMesh::new(vec![a.clone(), b]).unwrap();
        let mut rnd = xorshift(seed);
        for bounds in BOUNDS {
            let bvh = MotionBvh::build(&mesh, &BuildOptions::default(), bounds).unwrap();
            for ray in rays_for(&a, seed, 64) {
                let time = [0.0, 1.0, rnd()][(seed % 3) as usize];
                let at = mesh.at(time);
                let got = bvh.trace(&ray, time, Query::Closest).0;
                let want = brute(&at, &ray, Query::Closest);
                // The static walks' one exception (`common::f32_departure`): a box may
                // cull an f32 hit that lies outside its triangle's box by more than the
                // box test's slack.
                prop_assert!(got == want || common::f32_departure(&at, &ray, &got, &want),
                    "{:?} at {}: {:?} vs brute force {:?} on {:?}", bounds, time, got, want, ray);
            }
        }
    }
}

/// Spheres placed by moving transforms: `(meshes, instances, the same as one moving mesh)`.
fn moving_spheres() -> (Vec<Vec<Triangle>>, Vec<MovingInstance>, MotionMesh) {
    let sphere = uv_sphere(8, 1.0, Vec3::ZERO);
    let instances: Vec<MovingInstance> = (0..6)
        .map(|i| {
            let x = i as f32 * 2.5;
            let at = |k: f32| {
                Mat4::from_scale_rotation_translation(
                    Vec3::splat(1.0 + 0.2 * k),
                    glam::Quat::from_rotation_y(0.3 * k * i as f32),
                    Vec3::new(x + k * (i % 3) as f32, 0.5 * k, 0.0),
                )
            };
            let transforms = if i == 2 {
                vec![at(0.0)]
            } else {
                vec![at(0.0), at(1.0), at(1.5)]
            };
            MovingInstance {
                mesh: 0,
                transforms,
            }
        })
        .collect();
    let steps = (0..3)
        .map(|k| {
            instances
                .iter()
                .flat_map(|inst| {
                    let m = inst.transforms[k.min(inst.transforms.len() - 1)];
                    sphere.iter().map(move |t| t.map(|p| m.transform_point3(p)))
                })
                .collect()
        })
        .collect();
    (vec![sphere], instances, MotionMesh::new(steps).unwrap())
}

#[test]
fn moving_instances_answer_as_the_same_moving_mesh_flattened() {
    let (meshes, instances, flat) = moving_spheres();
    let opts = BuildOptions::default();
    let mut rnd = xorshift(31);
    for bounds in BOUNDS {
        let two = MotionInstancedBvh::build(&meshes, instances.clone(), &opts, bounds).unwrap();
        let one = MotionBvh::build(&flat, &opts, bounds).unwrap();
        let (mut same, mut hits) = (0, 0);
        let rays = rays_for(flat.step(1), 41, 4000);
        for (i, ray) in rays.iter().enumerate() {
            let time = rnd();
            let (a, b) = (
                one.trace(ray, time, Query::Closest).0,
                two.trace(ray, time, Query::Closest).0,
            );
            hits += a.is_hit() as usize;
            if a.prim == b.prim {
                same += 1;
                continue;
            }
            // The instance is walked in its own space: the same surface, rounded apart.
            let at = flat.at(time);
            let rule = oracle::agreement(&at, ray, &a, &b, false);
            assert!(
                rule.agrees(),
                "{bounds:?} ray {i} at {time}: {a:?} vs {b:?}"
            );
            let any = two.trace(ray, time, Query::Any).0;
            assert_eq!(any.is_hit(), b.is_hit(), "{bounds:?} ray {i}: any hit");
        }
        eprintln!(
            "{bounds:?}: {same} of {} the same primitive, {hits} hits",
            rays.len()
        );
        assert!(same * 1000 >= rays.len() * 995 && hits > rays.len() / 4);
    }
}

#[test]
fn no_ray_escapes_a_moving_instance_at_any_time() {
    let (meshes, instances, _) = moving_spheres();
    let bvh = MotionInstancedBvh::build(
        &meshes,
        instances.clone(),
        &BuildOptions::default(),
        TimeBounds::Linear,
    )
    .unwrap();
    let mut rnd = xorshift(77);
    for inst in &instances {
        for time in [0.0, 0.3, 0.5, 0.77, 1.0] {
            let m = inst.transform_at(motion::time_segment(time, 3));
            let centre = m.transform_point3(Vec3::ZERO);
            let rays: Vec<Ray> = (0..500)
                .map(|_| Ray::new(centre, Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5)))
                .collect();
            let hits = bvh.trace_rays(&rays, &vec![time; rays.len()], Query::Closest);
            assert!(hits.iter().all(|h| h.is_hit()), "a ray escaped at {time}");
        }
    }
}

#[test]
fn bad_moving_instances_are_refused_by_name() {
    let (meshes, mut instances, _) = moving_spheres();
    let build = |i: Vec<MovingInstance>| {
        MotionInstancedBvh::build(&meshes, i, &BuildOptions::default(), TimeBounds::Linear)
            .unwrap_err()
            .to_string()
    };
    instances[1].transforms.pop();
    assert_eq!(
        build(instances.clone()),
        "instance 1 has 2 transforms; each has 1 or 3 (at most 129)"
    );
    instances[1].mesh = 4;
    assert!(build(instances.clone()).starts_with("instance 1: mesh 4 does not exist"));
    instances[1] = MovingInstance {
        mesh: 0,
        transforms: vec![Mat4::ZERO],
    };
    assert!(build(instances.clone()).contains("instance 1, time step 0"));
    assert_eq!(build(Vec::new()), "no instances to build over");
}
