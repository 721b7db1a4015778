//! What the parity tests share: the scenes they run on, their rays, the bytewise
//! comparison and a small deterministic generator. Used by `tests/conformance.rs`,
//! `tests/wgpu_api.rs` and, through `#[path]`, by `crates/vk/tests/vk_api.rs`, so every
//! backend is checked on the same scenes.
#![allow(dead_code)]

pub mod masked;

use bvhtrace_core::{
    BuildOptions, BuilderKind, Counters, FlatBvh, Hit, InstancedBvh, Ray, TraceOptions, Triangle,
    trace_rays,
};
use bvhtrace_scene::{Camera, shared_scenes_dir};
use glam::Vec3;

/// A small deterministic generator (SplitMix64).
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// A random unit vector (rejection sampling in the unit ball).
    pub fn unit_vector(&mut self) -> Vec3 {
        loop {
            let v = Vec3::new(self.f32(), self.f32(), self.f32()) * 2.0 - Vec3::ONE;
            let l = v.length_squared();
            if l > 1e-4 && l <= 1.0 {
                return v / l.sqrt();
            }
        }
    }
}

/// The BVH of one triangle in the z = 0 plane, corners (-1, -1), (1, -1), (0, 1): for
/// tests about the API rather than the walk.
pub fn one_triangle() -> FlatBvh {
    let tris = vec![[
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ]];
    FlatBvh::build(&tris, &BuildOptions::default()).expect("build")
}

/// Walls across the x axis at `xs`, one triangle each, built with midpoint splits and one
/// triangle per leaf: each split takes off few triangles, so the tree is as deep as there
/// are walls.
fn walls_along_x(xs: impl Iterator<Item = f32>) -> FlatBvh {
    let tris: Vec<Triangle> = xs
        .map(|x| {
            let p = Vec3::new(x, 0.0, 0.0);
            [
                p + Vec3::new(0.0, -1.0, -1.0),
                p + Vec3::new(0.0, 1.0, -1.0),
                p + Vec3::new(0.0, 0.0, 1.0),
            ]
        })
        .collect();
    let opts = BuildOptions {
        builder: bvhtrace_core::BuilderKind::Midpoint,
        max_depth: 1000,
        max_leaf_size: 1,
        ..Default::default()
    };
    FlatBvh::build(&tris, &opts).expect("build")
}

/// A tree deeper than the full stack's 64 entries: 120 triangles at exponentially spaced
/// positions along x, midpoint splits, one triangle per leaf.
pub fn deep_tree() -> FlatBvh {
    walls_along_x((0..120).map(|i| 2f32.powi(i - 60)))
}

/// A tree whose wide layout is deeper than the wide walk's stack
/// (`bvhtrace_engine::walks::WIDE_STACK_GROUPS` groups): [`DEEP_WIDE_TRIANGLES`] triangles along
/// x ([`deep_wide_x`]), midpoint splits, one triangle per leaf. Each binary level splits
/// off one triangle, so a wide node takes seven leaves and one interior child, and the wide
/// tree is about a seventh as deep as the binary one. Built with its wide layout.
pub fn deep_wide_tree() -> FlatBvh {
    walls_along_x((0..DEEP_WIDE_TRIANGLES).map(deep_wide_x)).with_wide()
}

/// Triangles of [`deep_wide_tree`]: as many as f32's exponents hold from 2^-120.
pub const DEEP_WIDE_TRIANGLES: i32 = 247;

/// The x of [`deep_wide_tree`]'s triangle `i`: `2^(i - 120)`, a little less by a factor
/// that grows towards 1 with `i`, so that every triangle lies strictly below the midpoint
/// of those up to the next one (plain powers of two fall on it, and the midpoint split
/// would then take two at a time).
pub fn deep_wide_x(i: i32) -> f32 {
    2f32.powi(i - 120) * (1.0 - (DEEP_WIDE_TRIANGLES - i) as f32 * 2f32.powi(-24))
}

/// Rays through [`deep_wide_tree`]: along +x from before each triangle (through all those
/// after it), with intervals ending just past one, from the far end back along -x, and
/// past the triangles' corners.
pub fn deep_wide_rays() -> Vec<Ray> {
    let mut rays = Vec::new();
    for i in 0..DEEP_WIDE_TRIANGLES {
        let x = deep_wide_x(i);
        rays.push(Ray::new(Vec3::new(x * 0.5, 0.1, 0.0), Vec3::X));
        rays.push(Ray::with_interval(
            Vec3::new(-1.0, 0.0, 0.0),
            Vec3::X,
            0.0,
            1.0 + x,
        ));
    }
    let far = 2f32.powi(127);
    for (y, z) in [(0.9f32, 0.9f32), (-0.9, 0.8), (0.95, -0.0), (0.1, 0.0)] {
        for dir in [Vec3::X, -Vec3::X, Vec3::new(1.0, 1e-9, -1e-9)] {
            let o = Vec3::new(if dir.x > 0.0 { -1.0 } else { far }, y, z);
            rays.push(Ray::new(o, dir));
            rays.push(Ray::with_interval(o, dir, 0.5, 1.0 + 2f32.powi(-20)));
        }
    }
    rays
}

/// Rays along the x axis of [`deep_tree`] (`n` triangles at `2^(i - n / 2)`): from just before each triangle, up to just past it, and rays in both
/// directions past the triangles' corners and edges.
pub fn deep_tree_rays(n: i32) -> Vec<Ray> {
    let mut rays = Vec::new();
    for i in 0..n {
        let x = 2f32.powi(i - n / 2);
        rays.push(Ray::new(Vec3::new(x - 1e-30, 0.1, 0.0), Vec3::X));
        rays.push(Ray::with_interval(
            Vec3::new(-1.0, 0.0, 0.0),
            Vec3::X,
            0.0,
            1.0 + x,
        ));
    }
    for (y, z) in [(0.9f32, 0.9f32), (-0.9, 0.8), (0.95, -0.0), (0.1, 0.0)] {
        for dir in [Vec3::X, -Vec3::X, Vec3::new(1.0, 1e-9, -1e-9)] {
            let o = Vec3::new(if dir.x > 0.0 { -1.0 } else { 2.0 }, y, z);
            rays.push(Ray::new(o, dir));
            rays.push(Ray::with_interval(o, dir, 0.5, 1.0 + 2f32.powi(-20)));
        }
    }
    rays
}

/// One scene of the parity tests.
pub struct SceneCase {
    pub name: String,
    pub bvh: FlatBvh,
    /// The triangles by primitive index (for the oracle).
    pub tris: Vec<Triangle>,
}

/// Loads `spec` and flattens its triangles (by primitive id), or prints SKIP and returns
/// `None` when it cannot be read.
fn load_or_skip(spec: &str, name: &str) -> Option<(bvhtrace_scene::Scene, Vec<Triangle>)> {
    let scene = match bvhtrace_scene::load(spec) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("SKIP scene {name}: {e}");
            return None;
        }
    };
    let tris = scene
        .flattened_triangles()
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    Some((scene, tris))
}

/// Loads and builds `spec`, or prints SKIP and returns `None` when it cannot be read.
pub fn load_scene(spec: &str, name: &str) -> Option<SceneCase> {
    load_scene_with(spec, name, &BuildOptions::default())
}

/// [`load_scene`] with other build options.
pub fn load_scene_with(spec: &str, name: &str, opts: &BuildOptions) -> Option<SceneCase> {
    let (_, tris) = load_or_skip(spec, name)?;
    let bvh = FlatBvh::build(&tris, opts).unwrap_or_else(|e| panic!("{name}: {e}"));
    Some(SceneCase {
        name: name.to_string(),
        bvh,
        tris,
    })
}

/// Loads `spec` and builds it as a two-level BVH (one BVH per mesh, a top level over its
/// instances), `tris` its flattened triangles by primitive id; `None` (SKIP printed) when
/// it cannot be read.
pub fn load_instanced_scene(spec: &str, name: &str) -> Option<SceneCase> {
    load_instanced_scene_with(spec, name, &BuildOptions::default())
}

/// [`load_instanced_scene`] with other build options (for the meshes' trees).
pub fn load_instanced_scene_with(spec: &str, name: &str, opts: &BuildOptions) -> Option<SceneCase> {
    let (scene, tris) = load_or_skip(spec, name)?;
    let bvh = scene
        .instanced_bvh(opts)
        .unwrap_or_else(|e| panic!("{name}: {e}"))
        .bvh()
        .clone();
    Some(SceneCase {
        name: format!("{name} (two levels)"),
        bvh,
        tris,
    })
}

/// The parity scenes: shared meshes when present (a small one, `bunny_69k`, the bunny at
/// 1e-3 scale), the degenerate-heavy builtin and the Cornell box, the builtins in two
/// levels, and SBVH trees (one level and two).
pub fn parity_scenes() -> Vec<SceneCase> {
    let mut out = Vec::new();
    match shared_scenes_dir().map(|d| d.join("glb")) {
        Some(dir) => {
            let p = |f: &str| dir.join(f).to_string_lossy().into_owned();
            out.extend(load_scene(&p("suzanne_968.glb"), "suzanne_968"));
            out.extend(load_scene(&p("bunny_69k.glb"), "bunny_69k"));
            out.extend(load_scene(
                &format!("{}#scale=1e-3", p("bunny_69k.glb")),
                "bunny_69k#scale=1e-3",
            ));
        }
        None => eprintln!("SKIP the shared .glb scenes: no shared/scenes folder found"),
    }
    out.extend(load_scene("builtin:degenerate", "builtin:degenerate"));
    out.extend(load_scene("builtin:cornell", "builtin:cornell"));
    // Spatial splits: leaves that share triangles, boxes clipped to split planes (a
    // quarter more references than triangles here), in one level and two.
    let sbvh = BuildOptions::with_builder(BuilderKind::Sbvh);
    out.extend(load_scene_with(
        "builtin:degenerate",
        "builtin:degenerate (sbvh)",
        &sbvh,
    ));
    // Two levels: five meshes instanced on a ground grid, and a grid of rotated, scaled
    // copies of one mesh, mirrored by the scene suffix.
    out.extend(load_instanced_scene("builtin:spheres", "builtin:spheres"));
    out.extend(load_instanced_scene(
        "builtin:grid:icosphere:4x3#scale=-1#offset=3,0,0",
        "builtin:grid:icosphere:4x3 mirrored",
    ));
    out.extend(load_instanced_scene_with(
        "builtin:spheres",
        "builtin:spheres (sbvh)",
        &sbvh,
    ));
    out
}

/// 128x96 primary rays, random rays from inside the bounds (full and finite intervals),
/// axis-parallel rays with signed zeros, and invalid rays.
pub fn parity_rays(bvh: &FlatBvh) -> Vec<Ray> {
    let b = bvh.bounds();
    let (lo, hi) = (b.min, b.max);
    let size = hi - lo;
    let mut rays = Camera::frame(lo, hi, 128.0 / 96.0).rays(128, 96);
    let mut rng = Rng(7);
    for i in 0..3072 {
        let o = lo + size * Vec3::new(rng.f32(), rng.f32(), rng.f32());
        let d = rng.unit_vector();
        rays.push(if i % 3 == 0 {
            Ray::with_interval(o, d, 1e-4 * size.length(), size.length() * rng.f32())
        } else {
            Ray::new(o, d)
        });
    }
    for axis in 0..3 {
        for zero in [0.0f32, -0.0] {
            for i in 0..8 {
                let mut d = Vec3::splat(zero);
                d[axis] = if i % 2 == 0 { 1.0 } else { -1.0 };
                let mut o = lo + size * ((i as f32 + 0.5) / 8.0);
                o[axis] = if d[axis] > 0.0 {
                    lo[axis] - size[axis]
                } else {
                    hi[axis] + size[axis]
                };
                rays.push(Ray::new(o, d));
            }
        }
    }
    let eye = hi + size;
    let d = ((lo + hi) * 0.5 - eye).normalize();
    rays.extend([
        Ray::new(Vec3::new(f32::NAN, 0.0, 0.0), d),
        Ray::new(eye, Vec3::ZERO),
        Ray::with_interval(eye, d, 1.0, 0.5),
        Ray::with_interval(eye, d, f32::NEG_INFINITY, f32::INFINITY),
    ]);
    rays
}

/// Indices where two Pod slices differ bytewise.
pub fn differ<T: bytemuck::Pod>(a: &[T], b: &[T]) -> Vec<usize> {
    assert_eq!(a.len(), b.len());
    (0..a.len())
        .filter(|&i| bytemuck::bytes_of(&a[i]) != bytemuck::bytes_of(&b[i]))
        .collect()
}

/// The CPU twin's hits and counters for `opts`, counted.
pub fn cpu_counted(bvh: &FlatBvh, rays: &[Ray], opts: &TraceOptions) -> (Vec<Hit>, Vec<Counters>) {
    let out = trace_rays(bvh, rays, &opts.with_counters(true));
    (out.hits, out.counters.expect("counters asked for"))
}

/// How a tracer's hits (traced with counters and without) and counters differ bytewise
/// from the CPU twin's: a line for each that differs, naming `who` and the first ray.
pub fn differences(
    who: &str,
    rays: &[Ray],
    (hits, counters): (&[Hit], &[Counters]),
    plain_hits: &[Hit],
    (cpu_hits, cpu_counters): (&[Hit], &[Counters]),
) -> Vec<String> {
    let mut out = Vec::new();
    for (what, bad) in [
        ("hits", differ(hits, cpu_hits)),
        ("uncounted hits", differ(plain_hits, cpu_hits)),
        ("counters", differ(counters, cpu_counters)),
    ] {
        if let Some(&i) = bad.first() {
            out.push(format!(
                "{who}: {what}: {} rays differ; first {i}: ray {:?}, got {:?} {:?}, cpu {:?} {:?}",
                bad.len(),
                rays[i],
                hits[i],
                counters[i],
                cpu_hits[i],
                cpu_counters[i]
            ));
        }
    }
    out
}

/// The `k`th axis-parallel ray lying in a face of the box `bmin`..`bmax`: from outside
/// the scene's bounds `lo`..`hi`, from the box's min or max corner, along either sign of
/// one axis, with +0 or -0 in the other components. Its origin, direction and axis.
pub fn in_box_face(k: usize, bmin: Vec3, bmax: Vec3, lo: Vec3, hi: Vec3) -> (Vec3, Vec3, usize) {
    let axis = k % 3;
    let mut o = if k.is_multiple_of(2) { bmin } else { bmax };
    let sign = if k % 4 < 2 { 1.0 } else { -1.0 };
    o[axis] = if sign > 0.0 {
        lo[axis] - 1.0
    } else {
        hi[axis] + 1.0
    };
    let mut d = Vec3::splat(if k % 8 < 4 { 0.0 } else { -0.0 });
    d[axis] = sign;
    (o, d, axis)
}

/// The conformance suite's large ray set: 128x96 primary rays, random rays from inside
/// the bounds, axis-parallel rays with +0/-0 components, rays lying in the faces of node
/// boxes (and of the wide layout's child boxes), rays with finite and awkward intervals,
/// and invalid rays.
pub fn ray_set(bvh: &FlatBvh, seed: u64) -> Vec<Ray> {
    let b = bvh.bounds();
    let (lo, hi) = (b.min, b.max);
    let size = hi - lo;
    let center = (lo + hi) * 0.5;
    let mut rays = Camera::frame(lo, hi, 128.0 / 96.0).rays(128, 96);
    let mut rng = Rng(seed);
    let inside = |rng: &mut Rng| lo + size * Vec3::new(rng.f32(), rng.f32(), rng.f32());
    for _ in 0..4096 {
        rays.push(Ray::new(inside(&mut rng), rng.unit_vector()));
    }
    // Finite intervals (shadow-ray like): t_min > 0, t_max a fraction of the scene.
    for _ in 0..2048 {
        let o = inside(&mut rng);
        let d = rng.unit_vector();
        let t_max = size.length() * rng.f32();
        rays.push(Ray::with_interval(o, d, 1e-4 * size.length(), t_max));
    }
    // Axis-parallel rays with signed zeros, through a grid over the bounds.
    for axis in 0..3 {
        for sign in [1.0f32, -1.0] {
            for zero in [0.0f32, -0.0] {
                for i in 0..16 {
                    for j in 0..16 {
                        let mut d = Vec3::splat(zero);
                        d[axis] = sign;
                        let mut o = lo + size * Vec3::splat((i as f32 + 0.5) / 16.0);
                        o[(axis + 1) % 3] =
                            lo[(axis + 1) % 3] + size[(axis + 1) % 3] * (i as f32 + 0.5) / 16.0;
                        o[(axis + 2) % 3] =
                            lo[(axis + 2) % 3] + size[(axis + 2) % 3] * (j as f32 + 0.5) / 16.0;
                        o[axis] = if sign > 0.0 {
                            lo[axis] - size[axis]
                        } else {
                            hi[axis] + size[axis]
                        };
                        rays.push(Ray::new(o, d));
                    }
                }
            }
        }
    }
    // Axis-parallel rays lying exactly in the faces of node boxes (the box test's
    // parallel path), both signs, both zero signs.
    for k in 0..2048 {
        let n = &bvh.nodes()[(rng.next_u64() % bvh.nodes().len() as u64) as usize];
        let (o, mut d, axis) = in_box_face(k, Vec3::from(n.min), Vec3::from(n.max), lo, hi);
        rays.push(Ray::new(o, d));
        // Also nearly parallel: a subnormal component (flushed to zero by both sides).
        d[(axis + 1) % 3] = if k % 16 < 8 { 1e-40 } else { -1e-40 };
        rays.push(Ray::new(o, d));
    }
    // Rays through the centre with awkward intervals.
    let towards = |from: Vec3| (center - from).normalize();
    let eye = center + size;
    for (t_min, t_max) in [
        (0.0, 0.0),
        (1.0, 0.5),
        (f32::NEG_INFINITY, f32::INFINITY),
        (-1.0, f32::INFINITY),
        (0.0, f32::MAX),
        (f32::INFINITY, f32::INFINITY),
    ] {
        rays.push(Ray::with_interval(eye, towards(eye), t_min, t_max));
    }
    // Invalid rays.
    let d = towards(eye);
    for r in [
        Ray::new(Vec3::new(f32::NAN, 0.0, 0.0), d),
        Ray::new(eye, Vec3::new(f32::INFINITY, 0.0, 0.0)),
        Ray::new(Vec3::new(0.0, f32::NEG_INFINITY, 0.0), d),
        Ray::new(eye, Vec3::ZERO),
        Ray::new(eye, Vec3::new(-0.0, 0.0, -0.0)),
        Ray::with_interval(eye, d, f32::NAN, 1.0),
        Ray::with_interval(eye, d, 0.0, f32::NAN),
        Ray::new(eye, Vec3::new(0.0, f32::NAN, 1.0)),
    ] {
        rays.push(r);
    }
    // With a wide layout: axis-parallel rays lying exactly in the faces of its decoded
    // child boxes (which are not the binary nodes' boxes), as above.
    if let Some(w) = bvh.wide().map(|w| &**w) {
        for k in 0..1024 {
            let n = &w.nodes[(rng.next_u64() % w.nodes.len() as u64) as usize];
            let Some(slot) = (0..8).map(|i| (i + k) % 8).find(|&s| n.is_used(s)) else {
                continue;
            };
            let (bmin, bmax) = n.child_box(slot);
            let (o, d, _) = in_box_face(k, bmin, bmax, lo, hi);
            rays.push(Ray::new(o, d));
        }
    }
    rays
}

/// The instances of `ib` moved for an update test: instance `k` turned by `0.3 k` about y
/// and lifted by `0.1 k`, after its own transform.
pub fn moved_transforms(ib: &InstancedBvh) -> Vec<glam::Affine3A> {
    ib.instances()
        .iter()
        .enumerate()
        .map(|(k, i)| {
            glam::Affine3A::from_rotation_y(0.3 * k as f32)
                * glam::Affine3A::from_translation(Vec3::new(0.2, 0.1 * k as f32, 0.0))
                * i.transform
        })
        .collect()
}

/// Mesh `mesh` of `ib` swollen by 1.3 and lifted, by primitive id: a refit's new vertices.
pub fn swollen_mesh(ib: &InstancedBvh, mesh: usize) -> Vec<Triangle> {
    let mut tris: Vec<_> = ib.mesh_bvh(mesh).triangles().to_vec();
    tris.sort_by_key(|t| t.prim);
    tris.iter()
        .map(|t| t.corners().map(|p| p * 1.3 + Vec3::new(0.0, 0.05, 0.0)))
        .collect()
}
