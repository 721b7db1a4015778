// traverse_stack.wgsl: the per-lane stacks of the full-stack and short-stack walks, in
// workgroup memory.
//
// Why not a function-scope array: WGSL zero-initialises every function variable, and a
// driver that runs lanes as SIMD on the CPU (lavapipe) then writes every entry of every
// lane, lane by lane, at the start of each ray: on `bunny_69k` that cost the full-stack walk
// 10-15% of its time for a 64-entry stack. Workgroup memory is not initialised per ray
// (the pipelines turn off its zero-initialisation: every entry is written before it is
// read), and interleaving the lanes (entry `e` of lane `l` at `e * STACK_LANES + l`) keeps
// neighbouring lanes' entries together on GPUs.
//
// A caller passes its `local_invocation_index` as `lane`; its workgroup has at most
// `STACK_LANES` invocations, so lanes never share entries.

// Lanes per workgroup the stacks are laid out for (`bvhtrace_gpu::STACK_LANES`).
const BVH_STACK_LANES: u32 = 64u;
// Entries per lane: the full stack's depth (`FULL_STACK_SIZE`), which covers the short
// stack's ring (`MAX_SHORT_STACK`) too.
const BVH_STACK_ENTRIES: u32 = 64u;

var<workgroup> bvh_lane_stacks: array<u32, BVH_STACK_ENTRIES * BVH_STACK_LANES>;

// The slot of entry `e` of `lane`'s stack.
fn bvh_stack_slot(lane: u32, e: u32) -> u32 {
    return e * BVH_STACK_LANES + lane;
}
