//! Mutation fuzzing of real glTF and GLB files: bit flips, truncation, byte insertions
//! and deletions, edited JSON numbers and strings (inside the GLB JSON chunk too, with
//! the container's lengths fixed up so that the edit reaches the loader), overwritten
//! binary data. Every case must give `Ok` (a scene whose invariants hold and whose
//! `flatten().triangles()` is `Ok` or a clean `Err`) or a `SceneError` naming the file,
//! and never a panic (a textured GLB sends mutated PNG and JPEG bytes to the decoders).
//! Deterministic: case `i` of a run is reproducible from its seed.
//!
//! `BVHTRACE_FUZZ_CASES` overrides the number of cases (default 40,000: about a second).

mod common;

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;
use std::time::Instant;

use bvhtrace_scene::{load, load_gltf_slice};
use common::{Gltf, TRI};
use serde_json::json;

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
    fn pick<'a, T>(&mut self, v: &'a [T]) -> &'a T {
        &v[self.below(v.len())]
    }
}

struct Source {
    label: String,
    bytes: Vec<u8>,
    base_dir: Option<PathBuf>,
}

/// A small file with many features: node hierarchy, instancing, a mirror, TRS and
/// matrix, strips and fans, u8/u16 indices, sparse data, attributes, materials, a camera.
fn feature_file() -> String {
    let mut g = Gltf::default();
    let p = g.positions(&[
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
        [2.0, 0.0, 0.5],
    ]);
    let n = g.vec3(&[[0.0, 0.0, 1.0]; 5]);
    let uv = g.raw(
        &[0u8, 0, 255, 0, 0, 255, 255, 255, 128, 128],
        5,
        "VEC2",
        common::U8,
        json!({"normalized": true}),
    );
    let i8 = g.indices_u8(&[0, 1, 2, 1, 3, 2]);
    let i16 = g.indices_u16(&[0, 1, 2, 3, 4]);
    let si = g.raw(&[4u8], 1, "SCALAR", common::U8, json!({}));
    let sv = g.vec3(&[[2.0, 2.0, 2.0]]);
    let mut sparse = g.accessors[p].clone();
    sparse["sparse"] = json!({"count": 1, "indices": {"bufferView": si, "componentType": common::U8}, "values": {"bufferView": sv}});
    g.accessors.push(sparse);
    let sp = g.accessors.len() - 1;
    let _ = TRI;
    g.to_gltf(json!({
        "materials": [{"name": "m", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 1, 1]}}],
        "meshes": [
            {"primitives": [
                {"attributes": {"POSITION": p, "NORMAL": n, "TEXCOORD_0": uv}, "indices": i8, "material": 0},
                {"attributes": {"POSITION": p}, "indices": i16, "mode": 5},
                {"attributes": {"POSITION": sp}, "mode": 6},
                {"attributes": {"POSITION": p}, "mode": 1},
            ]},
            {"primitives": [{"attributes": {"POSITION": sp}, "indices": i16, "mode": 4}]},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.01}}],
        "nodes": [
            {"children": [1, 2], "translation": [1, 2, 3], "rotation": [0, 0.3826834, 0, 0.9238795]},
            {"mesh": 0, "scale": [-1, 1, 1]},
            {"mesh": 0, "matrix": [2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 5, 0, 0, 1], "children": [3]},
            {"mesh": 1, "camera": 0},
        ],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }))
}

/// A GLB whose materials sample a PNG and a JPEG stored in its binary chunk, so that
/// mutations reach the image decoders: every texture slot, a mask, shared images.
fn textured_glb() -> Vec<u8> {
    let encode = |format: image::ImageFormat| {
        let img = image::RgbaImage::from_fn(8, 8, |x, y| {
            image::Rgba([x as u8 * 30, y as u8 * 30, 90, (x * y) as u8 * 4])
        });
        let mut out = std::io::Cursor::new(Vec::new());
        match format {
            image::ImageFormat::Jpeg => image::DynamicImage::from(img)
                .to_rgb8()
                .write_to(&mut out, format),
            _ => img.write_to(&mut out, format),
        }
        .expect("encode");
        out.into_inner()
    };
    let mut g = Gltf::default();
    let p = g.positions(&TRI);
    let uv = g.raw(
        bytemuck::cast_slice(&[[0.0f32, 0.0], [1.0, 0.0], [0.0, 1.0]]),
        3,
        "VEC2",
        common::F32,
        json!({}),
    );
    let i = g.indices_u8(&[0, 1, 2]);
    for bytes in [
        encode(image::ImageFormat::Png),
        encode(image::ImageFormat::Jpeg),
    ] {
        g.views
            .push(json!({"buffer": 0, "byteOffset": g.bin.len(), "byteLength": bytes.len()}));
        g.bin.extend_from_slice(&bytes);
    }
    let n = g.views.len();
    let doc = g.document(
        json!({
            "materials": [
                {"alphaMode": "MASK", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1}}},
                {"emissiveTexture": {"index": 1}, "normalTexture": {"index": 0, "scale": 0.5}},
            ],
            "textures": [{"source": 0, "sampler": 0}, {"source": 1}],
            "samplers": [{"wrapS": 33071, "wrapT": 33648}],
            "images": [
                {"bufferView": n - 2, "mimeType": "image/png"},
                {"bufferView": n - 1, "mimeType": "image/jpeg"},
            ],
            "meshes": [
                {"primitives": [{"attributes": {"POSITION": p, "TEXCOORD_0": uv}, "indices": i, "material": 0}]},
                {"primitives": [{"attributes": {"POSITION": p, "TEXCOORD_0": uv}, "indices": i, "material": 1}]},
            ],
            "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [0, 0, 1]}],
            "scenes": [{"nodes": [0, 1]}],
        }),
        json!([{"byteLength": g.bin.len()}]),
    );
    join_glb(doc.to_string().as_bytes(), &g.bin)
}

fn sources() -> Vec<Source> {
    let cornell = load("builtin:cornell").expect("cornell");
    let mut v = vec![
        Source {
            label: "cornell.glb".into(),
            bytes: bvhtrace_scene::glb_bytes(&cornell),
            base_dir: None,
        },
        Source {
            label: "cornell.gltf".into(),
            bytes: bvhtrace_scene::gltf_embedded_string(&cornell).into_bytes(),
            base_dir: None,
        },
        Source {
            label: "features.gltf".into(),
            bytes: feature_file().into_bytes(),
            base_dir: None,
        },
    ];
    let textured = textured_glb();
    let s = load_gltf_slice(&textured, "textured.glb", None).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        s.warnings.is_empty() && s.textures.len() == 2,
        "{:?}",
        s.warnings
    );
    v.push(Source {
        label: "textured.glb".into(),
        bytes: textured,
        base_dir: None,
    });
    let ico = bvhtrace_scene::glb_bytes(&load("builtin:icosphere:1").expect("icosphere"));
    v.push(Source {
        label: "icosphere.glb".into(),
        bytes: ico,
        base_dir: None,
    });
    if let Some(dir) = common::shared("fuzz (shared files)") {
        for rel in [
            "glb/khronos_box.glb",
            "glb/cornell_box.glb",
            "gltf/Box/Box.gltf",
            "glb/suzanne_968.glb",
        ] {
            let p = dir.join(rel);
            match std::fs::read(&p) {
                Ok(bytes) => v.push(Source {
                    label: p.display().to_string(),
                    bytes,
                    base_dir: p.parent().map(PathBuf::from),
                }),
                Err(e) => println!("fuzz: {rel} unreadable ({e}), not used"),
            }
        }
    }
    v
}

/// Splits a GLB into (JSON, BIN) chunks; `None` when it is not a well-formed GLB.
fn split_glb(b: &[u8]) -> Option<(Vec<u8>, Vec<u8>)> {
    let u32_at = |at: usize| Some(u32::from_le_bytes(b.get(at..at + 4)?.try_into().ok()?) as usize);
    if b.get(..4)? != b"glTF" {
        return None;
    }
    let jl = u32_at(12)?;
    let json = b.get(20..20 + jl)?.to_vec();
    let bin = match u32_at(20 + jl) {
        Some(bl) => b.get(28 + jl..28 + jl + bl)?.to_vec(),
        None => Vec::new(),
    };
    Some((json, bin))
}

fn join_glb(json: &[u8], bin: &[u8]) -> Vec<u8> {
    let pad = |n: usize| (4 - n % 4) % 4;
    let (jl, bl) = (json.len() + pad(json.len()), bin.len() + pad(bin.len()));
    let total = 12 + 8 + jl + if bin.is_empty() { 0 } else { 8 + bl };
    let mut out = b"glTF".to_vec();
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(jl as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json);
    out.resize(out.len() + pad(json.len()), b' ');
    if !bin.is_empty() {
        out.extend_from_slice(&(bl as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(bin);
        out.resize(out.len() + pad(bin.len()), 0);
    }
    out
}

#[derive(Clone, Copy, PartialEq)]
enum Tok {
    Num,
    Str,
}

/// Number and string tokens of a JSON text, as byte ranges (strings with their quotes).
fn tokens(j: &[u8]) -> Vec<(Tok, usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < j.len() {
        match j[i] {
            b'"' => {
                let s = i;
                i += 1;
                while i < j.len() && j[i] != b'"' {
                    i += if j[i] == b'\\' { 2 } else { 1 };
                }
                i += 1;
                out.push((Tok::Str, s, i.min(j.len())));
            }
            b'-' | b'0'..=b'9' => {
                let s = i;
                while i < j.len() && matches!(j[i], b'-' | b'+' | b'.' | b'e' | b'E' | b'0'..=b'9')
                {
                    i += 1;
                }
                out.push((Tok::Num, s, i));
            }
            _ => i += 1,
        }
    }
    out
}

const NUMBERS: &[&str] = &[
    "0",
    "1",
    "-1",
    "2",
    "3",
    "4",
    "5",
    "6",
    "7",
    "8",
    "12",
    "16",
    "255",
    "256",
    "65535",
    "65536",
    "4294967295",
    "4294967296",
    "18446744073709551615",
    "1e39",
    "-1e39",
    "1e30",
    "3.5",
    "-0",
    "1e-45",
    "5120",
    "5121",
    "5122",
    "5123",
    "5125",
    "5126",
    "34962",
    "34963",
    "100000000",
    "9007199254740993",
    "0.0",
    "NaN",
    "1e",
    "--1",
];

const STRINGS: &[&str] = &[
    "\"SCALAR\"",
    "\"VEC2\"",
    "\"VEC3\"",
    "\"VEC4\"",
    "\"MAT2\"",
    "\"MAT4\"",
    "\"POSITION\"",
    "\"NORMAL\"",
    "\"TEXCOORD_0\"",
    "\"COLOR_0\"",
    "\"indices\"",
    "\"mode\"",
    "\"byteOffset\"",
    "\"byteStride\"",
    "\"byteLength\"",
    "\"count\"",
    "\"bufferView\"",
    "\"children\"",
    "\"mesh\"",
    "\"matrix\"",
    "\"scale\"",
    "\"sparse\"",
    "\"KHR_draco_mesh_compression\"",
    "\"extensionsRequired\"",
    "\"data:application/octet-stream;base64,AAAA\"",
    "\"data:,\"",
    "\"data:;base64,%%%\"",
    "\"missing.bin\"",
    "\"/dev/zero\"",
    "\".\"",
    "\"../\"",
    "\"\"",
    "\"2.0\"",
    "\"1.0\"",
    "\"perspective\"",
    "\"orthographic\"",
    "\"\\u0000\"",
    "\"é\"",
];

/// Edits 1 to 3 JSON tokens.
fn edit_json(rng: &mut Rng, j: &[u8]) -> (Vec<u8>, String) {
    let toks = tokens(j);
    let mut out = j.to_vec();
    let mut what = Vec::new();
    if toks.is_empty() {
        return (out, "no tokens".into());
    }
    let n = 1 + rng.below(3);
    // Edit from the back so earlier ranges stay valid.
    let mut picks: Vec<usize> = (0..n).map(|_| rng.below(toks.len())).collect();
    picks.sort_unstable();
    picks.dedup();
    for &k in picks.iter().rev() {
        let (kind, s, e) = toks[k];
        let new: String = match (kind, rng.below(4)) {
            (Tok::Num, 0) => rng.next().to_string(),
            (Tok::Num, 1) => ((rng.next() % 64) as i64 - 8).to_string(),
            (Tok::Num, _) => rng.pick(NUMBERS).to_string(),
            (Tok::Str, 0) => rng.pick(NUMBERS).to_string(),
            (Tok::Str, _) => rng.pick(STRINGS).to_string(),
        };
        what.push(format!("{}@{s}={new}", String::from_utf8_lossy(&j[s..e])));
        out.splice(s..e, new.bytes());
    }
    (out, format!("json edit {}", what.join(", ")))
}

fn mutate(rng: &mut Rng, src: &[u8]) -> (Vec<u8>, String) {
    let mut b = src.to_vec();
    let glb = split_glb(src);
    match rng.below(8) {
        0 => {
            let n = 1 + rng.below(8);
            let mut at = Vec::new();
            for _ in 0..n {
                let i = rng.below(b.len());
                b[i] ^= 1 << rng.below(8);
                at.push(i);
            }
            (b, format!("bit flips at {at:?}"))
        }
        1 => {
            let n = rng.below(b.len());
            b.truncate(n);
            (b, format!("truncated to {n}"))
        }
        2 => {
            let at = rng.below(b.len() + 1);
            let n = 1 + rng.below(16);
            let ins: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
            b.splice(at..at, ins);
            (b, format!("{n} bytes inserted at {at}"))
        }
        3 => {
            let at = rng.below(b.len());
            let n = (1 + rng.below(16)).min(b.len() - at);
            b.drain(at..at + n);
            (b, format!("{n} bytes deleted at {at}"))
        }
        4..=6 => match glb {
            Some((j, bin)) => {
                let (j2, what) = edit_json(rng, &j);
                (join_glb(&j2, &bin), format!("GLB {what}"))
            }
            None => edit_json(rng, &b),
        },
        _ => match glb {
            Some((j, mut bin)) if bin.len() >= 4 => {
                let vals = [
                    f32::NAN.to_bits(),
                    f32::INFINITY.to_bits(),
                    u32::MAX,
                    0x7FFF_FFFF,
                    1 << 20,
                    65535,
                ];
                let mut at = Vec::new();
                for _ in 0..1 + rng.below(4) {
                    let i = rng.below(bin.len() / 4) * 4;
                    bin[i..i + 4].copy_from_slice(&rng.pick(&vals).to_le_bytes());
                    at.push(i);
                }
                (
                    join_glb(&j, &bin),
                    format!("BIN words overwritten at {at:?}"),
                )
            }
            _ => {
                let (b2, what) = edit_json(rng, &b);
                let (b3, what2) = {
                    let mut b3 = b2;
                    let i = rng.below(b3.len().max(1));
                    if let Some(x) = b3.get_mut(i) {
                        *x ^= 0x20;
                    }
                    (b3, format!("then byte {i} flipped"))
                };
                (b3, format!("{what}, {what2}"))
            }
        },
    }
}

#[test]
fn mutated_files_never_panic() {
    let cases: usize = std::env::var("BVHTRACE_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(40_000);
    let srcs = sources();
    // The unmutated sources load.
    for s in &srcs {
        load_gltf_slice(&s.bytes, &s.label, s.base_dir.as_deref())
            .unwrap_or_else(|e| panic!("{e}"));
    }
    let start = Instant::now();
    let (mut ok, mut err) = (0usize, 0usize);
    let mut failures = Vec::new();
    let mut kinds: std::collections::BTreeMap<String, usize> = Default::default();
    for case in 0..cases {
        let src = &srcs[case % srcs.len()];
        let seed = 0xF022_0000 + case as u64;
        let mut rng = Rng(seed);
        let (bytes, what) = mutate(&mut rng, &src.bytes);
        let label = src.label.clone();
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            match load_gltf_slice(&bytes, &label, src.base_dir.as_deref()) {
                Ok(scene) => {
                    scene
                        .check_invariants()
                        .map_err(|e| format!("invariant broken: {e}"))?;
                    let (lo, hi) = scene.bounds();
                    if !(lo.is_finite() && hi.is_finite()) {
                        return Err("non-finite bounds".to_string());
                    }
                    let flat = scene.flatten();
                    let _ = flat.triangles();
                    let _ = scene.flatten_with_attributes();
                    let _ = scene.camera_or_frame(1.5).rays(3, 2);
                    Ok(true)
                }
                Err(e) => {
                    let msg = e.to_string();
                    if msg.starts_with(&format!("{label}: ")) {
                        let cause = &msg[label.len() + 2..];
                        let key: String = cause
                            .split(|c: char| c.is_ascii_digit() || c == ':' || c == '(')
                            .next()
                            .unwrap_or("")
                            .chars()
                            .take(40)
                            .collect();
                        *kinds.entry(key).or_default() += 1;
                        Ok(false)
                    } else {
                        Err(format!("error does not name the file: {msg}"))
                    }
                }
            }
        }));
        match outcome {
            Ok(Ok(true)) => ok += 1,
            Ok(Ok(false)) => err += 1,
            Ok(Err(why)) => failures.push(format!(
                "case {case} (seed {seed:#x}) {label}: {what}: {why}"
            )),
            Err(_) => failures.push(format!(
                "case {case} (seed {seed:#x}) {label}: {what}: PANIC"
            )),
        }
    }
    println!(
        "fuzz: {cases} cases over {} files in {:.2} s: {ok} loaded, {err} clean errors, {} failures",
        srcs.len(),
        start.elapsed().as_secs_f64(),
        failures.len()
    );
    let mut top: Vec<_> = kinds.into_iter().collect();
    top.sort_by_key(|k| std::cmp::Reverse(k.1));
    for (k, n) in top.iter().take(25) {
        println!("  {n:>7}  {k}");
    }
    for f in failures.iter().take(20) {
        println!("  {f}");
    }
    assert!(
        failures.is_empty(),
        "{} failing cases, first: {}",
        failures.len(),
        failures[0]
    );
}
