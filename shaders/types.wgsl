// types.wgsl: the data shared between the CPU and the GPU, field for field.
//
// Each struct is the WGSL twin of a `#[repr(C)]` Rust type of `bvhtrace_core`; the test
// `crates/engine/tests/wgsl_layout.rs` parses the composed source with naga and checks every
// size and field offset against `std::mem::offset_of!`, so the layout has one source of
// truth (`crates/core/src/flat.rs` and `ray.rs`).

// `FlatNode` (32 bytes). Interior: the first child is the next node, `right_or_first` is the
// second child. Leaf: triangles `right_or_first .. right_or_first + count`.
// `meta_bits` is `FlatNode::meta` = `count << 2 | axis` (`meta` is reserved in WGSL).
struct BvhNode {
    min: vec3<f32>,
    right_or_first: u32,
    max: vec3<f32>,
    meta_bits: u32,
}

// `FlatTriangle` (48 bytes): the corners, and the triangle's index in the builder's input.
struct BvhTriangle {
    v0: vec3<f32>,
    prim: u32,
    v1: vec3<f32>,
    pad1: u32,
    v2: vec3<f32>,
    pad2: u32,
}

// `WideNode` (80 bytes), a node of the wide layout (`bvhtrace_core::wide`, where the encoding
// is described): up to eight children in slots `0..8`. Child `s`'s box on axis `a` is
// `origin[a] + q * 2^(e[a] - 127)`, `q` byte `s % 4` of word `s / 4` of `q_lo[a]` (lower
// plane) or `q_hi[a]` (upper); `e[a]` is byte `a` of `exponents`, whose byte 3 is `imask`
// (bit `s`: slot `s` holds an interior child). Interior children are nodes
// `child_base + popcount(imask & ((1 << s) - 1))`; byte `s` of `counts` is leaf child `s`'s
// triangle count, its triangles start at `triangle_base` plus the counts before it.
struct BvhWideNode {
    origin: vec3<f32>,
    exponents: u32,
    child_base: u32,
    triangle_base: u32,
    counts: vec2<u32>,
    q_lo: array<vec2<u32>, 3>,
    q_hi: array<vec2<u32>, 3>,
}

// `Ray` (32 bytes). Hits are accepted for `t_min <= t < t_max`.
struct BvhRay {
    origin: vec3<f32>,
    t_min: f32,
    dir: vec3<f32>,
    t_max: f32,
}

// `Hit` (16 bytes). `prim` is the primitive index, `MISS`, `INVALID_RAY` or `INCOMPLETE`; `u`, `v` are the
// barycentric weights of corners 1 and 2.
struct BvhHit {
    t: f32,
    prim: u32,
    u: f32,
    v: f32,
}

// `Counters` (8 bytes): boxes and triangles tested for one ray.
struct BvhCounters {
    nodes: u32,
    tris: u32,
}

// What a traversal function returns for one ray.
struct BvhTraceResult {
    hit: BvhHit,
    counters: BvhCounters,
}

// `bvhtrace_core::MISS` and `bvhtrace_core::INVALID_RAY`.
const BVH_MISS: u32 = 0xffffffffu;
const BVH_INVALID_RAY: u32 = 0xfffffffeu;
// `bvhtrace_core::INCOMPLETE`: the kernel ran out of its trip budget (`TRIP_LIMIT`) before
// the ray's answer was certain; the host finishes such rays (`GpuBvh::trace`).
const BVH_INCOMPLETE: u32 = 0xfffffffdu;
// `bvhtrace_core::traverse::MAX_SHORT_STACK`: the ring buffer's storage.
const BVH_MAX_SHORT_STACK: u32 = 32u;

fn bvh_node_count(n: BvhNode) -> u32 {
    return n.meta_bits >> 2u;
}

// `v[k]` for k in 0..3, written as selects (a dynamic vector index costs more on
// lavapipe; the value is the same).
fn bvh_component(v: vec3<f32>, k: u32) -> f32 {
    return select(select(v.z, v.y, k == 1u), v.x, k == 0u);
}

// `FlatInstance` (64 bytes): one instance of a two-level BVH. `world_to_object` holds the
// three rows of a 3x4 matrix (`bvh_ray_to_object`); `root` is the mesh's root node,
// `prim_base` the instance's first primitive id, `mask` its visibility mask (8 bits).
struct BvhInstance {
    world_to_object: array<vec4<f32>, 3>,
    root: u32,
    prim_base: u32,
    mask: u32,
    user_id: u32,
}
