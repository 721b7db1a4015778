//! Runs the real viewer window under Xvfb (on whatever Vulkan driver is there, lavapipe in
//! CI): a screenshot after 20 frames shows the Cornell box, and the animated glTF scene
//! plays (its top level rebuilt every frame) and looks different at two times.

use std::collections::HashSet;
use std::fs::File;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// One viewer (and one Xvfb) at a time: `xvfb-run -a` picks a free display number, and
/// two starting at once may pick the same one.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

const TIMEOUT: Duration = Duration::from_secs(120);
const SIZE: (u32, u32) = (1024, 640);

fn on_path(program: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|paths| std::env::split_paths(&paths).any(|d| d.join(program).is_file()))
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!(
        "bvhtrace-viewer-smoke-{}-{name}",
        std::process::id()
    ));
    std::fs::create_dir_all(&d).expect("create a temporary folder");
    d
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

/// The normal-shaded colours of the Cornell box's inner faces (`n * 0.5 + 0.5`): left wall
/// (+x), right wall (-x), floor (+y), ceiling (-y), back wall (+z).
const WALLS: [(&str, [u8; 3]); 5] = [
    ("left wall", [255, 128, 128]),
    ("right wall", [0, 128, 128]),
    ("floor", [128, 255, 128]),
    ("ceiling", [128, 0, 128]),
    ("back wall", [128, 128, 255]),
];

/// Runs the viewer under Xvfb with `args` (the window size is [`SIZE`] unless `args` say
/// otherwise), writing its screenshot to `shot`; kills it past [`TIMEOUT`]. Returns its
/// status and stderr.
fn run_viewer(dir: &Path, shot: &Path, args: &[&str]) -> (ExitStatus, String, Duration) {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let stem = shot
        .file_stem()
        .map_or("viewer".into(), |s| s.to_string_lossy().into_owned());
    let (out_path, err_path) = (
        dir.join(format!("{stem}.stdout.txt")),
        dir.join(format!("{stem}.stderr.txt")),
    );
    let runtime = dir.join("xdg");
    std::fs::create_dir_all(&runtime).expect("runtime dir");
    {
        use std::os::unix::fs::PermissionsExt;
        let _ = std::fs::set_permissions(&runtime, std::fs::Permissions::from_mode(0o700));
    }
    let start = Instant::now();
    let mut child = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1280x800x24"])
        .arg(env!("CARGO_BIN_EXE_bvhtrace-viewer"))
        .arg("--screenshot")
        .arg(shot)
        .arg("--size")
        .arg(format!("{}x{}", SIZE.0, SIZE.1))
        .args(args)
        .env("XDG_RUNTIME_DIR", &runtime)
        .stdin(Stdio::null())
        .stdout(File::create(&out_path).expect("stdout file"))
        .stderr(File::create(&err_path).expect("stderr file"))
        // Its own process group, so that a timeout kills Xvfb and the viewer too.
        .process_group(0)
        .spawn()
        .expect("start xvfb-run");
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait for xvfb-run") {
            break s;
        }
        if start.elapsed() > TIMEOUT {
            let _ = Command::new("kill")
                .args(["-KILL", &format!("-{}", child.id())])
                .status();
            let _ = child.wait();
            panic!(
                "the viewer did not finish within {TIMEOUT:?}\nstderr:\n{}",
                read(&err_path)
            );
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let elapsed = start.elapsed();
    let stderr = read(&err_path);
    assert!(
        status.success(),
        "the viewer failed ({status}):\nstdout:\n{}\nstderr:\n{stderr}",
        read(&out_path)
    );
    (status, stderr, elapsed)
}

#[test]
fn screenshot_shows_the_cornell_box() {
    if !on_path("xvfb-run") {
        println!("SKIP: xvfb-run not found (apt-get install xvfb)");
        return;
    }
    let dir = temp_dir("cornell");
    let shot = dir.join("viewer.png");
    let (_, stderr, elapsed) = run_viewer(&dir, &shot, &["--frames", "20", "builtin:cornell"]);
    println!("viewer run took {elapsed:?}; it said: {}", stderr.trim());

    let img = image::open(&shot)
        .unwrap_or_else(|e| panic!("{}: {e}\nstderr:\n{stderr}", shot.display()))
        .to_rgb8();
    assert_eq!(
        img.dimensions(),
        SIZE,
        "the screenshot is not the window's size"
    );

    let colours: HashSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    assert!(
        colours.len() > 200,
        "only {} distinct colours: the window looks blank",
        colours.len()
    );

    // The central panel (right of the side panel) shows the traced box: mostly not the
    // background, and the walls' normal colours among its pixels.
    let (w, h) = SIZE;
    let (x0, x1, y0, y1) = (w * 45 / 100, w * 95 / 100, h * 10 / 100, h * 95 / 100);
    let mut total = 0usize;
    let mut not_background = 0usize;
    let mut wall_counts = [0usize; WALLS.len()];
    for y in y0..y1 {
        for x in x0..x1 {
            let p = img.get_pixel(x, y).0;
            total += 1;
            let near = |c: [u8; 3], tol: i32| {
                p.iter()
                    .zip(c)
                    .all(|(&a, b)| (i32::from(a) - i32::from(b)).abs() <= tol)
            };
            if !near([24, 26, 32], 12) {
                not_background += 1;
            }
            for (k, (_, c)) in WALLS.iter().enumerate() {
                if near(*c, 8) {
                    wall_counts[k] += 1;
                }
            }
        }
    }
    assert!(
        not_background * 2 > total,
        "the central region is mostly background ({not_background} of {total} pixels differ)"
    );
    let seen: Vec<&str> = WALLS
        .iter()
        .zip(wall_counts)
        .filter(|(_, n)| *n * 100 >= total)
        .map(|((name, _), _)| *name)
        .collect();
    assert!(
        seen.len() >= 3,
        "expected at least three of the Cornell box's wall colours in the central region, \
         saw {seen:?} (counts {wall_counts:?} of {total})"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The central panel's pixels (right of the side panel) that differ between `a` and `b` by
/// more than a little in some channel, and the pixels compared.
fn central_difference(a: &image::RgbImage, b: &image::RgbImage) -> (usize, usize) {
    let (w, h) = a.dimensions();
    let (x0, x1, y0, y1) = (w * 45 / 100, w * 98 / 100, h * 8 / 100, h * 98 / 100);
    let mut differ = 0;
    let mut total = 0;
    for y in y0..y1 {
        for x in x0..x1 {
            total += 1;
            let (p, q) = (a.get_pixel(x, y).0, b.get_pixel(x, y).0);
            if p.iter()
                .zip(q)
                .any(|(&u, v)| (i32::from(u) - i32::from(v)).abs() > 24)
            {
                differ += 1;
            }
        }
    }
    (differ, total)
}

/// The `t = T s` and `N new poses` of a screenshot run's message.
fn played(stderr: &str) -> (f32, u64) {
    let after = |key: &str| {
        let i = stderr
            .find(key)
            .unwrap_or_else(|| panic!("no '{key}' in the viewer's message:\n{stderr}"));
        stderr[i + key.len()..]
            .split([' ', ',', ')'])
            .find(|s| !s.is_empty())
            .unwrap_or_default()
            .to_string()
    };
    let t = after("animation at t = ").parse().expect("a time");
    let before_poses = stderr
        .split(" new poses")
        .next()
        .and_then(|s| s.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no 'N new poses' in the viewer's message:\n{stderr}"));
    (t, before_poses)
}

#[test]
fn the_animated_scene_plays_and_differs_between_two_times() {
    if !on_path("xvfb-run") {
        println!("SKIP: xvfb-run not found (apt-get install xvfb)");
        return;
    }
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/animated.gltf");
    let dir = temp_dir("animated");
    let mut images = Vec::new();
    // Playing from 0 s and from 1 s; a screenshot run advances 1/30 s per frame.
    for (start, name) in [("0", "t0.png"), ("1", "t1.png")] {
        let shot = dir.join(name);
        let (_, stderr, elapsed) = run_viewer(
            &dir,
            &shot,
            &["--play", "--time", start, "--frames", "6", scene],
        );
        println!(
            "viewer run from t = {start} s took {elapsed:?}; it said: {}",
            stderr.trim()
        );
        let lower = stderr.to_lowercase();
        assert!(
            !lower.contains("error") && !lower.contains("failed"),
            "the viewer reported a problem:\n{stderr}"
        );
        assert!(
            stderr.contains("traced on the GPU")
                && stderr.contains("top level rebuilt and updated in place")
                && stderr.contains("playing"),
            "expected a two-level scene played on the GPU:\n{stderr}"
        );
        let (t, poses) = played(&stderr);
        let start: f32 = start.parse().expect("a number");
        assert!(
            poses >= 5 && t > start && t < start + 0.5,
            "expected at least 5 new poses past t = {start} s, got {poses} at t = {t} s"
        );
        let img = image::open(&shot)
            .unwrap_or_else(|e| panic!("{}: {e}\nstderr:\n{stderr}", shot.display()))
            .to_rgb8();
        assert_eq!(img.dimensions(), SIZE);
        images.push(img);
    }
    let (differ, total) = central_difference(&images[0], &images[1]);
    assert!(
        differ * 100 >= total,
        "the frames at two times look the same: {differ} of {total} central pixels differ"
    );
    // Something is drawn at all: the central region is not all background.
    let drawn = images[0]
        .enumerate_pixels()
        .filter(|(x, _, p)| {
            *x > SIZE.0 / 2
                && p.0
                    .iter()
                    .zip([24u8, 26, 32])
                    .any(|(&a, b)| (i32::from(a) - i32::from(b)).abs() > 12)
        })
        .count();
    assert!(drawn > 1000, "only {drawn} non-background pixels");
    println!("{differ} of {total} central pixels differ between the two times");
    let _ = std::fs::remove_dir_all(&dir);
}
