//! Two-level trees (instances over meshes): the layout's walks against the core's full
//! stack, closest hits bit for bit, any hits on hit or miss, every instruction set equal,
//! with the rays' visibility mask.

mod common;

use bvhtrace_core::intersect::{PreparedRay, intersect_triangle};
use bvhtrace_core::{
    BuildOptions, FlatBvh, Hit, Instance, InstancedBvh, Query, Ray, TraceOptions, Traversal,
    Triangle, oracle,
};
use bvhtrace_cpu::{ConvertError, CpuBvh, Isa};
use common::{rays_for, same, triangle, uv_sphere};
use glam::{Affine3A, Quat, Vec3};
use proptest::prelude::*;

/// The core's full stack with the rays' visibility mask `mask`.
fn reference(flat: &FlatBvh, rays: &[Ray], q: Query, mask: u8) -> Vec<Hit> {
    let opts = TraceOptions::new(Traversal::FullStack, q).with_mask(mask);
    bvhtrace_core::trace_rays(flat, rays, &opts).hits
}

/// Every instruction set's answers with `mask`, equal to the bit; returns the first's.
fn every_isa(bvh: &CpuBvh, rays: &[Ray], q: Query, mask: u8) -> Vec<Hit> {
    let isas = Isa::all_available();
    let first = bvhtrace_cpu::trace_rays_with_mask(bvh, rays, q, mask, isas[0]);
    for &isa in &isas[1..] {
        let h = bvhtrace_cpu::trace_rays_with_mask(bvh, rays, q, mask, isa);
        for (i, (a, b)) in first.iter().zip(&h).enumerate() {
            assert!(same(a, b), "{isa} differs on ray {i}: {b:?} vs {a:?}");
        }
    }
    first
}

/// The core walks' f32 exception, where it arises: in the mesh's space, for the ray the
/// walks test the mesh's triangle with. Each hit must be what the scalar test of its
/// primitive's triangle gives (so a wrong primitive id is no exception).
fn f32_departure(ib: &InstancedBvh, meshes: &[Vec<Triangle>], ray: &Ray, hits: [&Hit; 2]) -> bool {
    let object = |p: u32| {
        let (i, local) = ib.locate(p)?;
        let mesh = &meshes[ib.instances()[i as usize].mesh as usize];
        let r = ib.bvh().instances()[i as usize].ray_to_object(ray);
        Some((mesh[local as usize], r))
    };
    let real = |h: &Hit| {
        object(h.prim).is_some_and(|([a, b, c], r)| {
            intersect_triangle(&PreparedRay::new(&r), a, b, c)
                .is_some_and(|t| (t.t, t.u, t.v) == (h.t, h.u, h.v))
        })
    };
    if !hits.iter().all(|h| real(h)) {
        return false;
    }
    let terr = |p: u32| object(p).map_or(0.0, |(t, r)| oracle::f32_t_error_bound(&t, &r));
    hits.iter()
        .any(|h| object(h.prim).is_some_and(|(t, r)| oracle::f32_indeterminate(&t, &r)))
        || (hits[0].t as f64 - hits[1].t as f64).abs() <= terr(hits[0].prim) + terr(hits[1].prim)
}

/// The layout's answers against the full stack's on `rays` with `mask`: closest hits to
/// the bit (or, when `exceptions`, the f32 exception), any hits on hit or miss as the
/// closest hits. Returns how many closest hits took the exception.
fn check(
    ib: &InstancedBvh,
    meshes: &[Vec<Triangle>],
    rays: &[Ray],
    mask: u8,
    exceptions: bool,
) -> usize {
    let flat = ib.bvh();
    let bvh = CpuBvh::from_flat(flat).expect("converts");
    assert!(bvh.is_instanced());
    let mut taken = 0;
    let want = reference(flat, rays, Query::Closest, mask);
    let closest = every_isa(&bvh, rays, Query::Closest, mask);
    for (i, (g, w)) in closest.iter().zip(&want).enumerate() {
        if same(g, w) {
            continue;
        }
        assert!(
            exceptions && f32_departure(ib, meshes, &rays[i], [g, w]),
            "closest, ray {i} {:?} mask {mask:#x}: got {g:?}, full stack {w:?}",
            rays[i]
        );
        taken += 1;
    }
    // Any hits give the verdict of the closest hits judged above (the full stack's, or
    // where those took the f32 exception, theirs).
    let any = every_isa(&bvh, rays, Query::Any, mask);
    for (i, (g, c)) in any.iter().zip(&closest).enumerate() {
        assert_eq!(
            g.is_hit(),
            c.is_hit(),
            "any, ray {i} {:?} mask {mask:#x}: got {g:?}, closest hit {c:?}",
            rays[i]
        );
        if !c.is_hit() {
            assert!(
                same(g, c),
                "any, ray {i}: a miss to the bit: {g:?} vs {c:?}"
            );
        }
    }
    taken
}

/// Every instance's world triangles (what rays are aimed at).
fn world_triangles(meshes: &[Vec<Triangle>], instances: &[Instance]) -> Vec<Triangle> {
    instances
        .iter()
        .flat_map(|i| {
            let m = i.transform;
            meshes[i.mesh as usize]
                .iter()
                .map(move |t| t.map(|p| m.transform_point3(p)))
        })
        .collect()
}

/// An instance of `mesh`: scaled (`scale`, negative components mirror), turned by `turn`
/// radians about `axis`, moved to `at`, with visibility mask `mask`.
fn placed(mesh: u32, scale: Vec3, axis: Vec3, turn: f32, at: Vec3, mask: u8) -> Instance {
    let rot = Quat::from_axis_angle(axis.try_normalize().unwrap_or(Vec3::Y), turn);
    Instance {
        mask,
        ..Instance::new(
            mesh,
            Affine3A::from_scale_rotation_translation(scale, rot, at),
        )
    }
}

fn instance() -> impl Strategy<Value = (u32, Vec3, Vec3, f32, Vec3, u8)> {
    let scale = prop_oneof![
        3 => Just(Vec3::ONE),
        2 => (0.3f32..3.0, 0.3f32..3.0, 0.3f32..3.0).prop_map(|(x, y, z)| Vec3::new(x, y, z)),
        1 => (0.5f32..2.0).prop_map(|s| Vec3::new(-s, s, s)),
        1 => Just(Vec3::new(1.0, -1.0, -1.0)),
        1 => Just(Vec3::splat(1e-3)),
    ];
    let axis = (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    let at =
        (-30.0f32..30.0, -30.0f32..30.0, -30.0f32..30.0).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    let mask = prop::sample::select(vec![0xffu8, 0x01, 0x02, 0x80]);
    (0u32..3, scale, axis, -4.0f32..4.0, at, mask)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// Random soups placed by random instances (mirrored, scaled, turned, tiny, sharing
    /// meshes, overlapping), random leaf sizes, rays aimed at the placed triangles, and
    /// every visibility mask kind: the full stack's answers.
    #[test]
    fn instanced_soups_give_the_reference_hits(
        meshes in prop::collection::vec(prop::collection::vec(triangle(), 1..60), 1..4),
        placements in prop::collection::vec(instance(), 1..12),
        leaf in prop::sample::select(vec![1usize, 4, 8]),
        mask in prop::sample::select(vec![0xffu8, 0x01, 0x82, 0x00]),
        seed in 1u64..u64::MAX,
    ) {
        let instances: Vec<Instance> = placements
            .iter()
            .map(|&(m, s, a, r, at, k)| placed(m % meshes.len() as u32, s, a, r, at, k))
            .collect();
        let opts = BuildOptions { max_leaf_size: leaf, ..BuildOptions::default() };
        let Ok(ib) = InstancedBvh::build(&meshes, instances.clone(), &opts) else {
            return Ok(());
        };
        let rays = rays_for(&world_triangles(&meshes, &instances), seed, 300);
        check(&ib, &meshes, &rays, mask, true);
    }
}

/// A grid of closed spheres (one mesh, many instances) mirrored, scaled, turned, and
/// two exact copies on top of each other (the tie goes to the lower global id): every
/// closest hit the full stack's to the bit, no exception taken.
#[test]
fn many_instances_of_closed_meshes() {
    let meshes = vec![uv_sphere(12, 1.0, Vec3::ZERO), uv_sphere(5, 0.5, Vec3::X)];
    let mut instances = Vec::new();
    for k in 0..36 {
        let (x, y) = ((k % 6) as f32 * 3.0, (k / 6) as f32 * 3.0);
        let scale = match k % 4 {
            0 => Vec3::ONE,
            1 => Vec3::new(-1.0, 1.0, 1.0),
            2 => Vec3::new(1.3, 0.6, 0.9),
            _ => Vec3::splat(0.7),
        };
        instances.push(placed(
            k % 2,
            scale,
            Vec3::new(1.0, 2.0, 0.5),
            k as f32 * 0.37,
            Vec3::new(x, y, 0.0),
            0xff,
        ));
    }
    // Two copies of one placement: the same t on the same mesh triangle, other ids.
    instances.push(instances[6]);
    let ib = InstancedBvh::build(&meshes, instances.clone(), &BuildOptions::default()).unwrap();
    let mut rays = rays_for(&world_triangles(&meshes, &instances), 7, 4000);
    // Straight at the doubled instance, from in front.
    let c = Vec3::from(instances[6].transform.translation);
    for k in 0..200 {
        let o = Vec3::new(k as f32 * 0.01 - 1.0, 0.3, 8.0) + c;
        rays.push(Ray::new(o, c - o));
    }
    assert_eq!(check(&ib, &meshes, &rays, 0xff, false), 0);
    // The doubled instance's hits report the first copy's ids.
    let bvh = CpuBvh::from_flat(ib.bvh()).unwrap();
    let hits = bvhtrace_cpu::trace_rays(&bvh, &rays[rays.len() - 200..], Query::Closest);
    let bases: Vec<u32> = ib.bvh().instances().iter().map(|i| i.prim_base).collect();
    assert!(hits.iter().all(|h| h.is_hit()));
    assert!(
        hits.iter().all(|h| h.prim >= bases[6] && h.prim < bases[7]),
        "the tie goes to the lower id"
    );
}

/// Instances with visibility masks: rays see only the instances whose mask shares a bit
/// with theirs, as in the core walks.
#[test]
fn instance_masks_hide_instances() {
    let meshes = vec![uv_sphere(8, 1.0, Vec3::ZERO)];
    let masks = [0x01u8, 0x02, 0x04, 0xff];
    // Four spheres in a row along -z, each behind the last.
    let instances: Vec<Instance> = (0..4)
        .map(|k| {
            placed(
                0,
                Vec3::ONE,
                Vec3::Y,
                0.0,
                Vec3::new(0.0, 0.0, -3.0 * k as f32),
                masks[k],
            )
        })
        .collect();
    let ib = InstancedBvh::build(&meshes, instances.clone(), &BuildOptions::default()).unwrap();
    let rays: Vec<Ray> = (0..400)
        .map(|k| {
            let (x, y) = ((k % 20) as f32 * 0.08 - 0.8, (k / 20) as f32 * 0.08 - 0.8);
            Ray::new(Vec3::new(x, y, 5.0), Vec3::NEG_Z)
        })
        .collect();
    let bvh = CpuBvh::from_flat(ib.bvh()).unwrap();
    for mask in [0xffu8, 0x01, 0x02, 0x04, 0x08, 0x06, 0x00] {
        check(&ib, &meshes, &rays, mask, false);
        let hits =
            bvhtrace_cpu::trace_rays_with_mask(&bvh, &rays, Query::Closest, mask, Isa::detect());
        // The nearest instance the mask sees is hit by the central rays.
        let seen = instances.iter().position(|i| i.mask & mask != 0);
        let centre = &hits[10 * 20 + 10];
        match seen {
            Some(k) => assert!(ib.locate(centre.prim).is_some_and(|(i, _)| i as usize == k)),
            None => assert!(!centre.is_hit()),
        }
    }
    // The plain entries see every instance.
    let all = bvhtrace_cpu::trace_rays(&bvh, &rays, Query::Closest);
    assert_eq!(ib.locate(all[10 * 20 + 10].prim).map(|l| l.0), Some(0));
}

/// Each mesh is converted once, whatever the number of its instances: the blocks are
/// the mesh's own, the nodes the top level's and the mesh's.
#[test]
fn meshes_are_converted_once() {
    let mesh = uv_sphere(20, 1.0, Vec3::ZERO);
    let alone =
        CpuBvh::from_flat(&FlatBvh::build(&mesh, &BuildOptions::default()).unwrap()).unwrap();
    let instances: Vec<Instance> = (0..50)
        .map(|k| {
            placed(
                0,
                Vec3::ONE,
                Vec3::Y,
                k as f32,
                Vec3::new(k as f32 * 2.5, 0.0, 0.0),
                0xff,
            )
        })
        .collect();
    let ib = InstancedBvh::build(&[mesh], instances, &BuildOptions::default()).unwrap();
    let bvh = CpuBvh::from_flat(ib.bvh()).unwrap();
    assert_eq!(bvh.blocks(), alone.blocks());
    assert_eq!(bvh.instance_count(), 50);
    assert_eq!(bvh.instance_bytes(), 50 * 72);
    let top = bvh.nodes().len() - alone.nodes().len();
    assert!(
        (7..=49).contains(&top),
        "{top} top-level nodes for 50 instances"
    );
    assert_eq!(&bvh.nodes()[top..].len(), &alone.nodes().len());
    assert!(bvh.depth() > alone.depth());
}

/// A mesh of one leaf starts at its leaf, and a tree of one instance (its top level one
/// leaf) traces.
#[test]
fn one_leaf_meshes_and_one_instance() {
    let tri = vec![[
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ]];
    for n in [1usize, 2, 5] {
        let instances: Vec<Instance> = (0..n)
            .map(|k| {
                placed(
                    0,
                    Vec3::new(1.0, 1.0, -1.0),
                    Vec3::X,
                    0.2,
                    Vec3::new(0.0, 0.0, -(k as f32)),
                    0xff,
                )
            })
            .collect();
        let ib = InstancedBvh::build(
            std::slice::from_ref(&tri),
            instances.clone(),
            &BuildOptions::default(),
        )
        .unwrap();
        let rays = rays_for(
            &world_triangles(std::slice::from_ref(&tri), &instances),
            3,
            500,
        );
        assert_eq!(
            check(&ib, std::slice::from_ref(&tri), &rays, 0xff, false),
            0
        );
    }
}

/// Trees whose instances point outside the arrays, or whose boxes are out of order, are
/// refused with an error, not a panic.
#[test]
fn malformed_two_level_trees_are_refused() {
    let mesh = uv_sphere(4, 1.0, Vec3::ZERO);
    let instances: Vec<Instance> = (0..3)
        .map(|k| {
            placed(
                0,
                Vec3::ONE,
                Vec3::Y,
                0.0,
                Vec3::new(k as f32 * 3.0, 0.0, 0.0),
                0xff,
            )
        })
        .collect();
    let ib = InstancedBvh::build(&[mesh], instances, &BuildOptions::default()).unwrap();
    let corrupt = |edit: &dyn Fn(&mut bvhtrace_core::flat::FlatParts<'_>)| {
        let mut f = ib.bvh().clone();
        edit(&mut f.parts_mut());
        CpuBvh::from_flat(&f).unwrap_err()
    };
    let e = corrupt(&|p| p.instances[1].root = 0);
    assert!(matches!(e, ConvertError::Malformed(_)), "{e}");
    let e = corrupt(&|p| p.instances[2].root = u32::MAX);
    assert!(e.to_string().contains("instance 2"), "{e}");
    let e = corrupt(&|p| {
        let leaf = p.nodes.iter().position(|n| n.is_instance_leaf()).unwrap();
        p.nodes[leaf].right_or_first = 9;
    });
    assert!(e.to_string().contains("instances"), "{e}");
    // A box out of order or NaN (the packets' box test takes the planes' order as given).
    for bad in [f32::NAN, 1e6] {
        let e = corrupt(&|p| {
            let leaf = p.nodes.iter().position(|n| n.is_instance_leaf()).unwrap();
            p.nodes[leaf].min[1] = bad;
        });
        assert!(e.to_string().contains("inverted or NaN on axis 1"), "{e}");
    }
}

/// The committed scenes that trace in two levels (`skinned.gltf`: a ground placed twice;
/// `foliage.gltf` without its masks: a crown placed twice, once mirrored), and
/// `builtin:grid:bunny_69k:3x3` when the shared scenes are there: camera rays and shadow
/// rays from their hits, the full stack's answers with no exception.
#[test]
fn instanced_scenes_give_the_reference_hits() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/");
    let mut specs = vec![format!("{dir}skinned.gltf"), format!("{dir}foliage.gltf")];
    if bvhtrace_scene::shared_scenes_dir().is_some_and(|d| d.join("glb/bunny_69k.glb").is_file()) {
        specs.push("builtin:grid:bunny_69k:3x3".into());
    }
    for spec in specs {
        let opts = bvhtrace_scene::LoadOptions::with_meshes(bvhtrace_scene::shared_scenes_dir());
        let scene = bvhtrace_scene::load_with(&spec, &opts).unwrap();
        let mut traced = scene.tracing_bvh(&BuildOptions::default(), false).unwrap();
        traced.set_masks(None).unwrap();
        let bvhtrace_scene::SceneBvh::Instanced(ib) = &traced else {
            panic!("{spec} traces in two levels");
        };
        let flat = ib.bvh();
        let bvh = CpuBvh::from_flat(flat).unwrap();
        let cam = scene.camera_or_frame(4.0 / 3.0);
        let primary = cam.rays(200, 150);
        let want = reference(flat, &primary, Query::Closest, 0xff);
        let light = cam.eye + Vec3::new(0.3, 1.0, 0.2) * (cam.target - cam.eye).length();
        let shadow: Vec<Ray> = primary
            .iter()
            .zip(&want)
            .filter(|(_, h)| h.is_hit())
            .filter_map(|(r, h)| {
                Some(
                    h.surface(&traced.triangle(h.prim)?, Vec3::from(r.dir))
                        .ray_toward(light),
                )
            })
            .collect();
        assert!(shadow.len() > 1000, "{spec}: {} hits", shadow.len());
        eprintln!(
            "{spec}: {} instances, {} primary and {} shadow rays",
            bvh.instance_count(),
            primary.len(),
            shadow.len()
        );
        for (kind, rays) in [("primary", &primary), ("shadow", &shadow)] {
            for q in [Query::Closest, Query::Any] {
                let want = reference(flat, rays, q, 0xff);
                let got = every_isa(&bvh, rays, q, 0xff);
                let bad = (0..rays.len())
                    .filter(|&i| match q {
                        Query::Closest => !same(&got[i], &want[i]),
                        Query::Any => got[i].is_hit() != want[i].is_hit(),
                    })
                    .count();
                assert_eq!(
                    bad,
                    0,
                    "{spec} {kind} {q:?}: {bad} of {} rays differ",
                    rays.len()
                );
            }
        }
    }
}
