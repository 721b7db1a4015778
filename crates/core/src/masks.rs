//! A BVH's alpha-tested triangles as every walk reads them: one table per primitive
//! ([`MaskTables`]), attached to the BVH ([`FlatBvh::set_masks`](crate::FlatBvh::set_masks)),
//! so that the CPU walks and every device backend cut the same candidates from the same
//! data by the rule in [`crate::alpha`].
//!
//! A candidate on a triangle whose mesh primitive is `p` looks up `states[base + p]`,
//! where `base` is 0 for one mesh and the instance's entry of `instance_bases` for two
//! levels (an instance of a mesh without masked triangles has [`NO_MASKS`] and is opaque
//! without a look-up). A state is [`MASK_OPAQUE`], [`MASK_TRANSPARENT`], or the index of
//! the triangle's [`MaskTriangle`]: its corners' texture coordinates, its material (whose
//! [`MaskMaterial`] places its texels in `texels`) and its micromap. Only triangles that
//! need the texture have a record, and only masked materials' textures are stored.
//!
//! The micromap (an opacity micromap, as DXR and Vulkan call theirs) settles most
//! candidates on a tested triangle too: the triangle's barycentric domain is cut into
//! [`MICRO_CELLS`] x [`MICRO_CELLS`] cells, each halved into a lower and an upper
//! micro-triangle ([`micro_slot`]), and each micro-triangle holds two bits: opaque,
//! transparent, or test (from the texels its coordinates can reach, with a texel of
//! margin, as for whole triangles). Only a candidate in a micro-triangle to test reads
//! the texture.
//!
//! On a device the tables are one `array<u32>` ([`MaskTables::words`]): a
//! [`MaskHeader`] of word offsets, then the instance bases in the uploaded layout's
//! instance order, the states, the triangles, the materials and the texels, four to a
//! word, little end first.

use std::sync::atomic::{AtomicU64, Ordering};

use bytemuck::{Pod, Zeroable};
use glam::Vec2;

use crate::alpha::{AlphaMask, TriangleState, Wrap, interpolate_uv, triangle_state};

/// The state of a triangle every candidate passes, without a texture read.
pub const MASK_OPAQUE: u32 = u32::MAX;
/// The state of a triangle no candidate passes.
pub const MASK_TRANSPARENT: u32 = u32::MAX - 1;
/// The instance base of an instance whose mesh has no masked triangle.
pub const NO_MASKS: u32 = u32::MAX;

/// Cells along each barycentric axis of a micromap: `MICRO_CELLS^2` cells, two
/// micro-triangles each.
pub const MICRO_CELLS: u32 = 8;
/// A micro-triangle every candidate in which passes.
pub const MICRO_OPAQUE: u32 = 1;
/// A micro-triangle no candidate in which passes.
pub const MICRO_TRANSPARENT: u32 = 2;
/// A micro-triangle whose candidates read the texture (0, so that unset slots test).
pub const MICRO_TEST: u32 = 0;
/// Words of a micromap: two bits per slot, `2 MICRO_CELLS^2` slots.
pub const MICRO_WORDS: usize = (2 * MICRO_CELLS * MICRO_CELLS * 2 / 32) as usize;

/// The micromap slot of barycentrics `(u, v)` (the weights of corners 1 and 2): cell
/// `(i, j) = (floor(8u), floor(8v))`, clamped into the triangle, and its upper half when
/// the fractions sum to 1 or more; slot `2 (8j + i) + upper`. Exact in f32 (products by a
/// power of two, differences of a number and its floor), so a device computes the same.
#[inline]
pub fn micro_slot(u: f32, v: f32) -> usize {
    let n = MICRO_CELLS as f32;
    let last = MICRO_CELLS - 1;
    let (fu, fv) = (u * n, v * n);
    let i = (fu.floor().max(0.0) as u32).min(last);
    let j = (fv.floor().max(0.0) as u32).min(last - i);
    let upper = (fu - i as f32) + (fv - j as f32) >= 1.0 && i + j < last;
    (2 * (j * MICRO_CELLS + i) + u32::from(upper)) as usize
}

/// The barycentric corners `(u, v)` of micromap slot `slot`.
pub fn micro_corners(slot: usize) -> [(f32, f32); 3] {
    let cell = (slot / 2) as u32;
    let (i, j) = (cell % MICRO_CELLS, cell / MICRO_CELLS);
    let at = |a: u32, b: u32| (a as f32 / MICRO_CELLS as f32, b as f32 / MICRO_CELLS as f32);
    if slot.is_multiple_of(2) {
        [at(i, j), at(i + 1, j), at(i, j + 1)]
    } else {
        [at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)]
    }
}

/// The micromap of a triangle with corner coordinates `uv` under `mask`: each
/// micro-triangle settled as a whole triangle is ([`triangle_state`] of its corners'
/// coordinates, interpolated by the rule's arithmetic), so that a settled slot answers as
/// the texture would for every candidate in it.
pub fn micromap(uv: &[Vec2; 3], mask: &AlphaMask<'_>) -> [u32; MICRO_WORDS] {
    let mut t = MaskTriangle::default();
    for slot in 0..(2 * MICRO_CELLS * MICRO_CELLS) as usize {
        let corners = micro_corners(slot).map(|(u, v)| interpolate_uv(uv, u, v));
        let state = match triangle_state(&corners, mask) {
            TriangleState::Opaque => MICRO_OPAQUE,
            TriangleState::Transparent => MICRO_TRANSPARENT,
            TriangleState::Test => MICRO_TEST,
        };
        t.set_micro_state(slot, state);
    }
    t.micro
}

/// One triangle that samples its material's texture (`BvhMaskTriangle` in
/// `alpha_masks.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MaskTriangle {
    /// Texture coordinates of corners 0, 1 and 2 (`u0, v0, u1, v1, u2, v2`), in the corner
    /// order of the traced triangle.
    pub uv: [f32; 6],
    /// Index into [`MaskTables::materials`].
    pub material: u32,
    /// The micromap: slot `s`'s state ([`MICRO_OPAQUE`], [`MICRO_TRANSPARENT`] or
    /// [`MICRO_TEST`]) in bits `2 (s % 16)` of word `s / 16`; all zero tests every
    /// candidate.
    pub micro: [u32; MICRO_WORDS],
}

impl MaskTriangle {
    /// The state of micromap slot `slot`.
    #[inline]
    pub fn micro_state(&self, slot: usize) -> u32 {
        (self.micro[slot / 16] >> (2 * (slot % 16))) & 3
    }

    /// Sets micromap slot `slot` to `state`.
    pub fn set_micro_state(&mut self, slot: usize, state: u32) {
        let shift = 2 * (slot % 16);
        self.micro[slot / 16] = (self.micro[slot / 16] & !(3 << shift)) | ((state & 3) << shift);
    }

    /// The corners' coordinates as three points.
    pub fn corners(&self) -> [Vec2; 3] {
        let c = |k: usize| Vec2::new(self.uv[2 * k], self.uv[2 * k + 1]);
        [c(0), c(1), c(2)]
    }
}

/// One masked material's texture and threshold (`BvhMaskMaterial` in `alpha_masks.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Pod, Zeroable)]
pub struct MaskMaterial {
    /// The texture's first texel in [`MaskTables::texels`].
    pub first_texel: u32,
    /// Texels per row (at least 1).
    pub width: u32,
    /// Rows (at least 1).
    pub height: u32,
    /// The wrap modes: `u`'s [`Wrap::index`] in bits 0-1, `v`'s in bits 2-3.
    pub wrap: u32,
    /// The smallest texel alpha that passes ([`crate::alpha::min_passing_texel`]).
    pub min_texel: u32,
}

impl MaskMaterial {
    /// The wrap modes along `u` and `v`.
    pub fn wraps(&self) -> [Wrap; 2] {
        let w = |i: u32| match i & 3 {
            1 => Wrap::ClampToEdge,
            2 => Wrap::MirroredRepeat,
            _ => Wrap::Repeat,
        };
        [w(self.wrap), w(self.wrap >> 2)]
    }

    /// [`MaskMaterial::wrap`] for the modes along `u` and `v`.
    pub fn pack_wrap(wrap: [Wrap; 2]) -> u32 {
        wrap[0].index() | (wrap[1].index() << 2)
    }
}

/// Where each table starts in [`MaskTables::words`], in words (`BvhMaskHeader` in
/// `alpha_masks.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct MaskHeader {
    /// The instance bases.
    pub instance_bases: u32,
    /// The states.
    pub states: u32,
    /// The [`MaskTriangle`]s.
    pub triangles: u32,
    /// The [`MaskMaterial`]s.
    pub materials: u32,
    /// The texels, four to a word.
    pub texels: u32,
}

/// A BVH's masked triangles: see the [module documentation](self). Counts the candidates
/// its states settle and those that sample a texture on the CPU walks.
#[derive(Debug, Default)]
pub struct MaskTables {
    /// Per primitive (offset by the instance's base in two levels): [`MASK_OPAQUE`],
    /// [`MASK_TRANSPARENT`], or an index into `triangles`.
    pub states: Vec<u32>,
    /// The triangles a candidate on which samples a texture.
    pub triangles: Vec<MaskTriangle>,
    /// The masked materials those triangles name.
    pub materials: Vec<MaskMaterial>,
    /// Every material's texels' alpha, 8 bits each, row by row from the top.
    pub texels: Vec<u8>,
    /// Per instance of a two-level BVH (in [`FlatBvh::instances`](crate::FlatBvh::instances)'
    /// order): where its mesh's states start, or [`NO_MASKS`]. Empty for one mesh.
    pub instance_bases: Vec<u32>,
    settled: AtomicU64,
    sampled: AtomicU64,
}

impl Clone for MaskTables {
    /// The tables, with counts from zero.
    fn clone(&self) -> Self {
        MaskTables {
            states: self.states.clone(),
            triangles: self.triangles.clone(),
            materials: self.materials.clone(),
            texels: self.texels.clone(),
            instance_bases: self.instance_bases.clone(),
            ..MaskTables::default()
        }
    }
}

impl PartialEq for MaskTables {
    /// Equal tables; the counts are not compared.
    fn eq(&self, o: &Self) -> bool {
        self.states == o.states
            && self.triangles == o.triangles
            && self.materials == o.materials
            && self.texels == o.texels
            && self.instance_bases == o.instance_bases
    }
}

impl MaskTables {
    /// Tables from their parts, checked: every state names a triangle, every triangle a
    /// material, every material's texels are within `texels`, every base within `states`.
    pub fn new(
        states: Vec<u32>,
        triangles: Vec<MaskTriangle>,
        materials: Vec<MaskMaterial>,
        texels: Vec<u8>,
        instance_bases: Vec<u32>,
    ) -> Result<MaskTables, String> {
        let tables = MaskTables {
            states,
            triangles,
            materials,
            texels,
            instance_bases,
            ..MaskTables::default()
        };
        tables.check()?;
        Ok(tables)
    }

    fn check(&self) -> Result<(), String> {
        let n = self.triangles.len();
        if let Some((p, s)) = (self.states.iter().enumerate())
            .find(|&(_, &s)| s < MASK_TRANSPARENT && s as usize >= n)
        {
            return Err(format!("primitive {p}'s state {s} names no triangle ({n})"));
        }
        let m = self.materials.len();
        if let Some((i, t)) =
            (self.triangles.iter().enumerate()).find(|(_, t)| t.material as usize >= m)
        {
            return Err(format!(
                "masked triangle {i} names material {} of {m}",
                t.material
            ));
        }
        for (i, mat) in self.materials.iter().enumerate() {
            let len = u64::from(mat.width) * u64::from(mat.height);
            let end = u64::from(mat.first_texel) + len;
            if len == 0 || end > self.texels.len() as u64 {
                return Err(format!(
                    "masked material {i}: {}x{} texels from {} of {}",
                    mat.width,
                    mat.height,
                    mat.first_texel,
                    self.texels.len()
                ));
            }
        }
        let s = self.states.len() as u64;
        if let Some((i, b)) = (self.instance_bases.iter().enumerate())
            .find(|&(_, &b)| b != NO_MASKS && u64::from(b) > s)
        {
            return Err(format!("instance {i}'s base {b} is past the {s} states"));
        }
        Ok(())
    }

    /// The base of the instance a walk enters (`None`: one mesh).
    #[inline]
    pub fn base(&self, instance: Option<u32>) -> u32 {
        match instance {
            None => 0,
            Some(i) => self
                .instance_bases
                .get(i as usize)
                .copied()
                .unwrap_or(NO_MASKS),
        }
    }

    /// The texture of material `m`.
    pub fn mask(&self, m: &MaskMaterial) -> AlphaMask<'_> {
        let start = m.first_texel as usize;
        let end = start + (m.width as usize) * (m.height as usize);
        AlphaMask {
            alpha: self.texels.get(start..end).unwrap_or(&[]),
            width: m.width,
            height: m.height,
            wrap: m.wraps(),
            min_texel: m.min_texel,
        }
    }

    /// Whether a candidate at barycentrics `(u, v)` on mesh primitive `prim` of an instance
    /// with `base` ([`MaskTables::base`]) counts as a hit.
    #[inline]
    pub fn accept(&self, base: u32, prim: u32, u: f32, v: f32) -> bool {
        if base == NO_MASKS {
            return true;
        }
        let state = (self.states.get(base.wrapping_add(prim) as usize))
            .copied()
            .unwrap_or(MASK_OPAQUE);
        if state >= MASK_TRANSPARENT {
            self.settled.fetch_add(1, Ordering::Relaxed);
            return state == MASK_OPAQUE;
        }
        let Some(t) = self.triangles.get(state as usize) else {
            return true;
        };
        let micro = t.micro_state(micro_slot(u, v));
        if micro != MICRO_TEST {
            self.settled.fetch_add(1, Ordering::Relaxed);
            return micro == MICRO_OPAQUE;
        }
        self.sampled.fetch_add(1, Ordering::Relaxed);
        let Some(m) = self.materials.get(t.material as usize) else {
            return true;
        };
        let mask = self.mask(m);
        mask.texel(interpolate_uv(&t.corners(), u, v)) >= mask.min_texel
    }

    /// Candidates settled by their triangle's state or micromap (no texture read) and candidates that
    /// sampled a texture on the CPU walks, since the tables were made or last reset.
    pub fn counts(&self) -> (u64, u64) {
        (
            self.settled.load(Ordering::Relaxed),
            self.sampled.load(Ordering::Relaxed),
        )
    }

    /// Sets [`MaskTables::counts`] back to zero.
    pub fn reset_counts(&self) {
        self.settled.store(0, Ordering::Relaxed);
        self.sampled.store(0, Ordering::Relaxed);
    }

    /// The tables as the kernels read them, with `instance_bases` in the uploaded layout's
    /// instance order ([`MaskTables::bases_in_order`]).
    pub fn words(&self, instance_bases: &[u32]) -> Vec<u32> {
        let header_words = (size_of::<MaskHeader>() / 4) as u32;
        let mut h = MaskHeader {
            instance_bases: header_words,
            ..MaskHeader::default()
        };
        h.states = h.instance_bases + instance_bases.len() as u32;
        h.triangles = h.states + self.states.len() as u32;
        h.materials = h.triangles + (self.triangles.len() * size_of::<MaskTriangle>() / 4) as u32;
        h.texels = h.materials + (self.materials.len() * size_of::<MaskMaterial>() / 4) as u32;
        let mut w: Vec<u32> = Vec::with_capacity(h.texels as usize + self.texels.len() / 4 + 1);
        w.extend_from_slice(bytemuck::cast_slice(&[h]));
        w.extend_from_slice(instance_bases);
        w.extend_from_slice(&self.states);
        w.extend_from_slice(bytemuck::cast_slice(&self.triangles));
        w.extend_from_slice(bytemuck::cast_slice(&self.materials));
        w.extend(self.texels.chunks(4).map(|c| {
            c.iter()
                .rev()
                .fold(0u32, |acc, &b| (acc << 8) | u32::from(b))
        }));
        // A storage binding may not be empty.
        if w.len() == h.texels as usize {
            w.push(0);
        }
        w
    }

    /// The tables from their words ([`MaskTables::words`]; the instance bases as written,
    /// in the order of the layout they were written for): what a device holding only the
    /// words reads back. The texels come back padded to a whole word. Checked as
    /// [`MaskTables::new`] checks.
    pub fn from_words(words: &[u32]) -> Result<MaskTables, String> {
        let header_words = size_of::<MaskHeader>() / 4;
        let header = words
            .get(..header_words)
            .ok_or_else(|| format!("{} words hold no header", words.len()))?;
        let h: MaskHeader = bytemuck::pod_read_unaligned(bytemuck::cast_slice(header));
        let part = |from: u32, to: u32| {
            words.get(from as usize..to as usize).ok_or_else(|| {
                format!(
                    "the words {from}..{to} are past the {} written",
                    words.len()
                )
            })
        };
        MaskTables::new(
            part(h.states, h.triangles)?.to_vec(),
            bytemuck::pod_collect_to_vec(part(h.triangles, h.materials)?),
            bytemuck::pod_collect_to_vec(part(h.materials, h.texels)?),
            (words.get(h.texels as usize..).unwrap_or(&[]).iter())
                .flat_map(|w| w.to_le_bytes())
                .collect(),
            part(h.instance_bases, h.states)?.to_vec(),
        )
    }

    /// The instance bases in another layout's instance order: `order[k]` is the index in
    /// [`MaskTables::instance_bases`] of that layout's instance `k`
    /// ([`WideBvh::instance_order`](crate::WideBvh::instance_order)).
    pub fn bases_in_order(&self, order: &[u32]) -> Vec<u32> {
        order
            .iter()
            .map(|&i| self.base(Some(i)))
            .collect::<Vec<u32>>()
    }

    /// Bytes of the tables on a device ([`MaskTables::words`]).
    pub fn device_bytes(&self) -> usize {
        4 * self.words(&self.instance_bases).len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_place_every_table_where_the_header_says() {
        let tables = MaskTables::new(
            vec![MASK_OPAQUE, 0, MASK_TRANSPARENT],
            vec![MaskTriangle {
                uv: [0.0, 0.0, 1.0, 0.0, 0.0, 1.0],
                material: 0,
                micro: [0; MICRO_WORDS],
            }],
            vec![MaskMaterial {
                first_texel: 0,
                width: 2,
                height: 3,
                wrap: MaskMaterial::pack_wrap([Wrap::ClampToEdge, Wrap::MirroredRepeat]),
                min_texel: 128,
            }],
            vec![1, 2, 3, 4, 5, 6],
            vec![],
        )
        .expect("valid");
        let w = tables.words(&[7, NO_MASKS]);
        let h: MaskHeader = bytemuck::cast([w[0], w[1], w[2], w[3], w[4]]);
        assert_eq!(
            &w[h.instance_bases as usize..h.states as usize],
            &[7, NO_MASKS]
        );
        assert_eq!(
            &w[h.states as usize..h.triangles as usize],
            &tables.states[..]
        );
        assert_eq!(w[h.triangles as usize + 2], 1.0f32.to_bits());
        assert_eq!(w[h.triangles as usize + 6], 0, "the triangle's material");
        assert_eq!(w[h.materials as usize + 3], 1 | (2 << 2));
        assert_eq!(
            &w[h.texels as usize..],
            &[0x0403_0201, 0x0000_0605],
            "little end first"
        );
        assert_eq!(
            tables.materials[0].wraps(),
            [Wrap::ClampToEdge, Wrap::MirroredRepeat]
        );
        // Read back from the words: the same tables, the bases as written, the texels
        // padded to a whole word.
        assert!(
            MaskTables::from_words(&w).is_err(),
            "a base past the states"
        );
        let w = tables.words(&[2, NO_MASKS]);
        let back = MaskTables::from_words(&w).expect("the words read back");
        assert_eq!(back.instance_bases, [2, NO_MASKS]);
        assert_eq!(back.texels, [1, 2, 3, 4, 5, 6, 0, 0]);
        let padded = MaskTables {
            texels: back.texels.clone(),
            instance_bases: vec![],
            ..tables.clone()
        };
        assert_eq!(
            MaskTables {
                instance_bases: vec![],
                ..back
            },
            padded
        );
        assert!(MaskTables::from_words(&w[..3]).is_err());
        assert!(MaskTables::from_words(&w[..h.materials as usize]).is_err());
    }

    /// Every point of the triangle falls in the micro-triangle its slot names, and every
    /// slot of the triangle is reached.
    #[test]
    fn micro_slots_tile_the_triangle() {
        let n = 97;
        let mut seen = std::collections::BTreeSet::new();
        for a in 0..=n {
            for b in 0..=(n - a) {
                let (u, v) = (a as f32 / n as f32, b as f32 / n as f32);
                let slot = micro_slot(u, v);
                seen.insert(slot);
                let [p, q, r] = micro_corners(slot);
                // Barycentric coordinates of (u, v) in the micro-triangle, all >= 0.
                let d = (q.0 - p.0) * (r.1 - p.1) - (r.0 - p.0) * (q.1 - p.1);
                let l1 = ((u - p.0) * (r.1 - p.1) - (r.0 - p.0) * (v - p.1)) / d;
                let l2 = ((q.0 - p.0) * (v - p.1) - (u - p.0) * (q.1 - p.1)) / d;
                let eps = 1e-5;
                assert!(
                    l1 >= -eps && l2 >= -eps && l1 + l2 <= 1.0 + eps,
                    "({u}, {v}) in slot {slot} {:?}",
                    [p, q, r]
                );
            }
        }
        let cells = (MICRO_CELLS * MICRO_CELLS) as usize;
        assert_eq!(seen.len(), cells, "{} micro-triangles", seen.len());
        // Outside the triangle by rounding: still a slot of it.
        assert_eq!(micro_slot(-1e-9, 1.0 + 1e-7), micro_slot(0.0, 0.999));
    }

    #[test]
    fn bad_tables_are_refused_by_what_is_wrong() {
        let e = MaskTables::new(vec![3], vec![], vec![], vec![], vec![]).unwrap_err();
        assert!(e.contains("names no triangle"), "{e}");
        let mat = MaskMaterial {
            first_texel: 2,
            width: 2,
            height: 2,
            wrap: 0,
            min_texel: 1,
        };
        let e = MaskTables::new(vec![], vec![], vec![mat], vec![0; 5], vec![]).unwrap_err();
        assert!(e.contains("masked material 0"), "{e}");
        let e = MaskTables::new(vec![], vec![], vec![], vec![], vec![2]).unwrap_err();
        assert!(e.contains("instance 0"), "{e}");
    }

    #[test]
    fn states_settle_and_triangles_sample() {
        // One 2x1 texture: left texel cut, right texel kept.
        let tables = MaskTables::new(
            vec![MASK_OPAQUE, MASK_TRANSPARENT, 0],
            vec![MaskTriangle {
                uv: [0.0, 0.0, 1.0, 0.0, 0.0, 1.0],
                material: 0,
                micro: [0; MICRO_WORDS],
            }],
            vec![MaskMaterial {
                first_texel: 0,
                width: 2,
                height: 1,
                wrap: 0,
                min_texel: 128,
            }],
            vec![0, 255],
            vec![],
        )
        .expect("valid");
        assert!(tables.accept(0, 0, 0.2, 0.2));
        assert!(!tables.accept(0, 1, 0.2, 0.2));
        assert!(!tables.accept(0, 2, 0.1, 0.1), "u = 0.1: the cut texel");
        assert!(tables.accept(0, 2, 0.7, 0.1), "u = 0.7: the kept one");
        assert!(tables.accept(NO_MASKS, 1, 0.0, 0.0), "an unmasked instance");
        assert_eq!(tables.counts(), (2, 2));
        // A micromap settles its slots without the texture, whatever the texel says.
        let mut t = tables.clone();
        t.triangles[0].set_micro_state(micro_slot(0.1, 0.1), MICRO_OPAQUE);
        t.triangles[0].set_micro_state(micro_slot(0.7, 0.1), MICRO_TRANSPARENT);
        assert!(t.accept(0, 2, 0.1, 0.1) && !t.accept(0, 2, 0.7, 0.1));
        assert!(
            !t.accept(0, 2, 0.2, 0.01),
            "an unset slot tests: the cut texel"
        );
        assert_eq!(t.counts(), (2, 1));
    }
}
