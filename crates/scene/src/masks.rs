//! A scene's masked materials as a hit filter for the CPU walks
//! ([`bvhtrace_core::HitFilter`]): each candidate on a masked triangle is kept or skipped
//! by the rule in [`bvhtrace_core::alpha`], most of them settled by the triangle's state
//! computed here once, without reading the texture.

use std::sync::atomic::{AtomicU64, Ordering};

use bvhtrace_core::alpha::{AlphaMask, TriangleState, triangle_state};
use bvhtrace_core::{Candidate, HitFilter};
use glam::Vec2;

use crate::{AlphaTexture, Scene, SceneBvh, Wrap};

/// One masked material's mask, owned.
#[derive(Clone, Debug)]
struct OwnedMask {
    texture: AlphaTexture,
    wrap: [Wrap; 2],
    min_texel: u32,
}

impl OwnedMask {
    fn mask(&self) -> AlphaMask<'_> {
        AlphaMask {
            alpha: &self.texture.alpha,
            width: self.texture.width,
            height: self.texture.height,
            wrap: self.wrap,
            min_texel: self.min_texel,
        }
    }
}

/// A masked mesh's triangles: each one's state, and for those to test, its material's
/// mask and its corners' texture coordinates.
#[derive(Clone, Debug, Default)]
struct MaskedMesh {
    states: Vec<TriangleState>,
    materials: Vec<u32>,
    uvs: Vec<[Vec2; 3]>,
}

/// How a candidate names its scene instance and mesh triangle.
#[derive(Clone, Debug)]
enum Locate {
    /// Flattened: each scene instance's first primitive id (and one past the last), and
    /// whether it mirrors (its triangles' corners 1 and 2 are swapped).
    Flat {
        starts: Vec<u64>,
        mirrors: Vec<bool>,
    },
    /// Two levels: each BVH instance's scene instance.
    TwoLevel { scene_instance: Vec<u32> },
}

/// The alpha test of a scene's masked materials, for the CPU walks
/// (`trace_rays_filtered`, `CpuTracer::with_filter`), built by [`Scene::alpha_filter`].
/// Counts the candidates it settles from the triangles' states and those it samples.
#[derive(Debug)]
pub struct AlphaFilter {
    meshes: Vec<Option<MaskedMesh>>,
    masks: Vec<Option<OwnedMask>>,
    instance_mesh: Vec<u32>,
    locate: Locate,
    settled: AtomicU64,
    sampled: AtomicU64,
}

impl Scene {
    /// The alpha test of this scene's masked materials for `traced` (its BVH, flattened or
    /// two-level, as [`Scene::tracing_bvh`] made it); `None` when no triangle is masked,
    /// so the walks run unfiltered.
    pub fn alpha_filter(&self, traced: &SceneBvh) -> Option<AlphaFilter> {
        let masks: Vec<Option<OwnedMask>> = (self.materials.iter())
            .map(|m| {
                let mask = m.alpha_mask(&self.alpha_textures)?;
                Some(OwnedMask {
                    texture: AlphaTexture {
                        name: String::new(),
                        width: mask.width,
                        height: mask.height,
                        alpha: mask.alpha.to_vec(),
                    },
                    wrap: mask.wrap,
                    min_texel: mask.min_texel,
                })
            })
            .collect();
        if masks.iter().all(Option::is_none) {
            return None;
        }
        let meshes: Vec<Option<MaskedMesh>> =
            self.meshes.iter().map(|m| masked_mesh(m, &masks)).collect();
        if meshes.iter().all(Option::is_none) {
            return None;
        }
        let locate = match traced {
            SceneBvh::Flat { .. } => {
                let mut starts = vec![0u64];
                for inst in &self.instances {
                    let n = self.meshes.get(inst.mesh).map_or(0, |m| m.indices.len());
                    starts.push(starts.last().copied().unwrap_or(0) + n as u64);
                }
                let mirrors = self.instances.iter().map(|i| i.flips_winding()).collect();
                Locate::Flat { starts, mirrors }
            }
            SceneBvh::Instanced(ib) => Locate::TwoLevel {
                scene_instance: ib.instances().iter().map(|i| i.user_id).collect(),
            },
        };
        Some(AlphaFilter {
            meshes,
            masks,
            instance_mesh: self.instances.iter().map(|i| i.mesh as u32).collect(),
            locate,
            settled: AtomicU64::new(0),
            sampled: AtomicU64::new(0),
        })
    }
}

/// A mesh's masked triangles, or `None` when it has none.
fn masked_mesh(m: &crate::Mesh, masks: &[Option<OwnedMask>]) -> Option<MaskedMesh> {
    let masked = |t: usize| {
        let mat = m.materials.get(t).copied()? as usize;
        masks.get(mat)?.as_ref()
    };
    if !(0..m.indices.len()).any(|t| masked(t).is_some()) {
        return None;
    }
    let uv = |i: u32| m.texcoords.get(i as usize).copied().unwrap_or(Vec2::ZERO);
    let uvs: Vec<[Vec2; 3]> = m.indices.iter().map(|t| t.map(uv)).collect();
    let states = (0..m.indices.len())
        .map(|t| match masked(t) {
            None => TriangleState::Opaque,
            Some(mask) => triangle_state(&uvs[t], &mask.mask()),
        })
        .collect();
    Some(MaskedMesh {
        states,
        materials: m.materials.clone(),
        uvs,
    })
}

impl AlphaFilter {
    /// Candidates settled by their triangle's state (no texture read) and candidates that
    /// sampled the texture, since it was made.
    pub fn counts(&self) -> (u64, u64) {
        (
            self.settled.load(Ordering::Relaxed),
            self.sampled.load(Ordering::Relaxed),
        )
    }

    /// The candidate's scene instance, mesh triangle, and whether its corners 1 and 2 are
    /// swapped in the traced triangle.
    fn locate(&self, c: &Candidate) -> Option<(usize, usize, bool)> {
        match &self.locate {
            Locate::Flat { starts, mirrors } => {
                let p = u64::from(c.prim);
                let k = starts.partition_point(|&s| s <= p).checked_sub(1)?;
                Some((k, (p - starts[k]) as usize, *mirrors.get(k)?))
            }
            Locate::TwoLevel { scene_instance } => {
                let i = *scene_instance.get(c.instance? as usize)?;
                Some((i as usize, c.mesh_prim as usize, false))
            }
        }
    }
}

impl HitFilter for AlphaFilter {
    fn accept(&self, c: &Candidate) -> bool {
        let Some((instance, tri, swapped)) = self.locate(c) else {
            return true;
        };
        let mesh = self
            .instance_mesh
            .get(instance)
            .copied()
            .unwrap_or(u32::MAX);
        let Some(Some(m)) = self.meshes.get(mesh as usize) else {
            return true;
        };
        let state = m.states.get(tri).copied().unwrap_or(TriangleState::Opaque);
        if state != TriangleState::Test {
            self.settled.fetch_add(1, Ordering::Relaxed);
            return state == TriangleState::Opaque;
        }
        self.sampled.fetch_add(1, Ordering::Relaxed);
        let mat = m.materials.get(tri).copied().unwrap_or(u32::MAX) as usize;
        let Some(Some(mask)) = self.masks.get(mat) else {
            return true;
        };
        let mut uv = m.uvs[tri];
        if swapped {
            uv.swap(1, 2);
        }
        mask.mask().passes(&uv, c.u, c.v)
    }
}
