//! glTF node animations: interpolation (LINEAR with slerp, STEP, CUBICSPLINE), clamping,
//! hierarchies, the global transform, skins and morph targets, `scenes/animated.gltf`,
//! `scenes/skinned.gltf` and `scenes/morph.gltf`, and bad input.
//!
//! Set `BVHTRACE_WRITE_ANIMATED=1` to rewrite `scenes/animated.gltf` from
//! [`animated_asset`] (the test `committed_asset_matches_its_generator` then passes).

mod common;

use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};

use bvhtrace_scene::{
    Channel, ErrorKind, Interpolation, Property, Scene, SceneError, load, load_gltf_file,
    load_gltf_slice,
};
use common::{F32, Gltf, TRI};
use glam::{DVec3, Mat4, Quat, Vec3, Vec4};
use serde_json::{Value, json};

// ---------------------------------------------------------------------------------------
// Helpers: hand-made animated files.

/// A document with the unit triangle as accessors 0 (POSITION) and 1 (indices).
fn base() -> Gltf {
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    g
}

fn scalars(g: &mut Gltf, v: &[f32]) -> usize {
    g.raw(bytemuck::cast_slice(v), v.len(), "SCALAR", F32, json!({}))
}

fn vec4s(g: &mut Gltf, v: &[[f32; 4]]) -> usize {
    g.raw(bytemuck::cast_slice(v), v.len(), "VEC4", F32, json!({}))
}

/// Output values of a sampler.
enum Out<'a> {
    V3(&'a [[f32; 3]]),
    V4(&'a [[f32; 4]]),
}

fn output(g: &mut Gltf, out: Out) -> usize {
    match out {
        Out::V3(v) => g.vec3(v),
        Out::V4(v) => vec4s(g, v),
    }
}

/// `nodes` (mesh 0 is the triangle), the scene made of `roots`, and `rest` (animations...).
fn document(g: &Gltf, nodes: Value, roots: &[usize], rest: Value) -> String {
    let mut doc = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": nodes,
        "scenes": [{"nodes": roots}],
        "scene": 0,
    });
    if let Value::Object(m) = rest {
        for (k, v) in m {
            doc[k] = v;
        }
    }
    g.to_gltf(doc)
}

fn parse(text: &str) -> Result<Scene, SceneError> {
    load_gltf_slice(text.as_bytes(), "test.gltf", None)
}

/// One animation with one channel on `node` (`path`, `interp`) over the given keys.
fn one_channel(
    nodes: Value,
    roots: &[usize],
    node: usize,
    path: &str,
    interp: &str,
    times: &[f32],
    out: Out,
) -> Result<Scene, SceneError> {
    let mut g = base();
    let i = scalars(&mut g, times);
    let o = output(&mut g, out);
    parse(&document(
        &g,
        nodes,
        roots,
        json!({"animations": [{
            "name": "clip",
            "samplers": [{"input": i, "output": o, "interpolation": interp}],
            "channels": [{"sampler": 0, "target": {"node": node, "path": path}}],
        }]}),
    ))
}

fn ok(r: Result<Scene, SceneError>) -> Scene {
    r.unwrap_or_else(|e| panic!("{e}"))
}

/// The committed `scenes/animated.gltf`, or `None` (saying so for `test`) without the
/// repository's scenes folder.
fn animated_gltf(test: &str) -> Option<std::path::PathBuf> {
    let Some(dir) = bvhtrace_scene::repo_scenes_dir() else {
        println!("{test}: skipped, no scenes/ folder");
        return None;
    };
    Some(dir.join("animated.gltf"))
}

/// A scene of one mesh node animated along `path` by one channel.
fn node0(path: &str, interp: &str, times: &[f32], out: Out) -> Scene {
    ok(one_channel(
        json!([{"mesh": 0}]),
        &[0],
        0,
        path,
        interp,
        times,
        out,
    ))
}

/// A scene whose node 0 is animated along `path` by one CUBICSPLINE vec3 channel: `keys`
/// are (in-tangent, value, out-tangent) at `times`.
fn cubic_v3(path: &str, times: &[f32], keys: &[[[f32; 3]; 3]]) -> Scene {
    let out: Vec<[f32; 3]> = keys.iter().flatten().copied().collect();
    node0(path, "CUBICSPLINE", times, Out::V3(&out))
}

/// The cubic spline through `keys` (as [`cubic_v3`] takes them) at `t`, between the first
/// and the last of `times`, in f64 ([`hermite`]).
fn cubic_v3_at(times: &[f32], keys: &[[[f32; 3]; 3]], t: f32) -> Vec3 {
    let k = (0..times.len() - 1).rfind(|&k| times[k] <= t).unwrap_or(0);
    let d = |a: [f32; 3]| Vec3::from(a).as_dvec3();
    hermite(
        f64::from(t),
        f64::from(times[k]),
        f64::from(times[k + 1]),
        d(keys[k][1]),
        d(keys[k][2]),
        d(keys[k + 1][0]),
        d(keys[k + 1][1]),
    )
    .as_vec3()
}

fn translation(m: Mat4) -> Vec3 {
    m.w_axis.truncate()
}

/// The single instance's transform at time `t`.
fn at(s: &Scene, t: f32) -> Mat4 {
    let v = s.instance_transforms_at(t);
    assert_eq!(v.len(), s.instances.len());
    v[0]
}

fn close(a: Vec3, b: Vec3, eps: f32) -> bool {
    (a - b).abs().max_element() <= eps
}

/// The cubic Hermite spline of the glTF specification, in f64, written out term by term.
fn hermite(t: f64, t0: f64, t1: f64, v0: DVec3, out0: DVec3, in1: DVec3, v1: DVec3) -> DVec3 {
    let td = t1 - t0;
    let s = (t - t0) / td;
    let h00 = 2.0 * s.powi(3) - 3.0 * s.powi(2) + 1.0;
    let h10 = s.powi(3) - 2.0 * s.powi(2) + s;
    let h01 = -2.0 * s.powi(3) + 3.0 * s.powi(2);
    let h11 = s.powi(3) - s.powi(2);
    v0 * h00 + out0 * (td * h10) + v1 * h01 + in1 * (td * h11)
}

/// Loads `text`, expecting an error that names the file, animation 0 and each of `causes`.
fn expect_error(text: &str, causes: &[&str]) -> SceneError {
    let e = parse(text).expect_err("expected an error");
    let msg = e.to_string();
    assert!(msg.starts_with("test.gltf: "), "{msg}");
    for c in causes {
        assert!(msg.contains(c), "{msg:?} does not mention {c:?}");
    }
    e
}

// ---------------------------------------------------------------------------------------
// Interpolation.

#[test]
fn linear_translation_hits_keys_exactly_and_averages_midpoints() {
    let keys = [[0.0, 0.0, 0.0], [2.0, 4.0, -6.0], [1.0, 1.0, 1.0]];
    let s = node0("translation", "LINEAR", &[0.0, 1.0, 3.0], Out::V3(&keys));
    assert_eq!(s.duration(), 3.0);
    for (t, k) in [(0.0, keys[0]), (1.0, keys[1]), (3.0, keys[2])] {
        assert_eq!(translation(at(&s, t)), Vec3::from(k), "key at {t}");
    }
    let mid = |a: [f32; 3], b: [f32; 3]| (Vec3::from(a) + Vec3::from(b)) * 0.5;
    assert!(close(translation(at(&s, 0.5)), mid(keys[0], keys[1]), 1e-6));
    assert!(close(translation(at(&s, 2.0)), mid(keys[1], keys[2]), 1e-6));
    // A quarter of the way along the second interval.
    let q = Vec3::from(keys[1]).lerp(Vec3::from(keys[2]), 0.25);
    assert!(close(translation(at(&s, 1.5)), q, 1e-6));
}

#[test]
fn channel_value_at_returns_keys_exactly() {
    let times = vec![0.25, 0.5, 1.75];
    let values = vec![
        Vec4::new(0.1, 0.2, 0.3, 0.0),
        Vec4::new(-7.7, 1e-3, 3.3, 0.0),
        Vec4::new(1e5, -1e-5, 0.7, 0.0),
    ];
    for interp in [Interpolation::Linear, Interpolation::Step] {
        let c = Channel::new(0, Property::Scale, interp, times.clone(), values.clone())
            .expect("valid channel");
        for (t, v) in times.iter().zip(&values) {
            assert_eq!(c.value_at(*t), *v, "{interp:?} at {t}");
        }
    }
    // CUBICSPLINE: the middle value of each triplet, whatever the tangents.
    let tangents = Vec4::new(5.0, -3.0, 2.0, 0.0);
    let cubic: Vec<Vec4> = values
        .iter()
        .flat_map(|&v| [tangents, v, -tangents])
        .collect();
    let c = Channel::new(
        0,
        Property::Translation,
        Interpolation::CubicSpline,
        times.clone(),
        cubic,
    )
    .expect("valid channel");
    for (t, v) in times.iter().zip(&values) {
        assert_eq!(c.value_at(*t), *v, "CUBICSPLINE at {t}");
    }
}

#[test]
fn clamps_before_the_first_and_after_the_last_key() {
    let keys = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]];
    let s = ok(one_channel(
        json!([{"mesh": 0, "translation": [9.0, 9.0, 9.0]}]),
        &[0],
        0,
        "translation",
        "LINEAR",
        &[1.0, 2.0],
        Out::V3(&keys),
    ));
    for t in [-5.0, 0.0, 0.5, 1.0, f32::NAN, f32::NEG_INFINITY] {
        assert_eq!(translation(at(&s, t)), Vec3::from(keys[0]), "at {t}");
    }
    for t in [2.0, 2.5, 1e9, f32::INFINITY] {
        assert_eq!(translation(at(&s, t)), Vec3::from(keys[1]), "at {t}");
    }
    // The loaded transform is the node's static one, not a key.
    assert_eq!(translation(s.instances[0].transform), Vec3::splat(9.0));
}

#[test]
fn slerp_midpoint_of_a_90_degree_turn_is_45_degrees() {
    let q0 = Quat::IDENTITY.to_array();
    let q1 = Quat::from_rotation_y(FRAC_PI_2).to_array();
    let run = |q1: [f32; 4]| node0("rotation", "LINEAR", &[0.0, 2.0], Out::V4(&[q0, q1]));
    let s = run(q1);
    // Where +X goes at time t: rotated about +Y by `angle`.
    let x_at = |s: &Scene, t: f32| at(s, t).transform_vector3(Vec3::X);
    let about_y = |angle: f32| Vec3::new(angle.cos(), 0.0, -angle.sin());
    assert!(
        close(x_at(&s, 1.0), about_y(FRAC_PI_4), 1e-6),
        "{}",
        x_at(&s, 1.0)
    );
    // Constant angular velocity: a quarter of the time is a quarter of the angle
    // (normalised linear interpolation would give 21.6 degrees, not 22.5).
    assert!(
        close(x_at(&s, 0.5), about_y(PI / 8.0), 1e-6),
        "{}",
        x_at(&s, 0.5)
    );
    assert!(close(x_at(&s, 1.5), about_y(3.0 * PI / 8.0), 1e-6));
    assert!(close(x_at(&s, 2.0), about_y(FRAC_PI_2), 1e-6));
    // The same turn written with the opposite sign of the second key takes the short way.
    let neg = run((-Quat::from_array(q1)).to_array());
    assert!(
        close(x_at(&neg, 1.0), about_y(FRAC_PI_4), 1e-6),
        "{}",
        x_at(&neg, 1.0)
    );
    // The instance stays rigid.
    let m = at(&s, 0.7);
    assert!((m.determinant() - 1.0).abs() < 1e-5);
}

#[test]
fn step_holds_the_previous_value() {
    let keys = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 5.0, 0.0]];
    let s = node0("translation", "STEP", &[0.0, 1.0, 2.0], Out::V3(&keys));
    for (t, k) in [
        (0.0, 0),
        (0.5, 0),
        (0.999, 0),
        (1.0, 1),
        (1.5, 1),
        (1.999, 1),
        (2.0, 2),
        (7.0, 2),
    ] {
        assert_eq!(translation(at(&s, t)), Vec3::from(keys[k]), "at {t}");
    }
}

#[test]
fn cubic_spline_with_zero_tangents_matches_hermite() {
    // Scale, keys at uneven intervals; tangents zero: a smooth step between keys.
    let times = [0.0f32, 0.5, 2.0];
    let v = [[1.0f32, 1.0, 1.0], [2.0, 3.0, 0.5], [1.0, 1.0, 1.0]];
    let z = [0.0f32; 3];
    let keys = v.map(|x| [z, x, z]);
    let s = cubic_v3("scale", &times, &keys);
    for t in [0.1f32, 0.25, 0.4, 0.5, 0.6, 1.0, 1.25, 1.9] {
        let want = cubic_v3_at(&times, &keys, t);
        let m = at(&s, t);
        let scale = Vec3::new(m.x_axis.x, m.y_axis.y, m.z_axis.z);
        assert!(close(scale, want, 1e-5), "at {t}: {scale} != {want}");
    }
}

#[test]
fn cubic_spline_with_tangents_matches_hermite() {
    // Translation, keys at uneven intervals (the tangents are scaled by the interval).
    let times = [0.0f32, 0.5, 2.0];
    let keys: [[[f32; 3]; 3]; 3] = [
        // in-tangent, value, out-tangent
        [[9.0, 9.0, 9.0], [0.0, 0.0, 0.0], [1.0, -2.0, 3.0]],
        [[4.0, 0.5, -1.0], [1.0, 2.0, 3.0], [-2.0, 1.0, 0.25]],
        [[3.0, 3.0, -3.0], [0.0, 1.0, 0.0], [7.0, 7.0, 7.0]],
    ];
    let s = cubic_v3("translation", &times, &keys);
    for t in [0.05f32, 0.25, 0.45, 0.75, 1.0, 1.5, 1.99] {
        let want = cubic_v3_at(&times, &keys, t);
        let got = translation(at(&s, t));
        assert!(close(got, want, 1e-5), "at {t}: {got} != {want}");
    }
    // Keys are exact, clamping holds the values (not the tangents).
    assert_eq!(translation(at(&s, 0.5)), Vec3::new(1.0, 2.0, 3.0));
    assert_eq!(translation(at(&s, -1.0)), Vec3::ZERO);
    assert_eq!(translation(at(&s, 3.0)), Vec3::new(0.0, 1.0, 0.0));
}

#[test]
fn cubic_spline_rotations_are_normalised() {
    let z = [0.0f32; 4];
    let q0 = Quat::IDENTITY.to_array();
    let q1 = Quat::from_rotation_z(FRAC_PI_2).to_array();
    let s = node0(
        "rotation",
        "CUBICSPLINE",
        &[0.0, 1.0],
        Out::V4(&[z, q0, z, z, q1, z]),
    );
    for t in [0.1, 0.3, 0.5, 0.8] {
        let m = at(&s, t);
        // Unnormalised, the midpoint quaternion has length cos(22.5°) and the matrix
        // would not be a rotation.
        assert!(
            (m.determinant() - 1.0).abs() < 1e-5,
            "at {t}: {}",
            m.determinant()
        );
        assert!((m.x_axis.truncate().length() - 1.0).abs() < 1e-6);
    }
    // The channel's own value is a unit quaternion too (the composition would hide it).
    let c = &s.animation.as_ref().expect("animated").channels()[0];
    for t in [0.25, 0.5, 0.75] {
        let q = c.value_at(t);
        assert!((q.length() - 1.0).abs() < 1e-6, "at {t}: {q}");
    }
    // With zero tangents the midpoint lies halfway: 45 degrees about +Z.
    let x = at(&s, 0.5).transform_vector3(Vec3::X);
    assert!(
        close(x, Vec3::new(FRAC_PI_4.cos(), FRAC_PI_4.sin(), 0.0), 1e-6),
        "{x}"
    );
}

// ---------------------------------------------------------------------------------------
// Hierarchy, several channels, global transforms.

#[test]
fn children_inherit_animated_parents() {
    let mut g = base();
    let times = scalars(&mut g, &[0.0, 1.0]);
    let moves = g.vec3(&[[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]);
    let turns = vec4s(
        &mut g,
        &[
            Quat::IDENTITY.to_array(),
            Quat::from_rotation_z(FRAC_PI_2).to_array(),
        ],
    );
    let grows = g.vec3(&[[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]]);
    // 0: parent (no mesh) translated and rotated; 1: child with the mesh at a static
    // offset; 2: grandchild with its own scale channel.
    let text = document(
        &g,
        json!([
            {"children": [1]},
            {"mesh": 0, "translation": [0.0, 2.0, 0.0], "children": [2]},
            {"mesh": 0, "translation": [1.0, 0.0, 0.0]},
        ]),
        &[0],
        json!({"animations": [{
            "samplers": [
                {"input": times, "output": moves},
                {"input": times, "output": turns},
                {"input": times, "output": grows, "interpolation": "STEP"},
            ],
            "channels": [
                {"sampler": 0, "target": {"node": 0, "path": "translation"}},
                {"sampler": 1, "target": {"node": 0, "path": "rotation"}},
                {"sampler": 2, "target": {"node": 2, "path": "scale"}},
            ],
        }]}),
    );
    let s = ok(parse(&text));
    assert_eq!(s.instances.len(), 2);
    let child_local = Mat4::from_translation(Vec3::new(0.0, 2.0, 0.0));
    let grand_local = |scale: f32| {
        Mat4::from_scale_rotation_translation(
            Vec3::splat(scale),
            Quat::IDENTITY,
            Vec3::new(1.0, 0.0, 0.0),
        )
    };
    for t in [0.0f32, 0.25, 0.5, 1.0] {
        let parent = Mat4::from_rotation_translation(
            Quat::from_rotation_z(FRAC_PI_2 * t),
            Vec3::new(10.0 * t, 0.0, 0.0),
        );
        let scale = if t < 1.0 { 1.0 } else { 3.0 };
        let got = s.instance_transforms_at(t);
        let want = [
            parent * child_local,
            parent * child_local * grand_local(scale),
        ];
        for (g, w) in got.iter().zip(want) {
            assert!(g.abs_diff_eq(w, 1e-5), "at {t}:\n{g}\n!=\n{w}");
        }
    }
    // At t = 1 the child sits at (10, 0, 0) + rot90(0, 2, 0) = (8, 0, 0).
    let at1 = s.instance_transforms_at(1.0);
    assert!(close(translation(at1[0]), Vec3::new(8.0, 0.0, 0.0), 1e-5));
    assert!(close(translation(at1[1]), Vec3::new(8.0, 1.0, 0.0), 1e-5));
}

#[test]
fn later_channels_win_and_unanimated_properties_keep_their_static_values() {
    let mut g = base();
    let times = scalars(&mut g, &[0.0, 1.0]);
    let a = g.vec3(&[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]);
    let b = g.vec3(&[[0.0, 5.0, 0.0], [0.0, 5.0, 0.0]]);
    let text = document(
        &g,
        json!([{"mesh": 0, "scale": [2.0, 2.0, 2.0], "translation": [0.0, 0.0, 7.0]}]),
        &[0],
        json!({"animations": [
            {"samplers": [{"input": times, "output": a}],
             "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}]},
            {"samplers": [{"input": times, "output": b}],
             "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}]},
        ]}),
    );
    let s = ok(parse(&text));
    let m = at(&s, 0.5);
    assert_eq!(translation(m), Vec3::new(0.0, 5.0, 0.0));
    assert_eq!(m.x_axis.x, 2.0, "the static scale is kept");
}

#[test]
fn global_transforms_are_applied_to_the_animated_pose() {
    let Some(path) = animated_gltf("global_transforms_are_applied_to_the_animated_pose") else {
        return;
    };
    let plain = load_gltf_file(&path).unwrap_or_else(|e| panic!("{e}"));
    let spec = format!("{}#scale=2#offset=1,2,3", path.display());
    let mut moved = load(&spec).unwrap_or_else(|e| panic!("{e}"));
    let m = Mat4::from_translation(Vec3::new(1.0, 2.0, 3.0)) * Mat4::from_scale(Vec3::splat(2.0));
    let global = moved
        .animation
        .as_ref()
        .expect("animated")
        .global_transform();
    assert!(global.abs_diff_eq(m, 1e-6), "{global}");
    for t in [0.0, 0.3, 0.9, 1.7] {
        let a = plain.instance_transforms_at(t);
        let b = moved.instance_transforms_at(t);
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(&b) {
            assert!((m * *x).abs_diff_eq(*y, 1e-5), "at {t}");
        }
    }
    // Back to time 0, the loaded (already transformed) instances come back exactly.
    let loaded = moved.instances.clone();
    moved.set_time(1.1);
    assert_ne!(moved.instances, loaded);
    moved.set_time(0.0);
    assert_eq!(moved.instances, loaded);
}

// ---------------------------------------------------------------------------------------
// What is ignored, and scenes without animation.

#[test]
fn scenes_without_animation_are_static() {
    let mut s = load("builtin:cornell").expect("cornell");
    assert!(s.animation.is_none());
    assert_eq!(s.duration(), 0.0);
    let loaded: Vec<Mat4> = s.instances.iter().map(|i| i.transform).collect();
    assert_eq!(s.instance_transforms_at(3.0), loaded);
    s.set_time(3.0);
    assert_eq!(
        s.instances.iter().map(|i| i.transform).collect::<Vec<_>>(),
        loaded
    );

    let g = base();
    let text = document(
        &g,
        json!([{"mesh": 0, "translation": [1.0, 2.0, 3.0]}]),
        &[0],
        json!({}),
    );
    let s = ok(parse(&text));
    assert!(s.animation.is_none());
    assert_eq!(s.duration(), 0.0);
    assert_eq!(
        s.instance_transforms_at(1.0),
        vec![s.instances[0].transform]
    );
}

#[test]
fn weights_channels_of_nodes_without_morph_targets_are_ignored_with_a_warning() {
    let mut g = base();
    let times = scalars(&mut g, &[0.0, 1.0]);
    let w = scalars(&mut g, &[0.0, 1.0]);
    let tr = g.vec3(&[[0.0, 0.0, 0.0], [0.0, 3.0, 0.0]]);
    let anim = |channels: Value| {
        json!({"animations": [{
            "samplers": [{"input": times, "output": w}, {"input": times, "output": tr}],
            "channels": channels,
        }]})
    };
    let weights = json!({"sampler": 0, "target": {"node": 0, "path": "weights"}});
    let moves = json!({"sampler": 1, "target": {"node": 0, "path": "translation"}});
    let only = ok(parse(&document(
        &g,
        json!([{"mesh": 0}]),
        &[0],
        anim(json!([weights])),
    )));
    assert!(only.animation.is_none());
    assert!(
        only.warnings
            .iter()
            .any(|w| w.contains("without morph targets")),
        "{:?}",
        only.warnings
    );
    let both = ok(parse(&document(
        &g,
        json!([{"mesh": 0}]),
        &[0],
        anim(json!([weights, moves])),
    )));
    assert_eq!(
        both.animation.as_ref().expect("animated").channels().len(),
        1
    );
    assert_eq!(translation(at(&both, 1.0)), Vec3::new(0.0, 3.0, 0.0));
    assert!(
        both.warnings
            .iter()
            .any(|w| w.contains("without morph targets"))
    );
}

#[test]
fn channels_on_nodes_outside_the_scene_or_with_a_matrix_are_ignored() {
    let mut g = base();
    let times = scalars(&mut g, &[0.0, 1.0]);
    let tr = g.vec3(&[[0.0, 0.0, 0.0], [0.0, 3.0, 0.0]]);
    // Node 1 is not in scene 0; node 2 has a matrix.
    let text = document(
        &g,
        json!([
            {"mesh": 0},
            {"mesh": 0},
            {"mesh": 0, "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 5, 0, 0, 1]},
        ]),
        &[0, 2],
        json!({"animations": [{
            "samplers": [{"input": times, "output": tr}],
            "channels": [
                {"sampler": 0, "target": {"node": 1, "path": "translation"}},
                {"sampler": 0, "target": {"node": 2, "path": "translation"}},
            ],
        }]}),
    );
    let s = ok(parse(&text));
    assert!(s.animation.is_none());
    assert!(
        s.warnings.iter().any(|w| w.contains("matrix")),
        "{:?}",
        s.warnings
    );
    assert_eq!(
        s.instance_transforms_at(1.0),
        s.instances.iter().map(|i| i.transform).collect::<Vec<_>>()
    );
}

#[test]
fn dropped_empty_instances_keep_the_others_animated() {
    // Node 0's mesh has no triangles (points): its instance is dropped after loading,
    // and node 1's instance must still follow node 1's channel.
    let mut g = base();
    let times = scalars(&mut g, &[0.0, 1.0]);
    let tr = g.vec3(&[[0.0, 0.0, 0.0], [0.0, 3.0, 0.0]]);
    let doc = json!({
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": 0}, "mode": 0}]},
            {"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]},
        ],
        "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [4.0, 0.0, 0.0]}],
        "scenes": [{"nodes": [0, 1]}],
        "animations": [{
            "samplers": [{"input": times, "output": tr}],
            "channels": [{"sampler": 0, "target": {"node": 1, "path": "scale"}}],
        }],
    });
    let mut s = ok(parse(&g.to_gltf(doc)));
    assert_eq!(s.instances.len(), 1);
    let a = s.animation.as_ref().expect("animated");
    assert_eq!(a.instance_nodes().len(), 1);
    assert_eq!(a.nodes()[a.instance_nodes()[0]].gltf_node(), 1);
    // Scale (0, 3, 0) at t = 1 flattens x and z; the translation stays.
    s.set_time(1.0);
    let m = s.instances[0].transform;
    assert_eq!(translation(m), Vec3::new(4.0, 0.0, 0.0));
    assert_eq!((m.x_axis.x, m.y_axis.y), (0.0, 3.0));
}

// ---------------------------------------------------------------------------------------
// The committed asset.

/// `scenes/animated.gltf`: a box translating (LINEAR), a box turning about +Y (LINEAR,
/// slerp through 90 to 180 degrees), a tetrahedron pulsing in scale (CUBICSPLINE), a
/// box stepping up and down (STEP) carrying a tetrahedron (a child node), and a camera;
/// 2 seconds. Every animated node's static transform is its pose at time 0.
fn animated_asset() -> String {
    let boxv: [[f32; 3]; 8] = std::array::from_fn(|i| {
        let c = |b: usize| if i & b != 0 { 0.5 } else { -0.5 };
        [c(1), c(2), c(4)]
    });
    // Outward-facing (counter-clockwise) quads of the box, as triangles.
    let box_tris: [u8; 36] = [
        0, 2, 3, 0, 3, 1, // -z
        4, 5, 7, 4, 7, 6, // +z
        0, 1, 5, 0, 5, 4, // -y
        2, 6, 7, 2, 7, 3, // +y
        0, 4, 6, 0, 6, 2, // -x
        1, 3, 7, 1, 7, 5, // +x
    ];
    let tetv: [[f32; 3]; 4] = [
        [0.5, 0.5, 0.5],
        [-0.5, -0.5, 0.5],
        [-0.5, 0.5, -0.5],
        [0.5, -0.5, -0.5],
    ];
    let tet_tris: [u8; 12] = [0, 1, 3, 0, 2, 1, 0, 3, 2, 1, 2, 3];
    let mut g = Gltf::default();
    let box_pos = g.positions(&boxv);
    let box_idx = g.indices_u8(&box_tris);
    let tet_pos = g.positions(&tetv);
    let tet_idx = g.indices_u8(&tet_tris);
    let minmax = |v: &[f32]| json!({"min": [v[0]], "max": [v[v.len() - 1]]});
    let times =
        |g: &mut Gltf, v: &[f32]| g.raw(bytemuck::cast_slice(v), v.len(), "SCALAR", F32, minmax(v));
    let t3 = times(&mut g, &[0.0, 1.0, 2.0]);
    let t4 = times(&mut g, &[0.0, 0.5, 1.0, 1.5]);
    let slide = g.vec3(&[[-3.0, 0.0, 0.0], [-3.0, 1.5, 0.0], [-3.0, 0.0, 0.0]]);
    let turn = vec4s(
        &mut g,
        &[
            Quat::IDENTITY.to_array(),
            [
                0.0,
                std::f32::consts::FRAC_1_SQRT_2,
                0.0,
                std::f32::consts::FRAC_1_SQRT_2,
            ],
            [0.0, 1.0, 0.0, 0.0],
        ],
    );
    let s = |x: f32| [x, x, x];
    let pulse = g.vec3(&[
        s(0.0),
        s(1.0),
        s(1.2), // key 0: in, value, out
        s(0.0),
        s(1.6),
        s(0.0), // key 1
        s(-1.2),
        s(1.0),
        s(0.0), // key 2
    ]);
    let step = g.vec3(&[
        [3.0, 0.0, 0.0],
        [3.0, 0.5, 0.0],
        [3.0, 1.0, 0.0],
        [3.0, 0.5, 0.0],
    ]);
    let prim = |pos: usize, idx: usize, mat: usize| json!([{"attributes": {"POSITION": pos}, "indices": idx, "material": mat}]);
    let rest = json!({
        "asset": {"version": "2.0", "generator": "bvhtrace-scene tests/animation.rs"},
        "scene": 0,
        "scenes": [{"name": "animated", "nodes": [0, 1, 2, 3, 5]}],
        "materials": [
            {"name": "orange", "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.45, 0.1, 1.0]}},
            {"name": "blue", "pbrMetallicRoughness": {"baseColorFactor": [0.15, 0.35, 0.9, 1.0]}},
        ],
        "meshes": [
            {"name": "box", "primitives": prim(box_pos, box_idx, 0)},
            {"name": "tetrahedron", "primitives": prim(tet_pos, tet_idx, 1)},
        ],
        "nodes": [
            {"name": "slider", "mesh": 0, "translation": [-3.0, 0.0, 0.0]},
            {"name": "spinner", "mesh": 0, "translation": [-1.0, 0.0, 0.0]},
            {"name": "pulser", "mesh": 1, "translation": [1.0, 0.0, 0.0]},
            {"name": "stepper", "mesh": 0, "translation": [3.0, 0.0, 0.0], "scale": [0.5, 0.5, 0.5], "children": [4]},
            {"name": "rider", "mesh": 1, "translation": [0.0, 1.6, 0.0]},
            {"name": "camera", "camera": 0, "translation": [0.0, 1.0, 9.0]},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.01}}],
        "animations": [{
            "name": "demo",
            "samplers": [
                {"input": t3, "output": slide, "interpolation": "LINEAR"},
                {"input": t3, "output": turn, "interpolation": "LINEAR"},
                {"input": t3, "output": pulse, "interpolation": "CUBICSPLINE"},
                {"input": t4, "output": step, "interpolation": "STEP"},
            ],
            "channels": [
                {"sampler": 0, "target": {"node": 0, "path": "translation"}},
                {"sampler": 1, "target": {"node": 1, "path": "rotation"}},
                {"sampler": 2, "target": {"node": 2, "path": "scale"}},
                {"sampler": 3, "target": {"node": 3, "path": "translation"}},
            ],
        }],
    });
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::Engine::encode(&base64::engine::general_purpose::STANDARD, &g.bin)
    );
    let doc = g.document(rest, json!([{"byteLength": g.bin.len(), "uri": uri}]));
    let mut text = serde_json::to_string_pretty(&doc).expect("JSON");
    text.push('\n');
    text
}

#[test]
fn committed_asset_matches_its_generator() {
    let Some(path) = animated_gltf("committed_asset_matches_its_generator") else {
        return;
    };
    let generated = animated_asset();
    if std::env::var_os("BVHTRACE_WRITE_ANIMATED").is_some_and(|v| v == "1") {
        std::fs::write(&path, &generated).expect("write scenes/animated.gltf");
    }
    let committed = std::fs::read(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (write it with BVHTRACE_WRITE_ANIMATED=1 cargo test -p bvhtrace-scene --test animation)",
            path.display()
        )
    });
    let a = load_gltf_slice(&committed, "animated.gltf", None).unwrap_or_else(|e| panic!("{e}"));
    let b = load_gltf_slice(generated.as_bytes(), "animated.gltf", None)
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        a == b,
        "scenes/animated.gltf differs from animated_asset(): regenerate it with BVHTRACE_WRITE_ANIMATED=1"
    );
}

#[test]
fn the_asset_moves_and_set_time_zero_restores_the_loaded_pose() {
    let Some(path) = animated_gltf("the_asset_moves...") else {
        return;
    };
    let mut s = load_gltf_file(&path).unwrap_or_else(|e| panic!("{e}"));
    s.check_invariants().expect("invariants");
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    assert!(s.camera.is_some());
    assert_eq!(s.instances.len(), 5);
    assert_eq!(s.duration(), 2.0);
    let a = s.animation.as_ref().expect("animated");
    let kinds: Vec<Interpolation> = a.channels().iter().map(|c| c.interpolation()).collect();
    assert_eq!(
        kinds,
        [
            Interpolation::Linear,
            Interpolation::Linear,
            Interpolation::CubicSpline,
            Interpolation::Step
        ]
    );
    let loaded = s.instances.clone();
    let loaded_m: Vec<Mat4> = loaded.iter().map(|i| i.transform).collect();
    assert_eq!(
        s.instance_transforms_at(0.0),
        loaded_m,
        "time 0 is the static pose"
    );
    let t1 = s.instance_transforms_at(0.6);
    let t2 = s.instance_transforms_at(1.3);
    for (i, (a, b)) in t1.iter().zip(&t2).enumerate() {
        assert_ne!(a, b, "instance {i} does not move between 0.6 s and 1.3 s");
    }
    // The rider (instance 4, a child of the stepper) moves with the stepper.
    assert!(close(
        translation(t2[4]) - translation(t1[4]),
        translation(t2[3]) - translation(t1[3]),
        1e-6
    ));
    let flat0 = s.flatten();
    s.set_time(0.6);
    assert_eq!(
        s.instances.iter().map(|i| i.transform).collect::<Vec<_>>(),
        t1
    );
    assert_ne!(s.flatten().positions, flat0.positions);
    s.check_invariants().expect("invariants at 0.6 s");
    s.set_time(0.0);
    assert_eq!(s.instances, loaded);
    assert_eq!(s.flatten(), flat0);
    // Past the end, the last keys hold: 180 degrees for the spinner, back to rest for
    // the others.
    let end = s.instance_transforms_at(5.0);
    assert_eq!(end, s.instance_transforms_at(2.0));
    let x = end[1].transform_vector3(Vec3::X);
    assert!(close(x, -Vec3::X, 1e-6), "{x}");
    assert_eq!(end[0], loaded_m[0]);
}

#[test]
fn shared_drone_animation_plays() {
    let Some(dir) = common::shared("shared_drone_animation_plays") else {
        return;
    };
    let p = dir.join("gltf/drone/scene.gltf");
    if !p.is_file() {
        println!("shared_drone_animation_plays: skipped, no {}", p.display());
        return;
    }
    let mut s = load_gltf_file(&p).unwrap_or_else(|e| panic!("{e}"));
    let d = s.duration();
    assert!(d > 0.0, "the drone has an animation");
    let loaded = s.instances.clone();
    let mut moved = false;
    for k in 0..=8 {
        s.set_time(d * k as f32 / 8.0);
        s.check_invariants()
            .unwrap_or_else(|e| panic!("at {}: {e}", d * k as f32 / 8.0));
        moved |= s.instances != loaded;
    }
    assert!(moved, "the drone's instances never moved");
}

// ---------------------------------------------------------------------------------------
// Bad input: errors that name the animation, the channel and the cause; no panics.

/// A valid single-channel document whose pieces the bad-input tests replace.
fn bad_doc(times: &[f32], values: &[[f32; 3]], interp: &str, sampler: Value) -> String {
    let mut g = base();
    let i = scalars(&mut g, times);
    let o = g.vec3(values);
    let mut smp = json!({"input": i, "output": o, "interpolation": interp});
    if let Value::Object(m) = sampler {
        for (k, v) in m {
            smp[k] = v;
        }
    }
    document(
        &g,
        json!([{"mesh": 0}]),
        &[0],
        json!({"animations": [{
            "name": "walk",
            "samplers": [smp],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
        }]}),
    )
}

const V2: [[f32; 3]; 2] = [[0.0; 3], [1.0; 3]];
const V3: [[f32; 3]; 3] = [[0.0; 3], [1.0; 3], [2.0; 3]];

#[test]
fn non_increasing_times_are_errors() {
    let e = expect_error(
        &bad_doc(&[0.0, 1.0, 0.5], &V3, "LINEAR", json!({})),
        &[
            "animation 0 (\"walk\") channel 0",
            "sampler 0",
            "key time 2 (0.5) is not greater than key time 1 (1)",
        ],
    );
    assert!(matches!(e.kind, ErrorKind::Invalid(_)), "{e}");
    expect_error(
        &bad_doc(&[0.0, 1.0, 1.0], &V3, "STEP", json!({})),
        &["channel 0", "strictly increasing"],
    );
    expect_error(
        &bad_doc(&[0.0, f32::INFINITY], &V2, "LINEAR", json!({})),
        &["channel 0", "key time 1 is not finite"],
    );
    expect_error(
        &bad_doc(&[f32::NAN, 1.0], &V2, "LINEAR", json!({})),
        &["key time 0 is not finite"],
    );
    expect_error(
        &bad_doc(&[], &[], "LINEAR", json!({})),
        &["channel 0", "no keys"],
    );
}

#[test]
fn count_mismatches_are_errors() {
    expect_error(
        &bad_doc(&[0.0, 1.0, 2.0], &V2, "LINEAR", json!({})),
        &[
            "animation 0 (\"walk\") channel 0",
            "2 values",
            "3 keys",
            "LINEAR",
        ],
    );
    // CUBICSPLINE needs three values per key.
    expect_error(
        &bad_doc(&[0.0, 1.0, 2.0], &V3, "CUBICSPLINE", json!({})),
        &["channel 0", "3 values", "3 keys", "CUBICSPLINE", "so 9"],
    );
    let six = [[0.0f32; 3]; 6];
    let s = ok(parse(&bad_doc(&[0.0, 1.0], &six, "CUBICSPLINE", json!({}))));
    assert!(s.animation.is_some());
    expect_error(
        &bad_doc(&[0.0, 1.0], &six, "STEP", json!({})),
        &["6 values", "2 keys", "STEP"],
    );
}

#[test]
fn non_finite_outputs_are_errors() {
    let mut v = V3;
    v[1][2] = f32::NAN;
    expect_error(
        &bad_doc(&[0.0, 1.0, 2.0], &v, "LINEAR", json!({})),
        &[
            "animation 0 (\"walk\") channel 0",
            "output value 1 is not finite",
        ],
    );
    v[1][2] = f32::INFINITY;
    expect_error(
        &bad_doc(&[0.0, 1.0, 2.0], &v, "STEP", json!({})),
        &["output value 1 is not finite"],
    );
    // A NaN tangent is as bad as a NaN value.
    let mut c = [[0.0f32; 3]; 6];
    c[5][0] = f32::NAN;
    expect_error(
        &bad_doc(&[0.0, 1.0], &c, "CUBICSPLINE", json!({})),
        &["output value 5 is not finite"],
    );
}

#[test]
fn bad_indices_and_types_are_errors() {
    let good = |s: Value| bad_doc(&[0.0, 1.0], &V2, "LINEAR", s);
    expect_error(
        &good(json!({"input": 99})),
        &[
            "animation 0 (\"walk\") channel 0",
            "input",
            "accessor 99 does not exist",
        ],
    );
    expect_error(
        &good(json!({"output": 42})),
        &["channel 0", "output", "accessor 42 does not exist"],
    );
    // The input is the VEC3 output accessor, the output the SCALAR input one.
    expect_error(&good(json!({"input": 3})), &["input", "accessor 3", "Vec3"]);
    expect_error(
        &good(json!({"output": 2})),
        &["output", "accessor 2", "Scalar"],
    );
    expect_error(
        &good(json!({"interpolation": "QUADRATIC"})),
        &["channel 0", "unknown interpolation"],
    );

    // Sampler and node indices.
    let mut g = base();
    let i = scalars(&mut g, &[0.0, 1.0]);
    let o = g.vec3(&V2);
    let with = |channel: Value| {
        document(
            &g,
            json!([{"mesh": 0}]),
            &[0],
            json!({"animations": [{
                "samplers": [{"input": i, "output": o}],
                "channels": [channel],
            }]}),
        )
    };
    expect_error(
        &with(json!({"sampler": 3, "target": {"node": 0, "path": "translation"}})),
        &["animation 0 channel 0", "sampler 3 does not exist"],
    );
    expect_error(
        &with(json!({"sampler": 0, "target": {"node": 7, "path": "translation"}})),
        &["animation 0 channel 0", "node 7 does not exist"],
    );
    // A rotation needs VEC4 outputs.
    expect_error(
        &with(json!({"sampler": 0, "target": {"node": 0, "path": "rotation"}})),
        &["rotation", "output", "accessor 3", "4 components"],
    );
}

#[test]
fn truncated_and_degenerate_animation_data_are_errors() {
    // The output accessor claims more elements than its view holds.
    let mut g = base();
    let i = scalars(&mut g, &[0.0, 1.0]);
    let o = g.raw(bytemuck::cast_slice(&V2), 50, "VEC3", F32, json!({}));
    let text = document(
        &g,
        json!([{"mesh": 0}]),
        &[0],
        json!({"animations": [{
            "samplers": [{"input": i, "output": o}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "scale"}}],
        }]}),
    );
    expect_error(
        &text,
        &["animation 0 channel 0", "output", "reads past the end"],
    );
    // A zero rotation key cannot be normalised.
    let mut g = base();
    let i = scalars(&mut g, &[0.0, 1.0]);
    let o = vec4s(&mut g, &[[0.0; 4], [0.0, 0.0, 0.0, 1.0]]);
    let text = document(
        &g,
        json!([{"mesh": 0}]),
        &[0],
        json!({"animations": [{
            "samplers": [{"input": i, "output": o}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}],
        }]}),
    );
    expect_error(&text, &["rotation key 0", "not a unit quaternion"]);
}

#[test]
fn channel_new_checks_its_input() {
    let v = |n: usize| vec![Vec4::ZERO; n];
    let lin = Interpolation::Linear;
    let tr = Property::Translation;
    assert!(Channel::new(0, tr, lin, vec![0.0, 1.0], v(2)).is_ok());
    for (times, values, interp, cause) in [
        (vec![], v(0), lin, "no keys"),
        (vec![1.0, 0.0], v(2), lin, "strictly increasing"),
        (vec![0.0, f32::NAN], v(2), lin, "not finite"),
        (vec![0.0, 1.0], v(3), lin, "3 values"),
        (vec![0.0, 1.0], v(2), Interpolation::CubicSpline, "so 6"),
        (
            vec![0.0],
            vec![Vec4::new(f32::NAN, 0.0, 0.0, 0.0)],
            lin,
            "not finite",
        ),
    ] {
        let e = Channel::new(0, tr, interp, times.clone(), values).expect_err("bad channel");
        assert!(
            e.contains(cause),
            "{times:?}: {e:?} does not mention {cause:?}"
        );
    }
    // Rotation keys are normalised (unit ones kept bit for bit).
    let q = Quat::from_rotation_x(0.3);
    let c = Channel::new(
        0,
        Property::Rotation,
        Interpolation::Step,
        vec![0.0, 1.0],
        vec![Vec4::from(q), Vec4::new(0.0, 0.0, 0.0, 2.0)],
    )
    .expect("valid");
    assert_eq!(c.values()[0], Vec4::from(q));
    assert_eq!(c.values()[1], Vec4::W);
}

/// `scenes/skinned.gltf`: the skin's static pose is the file's positions, the top of the
/// tube follows its joint chain at `t = 1` as the glTF formula gives it, the skinned
/// instance is not moved by its node, and the unskinned ground stays put.
#[test]
fn skins_place_vertices_by_their_joints() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/skinned.gltf");
    let mut scene = bvhtrace_scene::load(path).expect("loads");
    assert!(scene.warnings.is_empty(), "{:?}", scene.warnings);
    let anim = scene.animation.clone().expect("animated");
    assert_eq!(anim.skins().len(), 1);
    let skin = &anim.skins()[0];
    assert_eq!(skin.joint_count(), 2);
    let tube = scene.instances[skin.instance()].mesh;
    // The top cap's centre, weighted fully to the second joint, last of the 210 vertices.
    let top = |s: &bvhtrace_scene::Scene| s.meshes[tube].positions[209];
    assert!(
        (top(&scene) - Vec3::new(0.0, 2.0, 0.0)).length() < 1e-6,
        "{}",
        top(&scene)
    );
    let ground_before = scene.meshes[1 - tube].positions.clone();
    scene.set_time(1.0);
    assert_eq!(scene.instances[skin.instance()].transform, Mat4::IDENTITY);
    // root: 90 degrees about +Y; mid joint at (0, 1, 0) under it, 70 degrees about +Z.
    let (s, c) = 70f32.to_radians().sin_cos();
    let bent = Quat::from_rotation_y(FRAC_PI_2) * Vec3::new(-s, 1.0 + c, 0.0);
    assert!(
        (top(&scene) - bent).length() < 1e-5,
        "{} vs {bent}",
        top(&scene)
    );
    assert_eq!(scene.meshes[1 - tube].positions, ground_before);
    // Back to the start: the bind pose again.
    scene.set_time(0.0);
    assert!((top(&scene) - Vec3::new(0.0, 2.0, 0.0)).length() < 1e-6);
}

/// The unit triangle with five morph targets (target `i` moves vertex `v` by
/// `(i + 1, v, -1) / 8`, so weights past the first four are read too), mesh weights
/// `[0.25, 0, 0, 0, 0]`, and a LINEAR weights channel on its node when `animated`.
fn morph_document(targets: usize, animated: bool, weights_out: &[f32]) -> String {
    let mut g = base();
    let deltas: Vec<usize> = (0..targets)
        .map(|i| {
            let d: Vec<[f32; 3]> = (0..3)
                .map(|v| [(i + 1) as f32 / 8.0, v as f32 / 8.0, -1.0 / 8.0])
                .collect();
            g.vec3(&d)
        })
        .collect();
    let times = scalars(&mut g, &[0.0, 1.0]);
    let out = scalars(&mut g, weights_out);
    let targets: Vec<Value> = deltas.iter().map(|&a| json!({"POSITION": a})).collect();
    let mut rest = json!({"meshes": [{
        "primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "targets": targets}],
        "weights": [0.25, 0.0, 0.0, 0.0, 0.0],
    }]});
    if animated {
        rest["animations"] = json!([{
            "samplers": [{"input": times, "output": out}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
        }]);
    }
    document(
        &g,
        json!([{"mesh": 0, "translation": [0.0, 0.0, 2.0]}]),
        &[0],
        rest,
    )
}

/// Morph targets: the static pose is the mesh's weights, a weights channel over five
/// targets drives them all (`Property::Weights(0)` and `(1)`), each vertex is
/// `base + Σ w_i d_i` in target order, and the node still places the instance.
#[test]
fn morph_targets_move_vertices_by_their_weights() {
    // Key 0: all 0; key 1: 1, 0.5, 0, 0, 2.
    let out = [0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.5, 0.0, 0.0, 2.0];
    let mut s = ok(parse(&morph_document(5, true, &out)));
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let anim = s.animation.clone().expect("animated");
    let props: Vec<Property> = anim.channels().iter().map(|c| c.property()).collect();
    assert_eq!(props, [Property::Weights(0), Property::Weights(1)]);
    let morph = &anim.morphs()[0];
    assert_eq!(morph.target_count(), 5);
    let expect = |w: [f32; 5]| -> Vec<Vec3> {
        (0..3)
            .map(|v| {
                let mut p = Vec3::from(TRI[v]);
                for (i, &w) in w.iter().enumerate() {
                    if w != 0.0 {
                        let d = Vec3::new((i + 1) as f32 / 8.0, v as f32 / 8.0, -1.0 / 8.0);
                        p = Vec3::new(p.x + d.x * w, p.y + d.y * w, p.z + d.z * w);
                    }
                }
                p
            })
            .collect()
    };
    // Loaded: the mesh's weights.
    assert_eq!(s.meshes[0].positions, expect([0.25, 0.0, 0.0, 0.0, 0.0]));
    assert_eq!(
        anim.morph_weights_at(morph, Some(0.5)),
        [0.5, 0.25, 0.0, 0.0, 1.0]
    );
    s.set_time(0.5);
    assert_eq!(s.meshes[0].positions, expect([0.5, 0.25, 0.0, 0.0, 1.0]));
    assert_eq!(
        translation(s.instances[0].transform),
        Vec3::new(0.0, 0.0, 2.0)
    );
    s.set_time(0.0);
    assert_eq!(s.meshes[0].positions, expect([0.0; 5]));
    assert_eq!(s.meshes[0].positions, TRI.map(Vec3::from));
}

/// Bad morph data is an error naming it: a target with the wrong count of deltas, a
/// weights output that is not a whole number of entries.
#[test]
fn bad_morph_targets_are_errors_naming_them() {
    let mut g = base();
    let short = g.vec3(&[[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]);
    let text = document(
        &g,
        json!([{"mesh": 0}]),
        &[0],
        json!({"meshes": [{"primitives": [{
            "attributes": {"POSITION": 0}, "indices": 1, "targets": [{"POSITION": short}],
        }]}]}),
    );
    let e = parse(&text).expect_err("2 deltas for 3 vertices");
    assert!(e.to_string().contains("morph target 0 POSITION"), "{e}");
    // Two targets, three weights per... key: not a whole number of entries.
    let e = parse(&morph_document(2, true, &[0.0, 0.0, 1.0])).expect_err("3 weights");
    let msg = e.to_string();
    assert!(msg.contains("weights") && msg.contains("2"), "{msg}");
}

/// `scenes/morph.gltf`: the sphere morphs alone (two LINEAR targets, placed by its node),
/// the tube swells (one STEP target) before it is skinned; `deformed_at` is what
/// `set_time` writes, and the two deformed meshes change over time.
#[test]
fn morph_scene_deforms_before_skinning() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/morph.gltf");
    let mut scene = load(path).expect("loads");
    assert!(scene.warnings.is_empty(), "{:?}", scene.warnings);
    let anim = scene.animation.clone().expect("animated");
    assert_eq!((anim.morphs().len(), anim.skins().len()), (2, 1));
    let tube = anim.skins()[0].instance();
    let sphere = anim
        .morphs()
        .iter()
        .find(|m| m.instance() != tube)
        .expect("sphere");
    let tube_morph = anim
        .morphs()
        .iter()
        .find(|m| m.instance() == tube)
        .expect("tube");
    // Static pose: the node's weights (0, 0) for the sphere, the mesh's (0.5) for the tube.
    assert_eq!(sphere.static_weights(), [0.0, 0.0]);
    assert_eq!(tube_morph.static_weights(), [0.5]);
    assert_eq!(anim.morph_weights_at(sphere, Some(0.25)), [0.5, 0.0]);
    assert_eq!(anim.morph_weights_at(sphere, Some(1.0)), [0.5, 1.0]);
    assert_eq!(anim.morph_weights_at(tube_morph, Some(0.4)), [0.0]);
    assert_eq!(anim.morph_weights_at(tube_morph, Some(0.6)), [1.0]);
    let mesh_of = |s: &Scene, i: usize| s.meshes[s.instances[i].mesh].positions.clone();
    let loaded = mesh_of(&scene, sphere.instance());
    assert_eq!(loaded, sphere.base_positions());
    for t in [0.6f32, 1.0] {
        scene.set_time(t);
        for d in anim.deformed_at(Some(t)) {
            assert_eq!(mesh_of(&scene, d.instance), d.positions, "t = {t}");
        }
    }
    // The sphere at t = 1: base + 0.5 stretch + 1.0 bulge, by the targets' deltas.
    let n = sphere.base_positions().len();
    let (stretch, bulge) = sphere.position_deltas().split_at(n);
    let want: Vec<Vec3> = (sphere.base_positions().iter().zip(stretch).zip(bulge))
        .map(|((&b, &s), &u)| bvhtrace_scene::morph_vertex(b, [(0.5, s), (1.0, u)]))
        .collect();
    assert_eq!(mesh_of(&scene, sphere.instance()), want);
    assert_ne!(want, loaded, "the sphere did not morph");
    assert_eq!(
        translation(scene.instances[sphere.instance()].transform),
        Vec3::new(-0.9, 0.6, 0.3)
    );
    // The tube swells, then bends: its middle ring is wider than the unmorphed skin's.
    let unmorphed = anim.skins()[0].skinned(
        &anim.skins()[0].joint_matrices(&anim.node_transforms_at(1.0), anim.global_transform()),
    );
    assert_ne!(mesh_of(&scene, tube), unmorphed.0, "the tube did not swell");
}
