//! The command line.

use std::path::PathBuf;

use bvhtrace_core::{BuilderKind, Traversal};
use bvhtrace_shade::args;
use glam::Vec3;

use crate::shade::Shade;

/// The window size flag: [`args::parse_size`], between 200x150 and 8192x8192.
fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = args::parse_size(s)?;
    if !(200..=8192).contains(&w) || !(150..=8192).contains(&h) {
        return Err(format!(
            "the window must be between 200x150 and 8192x8192, got {s}"
        ));
    }
    Ok((w, h))
}

fn parse_scale(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if (0.1..=2.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!(
            "the render scale must be between 0.1 and 2, got {s}"
        ))
    }
}

fn parse_fov(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if v > 0.0 && v < 180.0 {
        Ok(v)
    } else {
        Err(format!("--fov must be between 0 and 180 degrees, got {s}"))
    }
}

fn parse_time(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(format!(
            "--time must be a finite number of seconds, got {s}"
        ))
    }
}

/// `bvhtrace-viewer [SCENE]`: the interactive viewer. The GPU-traced image fills the
/// window; the side panel has the scene's statistics, the builder, traversal and shading
/// choices, the camera and a comparison with the CPU traversal.
#[derive(clap::Parser, Debug, Clone)]
#[command(name = "bvhtrace-viewer", version, about, long_about = None)]
pub struct Args {
    /// A .gltf/.glb file or a `builtin:` name (see `bvhtrace info --list`); default: the
    /// Cornell box.
    pub scene: Option<String>,
    /// Render --frames frames, save a screenshot of the window to this PNG and exit
    /// (status 0 on success, non-zero with a message on failure).
    #[arg(long, value_name = "PNG")]
    pub screenshot: Option<PathBuf>,
    /// Frames to render (after the scene is loaded) before the screenshot.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub frames: u32,
    /// Window size in points, WxH.
    #[arg(long, default_value = "1280x800", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Initial shading (`heatmap` is the same as `--heatmap`; `path` path traces on the
    /// GPU, progressively).
    #[arg(long, value_enum, default_value_t = Shade::Normal)]
    pub shade: Shade,
    /// Start with the node-visit heatmap on.
    #[arg(long)]
    pub heatmap: bool,
    /// stackless, short-stack, short-stack:K or full-stack.
    #[arg(long, default_value = "stackless")]
    pub traversal: Traversal,
    /// BVH builder: sah, sweep-sah, median or midpoint.
    #[arg(long, default_value = "sah")]
    pub builder: BuilderKind,
    /// Trace on the CPU twin instead of the GPU (the device still draws the window).
    #[arg(long)]
    pub cpu: bool,
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// Traced pixels per window pixel, 0.1..=2 (default: 1 on a GPU, 0.5 on a CPU driver
    /// such as lavapipe).
    #[arg(long, value_parser = parse_scale)]
    pub scale: Option<f32>,
    /// Camera position X,Y,Z (with --target); the same flags as `bvhtrace render`.
    #[arg(long, value_parser = args::parse_vec3, requires = "target", allow_hyphen_values = true)]
    pub eye: Option<Vec3>,
    /// Point the camera looks at.
    #[arg(long, value_parser = args::parse_vec3, requires = "eye", allow_hyphen_values = true)]
    pub target: Option<Vec3>,
    /// Vertical field of view in degrees.
    #[arg(long, value_parser = parse_fov)]
    pub fov: Option<f32>,
    /// Compare the first image's hits with the CPU twin's and open the difference window
    /// (as the "Compare with CPU" button does).
    #[arg(long)]
    pub compare: bool,
    /// Start an animated glTF scene at this time, seconds (wrapped into the animation;
    /// ignored by scenes without one).
    #[arg(long, default_value_t = 0.0, value_parser = parse_time, allow_hyphen_values = true)]
    pub time: f32,
    /// Start playing the scene's animation (the side panel's Play button, or Space). In a
    /// --screenshot run time advances 1/30 s per frame, so that the image does not depend
    /// on the machine's speed.
    #[arg(long)]
    pub play: bool,
    /// An equirectangular Radiance HDR image (`.hdr`, +Y up) the path mode's sky comes
    /// from, sampled by its luminance (`--shade path`; a file of this machine, so not in a
    /// browser).
    #[arg(long, value_name = "FILE.hdr")]
    pub environment: Option<PathBuf>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[test]
    fn flags_parse() {
        let a = Args::try_parse_from([
            "bvhtrace-viewer",
            "builtin:cornell",
            "--screenshot",
            "x.png",
            "--frames",
            "3",
            "--eye",
            "-1,2,3",
            "--target",
            "0,0,0",
            "--fov",
            "40",
            "--traversal",
            "short-stack:4",
            "--shade",
            "ao",
            "--time",
            "1.5",
            "--play",
        ])
        .expect("parses");
        assert_eq!(a.frames, 3);
        assert_eq!(a.eye, Some(Vec3::new(-1.0, 2.0, 3.0)));
        assert_eq!(a.traversal, Traversal::ShortStack(4));
        assert_eq!(a.shade, Shade::Ao);
        assert_eq!(a.size, (1280, 800));
        assert_eq!(a.time, 1.5);
        assert!(a.play);
        let p = Args::try_parse_from(["v", "--shade", "path"]).expect("parses");
        assert_eq!(p.shade, Shade::Path);
        let e = Args::try_parse_from(["v", "--shade", "sepia"])
            .map(|_| ())
            .unwrap_err();
        assert!(e.to_string().contains("invalid value 'sepia'"), "{e}");
        let d = Args::try_parse_from(["v"]).expect("parses");
        assert_eq!(d.time, 0.0);
        assert!(!d.play);
        for bad in [
            &["v", "--frames", "0"][..],
            &["v", "--eye", "1,2,3"],
            &["v", "--size", "10x10"],
            &["v", "--fov", "200"],
            &["v", "--scale", "9"],
            &["v", "--traversal", "zigzag"],
            &["v", "--time", "inf"],
            &["v", "--time", "soon"],
        ] {
            assert!(Args::try_parse_from(bad).is_err(), "{bad:?}");
        }
    }
}
