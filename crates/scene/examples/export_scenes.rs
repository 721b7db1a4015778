//! Regenerates the small scenes committed in the repository's `scenes/` folder:
//! `cargo run -p bvhtrace-scene --example export_scenes [-- OUT_DIR]`.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = match std::env::args().nth(1) {
        Some(d) => PathBuf::from(d),
        None => bvhtrace_scene::repo_scenes_dir().ok_or("no scenes/ folder found; give one")?,
    };
    let cornell = bvhtrace_scene::load("builtin:cornell")?;
    bvhtrace_scene::write_gltf_embedded(&cornell, out.join("cornell.gltf"))?;
    let ico = bvhtrace_scene::load("builtin:icosphere:2")?;
    bvhtrace_scene::write_glb(&ico, out.join("icosphere.glb"))?;
    println!("wrote cornell.gltf and icosphere.glb to {}", out.display());
    Ok(())
}
