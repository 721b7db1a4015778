// bvh_buffers_parents.wgsl: the parent links of a `BvhStorage::Buffers` upload
// (`FlatBvh::parents`, one u32 per node). Composed after `bvh_buffers.wgsl`, and only into
// modules whose traversal climbs the tree (stackless, short stack): the full-stack kernels
// neither declare nor bind it, and the upload leaves the buffer out.

@group(0) @binding(2) var<storage, read> bvh_parents: array<u32>;

fn load_parent(i: u32) -> u32 {
    return bvh_parents[i];
}
