// entry_rays_texture.wgsl: the batch's rays in a read-only `Rgba32Uint` storage texture
// (`RayInput::Texture`), two texels per ray: `(origin, t_min)` and `(dir, t_max)`, the
// bytes of `Ray`. Ray `i` is texels `2i` and `2i + 1`, at `(t % 8192, t / 8192)` as in
// `bvh_textures.wgsl` (`bvhtrace_gpu::TEXEL_ROW`); both are on one row.
//
// Why: on lavapipe a storage-buffer load with a per-lane index is a loop over the 8 lanes,
// one component at a time, each lane's word inserted through memory; loading the 8 words
// of a ray that way was about a quarter of the full-stack kernel's time on `bunny_69k`.
// A texel load is one address computation and a vector gather. `GpuBvh::trace` uses it
// with `BvhStorage::Textures` (the layout for CPU drivers).

@group(1) @binding(0) var ray_texels: texture_storage_2d<rgba32uint, read>;

fn load_ray(i: u32) -> Ray {
    let t = 2u * i;
    let c = vec2<u32>(t & 8191u, t >> 13u);
    let a = textureLoad(ray_texels, c);
    let b = textureLoad(ray_texels, c + vec2<u32>(1u, 0u));
    return Ray(bitcast<vec3<f32>>(a.xyz), bitcast<f32>(a.w), bitcast<vec3<f32>>(b.xyz), bitcast<f32>(b.w));
}
