// triangle_hit.wgsl: what every triangle module's
// `intersect_triangle(r: PreparedRay, v0, v1, v2) -> TriHit` returns. Exactly one triangle
// module is composed after this file: `triangle.wgsl` (watertight f32, the default),
// `triangle_moller_trumbore.wgsl` or `triangle_f64.wgsl` (`bvhtrace_core::Precision`).

struct BvhTriHit {
    t: f32,
    u: f32,
    v: f32,
    hit: bool,
}
