//! Rays and scalings the core's numerics tests and the workspace's precision and
//! real-mesh tests share. Only `bvhtrace_core` and `glam`: `crates/core/tests/numerics.rs`
//! includes it through `#[path]`.
#![allow(dead_code)]

use bvhtrace_core::{Ray, Triangle};
use glam::Vec3;

/// Rays from `from` (inside the closed mesh) aimed exactly at every vertex and at points
/// on every edge.
pub fn edge_rays(tris: &[Triangle], from: Vec3) -> Vec<Ray> {
    let mut rays = Vec::new();
    for t in tris {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            for s in [0.0f32, 0.5, 0.25, 1.0 / 3.0, 0.9] {
                rays.push(Ray::new(from, a + (b - a) * s - from));
            }
        }
    }
    rays
}

/// The scene and the rays scaled by `s` about the origin (directions unchanged).
pub fn scaled(tris: &[Triangle], rays: &[Ray], s: f32) -> (Vec<Triangle>, Vec<Ray>) {
    let st = tris.iter().map(|t| t.map(|p| p * s)).collect();
    let sr = rays
        .iter()
        .map(|r| Ray::new(Vec3::from(r.origin) * s, Vec3::from(r.dir)))
        .collect();
    (st, sr)
}
