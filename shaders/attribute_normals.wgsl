// attribute_normals.wgsl: per-vertex normals (glTF `NORMAL`) for smooth shading: three
// `vec4` per triangle (w unused), indexed by the hit's primitive (input) index.
//
// An optional attribute module: composed in only when the scene has normals *and* the job
// shades with them (`bvhtrace_gpu::VertexAttributes`). No entry point reads it yet (shading
// happens on the host from the geometric normal), so no pipeline composes it today and no
// upload carries normals; a positions-only scene's modules never declare it.

@group(0) @binding(3) var<storage, read> vertex_normals: array<vec4<f32>>;

// The interpolated unit normal at `h` (barycentrics `u`, `v` of corners 1 and 2).
fn bvh_shading_normal(h: BvhHit) -> vec3<f32> {
    let b = 3u * h.prim;
    let n = vertex_normals[b].xyz * (1.0 - h.u - h.v) + vertex_normals[b + 1u].xyz * h.u
        + vertex_normals[b + 2u].xyz * h.v;
    return normalize(n);
}
