// bvh_motion_buffers.wgsl: a moving mesh's tree (`bvhtrace_core::motion::MotionBvh`) in
// storage buffers, in place of `bvh_buffers.wgsl` and `bvh_buffers_triangles.wgsl`, so the
// binary walks run on it unchanged: its fetch functions give a node's box and a triangle
// where they are at the current ray's time (`bvh_set_time`, which `entry_ray_times.wgsl`
// calls as it loads a ray). Twin of `MotionBvh::node_box` and `MotionBvh::visit_leaf`.
// Composed with `bvh_motion_instances.wgsl`, it holds moving instances' joined tree
// (`MovingInstancesLayout`) instead: the top level's boxes move, the meshes' are static.
//
// Binding 0: the nodes, each box over the whole shutter (`FlatNode`); binding 1: the
// triangles at every time step, step `k`'s at `k * count` (`MotionBvh::triangles`);
// binding 6: each node's box at every step, node `i`'s at step `k` at `i * steps + k`
// (`MotionBvh::step_boxes`, read with linear bounds only).

const BVH_WIDE_LAYOUT: bool = false;

// Time steps (`MotionBvh::time_steps`), at least 2.
override BVH_TIME_STEPS: u32 = 2u;
// Linear bounds (a box per step) rather than merged ones (`TimeBounds`).
override BVH_LINEAR_BOUNDS: bool = true;

// `MotionBox` (32 bytes).
struct BvhMotionBox {
    min: vec3<f32>,
    max: vec3<f32>,
}

@group(0) @binding(0) var<storage, read> bvh_nodes: array<BvhNode>;
@group(0) @binding(1) var<storage, read> bvh_triangles: array<BvhTriangle>;
@group(0) @binding(6) var<storage, read> bvh_step_boxes: array<BvhMotionBox>;

// The current ray's time segment (between steps `s` and `s + 1`) and how far through it.
var<private> bvh_time_segment: u32;
var<private> bvh_time_fraction: f32;

// Twin of `motion::time_segment` (Embree's `getTimeSegment`), the time clamped to [0, 1].
fn bvh_set_time(time: f32) {
    let segments = f32(BVH_TIME_STEPS - 1u);
    let scaled = clamp(time, 0.0, 1.0) * segments;
    let s = clamp(floor(scaled), 0.0, segments - 1.0);
    bvh_time_segment = u32(s);
    bvh_time_fraction = scaled - s;
}

// Twin of `motion::lerp_box`: widened by 2^-20 of the largest coordinate involved.
fn bvh_lerp_box(a: BvhMotionBox, b: BvhMotionBox, f: f32) -> BvhMotionBox {
    let g = 1.0 - f;
    let scale = max(max(abs(a.min), abs(a.max)), max(abs(b.min), abs(b.max)));
    let slack = scale * (1.0 / 1048576.0);
    return BvhMotionBox(g * a.min + f * b.min - slack, g * a.max + f * b.max + slack);
}

// Twin of `motion::lerp_point`.
fn bvh_lerp_point(a: vec3<f32>, b: vec3<f32>, f: f32) -> vec3<f32> {
    return clamp((1.0 - f) * a + f * b, min(a, b), max(a, b));
}

fn bvh_load_node(i: u32) -> BvhNode {
    var n = bvh_nodes[i];
    // With moving instances (`bvh_motion_instances.wgsl`) only the top level moves.
    if (BVH_LINEAR_BOUNDS && (!BVH_INSTANCED || i < bvh_top_nodes())) {
        let k = i * BVH_TIME_STEPS + bvh_time_segment;
        let b = bvh_lerp_box(bvh_step_boxes[k], bvh_step_boxes[k + 1u], bvh_time_fraction);
        n.min = b.min;
        n.max = b.max;
    }
    return n;
}

fn bvh_load_node_links(i: u32) -> vec2<u32> {
    return vec2<u32>(bvh_nodes[i].right_or_first, bvh_nodes[i].meta_bits);
}

fn bvh_load_triangle(i: u32) -> BvhTriangle {
    // The meshes under moving instances are static: one copy of their triangles.
    if (BVH_INSTANCED) {
        return bvh_triangles[i];
    }
    let count = arrayLength(&bvh_triangles) / BVH_TIME_STEPS;
    let a = bvh_triangles[bvh_time_segment * count + i];
    let b = bvh_triangles[(bvh_time_segment + 1u) * count + i];
    let f = bvh_time_fraction;
    var t = a;
    t.v0 = bvh_lerp_point(a.v0, b.v0, f);
    t.v1 = bvh_lerp_point(a.v1, b.v1, f);
    t.v2 = bvh_lerp_point(a.v2, b.v2, f);
    return t;
}
