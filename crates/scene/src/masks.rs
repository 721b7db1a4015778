//! A scene's masked materials as the tables every walk cuts candidates by
//! ([`bvhtrace_core::MaskTables`]): each masked triangle settled once as opaque,
//! transparent, or one to test, and the coordinates and textures of those to test.

use std::collections::HashMap;
use std::sync::Arc;

use bvhtrace_core::MaskTables;
use bvhtrace_core::alpha::{AlphaMask, TriangleState, triangle_state};
use bvhtrace_core::masks::{
    MASK_OPAQUE, MASK_TRANSPARENT, MaskMaterial, MaskTriangle, NO_MASKS, micromap,
};
use glam::Vec2;

use crate::{Mesh, Scene, SceneBvh};

/// The tables being filled: the masked materials' entries (by scene material) and the
/// triangles that sample them.
struct Tables<'a> {
    masks: Vec<Option<AlphaMask<'a>>>,
    materials: Vec<MaskMaterial>,
    /// Scene material to its entry in `materials`, made on first use.
    entries: HashMap<usize, u32>,
    /// Where each texture's texels start, by the texels' address (materials can share one).
    placed: HashMap<usize, u32>,
    texels: Vec<u8>,
    triangles: Vec<MaskTriangle>,
    states: Vec<u32>,
}

impl<'a> Tables<'a> {
    /// The entry of scene material `m`, adding it (and its texels) the first time.
    fn material(&mut self, m: usize, mask: &AlphaMask<'a>) -> u32 {
        if let Some(&e) = self.entries.get(&m) {
            return e;
        }
        let key = mask.alpha.as_ptr() as usize;
        let first_texel = *self.placed.entry(key).or_insert_with(|| {
            let at = self.texels.len() as u32;
            self.texels.extend_from_slice(mask.alpha);
            at
        });
        let e = self.materials.len() as u32;
        self.materials.push(MaskMaterial {
            first_texel,
            width: mask.width,
            height: mask.height,
            wrap: MaskMaterial::pack_wrap(mask.wrap),
            min_texel: mask.min_texel,
        });
        self.entries.insert(m, e);
        e
    }

    /// True when some triangle of `mesh` has a masked material.
    fn is_masked(&self, mesh: &Mesh) -> bool {
        (mesh.materials.iter()).any(|&m| matches!(self.masks.get(m as usize), Some(Some(_))))
    }

    /// Appends the states of `mesh`'s triangles, corners 1 and 2 swapped when `swap`.
    fn push_mesh(&mut self, mesh: &Mesh, swap: bool) {
        let uv = |i: u32| {
            mesh.texcoords
                .get(i as usize)
                .copied()
                .unwrap_or(Vec2::ZERO)
        };
        for (t, idx) in mesh.indices.iter().enumerate() {
            let mat = mesh.materials.get(t).copied().unwrap_or(u32::MAX) as usize;
            let Some(Some(mask)) = self.masks.get(mat).copied() else {
                self.states.push(MASK_OPAQUE);
                continue;
            };
            let mut corners = idx.map(uv);
            if swap {
                corners.swap(1, 2);
            }
            let state = match triangle_state(&corners, &mask) {
                TriangleState::Opaque => MASK_OPAQUE,
                TriangleState::Transparent => MASK_TRANSPARENT,
                TriangleState::Test => {
                    let material = self.material(mat, &mask);
                    self.triangles.push(MaskTriangle {
                        uv: bytemuck::cast(corners.map(|c| c.to_array())),
                        material,
                        micro: micromap(&corners, &mask),
                    });
                    self.triangles.len() as u32 - 1
                }
            };
            self.states.push(state);
        }
    }
}

impl Scene {
    /// True when some material is alpha-tested: [`Scene::tracing_bvh`] then attaches
    /// [`Scene::alpha_masks`] to the tree, and the walks cut candidates by them.
    pub fn has_alpha_masks(&self) -> bool {
        (self.materials.iter()).any(|m| m.alpha_mask(&self.alpha_textures).is_some())
    }

    /// The alpha-tested triangles of `traced` (this scene's BVH, flattened or two-level,
    /// as [`Scene::tracing_bvh`] made it), as every walk reads them; `None` when no
    /// triangle's material is masked. [`Scene::tracing_bvh`] attaches them already.
    pub fn alpha_masks(&self, traced: &SceneBvh) -> Option<MaskTables> {
        if !self.has_alpha_masks() {
            return None;
        }
        let masks: Vec<Option<AlphaMask<'_>>> = (self.materials.iter())
            .map(|m| m.alpha_mask(&self.alpha_textures))
            .collect();
        let mut t = Tables {
            masks,
            materials: Vec::new(),
            entries: HashMap::new(),
            placed: HashMap::new(),
            texels: Vec::new(),
            triangles: Vec::new(),
            states: Vec::new(),
        };
        let mut instance_bases = Vec::new();
        match traced {
            SceneBvh::Flat { .. } => {
                // Primitive ids number the instances' triangles in instance order.
                for inst in &self.instances {
                    let Some(mesh) = self.meshes.get(inst.mesh) else {
                        continue;
                    };
                    if t.is_masked(mesh) {
                        t.push_mesh(mesh, inst.flips_winding());
                    } else {
                        t.states
                            .resize(t.states.len() + mesh.indices.len(), MASK_OPAQUE);
                    }
                }
            }
            SceneBvh::Instanced(ib) => {
                let mut bases: HashMap<usize, u32> = HashMap::new();
                for inst in ib.instances() {
                    let mesh = (self.instances.get(inst.user_id as usize)).map(|i| i.mesh);
                    let base = match mesh.and_then(|m| Some((m, self.meshes.get(m)?))) {
                        Some((m, mesh)) if t.is_masked(mesh) => {
                            *bases.entry(m).or_insert_with(|| {
                                let base = t.states.len() as u32;
                                t.push_mesh(mesh, false);
                                base
                            })
                        }
                        _ => NO_MASKS,
                    };
                    instance_bases.push(base);
                }
            }
        }
        if t.states.iter().all(|&s| s == MASK_OPAQUE)
            && instance_bases.iter().all(|&b| b == NO_MASKS)
        {
            return None;
        }
        MaskTables::new(t.states, t.triangles, t.materials, t.texels, instance_bases).ok()
    }
}

impl SceneBvh {
    /// Attaches alpha masks to the traced BVH ([`bvhtrace_core::FlatBvh::set_masks`]), or
    /// drops them with `None` (every triangle opaque).
    pub fn set_masks(&mut self, masks: Option<Arc<MaskTables>>) -> Result<(), String> {
        match self {
            SceneBvh::Flat { bvh, .. } => bvh.set_masks(masks),
            SceneBvh::Instanced(ib) => ib.set_masks(masks),
        }
    }
}
