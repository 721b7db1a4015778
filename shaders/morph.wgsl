// morph.wgsl: morph targets on the device, twin of `bvhtrace_scene::morph_vertex`
// operation for operation (`GpuMorph` in bvhtrace-gpu runs it): each vertex starts at its
// base position and adds `delta * weight` for each target in order whose weight is not
// zero, coordinate by coordinate. The positions it writes are what `GpuSkin` skins or
// `GpuRefit` reads.

struct MorphParams {
    // Vertices.
    vertices: u32,
    // Targets: entries of `morph_weights`, blocks of `morph_deltas`.
    targets: u32,
    // Invocations per row of the dispatch grid.
    row: u32,
    pad: u32,
}

@group(0) @binding(0) var<uniform> morph_params: MorphParams;
// Base positions, packed `xyz`.
@group(0) @binding(1) var<storage, read> morph_base: array<f32>;
// Position deltas, packed `xyz`, target by target: target `i`, vertex `v` at `i * vertices + v`.
@group(0) @binding(2) var<storage, read> morph_deltas: array<f32>;
@group(0) @binding(3) var<storage, read> morph_weights: array<f32>;
// Morphed positions, packed `xyz`.
@group(0) @binding(4) var<storage, read_write> morph_positions: array<f32>;

@compute @workgroup_size(256)
fn morph_vertices(@builtin(global_invocation_id) gid: vec3<u32>) {
    let v = gid.x + gid.y * morph_params.row;
    if (v >= morph_params.vertices) {
        return;
    }
    var p = vec3<f32>(morph_base[3u * v], morph_base[3u * v + 1u], morph_base[3u * v + 2u]);
    for (var i = 0u; i < morph_params.targets; i++) {
        let w = morph_weights[i];
        if (w != 0.0) {
            let d = 3u * (i * morph_params.vertices + v);
            p = vec3<f32>(p.x + morph_deltas[d] * w, p.y + morph_deltas[d + 1u] * w, p.z + morph_deltas[d + 2u] * w);
        }
    }
    morph_positions[3u * v] = p.x;
    morph_positions[3u * v + 1u] = p.y;
    morph_positions[3u * v + 2u] = p.z;
}
