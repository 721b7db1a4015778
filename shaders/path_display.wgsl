// path_display.wgsl: the path tracer's sums shown without a readback: each pixel's mean
// radiance times the exposure, tone mapped (`x / (1 + x)` of twice the value) and encoded
// with the sRGB curve into an RGBA8 texture a renderer samples
// (`bvhtrace_path::Accumulation::to_srgb8` on the host, up to the rounding of `pow`).

struct PathDisplay {
    width: u32,
    height: u32,
    exposure: f32,
    pad: u32,
}

@group(0) @binding(0) var<uniform> path_display: PathDisplay;
@group(0) @binding(1) var<storage, read> path_sums: array<vec4<f32>>;
@group(0) @binding(2) var path_image: texture_storage_2d<rgba8unorm, write>;

fn path_encode(c: f32) -> f32 {
    let x = max(c * path_display.exposure, 0.0);
    let t = 2.0 * x / (1.0 + 2.0 * x);
    return select(1.055 * pow(t, 1.0 / 2.4) - 0.055, 12.92 * t, t <= 0.0031308);
}

@compute @workgroup_size(8, 8)
fn path_display_main(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= path_display.width || id.y >= path_display.height) {
        return;
    }
    let s = path_sums[id.y * path_display.width + id.x];
    let n = max(s.w, 1.0);
    let c = vec3<f32>(path_encode(s.x / n), path_encode(s.y / n), path_encode(s.z / n));
    textureStore(path_image, vec2<i32>(id.xy), vec4<f32>(c, 1.0));
}
