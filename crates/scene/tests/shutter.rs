//! A scene over an open shutter (`Scene::motion`): the time steps are the animation's
//! poses, as many as keep the motion within the tolerance, and bad shutters are refused.

use bvhtrace_scene::{SHUTTER_TOLERANCE, load, repo_scenes_dir};
use glam::Vec3;

#[test]
fn the_steps_are_the_poses_and_follow_curved_motion() {
    let Some(dir) = repo_scenes_dir() else {
        println!("skipped: no scenes/ folder");
        return;
    };
    let scene = load(dir.join("skinned.gltf").to_str().unwrap()).unwrap_or_else(|e| panic!("{e}"));
    let (open, close) = (0.1f32, 0.9f32);
    let mesh = scene.motion(open, close).unwrap_or_else(|e| panic!("{e}"));
    let steps = mesh.time_steps();
    // The tube bends 70 degrees and turns 90: no two steps follow that within 1e-3.
    println!("{steps} time steps");
    assert!(steps > 2, "{steps} steps");
    let posed = |t: f32| {
        let mut s = scene.clone();
        s.set_time(t);
        s.flattened_triangles().unwrap()
    };
    for k in [0, steps / 2, steps - 1] {
        let t = open + (close - open) * (k as f32 / (steps - 1) as f32);
        assert_eq!(mesh.step(k), &posed(t)[..], "step {k} is the pose at {t}");
    }
    // Between the steps the motion is straight to within the tolerance.
    let (lo, hi) = mesh
        .step(0)
        .iter()
        .flatten()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(l, h), &p| {
            (l.min(p), h.max(p))
        });
    let tolerance = SHUTTER_TOLERANCE * (hi - lo).length() * 1.5;
    for s in 0..steps - 1 {
        let u = (s as f32 + 0.5) / (steps - 1) as f32;
        let truth = posed(open + (close - open) * u);
        for (a, b) in mesh.at(u).iter().zip(&truth) {
            for k in 0..3 {
                assert!(
                    a[k].distance(b[k]) <= tolerance,
                    "segment {s}: {} off",
                    a[k].distance(b[k])
                );
            }
        }
    }
}

#[test]
fn a_still_scene_has_two_equal_steps_and_bad_shutters_are_refused() {
    let scene = load("builtin:cornell").unwrap();
    let mesh = scene.motion(0.0, 1.0).unwrap();
    assert_eq!(mesh.time_steps(), 2);
    assert_eq!(mesh.step(0), mesh.step(1));
    assert_eq!(mesh.len(), scene.triangle_count());
    for (open, close) in [
        (1.0, 1.0),
        (2.0, 1.0),
        (f32::NAN, 1.0),
        (0.0, f32::INFINITY),
    ] {
        let e = scene.motion(open, close).unwrap_err().to_string();
        assert!(e.contains("the shutter must open before it closes"), "{e}");
    }
}

#[test]
fn the_moving_builtin_moves_its_right_copy_only() {
    let Some(_) = repo_scenes_dir() else {
        println!("skipped: no scenes/ folder");
        return;
    };
    let scene = load("builtin:moving:icosphere").unwrap_or_else(|e| panic!("{e}"));
    let n = scene.triangle_count() / 2;
    let mesh = scene.motion(0.0, 1.0).unwrap();
    // A 30-degree turn is not straight enough for two steps.
    assert!(mesh.time_steps() > 2, "{} steps", mesh.time_steps());
    let (first, last) = (mesh.step(0), mesh.step(mesh.time_steps() - 1));
    assert_eq!(first[..n], last[..n], "the left copy moved");
    let centre = |t: &[[Vec3; 3]]| t.iter().flatten().sum::<Vec3>() / (3 * t.len()) as f32;
    let moved = centre(&last[n..]) - centre(&first[n..]);
    // Right by a third of the mesh's size (2, the unit sphere's diameter).
    assert!(
        (moved.x - 2.0 / 3.0).abs() < 1e-3 && moved.y.abs() < 1e-3,
        "{moved}"
    );
    // Past the animation's end nothing moves.
    let still = scene.motion(2.0, 3.0).unwrap();
    assert_eq!((still.time_steps(), still.step(0)), (2, still.step(1)));
}
