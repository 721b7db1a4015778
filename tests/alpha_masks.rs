//! Alpha-tested geometry on every tracer: the masks travel with the BVH
//! (`FlatBvh::set_masks`, attached by `Scene::tracing_bvh`), and the kernels on wgpu (buffers
//! and textures) and ash cut the same candidates as the CPU walks, ray by ray and bit for
//! bit, for every walk, closest and any hit, one level and two. The scenes: the committed
//! foliage (`scenes/foliage.gltf`) and a made-up one of edge cases: coordinates far outside
//! `0..1` under each wrap mode, texels exactly at the cutoff and one below, a texture of one
//! texel, a material naming a texture that is missing, and a mirrored instance.

use bvhtrace_core::{FlatBvh, Query, Ray, TraceOptions, Traversal, trace_rays};
use bvhtrace_scene::{
    AlphaMode, AlphaTexture, AlphaTextureRef, Instance, Material, Mesh, Scene, Wrap,
};
use glam::{Mat4, Vec2, Vec3, Vec4};

mod common;
mod support;
use common::{Devices, name, tracers};
use support::ray_set;

const WALKS: [Traversal; 4] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(4),
    Traversal::Wide,
];

/// A `n` x `n` grid of quads over `[0, size]^2` at height `z`, texture coordinates
/// `scale * position + offset`, triangle `t`'s material `material(t)`.
fn grid(n: u32, size: f32, z: f32, uv: (f32, f32), material: impl Fn(u32) -> u32) -> Mesh {
    let mut m = Mesh::default();
    for j in 0..=n {
        for i in 0..=n {
            let p = Vec2::new(i as f32, j as f32) * (size / n as f32);
            m.positions.push(p.extend(z));
            m.texcoords.push(p * uv.0 + Vec2::splat(uv.1));
        }
    }
    for j in 0..n {
        for i in 0..n {
            let v = j * (n + 1) + i;
            m.indices.push([v, v + 1, v + n + 2]);
            m.indices.push([v, v + n + 2, v + n + 1]);
        }
    }
    m.materials = (0..m.indices.len() as u32).map(material).collect();
    m
}

fn masked(name: &str, cutoff: f32, alpha: f32, texture: Option<(usize, [Wrap; 2])>) -> Material {
    Material {
        alpha_mode: AlphaMode::Mask { cutoff },
        alpha_texture: texture.map(|(texture, wrap)| AlphaTextureRef { texture, wrap }),
        ..Material::opaque(name, Vec4::new(0.8, 0.8, 0.8, alpha))
    }
}

/// The edge cases: a grid under four masked materials (each wrap mode, coordinates from
/// -2.3 to 4.1, a 5 x 3 texture with texels 127 and 128 around a cutoff of 128/255),
/// one-texel and missing textures, a second grid placed twice (once mirrored), and an
/// opaque floor behind them all.
fn edge_cases() -> Scene {
    let cutoff = 128.0f32 / 255.0;
    let texels: Vec<u8> = vec![
        0, 127, 128, 255, 129, 128, 127, 40, 250, 0, 255, 128, 127, 3, 200,
    ];
    let mut s = Scene {
        alpha_textures: vec![
            AlphaTexture {
                name: "edges".into(),
                width: 5,
                height: 3,
                alpha: texels,
            },
            AlphaTexture {
                name: "one texel".into(),
                width: 1,
                height: 1,
                alpha: vec![128],
            },
        ],
        ..Scene::default()
    };
    let w = |u, v| [u, v];
    s.materials = vec![
        Material::opaque("floor", Vec4::ONE),
        masked(
            "repeat",
            cutoff,
            1.0,
            Some((0, w(Wrap::Repeat, Wrap::Repeat))),
        ),
        masked(
            "clamp",
            cutoff,
            1.0,
            Some((0, w(Wrap::ClampToEdge, Wrap::MirroredRepeat))),
        ),
        masked(
            "mirror",
            cutoff,
            1.0,
            Some((0, w(Wrap::MirroredRepeat, Wrap::ClampToEdge))),
        ),
        masked(
            "one texel",
            cutoff,
            1.0,
            Some((1, w(Wrap::Repeat, Wrap::Repeat))),
        ),
        masked(
            "missing",
            0.3,
            0.5,
            Some((7, w(Wrap::Repeat, Wrap::Repeat))),
        ),
        masked("faint", 0.6, 0.5, None),
    ];
    s.meshes.push(grid(1, 8.0, -1.0, (0.0, 0.0), |_| 0));
    s.meshes
        .push(grid(9, 3.0, 0.0, (2.1, -2.3), |t| 1 + (t / 2) % 6));
    s.meshes
        .push(grid(5, 2.0, 0.5, (0.9, 0.05), |t| 1 + (t / 2) % 3));
    s.instances = vec![
        Instance {
            mesh: 0,
            transform: Mat4::from_translation(Vec3::new(-2.0, -2.0, 0.0)),
        },
        Instance {
            mesh: 1,
            transform: Mat4::IDENTITY,
        },
        Instance {
            mesh: 2,
            transform: Mat4::from_translation(Vec3::new(-1.0, 0.5, 0.0)),
        },
        Instance {
            mesh: 2,
            transform: Mat4::from_translation(Vec3::new(5.5, 0.5, 0.0))
                * Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0)),
        },
    ];
    s
}

/// Rays straight down over the scene, on a fine grid, and the random ray set.
fn rays_for(bvh: &FlatBvh) -> Vec<Ray> {
    let b = bvh.bounds();
    let mut rays = Vec::new();
    for j in 0..96 {
        for i in 0..128 {
            let x = b.min.x + (b.max.x - b.min.x) * (i as f32 + 0.5) / 128.0;
            let y = b.min.y + (b.max.y - b.min.y) * (j as f32 + 0.5) / 96.0;
            rays.push(Ray::new(Vec3::new(x, y, b.max.z + 1.0), Vec3::NEG_Z));
        }
    }
    rays.extend(ray_set(bvh, 0xa1fa));
    rays
}

/// Every tracer against the CPU twin, every walk and query; returns the CPU's closest hits
/// of the full stack.
fn check(label: &str, devices: &Devices, bvh: &FlatBvh, rays: &[Ray]) -> Vec<u32> {
    let all = tracers(devices, bvh);
    assert!(bvh.masks().is_some(), "{label}: no masks");
    let mut failures = Vec::new();
    for walk in WALKS {
        for query in [Query::Closest, Query::Any] {
            let opts = TraceOptions::new(walk, query);
            let cpu = all[0].trace(rays, &opts).expect("cpu trace");
            for t in &all[1..] {
                let got = t.trace(rays, &opts).expect("device trace");
                let who = format!("{label} {walk} {query:?} on {}", name(&**t));
                assert_eq!(
                    t.upload_stats().map(|s| s.masks_bytes > 0),
                    Some(true),
                    "{who}"
                );
                let bad: Vec<usize> = (0..rays.len())
                    .filter(|&i| {
                        let (a, b) = (&cpu.hits[i], &got.hits[i]);
                        (a.prim, a.t.to_bits(), a.u.to_bits(), a.v.to_bits())
                            != (b.prim, b.t.to_bits(), b.u.to_bits(), b.v.to_bits())
                    })
                    .collect();
                if let Some(&i) = bad.first() {
                    // Where only the last bits differ (a device that fuses products into
                    // sums), the primitives still say whether the masks decided alike.
                    let prims = bad
                        .iter()
                        .filter(|&&i| cpu.hits[i].prim != got.hits[i].prim)
                        .count();
                    failures.push(format!(
                        "{who}: {} of {} rays differ ({prims} in the primitive); ray {i} {:?}: \
                         cpu {:?}, device {:?}",
                        bad.len(),
                        rays.len(),
                        rays[i],
                        cpu.hits[i],
                        got.hits[i]
                    ));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    devices.check_validation();
    let opts = TraceOptions::closest(Traversal::FullStack);
    trace_rays(bvh, rays, &opts)
        .hits
        .iter()
        .map(|h| h.prim)
        .collect()
}

/// The same rays with the masks dropped stop at other triangles: the masks cut.
fn assert_cuts(label: &str, bvh: &FlatBvh, rays: &[Ray], masked: &[u32]) {
    let mut opaque = bvh.clone();
    opaque.set_masks(None).expect("dropped");
    let opts = TraceOptions::closest(Traversal::FullStack);
    let whole = trace_rays(&opaque, rays, &opts).hits;
    let changed = whole
        .iter()
        .zip(masked)
        .filter(|(h, p)| h.prim != **p)
        .count();
    assert!(
        changed > rays.len() / 50,
        "{label}: the masks changed only {changed} hits"
    );
}

#[test]
fn masked_scenes_equal_the_cpu_on_every_tracer() {
    let devices = Devices::open("alpha_masks");
    let foliage = bvhtrace_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/foliage.gltf"
    ))
    .expect("scenes/foliage.gltf");
    for (label, scene) in [("edge cases", edge_cases()), ("foliage", foliage)] {
        for flatten in [true, false] {
            let mut traced = scene
                .tracing_bvh(&Default::default(), flatten)
                .unwrap_or_else(|e| panic!("{label}: {e}"));
            traced.build_wide();
            let label = format!(
                "{label} ({})",
                if flatten { "flattened" } else { "two levels" }
            );
            let bvh = traced.bvh();
            let rays = rays_for(bvh);
            let masks = bvh.masks().expect("masks attached").clone();
            masks.reset_counts();
            let prims = check(&label, devices, bvh, &rays);
            let (settled, sampled) = masks.counts();
            assert!(
                settled > 0 && sampled > 0,
                "{label}: {settled} settled, {sampled} sampled"
            );
            assert_cuts(&label, bvh, &rays, &prims);
        }
    }
}

/// A BVH without masks uploads and runs exactly what it did: no masks binding, no alpha
/// test in the kernels; dropping a scene's masks gives that same upload.
#[test]
fn unmasked_trees_upload_and_compose_nothing_of_the_masks() {
    let devices = Devices::open("alpha_masks");
    let mut traced = edge_cases()
        .tracing_bvh(&Default::default(), true)
        .expect("bvh");
    traced.build_wide();
    let with = traced.bvh().clone();
    traced.set_masks(None).expect("dropped");
    let without = traced.bvh();
    let rays = rays_for(without);
    let (a, b) = (tracers(devices, &with), tracers(devices, without));
    for (m, u) in a.iter().zip(&b).skip(1) {
        let (sm, su) = (
            m.upload_stats().expect("device"),
            u.upload_stats().expect("device"),
        );
        assert_eq!(su.masks_bytes, 0, "{}", name(&**u));
        assert_eq!(
            sm.total_bytes() - sm.masks_bytes,
            su.total_bytes(),
            "{}: the masks changed the other arrays",
            name(&**u)
        );
        let opts = TraceOptions::closest(Traversal::Stackless);
        u.trace(&rays, &opts).expect("trace");
        m.trace(&rays, &opts).expect("trace");
        let (km, ku) = (m.kernels_used(), u.kernels_used());
        assert!(km.iter().all(|k| k.masks) && ku.iter().all(|k| !k.masks));
        for k in &ku {
            let src = k.source();
            assert!(
                !src.contains("bvh_alpha") && !src.contains("bvh_masks"),
                "{k:?}"
            );
        }
        for k in &km {
            assert!(
                k.source()
                    .contains("&& bvh_alpha_accept(tri.prim, h.u, h.v)"),
                "{k:?}"
            );
        }
    }
}
