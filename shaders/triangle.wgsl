// triangle.wgsl: the watertight ray/triangle test (Woop, Benthin, Wald 2013), twin of
// `bvhtrace_core::intersect::intersect_triangle`, operation for operation. The default
// (`Precision::WatertightF32`); `triangle_moller_trumbore.wgsl` and `triangle_f64.wgsl`
// define the same function for the other precisions (`TriHit` is in `triangle_hit.wgsl`).

// `intersect::edge`: `p.x q.y - p.y q.x` with the two corners in one fixed order and the
// sign restored, so that triangles sharing an edge compute it from the same operands, and
// stay watertight, even where the device fuses a product into the subtraction (an FMA).
fn bvh_edge(px: f32, py: f32, qx: f32, qy: f32) -> f32 {
    let swap = px > qx || (px == qx && py > qy);
    let e = select(px, qx, swap) * select(qy, py, swap) - select(py, qy, swap) * select(qx, px, swap);
    return select(e, -e, swap);
}

fn bvh_intersect_triangle(r: BvhPreparedRay, v0: vec3<f32>, v1: vec3<f32>, v2: vec3<f32>) -> BvhTriHit {
    let a = v0 - r.org;
    let b = v1 - r.org;
    let c = v2 - r.org;
    let az_ = bvh_component(a, r.kz);
    let bz_ = bvh_component(b, r.kz);
    let cz_ = bvh_component(c, r.kz);
    let ax = bvh_component(a, r.kx) - r.sx * az_;
    let ay = bvh_component(a, r.ky) - r.sy * az_;
    let bx = bvh_component(b, r.kx) - r.sx * bz_;
    let by = bvh_component(b, r.ky) - r.sy * bz_;
    let cx = bvh_component(c, r.kx) - r.sx * cz_;
    let cy = bvh_component(c, r.ky) - r.sy * cz_;
    let u = bvh_edge(cx, cy, bx, by);
    let v = bvh_edge(ax, ay, cx, cy);
    let w = bvh_edge(bx, by, ax, ay);
    let az = r.sz * az_;
    let bz = r.sz * bz_;
    let cz = r.sz * cz_;
    let det = u + v + w;
    let t_scaled = u * az + v * bz + w * cz;
    let inv_det = 1.0 / det;
    let t = t_scaled * inv_det;
    // Computed whatever the outcome, then judged: on a CPU driver every lane runs every
    // branch under a mask, so early returns only add mask work. NaN fails `t >= t_min`.
    let outside = (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0);
    let hit = !outside && det != 0.0 && t >= r.t_min;
    return BvhTriHit(t, v * inv_det, w * inv_det, hit);
}
