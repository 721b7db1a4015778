// bvh_textures_escapes.wgsl: the escape links of a `BvhStorage::Textures` upload
// (`FlatBvh::escapes`), one `R32Uint` texel per node and octant: link `e = escape_index(i,
// oct)` (`traverse_short_stack.wgsl`) at `bvh_texel_coord(e)`
// (`bvh_textures_triangles.wgsl`). Composed in only when the traversal reads them
// (stackless, short stack).

@group(0) @binding(2) var bvh_escape_texels: texture_storage_2d<r32uint, read>;

// Where a walk in octant `oct` goes when it is done with node `i`'s subtree
// (`NO_ESCAPE`: nowhere, the walk is over).
fn bvh_load_escape(i: u32, oct: u32) -> u32 {
    return textureLoad(bvh_escape_texels, bvh_texel_coord(bvh_escape_index(i, oct))).x;
}
