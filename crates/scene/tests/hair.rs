//! Hair: `builtin:hair` in every kind and as tubes, and Cem Yuksel's `.hair` files read
//! back as written, transformed with the scene, and refused by name when malformed.

use bvhtrace_core::CurveKind;
use bvhtrace_scene::{hair_file_bytes, has_curves, load};

fn temp(name: &str, bytes: &[u8]) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("bvhtrace-hair-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

#[test]
fn every_kind_of_hair_loads() {
    for kind in CurveKind::ALL {
        let spec = format!("builtin:hair:{}:40", kind.name());
        assert!(has_curves(&spec));
        let scene = load(&spec).unwrap();
        let c = scene.curves.as_ref().expect("curves");
        assert_eq!(c.kind, kind);
        let per_strand = if kind.degree() == 1 { 9 } else { 7 };
        assert_eq!(c.len(), 40 * per_strand, "{spec}");
        assert_eq!(scene.triangle_count(), 1280);
        c.validate().unwrap();
    }
    let scene = load("builtin:hair").unwrap();
    assert_eq!(scene.curves.unwrap().kind, CurveKind::RoundBSpline);
    let tubes = load("builtin:hair:tubes:20").unwrap();
    assert!(!has_curves("builtin:hair:tubes:20") && tubes.curves.is_none());
    assert_eq!(tubes.triangle_count(), 1280 + 20 * 9 * 16);
}

#[test]
fn bad_hair_specs_are_refused_by_name() {
    for (spec, says) in [
        ("builtin:hair:spiky", "KIND is one of round-linear"),
        ("builtin:hair:round-linear:0", "N must be 1 to 1,000,000"),
        ("builtin:hair:round-linear:12:x", "unexpected \"x\""),
    ] {
        let e = load(spec).unwrap_err().to_string();
        assert!(e.contains(spec) && e.contains(says), "{spec}: {e}");
    }
}

#[test]
fn hair_files_read_back_as_written() {
    let scene = load("builtin:hair:round-linear:30").unwrap();
    let curves = scene.curves.unwrap();
    let path = temp("thirty.hair", &hair_file_bytes(&curves));
    let spec = path.to_str().unwrap();
    assert!(has_curves(spec));
    let back = load(spec).unwrap();
    assert_eq!(back.triangle_count(), 0);
    assert_eq!(back.curves.as_ref(), Some(&curves));
    // A scene transform moves the points and scales the radii.
    let moved = load(&format!("{spec}#scale=2#offset=1,0,0")).unwrap();
    let (a, b) = (curves.points[5], moved.curves.unwrap().points[5]);
    assert!((b.truncate() - (a.truncate() * 2.0 + glam::Vec3::X)).length() < 1e-5);
    assert!((b.w - 2.0 * a.w).abs() < 1e-6);
}

#[test]
fn malformed_hair_files_are_refused_by_name() {
    let curves = load("builtin:hair:round-linear:5").unwrap().curves.unwrap();
    let good = hair_file_bytes(&curves);
    let mut wrong_count = good.clone();
    wrong_count[8] ^= 1; // the total point count
    let cases: [(&str, Vec<u8>, &str); 4] = [
        (
            "magic.hair",
            b"HAIX".iter().chain(&good[4..]).copied().collect(),
            "no HAIR magic",
        ),
        ("short.hair", good[..good.len() - 10].to_vec(), "truncated"),
        ("count.hair", wrong_count, "points"),
        ("tiny.hair", b"HAIR".to_vec(), "128-byte header"),
    ];
    for (name, bytes, says) in cases {
        let path = temp(name, &bytes);
        let e = load(path.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains(name) && e.contains(says), "{name}: {e}");
    }
    // Any byte changed: an error or a scene, never a panic.
    for i in (0..good.len()).step_by(7) {
        let mut b = good.clone();
        b[i] = b[i].wrapping_add(0x5b);
        let path = temp("flipped.hair", &b);
        let _ = load(path.to_str().unwrap());
    }
}
