// texel.wgsl: the nearest texel of a texture along an axis, as `bvhtrace_core::alpha`
// samples it, for the alpha masks' test and for a shader's own textures (the path
// tracer's). Composed with every library.

// `bvhtrace_core::alpha::texel_index`: the texel along an axis of `size` texels for
// coordinate `x`, wrapped by mode `wrap` (0 repeat, 1 clamp to edge, 2 mirrored repeat).
fn bvh_texel_index(x: f32, size: u32, wrap: u32) -> u32 {
    if ((bitcast<u32>(x) & 0x7f800000u) == 0x7f800000u) {
        return 0u;
    }
    var f = x - floor(x);
    if (wrap == 1u) {
        f = clamp(x, 0.0, 1.0);
    } else if (wrap == 2u) {
        let g = x - 2.0 * floor(x * 0.5);
        f = select(g, 2.0 - g, g > 1.0);
    }
    return min(u32(floor(f * f32(size))), size - 1u);
}
