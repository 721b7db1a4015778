//! Helpers shared by the integration tests: the shared scenes folder, a scratch folder,
//! and a tiny glTF builder for hand-made files.
#![allow(dead_code)]

use std::path::PathBuf;

use base64::Engine as _;
use serde_json::{Value, json};

/// The shared scenes folder, or `None` (after printing why the caller skips).
pub fn shared(test: &str) -> Option<PathBuf> {
    match bvhtrace_scene::shared_scenes_dir() {
        Some(d) if d.join("glb").is_dir() => Some(d),
        _ => {
            println!("{test}: skipped, no shared/scenes folder");
            None
        }
    }
}

/// A fresh scratch folder for this test.
pub fn scratch(test: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("bvhtrace-scene")
        .join(test);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("create scratch folder");
    d
}

/// Builds a glTF document by hand: add accessors, then wrap with the rest of the JSON.
#[derive(Default)]
pub struct Gltf {
    pub bin: Vec<u8>,
    pub views: Vec<Value>,
    pub accessors: Vec<Value>,
}

pub const F32: u32 = 5126;
pub const U8: u32 = 5121;
pub const U16: u32 = 5123;
pub const U32: u32 = 5125;

impl Gltf {
    /// Adds raw bytes as a buffer view and an accessor over it; returns the accessor.
    pub fn raw(&mut self, bytes: &[u8], count: usize, ty: &str, ctype: u32, extra: Value) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views
            .push(json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()}));
        self.bin.extend_from_slice(bytes);
        let mut acc = json!({"bufferView": self.views.len() - 1, "componentType": ctype, "count": count, "type": ty});
        if let Value::Object(m) = extra {
            for (k, v) in m {
                acc[k] = v;
            }
        }
        self.accessors.push(acc);
        self.accessors.len() - 1
    }

    pub fn positions(&mut self, p: &[[f32; 3]]) -> usize {
        let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
        for v in p {
            for c in 0..3 {
                lo[c] = lo[c].min(v[c]);
                hi[c] = hi[c].max(v[c]);
            }
        }
        self.raw(
            bytemuck::cast_slice(p),
            p.len(),
            "VEC3",
            F32,
            json!({"min": lo, "max": hi}),
        )
    }

    pub fn vec3(&mut self, p: &[[f32; 3]]) -> usize {
        self.raw(bytemuck::cast_slice(p), p.len(), "VEC3", F32, json!({}))
    }

    pub fn indices_u8(&mut self, i: &[u8]) -> usize {
        self.raw(i, i.len(), "SCALAR", U8, json!({}))
    }

    pub fn indices_u16(&mut self, i: &[u16]) -> usize {
        self.raw(bytemuck::cast_slice(i), i.len(), "SCALAR", U16, json!({}))
    }

    pub fn indices_u32(&mut self, i: &[u32]) -> usize {
        self.raw(bytemuck::cast_slice(i), i.len(), "SCALAR", U32, json!({}))
    }

    /// The document as `.gltf` text with the buffer as a `data:` URI; `rest` holds the
    /// other top-level properties (meshes, nodes, scenes...).
    pub fn to_gltf(&self, rest: Value) -> String {
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&self.bin)
        );
        self.document(rest, json!([{"byteLength": self.bin.len(), "uri": uri}]))
            .to_string()
    }

    /// The document as JSON with the given `buffers`.
    pub fn document(&self, rest: Value, buffers: Value) -> Value {
        let mut root = json!({
            "asset": {"version": "2.0"},
            "buffers": buffers,
            "bufferViews": self.views,
            "accessors": self.accessors,
        });
        if let Value::Object(m) = rest {
            for (k, v) in m {
                root[k] = v;
            }
        }
        root
    }
}

/// A unit right triangle in the z = 0 plane, facing +z (counter-clockwise from +z).
pub const TRI: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

/// The geometric normal `cross(b - a, c - a)` of each triangle of a flattened scene.
pub fn normals(m: &bvhtrace_core::mesh::TriangleMesh) -> Vec<glam::Vec3> {
    m.triangles()
        .expect("valid triangles")
        .iter()
        .map(|[a, b, c]| (*b - *a).cross(*c - *a))
        .collect()
}
