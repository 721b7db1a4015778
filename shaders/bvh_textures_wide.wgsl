// bvh_textures_wide.wgsl: the wide layout's nodes (`WideBvh::nodes`) as a read-only
// `Rgba32Uint` storage texture at binding 0 (`BvhStorage::Textures`), and the same fetch
// functions as `bvh_buffers_wide.wgsl`. Composed for `Traversal::Wide` in place of
// `bvh_textures.wgsl`, followed by `bvh_textures_triangles.wgsl` (the wide tree's
// triangles, and the texel addressing) and the instances file.
//
// Why: a storage-buffer load with a per-lane index is a loop over lavapipe's 8 lanes per
// 32-bit word (20 words a node), a texel load one gather of 16 bytes per lane
// (`bvh_textures.wgsl`).
//
// Five texels per node, `WideNode`'s bytes in order, so the upload is the Rust nodes as
// they are: `(origin, exponents)`, `(child_base, triangle_base, counts)`,
// `(q_lo[0], q_lo[1])`, `(q_lo[2], q_hi[0])`, `(q_hi[1], q_hi[2])`. Node `i` is texels
// `5i .. 5i + 5` at `bvh_texel_coord`; 5 does not divide a row, so a node may span two rows
// and each texel's place is computed on its own.

// The wide layout (`bvh_instances.wgsl` counts its top-level nodes by it).
const BVH_WIDE_LAYOUT: bool = true;

// Texels per node: `size_of::<WideNode>() / 16`.
const BVH_WIDE_NODE_TEXELS: u32 = 5u;

@group(0) @binding(0) var bvh_wide_node_texels: texture_storage_2d<rgba32uint, read>;

// Texel `k` (0..5) of node `i`.
fn bvh_wide_texel(i: u32, k: u32) -> vec4<u32> {
    return textureLoad(bvh_wide_node_texels, bvh_texel_coord(BVH_WIDE_NODE_TEXELS * i + k));
}

fn bvh_load_wide_node(i: u32) -> BvhWideNode {
    let a = bvh_wide_texel(i, 0u);
    let b = bvh_wide_texel(i, 1u);
    let c = bvh_wide_texel(i, 2u);
    let d = bvh_wide_texel(i, 3u);
    let e = bvh_wide_texel(i, 4u);
    return BvhWideNode(
        bitcast<vec3<f32>>(a.xyz),
        a.w,
        b.x,
        b.y,
        b.zw,
        array<vec2<u32>, 3>(c.xy, c.zw, d.xy),
        array<vec2<u32>, 3>(d.zw, e.xy, e.zw),
    );
}

// What the walk reads of node `i` when it goes back to a group it pushed
// (`traverse_wide.wgsl`): two texels of the five, `imask` (byte 3 of `exponents`) and the
// children's places.
fn bvh_load_wide_links(i: u32) -> BvhWideLinks {
    let a = bvh_wide_texel(i, 0u);
    let b = bvh_wide_texel(i, 1u);
    return BvhWideLinks(a.w >> 24u, b.x, b.y, b.zw);
}
