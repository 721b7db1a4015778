//! Materials: factors; the base colour, metallic-roughness, emissive and normal textures
//! (PNG and JPEG, each image decoded once) with their samplers' wrap modes; for MASK (and
//! BLEND, taken as MASK at 0.5) the base colour texture's alpha, which opaque materials do
//! not keep. An unusable texture leaves the factors with one warning naming the material
//! and the image.

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
fn blend_is_a_mask_at_one_half_and_opaque_materials_keep_no_alpha() {
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
    let s = textured(
        "OPAQUE",
        json!({"uri": data_uri("image/png", &png([0, 0, 0, 0]))}),
    );
    assert_eq!(s.materials[0].alpha_mode, AlphaMode::Opaque);
    assert!(s.alpha_textures.is_empty() && s.materials[0].alpha_texture.is_none());
    // Its colour is loaded all the same.
    assert!(s.materials[0].base_color_texture.is_some());
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
    // A JPEG has no alpha: read as 1 everywhere, without a warning (its colour is kept).
    let jpeg = jpeg(4, 4, [10, 20, 30]);
    let s = textured("MASK", json!({"uri": data_uri("image/jpeg", &jpeg)}));
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    assert!(s.materials[0].alpha_texture.is_none() && s.alpha_textures.is_empty());
    assert!(s.materials[0].base_color_texture.is_some());
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

/// A `width` x `height` PNG of the RGBA bytes `rgba` (row by row from the top).
fn png_rgba(width: u32, height: u32, rgba: &[u8]) -> Vec<u8> {
    let img = image::RgbaImage::from_raw(width, height, rgba.to_vec()).expect("sized");
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .expect("encode");
    out.into_inner()
}

/// A `width` x `height` JPEG of one colour.
fn jpeg(width: u32, height: u32, rgb: [u8; 3]) -> Vec<u8> {
    jpeg_of(&image::RgbImage::from_pixel(width, height, image::Rgb(rgb)))
}

fn jpeg_of(img: &image::RgbImage) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95);
    img.write_with_encoder(encoder).expect("encode");
    out.into_inner()
}

/// A PNG whose header claims `width` x `height` texels (its CRC made right, its data not).
fn png_claiming(width: u32, height: u32) -> Vec<u8> {
    let mut b = png([255; 4]);
    // After the 8-byte signature: IHDR's length (8..12), type (12..16), data (16..29), CRC.
    b[16..20].copy_from_slice(&width.to_be_bytes());
    b[20..24].copy_from_slice(&height.to_be_bytes());
    let crc = crc32(&b[12..29]);
    b[29..33].copy_from_slice(&crc.to_be_bytes());
    b
}

/// CRC-32 as PNG chunks use it (IEEE, reflected).
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &x in bytes {
        c ^= u32::from(x);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

#[test]
fn every_texture_slot_is_loaded_with_its_texels_wraps_and_scale() {
    // Four images told apart by their sizes and texels.
    let texels: [(u32, u32, Vec<u8>); 4] = [
        (2, 1, vec![255, 0, 0, 255, 0, 255, 0, 128]),
        (1, 2, vec![0, 64, 200, 255, 0, 128, 100, 255]),
        (2, 2, (0..16).map(|i| i * 16).collect()),
        (1, 1, vec![128, 128, 255, 255]),
    ];
    let images: Vec<Value> = (texels.iter())
        .map(|(w, h, t)| json!({"uri": data_uri("image/png", &png_rgba(*w, *h, t))}))
        .collect();
    let s = scene(
        json!([{
            "name": "brass",
            "pbrMetallicRoughness": {
                "baseColorFactor": [0.5, 0.6, 0.7, 1],
                "metallicFactor": 0.9,
                "roughnessFactor": 0.4,
                "baseColorTexture": {"index": 0},
                "metallicRoughnessTexture": {"index": 1, "texCoord": 0},
            },
            "emissiveFactor": [1, 0.5, 0.25],
            "emissiveTexture": {"index": 2},
            "normalTexture": {"index": 3, "scale": 0.5},
        }]),
        json!({
            "textures": [
                {"source": 0, "sampler": 0},
                {"source": 1},
                {"source": 2, "sampler": 1},
                {"source": 3, "sampler": 0},
            ],
            "samplers": [{"wrapS": 33071, "wrapT": 33648}, {"wrapS": 33648, "wrapT": 10497}],
            "images": images,
        }),
    );
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let m = &s.materials[0];
    // The factors stay: the texels multiply them.
    assert_eq!(m.base_color.to_array(), [0.5, 0.6, 0.7, 1.0]);
    assert_eq!((m.metallic, m.roughness), (0.9, 0.4));
    assert_eq!(m.emissive.to_array(), [1.0, 0.5, 0.25]);
    assert_eq!(m.normal_scale, 0.5);
    use Wrap::{ClampToEdge as C, MirroredRepeat as M, Repeat as R};
    let slots = [
        (m.base_color_texture, [C, M]),
        (m.metallic_roughness_texture, [R, R]),
        (m.emissive_texture, [M, R]),
        (m.normal_texture, [C, M]),
    ];
    assert_eq!(s.textures.len(), 4);
    for (i, (r, wrap)) in slots.into_iter().enumerate() {
        let r = r.unwrap_or_else(|| panic!("slot {i} has no texture"));
        assert_eq!(r.wrap, wrap, "slot {i}");
        let t = &s.textures[r.texture];
        let (w, h, want) = &texels[i];
        assert_eq!((t.width, t.height, &t.rgba), (*w, *h, want), "slot {i}");
        assert_eq!(t.name, format!("image {i}"));
    }
    // An opaque material keeps no alpha texture.
    assert!(m.alpha_texture.is_none() && s.alpha_textures.is_empty());
    // Without a normal texture the scale is glTF's default.
    let s = scene(json!([{}]), json!({}));
    assert_eq!(s.materials[0].normal_scale, 1.0);
    assert!(s.textures.is_empty());
}

#[test]
fn materials_sharing_an_image_decode_it_once() {
    let s = scene(
        json!([
            {
                "name": "a",
                "alphaMode": "MASK",
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}},
                "emissiveTexture": {"index": 1},
            },
            {
                "name": "b",
                "alphaMode": "MASK",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": 1},
                    "metallicRoughnessTexture": {"index": 0},
                },
            },
        ]),
        json!({
            "textures": [{"source": 0}, {"source": 0, "sampler": 0}],
            "samplers": [{"wrapS": 33071, "wrapT": 33071}],
            "images": [{"uri": data_uri("image/png", &png([10, 20, 30, 40]))}],
        }),
    );
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    assert_eq!(s.textures.len(), 1);
    assert_eq!(s.alpha_textures.len(), 1);
    assert_eq!(s.alpha_textures[0].alpha, [10, 20, 30, 40]);
    let (a, b) = (&s.materials[0], &s.materials[1]);
    let r = |t: Option<bvhtrace_scene::TextureRef>| t.map(|t| (t.texture, t.wrap));
    let (rep, clamp) = ([Wrap::Repeat; 2], [Wrap::ClampToEdge; 2]);
    assert_eq!(r(a.base_color_texture), Some((0, rep)));
    assert_eq!(r(a.emissive_texture), Some((0, clamp)));
    assert_eq!(r(b.base_color_texture), Some((0, clamp)));
    assert_eq!(r(b.metallic_roughness_texture), Some((0, rep)));
    let alpha = |m: &bvhtrace_scene::Material| m.alpha_texture.map(|t| (t.texture, t.wrap));
    assert_eq!((alpha(a), alpha(b)), (Some((0, rep)), Some((0, clamp))));
}

#[test]
fn a_jpeg_texture_is_decoded() {
    let s = scene(
        json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]),
        json!({
            "textures": [{"source": 0}],
            "images": [{"uri": data_uri("image/jpeg", &jpeg(16, 8, [200, 100, 50]))}],
        }),
    );
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let t = &s.textures[s.materials[0]
        .base_color_texture
        .expect("a texture")
        .texture];
    assert_eq!((t.width, t.height, t.rgba.len()), (16, 8, 16 * 8 * 4));
    // Lossy, but a flat colour comes back within a step or two; alpha is opaque.
    for p in t.rgba.chunks_exact(4) {
        let near = |got: u8, want: u8| got.abs_diff(want) <= 3;
        assert!(
            near(p[0], 200) && near(p[1], 100) && near(p[2], 50),
            "{p:?}"
        );
        assert_eq!(p[3], 255);
    }
}

#[test]
fn an_image_in_a_buffer_view_is_decoded() {
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    let img = png([9, 8, 7, 6]);
    g.views
        .push(json!({"buffer": 0, "byteOffset": g.bin.len(), "byteLength": img.len()}));
    g.bin.extend_from_slice(&img);
    let doc = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}],
        "images": [{"bufferView": 2, "mimeType": "image/png", "name": "packed"}],
    });
    let s = load_gltf_slice(g.to_gltf(doc).as_bytes(), "packed.gltf", None)
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    assert_eq!(s.textures.len(), 1);
    let t = &s.textures[0];
    assert_eq!((t.name.as_str(), t.width, t.height), ("packed", 2, 2));
    let alpha: Vec<u8> = t.rgba.chunks_exact(4).map(|p| p[3]).collect();
    assert_eq!(alpha, [9, 8, 7, 6]);
}

#[test]
fn images_beside_the_gltf_file_are_read() {
    let dir = common::scratch("images_beside_the_gltf_file_are_read");
    std::fs::create_dir_all(dir.join("tex")).expect("mkdir");
    std::fs::write(dir.join("tex/a b.png"), png([1, 2, 3, 4])).expect("write");
    std::fs::write(dir.join("c.jpg"), jpeg(3, 5, [0, 0, 0])).expect("write");
    let mut g = Gltf::default();
    g.positions(&TRI);
    g.indices_u8(&[0, 1, 2]);
    let doc = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}, "emissiveTexture": {"index": 1}}],
        "textures": [{"source": 0}, {"source": 1}],
        "images": [{"uri": "tex/a%20b.png"}, {"uri": "c.jpg"}],
    });
    let path = dir.join("beside.gltf");
    std::fs::write(&path, g.to_gltf(doc)).expect("write");
    let s = bvhtrace_scene::load_gltf_file(&path).unwrap_or_else(|e| panic!("{e}"));
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    let sizes: Vec<(&str, u32, u32)> = (s.textures.iter())
        .map(|t| (t.name.as_str(), t.width, t.height))
        .collect();
    assert_eq!(sizes, [("tex/a%20b.png", 2, 2), ("c.jpg", 3, 5)]);
    // A missing file: the texture warning names it, beside the missing-files one.
    let text = std::fs::read_to_string(&path).expect("read");
    std::fs::write(&path, text.replace("c.jpg", "gone.jpg")).expect("write");
    let s = bvhtrace_scene::load_gltf_file(&path).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(s.textures.len(), 1);
    let w = s.warnings.join("\n");
    assert!(
        w.contains("material 0 (material 0) emissive: image 1 (gone.jpg): the file is missing"),
        "{w}"
    );
    assert_eq!(s.warnings.len(), 2, "{w}");
}

#[test]
fn unusable_textures_leave_the_factors_with_one_warning() {
    let s = scene(
        json!([
            {
                "name": "rusty",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.2, 0.3, 0.4, 1],
                    "metallicFactor": 0.7,
                    "roughnessFactor": 0.3,
                    "baseColorTexture": {"index": 0},
                    "metallicRoughnessTexture": {"index": 9},
                },
                "emissiveFactor": [0.5, 0.5, 0.5],
                "emissiveTexture": {"index": 1},
                "normalTexture": {"index": 2, "scale": 2},
            },
            {"name": "fine", "pbrMetallicRoughness": {"baseColorTexture": {"index": 3}}},
        ]),
        json!({
            "textures": [{"source": 0}, {"source": 1}, {"source": 7}, {"source": 2}],
            "images": [
                {"name": "garbage", "uri": data_uri("image/png", b"\x89PNG\r\n\x1a\nbroken")},
                {"uri": data_uri("image/gif", b"GIF89a\x01\x00\x01\x00")},
                {"uri": data_uri("image/png", &png([1, 2, 3, 4]))},
            ],
        }),
    );
    assert_eq!(s.warnings.len(), 1, "{:?}", s.warnings);
    let w = &s.warnings[0];
    for part in [
        "4 material texture(s) are unusable",
        "material 0 (rusty) base colour: image 0 (garbage): not a readable PNG",
        "material 0 (rusty) metallic-roughness: texture 9 does not exist",
        "material 0 (rusty) emissive: image 1: a Gif image",
        "material 0 (rusty) normal: texture 2's image 7 does not exist",
    ] {
        assert!(w.contains(part), "{part:?} not in {w}");
    }
    assert!(!w.contains("fine") && !w.contains("masked"), "{w}");
    let m = &s.materials[0];
    assert_eq!(m.base_color.to_array(), [0.2, 0.3, 0.4, 1.0]);
    assert_eq!((m.metallic, m.roughness, m.normal_scale), (0.7, 0.3, 2.0));
    assert_eq!(m.emissive.to_array(), [0.5; 3]);
    assert!(m.base_color_texture.is_none() && m.metallic_roughness_texture.is_none());
    assert!(m.emissive_texture.is_none() && m.normal_texture.is_none());
    // The other material's good image is loaded, alone.
    assert_eq!(
        s.materials[1].base_color_texture.map(|r| r.texture),
        Some(0)
    );
    assert_eq!(s.textures.len(), 1);
}

#[test]
fn a_second_texcoord_set_and_oversized_images_warn_once() {
    let s = scene(
        json!([
            {"name": "second set", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0, "texCoord": 1}}},
            {"name": "huge", "alphaMode": "MASK", "pbrMetallicRoughness": {"baseColorTexture": {"index": 1}}},
            {"name": "empty", "emissiveTexture": {"index": 2}},
        ]),
        json!({
            "textures": [{"source": 0}, {"source": 1}, {"source": 2}],
            "images": [
                {"uri": data_uri("image/png", &png([1, 2, 3, 4]))},
                {"uri": data_uri("image/png", &png_claiming(16384, 8192))},
                {"uri": data_uri("image/png", &png_claiming(0, 4))},
            ],
        }),
    );
    assert_eq!(s.warnings.len(), 1, "{:?}", s.warnings);
    let w = &s.warnings[0];
    for part in [
        "3 material texture(s)",
        "(1 masked material(s) are cut by the base colour factor's alpha alone)",
        "material 0 (second set) base colour: it reads TEXCOORD_1",
        "material 1 (huge) base colour: image 1: 16384 x 8192 texels",
        "material 2 (empty) emissive: image 2",
    ] {
        assert!(w.contains(part), "{part:?} not in {w}");
    }
    // Nothing was decoded: image 0 is only read through TEXCOORD_1.
    assert!(s.textures.is_empty() && s.alpha_textures.is_empty());
    assert!(s.materials.iter().all(|m| m.base_color_texture.is_none()));
}

/// The four texture slots every material of `s` fills, or which it lacks.
fn missing_slots(s: &Scene) -> Vec<String> {
    let mut out = Vec::new();
    for m in &s.materials {
        for (slot, r) in [
            ("base colour", m.base_color_texture),
            ("metallic-roughness", m.metallic_roughness_texture),
            ("emissive", m.emissive_texture),
            ("normal", m.normal_texture),
        ] {
            if r.is_none() {
                out.push(format!("{}: {slot}", m.name));
            }
        }
    }
    out
}

/// DamagedHelmet loads its base colour, metallic-roughness, emissive and normal JPEG
/// textures without a warning, and says how long that takes. The shared folder keeps
/// neither its images nor, in the GLB, its materials: the glTF original is loaded from a
/// copy beside which stand-in JPEGs of the published size (2048 x 2048) are written.
#[test]
fn damaged_helmet_loads_its_textures() {
    use std::time::Instant;
    let dir = bvhtrace_scene::shared_scenes_dir();
    let Some(dir) = dir.filter(|d| d.join("gltf/DamagedHelmet/DamagedHelmet.gltf").is_file())
    else {
        println!("damaged_helmet_loads_its_textures: skipped, no shared/scenes folder");
        return;
    };
    let glb = bvhtrace_scene::load_gltf_file(&dir.join("glb/damaged_helmet.glb"))
        .unwrap_or_else(|e| panic!("{e}"));
    if glb.textures.is_empty() {
        println!(
            "note: glb/damaged_helmet.glb is geometry only ({} material(s), no images): its \
             textures are checked through the glTF original",
            glb.materials.len()
        );
    } else {
        assert!(glb.warnings.is_empty(), "{:?}", glb.warnings);
        assert_eq!(missing_slots(&glb), Vec::<String>::new());
    }
    let original = dir.join("gltf/DamagedHelmet");
    let t = Instant::now();
    let bare = bvhtrace_scene::load_gltf_file(&original.join("DamagedHelmet.gltf"))
        .unwrap_or_else(|e| panic!("{e}"));
    let bare_s = t.elapsed().as_secs_f64();
    assert!(bare.textures.is_empty(), "the shared folder has no images");

    let work = common::scratch("damaged_helmet_loads_its_textures");
    for f in ["DamagedHelmet.gltf", "DamagedHelmet.bin"] {
        std::fs::copy(original.join(f), work.join(f)).expect("copy");
    }
    let text = std::fs::read_to_string(work.join("DamagedHelmet.gltf")).expect("read");
    let doc: Value = serde_json::from_str(&text).expect("json");
    let uris: Vec<&str> = (doc["images"].as_array().expect("images").iter())
        .filter_map(|i| i["uri"].as_str())
        .collect();
    assert_eq!(
        uris.len(),
        5,
        "albedo, metal-roughness, emissive, AO, normal"
    );
    for (k, uri) in uris.iter().enumerate() {
        // Varied content, so the decoder does real work.
        let img = image::RgbImage::from_fn(2048, 2048, |x, y| {
            image::Rgb([
                (x / 8) as u8,
                (y / 8) as u8,
                ((x ^ y) as u8).wrapping_add(k as u8),
            ])
        });
        std::fs::write(work.join(uri), jpeg_of(&img)).expect("write");
    }
    let t = Instant::now();
    let s = bvhtrace_scene::load_gltf_file(&work.join("DamagedHelmet.gltf"))
        .unwrap_or_else(|e| panic!("{e}"));
    let load_s = t.elapsed().as_secs_f64();
    assert!(s.warnings.is_empty(), "{:?}", s.warnings);
    assert_eq!(missing_slots(&s), Vec::<String>::new());
    // Four textures: the occlusion map is not one the tracer samples.
    assert_eq!(s.textures.len(), 4);
    for t in &s.textures {
        assert_eq!((t.width, t.height), (2048, 2048), "{}", t.name);
        assert_eq!(t.rgba.len(), 2048 * 2048 * 4);
    }
    let sizes: Vec<String> = (s.textures.iter())
        .map(|t| format!("{} {}x{}", t.name, t.width, t.height))
        .collect();
    println!(
        "DamagedHelmet.gltf with {} JPEG textures ({}): load {:.0} ms; without its images \
         {:.0} ms{}",
        s.textures.len(),
        sizes.join(", "),
        load_s * 1e3,
        bare_s * 1e3,
        if cfg!(debug_assertions) {
            " [debug build: run with --release for the real figure]"
        } else {
            ""
        }
    );
}
