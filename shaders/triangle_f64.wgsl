// triangle_f64.wgsl: the watertight ray/triangle test in f64, twin of
// `bvhtrace_core::precision::intersect_triangle_f64` operation for operation. Composed
// instead of `triangle.wgsl` for `Precision::WatertightF64` (the device needs
// `SHADER_F64`); same signature. The f32 ray and corners convert to f64 exactly; the axes
// are the f32 ray's, the shear is recomputed in f64, and `t`, `u`, `v` are rounded to f32
// once.

fn bvh_component_f64(v: vec3<f64>, i: u32) -> f64 {
    if (i == 0u) {
        return v.x;
    }
    if (i == 1u) {
        return v.y;
    }
    return v.z;
}

// `intersect::edge` in f64 (see `bvh_edge` in `triangle.wgsl`).
fn bvh_edge_f64(px: f64, py: f64, qx: f64, qy: f64) -> f64 {
    let swap = px > qx || (px == qx && py > qy);
    let e = select(px, qx, swap) * select(qy, py, swap) - select(py, qy, swap) * select(qx, px, swap);
    return select(e, -e, swap);
}

fn bvh_intersect_triangle(r: BvhPreparedRay, v0: vec3<f32>, v1: vec3<f32>, v2: vec3<f32>) -> BvhTriHit {
    var out = BvhTriHit(0.0, 0.0, 0.0, false);
    let org = vec3<f64>(r.org);
    let d = vec3<f64>(r.dir);
    let dz = bvh_component_f64(d, r.kz);
    let sx = bvh_component_f64(d, r.kx) / dz;
    let sy = bvh_component_f64(d, r.ky) / dz;
    let sz = f64(1.0) / dz;
    let a = vec3<f64>(v0) - org;
    let b = vec3<f64>(v1) - org;
    let c = vec3<f64>(v2) - org;
    let az_ = bvh_component_f64(a, r.kz);
    let bz_ = bvh_component_f64(b, r.kz);
    let cz_ = bvh_component_f64(c, r.kz);
    let ax = bvh_component_f64(a, r.kx) - sx * az_;
    let ay = bvh_component_f64(a, r.ky) - sy * az_;
    let bx = bvh_component_f64(b, r.kx) - sx * bz_;
    let by = bvh_component_f64(b, r.ky) - sy * bz_;
    let cx = bvh_component_f64(c, r.kx) - sx * cz_;
    let cy = bvh_component_f64(c, r.ky) - sy * cz_;
    let u = bvh_edge_f64(cx, cy, bx, by);
    let v = bvh_edge_f64(ax, ay, cx, cy);
    let w = bvh_edge_f64(bx, by, ax, ay);
    let zero = f64(0.0);
    if ((u < zero || v < zero || w < zero) && (u > zero || v > zero || w > zero)) {
        return out;
    }
    let det = u + v + w;
    if (det == zero) {
        return out;
    }
    let az = sz * az_;
    let bz = sz * bz_;
    let cz = sz * cz_;
    let t_scaled = u * az + v * bz + w * cz;
    let t = f32(t_scaled / det);
    // NaN fails this comparison and is rejected.
    if (!(t >= r.t_min)) {
        return out;
    }
    out.t = t;
    out.u = f32(v / det);
    out.v = f32(w / det);
    out.hit = true;
    return out;
}
