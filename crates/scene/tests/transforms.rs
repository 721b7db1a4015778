//! Node hierarchies, transforms, instancing, strips and fans, index types, attributes,
//! cameras and the `#scale` / `#offset` suffixes, on hand-made glTF files.

mod common;

use bvhtrace_scene::{Scene, load, load_gltf_slice};
use common::{Gltf, TRI, normals};
use glam::{Mat4, Quat, Vec3};
use serde_json::json;

fn from_text(text: &str) -> Scene {
    load_gltf_slice(text.as_bytes(), "test.gltf", None).unwrap_or_else(|e| panic!("{e}"))
}

/// One mesh (the unit triangle, facing +z) placed by each of `nodes`.
fn tri_scene(nodes: serde_json::Value) -> Scene {
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    let n = nodes.as_array().expect("array").len();
    from_text(&g.to_gltf(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": nodes,
        "scenes": [{"nodes": (0..n).collect::<Vec<_>>()}],
    })))
}

#[test]
fn negative_determinant_flips_winding() {
    let s = tri_scene(json!([
        {"mesh": 0},
        {"mesh": 0, "scale": [-1, 1, 1]},
        {"mesh": 0, "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]},
        {"mesh": 0, "scale": [-1, -1, 1]},
    ]));
    assert_eq!(s.meshes.len(), 1);
    assert_eq!(s.instance_count(), 4);
    assert_eq!(
        s.instances
            .iter()
            .map(|i| i.flips_winding())
            .collect::<Vec<_>>(),
        [false, true, true, false]
    );
    let flat = s.flatten();
    let n = normals(&flat);
    // Mirrored in x: the triangle still faces +z, so its normal must stay +z.
    assert!(n[0].z > 0.0 && n[1].z > 0.0, "{n:?}");
    // Mirrored in z: the triangle is flat in z, so the front face now looks down -z.
    assert!(n[2].z < 0.0, "{n:?}");
    // A rotation by 180 degrees (two mirrors) keeps the winding.
    assert!(n[3].z > 0.0, "{n:?}");
    // The mirrored copy is where the mirror puts it.
    let t = flat.triangles().expect("valid");
    assert_eq!(t[1][0], Vec3::ZERO);
    assert!(t[1].contains(&Vec3::new(-1.0, 0.0, 0.0)));
}

#[test]
fn matrix_and_trs_agree_and_compose_parent_first() {
    let t = Vec3::new(1.0, 2.0, 3.0);
    let r = Quat::from_rotation_y(0.7) * Quat::from_rotation_x(0.3);
    let sc = Vec3::new(2.0, 0.5, 1.5);
    let m = Mat4::from_scale_rotation_translation(sc, r, t);
    let s = tri_scene(json!([
        {"mesh": 0, "translation": t.to_array(), "rotation": r.to_array(), "scale": sc.to_array()},
        {"mesh": 0, "matrix": m.to_cols_array()},
        {"translation": [10, 0, 0], "rotation": Quat::from_rotation_z(1.0).to_array(), "children": [3]},
        {"mesh": 0, "scale": [3, 3, 3]},
    ]));
    let tris = s.flatten().triangles().expect("valid");
    for c in 0..3 {
        assert!(
            tris[0][c].abs_diff_eq(tris[1][c], 1e-6),
            "{:?} vs {:?}",
            tris[0],
            tris[1]
        );
        let want = (Mat4::from_translation(Vec3::new(10.0, 0.0, 0.0))
            * Mat4::from_quat(Quat::from_rotation_z(1.0))
            * Mat4::from_scale(Vec3::splat(3.0)))
        .transform_point3(Vec3::from(TRI[c]));
        assert!(
            tris[2][c].abs_diff_eq(want, 1e-5),
            "child: {:?} vs {want}",
            tris[2][c]
        );
    }
    // A non-unit quaternion is normalised.
    let s2 = tri_scene(json!([{"mesh": 0, "rotation": (r.to_array().map(|x| x * 3.0))}]));
    let t2 = s2.flatten().triangles().expect("valid");
    let want = Mat4::from_quat(r).transform_point3(Vec3::X);
    assert!(t2[0][1].abs_diff_eq(want, 1e-6));
}

#[test]
fn a_mesh_used_by_many_nodes_is_loaded_once() {
    let nodes: Vec<_> = (0..7)
        .map(|i| json!({"mesh": 0, "translation": [i, 0, 0]}))
        .collect();
    let s = tri_scene(json!(nodes));
    assert_eq!(s.meshes.len(), 1);
    assert_eq!(s.instance_count(), 7);
    assert_eq!(s.triangle_count(), 7);
    let flat = s.flatten();
    assert_eq!(flat.positions.len(), 21);
    assert_eq!(s.bounds(), (Vec3::ZERO, Vec3::new(7.0, 1.0, 0.0)));
}

#[test]
fn strips_fans_and_index_types() {
    // A planar zig-zag of 5 vertices facing +z.
    let strip = [
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [2.0, 0.0, 0.0],
    ];
    // swap 0/1 so the first triangle is CCW from +z: (0,0) (1,0) (0,1)...
    let strip = [strip[0], strip[2], strip[1], strip[4], strip[3]];
    let fan: Vec<[f32; 3]> = std::iter::once([0.0, 0.0, 0.0])
        .chain((0..5).map(|i| {
            let a = i as f32 * 0.5;
            [a.cos(), a.sin(), 0.0]
        }))
        .collect();
    let mut g = Gltf::default();
    let ps = g.positions(&strip);
    let pf = g.positions(&fan);
    let i8 = g.indices_u8(&[0, 1, 2, 3, 4]);
    let i16 = g.indices_u16(&[0, 1, 2, 3, 4]);
    let i32 = g.indices_u32(&[0, 1, 2, 3, 4]);
    let pl = g.positions(&[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]);
    let text = g.to_gltf(json!({
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": ps}, "mode": 5, "indices": i8},
            {"attributes": {"POSITION": ps}, "mode": 5, "indices": i16},
            {"attributes": {"POSITION": ps}, "mode": 5, "indices": i32},
            {"attributes": {"POSITION": ps}, "mode": 5},
            {"attributes": {"POSITION": pf}, "mode": 6},
            {"attributes": {"POSITION": pl}, "mode": 1},
            {"attributes": {"POSITION": pl}, "mode": 3},
        ]}],
        "nodes": [{"mesh": 0}],
    }));
    let s = from_text(&text);
    // 4 strips of 3 triangles, a fan of 4; the lines skipped with one warning each.
    assert_eq!(s.triangle_count(), 4 * 3 + 4);
    let skipped: Vec<_> = s
        .warnings
        .iter()
        .filter(|w| w.contains("not triangles"))
        .collect();
    assert_eq!(skipped.len(), 2, "{:?}", s.warnings);
    assert!(skipped[0].contains("primitive 5") && skipped[1].contains("primitive 6"));
    // Primitives sharing POSITION share the vertices.
    assert_eq!(s.meshes[0].positions.len(), 5 + 6);
    let flat = s.flatten();
    for (i, n) in normals(&flat).iter().enumerate() {
        assert!(n.z > 0.0 && n.x == 0.0 && n.y == 0.0, "triangle {i}: {n}");
    }
    // All four index types give the same strip.
    let t = &s.meshes[0].indices;
    assert_eq!(t[0..3], t[3..6]);
    assert_eq!(t[0..3], t[6..9]);
    assert_eq!(t[0..3], t[9..12]);
    assert_eq!(t[0..3], [[0, 1, 2], [1, 3, 2], [2, 3, 4]]);
    // The fan's triangles all use the centre.
    assert!(t[12..].iter().all(|tri| tri.contains(&5)));
}

#[test]
fn attributes_are_kept_and_filled() {
    let mut g = Gltf::default();
    let p = g.positions(&TRI);
    let n = g.vec3(&[[0.0, 0.0, 2.0]; 3]);
    let uv = g.raw(
        &[0u8, 0, 255, 0, 0, 255],
        3,
        "VEC2",
        common::U8,
        json!({"normalized": true}),
    );
    let col = g.raw(
        bytemuck::cast_slice(&[65535u16, 0, 0, 0, 65535, 0, 0, 0, 65535]),
        3,
        "VEC3",
        common::U16,
        json!({"normalized": true}),
    );
    let idx = g.indices_u8(&[0, 1, 2]);
    let text = g.to_gltf(json!({
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.25, 1, 1]}}],
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": p, "NORMAL": n, "TEXCOORD_0": uv, "COLOR_0": col}, "indices": idx, "material": 0}]},
            {"primitives": [{"attributes": {"POSITION": p}, "indices": idx}]},
        ],
        "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [5, 0, 0]}],
    }));
    let s = from_text(&text);
    let a = s.attributes;
    assert!(a.normals && a.texcoords && a.colors && a.materials);
    s.check_invariants().expect("invariants");
    let m0 = &s.meshes[0];
    assert_eq!(m0.normals, vec![Vec3::Z; 3], "normalised");
    assert_eq!(m0.texcoords[1], glam::Vec2::new(1.0, 0.0));
    assert_eq!(m0.colors[0], glam::Vec4::new(1.0, 0.0, 0.0, 1.0));
    assert_eq!(
        s.materials[m0.materials[0] as usize].base_color,
        glam::Vec4::new(0.5, 0.25, 1.0, 1.0)
    );
    // The second mesh had nothing: computed normals, zero uv, white, the default material.
    let m1 = &s.meshes[1];
    assert_eq!(m1.normals, vec![Vec3::Z; 3]);
    assert_eq!(m1.colors, vec![glam::Vec4::ONE; 3]);
    assert_eq!(
        s.materials[m1.materials[0] as usize].base_color,
        glam::Vec4::ONE
    );
    let (flat, fa) = s.flatten_with_attributes();
    assert_eq!(fa.normals.len(), flat.positions.len());
    assert_eq!(fa.materials.len(), flat.len());
}

#[test]
fn sparse_accessors() {
    let mut g = Gltf::default();
    let base = g.positions(&[[0.0; 3]; 3]);
    g.raw(&[1u8, 2], 2, "SCALAR", common::U8, json!({}));
    g.raw(
        bytemuck::cast_slice(&[[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0]]),
        2,
        "VEC3",
        common::F32,
        json!({}),
    );
    let mut acc = g.accessors[base].clone();
    acc["sparse"] = json!({"count": 2, "indices": {"bufferView": 1, "componentType": common::U8}, "values": {"bufferView": 2}});
    g.accessors.push(acc.clone());
    acc.as_object_mut().expect("object").remove("bufferView");
    g.accessors.push(acc);
    let text = g.to_gltf(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 3}}, {"attributes": {"POSITION": 4}}]}],
        "nodes": [{"mesh": 0}],
    }));
    let s = from_text(&text);
    let tris = s.flatten().triangles().expect("valid");
    assert_eq!(tris.len(), 2);
    for t in tris {
        assert_eq!(t, [Vec3::ZERO, Vec3::X, Vec3::Y]);
    }
}

#[test]
fn gltf_camera_on_a_node() {
    let mut g = Gltf::default();
    g.positions(&TRI);
    let rot = Quat::from_rotation_y(std::f32::consts::FRAC_PI_2);
    let text = g.to_gltf(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "cameras": [
            {"type": "orthographic", "orthographic": {"xmag": 1, "ymag": 1, "znear": 0.1, "zfar": 10}},
            {"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.1}},
        ],
        "nodes": [
            {"mesh": 0},
            {"camera": 0},
            {"translation": [0, 2, 0], "children": [3]},
            {"camera": 1, "translation": [5, 0, 0], "rotation": rot.to_array()},
        ],
        "scenes": [{"nodes": [0, 1, 2]}],
    }));
    let s = from_text(&text);
    let c = s.camera.expect("a camera");
    assert!(c.eye.abs_diff_eq(Vec3::new(5.0, 2.0, 0.0), 1e-6), "{c:?}");
    // -Z rotated by +90 degrees about Y is -X.
    let (fwd, _, _) = c.basis();
    assert!(fwd.abs_diff_eq(Vec3::NEG_X, 1e-6), "{fwd}");
    assert!((c.fov_y_deg - 0.5f32.to_degrees()).abs() < 1e-4);
    assert!(
        s.warnings.iter().any(|w| w.contains("camera")),
        "{:?}",
        s.warnings
    );
}

#[test]
fn scale_and_offset_suffixes() {
    let base = load("builtin:cornell").expect("cornell");
    let s = load("builtin:cornell#scale=1e-3#offset=1e6,0,-5").expect("suffixed");
    assert_eq!(s.triangle_count(), base.triangle_count());
    let (lo, hi) = s.bounds();
    assert!(
        (lo.x - (1e6 - 1e-3)).abs() <= 0.0625 && (hi.y - 2e-3).abs() < 1e-6,
        "{lo} {hi}"
    );
    assert_eq!(lo.z, -5.0 - 1e-3);
    let c = s.camera.expect("camera");
    let c0 = base.camera.expect("camera");
    assert!((c.eye.y - c0.eye.y * 1e-3).abs() < 1e-6);
    assert_eq!(c.eye.x, 1e6);
    // Order matters: offset then scale scales the offset too.
    let s2 = load("builtin:cornell#offset=1,0,0#scale=2").expect("suffixed");
    assert_eq!(s2.bounds().1.x, 4.0);
    // Suffixes work on files too.
    let dir = common::scratch("scale_and_offset_suffixes");
    let p = dir.join("c.glb");
    bvhtrace_scene::write_glb(&base, &p).expect("write");
    let s3 = load(&format!("{}#scale=10", p.display())).expect("file with suffix");
    assert_eq!(s3.bounds().1, Vec3::new(10.0, 20.0, 10.0));
}

#[test]
fn export_round_trips() {
    for spec in ["builtin:cornell", "builtin:spheres", "builtin:degenerate"] {
        let s = load(spec).expect("builtin");
        let glb = bvhtrace_scene::glb_bytes(&s);
        let text = bvhtrace_scene::gltf_embedded_string(&s);
        for back in [
            load_gltf_slice(&glb, "round.glb", None).expect("glb loads"),
            load_gltf_slice(text.as_bytes(), "round.gltf", None).expect("gltf loads"),
        ] {
            assert_eq!(back.meshes.len(), s.meshes.len(), "{spec}");
            assert_eq!(back.instances, s.instances, "{spec}");
            assert_eq!(back.attributes, s.attributes, "{spec}");
            for (a, b) in back.meshes.iter().zip(&s.meshes) {
                assert!(a.positions == b.positions, "{spec}: positions differ");
                assert!(a.indices == b.indices, "{spec}: indices differ");
                assert!(a.normals == b.normals, "{spec}: normals differ");
                assert!(a.materials == b.materials, "{spec}: materials differ");
            }
            let (c, c0) = (back.camera.expect("camera"), s.camera.expect("camera"));
            assert!(c.eye.abs_diff_eq(c0.eye, 1e-5));
            assert!(c.basis().0.abs_diff_eq(c0.basis().0, 1e-6));
            assert!((c.fov_y_deg - c0.fov_y_deg).abs() < 1e-4);
            let ra = c.rays(9, 7);
            let rb = c0.rays(9, 7);
            for (x, y) in ra.iter().zip(&rb) {
                assert!(Vec3::from(x.dir).abs_diff_eq(Vec3::from(y.dir), 1e-5));
            }
        }
    }
}

#[test]
fn committed_scenes_match_the_builtins() {
    let Some(dir) = bvhtrace_scene::repo_scenes_dir() else {
        println!("committed_scenes_match_the_builtins: skipped, no scenes/ folder");
        return;
    };
    for (file, spec) in [
        ("cornell.gltf", "builtin:cornell"),
        ("icosphere.glb", "builtin:icosphere:2"),
    ] {
        let f = bvhtrace_scene::load_gltf_file(&dir.join(file)).unwrap_or_else(|e| panic!("{e}"));
        let b = load(spec).expect("builtin");
        assert!(
            f.flatten() == b.flatten(),
            "{file} differs from {spec}: regenerate it with the export_scenes example"
        );
        assert_eq!(f.materials, b.materials);
        assert!(f.warnings.is_empty(), "{:?}", f.warnings);
    }
}
