//! Camera controls: orbit, pan, zoom and fly moves on a [`Camera`], and the
//! `--eye X,Y,Z --target X,Y,Z --fov F` flags that `bvhtrace render` takes.
//!
//! Every move is a pure function of the camera and the input, so the tests can check the
//! invariants (orbiting keeps the distance to the target, panning moves eye and target
//! together, the flags round-trip exactly).

use bvhtrace_scene::Camera;
use bvhtrace_shade::args::parse_vec3;
use glam::Vec3;

/// The largest pitch (angle above or below the target's horizontal plane) orbiting reaches,
/// in radians: just short of straight up or down, where the camera's "up" (world +Y) would
/// be undefined.
pub const MAX_PITCH: f32 = 1.55;

/// The smallest eye-to-target distance zooming reaches, relative to the distance the
/// controls were given when the scene was framed (see [`zoom`]).
pub const MIN_DISTANCE: f32 = 1e-4;

/// Turns the eye around the target: `yaw` (radians) about world +Y, `pitch` (radians)
/// up or down, clamped to ±[`MAX_PITCH`]. The distance to the target is kept.
pub fn orbit(cam: &mut Camera, yaw: f32, pitch: f32) {
    let offset = cam.eye - cam.target;
    let r = offset.length();
    if !(r.is_finite() && r > 0.0 && yaw.is_finite() && pitch.is_finite()) {
        return;
    }
    let cur_yaw = offset.x.atan2(offset.z);
    let cur_pitch = (offset.y / r).clamp(-1.0, 1.0).asin();
    let y = cur_yaw + yaw;
    let p = (cur_pitch + pitch).clamp(-MAX_PITCH, MAX_PITCH);
    let dir = Vec3::new(p.cos() * y.sin(), p.sin(), p.cos() * y.cos());
    cam.eye = cam.target + dir * r;
}

/// World units one pixel covers at the target's distance, for a viewport `height_px`
/// pixels tall.
pub fn units_per_pixel(cam: &Camera, height_px: f32) -> f32 {
    let dist = (cam.eye - cam.target).length();
    let half = (cam.fov_y_deg.to_radians() * 0.5).tan();
    2.0 * dist * half / height_px.max(1.0)
}

/// Slides the camera in its image plane so that the point under the cursor follows a drag of
/// `(dx, dy)` pixels (x right, y down) in a viewport `height_px` pixels tall. Eye and target
/// move by the same vector.
pub fn pan(cam: &mut Camera, dx: f32, dy: f32, height_px: f32) {
    let (_, right, up) = cam.basis();
    let s = units_per_pixel(cam, height_px);
    let delta = (-right * dx + up * dy) * s;
    if delta.is_finite() {
        cam.eye += delta;
        cam.target += delta;
    }
}

/// Moves the eye towards the target (`steps > 0`) or away from it (`steps < 0`): each step
/// scales the distance by 0.9. The distance never falls below `min_distance` (pass
/// [`MIN_DISTANCE`] times the scene's size).
pub fn zoom(cam: &mut Camera, steps: f32, min_distance: f32) {
    let offset = cam.eye - cam.target;
    let r = offset.length();
    if !(r.is_finite() && r > 0.0 && steps.is_finite()) {
        return;
    }
    let new_r = (r * 0.9f32.powf(steps)).max(min_distance.max(f32::MIN_POSITIVE));
    if new_r.is_finite() {
        cam.eye = cam.target + offset / r * new_r;
    }
}

/// Fly mode: moves eye and target together by `forward`, `right` and `up` world units
/// along the camera's own axes.
pub fn fly(cam: &mut Camera, forward: f32, right: f32, up: f32) {
    let (f, r, u) = cam.basis();
    let delta = f * forward + r * right + u * up;
    if delta.is_finite() {
        cam.eye += delta;
        cam.target += delta;
    }
}

/// The camera as `bvhtrace render` flags: `--eye X,Y,Z --target X,Y,Z --fov F`. Numbers
/// are written in their shortest exact form, so [`parse_render_flags`] gives the same
/// camera back bit for bit.
pub fn render_flags(cam: &Camera) -> String {
    let v = |p: Vec3| format!("{},{},{}", p.x, p.y, p.z);
    format!(
        "--eye {} --target {} --fov {}",
        v(cam.eye),
        v(cam.target),
        cam.fov_y_deg
    )
}

/// Reads `--eye X,Y,Z --target X,Y,Z [--fov F]` (also `--eye=X,Y,Z`), in any order, into a
/// camera; `fallback_fov` is used when `--fov` is absent. Unknown words, missing values,
/// non-finite numbers, a field of view outside (0, 180) degrees and an eye equal to the
/// target are errors.
pub fn parse_render_flags(s: &str, fallback_fov: f32) -> Result<Camera, String> {
    let mut words = s.split_whitespace();
    let (mut eye, mut target, mut fov) = (None, None, None);
    while let Some(w) = words.next() {
        let (name, inline) = match w.split_once('=') {
            Some((n, v)) => (n, Some(v)),
            None => (w, None),
        };
        let mut value = || {
            inline
                .map(str::to_string)
                .or_else(|| words.next().map(str::to_string))
                .ok_or_else(|| format!("{name} needs a value"))
        };
        match name {
            "--eye" => eye = Some(parse_vec3(&value()?)?),
            "--target" => target = Some(parse_vec3(&value()?)?),
            "--fov" => {
                let v = value()?;
                let f: f32 = v
                    .trim()
                    .parse()
                    .map_err(|_| format!("--fov: '{v}' is not a number"))?;
                fov = Some(f);
            }
            other => {
                return Err(format!(
                    "unexpected '{other}' (expected --eye, --target, --fov)"
                ));
            }
        }
    }
    let eye = eye.ok_or("--eye X,Y,Z is missing")?;
    let target = target.ok_or("--target X,Y,Z is missing")?;
    let fov_y_deg = fov.unwrap_or(fallback_fov);
    if !(fov_y_deg > 0.0 && fov_y_deg < 180.0) {
        return Err(format!(
            "--fov must be between 0 and 180 degrees, got {fov_y_deg}"
        ));
    }
    if eye == target {
        return Err("--eye and --target are the same point".into());
    }
    Ok(Camera {
        eye,
        target,
        fov_y_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        Camera {
            eye: Vec3::new(1.5, 2.0, 7.25),
            target: Vec3::new(0.25, 0.5, -0.75),
            fov_y_deg: 45.0,
        }
    }

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() <= 1e-4 * a.abs().max(b.abs()).max(1.0)
    }

    #[test]
    fn orbit_keeps_the_distance_to_the_target() {
        let mut c = cam();
        let r0 = (c.eye - c.target).length();
        let t0 = c.target;
        for (yaw, pitch) in [
            (0.3, 0.1),
            (-2.0, 0.7),
            (1.0, 3.0),
            (0.0, -5.0),
            (10.0, 0.0),
        ] {
            orbit(&mut c, yaw, pitch);
            assert!(close((c.eye - c.target).length(), r0), "{c:?}");
            assert_eq!(c.target, t0);
            // Pitch stays within the clamp: never straight up or down.
            let p = ((c.eye.y - c.target.y) / r0).asin();
            assert!(p.abs() <= MAX_PITCH + 1e-4, "{p}");
        }
        // A yaw of a full turn comes back to the same place.
        let before = c.eye;
        orbit(&mut c, std::f32::consts::TAU, 0.0);
        assert!((c.eye - before).length() < 1e-3 * r0);
    }

    #[test]
    fn pan_moves_eye_and_target_together() {
        let mut c = cam();
        let d0 = c.eye - c.target;
        let (f0, _, _) = c.basis();
        pan(&mut c, 37.0, -12.0, 600.0);
        assert!((c.eye - c.target - d0).length() < 1e-5);
        let (f1, _, _) = c.basis();
        assert!((f0 - f1).length() < 1e-5, "the view direction is kept");
        assert_ne!(c.target, cam().target);
        // Dragging right moves the camera left (the scene follows the cursor).
        let (_, right, _) = cam().basis();
        assert!((c.target - cam().target).dot(right) < 0.0);
        // One viewport height of drag moves by the visible height at the target.
        let mut c2 = cam();
        let h = 2.0 * (c2.eye - c2.target).length() * (22.5f32).to_radians().tan();
        pan(&mut c2, 0.0, 500.0, 500.0);
        assert!(close((c2.target - cam().target).length(), h));
    }

    #[test]
    fn zoom_moves_along_the_view_and_stops_short_of_the_target() {
        let mut c = cam();
        let r0 = (c.eye - c.target).length();
        zoom(&mut c, 1.0, 1e-3);
        assert!(close((c.eye - c.target).length(), r0 * 0.9));
        zoom(&mut c, -1.0, 1e-3);
        assert!(close((c.eye - c.target).length(), r0));
        zoom(&mut c, 1000.0, 0.5);
        assert!(close((c.eye - c.target).length(), 0.5));
        assert!(c.eye.is_finite());
    }

    #[test]
    fn fly_moves_both_points() {
        let mut c = cam();
        let (f, r, _) = c.basis();
        fly(&mut c, 2.0, -1.0, 0.0);
        let d = c.target - cam().target;
        assert!((d - (f * 2.0 - r)).length() < 1e-5);
        assert!((c.eye - cam().eye - d).length() < 1e-5);
    }

    #[test]
    fn render_flags_round_trip() {
        let cams = [
            cam(),
            Camera {
                eye: Vec3::new(-0.1, 1e-7, -3.4028235e38),
                target: Vec3::new(1.0 / 3.0, -2.5, 123456.79),
                fov_y_deg: 12.345678,
            },
        ];
        for c in cams {
            let s = render_flags(&c);
            assert!(s.starts_with("--eye ") && s.contains(" --target ") && s.contains(" --fov "));
            let back = parse_render_flags(&s, 60.0).expect("parses");
            assert_eq!(back, c, "{s}");
        }
        assert_eq!(
            render_flags(&Camera {
                eye: Vec3::new(0.0, 1.0, -2.5),
                target: Vec3::ZERO,
                fov_y_deg: 45.0
            }),
            "--eye 0,1,-2.5 --target 0,0,0 --fov 45"
        );
        let c = parse_render_flags("--target=0,0,0 --eye 1,2,3", 30.0).expect("parses");
        assert_eq!((c.eye, c.fov_y_deg), (Vec3::new(1.0, 2.0, 3.0), 30.0));
        for bad in [
            "--eye 1,2 --target 0,0,0",
            "--eye 1,2,x --target 0,0,0",
            "--eye 1,2,3",
            "--eye 1,2,3 --target 1,2,3",
            "--eye 1,2,3 --target 0,0,0 --fov 180",
            "--eye 1,2,3 --target 0,0,0 --fov",
            "--eye 1,2,inf --target 0,0,0",
            "--size 3x4",
        ] {
            assert!(parse_render_flags(bad, 45.0).is_err(), "{bad}");
        }
    }
}
