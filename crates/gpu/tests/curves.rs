//! Curves on the device (`GpuCurveBvh`): the kernel answers as the CPU twin
//! (`CurveBvh::trace`) does (bit for bit for linear curves; for cubic ones the same
//! primitive, and t and u within 1e-5), closest and any hit, for every kind of curve on
//! `builtin:hair` (strands beside a head of triangles), camera rays and rays leaving the
//! strands. Without a Vulkan adapter the tests print SKIP.

use std::sync::Arc;

use bvhtrace_core::{BuildOptions, CurveBvh, CurveKind, Hit, Query, Ray};
use bvhtrace_gpu::GpuCurveBvh;
use glam::Vec3;

mod support;

/// The hair's camera rays, and rays leaving each hit towards the light and sideways.
fn rays(scene: &bvhtrace_scene::Scene, bvh: &CurveBvh) -> Vec<Ray> {
    let cam = scene.camera_or_frame(4.0 / 3.0);
    let mut rays = cam.rays(160, 120);
    let hits = bvh.trace_rays(&rays, Query::Closest);
    let secondary: Vec<Ray> = (rays.iter().zip(&hits))
        .filter(|(_, h)| h.is_hit())
        .flat_map(|(r, h)| {
            let p = Vec3::from(r.origin) + h.t * Vec3::from(r.dir);
            [Vec3::new(1.0, 2.0, 0.5), Vec3::new(-1.0, 0.1, 0.3)]
                .map(|d| Ray::with_interval(p, d, 1e-4, f32::INFINITY))
        })
        .collect();
    rays.extend(secondary);
    rays
}

fn differing(a: &[Hit], b: &[Hit]) -> Vec<usize> {
    (0..a.len())
        .filter(|&i| bytemuck::bytes_of(&a[i]) != bytemuck::bytes_of(&b[i]))
        .collect()
}

#[test]
fn curves_answer_as_the_cpu_twin() {
    let Some(ctx) = support::context("curves") else {
        return;
    };
    for kind in CurveKind::ALL {
        let spec = format!("builtin:hair:{}:1500", kind.name());
        let scene = bvhtrace_scene::load(&spec).unwrap_or_else(|e| panic!("{e}"));
        let tris = scene.flattened_triangles().unwrap();
        let curves = scene.curves.clone().unwrap();
        let bvh = Arc::new(CurveBvh::build(&tris, curves, &BuildOptions::default()).unwrap());
        let gpu = GpuCurveBvh::upload(&ctx, bvh.clone()).expect("upload");
        let rays = rays(&scene, &bvh);
        for query in [Query::Closest, Query::Any] {
            let want = bvh.trace_rays(&rays, query);
            let got = gpu.trace(&rays, query).expect("trace");
            let differ = differing(&got, &want);
            let on_curves = (want.iter())
                .filter(|h| h.is_hit() && bvh.segment_of(h.prim).is_some())
                .count();
            let other = differ
                .iter()
                .filter(|&&i| got[i].prim != want[i].prim)
                .count();
            eprintln!(
                "{spec} {query:?}: {} rays, {on_curves} curve hits, {} differ in bits, {other} in primitive",
                rays.len(),
                differ.len()
            );
            assert!(
                on_curves > rays.len() / 20,
                "{spec}: the rays miss the hair"
            );
            if kind.degree() == 1 {
                if let Some(&i) = differ.first() {
                    panic!(
                        "{spec} {query:?}: {} rays differ, first {i}: device {:?}, CPU {:?}",
                        differ.len(),
                        got[i],
                        want[i]
                    );
                }
                continue;
            }
            // Cubic curves: the shader compiler may reassociate the curve's evaluation, so
            // Newton's method can end an ulp away. The same primitive on all but 1 ray in
            // 1,000, and where it is, t within 1e-5 of it (of 1 below 1: the scene's scale) and u
            // within 1e-5.
            let other_prim = differ
                .iter()
                .filter(|&&i| got[i].prim != want[i].prim)
                .count();
            for &i in &differ {
                let (g, w) = (&got[i], &want[i]);
                if g.prim == w.prim && g.is_hit() {
                    let close =
                        (g.t - w.t).abs() <= 1e-5 * w.t.max(1.0) && (g.u - w.u).abs() <= 1e-5;
                    assert!(close, "{spec} {query:?} ray {i}: device {g:?}, CPU {w:?}");
                }
            }
            assert!(
                other_prim * 1000 <= rays.len(),
                "{spec} {query:?}: {other_prim} rays hit another primitive"
            );
        }
    }
}
