// entry_counters.wgsl: the per-ray work counters (boxes and triangles tested), for the
// heatmap and the statistics. Composed in only when counters are asked for, with one of
// the `*_counted` entry points; without it the module declares no `counters` binding and
// the counts the traversal keeps are dead code the driver's compiler removes.

@group(1) @binding(2) var<storage, read_write> counters: array<Counters>;

fn store_counted(i: u32, res: TraceResult) {
    hits[i] = res.hit;
    counters[i] = res.counters;
}
