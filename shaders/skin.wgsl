// skin.wgsl: linear blend skinning on the device, twin of `bvhtrace_scene::skin_vertex`
// operation for operation (`GpuSkin` in bvhtrace-gpu runs it): each vertex's blended
// matrix, element by element, weights in order, then each coordinate
// `((m0 x + m1 y) + m2 z) + m3`. The positions it writes are what `GpuRefit` reads.

struct SkinParams {
    // Vertices.
    vertices: u32,
    // Joints in `skin_matrices`.
    joints: u32,
    // Invocations per row of the dispatch grid.
    row: u32,
    pad: u32,
}

@group(0) @binding(0) var<uniform> skin_params: SkinParams;
// Bind-pose positions, packed `xyz`.
@group(0) @binding(1) var<storage, read> skin_bind: array<f32>;
@group(0) @binding(2) var<storage, read> skin_joints: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> skin_weights: array<vec4<f32>>;
// Each joint's `joint_world * inverse_bind`.
@group(0) @binding(4) var<storage, read> skin_matrices: array<mat4x4<f32>>;
// Skinned positions, packed `xyz`.
@group(0) @binding(5) var<storage, read_write> skin_positions: array<f32>;

@compute @workgroup_size(256)
fn skin_vertices(@builtin(global_invocation_id) gid: vec3<u32>) {
    let v = gid.x + gid.y * skin_params.row;
    if (v >= skin_params.vertices) {
        return;
    }
    let j = skin_joints[v];
    let w = skin_weights[v];
    var m = mat4x4<f32>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
    for (var k = 0u; k < 4u; k++) {
        if (w[k] != 0.0 && j[k] < skin_params.joints) {
            let src = skin_matrices[j[k]];
            m = mat4x4<f32>(m[0] + src[0] * w[k], m[1] + src[1] * w[k], m[2] + src[2] * w[k], m[3] + src[3] * w[k]);
        }
    }
    let p = vec3<f32>(skin_bind[3u * v], skin_bind[3u * v + 1u], skin_bind[3u * v + 2u]);
    let r = ((m[0] * p.x + m[1] * p.y) + m[2] * p.z) + m[3];
    skin_positions[3u * v] = r.x;
    skin_positions[3u * v + 1u] = r.y;
    skin_positions[3u * v + 2u] = r.z;
}
