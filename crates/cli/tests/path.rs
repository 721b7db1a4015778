//! `bvhtrace render --shade path` as a user meets it: the device's image is the CPU
//! twin's, pixel for pixel, in PNG and in linear HDR; flags out of range are clear errors
//! that write nothing.

mod common;

use common::*;

#[test]
fn path_tracing_gives_the_same_image_on_the_device_and_the_cpu_twin() {
    let foliage = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/foliage.gltf");
    let sky = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/sky.hdr");
    // Alpha masks in one mesh; instanced spheres in two levels; the sky from a map.
    for (scene, flags) in [
        (foliage, &[][..]),
        ("builtin:spheres", &[]),
        (foliage, &["--environment", sky]),
    ] {
        same_image_on_device_and_twin(scene, flags);
    }
}

fn same_image_on_device_and_twin(scene: &str, flags: &[&str]) {
    let dir = scratch("path");
    let mut runs = Vec::new();
    for backend in ["auto", "cpu"] {
        let png = dir.join(format!("{backend}.png"));
        let hdr = dir.join(format!("{backend}.pfm"));
        let mut args = flags.to_vec();
        args.extend_from_slice(&[
            "--size",
            "96x72",
            "--shade",
            "path",
            "--spp",
            "3",
            "--sun",
            "0.3,1,0.5",
            "--backend",
            backend,
            "--traversal",
            "stackless",
            "--hdr",
            hdr.to_str().expect("path"),
        ]);
        let out = render(scene, &png, &args);
        assert!(out.status.success(), "path on {backend}");
        let stats = json(&out);
        if backend == "auto" && stats["backend"] != "wgpu" {
            eprintln!("SKIP: no Vulkan adapter; the device's image not compared");
            return;
        }
        assert_eq!(stats["shade"], "path");
        assert_eq!(stats["spp"], 3);
        assert_eq!(stats["not_finite"], 0);
        let img = image::open(&png).expect("a PNG was written").to_rgb8();
        assert_eq!(img.dimensions(), (96, 72));
        let pfm = std::fs::read(&hdr).expect("an HDR image was written");
        assert!(pfm.starts_with(b"PF\n96 72\n-1.0\n"));
        assert_eq!(pfm.len(), 14 + 96 * 72 * 12);
        runs.push((img, pfm, stats["rays"].clone()));
    }
    let (device, cpu) = (&runs[0], &runs[1]);
    let differ = (device.0.pixels().zip(cpu.0.pixels()))
        .filter(|(a, b)| a != b)
        .count();
    assert_eq!(
        differ, 0,
        "{differ} pixels differ between the device and the twin"
    );
    assert!(device.1 == cpu.1, "the linear images differ");
    assert_eq!(device.2, cpu.2, "rays traced");
    let distinct: std::collections::HashSet<_> = cpu.0.pixels().map(|p| p.0).collect();
    assert!(distinct.len() > 50, "the image looks blank");
}

#[test]
fn path_flags_out_of_range_are_clear_errors_that_write_nothing() {
    let foliage = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/foliage.gltf");
    let dir = scratch("path-flags");
    let png = dir.join("o.png");
    for (flags, says) in [
        (&["--spp", "0"][..], "--spp"),
        (&["--spp", "2000000"][..], "--spp"),
        (&["--sky", "-1,0,0"][..], "--sky"),
        (&["--sun", "0,0,0"][..], "--sun"),
        (&["--exposure", "nan"][..], "--exposure"),
        (&["--backend", "vulkan"][..], "--shade path runs on wgpu"),
        (&["--environment", "no-such-sky.hdr"][..], "no-such-sky.hdr"),
        (&["--environment", foliage][..], "foliage.gltf"),
    ] {
        let mut args = vec!["--shade", "path", "--size", "8x8"];
        args.extend_from_slice(flags);
        let out = render("builtin:cornell", &png, &args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{flags:?} succeeded");
        assert!(err.contains(says), "{flags:?}: {err}");
        assert!(!png.exists(), "{flags:?} left an image");
    }
}
