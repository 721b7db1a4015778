//! The walk and storage `bvhtrace tune --save` measured fastest on an adapter, kept per
//! adapter name in `$XDG_CACHE_HOME/bvhtrace/tuned.json` (else `~/.cache/...`): `render`
//! takes them on that adapter when no walk or storage is asked for. The library reads no
//! file; this cache is the command line's.

use std::path::PathBuf;

use anyhow::{Context, Result};
use bvhtrace::{BvhStorage, Traversal};
use serde_json::{Value, json};

use crate::output::AtomicFile;

/// What was measured fastest on one adapter.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tuned {
    pub walk: Traversal,
    pub storage: BvhStorage,
}

/// The cache file: `$XDG_CACHE_HOME/bvhtrace/tuned.json`, else `$HOME/.cache/...`.
pub fn path() -> Option<PathBuf> {
    let nonempty = |v: &str| std::env::var_os(v).filter(|p| !p.is_empty());
    let base = nonempty("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| nonempty("HOME").map(|h| PathBuf::from(h).join(".cache")))?;
    Some(base.join("bvhtrace").join("tuned.json"))
}

/// The whole cache, or an empty one when there is none (or it cannot be read as one).
fn read() -> Value {
    (path().and_then(|p| std::fs::read(p).ok()))
        .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
        .filter(Value::is_object)
        .unwrap_or_else(|| json!({ "adapters": {} }))
}

/// The entry for the adapter named `device`, when `tune --save` wrote one that reads back.
pub fn load(device: &str) -> Option<Tuned> {
    let entry = read()["adapters"][device].clone();
    let walk = entry["walk"].as_str()?.parse().ok()?;
    let storage = match entry["storage"].as_str()? {
        "buffers" => BvhStorage::Buffers,
        "textures" => BvhStorage::Textures,
        _ => return None,
    };
    Some(Tuned { walk, storage })
}

/// Records `tuned` for the adapter named `device` (with `detail`, what it was measured
/// on), keeping the other adapters' entries; the file is replaced whole or not at all.
pub fn save(device: &str, tuned: Tuned, detail: Value) -> Result<PathBuf> {
    let path = path().context("no cache folder: set XDG_CACHE_HOME or HOME")?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create the folder", dir.display()))?;
    }
    let mut all = read();
    if !all["adapters"].is_object() {
        all["adapters"] = json!({});
    }
    let storage = format!("{:?}", tuned.storage).to_lowercase();
    all["adapters"][device] = json!({
        "walk": flag(tuned.walk), "storage": storage, "measured": detail,
    });
    AtomicFile::create(&path)?.finish_with_bytes(serde_json::to_string_pretty(&all)?.as_bytes())?;
    Ok(path)
}

/// `walk` as `--traversal` takes it (a short stack as `short-stack:K`).
pub fn flag(walk: Traversal) -> String {
    match walk {
        Traversal::ShortStack(k) => format!("short-stack:{k}"),
        t => t.to_string(),
    }
}
