// path_wave_prepare.wgsl: between two waves of the path tracer (path_wavefront.wgsl), the
// paths queued become the next wave, its indirect dispatch sized to them. Its own module:
// the dispatch arguments it writes are read as `dispatch_workgroups_indirect`'s, which a
// pass may not also bind for the wave that reads them.

@group(0) @binding(0) var<storage, read_write> ctl: array<u32, 4>;
@group(0) @binding(1) var<storage, read_write> args: array<u32, 3>;

@compute @workgroup_size(1)
fn path_wave_prepare() {
    ctl[0] = ctl[1];
    ctl[1] = 0u;
    ctl[2] = ctl[2] ^ 1u;
    args[0] = (ctl[0] + 63u) / 64u;
    args[1] = 1u;
    args[2] = 1u;
}
