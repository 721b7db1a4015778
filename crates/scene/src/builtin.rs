//! Procedural scenes, addressed as `builtin:NAME` (see [`builtin_names`]).

use std::collections::HashMap;
use std::path::PathBuf;

use glam::{Mat4, Quat, Vec2, Vec3};

use crate::error::{ErrorKind, SceneError};
use crate::{Camera, Instance, LoadOptions, Material, Mesh, Scene};

/// The builtin scenes, as `(name, description)`; load one as `builtin:NAME`.
/// Names with parameters are shown with their placeholders (`N`, `MESH`, `AxB`).
pub fn builtin_names() -> &'static [(&'static str, &'static str)] {
    &[
        (
            "cornell",
            "the default scene: a Cornell box (floor, ceiling, back, red left and green right walls, a ceiling light) with a short and a tall block; 36 triangles, with normals, materials and a camera",
        ),
        (
            "cornell-textured",
            "the Cornell box with textures: a checkered base colour and a metallic-roughness texture (rough to smooth, metal on every other row) on its white walls and blocks, a patterned emissive texture on its light; 36 triangles, with texture coordinates",
        ),
        (
            "spheres",
            "icospheres of five sizes (subdivision 2 to 5, instanced) on a ground grid; 35,328 triangles, with normals, materials and a camera",
        ),
        (
            "icosphere:N",
            "a closed unit icosphere with N subdivisions (0 to 10; 20*4^N triangles), watertight with shared vertices, with normals",
        ),
        (
            "degenerate",
            "degenerate-heavy, deterministic: zero-area and collinear triangles, slivers up to aspect 1e6 spanning the scene, coincident duplicates and coplanar overlapping triangles, plus a ground grid and a sphere so that rays hit things; 3,580 triangles",
        ),
        (
            "grid:MESH:AxB",
            "synthetic: A*B copies of one mesh, instanced (one mesh, A*B instances) on a grid in the XY plane, each slightly rotated and scaled; MESH is <shared scenes>/glb/MESH.glb, or scenes/MESH.glb in this repository (e.g. grid:igea:3x3 has 2,418,174 triangles)",
        ),
        (
            "hair[:KIND[:N]]",
            "synthetic hair: a head (an icosphere of 1,280 triangles) with N strands (default 10,000) of curves of KIND: round-linear, flat-linear, round-bezier or round-bspline (the default), nine linear or seven cubic segments each; or tubes: the round-linear strands as 8-sided tubes of triangles",
        ),
        (
            "moving:MESH",
            "synthetic motion: two copies of one mesh side by side, the left one still, the right one moving right by a third of its size while it turns 30 degrees about +Y over one second (a LINEAR node animation, for `render --shutter 0,1`); MESH as for grid",
        ),
    ]
}

/// Loads `builtin:NAME` (`name` without the prefix; `spec` is the whole spec, for errors).
pub(crate) fn load_builtin(
    name: &str,
    spec: &str,
    opts: &LoadOptions,
) -> Result<Scene, SceneError> {
    let bad = |msg: String| SceneError::new(spec, ErrorKind::Spec(msg));
    let scene = match name {
        "cornell" => cornell(),
        "cornell-textured" => cornell_textured(),
        "spheres" => spheres(),
        "degenerate" => degenerate(),
        _ => {
            if let Some(n) = name.strip_prefix("icosphere:") {
                let n: u32 = n
                    .parse()
                    .map_err(|_| bad(format!("icosphere:{n}: N must be a whole number")))?;
                if n > 10 {
                    return Err(bad(format!(
                        "icosphere:{n}: at most 10 subdivisions (20,971,520 triangles)"
                    )));
                }
                let mut mesh = icosphere(n);
                mesh.name = format!("icosphere {n}");
                Scene {
                    name: format!("icosphere:{n}"),
                    description: format!(
                        "a closed unit icosphere with {n} subdivisions ({} triangles)",
                        mesh.len()
                    ),
                    synthetic: true,
                    meshes: vec![mesh],
                    instances: vec![Instance {
                        mesh: 0,
                        transform: Mat4::IDENTITY,
                    }],
                    ..Scene::default()
                }
            } else if let Some(rest) = name.strip_prefix("grid:") {
                grid(rest, spec, opts)?
            } else if let Some(rest) = name.strip_prefix("hair") {
                crate::hair::hair(rest.strip_prefix(':').unwrap_or(rest), spec)?
            } else if let Some(mesh) = name.strip_prefix("moving:") {
                moving_of(crate::load_gltf_file(&find_mesh(mesh, spec, opts)?)?, mesh)
            } else {
                let known: Vec<&str> = builtin_names().iter().map(|(n, _)| *n).collect();
                return Err(bad(format!(
                    "unknown builtin scene {name:?} (known: {})",
                    known.join(", ")
                )));
            }
        }
    };
    let mut scene = scene;
    scene.unify_attributes();
    scene.finish(spec)
}

/// A closed unit icosphere: the icosahedron with each triangle split in four `n` times,
/// vertices pushed onto the unit sphere. Vertices are shared (watertight), triangles wind
/// counter-clockwise seen from outside, normals are the positions.
pub fn icosphere(n: u32) -> Mesh {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut positions: Vec<Vec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|&p| Vec3::from(p).normalize())
    .collect();
    let mut indices: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..n {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::with_capacity(indices.len() * 3 / 2);
        let mut next = Vec::with_capacity(indices.len() * 4);
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<Vec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                let p = ((positions[a as usize] + positions[b as usize]) * 0.5).normalize();
                positions.push(p);
                (positions.len() - 1) as u32
            })
        };
        for &[a, b, c] in &indices {
            let ab = midpoint(a, b, &mut positions);
            let bc = midpoint(b, c, &mut positions);
            let ca = midpoint(c, a, &mut positions);
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        indices = next;
    }
    Mesh {
        name: format!("icosphere {n}"),
        normals: positions.clone(),
        positions,
        indices,
        ..Mesh::default()
    }
}

/// Appends a quad `a b c d` (in order around its edge) facing `normal`, with flat normals.
fn quad(m: &mut Mesh, q: [Vec3; 4], normal: Vec3, material: u32) {
    let base = m.positions.len() as u32;
    let [a, b, c, _] = q;
    let flip = (b - a).cross(c - a).dot(normal) < 0.0;
    m.positions.extend_from_slice(&q);
    m.normals.extend_from_slice(&[normal; 4]);
    let tris = if flip {
        [[0, 2, 1], [0, 3, 2]]
    } else {
        [[0, 1, 2], [0, 2, 3]]
    };
    for t in tris {
        m.indices.push(t.map(|i| i + base));
        m.materials.push(material);
    }
}

/// Appends the unit cube `[-0.5, 0.5]^3` placed by `xf`, faces outward.
fn cube(m: &mut Mesh, xf: Mat4, material: u32) {
    let nm = xf.inverse().transpose();
    for axis in 0..3 {
        for sign in [-1.0f32, 1.0] {
            let mut n = Vec3::ZERO;
            n[axis] = sign;
            let (u, v) = (Vec3::AXES[(axis + 1) % 3], Vec3::AXES[(axis + 2) % 3]);
            let c = n * 0.5;
            let q = [
                c - u * 0.5 - v * 0.5,
                c + u * 0.5 - v * 0.5,
                c + u * 0.5 + v * 0.5,
                c - u * 0.5 + v * 0.5,
            ]
            .map(|p| xf.transform_point3(p));
            quad(m, q, nm.transform_vector3(n).normalize(), material);
        }
    }
}

fn material(name: &str, rgb: [f32; 3]) -> Material {
    Material::opaque(name, Vec3::from(rgb).extend(1.0))
}

/// The Cornell box: the room is `[-1, 1] x [0, 2] x [-1, 1]`, open towards +z.
fn cornell() -> Scene {
    let materials = vec![
        material("white", [0.73, 0.73, 0.73]),
        material("red", [0.65, 0.05, 0.05]),
        material("green", [0.12, 0.45, 0.15]),
        // Emitting about what the classic Cornell box's light does, over its smaller area.
        material("light", [1.0, 1.0, 1.0]).with_emissive(Vec3::new(17.0, 12.0, 4.0)),
    ];
    let (white, red, green, light) = (0, 1, 2, 3);
    let mut m = Mesh {
        name: "cornell box".into(),
        ..Mesh::default()
    };
    let p = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    // Walls face into the room.
    quad(
        &mut m,
        [
            p(-1., 0., -1.),
            p(1., 0., -1.),
            p(1., 0., 1.),
            p(-1., 0., 1.),
        ],
        Vec3::Y,
        white,
    );
    quad(
        &mut m,
        [
            p(-1., 2., -1.),
            p(1., 2., -1.),
            p(1., 2., 1.),
            p(-1., 2., 1.),
        ],
        Vec3::NEG_Y,
        white,
    );
    quad(
        &mut m,
        [
            p(-1., 0., -1.),
            p(1., 0., -1.),
            p(1., 2., -1.),
            p(-1., 2., -1.),
        ],
        Vec3::Z,
        white,
    );
    quad(
        &mut m,
        [
            p(-1., 0., -1.),
            p(-1., 0., 1.),
            p(-1., 2., 1.),
            p(-1., 2., -1.),
        ],
        Vec3::X,
        red,
    );
    quad(
        &mut m,
        [p(1., 0., -1.), p(1., 0., 1.), p(1., 2., 1.), p(1., 2., -1.)],
        Vec3::NEG_X,
        green,
    );
    // The light, just below the ceiling, facing down.
    let (l, y) = (0.25, 1.98);
    quad(
        &mut m,
        [p(-l, y, -l), p(l, y, -l), p(l, y, l), p(-l, y, l)],
        Vec3::NEG_Y,
        light,
    );
    // A short block (front right) and a tall one (back left).
    let short = Mat4::from_scale_rotation_translation(
        Vec3::splat(0.6),
        Quat::from_rotation_y((-17f32).to_radians()),
        Vec3::new(0.33, 0.3, 0.3),
    );
    let tall = Mat4::from_scale_rotation_translation(
        Vec3::new(0.6, 1.2, 0.6),
        Quat::from_rotation_y(17f32.to_radians()),
        Vec3::new(-0.35, 0.6, -0.3),
    );
    cube(&mut m, short, white);
    cube(&mut m, tall, white);
    Scene {
        name: "cornell".into(),
        description: "a Cornell box with two blocks (procedural)".into(),
        synthetic: true,
        meshes: vec![m],
        instances: vec![Instance {
            mesh: 0,
            transform: Mat4::IDENTITY,
        }],
        materials,
        camera: Some(Camera {
            eye: Vec3::new(0.0, 1.0, 3.9),
            target: Vec3::new(0.0, 1.0, 0.0),
            fov_y_deg: 40.0,
        }),
        ..Scene::default()
    }
}

/// An `n` x `n` texture whose texel (x, y) is `f(x, y)`.
fn texture(name: &str, n: u32, f: impl Fn(u32, u32) -> [u8; 4]) -> crate::Texture {
    crate::Texture {
        name: name.into(),
        width: n,
        height: n,
        rgba: (0..n * n).flat_map(|i| f(i % n, i / n)).collect(),
    }
}

/// The Cornell box with a texture in each slot the path tracer reads: a checkered base
/// colour and a metallic-roughness texture on the white material, a glowing pattern on
/// the light; coordinates from the positions (`1.5 (x + z, y)`), in every wrap mode.
fn cornell_textured() -> Scene {
    use crate::{TextureRef, Wrap};
    let mut scene = cornell();
    scene.name = "cornell-textured".into();
    scene.description = "the Cornell box with textures (procedural)".into();
    scene.textures = vec![
        texture("checker", 8, |x, y| match (x + y) % 2 {
            0 => [240, 240, 240, 255],
            _ => [60, 90, 200, 255],
        }),
        // Roughness in G from 0.1 to 1 along x, metal in B on every other row.
        texture("metal-rough", 4, |x, y| {
            [0, 25 + 76 * x as u8, if y % 2 == 0 { 255 } else { 0 }, 255]
        }),
        texture("glow", 2, |x, y| {
            let c = if x == y { 255 } else { 40 };
            [c, c, c, 255]
        }),
    ];
    let r = |texture: usize, wrap: [Wrap; 2]| Some(TextureRef { texture, wrap });
    let white = &mut scene.materials[0];
    white.base_color_texture = r(0, [Wrap::Repeat, Wrap::MirroredRepeat]);
    white.metallic_roughness_texture = r(1, [Wrap::Repeat, Wrap::ClampToEdge]);
    white.metallic = 1.0;
    scene.materials[3].emissive_texture = r(2, [Wrap::Repeat; 2]);
    for mesh in &mut scene.meshes {
        mesh.texcoords = (mesh.positions.iter())
            .map(|p| Vec2::new(p.x + p.z, p.y) * 1.5)
            .collect();
    }
    scene.attributes.texcoords = true;
    scene
}

/// A flat grid of `n x n` quads over `[-half, half]^2` at height `y`, facing +y.
fn ground(half: f32, n: u32, y: f32, material: u32) -> Mesh {
    let mut m = Mesh {
        name: "ground".into(),
        ..Mesh::default()
    };
    let step = 2.0 * half / n as f32;
    for i in 0..n {
        for j in 0..n {
            let (x0, z0) = (-half + i as f32 * step, -half + j as f32 * step);
            let (x1, z1) = (x0 + step, z0 + step);
            quad(
                &mut m,
                [
                    Vec3::new(x0, y, z0),
                    Vec3::new(x0, y, z1),
                    Vec3::new(x1, y, z1),
                    Vec3::new(x1, y, z0),
                ],
                Vec3::Y,
                material,
            );
        }
    }
    m
}

fn spheres() -> Scene {
    let materials = vec![
        material("ground", [0.5, 0.5, 0.5]),
        material("orange", [0.9, 0.5, 0.1]),
        material("blue", [0.15, 0.3, 0.8]),
        material("green", [0.2, 0.7, 0.3]),
        material("red", [0.8, 0.15, 0.15]),
    ];
    let mut meshes = vec![ground(8.0, 8, 0.0, 0)];
    for (level, mat) in [(5u32, 1u32), (4, 2), (3, 3), (2, 4)] {
        let mut s = icosphere(level);
        s.materials = vec![mat; s.len()];
        meshes.push(s);
    }
    let place = |mesh: usize, r: f32, x: f32, z: f32| Instance {
        mesh,
        transform: Mat4::from_scale_rotation_translation(
            Vec3::splat(r),
            Quat::IDENTITY,
            Vec3::new(x, r, z),
        ),
    };
    let instances = vec![
        Instance {
            mesh: 0,
            transform: Mat4::IDENTITY,
        },
        place(1, 1.5, 0.0, 0.0),
        place(2, 0.8, -2.6, 0.6),
        place(2, 0.8, 2.5, -0.8),
        place(3, 0.45, -1.2, 2.2),
        place(3, 0.45, 1.4, 2.0),
        place(3, 0.45, 3.5, 1.5),
        place(4, 0.25, 0.2, 2.8),
        place(4, 0.25, -3.4, 2.4),
    ];
    Scene {
        name: "spheres".into(),
        description: "icospheres of five sizes on a ground grid (procedural)".into(),
        synthetic: true,
        meshes,
        instances,
        materials,
        camera: Some(Camera {
            eye: Vec3::new(0.0, 3.0, 9.0),
            target: Vec3::new(0.0, 1.0, 0.0),
            fov_y_deg: 40.0,
        }),
        ..Scene::default()
    }
}

/// SplitMix64: a tiny deterministic generator (same sequence on every platform).
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Self {
        Rng(seed)
    }
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in `[0, 1)`.
    pub(crate) fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    /// Uniform in `[lo, hi)`.
    pub(crate) fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }
    fn vec(&mut self, lo: Vec3, hi: Vec3) -> Vec3 {
        Vec3::new(
            self.range(lo.x, hi.x),
            self.range(lo.y, hi.y),
            self.range(lo.z, hi.z),
        )
    }
    fn unit(&mut self) -> Vec3 {
        loop {
            let v = self.vec(Vec3::splat(-1.0), Vec3::splat(1.0));
            let l = v.length_squared();
            if l > 1e-4 && l <= 1.0 {
                return v / l.sqrt();
            }
        }
    }
}

/// The degenerate-heavy scene. Everything in one mesh, no attributes.
fn degenerate() -> Scene {
    let mut rng = Rng::new(0x5EED_DE6E);
    let mut m = Mesh {
        name: "degenerate".into(),
        ..Mesh::default()
    };
    let tri = |m: &mut Mesh, a: Vec3, b: Vec3, c: Vec3| {
        let base = m.positions.len() as u32;
        m.positions.extend_from_slice(&[a, b, c]);
        m.indices.push([base, base + 1, base + 2]);
    };
    let lo = Vec3::new(-10.0, 0.0, -10.0);
    let hi = Vec3::new(10.0, 8.0, 10.0);

    // Normal geometry: a ground grid (200) and a sphere (1,280).
    let g = ground(10.0, 10, 0.0, 0);
    let s = icosphere(3);
    for (mesh, xf) in [
        (&g, Mat4::IDENTITY),
        (
            &s,
            Mat4::from_scale_rotation_translation(
                Vec3::splat(2.0),
                Quat::IDENTITY,
                Vec3::new(0.0, 2.0, 0.0),
            ),
        ),
    ] {
        let base = m.positions.len() as u32;
        m.positions
            .extend(mesh.positions.iter().map(|&p| xf.transform_point3(p)));
        m.indices
            .extend(mesh.indices.iter().map(|t| t.map(|i| i + base)));
    }
    // Zero-area: 150 point triangles, 150 with two equal corners.
    for _ in 0..150 {
        let p = rng.vec(lo, hi);
        tri(&mut m, p, p, p);
    }
    for _ in 0..150 {
        let (p, q) = (rng.vec(lo, hi), rng.vec(lo, hi));
        tri(&mut m, p, q, p);
    }
    // Collinear, distinct corners: 100 exactly (small integers), 100 along random lines.
    for _ in 0..100 {
        let p = rng.vec(lo, hi).round();
        let d = rng.vec(Vec3::splat(-2.0), Vec3::splat(2.0)).round();
        let d = if d == Vec3::ZERO { Vec3::X } else { d };
        let (t1, t2) = (
            1.0 + (rng.f32() * 3.0).floor(),
            -1.0 - (rng.f32() * 3.0).floor(),
        );
        tri(&mut m, p, p + d * t1, p + d * t2);
    }
    for _ in 0..100 {
        let p = rng.vec(lo, hi);
        let d = rng.unit() * rng.range(0.5, 10.0);
        tri(
            &mut m,
            p,
            p + d * rng.range(0.1, 1.0),
            p - d * rng.range(0.1, 1.0),
        );
    }
    // Slivers spanning the scene, aspect log-uniform in [10, 1e6].
    for _ in 0..300 {
        let a = rng.vec(lo, hi);
        let b = rng.vec(lo, hi);
        let len = (b - a).length();
        let aspect = 10f32.powf(rng.range(1.0, 6.0));
        let side = (b - a).cross(rng.unit()).normalize_or_zero();
        let side = if side == Vec3::ZERO { Vec3::Y } else { side };
        let apex = (a + b) * 0.5 + side * (len / aspect);
        tri(&mut m, a, b, apex);
    }
    // Coincident: 30 triangles repeated 10 times with their own vertices, 10 repeated 10
    // times sharing vertices.
    for _ in 0..30 {
        let c = rng.vec(lo, hi);
        let (a, b, d) = (c + rng.unit(), c + rng.unit(), c + rng.unit());
        for _ in 0..10 {
            tri(&mut m, a, b, d);
        }
    }
    for _ in 0..10 {
        let c = rng.vec(lo, hi);
        let base = m.positions.len() as u32;
        m.positions
            .extend_from_slice(&[c + rng.unit(), c + rng.unit(), c + rng.unit()]);
        for _ in 0..10 {
            m.indices.push([base, base + 1, base + 2]);
        }
    }
    // Coplanar overlapping: 600 in the wall plane z = -3, 300 lying on the ground plane.
    for _ in 0..600 {
        let c = Vec2::new(rng.range(-5.0, 5.0), rng.range(0.0, 8.0));
        let pts: Vec<Vec3> = (0..3)
            .map(|_| (c + Vec2::new(rng.range(-2.0, 2.0), rng.range(-2.0, 2.0))).extend(-3.0))
            .collect();
        tri(&mut m, pts[0], pts[1], pts[2]);
    }
    for _ in 0..300 {
        let c = Vec2::new(rng.range(-8.0, 8.0), rng.range(-8.0, 8.0));
        let pts: Vec<Vec3> = (0..3)
            .map(|_| {
                let q = c + Vec2::new(rng.range(-1.5, 1.5), rng.range(-1.5, 1.5));
                Vec3::new(q.x, 0.0, q.y)
            })
            .collect();
        tri(&mut m, pts[0], pts[1], pts[2]);
    }
    Scene {
        name: "degenerate".into(),
        description: "degenerate-heavy triangles (procedural, deterministic)".into(),
        synthetic: true,
        meshes: vec![m],
        instances: vec![Instance {
            mesh: 0,
            transform: Mat4::IDENTITY,
        }],
        camera: Some(Camera {
            eye: Vec3::new(0.0, 7.0, 18.0),
            target: Vec3::new(0.0, 2.0, 0.0),
            fov_y_deg: 50.0,
        }),
        ..Scene::default()
    }
}

/// Where `builtin:grid:MESH:...` finds MESH: the `glb/MESH.glb` of the folder `opts`
/// names, then the repository's `scenes/MESH.glb`.
fn grid_mesh_candidates(mesh: &str, opts: &LoadOptions) -> Vec<PathBuf> {
    let file = format!("{mesh}.glb");
    let mut out = Vec::new();
    if let Some(d) = &opts.meshes {
        out.push(d.join("glb").join(&file));
    }
    if let Some(d) = crate::repo_scenes_dir() {
        out.push(d.join(&file));
    }
    out
}

/// `grid:MESH:AxB`.
fn grid(rest: &str, spec: &str, opts: &LoadOptions) -> Result<Scene, SceneError> {
    let bad = |msg: String| SceneError::new(spec, ErrorKind::Spec(msg));
    let Some((mesh, dims)) = rest.rsplit_once(':') else {
        return Err(bad("expected grid:MESH:AxB, e.g. grid:igea:3x3".into()));
    };
    let dims_parsed = dims
        .split_once(['x', 'X'])
        .and_then(|(a, b)| Some((a.parse::<u32>().ok()?, b.parse::<u32>().ok()?)));
    let Some((a, b)) = dims_parsed.filter(|&(a, b)| a > 0 && b > 0) else {
        return Err(bad(format!(
            "grid size {dims:?}: expected AxB with positive whole numbers, e.g. 3x3"
        )));
    };
    if a as u64 * b as u64 > 1_000_000 {
        return Err(bad(format!("grid {a}x{b}: at most 1,000,000 copies")));
    }
    let src = crate::load_gltf_file(&find_mesh(mesh, spec, opts)?)?;
    Ok(grid_of(src, mesh, a, b))
}

/// The file of a builtin's MESH ([`grid_mesh_candidates`]).
fn find_mesh(mesh: &str, spec: &str, opts: &LoadOptions) -> Result<PathBuf, SceneError> {
    let bad = |msg: String| SceneError::new(spec, ErrorKind::Spec(msg));
    if mesh.is_empty() || mesh.contains(['/', '\\']) || mesh.contains("..") {
        return Err(bad(format!(
            "mesh {mesh:?}: give a file stem from the shared glb/ folder, e.g. igea"
        )));
    }
    let candidates = grid_mesh_candidates(mesh, opts);
    let Some(path) = candidates.iter().find(|p| p.is_file()) else {
        let looked: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
        return Err(bad(format!(
            "mesh {mesh:?} not found (looked for {})",
            if looked.is_empty() {
                "no folder: name the shared scenes folder, LoadOptions::meshes".to_string()
            } else {
                looked.join(" and ")
            }
        )));
    };
    Ok(path.clone())
}

/// `moving:MESH`: `src` twice, centred side by side along +x; the right copy's node moves
/// right by a third of the mesh's size and turns 30 degrees about +Y in one second.
pub(crate) fn moving_of(src: Scene, mesh_name: &str) -> Scene {
    use crate::animation::{
        Animation, AnimationNode, Channel, Interpolation, NodeTransform, Property,
    };
    let (lo, hi) = src.bounds();
    let center = (lo + hi) * 0.5;
    let size = (hi - lo).max_element().max(f32::MIN_POSITIVE);
    let half = Vec3::new(size * 0.65, 0.0, 0.0);
    // Node 0 carries the motion; every moving instance hangs from it.
    let mut nodes = vec![AnimationNode {
        gltf_node: 0,
        parent: None,
        local: NodeTransform::Trs {
            translation: half,
            rotation: Quat::IDENTITY,
            scale: Vec3::ONE,
        },
    }];
    let (mut instances, mut instance_nodes) = (Vec::new(), Vec::new());
    for (moves, offset) in [(false, -half), (true, Vec3::ZERO)] {
        for inst in &src.instances {
            let local = Mat4::from_translation(offset - center) * inst.transform;
            nodes.push(AnimationNode {
                gltf_node: nodes.len(),
                parent: moves.then_some(0),
                local: NodeTransform::Matrix(local),
            });
            instance_nodes.push(nodes.len() - 1);
            let parent = if moves {
                Mat4::from_translation(half)
            } else {
                Mat4::IDENTITY
            };
            instances.push(Instance {
                mesh: inst.mesh,
                transform: parent * local,
            });
        }
    }
    let keys = |a: glam::Vec4, b: glam::Vec4| vec![a, b];
    let channels = [
        (
            Property::Translation,
            keys(half.extend(0.0), (half + Vec3::X * size / 3.0).extend(0.0)),
        ),
        (
            Property::Rotation,
            keys(
                Quat::IDENTITY.into(),
                Quat::from_rotation_y(30f32.to_radians()).into(),
            ),
        ),
    ]
    .into_iter()
    .map(|(p, v)| Channel::new(0, p, Interpolation::Linear, vec![0.0, 1.0], v))
    .collect::<Result<Vec<_>, _>>()
    .expect("two finite keys in order");
    let tris = src.triangle_count();
    Scene {
        name: format!("moving:{mesh_name}"),
        description: format!(
            "synthetic motion: {mesh_name} ({tris} triangles) twice, the left copy still, the right one moving and turning over one second"
        ),
        synthetic: true,
        instances,
        camera: None,
        animation: Some(Animation {
            nodes,
            instance_nodes,
            channels,
            globals: Vec::new(),
            skins: Vec::new(),
            morphs: Vec::new(),
        }),
        ..src
    }
}

/// `a x b` copies of every instance of `src`, centred on the origin, on a grid in the XY
/// plane (a columns along +x, b rows along +y), each rotated by up to ±15° about Y and
/// scaled by 0.9 to 1.1 (deterministic).
pub(crate) fn grid_of(src: Scene, mesh_name: &str, a: u32, b: u32) -> Scene {
    let (lo, hi) = src.bounds();
    let center = (lo + hi) * 0.5;
    let size = (hi - lo).max_element().max(f32::MIN_POSITIVE);
    let spacing = size * 1.3;
    let mut rng = Rng::new(0x6121_D5EE_D000 ^ ((a as u64) << 32 | b as u64));
    let mut instances = Vec::with_capacity(src.instances.len() * a as usize * b as usize);
    for j in 0..b {
        for i in 0..a {
            let offset = Vec3::new(
                (i as f32 - (a - 1) as f32 * 0.5) * spacing,
                (j as f32 - (b - 1) as f32 * 0.5) * spacing,
                0.0,
            );
            let rot = Quat::from_rotation_y(rng.range(-15.0, 15.0).to_radians());
            let scale = rng.range(0.9, 1.1);
            let cell = Mat4::from_scale_rotation_translation(Vec3::splat(scale), rot, offset)
                * Mat4::from_translation(-center);
            for inst in &src.instances {
                instances.push(Instance {
                    mesh: inst.mesh,
                    transform: cell * inst.transform,
                });
            }
        }
    }
    let per_copy = src.triangle_count();
    let copies = a as usize * b as usize;
    Scene {
        name: format!("grid:{mesh_name}:{a}x{b}"),
        description: format!(
            "synthetic: a {a}x{b} grid of {copies} instanced copies of {mesh_name} ({per_copy} triangles each, {} in all), each slightly rotated and scaled",
            per_copy * copies
        ),
        synthetic: true,
        instances,
        camera: None,
        animation: None,
        ..src
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn watertight(m: &Mesh) -> bool {
        let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
        for t in &m.indices {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *edges.entry((a, b)).or_default() += 1;
            }
        }
        edges
            .iter()
            .all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
    }

    #[test]
    fn icospheres_are_closed_and_outward() {
        for n in 0..4 {
            let m = icosphere(n);
            assert_eq!(m.len(), 20 * 4usize.pow(n));
            assert_eq!(m.positions.len(), 10 * 4usize.pow(n) + 2);
            assert!(watertight(&m), "icosphere {n} is not watertight");
            for t in &m.indices {
                let [a, b, c] = t.map(|i| m.positions[i as usize]);
                assert!((b - a).cross(c - a).dot(a + b + c) > 0.0, "inward triangle");
            }
        }
    }

    #[test]
    fn builtins_have_expected_sizes() {
        let c =
            load_builtin("cornell", "builtin:cornell", &LoadOptions::default()).expect("cornell");
        assert_eq!(c.triangle_count(), 36);
        assert!(c.camera.is_some() && c.attributes.normals && c.attributes.materials);
        let s =
            load_builtin("spheres", "builtin:spheres", &LoadOptions::default()).expect("spheres");
        assert_eq!(s.triangle_count(), 35_328);
        let d = load_builtin("degenerate", "builtin:degenerate", &LoadOptions::default())
            .expect("degenerate");
        assert_eq!(d.triangle_count(), 3_580);
        assert_eq!(
            d,
            load_builtin("degenerate", "builtin:degenerate", &LoadOptions::default())
                .expect("again")
        );
        for sc in [&c, &s, &d] {
            sc.check_invariants().expect("invariants");
            sc.flatten().triangles().expect("valid triangles");
        }
    }

    #[test]
    fn cornell_walls_face_the_camera_side() {
        let c =
            load_builtin("cornell", "builtin:cornell", &LoadOptions::default()).expect("cornell");
        let m = &c.meshes[0];
        // The back wall (triangles 4 and 5) faces +z, towards the camera.
        for t in &m.indices[4..6] {
            let [a, b, cc] = t.map(|i| m.positions[i as usize]);
            assert!((b - a).cross(cc - a).z > 0.0);
        }
    }

    #[test]
    fn degenerate_has_slivers_up_to_1e6() {
        let d = degenerate();
        let m = &d.meshes[0];
        let mut max_aspect = 0f32;
        let mut zero = 0;
        for t in &m.indices {
            let [a, b, c] = t.map(|i| m.positions[i as usize]);
            let area2 = (b - a).cross(c - a).length();
            let longest = (b - a).length().max((c - b).length()).max((a - c).length());
            if area2 == 0.0 {
                zero += 1;
            } else {
                max_aspect = max_aspect.max(longest * longest / area2);
            }
        }
        assert!(zero >= 400, "{zero} zero-area triangles");
        assert!(max_aspect > 1e5, "max aspect {max_aspect}");
    }

    #[test]
    fn bad_builtin_specs() {
        for s in [
            "nope",
            "icosphere:x",
            "icosphere:11",
            "grid:igea",
            "grid:igea:0x3",
            "grid:../x:2x2",
            "grid:no_such_mesh:2x2",
        ] {
            let e = load_builtin(s, &format!("builtin:{s}"), &LoadOptions::default()).expect_err(s);
            assert!(e.to_string().starts_with(&format!("builtin:{s}: ")), "{e}");
        }
    }
}
