//! What the examples share: the command line (`[SCENE] [FLAGS...] [-o out.png]`) and
//! making a buffer.
#![allow(dead_code)]

use std::error::Error;
use std::path::PathBuf;

use bvhtrace_gpu::wgpu;

/// What the command line says.
pub struct Args {
    /// The scene: a glTF file or a `builtin:` name (the default scene when none is given).
    pub spec: String,
    /// The image to write.
    pub out: PathBuf,
    /// The flags given, of those the example takes.
    pub flags: Vec<String>,
}

/// Parses the command line: a scene, `-o FILE` (else `default_out`) and any of `flags`.
/// `None` after printing `usage` for `-h` or `--help`.
pub fn parse_args(
    usage: &str,
    default_out: &str,
    flags: &[&str],
) -> Result<Option<Args>, Box<dyn Error>> {
    let mut parsed = Args {
        spec: bvhtrace_scene::DEFAULT_SCENE.to_string(),
        out: PathBuf::from(default_out),
        flags: Vec::new(),
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "-o" => parsed.out = args.next().ok_or("-o needs a file name")?.into(),
            "-h" | "--help" => {
                println!("usage: {usage}");
                return Ok(None);
            }
            f if flags.contains(&f) => parsed.flags.push(f.to_string()),
            _ => parsed.spec = arg,
        }
    }
    Ok(Some(parsed))
}

/// A buffer of `size` bytes for `usage`, not mapped.
pub fn buffer(
    device: &wgpu::Device,
    label: &str,
    size: u64,
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage,
        mapped_at_creation: false,
    })
}
