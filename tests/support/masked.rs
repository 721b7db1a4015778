//! The alpha-mask edge cases the masked-scene tests share (`tests/alpha_masks.rs`,
//! `tests/ray_query.rs`): a scene built in Rust, and rays through its masks.

use bvhtrace_core::{FlatBvh, Ray};
use bvhtrace_scene::{
    AlphaMode, AlphaTexture, AlphaTextureRef, Instance, Material, Mesh, Scene, Wrap,
};
use glam::{Mat4, Vec2, Vec3, Vec4};

use super::ray_set;

/// A `n` x `n` grid of quads over `[0, size]^2` at height `z`, texture coordinates
/// `scale * position + offset`, triangle `t`'s material `material(t)`.
pub fn grid(n: u32, size: f32, z: f32, uv: (f32, f32), material: impl Fn(u32) -> u32) -> Mesh {
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

pub fn masked(
    name: &str,
    cutoff: f32,
    alpha: f32,
    texture: Option<(usize, [Wrap; 2])>,
) -> Material {
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
pub fn edge_cases() -> Scene {
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
pub fn masked_rays(bvh: &FlatBvh) -> Vec<Ray> {
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
