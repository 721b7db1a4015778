// entry_rays_buffer.wgsl: the batch's rays and hits in storage buffers (`RayInput::Buffer`,
// the default, and the only input of `GpuBvh::record`, which traces the caller's buffers).
// The hits buffer holds exactly the chunk's rays, so its length is the ray count.

@group(1) @binding(0) var<storage, read> rays: array<Ray>;

fn load_ray(i: u32) -> Ray {
    return rays[i];
}

@group(1) @binding(1) var<storage, read_write> hits: array<Hit>;

fn store_hit(i: u32, hit: Hit) {
    hits[i] = hit;
}

fn batch_len() -> u32 {
    return arrayLength(&hits);
}
