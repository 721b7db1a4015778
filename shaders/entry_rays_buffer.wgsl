// entry_rays_buffer.wgsl: the batch's rays in a storage buffer (`RayInput::Buffer`, the
// default, and the only input of `GpuBvh::record`, which traces the caller's buffers).

@group(1) @binding(0) var<storage, read> rays: array<Ray>;

fn load_ray(i: u32) -> Ray {
    return rays[i];
}
