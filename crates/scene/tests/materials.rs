//! Masked materials: `alphaMode`, `alphaCutoff`, the base colour texture's alpha and its
//! sampler's wrap modes are loaded for MASK (and BLEND, taken as MASK at 0.5); opaque
//! materials' textures are not read; an unusable texture leaves the mask to the base
//! colour factor with a warning naming the material and the image.

mod common;

use std::io::Cursor;

use base64::Engine as _;
use bvhtrace_scene::{AlphaMode, AlphaTexture, Scene, Wrap, load_gltf_slice};
use common::{Gltf, TRI};
use serde_json::{Value, json};

/// A 2x2 PNG whose texels' alpha are `alpha` (row by row from the top).
fn png(alpha: [u8; 4]) -> Vec<u8> {
    let rgba: Vec<u8> = alpha.iter().flat_map(|&a| [200, 120, 40, a]).collect();
    let img = image::RgbaImage::from_raw(2, 2, rgba).expect("2x2");
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .expect("encode");
    out.into_inner()
}

fn data_uri(mime: &str, bytes: &[u8]) -> String {
    let b64 = base64::engine::general_purpose::STANDARD.encode(bytes);
    format!("data:{mime};base64,{b64}")
}

/// The unit triangle with `materials`, its primitive using material 0, and `rest`.
fn scene(materials: Value, rest: Value) -> Scene {
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    let mut doc = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "materials": materials,
    });
    if let Value::Object(m) = rest {
        for (k, v) in m {
            doc[k] = v;
        }
    }
    load_gltf_slice(g.to_gltf(doc).as_bytes(), "masked.gltf", None)
        .unwrap_or_else(|e| panic!("{e}"))
}

fn textured(mode: &str, image: Value) -> Scene {
    scene(
        json!([{
            "name": "leaf",
            "alphaMode": mode,
            "alphaCutoff": 0.3,
            "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 0.8], "baseColorTexture": {"index": 0}},
        }]),
        json!({
            "textures": [{"source": 0, "sampler": 0}],
            "samplers": [{"wrapS": 33071, "wrapT": 33648}],
            "images": [image],
        }),
    )
}

#[test]
fn a_masked_materials_texture_alpha_and_wraps_are_loaded() {
    let s = textured(
        "MASK",
        json!({"uri": data_uri("image/png", &png([0, 100, 200, 255]))}),
    );
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let m = &s.materials[0];
    assert_eq!(m.alpha_mode, AlphaMode::Mask { cutoff: 0.3 });
    let r = m.alpha_texture.expect("a texture");
    assert_eq!(r.wrap, [Wrap::ClampToEdge, Wrap::MirroredRepeat]);
    assert_eq!(
        s.alpha_textures[r.texture],
        AlphaTexture {
            name: "image 0".into(),
            width: 2,
            height: 2,
            alpha: vec![0, 100, 200, 255],
        }
    );
    // 0.8 * t / 255 >= 0.3 from t = 96: texels 100, 200 and 255 pass, 0 does not.
    let mask = m.alpha_mask(&s.alpha_textures).expect("masked");
    assert_eq!(mask.min_texel, 96);
    assert_eq!((mask.width, mask.height), (2, 2));
}

#[test]
fn blend_is_a_mask_at_one_half_and_opaque_textures_are_not_read() {
    let s = textured(
        "BLEND",
        json!({"uri": data_uri("image/png", &png([0, 0, 0, 0]))}),
    );
    assert_eq!(s.materials[0].alpha_mode, AlphaMode::Mask { cutoff: 0.5 });
    assert!(
        s.warnings.iter().any(|w| w.contains("BLEND")),
        "{:?}",
        s.warnings
    );
    let s = textured("OPAQUE", json!({"uri": "not-even-read.png"}));
    assert_eq!(s.materials[0].alpha_mode, AlphaMode::Opaque);
    assert!(s.alpha_textures.is_empty() && s.materials[0].alpha_texture.is_none());
    assert!(s.materials[0].alpha_mask(&s.alpha_textures).is_none());
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
}

#[test]
fn an_unusable_texture_leaves_the_factor_with_a_warning() {
    for (image, cause) in [
        (json!({"uri": "missing.png"}), "given as bytes"),
        (
            json!({"uri": data_uri("image/png", b"not a png")}),
            "not a readable PNG",
        ),
        (
            json!({"bufferView": 99, "mimeType": "image/png"}),
            "buffer view 99",
        ),
    ] {
        let s = textured("MASK", image);
        let m = &s.materials[0];
        assert_eq!(m.alpha_mode, AlphaMode::Mask { cutoff: 0.3 });
        assert!(m.alpha_texture.is_none());
        let w = s.warnings.join("\n");
        assert!(w.contains("material 0 (leaf)") && w.contains(cause), "{w}");
        // The factor alone: one texel of alpha 1, 0.8 >= 0.3 passes.
        let mask = m.alpha_mask(&s.alpha_textures).expect("masked");
        assert_eq!((mask.width, mask.alpha), (1, &[255u8][..]));
    }
    // A JPEG has no alpha: read as 1 everywhere, without a warning and without decoding.
    let jpeg = [0xff, 0xd8, 0xff, 0xe0, 0, 0x10];
    let s = textured("MASK", json!({"uri": data_uri("image/jpeg", &jpeg)}));
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    assert!(s.materials[0].alpha_texture.is_none());
}

/// A unit quad (two triangles, texture coordinates 0..1) masked by a 4x4 texture whose
/// left half is opaque, placed as is and mirrored beside it, over an opaque backdrop.
fn masked_quads() -> Scene {
    let mut g = Gltf::default();
    let quad = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ];
    g.positions(&quad);
    g.indices_u8(&[0, 1, 2, 0, 2, 3]);
    // glTF's v runs down the image: the quad's y = 0 edge samples the top row.
    let uv: [[f32; 2]; 4] = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    g.raw(bytemuck::cast_slice(&uv), 4, "VEC2", common::F32, json!({}));
    let back = [
        [-1.0, -1.0, -1.0],
        [5.0, -1.0, -1.0],
        [5.0, 2.0, -1.0],
        [-1.0, 2.0, -1.0],
    ];
    g.positions(&back);
    let alpha: Vec<u8> = (0..16).map(|i| if i % 4 < 2 { 255 } else { 0 }).collect();
    let rgba: Vec<u8> = alpha.iter().flat_map(|&a| [90, 160, 60, a]).collect();
    let img = image::RgbaImage::from_raw(4, 4, rgba).expect("4x4");
    let mut bytes = Cursor::new(Vec::new());
    img.write_to(&mut bytes, image::ImageFormat::Png)
        .expect("encode");
    let doc = json!({
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, "material": 0}]},
            {"primitives": [{"attributes": {"POSITION": 3}, "indices": 1, "material": 1}]},
        ],
        "materials": [
            {"alphaMode": "MASK", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}},
            {"name": "backdrop"},
        ],
        "textures": [{"source": 0}],
        "images": [{"uri": data_uri("image/png", &bytes.into_inner())}],
        "nodes": [
            {"mesh": 0},
            {"mesh": 0, "translation": [3.0, 0.0, 0.0], "scale": [-1.0, 1.0, 1.0]},
            {"mesh": 1},
        ],
        "scenes": [{"nodes": [0, 1, 2]}],
    });
    load_gltf_slice(g.to_gltf(doc).as_bytes(), "quads.gltf", None).unwrap_or_else(|e| panic!("{e}"))
}

/// Rays down -z at each texel's centre of both quads: through the cut half they reach the
/// backdrop, on the kept half they stop at the quad, in one level and in two, every walk;
/// the mirrored quad keeps the half its texture coordinates say.
#[test]
fn masked_quads_cut_where_their_texture_says() {
    use bvhtrace_core::{Ray, TraceOptions, Traversal, trace_rays};
    let s = masked_quads();
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let mut rays = Vec::new();
    let mut want = Vec::new();
    for (x0, mirrored) in [(0.0f32, false), (2.0, true)] {
        for j in 0..4 {
            for i in 0..4 {
                let (x, y) = (x0 + (i as f32 + 0.5) / 4.0, (j as f32 + 0.5) / 4.0);
                let u = if mirrored { 3.0 - x } else { x };
                rays.push(Ray::new(glam::Vec3::new(x, y, 5.0), glam::Vec3::NEG_Z));
                want.push(if u < 0.5 { 5.0 } else { 6.0 });
            }
        }
    }
    for flatten in [true, false] {
        let mut traced = s.tracing_bvh(&Default::default(), flatten).expect("bvh");
        assert_eq!(traced.is_two_level(), !flatten);
        traced.build_wide();
        let masks = traced
            .bvh()
            .masks()
            .expect("the tree carries the masks")
            .clone();
        assert_eq!(Some(&*masks), s.alpha_masks(&traced).as_ref());
        for walk in [Traversal::FullStack, Traversal::Stackless, Traversal::Wide] {
            let opts = TraceOptions::closest(walk);
            let hits = trace_rays(traced.bvh(), &rays, &opts).hits;
            let t: Vec<f32> = hits.iter().map(|h| h.t).collect();
            assert_eq!(t, want, "flatten {flatten}, {walk}");
        }
        // The quads' triangles each straddle both halves: every candidate is sampled.
        let (settled, sampled) = masks.counts();
        assert!(sampled > 0, "{settled} settled, {sampled} sampled");
    }
    // Unmasked, the quads stop every ray.
    let mut traced = s.tracing_bvh(&Default::default(), false).expect("bvh");
    traced.set_masks(None).expect("dropped");
    let opts = TraceOptions::closest(Traversal::FullStack);
    let plain = bvhtrace_core::trace_rays(traced.bvh(), &rays, &opts).hits;
    assert!(plain.iter().all(|h| h.t == 5.0));
}

#[test]
fn metallic_roughness_and_emission_are_loaded_and_clamped() {
    let s = scene(
        json!([
            {
                "pbrMetallicRoughness": {"metallicFactor": 0.25, "roughnessFactor": 0.5},
                "emissiveFactor": [1, 0.5, 0],
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4}},
            },
            {
                "pbrMetallicRoughness": {"metallicFactor": 3, "roughnessFactor": -1},
                "emissiveFactor": [-1, 2, 0.5],
            },
            {},
        ]),
        json!({}),
    );
    let m = &s.materials;
    assert_eq!((m[0].metallic, m[0].roughness), (0.25, 0.5));
    assert_eq!(m[0].emissive.to_array(), [4.0, 2.0, 0.0]);
    assert_eq!((m[1].metallic, m[1].roughness), (1.0, 0.0));
    assert_eq!(m[1].emissive.to_array(), [0.0, 2.0, 0.5]);
    // glTF's defaults: a fully metallic, fully rough surface that does not glow.
    assert_eq!((m[2].metallic, m[2].roughness), (1.0, 1.0));
    assert_eq!(m[2].emissive.to_array(), [0.0; 3]);
    // Written and read back through the emissive-strength extension.
    let back = bvhtrace_scene::load_gltf_slice(
        bvhtrace_scene::gltf_embedded_string(&s).as_bytes(),
        "back.gltf",
        None,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(back.materials[..2], s.materials[..2]);
}
