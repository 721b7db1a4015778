// bvh_buffers_escapes.wgsl: the escape links of a `BvhStorage::Buffers` upload
// (`FlatBvh::escapes`, eight u32 per node, one per ray octant, in blocks of 16 nodes: see
// `escape_index` in `traverse_short_stack.wgsl`). Composed after
// `bvh_buffers.wgsl`, and only into modules whose traversal reads them (stackless, short
// stack): the full-stack kernels neither declare nor bind them, and the upload leaves the
// buffer out.

@group(0) @binding(2) var<storage, read> bvh_escapes: array<u32>;

// Where a walk in octant `oct` goes when it is done with node `i`'s subtree
// (`NO_ESCAPE`: nowhere, the walk is over).
fn bvh_load_escape(i: u32, oct: u32) -> u32 {
    return bvh_escapes[bvh_escape_index(i, oct)];
}
