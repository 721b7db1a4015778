//! The shared ray convention, checked against an independent f64 computation.

use bvhtrace_scene::Camera;
use glam::{DVec3, Vec3};

/// The convention of `bvhtrace_scene::camera`, computed in f64 from scratch.
fn reference_dir(c: &Camera, x: u32, y: u32, w: u32, h: u32) -> DVec3 {
    let eye = c.eye.as_dvec3();
    let forward = (c.target.as_dvec3() - eye).normalize();
    let right = forward.cross(DVec3::Y).normalize();
    let up = right.cross(forward);
    let t = ((c.fov_y_deg as f64).to_radians() * 0.5).tan();
    let (wf, hf) = (w as f64, h as f64);
    let px = (2.0 * (x as f64 + 0.5) / wf - 1.0) * t * wf / hf;
    let py = (1.0 - 2.0 * (y as f64 + 0.5) / hf) * t;
    (forward + px * right + py * up).normalize()
}

fn cameras() -> Vec<Camera> {
    vec![
        Camera {
            eye: Vec3::new(0.0, 1.0, 3.9),
            target: Vec3::new(0.0, 1.0, 0.0),
            fov_y_deg: 40.0,
        },
        Camera {
            eye: Vec3::new(3.0, -2.0, 7.5),
            target: Vec3::new(-1.0, 0.5, 0.25),
            fov_y_deg: 65.0,
        },
        Camera {
            eye: Vec3::new(-4.0, 10.0, -2.0),
            target: Vec3::new(0.1, 0.0, 0.3),
            fov_y_deg: 20.0,
        },
        Camera {
            eye: Vec3::new(1e3, 2e3, -5e2),
            target: Vec3::new(0.0, 0.0, 0.0),
            fov_y_deg: 90.0,
        },
    ]
}

#[test]
fn centre_pixel_of_an_odd_image_looks_forward() {
    for c in cameras() {
        let (forward, _, _) = c.basis();
        for (w, h) in [(1, 1), (3, 3), (641, 481), (1279, 719)] {
            let r = c.ray(w / 2, h / 2, w, h);
            let d = Vec3::from(r.dir);
            assert!(
                d.abs_diff_eq(forward, 1e-6),
                "{c:?} {w}x{h}: {d} vs {forward}"
            );
            assert_eq!(Vec3::from(r.origin), c.eye);
            assert_eq!((r.t_min, r.t_max), (0.0, f32::INFINITY));
        }
    }
}

#[test]
fn corner_rays_match_the_formula_in_f64() {
    for c in cameras() {
        for (w, h) in [(640, 480), (1920, 1080), (7, 5), (480, 640)] {
            for (x, y) in [
                (0, 0),
                (w - 1, 0),
                (0, h - 1),
                (w - 1, h - 1),
                (w / 3, h / 5),
            ] {
                let got = Vec3::from(c.ray(x, y, w, h).dir).as_dvec3();
                let want = reference_dir(&c, x, y, w, h);
                assert!(
                    (got - want).abs().max_element() < 1e-6,
                    "{c:?} ({x},{y}) in {w}x{h}: {got} vs {want}"
                );
            }
        }
    }
}

#[test]
fn image_orientation() {
    let c = Camera {
        eye: Vec3::new(0.0, 0.0, 5.0),
        target: Vec3::ZERO,
        fov_y_deg: 45.0,
    };
    let top_left = Vec3::from(c.ray(0, 0, 4, 4).dir);
    assert!(
        top_left.x < 0.0 && top_left.y > 0.0,
        "y = 0 is the top row, x = 0 the left column"
    );
    let bottom_right = Vec3::from(c.ray(3, 3, 4, 4).dir);
    assert!(bottom_right.x > 0.0 && bottom_right.y < 0.0);
}

#[test]
fn rays_are_row_major_and_equal_to_ray() {
    let c = cameras()[1];
    let (w, h) = (13, 9);
    let rays = c.rays(w, h);
    assert_eq!(rays.len(), (w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            assert_eq!(rays[(y * w + x) as usize], c.ray(x, y, w, h));
        }
    }
}

#[test]
fn framing_keeps_the_box_in_view() {
    let (lo, hi) = (Vec3::new(-3.0, 0.5, -1.0), Vec3::new(5.0, 2.0, 0.25));
    for aspect in [0.5f32, 1.0, 16.0 / 9.0, 3.0] {
        let c = Camera::frame(lo, hi, aspect);
        let (f, r, u) = c.basis();
        let t = (c.fov_y_deg.to_radians() * 0.5).tan();
        for i in 0..8 {
            let p = Vec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            );
            let v = p - c.eye;
            let z = v.dot(f);
            assert!(z > 0.0, "corner behind the camera");
            assert!(
                (v.dot(u) / z).abs() <= t,
                "corner {p} outside vertically (aspect {aspect})"
            );
            assert!(
                (v.dot(r) / z).abs() <= t * aspect,
                "corner {p} outside horizontally (aspect {aspect})"
            );
        }
        assert!(
            c.eye.y > (lo.y + hi.y) * 0.5 && c.eye.z > hi.z,
            "from +z, slightly above"
        );
    }
}

#[test]
fn looking_straight_up_or_down_gives_finite_rays() {
    for dy in [-1.0f32, 1.0] {
        let c = Camera {
            eye: Vec3::ZERO,
            target: Vec3::new(0.0, dy, 0.0),
            fov_y_deg: 50.0,
        };
        let (f, r, u) = c.basis();
        assert_eq!(r, Vec3::X);
        assert!(f.dot(u).abs() < 1e-7 && (u.length() - 1.0).abs() < 1e-6);
        for ray in c.rays(8, 6) {
            assert!(ray.is_valid());
        }
    }
}
