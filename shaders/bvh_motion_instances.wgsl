// bvh_motion_instances.wgsl: moving instances (`bvhtrace_core::motion::MotionInstancedBvh`,
// joined as `MovingInstancesLayout`), in place of `bvh_instances.wgsl`, composed after
// `bvh_motion_buffers.wgsl`: an instance's transform at the current ray's time is its
// steps' mixed entry by entry and inverted here, twin of
// `MovingInstance::world_to_object_at`, so `traverse_instances.wgsl` enters it unchanged.
//
// Binding 4: the instances in the top level's leaf order (`MovingInstanceRecord`); binding
// 7: their object-to-world transforms, three rows each.

const BVH_INSTANCED: bool = true;

// `MovingInstanceRecord` (16 bytes).
struct BvhMovingInstance {
    root: u32,
    prim_base: u32,
    first_transform: u32,
    transforms: u32,
}

// Three rows of an affine transform (48 bytes).
struct BvhRows {
    rows: array<vec4<f32>, 3>,
}

@group(0) @binding(4) var<storage, read> bvh_moving_instances: array<BvhMovingInstance>;
@group(0) @binding(7) var<storage, read> bvh_instance_transforms: array<BvhRows>;

// `a x b` as glam's `Vec3::cross` computes it (`motion::invert_rows`).
fn bvh_cross_ordered(a: vec3<f32>, b: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

// Twin of `motion::invert_rows`: the 3x3 part's inverse by cross products of its columns
// over its determinant, the translation taken back through it.
fn bvh_invert_rows(m: array<vec4<f32>, 3>) -> array<vec4<f32>, 3> {
    let c0 = vec3<f32>(m[0].x, m[1].x, m[2].x);
    let c1 = vec3<f32>(m[0].y, m[1].y, m[2].y);
    let c2 = vec3<f32>(m[0].z, m[1].z, m[2].z);
    let r0 = bvh_cross_ordered(c1, c2);
    let r1 = bvh_cross_ordered(c2, c0);
    let r2 = bvh_cross_ordered(c0, c1);
    let det = c0.x * r0.x + c0.y * r0.y + c0.z * r0.z;
    let inv = 1.0 / det;
    let t = vec3<f32>(m[0].w, m[1].w, m[2].w);
    let s0 = r0 * inv;
    let s1 = r1 * inv;
    let s2 = r2 * inv;
    return array<vec4<f32>, 3>(
        vec4<f32>(s0, -(s0.x * t.x + s0.y * t.y + s0.z * t.z)),
        vec4<f32>(s1, -(s1.x * t.x + s1.y * t.y + s1.z * t.z)),
        vec4<f32>(s2, -(s2.x * t.x + s2.y * t.y + s2.z * t.z)),
    );
}

// Instance `i` at the current ray's time: twin of `MovingInstance::transform_at`, then
// inverted.
fn bvh_load_instance(i: u32) -> BvhInstance {
    let inst = bvh_moving_instances[i];
    var rows = bvh_instance_transforms[inst.first_transform].rows;
    if (inst.transforms > 1u) {
        let a = bvh_instance_transforms[inst.first_transform + bvh_time_segment].rows;
        let b = bvh_instance_transforms[inst.first_transform + bvh_time_segment + 1u].rows;
        let f = bvh_time_fraction;
        for (var r = 0u; r < 3u; r += 1u) {
            rows[r] = a[r] * (1.0 - f) + b[r] * f;
        }
    }
    return BvhInstance(bvh_invert_rows(rows), inst.root, inst.prim_base, 0xffu, 0u);
}

fn bvh_instance_count() -> u32 {
    return arrayLength(&bvh_moving_instances);
}

// One instance per top-level leaf: `2n - 1` top-level nodes.
fn bvh_top_nodes() -> u32 {
    return 2u * arrayLength(&bvh_moving_instances) - 1u;
}
