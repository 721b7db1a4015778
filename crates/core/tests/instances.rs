//! Two levels on the CPU: every walk equals the brute-force answer over all instances bit
//! for bit, the flattened scene gives the same primitives, and moving things (new
//! transforms, refitted vertices) keeps both true.

use bvhtrace_core::instance::REFIT_REBUILD_ADVISED;
use bvhtrace_core::{
    BuildOptions, FlatBvh, Instance, InstanceError, InstancedBvh, Query, Ray, TraceOptions,
    Triangle, brute_force, trace_ray, trace_rays,
};
use glam::{Affine3A, Quat, Vec3};

mod common;

use common::{WALKS, same};

/// A bumpy open sheet: a second mesh with other triangle counts.
fn sheet(n: usize) -> Vec<Triangle> {
    let h = |x: usize, z: usize| Vec3::new(x as f32, ((x * 7 + z * 3) % 5) as f32 * 0.2, z as f32);
    let mut t = Vec::new();
    for x in 0..n {
        for z in 0..n {
            t.push([h(x, z), h(x + 1, z), h(x + 1, z + 1)]);
            t.push([h(x, z), h(x + 1, z + 1), h(x, z + 1)]);
        }
    }
    t
}

fn meshes() -> Vec<Vec<Triangle>> {
    vec![common::uv_sphere(12, 1.0, Vec3::ZERO), sheet(6)]
}

fn instances() -> Vec<Instance> {
    let axis = Vec3::new(1.0, 2.0, 0.5).normalize();
    vec![
        Instance::new(0, Affine3A::IDENTITY),
        Instance::new(
            0,
            Affine3A::from_rotation_translation(Quat::from_axis_angle(axis, 0.7), Vec3::X * 3.0),
        ),
        Instance::new(
            0,
            Affine3A::from_scale_rotation_translation(
                Vec3::new(2.0, 0.5, 1.0),
                Quat::from_rotation_y(0.3),
                Vec3::new(-3.0, 1.0, 0.5),
            ),
        ),
        // Mirrored.
        Instance::new(
            0,
            Affine3A::from_scale_rotation_translation(
                Vec3::new(-1.0, 1.0, 1.0),
                Quat::IDENTITY,
                Vec3::new(0.0, 3.0, 0.0),
            ),
        ),
        Instance::new(
            1,
            Affine3A::from_scale_rotation_translation(
                Vec3::splat(0.5),
                Quat::from_rotation_x(-0.4),
                Vec3::new(-2.0, -2.0, -1.0),
            ),
        ),
        Instance::new(1, Affine3A::from_translation(Vec3::new(1.0, -3.0, -2.0))),
    ]
}

/// The flattened scene: instance by instance, corners transformed in f32, a mirroring
/// instance's corners 1 and 2 swapped (as `Scene::flatten` does).
fn flatten(meshes: &[Vec<Triangle>], instances: &[Instance]) -> Vec<Triangle> {
    let mut out = Vec::new();
    for i in instances {
        let mirror = i.transform.matrix3.determinant() < 0.0;
        for t in &meshes[i.mesh as usize] {
            let [a, b, c] = t.map(|p| i.transform.transform_point3(p));
            out.push(if mirror { [a, c, b] } else { [a, b, c] });
        }
    }
    out
}

/// Rays from around the scene aimed at points of random world triangles.
fn rays(world: &[Triangle], n: usize) -> Vec<Ray> {
    let mut rnd = common::xorshift(0x9e37_79b9_7f4a_7c15u64);
    (0..n)
        .map(|k| {
            let t = &world[(rnd() * world.len() as f32) as usize % world.len()];
            let (a, b) = (rnd(), rnd());
            let target = t[0] + (t[1] - t[0]) * a * (1.0 - b) + (t[2] - t[0]) * b;
            let origin = Vec3::new(rnd(), rnd(), rnd()) * 16.0 - Vec3::splat(8.0);
            let dir = if k % 11 == 0 {
                Vec3::Y
            } else {
                target - origin
            };
            Ray::new(origin, dir)
        })
        .collect()
}

/// Every walk's closest hit equals brute force bit for bit; any-hit agrees on hit or miss.
fn check_walks(bvh: &FlatBvh, rays: &[Ray]) -> usize {
    let bvh = &bvh.clone().with_wide();
    let wide = bvh.wide().unwrap();
    wide.check_invariants(bvh).unwrap();
    let mut hits = 0;
    for ray in rays {
        let want = brute_force(bvh, ray, Default::default());
        hits += usize::from(want.is_hit());
        for w in WALKS {
            let got = trace_ray(bvh, ray, &TraceOptions::closest(w)).0;
            assert!(
                same(&got, &want),
                "{w}: {got:?} != brute force {want:?} for {ray:?}"
            );
            let any = trace_ray(bvh, ray, &TraceOptions::new(w, Query::Any)).0;
            assert_eq!(any.is_hit(), want.is_hit(), "{w} any-hit for {ray:?}");
        }
    }
    hits
}

#[test]
fn every_walk_equals_brute_force_over_instances() {
    let (m, inst) = (meshes(), instances());
    let ib = InstancedBvh::build(&m, inst.clone(), &BuildOptions::default()).unwrap();
    ib.bvh().check_invariants().unwrap();
    assert_eq!(ib.bvh().top_nodes() as usize, 2 * inst.len() - 1);
    let world = flatten(&m, &inst);
    let rays = rays(&world, 3000);
    let hits = check_walks(ib.bvh(), &rays);
    assert!(hits > 2000, "only {hits} of 3000 rays hit");
}

#[test]
fn flattened_scene_gives_the_same_primitives() {
    let (m, inst) = (meshes(), instances());
    let ib = InstancedBvh::build(&m, inst.clone(), &BuildOptions::default()).unwrap();
    let world = flatten(&m, &inst);
    let flat = FlatBvh::build(&world, &BuildOptions::default()).unwrap();
    let rays = rays(&world, 4000);
    let a = trace_rays(ib.bvh(), &rays, &TraceOptions::default()).hits;
    let b = trace_rays(&flat, &rays, &TraceOptions::default()).hits;
    let (mut same_prim, mut hits) = (0, 0);
    for ((x, y), ray) in a.iter().zip(&b).zip(&rays) {
        if !y.is_hit() {
            continue;
        }
        hits += 1;
        // Both `t` are the same parametrisation; they differ by the rounding of the
        // transformed ray and of the world corners: each moves the plane by a few ulps of
        // the coordinates, which moves `t` by that over the cosine. Where the primitives
        // differ, both are hit within that bound of each other (an edge shared by two
        // triangles, or two surfaces closer than the rounding).
        let bound = |prim: u32, t: f32| {
            let w = world[prim as usize];
            let n = (w[1] - w[0]).cross(w[2] - w[0]).normalize();
            let (o, d) = (Vec3::from(ray.origin), Vec3::from(ray.dir));
            32.0 * f32::EPSILON * (o.length() + t.abs() * d.length()) / n.dot(d).abs()
        };
        if !x.is_hit() {
            // Missed where the flattened scene grazes an edge: a tangent ray through the
            // edge on a silhouette, which either answer may take.
            assert!(y.u.min(y.v).min(1.0 - y.u - y.v) < 1e-3, "missed {y:?}");
            continue;
        }
        assert!(
            (x.t - y.t).abs() <= bound(x.prim, x.t).max(bound(y.prim, y.t)),
            "prim {} at t {} vs flattened prim {} at {}",
            x.prim,
            x.t,
            y.prim,
            y.t
        );
        if x.prim == y.prim {
            same_prim += 1;
            let (w, _) = ib.locate(x.prim).unwrap();
            assert_eq!(
                ib.world_triangle(x.prim).unwrap().map(|p| p.to_array()),
                {
                    let t = world[x.prim as usize];
                    if inst[w as usize].transform.matrix3.determinant() < 0.0 {
                        [t[0], t[2], t[1]]
                    } else {
                        t
                    }
                }
                .map(|p| p.to_array())
            );
        }
    }
    // Differences are rays through an edge or a silhouette, where f32 cannot decide.
    assert!(
        hits > 3000 && same_prim * 100 >= hits * 99,
        "{same_prim} of {hits} hits"
    );
}

#[test]
fn locate_splits_primitive_ids_instance_by_instance() {
    let (m, inst) = (meshes(), instances());
    let ib = InstancedBvh::build(&m, inst.clone(), &BuildOptions::default()).unwrap();
    let (s, q) = (m[0].len() as u32, m[1].len() as u32);
    assert_eq!(ib.locate(0), Some((0, 0)));
    assert_eq!(ib.locate(s - 1), Some((0, s - 1)));
    assert_eq!(ib.locate(s), Some((1, 0)));
    assert_eq!(ib.locate(4 * s + q + 2), Some((5, 2)));
    assert_eq!(ib.locate(4 * s + 2 * q), None);
    assert_eq!(ib.locate(bvhtrace_core::MISS), None);
    assert_eq!(ib.instanced_primitives(), u64::from(4 * s + 2 * q));
}

#[test]
fn masks_hide_instances() {
    let (m, mut inst) = (meshes(), instances());
    for (k, i) in inst.iter_mut().enumerate() {
        i.mask = if k % 2 == 0 { 1 } else { 2 };
    }
    let ib = InstancedBvh::build(&m, inst.clone(), &BuildOptions::default()).unwrap();
    let world = flatten(&m, &inst);
    let rays = rays(&world, 1000);
    let bvh = ib.bvh().clone().with_wide();
    for w in WALKS {
        let only_even = trace_rays(&bvh, &rays, &TraceOptions::closest(w).with_mask(1)).hits;
        let none = trace_rays(&bvh, &rays, &TraceOptions::closest(w).with_mask(4)).hits;
        assert!(
            none.iter().all(|h| !h.is_hit()),
            "{w}: mask 4 hit something"
        );
        let mut seen = 0;
        for h in only_even.iter().filter(|h| h.is_hit()) {
            let (i, _) = ib.locate(h.prim).unwrap();
            assert_eq!(i % 2, 0, "{w}: mask 1 hit odd instance {i}");
            seen += 1;
        }
        assert!(seen > 100, "{w}: {seen} hits with mask 1");
    }
}

#[test]
fn new_transforms_rebuild_the_top_level_in_place() {
    let (m, inst) = (meshes(), instances());
    let mut ib = InstancedBvh::build(&m, inst.clone(), &BuildOptions::default()).unwrap();
    let nodes_before = ib.bvh().nodes().len();
    // Built escape links: the rebuild rewrites the top level's in place.
    ib.bvh().escapes();
    let moved: Vec<Affine3A> = inst
        .iter()
        .enumerate()
        .map(|(k, i)| Affine3A::from_rotation_z(0.2 * k as f32) * i.transform)
        .collect();
    ib.set_transforms(&moved).unwrap();
    assert_eq!(ib.bvh().nodes().len(), nodes_before);
    assert!(ib.bvh().has_escapes());
    assert_eq!(
        ib.bvh().escapes(),
        bvhtrace_core::flat::escape_links(ib.bvh().nodes())
    );
    ib.bvh().check_invariants().unwrap();
    let inst2: Vec<Instance> = inst
        .iter()
        .zip(&moved)
        .map(|(i, t)| Instance {
            transform: *t,
            ..*i
        })
        .collect();
    let rebuilt = InstancedBvh::build(&m, inst2.clone(), &BuildOptions::default()).unwrap();
    assert_eq!(ib.bvh(), rebuilt.bvh());
    check_walks(ib.bvh(), &rays(&flatten(&m, &inst2), 1000));
}

/// A top level from another builder over the instances' boxes (as the device's builder
/// gives it) traces as the CPU's does, every walk; a tree that is not one box per leaf,
/// every box once, or a builder's error, is refused with the BVH left as it was.
#[test]
fn a_top_level_built_elsewhere_is_checked_and_traced() {
    use bvhtrace_core::{BuilderKind, instance::box_triangle};
    let (m, inst) = (meshes(), instances());
    let mut ib = InstancedBvh::build(&m, inst.clone(), &BuildOptions::default()).unwrap();
    let moved: Vec<Affine3A> = (inst.iter().enumerate())
        .map(|(k, i)| Affine3A::from_rotation_y(0.3 * k as f32) * i.transform)
        .collect();
    let over = |boxes: &[bvhtrace_core::Aabb], leaf: usize, skip: usize| {
        let tris: Vec<Triangle> = boxes[skip..].iter().map(box_triangle).collect();
        // Leaves of several boxes when allowed: traversal costs more than testing them.
        let opts = BuildOptions {
            builder: BuilderKind::Median,
            max_leaf_size: leaf,
            cost_traversal: if leaf > 1 { 100.0 } else { 1.0 },
            ..BuildOptions::default()
        };
        FlatBvh::build(&tris, &opts).map_err(|e| e.to_string())
    };
    let before = ib.clone();
    for (bad, want) in [((4, 0), "leaf"), ((1, 1), "nodes"), ((0, 0), "builder")] {
        let mut build = |b: &[bvhtrace_core::Aabb]| match bad {
            (0, _) => Err("the device is gone".to_string()),
            (leaf, skip) => over(b, leaf, skip),
        };
        let e = ib
            .set_transforms_with(&moved, &mut build)
            .expect_err("a bad top level");
        assert!(e.to_string().contains(want), "{e}");
        assert_eq!(ib, before, "a refused top level changed the BVH");
    }
    ib.set_transforms_with(&moved, &mut |b| over(b, 1, 0))
        .unwrap();
    ib.bvh().check_invariants().unwrap();
    let mut cpu = before.clone();
    cpu.set_transforms(&moved).unwrap();
    assert_ne!(
        ib.bvh().nodes(),
        cpu.bvh().nodes(),
        "the median tree is another tree"
    );
    let placed: Vec<Instance> = (inst.iter().zip(&moved))
        .map(|(i, t)| Instance {
            transform: *t,
            ..*i
        })
        .collect();
    check_walks(ib.bvh(), &rays(&flatten(&m, &placed), 1000));
}

#[test]
fn refit_keeps_every_walk_exact_and_reports_quality() {
    let (mut m, inst) = (meshes(), instances());
    let mut ib = InstancedBvh::build(&m, inst.clone(), &BuildOptions::default()).unwrap();
    assert_eq!(ib.refit_quality(0), 1.0);
    // Every vertex moves: the sphere becomes a wobbly ellipsoid.
    for t in &mut m[0] {
        for p in t.iter_mut() {
            *p = Vec3::new(p.x * 1.5, p.y + 0.3 * (p.x * 5.0).sin(), p.z * 0.8);
        }
    }
    ib.refit_mesh(0, &m[0]).unwrap();
    ib.bvh().check_invariants().unwrap();
    let q = ib.refit_quality(0);
    assert!(
        q.is_finite() && q > 0.5 && q < REFIT_REBUILD_ADVISED * 4.0,
        "quality {q}"
    );
    check_walks(ib.bvh(), &rays(&flatten(&m, &inst), 1500));
    let rebuilt = ib.rebuild_mesh(0, &m[0], &BuildOptions::default()).unwrap();
    rebuilt.bvh().check_invariants().unwrap();
    assert_eq!(rebuilt.refit_quality(0), 1.0);
}

/// `FlatBvh::refit` on one mesh: the boxes those of the two-level refit's mesh, every walk
/// exact on the moved mesh, the wide layout collapsed again, and refusals that leave the
/// tree as it was.
#[test]
fn a_one_mesh_refit_keeps_every_walk_exact() {
    let mut m = meshes().swap_remove(0);
    let mut bvh = FlatBvh::build(&m, &BuildOptions::default())
        .unwrap()
        .with_wide();
    let built = bvh.clone();
    for t in &mut m {
        for p in t.iter_mut() {
            *p = Vec3::new(p.x * 1.5, p.y + 0.3 * (p.x * 5.0).sin(), p.z * 0.8);
        }
    }
    bvh.refit(&m).unwrap();
    bvh.check_invariants().unwrap();
    assert_ne!(bvh.nodes(), built.nodes(), "the boxes moved");
    assert_eq!(bvh.wide().unwrap().check_invariants(&bvh), Ok(()));
    let mut two = InstancedBvh::build(
        std::slice::from_ref(&built_triangles(&built)),
        vec![Instance::new(0, Affine3A::IDENTITY)],
        &BuildOptions::default(),
    )
    .unwrap();
    two.refit_mesh(0, &m).unwrap();
    let top = two.bvh().top_nodes() as usize;
    let boxes =
        |n: &[bvhtrace_core::FlatNode]| n.iter().map(|n| (n.min, n.max)).collect::<Vec<_>>();
    assert_eq!(boxes(bvh.nodes()), boxes(&two.bvh().nodes()[top..]));
    check_walks(&bvh, &rays(&m, 1500));

    let before = bvh.clone();
    let mut bad = m.clone();
    bad[5][2].z = f32::INFINITY;
    assert!(
        bvh.refit(&bad)
            .unwrap_err()
            .to_string()
            .contains("triangle 5")
    );
    assert!(
        bvh.refit(&m[1..])
            .unwrap_err()
            .to_string()
            .contains("rebuild")
    );
    assert!(
        two.bvh().clone().refit(&m).is_err(),
        "two levels refit a mesh at a time"
    );
    assert_eq!(bvh, before, "a refused refit left the BVH changed");
}

/// The triangles of a one-mesh tree in the builder's input order.
fn built_triangles(bvh: &FlatBvh) -> Vec<Triangle> {
    let mut out = vec![[Vec3::ZERO; 3]; bvh.triangle_count()];
    for t in bvh.triangles() {
        out[t.prim as usize] = t.corners();
    }
    out
}

#[test]
fn unusable_instances_and_vertices_are_errors_naming_them() {
    let (m, mut inst) = (meshes(), instances());
    let build = |inst: Vec<Instance>| InstancedBvh::build(&m, inst, &BuildOptions::default());
    let index_of = |e: InstanceError| match e {
        InstanceError::BadInstance { index, .. } => index,
        e => panic!("unexpected {e}"),
    };
    inst[2].transform.matrix3.x_axis.y = f32::NAN;
    assert_eq!(index_of(build(inst.clone()).unwrap_err()), 2);
    inst[2] = Instance::new(0, Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0)));
    let e = build(inst.clone()).unwrap_err();
    assert!(e.to_string().contains("singular"), "{e}");
    assert_eq!(index_of(e), 2);
    inst[2] = Instance::new(0, Affine3A::from_translation(Vec3::splat(f32::INFINITY)));
    assert_eq!(index_of(build(inst.clone()).unwrap_err()), 2);
    inst[2] = Instance::new(7, Affine3A::IDENTITY);
    assert_eq!(index_of(build(inst.clone()).unwrap_err()), 2);
    assert_eq!(build(Vec::new()).unwrap_err(), InstanceError::NoInstances);

    let mut ib = build(instances()).unwrap();
    let before = ib.clone();
    let mut bad = m[1].clone();
    bad[3][1].x = f32::NAN;
    let e = ib.refit_mesh(1, &bad).unwrap_err();
    assert!(matches!(e, InstanceError::BadMesh { mesh: 1, .. }), "{e}");
    assert!(ib.refit_mesh(1, &bad[1..]).is_err());
    let mut t = vec![Affine3A::IDENTITY; 6];
    t[4] = Affine3A::from_scale(Vec3::ZERO);
    assert_eq!(index_of(ib.set_transforms(&t).unwrap_err()), 4);
    assert_eq!(ib, before, "a refused change left the BVH changed");
}
