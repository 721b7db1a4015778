//! A hit's instance on the CPU: `TraceOutput::instance_hit` gives every hit of a two-level
//! scene the instance, user id and mesh primitive `InstancedBvh::locate` gives, for every
//! walk; one mesh carries no table; `instance_surface` leaves each hit on the incoming side
//! with the world triangle's normal.

use bvhtrace_core::hits::instance_surface;
use bvhtrace_core::surface::facing_normal;
use bvhtrace_core::{
    BuildOptions, FlatBvh, Instance, InstancedBvh, Ray, TraceOptions, Traversal, Triangle,
    trace_rays,
};
use glam::{Affine3A, Quat, Vec3};

mod common;

fn scene() -> InstancedBvh {
    let meshes = vec![
        common::uv_sphere(10, 1.0, Vec3::ZERO),
        common::uv_sphere(6, 0.7, Vec3::new(0.2, 0.0, 0.0)),
    ];
    let place = |mesh, t: Affine3A, user_id| Instance {
        user_id,
        ..Instance::new(mesh, t)
    };
    let instances = vec![
        place(0, Affine3A::IDENTITY, 100),
        place(1, Affine3A::from_translation(Vec3::new(3.0, 0.0, 0.0)), 7),
        place(
            0,
            Affine3A::from_scale_rotation_translation(
                Vec3::new(1.5, 0.5, 1.0),
                Quat::from_rotation_z(0.6),
                Vec3::new(-3.0, 1.0, 0.0),
            ),
            55,
        ),
        place(
            1,
            Affine3A::from_translation(Vec3::new(0.0, -3.0, 0.5)),
            100,
        ),
    ];
    InstancedBvh::build(&meshes, instances, &BuildOptions::default()).expect("builds")
}

/// A grid of rays from +z towards the scene.
fn rays() -> Vec<Ray> {
    let mut v = Vec::new();
    for y in -40..40 {
        for x in -60..60 {
            let o = Vec3::new(x as f32 * 0.08, y as f32 * 0.08, 6.0);
            v.push(Ray::new(o, Vec3::new(0.01, -0.02, -1.0)));
        }
    }
    v
}

#[test]
fn every_hit_names_the_instance_and_primitive_locate_names() {
    let ib = scene();
    let rays = rays();
    for walk in [Traversal::FullStack, Traversal::Stackless, Traversal::Wide] {
        let bvh = ib.bvh().clone().with_wide();
        let out = trace_rays(&bvh, &rays, &TraceOptions::closest(walk));
        assert_eq!(out.instances.as_ref().map(|t| t.len()), Some(4));
        let mut seen = [0usize; 4];
        for (i, hit) in out.hits.iter().enumerate() {
            let got = out.instance_hit(i);
            if !hit.is_hit() {
                assert_eq!(got, None, "{walk}: ray {i} missed");
                continue;
            }
            let got = got.unwrap_or_else(|| panic!("{walk}: hit {i} has no instance"));
            let (inst, prim) = ib.locate(hit.prim).expect("locate knows every hit");
            assert_eq!((got.instance, got.prim), (inst, prim), "{walk}: ray {i}");
            assert_eq!(got.user_id, ib.instances()[inst as usize].user_id);
            seen[inst as usize] += 1;
        }
        assert!(
            seen.iter().all(|&n| n > 20),
            "{walk}: every instance is hit: {seen:?}"
        );
        assert_eq!(out.instance_hits().count(), rays.len());
    }
}

#[test]
fn one_mesh_has_no_instance_table() {
    let tris: Vec<Triangle> = common::uv_sphere(8, 1.0, Vec3::ZERO);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
    let out = trace_rays(&bvh, &rays(), &TraceOptions::default());
    assert!(out.instances.is_none());
    assert!(out.hits.iter().any(|h| h.is_hit()));
    assert!(out.instance_hits().all(|h| h.is_none()));
}

#[test]
fn instance_surface_faces_the_ray_with_the_world_normal() {
    let ib = scene();
    let bvh = ib.bvh();
    let rays = rays();
    let out = trace_rays(bvh, &rays, &TraceOptions::default());
    let mut checked = 0;
    for (i, hit) in out.hits.iter().enumerate().filter(|(_, h)| h.is_hit()) {
        let located = out.instance_hit(i).expect("a hit has an instance");
        let inst = &bvh.instances()[located.instance as usize];
        let mesh = &ib.meshes()[ib.instances()[located.instance as usize].mesh as usize];
        let tri = (mesh.tri_base..mesh.tri_base + mesh.triangles)
            .map(|s| &bvh.triangles()[s as usize])
            .find(|t| t.prim == located.prim)
            .expect("the mesh holds the primitive")
            .corners();
        let dir = Vec3::from(rays[i].dir);
        let s = instance_surface(hit, &tri, inst, &rays[i]);
        let world = ib.world_triangle(hit.prim).expect("a world triangle");
        let want = facing_normal(&world, dir);
        assert!(
            s.normal.dot(want) > 0.999,
            "ray {i}: normal {} against the world triangle's {want}",
            s.normal
        );
        assert!(
            s.normal.dot(dir) <= 0.0,
            "ray {i}: the normal faces the ray"
        );
        let p = Vec3::from(rays[i].origin) + dir * hit.t;
        assert!(
            (s.origin - p).dot(s.normal) > 0.0,
            "ray {i}: the origin is above the surface"
        );
        checked += 1;
    }
    assert!(checked > 500, "{checked} hits checked");
}
