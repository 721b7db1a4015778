// bvh_textures_parents.wgsl: the parent links of a `BvhStorage::Textures` upload, one
// `R32Uint` texel per node (texel `i` at `texel_coord(i)` of `bvh_textures.wgsl`).
// Composed in only when the traversal climbs the tree (stackless, short stack).

@group(0) @binding(2) var bvh_parent_texels: texture_storage_2d<r32uint, read>;

fn load_parent(i: u32) -> u32 {
    return textureLoad(bvh_parent_texels, texel_coord(i)).x;
}
