//! The device BVH builders on both device backends: the host side is one
//! (`bvhtrace_engine::builder`) and the WGSL is one, so on the same device the ash build
//! (`VkContext::build_bvh`) and the wgpu build (`GpuContext::build_bvh`) give the same tree,
//! node for node and triangle for triangle, bit for bit, for both builders; and it holds
//! every invariant. A backend without a device prints SKIP.

use bvhtrace_core::{FlatBvh, Triangle};
use bvhtrace_gpu::{GpuBuildOptions, GpuBuilderKind};
use glam::Vec3;

mod common;
use common::Devices;

fn scene(spec: &str) -> Vec<Triangle> {
    bvhtrace_scene::load(spec)
        .expect("builtin scene")
        .flattened_triangles()
        .expect("triangles")
}

/// The tree as bytes: nodes, triangles and depth.
fn bits(bvh: &FlatBvh) -> (Vec<u8>, Vec<u8>, u32) {
    (
        bytemuck::cast_slice(bvh.nodes()).to_vec(),
        bytemuck::cast_slice(bvh.triangles()).to_vec(),
        bvh.depth(),
    )
}

/// Builds `tris` with each builder on ash (and on wgpu when it opened) and checks the
/// ash tree's invariants and that both trees are the same.
fn check(devices: &Devices, name: &str, tris: &[Triangle]) {
    let Some(vk) = devices.vk() else { return };
    for kind in GpuBuilderKind::ALL {
        let opts = GpuBuildOptions::with_builder(kind);
        let who = format!("{name} ({kind})");
        let (ash, t) = vk.build_bvh(tris, &opts).expect("ash device build");
        ash.check_invariants()
            .unwrap_or_else(|e| panic!("{who} on ash: {e}"));
        assert_eq!(
            ash.triangles().len(),
            tris.len(),
            "{who}: every triangle once"
        );
        let mut prims: Vec<u32> = ash.triangles().iter().map(|t| t.prim).collect();
        prims.sort_unstable();
        assert!(
            prims.iter().copied().eq(0..tris.len() as u32),
            "{who}: prims"
        );
        // Again, one clustering iteration before the first read back: the batches that
        // follow give the same tree.
        let one_first = GpuBuildOptions {
            first_iterations: Some(1),
            ..opts
        };
        let (again, at) = vk.build_bvh(tris, &one_first).expect("ash device build");
        assert!(bits(&again) == bits(&ash), "{who}: ash is deterministic");
        assert_eq!(at.iterations, t.iterations, "{who}: iterations");
        eprintln!(
            "{who}: ash {} nodes, depth {}, {} iterations, {:.1} ms upload, {:.1} ms build, \
             {:.1} ms read back",
            ash.nodes().len(),
            ash.depth(),
            t.iterations,
            t.upload_ms,
            t.build_ms,
            t.readback_ms
        );
        let Some(wgpu) = devices.wgpu() else { continue };
        let (w, wt) = wgpu.build_bvh(tris, &opts).expect("wgpu device build");
        eprintln!(
            "{who}: wgpu {:.1} ms upload, {:.1} ms build, {:.1} ms read back; stages: ash \
             {:?}, wgpu {:?}",
            wt.upload_ms, wt.build_ms, wt.readback_ms, t.stages_ms, wt.stages_ms
        );
        assert_eq!(wt.iterations, t.iterations, "{who}: iterations");
        assert_eq!(w.nodes().len(), ash.nodes().len(), "{who}: node count");
        for (i, (a, b)) in ash.nodes().iter().zip(w.nodes()).enumerate() {
            assert!(
                bytemuck::bytes_of(a) == bytemuck::bytes_of(b),
                "{who}: node {i}: ash {a:?}, wgpu {b:?}"
            );
        }
        for (i, (a, b)) in ash.triangles().iter().zip(w.triangles()).enumerate() {
            assert!(
                bytemuck::bytes_of(a) == bytemuck::bytes_of(b),
                "{who}: triangle {i}: ash {a:?}, wgpu {b:?}"
            );
        }
        assert_eq!(w.depth(), ash.depth(), "{who}: depth");
    }
}

#[test]
fn ash_builds_the_same_tree_as_wgpu() {
    let devices = Devices::open("device builds on both backends");
    check(devices, "icosphere 3", &scene("builtin:icosphere:3"));
    check(devices, "cornell", &scene("builtin:cornell"));
    let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
    // Every centroid equal: the index breaks every tie.
    check(devices, "1000 copies of one triangle", &vec![t; 1000]);
    let nested: Vec<Triangle> = (1..=2000)
        .map(|i| [Vec3::ZERO, Vec3::X * i as f32, Vec3::Y * i as f32])
        .collect();
    check(devices, "2000 nested triangles", &nested);
    check(devices, "two triangles", &[t, t.map(|p| p + Vec3::Z)]);
    devices.check_validation();
}

#[test]
fn ash_build_errors_name_the_input() {
    let devices = Devices::open("device build errors on ash");
    let Some(vk) = devices.vk() else { return };
    let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
    for kind in GpuBuilderKind::ALL {
        let opts = GpuBuildOptions::with_builder(kind);
        let (one, _) = vk.build_bvh(&[t], &opts).expect("one triangle");
        one.check_invariants().expect("one triangle's tree");
        assert!(matches!(
            vk.build_bvh(&[], &opts),
            Err(bvhtrace_vk::TraceError::EmptyBvh)
        ));
        let err = vk
            .build_bvh(&[t, [Vec3::ZERO, Vec3::NAN, Vec3::Y]], &opts)
            .expect_err("a NaN corner");
        assert!(err.to_string().contains("triangle 1"), "{err}");
        let bad = GpuBuildOptions { radius: 0, ..opts };
        assert!(vk.build_bvh(&[t, t], &bad).is_err());
    }
}

/// The shared bunny (69k triangles), when the scenes are there: the same tree on both
/// backends, and each backend's build time.
#[test]
fn bunny_builds_the_same_on_both_backends() {
    let Some(dir) = bvhtrace_scene::shared_scenes_dir() else {
        eprintln!("SKIP bunny: no shared scenes");
        return;
    };
    let path = dir.join("glb/bunny_69k.glb");
    if !path.exists() {
        eprintln!("SKIP bunny: no {}", path.display());
        return;
    }
    let tris = scene(&path.to_string_lossy());
    let devices = Devices::open("bunny on both backends");
    check(devices, "bunny_69k", &tris);
    devices.check_validation();
    // Warm builds (programs compiled, first use done): the best of three on each.
    let (Some(vk), Some(wgpu)) = (devices.vk(), devices.wgpu()) else {
        return;
    };
    for kind in GpuBuilderKind::ALL {
        let opts = GpuBuildOptions::with_builder(kind);
        let best = |f: &dyn Fn() -> f64| (0..3).map(|_| f()).fold(f64::INFINITY, f64::min);
        let total = |t: bvhtrace_gpu::GpuBuildTimes| t.upload_ms + t.build_ms + t.readback_ms;
        let ash = best(&|| total(vk.build_bvh(&tris, &opts).expect("ash").1));
        let wg = best(&|| total(wgpu.build_bvh(&tris, &opts).expect("wgpu").1));
        eprintln!("bunny_69k ({kind}), warm, best of 3: ash {ash:.1} ms, wgpu {wg:.1} ms");
    }
}
