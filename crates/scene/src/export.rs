//! A small glTF 2.0 writer: enough to commit the scenes this project generates and to
//! round-trip scenes in tests.
//!
//! What is written: every mesh (positions with min/max, `u32` indices, and normals,
//! `TEXCOORD_0` and `COLOR_0` when [`crate::Attributes`] says the scene has them), one
//! primitive per run of triangles sharing a material (the primitives share the vertex
//! accessors, so loading the file gives back the same vertices and triangles in the same
//! order), the materials' base colour factors, one node per instance (a `matrix` unless
//! it is the identity) and the camera, if any, as a perspective camera on its own node.
//! Instancing is kept: a mesh is written once.

use std::path::Path;

use base64::Engine as _;
use glam::{Mat4, Vec3};
use serde_json::{Value, json};

use crate::error::{ErrorKind, SceneError};
use crate::{Scene, glb};

const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;

struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Builder {
    /// Appends `bytes` as a new buffer view (4-byte aligned) and an accessor over it.
    fn add(&mut self, bytes: &[u8], target: u32, accessor: Value) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views.push(json!({
            "buffer": 0,
            "byteOffset": self.bin.len(),
            "byteLength": bytes.len(),
            "target": target,
        }));
        self.bin.extend_from_slice(bytes);
        let mut acc = accessor;
        acc["bufferView"] = json!(self.views.len() - 1);
        self.accessors.push(acc);
        self.accessors.len() - 1
    }
}

/// The camera's node matrix: camera space (looking down -Z, +Y up) to world.
fn camera_matrix(c: &crate::Camera) -> Mat4 {
    let (forward, right, up) = c.basis();
    Mat4::from_cols(
        right.extend(0.0),
        up.extend(0.0),
        (-forward).extend(0.0),
        c.eye.extend(1.0),
    )
}

/// The glTF JSON (without `buffers`) and the binary payload of a scene.
fn build(scene: &Scene) -> (Value, Vec<u8>) {
    let a = scene.attributes;
    let mut b = Builder {
        bin: Vec::new(),
        views: Vec::new(),
        accessors: Vec::new(),
    };
    let mut meshes = Vec::new();
    for m in &scene.meshes {
        let (lo, hi) = m
            .positions
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &p| {
                (lo.min(p), hi.max(p))
            });
        let (lo, hi) = if m.positions.is_empty() {
            (Vec3::ZERO, Vec3::ZERO)
        } else {
            (lo, hi)
        };
        let n = m.positions.len();
        let mut attrs = serde_json::Map::new();
        let pos = b.add(
            bytemuck::cast_slice(&m.positions),
            ARRAY_BUFFER,
            json!({"componentType": FLOAT, "count": n, "type": "VEC3",
                   "min": lo.to_array(), "max": hi.to_array()}),
        );
        attrs.insert("POSITION".into(), json!(pos));
        if a.normals && m.normals.len() == n {
            let i = b.add(
                bytemuck::cast_slice(&m.normals),
                ARRAY_BUFFER,
                json!({"componentType": FLOAT, "count": n, "type": "VEC3"}),
            );
            attrs.insert("NORMAL".into(), json!(i));
        }
        if a.texcoords && m.texcoords.len() == n {
            let i = b.add(
                bytemuck::cast_slice(&m.texcoords),
                ARRAY_BUFFER,
                json!({"componentType": FLOAT, "count": n, "type": "VEC2"}),
            );
            attrs.insert("TEXCOORD_0".into(), json!(i));
        }
        if a.colors && m.colors.len() == n {
            let i = b.add(
                bytemuck::cast_slice(&m.colors),
                ARRAY_BUFFER,
                json!({"componentType": FLOAT, "count": n, "type": "VEC4"}),
            );
            attrs.insert("COLOR_0".into(), json!(i));
        }
        // One primitive per run of triangles with the same material, so that loading
        // the file gives the triangles back in their order.
        let with_materials = a.materials && m.materials.len() == m.indices.len();
        let mut groups: Vec<(Option<u32>, Vec<[u32; 3]>)> = Vec::new();
        for (t, tri) in m.indices.iter().enumerate() {
            let key = with_materials.then(|| m.materials[t]);
            match groups.last_mut() {
                Some((k, v)) if *k == key => v.push(*tri),
                _ => groups.push((key, vec![*tri])),
            }
        }
        let prims: Vec<Value> = groups
            .iter()
            .map(|(mat, tris)| {
                let idx = b.add(
                    bytemuck::cast_slice(tris),
                    ELEMENT_ARRAY_BUFFER,
                    json!({"componentType": UNSIGNED_INT, "count": tris.len() * 3, "type": "SCALAR"}),
                );
                let mut p = json!({"attributes": attrs.clone(), "indices": idx, "mode": 4});
                if let Some(mat) = mat {
                    p["material"] = json!(mat);
                }
                p
            })
            .collect();
        let mut mj = json!({ "primitives": prims });
        if !m.name.is_empty() {
            mj["name"] = json!(m.name);
        }
        meshes.push(mj);
    }
    let mut nodes: Vec<Value> = scene
        .instances
        .iter()
        .map(|inst| {
            let mut n = json!({ "mesh": inst.mesh });
            if inst.transform != Mat4::IDENTITY {
                n["matrix"] = json!(inst.transform.to_cols_array());
            }
            n
        })
        .collect();
    let mut root = json!({
        "asset": {"version": "2.0", "generator": "bvhtrace-scene"},
        "scene": 0,
        "meshes": meshes,
    });
    if let Some(c) = &scene.camera {
        let dist = (c.target - c.eye).length();
        let znear = if dist.is_finite() && dist > 0.0 {
            (dist * 1e-3).max(1e-30)
        } else {
            1e-3
        };
        root["cameras"] = json!([{
            "type": "perspective",
            "perspective": {"yfov": c.fov_y_deg.to_radians(), "znear": znear},
        }]);
        nodes.push(json!({
            "name": "camera",
            "camera": 0,
            "matrix": camera_matrix(c).to_cols_array(),
        }));
    }
    let node_ids: Vec<usize> = (0..nodes.len()).collect();
    let mut sc = json!({ "nodes": node_ids });
    if !scene.name.is_empty() {
        sc["name"] = json!(scene.name);
    }
    root["scenes"] = json!([sc]);
    root["nodes"] = json!(nodes);
    if !scene.materials.is_empty() {
        let (materials, strength) = materials_json(scene);
        root["materials"] = materials;
        if strength {
            root["extensionsUsed"] = json!(["KHR_materials_emissive_strength"]);
        }
    }
    root["bufferViews"] = Value::Array(b.views);
    root["accessors"] = Value::Array(b.accessors);
    (root, b.bin)
}

/// The scene's materials as glTF JSON, and whether one needs KHR_materials_emissive_strength
/// (glTF's emissiveFactor stops at 1: brighter light is a strength).
fn materials_json(scene: &Scene) -> (Value, bool) {
    let mut used_strength = false;
    let materials = (scene.materials.iter())
        .map(|m| {
            let mut j = json!({
                "name": m.name,
                "pbrMetallicRoughness": {
                    "baseColorFactor": m.base_color.to_array(),
                    "metallicFactor": m.metallic,
                    "roughnessFactor": m.roughness,
                },
            });
            let strength = m.emissive.max_element();
            if strength > 0.0 {
                j["emissiveFactor"] = json!((m.emissive / strength.max(1.0)).to_array());
            }
            if strength > 1.0 {
                j["extensions"] = json!({
                    "KHR_materials_emissive_strength": {"emissiveStrength": strength}
                });
                used_strength = true;
            }
            j
        })
        .collect();
    (Value::Array(materials), used_strength)
}

/// The scene as a binary glTF (GLB) file's bytes.
pub fn glb_bytes(scene: &Scene) -> Vec<u8> {
    let (mut root, bin) = build(scene);
    root["buffers"] = json!([{ "byteLength": bin.len() }]);
    let text = root.to_string();
    glb::assemble(text.as_bytes(), &bin)
}

/// The scene as a self-contained `.gltf` JSON text (the buffer is a base64 `data:` URI).
pub fn gltf_embedded_string(scene: &Scene) -> String {
    let (mut root, bin) = build(scene);
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    );
    root["buffers"] = json!([{ "byteLength": bin.len(), "uri": uri }]);
    let mut s = serde_json::to_string_pretty(&root).unwrap_or_else(|_| root.to_string());
    s.push('\n');
    s
}

fn write(path: &Path, bytes: &[u8]) -> Result<(), SceneError> {
    std::fs::write(path, bytes).map_err(|e| {
        SceneError::new(
            path.display().to_string(),
            ErrorKind::Io {
                what: "cannot write the file".into(),
                source: e,
            },
        )
    })
}

/// Writes the scene as a binary glTF (`.glb`) file.
pub fn write_glb(scene: &Scene, path: impl AsRef<Path>) -> Result<(), SceneError> {
    write(path.as_ref(), &glb_bytes(scene))
}

/// Writes the scene as one self-contained `.gltf` file (buffer embedded as a `data:` URI).
pub fn write_gltf_embedded(scene: &Scene, path: impl AsRef<Path>) -> Result<(), SceneError> {
    write(path.as_ref(), gltf_embedded_string(scene).as_bytes())
}
