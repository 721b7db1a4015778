// entry_rays_buffer.wgsl: the batch's rays and hits in storage buffers (`RayInput::Buffer`,
// the default, and the only input of `GpuBvh::record`, which traces the caller's buffers).
// The hits buffer holds exactly the chunk's rays, so its length is the ray count.

@group(1) @binding(0) var<storage, read> rays: array<BvhRay>;

fn bvh_load_ray(i: u32) -> BvhRay {
    return rays[i];
}

@group(1) @binding(1) var<storage, read_write> hits: array<BvhHit>;

fn bvh_store_hit(i: u32, hit: BvhHit) {
    hits[i] = hit;
}

fn bvh_batch_len() -> u32 {
    return arrayLength(&hits);
}
