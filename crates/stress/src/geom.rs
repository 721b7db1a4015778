//! Geometry helpers shared by the cases: indexed meshes, welding and closedness, exact
//! f64 placement, inside tests, camera and "aim at every vertex" ray sets, and a small
//! deterministic random number generator.

use std::collections::HashMap;

use bvhtrace_core::oracle;
use bvhtrace_core::{Instance, Ray, Triangle};
use glam::{Affine3A, DAffine3, DVec3, Mat4, Vec3};

/// A triangle mesh with shared vertices (the shape watertightness is defined on).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct IndexedMesh {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Three indices into `positions` per triangle.
    pub indices: Vec<[u32; 3]>,
}

/// How closed a mesh is, by counting the uses of every undirected edge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Closedness {
    /// Undirected edges used by exactly one triangle (holes).
    pub boundary_edges: usize,
    /// Undirected edges used by more than two triangles.
    pub nonmanifold_edges: usize,
    /// Edges used twice in the same direction (inconsistent winding).
    pub inconsistent_edges: usize,
    /// Undirected edges in all.
    pub edges: usize,
}

impl Closedness {
    /// True for a closed, manifold, consistently wound surface.
    pub fn is_closed(&self) -> bool {
        self.boundary_edges == 0 && self.nonmanifold_edges == 0 && self.inconsistent_edges == 0
    }
}

impl IndexedMesh {
    /// The triangles as corner triples, in index order.
    pub fn triangles(&self) -> Vec<Triangle> {
        self.indices
            .iter()
            .map(|t| t.map(|i| self.positions[i as usize]))
            .collect()
    }

    /// The mesh with vertices of bit-identical position merged (glTF files split vertices
    /// at UV and normal seams; the triangles still share those edges exactly). Triangles
    /// whose corners merge into fewer than three distinct vertices are kept.
    pub fn welded(&self) -> IndexedMesh {
        let mut map: HashMap<[u32; 3], u32> = HashMap::new();
        let mut positions = Vec::new();
        let remap: Vec<u32> = self
            .positions
            .iter()
            .map(|p| {
                let key = p.to_array().map(|c| (c + 0.0).to_bits()); // -0 == +0
                *map.entry(key).or_insert_with(|| {
                    positions.push(*p);
                    (positions.len() - 1) as u32
                })
            })
            .collect();
        IndexedMesh {
            positions,
            indices: self
                .indices
                .iter()
                .map(|t| t.map(|i| remap[i as usize]))
                .collect(),
        }
    }

    /// Counts edge uses (triangles with a repeated corner index are skipped: they add no
    /// edge to the surface).
    pub fn closedness(&self) -> Closedness {
        let mut uses: HashMap<(u32, u32), (u32, u32)> = HashMap::new(); // (forward, backward)
        for t in &self.indices {
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                continue;
            }
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let e = uses.entry((a.min(b), a.max(b))).or_default();
                if a < b {
                    e.0 += 1;
                } else {
                    e.1 += 1;
                }
            }
        }
        let mut c = Closedness {
            edges: uses.len(),
            ..Default::default()
        };
        for &(f, b) in uses.values() {
            match f + b {
                1 => c.boundary_edges += 1,
                2 if f != 1 => c.inconsistent_edges += 1,
                2 => {}
                _ => c.nonmanifold_edges += 1,
            }
        }
        c
    }

    /// Every undirected edge once, as vertex index pairs.
    pub fn edges(&self) -> Vec<(u32, u32)> {
        let mut e: Vec<(u32, u32)> = self
            .indices
            .iter()
            .flat_map(|t| (0..3).map(move |k| (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]))))
            .filter(|(a, b)| a != b)
            .collect();
        e.sort_unstable();
        e.dedup();
        e
    }

    /// Bounds `(min, max)` of the positions.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.positions
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(*p), hi.max(*p))
            })
    }

    /// The mesh placed at `p * scale + offset`, computed in f64 and rounded once to f32,
    /// with what the rounding did to it.
    pub fn placed(&self, scale: f64, offset: DVec3) -> (IndexedMesh, Placement) {
        let mut exact = true;
        let positions: Vec<Vec3> = self
            .positions
            .iter()
            .map(|p| {
                let q = p.as_dvec3() * scale + offset;
                let r = q.as_vec3();
                exact &= r.as_dvec3() == q;
                r
            })
            .collect();
        let m = IndexedMesh {
            positions,
            indices: self.indices.clone(),
        };
        let distinct = |ps: &[Vec3]| {
            let mut v: Vec<[u32; 3]> = ps
                .iter()
                .map(|p| p.to_array().map(|c| (c + 0.0).to_bits()))
                .collect();
            v.sort_unstable();
            v.dedup();
            v.len()
        };
        let merged_vertices = distinct(&self.positions) - distinct(&m.positions);
        let zero_area_before = count_zero_area(&self.triangles());
        let zero_area = count_zero_area(&m.triangles());
        (
            m,
            Placement {
                exact,
                merged_vertices,
                new_zero_area: zero_area.saturating_sub(zero_area_before),
            },
        )
    }

    /// Appends another mesh (indices shifted).
    pub fn append(&mut self, other: &IndexedMesh) {
        let base = self.positions.len() as u32;
        self.positions.extend_from_slice(&other.positions);
        self.indices
            .extend(other.indices.iter().map(|t| t.map(|i| i + base)));
    }
}

/// What placing a mesh in f32 did to it (see [`IndexedMesh::placed`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Placement {
    /// Every coordinate was representable: the f32 mesh is exactly the intended one.
    pub exact: bool,
    /// Distinct vertices that became one.
    pub merged_vertices: usize,
    /// Triangles that became exactly zero-area.
    pub new_zero_area: usize,
}

/// True when the triangle's area is exactly zero (the cross product of its f32 edges,
/// computed in f64, is zero: exact for coordinates within a few binades of each other).
pub fn is_zero_area(t: &Triangle) -> bool {
    let [a, b, c] = t.map(|p| p.as_dvec3());
    (b - a).cross(c - a) == DVec3::ZERO
}

/// Number of exactly zero-area triangles.
pub fn count_zero_area(tris: &[Triangle]) -> usize {
    tris.iter().filter(|t| is_zero_area(t)).count()
}

/// A closed icosphere (the scene crate's `builtin:icosphere:N`, unit radius, f32 positions)
/// placed at `center + radius * p` in f64 and rounded once.
pub fn icosphere(subdiv: u32, center: DVec3, radius: f64) -> IndexedMesh {
    unit_icosphere(subdiv).placed(radius, center).0
}

/// The scene crate's unit icosphere with `subdiv` subdivisions.
pub fn unit_icosphere(subdiv: u32) -> IndexedMesh {
    let m = bvhtrace_scene::icosphere(subdiv);
    IndexedMesh {
        positions: m.positions,
        indices: m.indices,
    }
}

/// A closed axis-aligned box `[lo, hi]` (12 triangles, wound outwards).
pub fn box_mesh(lo: DVec3, hi: DVec3) -> IndexedMesh {
    let p = |x: bool, y: bool, z: bool| {
        DVec3::new(
            if x { hi.x } else { lo.x },
            if y { hi.y } else { lo.y },
            if z { hi.z } else { lo.z },
        )
        .as_vec3()
    };
    let positions: Vec<Vec3> = (0..8)
        .map(|i| p(i & 1 != 0, i & 2 != 0, i & 4 != 0))
        .collect();
    // Corner i has x = bit 0, y = bit 1, z = bit 2.
    let quads = [
        [0, 2, 3, 1], // z = lo
        [4, 5, 7, 6], // z = hi
        [0, 1, 5, 4], // y = lo
        [2, 6, 7, 3], // y = hi
        [0, 4, 6, 2], // x = lo
        [1, 3, 7, 5], // x = hi
    ];
    let indices = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    IndexedMesh { positions, indices }
}

/// Rays from `from` aimed exactly (directions computed in f64, rounded once) at every
/// vertex, and at the points `a + s (b - a)` of every edge for each `s` in `fractions`.
pub fn aim_at_vertices_and_edges(mesh: &IndexedMesh, from: Vec3, fractions: &[f64]) -> Vec<Ray> {
    aim_at_placed_vertices_and_edges(mesh, |p| p, from, fractions)
}

/// Rays from `from` aimed exactly at every vertex of `mesh` and at the points
/// `a + s (b - a)` of every edge, each target placed by `place` (in f64: an instance's
/// transform, [`to_f64`]) and the direction computed in f64 and rounded once, as
/// [`aim_at_vertices_and_edges`] does for an untransformed mesh.
pub fn aim_at_placed_vertices_and_edges(
    mesh: &IndexedMesh,
    place: impl Fn(DVec3) -> DVec3,
    from: Vec3,
    fractions: &[f64],
) -> Vec<Ray> {
    let o = from.as_dvec3();
    let mut rays: Vec<Ray> = mesh
        .positions
        .iter()
        .map(|v| Ray::new(from, (place(v.as_dvec3()) - o).as_vec3()))
        .collect();
    for (a, b) in mesh.edges() {
        let (a, b) = (
            mesh.positions[a as usize].as_dvec3(),
            mesh.positions[b as usize].as_dvec3(),
        );
        for &s in fractions {
            rays.push(Ray::new(from, (place(a + (b - a) * s) - o).as_vec3()));
        }
    }
    rays.retain(|r| Vec3::from(r.dir) != Vec3::ZERO);
    rays
}

/// The f32 transform converted to f64 exactly (every entry).
pub fn to_f64(m: &Affine3A) -> DAffine3 {
    DAffine3::from_mat4(Mat4::from(*m).as_dmat4())
}

/// A transform made in f64 (`scale`, then `rotation`, then `translation`), each entry
/// rounded once to f32: the f32 transform is the input, exactly as [`to_f64`] reads it.
pub fn affine_from_f64(scale: DVec3, rotation: glam::DQuat, translation: DVec3) -> Affine3A {
    let d = DAffine3::from_scale_rotation_translation(scale, rotation, translation);
    Affine3A::from_mat4(glam::DMat4::from(d).as_mat4())
}

/// The flattened scene of two levels: each instance's mesh in world space
/// (`Affine3A::transform_point3` in f32, as `InstancedBvh::world_triangle` and the scene
/// crate's `Scene::flatten` place it), instance after instance, so that triangle `i` is
/// the two-level BVH's primitive `i`. A mirroring transform (determinant < 0) swaps
/// corners 1 and 2 to keep the winding. Instances naming no mesh are left out (the
/// two-level build refuses them).
pub fn flatten_instances(meshes: &[Vec<Triangle>], instances: &[Instance]) -> Vec<Triangle> {
    let mut out = Vec::new();
    for inst in instances {
        let Some(mesh) = meshes.get(inst.mesh as usize) else {
            continue;
        };
        let m = inst.transform;
        let mirror = m.matrix3.determinant() < 0.0;
        out.extend(mesh.iter().map(|t| {
            let w = t.map(|p| m.transform_point3(p));
            if mirror { [w[0], w[2], w[1]] } else { w }
        }));
    }
    out
}

/// Directions for the inside test: irrational-looking, so no ray runs exactly through an
/// edge or vertex of a generated mesh.
const PROBE_DIRS: [[f64; 3]; 7] = [
    [0.5773, 0.5774, 0.5775],
    [-0.31, 0.829, 0.4657],
    [0.7043, -0.0137, -0.7097],
    [-0.6235, -0.4339, 0.6502],
    [0.1234, -0.9411, 0.3147],
    [-0.8913, 0.3011, -0.3389],
    [0.0421, 0.2719, -0.9613],
];

/// True when `p` is inside the closed surface `tris`: every probe ray crosses the surface an
/// odd number of times (f64 oracle), and the nearest crossing is at least `clearance` away
/// (probe directions are unit vectors).
pub fn is_inside(tris: &[Triangle], p: Vec3, clearance: f64) -> bool {
    PROBE_DIRS.iter().all(|d| {
        let dir = DVec3::from_array(*d).normalize().as_vec3();
        let hits = oracle::all_hits(tris, &Ray::new(p, dir));
        hits.len() % 2 == 1 && hits[0].0 * dir.as_dvec3().length() >= clearance
    })
}

/// Finds up to `want` points inside the closed surface `tris` with some clearance: the
/// box centre, the vertex mean, then points on a lattice through the box, in that order.
pub fn inside_points(tris: &[Triangle], want: usize) -> Vec<Vec3> {
    let mut lo = DVec3::INFINITY;
    let mut hi = DVec3::NEG_INFINITY;
    let mut mean = DVec3::ZERO;
    for t in tris {
        for p in t {
            let p = p.as_dvec3();
            lo = lo.min(p);
            hi = hi.max(p);
            mean += p;
        }
    }
    mean /= (3 * tris.len().max(1)) as f64;
    let ext = hi - lo;
    let clearance = 0.02 * ext.min_element().max(ext.max_element() * 1e-3);
    let mut cands = vec![(lo + hi) * 0.5, mean];
    for i in 1..6 {
        for j in 1..6 {
            for k in 1..6 {
                let f = DVec3::new(i as f64, j as f64, k as f64) / 6.0 + 0.013;
                cands.push(lo + ext * f);
            }
        }
    }
    let mut out: Vec<Vec3> = Vec::new();
    for c in cands {
        let p = c.as_vec3();
        if out.len() < want && !out.contains(&p) && is_inside(tris, p, clearance) {
            out.push(p);
        }
    }
    out
}

/// A pinhole camera's rays over a `w` x `h` grid: eye and directions computed in f64
/// (relative to the eye), rounded once. `fov_deg` is the vertical field of view.
pub fn camera_rays(eye: DVec3, target: DVec3, fov_deg: f64, w: u32, h: u32) -> Vec<Ray> {
    let fwd = (target - eye).normalize();
    let up0 = if fwd.y.abs() > 0.9 {
        DVec3::X
    } else {
        DVec3::Y
    };
    let right = fwd.cross(up0).normalize();
    let up = right.cross(fwd);
    let tan = (fov_deg.to_radians() * 0.5).tan();
    let aspect = w as f64 / h as f64;
    let o = eye.as_vec3();
    let mut rays = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let sx = ((x as f64 + 0.5) / w as f64 * 2.0 - 1.0) * tan * aspect;
            let sy = (1.0 - (y as f64 + 0.5) / h as f64 * 2.0) * tan;
            let d = (fwd + right * sx + up * sy).normalize();
            rays.push(Ray::new(o, d.as_vec3()));
        }
    }
    rays
}

/// SplitMix64: small, deterministic, good enough for test inputs.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Rng(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f64()
    }

    /// Uniform in `0..n`.
    pub fn below(&mut self, n: usize) -> usize {
        (self.f64() * n as f64) as usize % n.max(1)
    }

    /// A uniformly distributed unit vector.
    pub fn unit(&mut self) -> DVec3 {
        loop {
            let v = DVec3::new(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            let l = v.length_squared();
            if l > 1e-6 && l <= 1.0 {
                return v / l.sqrt();
            }
        }
    }

    /// A uniformly distributed unit vector in the hemisphere around `n`.
    pub fn hemisphere(&mut self, n: DVec3) -> DVec3 {
        let v = self.unit();
        if v.dot(n) < 0.0 { -v } else { v }
    }

    /// A uniform point in the box `[lo, hi]`.
    pub fn in_box(&mut self, lo: DVec3, hi: DVec3) -> DVec3 {
        DVec3::new(
            self.range(lo.x, hi.x),
            self.range(lo.y, hi.y),
            self.range(lo.z, hi.z),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn icospheres_and_boxes_are_closed() {
        for n in 0..4 {
            assert!(unit_icosphere(n).closedness().is_closed());
        }
        let b = box_mesh(DVec3::splat(-1.0), DVec3::new(1.0, 2.0, 3.0));
        assert!(b.closedness().is_closed(), "{:?}", b.closedness());
        // Outward winding: the signed volume is positive.
        let vol: f64 = b
            .triangles()
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|p| p.as_dvec3());
                a.dot(b.cross(c)) / 6.0
            })
            .sum();
        assert!((vol - 24.0).abs() < 1e-9, "{vol}");
        let mut open = unit_icosphere(1);
        open.indices.pop();
        assert_eq!(open.closedness().boundary_edges, 3);
    }

    #[test]
    fn inside_points_are_inside() {
        let tris = icosphere(2, DVec3::new(3.0, 0.0, 0.0), 2.0).triangles();
        let p = inside_points(&tris, 2);
        assert_eq!(p.len(), 2);
        assert!(!is_inside(&tris, Vec3::ZERO, 0.0));
    }
}
