// path_wave_prepare.wgsl: between two waves of the path tracer (path_wavefront.wgsl), the
// paths queued become the next wave, its indirect dispatch sized to them. Its own module:
// the dispatch arguments it writes are read as `dispatch_workgroups_indirect`'s, which a
// pass may not also bind for the wave that reads them.

// The path tracer's `path_stats`: words 4, 5 and 6 are the paths in the wave's queue,
// those queued for the next, and which queue is the wave's.
@group(0) @binding(0) var<storage, read_write> ctl: array<u32, 8>;
@group(0) @binding(1) var<storage, read_write> args: array<u32, 3>;

@compute @workgroup_size(1)
fn path_wave_prepare() {
    ctl[4] = ctl[5];
    ctl[5] = 0u;
    ctl[6] = ctl[6] ^ 1u;
    args[0] = (ctl[4] + 63u) / 64u;
    args[1] = 1u;
    args[2] = 1u;
}
