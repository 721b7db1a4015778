// entry_rays_texture.wgsl: the batch's rays in a read-only `Rgba32Uint` storage texture
// and its hits in a write-only one (`RayInput::Texture`). Two texels per ray:
// `(origin, t_min)` and `(dir, t_max)`, the bytes of `Ray`; ray `i` is texels `2i` and
// `2i + 1`, at `(t % 8192, t / 8192)` as in `bvh_textures_triangles.wgsl`
// (`bvhtrace_gpu::TEXEL_ROW`), both on one row. One texel per hit, the bytes of `Hit`: hit `i` at `(i % 8192, i / 8192)`.
//
// Why: on lavapipe a storage-buffer access with a per-lane index is a loop over the 8
// lanes, one 32-bit word at a time, each word moved through memory; loading the 8 words of
// a ray that way was about a quarter of the full-stack kernel's time on `bunny_69k`, and
// storing the 4 words of a hit 7%. A texel load is one address computation and a vector
// gather, a texel store one loop over the lanes. `GpuBvh::trace` uses them with
// `BvhStorage::Textures` (the layout for CPU drivers).

@group(1) @binding(0) var ray_texels: texture_storage_2d<rgba32uint, read>;

fn bvh_load_ray(i: u32) -> BvhRay {
    let t = 2u * i;
    let c = vec2<u32>(t & 8191u, t >> 13u);
    let a = textureLoad(ray_texels, c);
    let b = textureLoad(ray_texels, c + vec2<u32>(1u, 0u));
    return BvhRay(bitcast<vec3<f32>>(a.xyz), bitcast<f32>(a.w), bitcast<vec3<f32>>(b.xyz), bitcast<f32>(b.w));
}

@group(1) @binding(1) var hit_texels: texture_storage_2d<rgba32uint, write>;

fn bvh_store_hit(i: u32, hit: BvhHit) {
    let c = vec2<u32>(i & 8191u, i >> 13u);
    let texel = vec4<u32>(bitcast<u32>(hit.t), hit.prim, bitcast<u32>(hit.u), bitcast<u32>(hit.v));
    textureStore(hit_texels, c, texel);
}

// Whole rows of rays: the host dispatches one workgroup per 64 rays of the chunk, and the
// invocations past its end trace what is left in the row and write hits it does not read.
fn bvh_batch_len() -> u32 {
    let d = textureDimensions(hit_texels);
    return d.x * d.y;
}
