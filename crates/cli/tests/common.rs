//! Running the `bvhtrace` binary from tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The binary under test.
pub fn bvhtrace() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_bvhtrace"));
    let xdg = std::env::temp_dir().join("bvhtrace-test-xdg");
    let _ = std::fs::create_dir_all(&xdg);
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let _ = std::fs::set_permissions(&xdg, std::fs::Permissions::from_mode(0o700));
    }
    c.env("XDG_RUNTIME_DIR", xdg);
    c
}

/// Runs and returns the output, printing stderr on failure.
pub fn run(args: &[&str]) -> Output {
    let out = bvhtrace().args(args).output().expect("bvhtrace runs");
    if !out.status.success() {
        eprintln!(
            "bvhtrace {args:?} failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    out
}

/// A fresh scratch folder for one test.
pub fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("bvhtrace-cli-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("scratch dir");
    d
}

/// The shared scenes folder, if present.
pub fn shared() -> Option<PathBuf> {
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    let p = here.join("../../../shared/scenes");
    p.is_dir().then_some(p)
}

/// Parses the JSON `render --json -` printed.
pub fn json(out: &Output) -> serde_json::Value {
    serde_json::from_slice(&out.stdout).expect("JSON on stdout")
}

/// Runs `bvhtrace render SCENE ARGS... -o PNG --json -` (see [`run`]).
pub fn render(scene: &str, png: &Path, args: &[&str]) -> Output {
    let mut a = vec!["render", scene];
    a.extend_from_slice(args);
    a.extend(["-o", png.to_str().unwrap(), "--json", "-"]);
    run(&a)
}

/// Asserts the command succeeded, showing its stderr when it did not.
#[track_caller]
pub fn assert_ok(out: &Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
