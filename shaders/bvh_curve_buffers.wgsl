// bvh_curve_buffers.wgsl: a tree over triangles and curve segments
// (`bvhtrace_core::CurveBvh`) in storage buffers, in place of `bvh_buffers.wgsl` and
// `bvh_buffers_triangles.wgsl`, so the binary walks run on it unchanged; the leaf visit
// tests a slot with `bvh_test_slot` (the curve module's leaf test), which holds either.
// Twin of `CurveBvh::visit_leaf`.
//
// Binding 0: the nodes (`FlatNode`); binding 1: the triangles by primitive id
// (`FlatTriangle`); binding 6: each leaf slot's primitive id (`CurveBvh::leaf_prims`);
// binding 7: the curve points (xyz, radius); binding 8: the segments (`CurveSegment`).

const BVH_WIDE_LAYOUT: bool = false;

// Triangles before the curve segments in the primitive ids (`CurveBvh::triangle_count`).
override BVH_CURVE_TRIANGLES: u32 = 0u;

// `CurveSegment` (8 bytes).
struct BvhCurveSegment {
    first: u32,
    // Bit 0: a segment before it in the strand; bit 1: one after it.
    neighbours: u32,
}

@group(0) @binding(0) var<storage, read> bvh_nodes: array<BvhNode>;
@group(0) @binding(1) var<storage, read> bvh_triangles: array<BvhTriangle>;
@group(0) @binding(6) var<storage, read> bvh_leaf_prims: array<u32>;
@group(0) @binding(7) var<storage, read> bvh_curve_points: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read> bvh_curve_segments: array<BvhCurveSegment>;

fn bvh_load_node(i: u32) -> BvhNode {
    return bvh_nodes[i];
}

fn bvh_load_node_links(i: u32) -> vec2<u32> {
    return vec2<u32>(bvh_nodes[i].right_or_first, bvh_nodes[i].meta_bits);
}

// Triangle `i` by primitive id.
fn bvh_load_triangle(i: u32) -> BvhTriangle {
    return bvh_triangles[i];
}

fn bvh_curve_point(i: u32) -> vec4<f32> {
    return bvh_curve_points[i];
}

fn bvh_curve_segment(s: u32) -> BvhCurveSegment {
    return bvh_curve_segments[s];
}

struct BvhSlotHit {
    hit: BvhTriHit,
    prim: u32,
}

// The primitive in leaf slot `i` against `r`, up to `t_max`: a triangle's hit (its
// interval applied by the caller, as for every triangle) or a curve's in
// `[r.t_min, t_max]`, and the primitive id.
fn bvh_test_slot(r: BvhPreparedRay, i: u32, t_max: f32) -> BvhSlotHit {
    let id = bvh_leaf_prims[i];
    if (id < BVH_CURVE_TRIANGLES) {
        let tri = bvh_triangles[id];
        return BvhSlotHit(bvh_intersect_triangle(r, tri.v0, tri.v1, tri.v2), id);
    }
    let h = bvh_curve_hit(r, id - BVH_CURVE_TRIANGLES, vec2<f32>(r.t_min, t_max));
    return BvhSlotHit(h, id);
}
