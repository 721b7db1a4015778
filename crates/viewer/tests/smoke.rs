//! Runs the real viewer window under Xvfb (on whatever Vulkan driver is there, lavapipe in
//! CI), takes a screenshot after 20 frames and checks that it shows the Cornell box.

use std::collections::HashSet;
use std::fs::File;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const TIMEOUT: Duration = Duration::from_secs(120);
const SIZE: (u32, u32) = (1024, 640);

fn on_path(program: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|paths| std::env::split_paths(&paths).any(|d| d.join(program).is_file()))
}

fn temp_dir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("bvhtrace-viewer-smoke-{}", std::process::id()));
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

#[test]
fn screenshot_shows_the_cornell_box() {
    if !on_path("xvfb-run") {
        println!("SKIP: xvfb-run not found (apt-get install xvfb)");
        return;
    }
    let dir = temp_dir();
    let shot = dir.join("viewer.png");
    let (out_path, err_path) = (dir.join("stdout.txt"), dir.join("stderr.txt"));
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
        .arg(&shot)
        .args(["--frames", "20"])
        .arg("--size")
        .arg(format!("{}x{}", SIZE.0, SIZE.1))
        .arg("builtin:cornell")
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
