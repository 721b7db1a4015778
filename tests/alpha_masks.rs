//! Alpha-tested geometry on every tracer: the masks travel with the BVH
//! (`FlatBvh::set_masks`, attached by `Scene::tracing_bvh`), and the kernels on wgpu (buffers
//! and textures) and ash cut the same candidates as the CPU walks, ray by ray and bit for
//! bit, for every walk, closest and any hit, one level and two. The scenes: the committed
//! foliage (`scenes/foliage.gltf`) and a made-up one of edge cases: coordinates far outside
//! `0..1` under each wrap mode, texels exactly at the cutoff and one below, a texture of one
//! texel, a material naming a texture that is missing, and a mirrored instance.

use bvhtrace_core::{FlatBvh, Query, Ray, TraceOptions, Traversal, trace_rays};
mod common;
mod support;
use common::{Devices, name, tracers};
use support::masked::{edge_cases, masked_rays};

const WALKS: [Traversal; 4] = [
    Traversal::FullStack,
    Traversal::Stackless,
    Traversal::ShortStack(4),
    Traversal::Wide,
];

/// Every tracer against the CPU twin, every walk and query; returns the CPU's closest hits
/// of the full stack.
fn check(label: &str, devices: &Devices, bvh: &FlatBvh, rays: &[Ray]) -> Vec<u32> {
    let all = tracers(devices, bvh);
    assert!(bvh.masks().is_some(), "{label}: no masks");
    let mut failures = Vec::new();
    for walk in WALKS {
        for query in [Query::Closest, Query::Any] {
            let opts = TraceOptions::new(walk, query);
            let cpu = all[0].trace(rays, &opts).expect("cpu trace");
            for t in &all[1..] {
                let got = t.trace(rays, &opts).expect("device trace");
                let who = format!("{label} {walk} {query:?} on {}", name(&**t));
                assert_eq!(
                    t.upload_stats().map(|s| s.masks_bytes > 0),
                    Some(true),
                    "{who}"
                );
                let bad: Vec<usize> = (0..rays.len())
                    .filter(|&i| {
                        let (a, b) = (&cpu.hits[i], &got.hits[i]);
                        (a.prim, a.t.to_bits(), a.u.to_bits(), a.v.to_bits())
                            != (b.prim, b.t.to_bits(), b.u.to_bits(), b.v.to_bits())
                    })
                    .collect();
                if let Some(&i) = bad.first() {
                    // Where only the last bits differ (a device that fuses products into
                    // sums), the primitives still say whether the masks decided alike.
                    let prims = bad
                        .iter()
                        .filter(|&&i| cpu.hits[i].prim != got.hits[i].prim)
                        .count();
                    failures.push(format!(
                        "{who}: {} of {} rays differ ({prims} in the primitive); ray {i} {:?}: \
                         cpu {:?}, device {:?}",
                        bad.len(),
                        rays.len(),
                        rays[i],
                        cpu.hits[i],
                        got.hits[i]
                    ));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    devices.check_validation();
    let opts = TraceOptions::closest(Traversal::FullStack);
    trace_rays(bvh, rays, &opts)
        .hits
        .iter()
        .map(|h| h.prim)
        .collect()
}

/// The same rays with the masks dropped stop at other triangles: the masks cut.
fn assert_cuts(label: &str, bvh: &FlatBvh, rays: &[Ray], masked: &[u32]) {
    let mut opaque = bvh.clone();
    opaque.set_masks(None).expect("dropped");
    let opts = TraceOptions::closest(Traversal::FullStack);
    let whole = trace_rays(&opaque, rays, &opts).hits;
    let changed = whole
        .iter()
        .zip(masked)
        .filter(|(h, p)| h.prim != **p)
        .count();
    assert!(
        changed > rays.len() / 50,
        "{label}: the masks changed only {changed} hits"
    );
}

#[test]
fn masked_scenes_equal_the_cpu_on_every_tracer() {
    let devices = Devices::open("alpha_masks");
    let foliage = bvhtrace_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/foliage.gltf"
    ))
    .expect("scenes/foliage.gltf");
    for (label, scene) in [("edge cases", edge_cases()), ("foliage", foliage)] {
        for flatten in [true, false] {
            let mut traced = scene
                .tracing_bvh(&Default::default(), flatten)
                .unwrap_or_else(|e| panic!("{label}: {e}"));
            traced.build_wide();
            let label = format!(
                "{label} ({})",
                if flatten { "flattened" } else { "two levels" }
            );
            let bvh = traced.bvh();
            let rays = masked_rays(bvh);
            let masks = bvh.masks().expect("masks attached").clone();
            masks.reset_counts();
            let prims = check(&label, devices, bvh, &rays);
            let (settled, sampled) = masks.counts();
            assert!(
                settled > 0 && sampled > 0,
                "{label}: {settled} settled, {sampled} sampled"
            );
            assert_cuts(&label, bvh, &rays, &prims);
        }
    }
}

/// A BVH without masks uploads and runs exactly what it did: no masks binding, no alpha
/// test in the kernels; dropping a scene's masks gives that same upload.
#[test]
fn unmasked_trees_upload_and_compose_nothing_of_the_masks() {
    let devices = Devices::open("alpha_masks");
    let mut traced = edge_cases()
        .tracing_bvh(&Default::default(), true)
        .expect("bvh");
    traced.build_wide();
    let with = traced.bvh().clone();
    traced.set_masks(None).expect("dropped");
    let without = traced.bvh();
    let rays = masked_rays(without);
    let (a, b) = (tracers(devices, &with), tracers(devices, without));
    for (m, u) in a.iter().zip(&b).skip(1) {
        let (sm, su) = (
            m.upload_stats().expect("device"),
            u.upload_stats().expect("device"),
        );
        assert_eq!(su.masks_bytes, 0, "{}", name(&**u));
        assert_eq!(
            sm.total_bytes() - sm.masks_bytes,
            su.total_bytes(),
            "{}: the masks changed the other arrays",
            name(&**u)
        );
        let opts = TraceOptions::closest(Traversal::Stackless);
        u.trace(&rays, &opts).expect("trace");
        m.trace(&rays, &opts).expect("trace");
        let (km, ku) = (m.kernels_used(), u.kernels_used());
        assert!(km.iter().all(|k| k.masks) && ku.iter().all(|k| !k.masks));
        for k in &ku {
            let src = k.source();
            assert!(
                !src.contains("bvh_alpha") && !src.contains("bvh_masks"),
                "{k:?}"
            );
        }
        for k in &km {
            assert!(
                k.source()
                    .contains("&& bvh_alpha_accept(tri.prim, h.u, h.v)"),
                "{k:?}"
            );
        }
    }
}
