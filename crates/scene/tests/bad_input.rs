//! Each kind of bad input gives a `SceneError` naming the file and the cause.

mod common;

use std::path::{Path, PathBuf};

use bvhtrace_scene::{ErrorKind, SceneError, load, load_gltf_file};
use common::{Gltf, TRI};
use serde_json::json;

/// Loads `path` expecting an error whose message is `"<path>: ..."` and contains `cause`.
fn expect_error(path: &Path, cause: &str) -> SceneError {
    let e = load_gltf_file(path).expect_err("expected an error");
    let msg = e.to_string();
    let prefix = format!("{}: ", path.display());
    assert!(
        msg.starts_with(&prefix),
        "{msg:?} does not start with {prefix:?}"
    );
    assert!(msg.contains(cause), "{msg:?} does not mention {cause:?}");
    e
}

fn one_triangle_scene() -> serde_json::Value {
    json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    })
}

fn write(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).expect("write test file");
    p
}

fn cornell_glb() -> Vec<u8> {
    bvhtrace_scene::glb_bytes(&load("builtin:cornell").expect("cornell"))
}

#[test]
fn truncated_glb() {
    let dir = common::scratch("truncated_glb");
    let glb = cornell_glb();
    for n in [0, 3, 11, 12, 19, 40, glb.len() / 2, glb.len() - 1] {
        let p = write(&dir, &format!("cut{n}.glb"), &glb[..n]);
        let e = expect_error(&p, "truncated");
        assert!(matches!(e.kind, ErrorKind::Truncated(_)), "{e}");
    }
}

#[test]
fn wrong_magic() {
    let dir = common::scratch("wrong_magic");
    let mut glb = cornell_glb();
    glb[3] = b'X';
    let p = write(&dir, "magic.glb", &glb);
    expect_error(&p, "wrong magic \"glTX\"");
    let p = write(&dir, "text.glb", b"{\"asset\": {\"version\": \"2.0\"}}");
    expect_error(&p, "wrong magic");
}

#[test]
fn json_errors() {
    let dir = common::scratch("json_errors");
    let p = write(
        &dir,
        "broken.gltf",
        "{\"asset\": {\"version\": \"2.0\"},, }",
    );
    expect_error(&p, "JSON error");
    let p = write(&dir, "empty.gltf", "");
    expect_error(&p, "JSON error");
    let p = write(
        &dir,
        "shape.gltf",
        "{\"asset\": {\"version\": \"2.0\"}, \"nodes\": 3}",
    );
    expect_error(&p, "JSON error");
    // A GLB whose JSON chunk is not JSON.
    let glb = cornell_glb();
    let mut bad = glb.clone();
    bad[20] = b'#';
    let p = write(&dir, "chunk.glb", &bad);
    expect_error(&p, "JSON error");
    let p = write(&dir, "v1.gltf", "{\"asset\": {\"version\": \"1.0\"}}");
    expect_error(&p, "only glTF 2.0");
}

#[test]
fn accessor_past_the_end_of_a_buffer() {
    let dir = common::scratch("accessor_past_the_end_of_a_buffer");
    // 100 vertices: 1200 bytes, in a view and buffer that say 1200 but a .bin of 800.
    let pos: Vec<[f32; 3]> = (0..100).map(|i| [i as f32, 0.0, 0.0]).collect();
    let mut g = Gltf::default();
    g.positions(&pos);
    let doc = g.document(
        json!({
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "nodes": [{"mesh": 0}],
        }),
        json!([{"byteLength": 1200, "uri": "data.bin"}]),
    );
    write(&dir, "data.bin", &g.bin[..800]);
    let p = write(&dir, "short.gltf", doc.to_string());
    let e = expect_error(
        &p,
        "accessor 0 reads past the end of buffer 0 (needs 1200 bytes, has 800)",
    );
    assert_eq!(
        e.to_string(),
        format!(
            "{}: accessor 0 reads past the end of buffer 0 (needs 1200 bytes, has 800)",
            p.display()
        )
    );

    // An accessor whose count runs past its buffer view.
    let mut doc = doc;
    doc["accessors"][0]["count"] = json!(101);
    write(&dir, "data.bin", &g.bin);
    let p = write(&dir, "view.gltf", doc.to_string());
    expect_error(
        &p,
        "accessor 0 reads past the end of buffer view 0 (needs 1212 bytes, has 1200)",
    );

    // A huge byteOffset must not overflow.
    doc["accessors"][0]["count"] = json!(100);
    doc["accessors"][0]["byteOffset"] = json!(u64::MAX - 4);
    let p = write(&dir, "offset.gltf", doc.to_string());
    expect_error(&p, "reads past the end of buffer view 0");

    // A stride smaller than the element.
    doc["accessors"][0]["byteOffset"] = json!(0);
    doc["bufferViews"][0]["byteStride"] = json!(4);
    let p = write(&dir, "stride.gltf", doc.to_string());
    expect_error(&p, "byte stride 4");
}

#[test]
fn indices_out_of_range() {
    let dir = common::scratch("indices_out_of_range");
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u16(&[0, 1, 2, 2, 1, 7]);
    let p = write(&dir, "range.gltf", g.to_gltf(one_triangle_scene()));
    let e = expect_error(
        &p,
        "mesh 0 primitive 0: triangle 1 uses vertex index 7, but the primitive has 3 vertices",
    );
    assert!(matches!(
        e.kind,
        ErrorKind::IndexOutOfRange { index: 7, .. }
    ));
}

#[test]
fn non_finite_positions() {
    let dir = common::scratch("non_finite_positions");
    for (name, bad) in [
        ("nan", f32::NAN),
        ("inf", f32::INFINITY),
        ("-inf", f32::NEG_INFINITY),
    ] {
        let mut g = Gltf::default();
        let mut tri = TRI;
        tri[1][2] = bad;
        g.vec3(&tri);
        g.accessors[0]["min"] = json!([0, 0, 0]);
        g.accessors[0]["max"] = json!([1, 1, 0]);
        g.indices_u8(&[0, 1, 2]);
        let p = write(
            &dir,
            &format!("{name}.gltf"),
            g.to_gltf(one_triangle_scene()),
        );
        expect_error(&p, "mesh 0 primitive 0: position 1 is not finite");
    }
    // A node transform that overflows f32 in the world.
    let mut g = Gltf::default();
    g.positions(&[[0.0, 0.0, 0.0], [1e30, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    let mut scene = one_triangle_scene();
    scene["meshes"][0]["primitives"][0]
        .as_object_mut()
        .expect("object")
        .remove("indices");
    scene["nodes"][0]["scale"] = json!([1e30, 1, 1]);
    let p = write(&dir, "overflow.gltf", g.to_gltf(scene));
    expect_error(&p, "not finite");
}

#[test]
fn zero_triangles() {
    let dir = common::scratch("zero_triangles");
    let mut g = Gltf::default();
    g.positions(&TRI);
    let scene = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 0}]}],
        "nodes": [{"mesh": 0}],
    });
    let p = write(&dir, "points.gltf", g.to_gltf(scene));
    expect_error(&p, "the scene has no triangles");
    let p = write(&dir, "nothing.gltf", "{\"asset\": {\"version\": \"2.0\"}}");
    expect_error(&p, "the scene has no triangles");
    // Two indices: not even one triangle.
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1]);
    let p = write(&dir, "two.gltf", g.to_gltf(one_triangle_scene()));
    expect_error(&p, "the scene has no triangles");
}

#[test]
fn unsupported_required_extensions() {
    let dir = common::scratch("unsupported_required_extensions");
    for ext in [
        "KHR_draco_mesh_compression",
        "EXT_meshopt_compression",
        "KHR_meshopt_compression",
    ] {
        let mut g = Gltf::default();
        g.positions(&TRI);
        g.indices_u8(&[0, 1, 2]);
        let mut scene = one_triangle_scene();
        scene["extensionsUsed"] = json!([ext]);
        scene["extensionsRequired"] = json!([ext]);
        let p = write(&dir, &format!("{ext}.gltf"), g.to_gltf(scene));
        let e = expect_error(&p, ext);
        assert!(matches!(e.kind, ErrorKind::UnsupportedExtension(_)), "{e}");
    }
    // Merely used (not required) is fine, and so is a required texture extension.
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    let mut scene = one_triangle_scene();
    scene["extensionsUsed"] = json!(["KHR_draco_mesh_compression", "KHR_texture_transform"]);
    scene["extensionsRequired"] = json!(["KHR_texture_transform"]);
    let p = write(&dir, "used.gltf", g.to_gltf(scene));
    let s = load_gltf_file(&p).expect("loads");
    assert_eq!(s.triangle_count(), 1);
}

#[test]
fn missing_buffer_file_and_missing_images() {
    let dir = common::scratch("missing_buffer_file_and_missing_images");
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    let mut doc = g.document(
        one_triangle_scene(),
        json!([{"byteLength": g.bin.len(), "uri": "nope.bin"}]),
    );
    let p = write(&dir, "nobin.gltf", doc.to_string());
    expect_error(&p, "buffer 0: cannot read");
    // With the buffer present, missing images are a single warning.
    write(&dir, "nope.bin", &g.bin);
    doc["images"] = json!([{"uri": "a.png"}, {"uri": "b%20c.png"}]);
    let p = write(&dir, "images.gltf", doc.to_string());
    let s = load_gltf_file(&p).expect("missing images are not an error");
    let w: Vec<_> = s.warnings.iter().filter(|w| w.contains("image")).collect();
    assert_eq!(w.len(), 1, "{:?}", s.warnings);
    assert!(
        w[0].contains("a.png") && w[0].contains("b%20c.png"),
        "{w:?}"
    );
    // A buffer URI naming a folder is refused, not read.
    doc["buffers"][0]["uri"] = json!(".");
    let p = write(&dir, "folder.gltf", doc.to_string());
    expect_error(&p, "not a regular file");
    // A bad data: URI.
    doc["buffers"][0]["uri"] = json!("data:application/octet-stream;base64,@@@@");
    let p = write(&dir, "datauri.gltf", doc.to_string());
    expect_error(&p, "buffer 0: the data: URI is not valid base64");
}

#[test]
fn invalid_references_and_transforms() {
    let dir = common::scratch("invalid_references_and_transforms");
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    let cases = [
        (
            json!({"nodes": [{"mesh": 3}]}),
            "node 0 refers to mesh 3, which does not exist",
        ),
        (
            json!({"nodes": [{"children": [9]}]}),
            "node 9 does not exist",
        ),
        (
            json!({"scene": 2, "scenes": []}),
            "the default scene 2 does not exist",
        ),
        (
            json!({"nodes": [{"mesh": 0, "rotation": [0, 0, 0, 0]}]}),
            "node 0: its rotation",
        ),
        (
            json!({"nodes": [{"mesh": 0, "matrix": [1e39, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}]}),
            "node 0: its matrix is not finite",
        ),
        (
            json!({"meshes": [{"primitives": [{"attributes": {"POSITION": 5}}]}]}),
            "accessor 5 does not exist",
        ),
    ];
    for (i, (over, cause)) in cases.into_iter().enumerate() {
        let mut scene = one_triangle_scene();
        for (k, v) in over.as_object().expect("object") {
            scene[k] = v.clone();
        }
        let p = write(&dir, &format!("case{i}.gltf"), g.to_gltf(scene));
        expect_error(&p, cause);
    }
    // A cycle in the node hierarchy ends with a warning, not a hang.
    let mut scene = one_triangle_scene();
    scene["nodes"] = json!([{"mesh": 0, "children": [1]}, {"mesh": 0, "children": [0]}]);
    let p = write(&dir, "cycle.gltf", g.to_gltf(scene));
    let s = load_gltf_file(&p).expect("a cycle is survivable");
    assert_eq!(s.instance_count(), 2);
    assert!(
        s.warnings.iter().any(|w| w.contains("cycle")),
        "{:?}",
        s.warnings
    );
}

#[test]
fn missing_file_and_bad_specs() {
    let e = load("/no/such/file.glb").expect_err("missing");
    assert!(
        e.to_string()
            .starts_with("/no/such/file.glb: cannot read the file"),
        "{e}"
    );
    for spec in [
        "builtin:nope",
        "builtin:icosphere:99",
        "builtin:cornell#scale=0",
        "builtin:cornell#offset=1,2",
    ] {
        let e = load(spec).expect_err(spec);
        assert!(
            e.to_string()
                .starts_with(&format!("{spec}: bad scene spec")),
            "{e}"
        );
    }
}
