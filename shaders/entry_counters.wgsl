// entry_counters.wgsl: the per-ray work counters (boxes and triangles tested), for the
// heatmap and the statistics. Composed in only when counters are asked for, with one of
// the `*_counted` entry points; without it the module declares no `counters` binding and
// the counts the traversal keeps are dead code the driver's compiler removes.

@group(1) @binding(2) var<storage, read_write> counters: array<BvhCounters>;

fn bvh_store_counted(i: u32, res: BvhTraceResult) {
    bvh_store_hit(i, res.hit);
    // With textures, `batch_len()` runs to the end of a row while the counters hold the
    // chunk; WGSL lets an out-of-bounds store land anywhere in the buffer.
    if (i < arrayLength(&counters)) {
        counters[i] = res.counters;
    }
}
