// bvh_textures_triangles.wgsl: the triangles of a `BvhStorage::Textures` upload as a
// read-only `Rgba32Uint` storage texture (binding 1), three texels per triangle,
// `FlatTriangle`'s bytes: `(v0, prim)`, `(v1, pad)`, `(v2, pad)`, in the leaf order of the
// layout composed before it: the binary tree's (`bvh_textures.wgsl`) or the wide tree's
// (`bvh_textures_wide.wgsl`, `WideBvh::triangles`). The twin of
// `bvh_buffers_triangles.wgsl`, and the home of the texel addressing every BVH texture
// shares.

// Texel `t` of every BVH texture is at `(t % 8192, t / 8192)` (`bvhtrace_gpu::TEXEL_ROW`).
const BVH_TEXEL_ROW_LOG2: u32 = 13u;
const BVH_TEXEL_ROW_MASK: u32 = 8191u;

fn bvh_texel_coord(t: u32) -> vec2<u32> {
    return vec2<u32>(t & BVH_TEXEL_ROW_MASK, t >> BVH_TEXEL_ROW_LOG2);
}

@group(0) @binding(1) var bvh_triangle_texels: texture_storage_2d<rgba32uint, read>;

fn bvh_load_triangle(i: u32) -> BvhTriangle {
    let t = 3u * i;
    let a = textureLoad(bvh_triangle_texels, bvh_texel_coord(t));
    let b = textureLoad(bvh_triangle_texels, bvh_texel_coord(t + 1u));
    let c = textureLoad(bvh_triangle_texels, bvh_texel_coord(t + 2u));
    return BvhTriangle(
        bitcast<vec3<f32>>(a.xyz),
        a.w,
        bitcast<vec3<f32>>(b.xyz),
        b.w,
        bitcast<vec3<f32>>(c.xyz),
        c.w,
    );
}
