//! What README.md promises a new user, checked as a new user would meet it:
//! * its "Use it from your project" lines and its library example build as a project of
//!   their own, outside the workspace (`cargo check` of a scratch crate; the example also
//!   runs as this crate's doctest);
//! * its two commands share their build: every dependency of `cargo run -p bvhtrace-cli`
//!   has the features `cargo test --workspace` gives it, so neither command recompiles
//!   what the other built.
//!
//! Both run cargo itself, offline: every crate they need is in cargo's cache once the
//! workspace has built.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

/// The repository's root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn readme() -> String {
    std::fs::read_to_string(root().join("README.md")).expect("README.md")
}

/// The first fenced block of language `lang` after the heading `heading`.
fn block_after(text: &str, heading: &str, lang: &str) -> String {
    let at = text
        .find(heading)
        .unwrap_or_else(|| panic!("README.md has no {heading:?}"));
    let fence = format!("```{lang}\n");
    let start = at
        + text[at..]
            .find(&fence)
            .unwrap_or_else(|| panic!("no ```{lang} block after {heading:?}"))
        + fence.len();
    let end = start + text[start..].find("```").expect("the block ends");
    text[start..end].to_string()
}

fn cargo() -> Command {
    Command::new(std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into()))
}

/// Runs `cmd`, panicking with its output when it fails; its stdout.
fn run(mut cmd: Command, what: &str) -> String {
    let out = cmd.output().unwrap_or_else(|e| panic!("{what}: {e}"));
    assert!(
        out.status.success(),
        "{what} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Where this test's binary was built (`target/<profile>/deps/..`): the target folder.
fn target_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("the test's path");
    exe.ancestors()
        .nth(3)
        .expect("target/<profile>/deps/<test>")
        .to_path_buf()
}

#[test]
fn a_project_of_your_own_builds_with_the_readme_lines() {
    let text = readme();
    let deps = block_after(&text, "### Use it from your project", "toml");
    let example = block_after(&text, "## Use it as a library", "rust");
    assert!(
        deps.contains("../bvhtrace/crates/bvhtrace"),
        "the lines depend on a clone beside the project:\n{deps}"
    );
    // The project beside a clone, as the README has it: `../bvhtrace` is this checkout.
    let clone = root().canonicalize().expect("the checkout");
    let deps = deps.replace("../bvhtrace/", &format!("{}/", clone.display()));
    let project =
        std::env::temp_dir().join(format!("bvhtrace-your-project-{}", std::process::id()));
    std::fs::create_dir_all(project.join("src")).expect("a scratch folder");
    let manifest = format!(
        "[package]\nname = \"your-project\"\nversion = \"0.1.0\"\nedition = \"2024\"\n\n{deps}"
    );
    std::fs::write(project.join("Cargo.toml"), manifest).expect("Cargo.toml");
    std::fs::write(project.join("src/main.rs"), &example).expect("main.rs");
    // The workspace's lock: the versions cargo's cache holds, so that it builds offline.
    std::fs::copy(clone.join("Cargo.lock"), project.join("Cargo.lock")).expect("Cargo.lock");
    let mut check = cargo();
    check
        .current_dir(&project)
        .args(["check", "--offline", "--quiet"])
        // A folder of its own: the outer `cargo test` holds the workspace's.
        .env("CARGO_TARGET_DIR", target_dir().join("your-project"))
        .env_remove("RUSTFLAGS");
    run(check, "cargo check of a project using the README's lines");
    std::fs::remove_dir_all(&project).ok();
}

/// Each package in `cargo tree`'s output (`{p} [{f}]` per line) with its features.
fn features(tree: &str) -> BTreeMap<String, Vec<String>> {
    let mut out: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for line in tree.lines() {
        let Some((package, rest)) = line.split_once(" [") else {
            continue;
        };
        // `name v1.2.3 (path)` or `name v1.2.3`: the name and version say which.
        let id: Vec<&str> = package.split(' ').take(2).collect();
        let list = rest.trim_end_matches(" (*)").trim_end_matches(']');
        let entry = out.entry(id.join(" ")).or_default();
        entry.extend(list.split(',').filter(|f| !f.is_empty()).map(String::from));
        entry.sort();
        entry.dedup();
    }
    out
}

fn tree(selection: &[&str], edges: &str) -> BTreeMap<String, Vec<String>> {
    let mut cmd = cargo();
    cmd.current_dir(root())
        .args(["tree", "--offline", "--prefix", "none", "-e", edges])
        .args(["-f", "{p} [{f}]"])
        .args(selection);
    features(&run(cmd, "cargo tree"))
}

#[test]
fn the_readme_commands_share_their_build() {
    let text = readme();
    assert!(
        text.contains("cargo run --release -p bvhtrace-cli -- render")
            && text.contains("cargo test --workspace --release"),
        "README.md's two commands changed: change this test with them"
    );
    let cli = tree(&["-p", "bvhtrace-cli"], "normal,build");
    let workspace = tree(&["--workspace"], "normal,build,dev");
    assert!(cli.len() > 50, "{} packages in the CLI's tree", cli.len());
    let differ: Vec<String> = cli
        .iter()
        .filter(|(p, f)| workspace.get(*p) != Some(*f))
        .map(|(p, f)| {
            let all = workspace.get(p).cloned().unwrap_or_default();
            let only: Vec<&String> = all.iter().filter(|x| !f.contains(x)).collect();
            format!("{p}: the workspace adds {only:?}")
        })
        .collect();
    assert!(
        differ.is_empty(),
        "`cargo run -p bvhtrace-cli` would build these with other features than `cargo test \
         --workspace` (turn them on in crates/cli/Cargo.toml):\n{}",
        differ.join("\n")
    );
}
