//! The moving-mesh cases (`motion-*`): a closed icosphere that moves, turns and grows
//! over three time steps, and one that turns inside out over two (every triangle flips,
//! passing through a flat mesh at mid-shutter). Each case traces all its rays at one time:
//! the shutter's ends exactly, a step boundary, a time between steps, and times outside the
//! shutter (clamped to its ends). A moving mesh at a time is the triangles
//! [`MotionMesh::at`] gives, the ones the walks test, so each case's `tris` is that scene
//! and it is judged as a static one: rays from inside aimed at its vertices and edges (a
//! miss is a crack, at any time), a camera against the f64 oracle, and the brute force.
//! The `motion-instances-*` cases place the sphere by instances that move (one still, one
//! moving, turning, growing and stretching, one mirrored), judged in each instance's space
//! as the two-level cases are, with the rays the moving walks take into it then.

use bvhtrace_core::motion::MovingInstance;
use bvhtrace_core::{Instance, MotionMesh, Triangle};
use glam::{Affine3A, DQuat, DVec3, Mat4, Quat, Vec3};

use crate::cases::{add_inside_rays, finish_input, fractions, quick, set_budget};
use crate::geom::{
    IndexedMesh, aim_at_placed_vertices_and_edges, camera_rays, flatten_instances, is_inside,
    to_f64, unit_icosphere,
};
use crate::{Case, Expect, Motion, MovingScene, Size};

/// A step of a moving mesh: the base mesh's points placed in f64, rounded once.
type Place = fn(DVec3) -> DVec3;

/// The three steps of the moving sphere: still at the origin, moved, grown and turned
/// 40 degrees, then moved on, shrunk and turned 100 degrees about another axis.
const MOVING: [Place; 3] = [
    |p| p,
    |p| {
        DQuat::from_axis_angle(DVec3::new(1.0, 1.0, 0.0).normalize(), 0.7) * (p * 1.5)
            + DVec3::new(1.5, 0.5, 0.0)
    },
    |p| {
        DQuat::from_axis_angle(DVec3::new(0.0, 1.0, 1.0).normalize(), 1.75) * (p * 0.75)
            + DVec3::new(3.0, -0.5, 1.0)
    },
];

/// The two steps of the sphere that turns inside out: mirrored in the plane `x = 0.25`,
/// so every triangle's winding flips and at mid-shutter the mesh is flat.
const FLIPPING: [Place; 2] = [
    |p| p + DVec3::new(0.25, 0.1, 0.0),
    |p| DVec3::new(0.25 - p.x, p.y + 0.1, p.z),
];

/// Every `motion-*` case.
pub(crate) fn motion_cases(size: Size) -> Vec<Case> {
    let base = unit_icosphere(if quick(size) { 2 } else { 4 });
    let moving = steps(&base, &MOVING);
    let flipping = steps(&base, &FLIPPING);
    let mut out = Vec::new();
    for (name, time, what) in [
        ("t0", 0.0, "the shutter's start exactly"),
        ("t1", 1.0, "the shutter's end exactly"),
        ("t0.5", 0.5, "the middle step exactly"),
        ("t0.3", 0.3, "between the first two steps"),
        ("before", -0.5, "before the shutter (clamped: the start)"),
        ("after", 1.5, "after the shutter (clamped: the end)"),
    ] {
        let description = format!(
            "a closed icosphere moving, turning and growing over 3 time steps, at time {time} ({what}): rays from inside aimed at its vertices and edges at that time, and a camera"
        );
        out.push(case(
            format!("motion-{name}"),
            description,
            &base,
            &moving,
            time,
            size,
        ));
    }
    for (name, time, what) in [
        ("t0.25", 0.25, "its first half: a squashed sphere"),
        ("t0.5", 0.5, "mid-shutter: every triangle in one plane"),
        (
            "t0.75",
            0.75,
            "its second half: inside out, every winding flipped",
        ),
    ] {
        let description = format!(
            "a closed icosphere mirrored over 2 time steps, at time {time} ({what}): rays from inside (where it has one) and a camera"
        );
        out.push(case(
            format!("motion-flip-{name}"),
            description,
            &base,
            &flipping,
            time,
            size,
        ));
    }
    for time in [0.0, 1.0, 0.5, 0.3, 0.8] {
        out.push(instances_case(&base, time, size));
    }
    out
}

/// Three instances of the base mesh: one that stays, one that moves, turns, grows and
/// stretches over 3 steps, and a mirrored one that moves and turns.
fn moving_instances() -> Vec<MovingInstance> {
    let place = |s: Vec3, axis: Vec3, angle: f32, t: Vec3| {
        Mat4::from_scale_rotation_translation(s, Quat::from_axis_angle(axis.normalize(), angle), t)
    };
    let mirror = Vec3::new(-1.0, 1.0, 1.0);
    vec![
        MovingInstance {
            mesh: 0,
            transforms: vec![Mat4::IDENTITY],
        },
        MovingInstance {
            mesh: 0,
            transforms: vec![
                place(Vec3::ONE, Vec3::Y, 0.0, Vec3::new(4.0, 0.0, 0.0)),
                place(Vec3::splat(2.0), Vec3::Y, 1.05, Vec3::new(6.0, 1.0, 0.0)),
                place(
                    Vec3::new(0.5, 1.0, 2.0),
                    Vec3::X,
                    0.5,
                    Vec3::new(8.0, 0.0, 1.0),
                ),
            ],
        },
        MovingInstance {
            mesh: 0,
            transforms: vec![
                place(mirror, Vec3::Y, 0.0, Vec3::new(0.0, 4.0, 0.0)),
                place(mirror * 1.5, Vec3::Z, 0.7, Vec3::new(2.0, 5.0, 0.0)),
                place(mirror, Vec3::Y, 1.57, Vec3::new(4.0, 4.0, 1.0)),
            ],
        },
    ]
}

/// The moving instances traced at `time`: rays from each instance's centre then, aimed at
/// its vertices and edge points there, and a camera.
fn instances_case(base: &IndexedMesh, time: f32, size: Size) -> Case {
    let moving = moving_instances();
    let seg = bvhtrace_core::motion::time_segment(time, 3);
    let placed: Vec<Instance> = (moving.iter())
        .map(|m| Instance::new(0, Affine3A::from_mat4(m.transform_at(seg))))
        .collect();
    let meshes = vec![base.triangles()];
    let mut c = Case::instanced(
        format!("motion-instances-t{time}"),
        format!(
            "a closed icosphere placed by 3 instances, one still, one moving, turning, growing and stretching over 3 steps, one mirrored and moving, at time {time}: rays from inside each and a camera"
        ),
        meshes.clone(),
        placed.clone(),
    );
    for (i, inst) in placed.iter().enumerate() {
        let from = inst.transform.transform_point3(Vec3::ZERO);
        let one = flatten_instances(&meshes, std::slice::from_ref(inst));
        let m = to_f64(&inst.transform);
        let rays = aim_at_placed_vertices_and_edges(
            base,
            |p| m.transform_point3(p),
            from,
            fractions(size),
        );
        if is_inside(&one, from, 0.0) {
            c.push_rays(rays, Expect::MustHit);
        } else {
            c.notes
                .push(format!("instance {i}: its centre is not verified inside"));
            c.push_rays(rays, Expect::Oracle);
        }
    }
    let (w, h) = if quick(size) { (24, 24) } else { (96, 96) };
    let eye = DVec3::new(4.0, 2.0, -12.0);
    c.push_rays(
        camera_rays(eye, DVec3::new(4.0, 2.0, 0.0), 60.0, w, h),
        Expect::Oracle,
    );
    c.motion = Some(Motion {
        scene: MovingScene::Instances {
            meshes,
            instances: moving,
        },
        time,
    });
    set_budget(&mut c, size);
    finish_input(&mut c);
    c
}

/// The base mesh's points at each step, as indexed meshes.
fn steps(base: &IndexedMesh, places: &[Place]) -> Vec<IndexedMesh> {
    (places.iter())
        .map(|place| IndexedMesh {
            positions: (base.positions.iter())
                .map(|p| place(p.as_dvec3()).as_vec3())
                .collect(),
            indices: base.indices.clone(),
        })
        .collect()
}

/// The case of `steps` traced at `time`: inside rays from the centre the mesh has then
/// (when the mesh there is closed around it: [`add_inside_rays`] checks), and a camera.
fn case(
    name: String,
    description: String,
    base: &IndexedMesh,
    steps: &[IndexedMesh],
    time: f32,
    size: Size,
) -> Case {
    let mut c = Case::new(name, description);
    let tri_steps: Vec<Vec<Triangle>> = steps.iter().map(IndexedMesh::triangles).collect();
    let Ok(mesh) = MotionMesh::new(tri_steps.clone()) else {
        c.notes.push("the moving mesh was refused".into());
        return c;
    };
    c.tris = mesh.at(time);
    // The vertices where the walks see them: each corner is interpolated alone, so the
    // shared vertices stay shared and the mesh at `time` stays closed.
    let at_time = IndexedMesh {
        positions: (0..base.positions.len())
            .map(|v| vertex_at(steps, v, time))
            .collect(),
        indices: base.indices.clone(),
    };
    debug_assert_eq!(at_time.triangles(), c.tris);
    let centre =
        (at_time.positions.iter()).fold(Vec3::ZERO, |a, &p| a + p) / at_time.positions.len() as f32;
    let tris = c.tris.clone();
    let flat = tris.iter().all(|t| t[0].x == t[1].x && t[1].x == t[2].x);
    if flat {
        c.notes
            .push("the mesh is flat at this time: no inside".into());
    } else {
        add_inside_rays(&mut c, &at_time, &tris, centre, fractions(size), "centre");
    }
    let (w, h) = if quick(size) { (24, 24) } else { (96, 96) };
    let eye = centre.as_dvec3() + DVec3::new(-1.5, 1.0, -4.0);
    c.push_rays(
        camera_rays(eye, centre.as_dvec3(), 50.0, w, h),
        Expect::Oracle,
    );
    c.motion = Some(Motion {
        scene: MovingScene::Mesh(tri_steps),
        time,
    });
    set_budget(&mut c, size);
    finish_input(&mut c);
    c
}

/// Vertex `v` at `time` as the walks interpolate a triangle's corner.
fn vertex_at(steps: &[IndexedMesh], v: usize, time: f32) -> Vec3 {
    let (s, f) = bvhtrace_core::motion::time_segment(time, steps.len());
    bvhtrace_core::motion::lerp_point(steps[s].positions[v], steps[s + 1].positions[v], f)
}
