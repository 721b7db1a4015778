//! Where the kernels read the tree and the rays from: storage buffers, or texel textures
//! (the layout CPU drivers reward), and the WGSL files that declare each.

use crate::shaders::{self, Wgsl};

/// Where the kernels read the BVH from. Both give bit-identical results.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum BvhStorage {
    /// Storage buffers in the exact layout of [`bvhtrace_core::flat`]
    /// (`bvh_buffers.wgsl`): the portable choice, and the one to bind from your own
    /// shaders when you already hold the buffers.
    #[default]
    Buffers,
    /// `Rgba32Uint`/`R32Uint` textures of [`TEXEL_ROW`] texels per row
    /// (`bvh_textures.wgsl`, `bvh_textures_wide.wgsl`). On lavapipe a texel fetch is a
    /// vector gather while a storage-buffer load is a per-lane scalar loop: traversal is
    /// about 2.5x faster.
    Textures,
}

impl BvhStorage {
    /// Both, buffers first.
    pub const ALL: [BvhStorage; 2] = [BvhStorage::Buffers, BvhStorage::Textures];

    /// The other storage.
    pub fn other(self) -> BvhStorage {
        match self {
            BvhStorage::Buffers => BvhStorage::Textures,
            BvhStorage::Textures => BvhStorage::Buffers,
        }
    }

    /// `buffer` or `texture`, as sentences say it.
    pub fn name(self) -> &'static str {
        match self {
            BvhStorage::Buffers => "buffer",
            BvhStorage::Textures => "texture",
        }
    }

    /// The file declaring this storage's binding of the binary layout's nodes and their
    /// fetch functions; [`BvhStorage::triangles_wgsl`] is composed after it.
    pub fn wgsl(self) -> Wgsl {
        match self {
            BvhStorage::Buffers => shaders::BVH_BUFFERS,
            BvhStorage::Textures => shaders::BVH_TEXTURES,
        }
    }

    /// The file declaring this storage's binding of the wide layout's nodes
    /// (`WideBvh::nodes`, binding 0), in place of [`BvhStorage::wgsl`] for the wide walk.
    pub fn wide_wgsl(self) -> Wgsl {
        match self {
            BvhStorage::Buffers => shaders::BVH_BUFFERS_WIDE,
            BvhStorage::Textures => shaders::BVH_TEXTURES_WIDE,
        }
    }

    /// The file declaring this storage's triangle binding (binding 1), shared by both
    /// layouts (for textures, with the texel addressing every BVH texture uses).
    pub fn triangles_wgsl(self) -> Wgsl {
        match self {
            BvhStorage::Buffers => shaders::BVH_BUFFERS_TRIANGLES,
            BvhStorage::Textures => shaders::BVH_TEXTURES_TRIANGLES,
        }
    }

    /// The file declaring this storage's escape-link binding (binding 2).
    pub fn escapes_wgsl(self) -> Wgsl {
        match self {
            BvhStorage::Buffers => shaders::BVH_BUFFERS_ESCAPES,
            BvhStorage::Textures => shaders::BVH_TEXTURES_ESCAPES,
        }
    }
}

/// Texels per row of the [`BvhStorage::Textures`] textures (`BVH_TEXEL_ROW_MASK + 1` in
/// `bvh_textures_triangles.wgsl`; 8192 is WebGPU's guaranteed `max_texture_dimension_2d`).
pub const TEXEL_ROW: u32 = 8192;

/// Rows of a [`TEXEL_ROW`]-wide texture holding `texels` texels (at least one).
pub fn texel_rows(texels: u64) -> u64 {
    texels.div_ceil(u64::from(TEXEL_ROW)).max(1)
}

/// The `(width, rows)` of the texture holding `texels` texels. One row is only as wide as
/// its texels (texel `t` is still at `(t, 0)`): no padding the kernel never reads. Taller
/// textures are [`TEXEL_ROW`] wide and pad their last row.
pub fn texel_extent(texels: u64) -> (u32, u32) {
    let rows = texel_rows(texels) as u32;
    if rows == 1 {
        ((texels as u32).max(1), 1)
    } else {
        (TEXEL_ROW, rows)
    }
}

/// Where an entry point reads the batch's rays and writes its hits (bindings 0 and 1 of
/// the batch group).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum RayInput {
    /// Storage buffers of [`bvhtrace_core::Ray`]s (`rays`) and [`bvhtrace_core::Hit`]s
    /// (`hits`): what a recorded trace reads, and every trace with [`BvhStorage::Buffers`].
    #[default]
    Buffer,
    /// `Rgba32Uint` storage textures, [`TEXEL_ROW`] texels wide: the rays read-only, two
    /// texels per ray (`ray_texels`), the hits write-only, one texel per hit
    /// (`hit_texels`; `entry_rays_texture.wgsl`). What a trace uses with
    /// [`BvhStorage::Textures`], the layout for CPU drivers, where a texel access is one
    /// vector gather or one loop over the lanes and a buffer access a loop over the lanes
    /// per 32-bit word.
    Texture,
}

impl RayInput {
    /// What a trace uses with the BVH in `storage`: a texture with textures (CPU drivers),
    /// a buffer with buffers.
    pub fn for_storage(storage: BvhStorage) -> RayInput {
        match storage {
            BvhStorage::Textures => RayInput::Texture,
            BvhStorage::Buffers => RayInput::Buffer,
        }
    }

    /// The file declaring this input's two bindings, `bvh_load_ray`, `bvh_store_hit` and
    /// `bvh_batch_len`.
    pub fn wgsl(self) -> Wgsl {
        match self {
            RayInput::Buffer => shaders::ENTRY_RAYS_BUFFER,
            RayInput::Texture => shaders::ENTRY_RAYS_TEXTURE,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A one-row texture is as wide as its texels; a taller one pads its last row.
    #[test]
    fn texel_extents_pad_only_tall_textures() {
        assert_eq!(texel_extent(5), (5, 1));
        assert_eq!(texel_extent(0), (1, 1));
        let row = u64::from(TEXEL_ROW);
        assert_eq!(texel_extent(row + 1), (TEXEL_ROW, 2));
    }
}
