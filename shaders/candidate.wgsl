// candidate.wgsl: a candidate hit as a filter of yours sees it, twin of
// `bvhtrace_core::Candidate`. Composed in only for a library with a filter
// (`LibraryShape::with_filter`): the leaf visit calls your `fn(BvhCandidate) -> bool` on
// every candidate that would become the hit (after the alpha masks, when there are some),
// and a candidate it rejects is as if the ray had missed that triangle.

// `instance` of a candidate in a one-mesh BVH.
const BVH_NO_INSTANCE: u32 = 0xffffffffu;

struct BvhCandidate {
    // The primitive id the hit would report (in two levels, the instance's first id plus
    // the mesh's primitive).
    prim: u32,
    // In two levels, the instance (an index into the uploaded layout's instances);
    // `BVH_NO_INSTANCE` in one.
    instance: u32,
    // The primitive in its mesh.
    mesh_prim: u32,
    // Distance along the ray, and the weights of corners 1 and 2.
    t: f32,
    u: f32,
    v: f32,
}

fn bvh_candidate(prim: u32, mesh_prim: u32, h: BvhTriHit) -> BvhCandidate {
    let instance = select(BVH_NO_INSTANCE, bvh_instance_index, BVH_INSTANCED && bvh_inside);
    return BvhCandidate(prim, instance, mesh_prim, h.t, h.u, h.v);
}
