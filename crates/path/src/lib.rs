//! A progressive path tracer in WGSL on bvhtrace's public traversal library, and its CPU
//! twin.
//!
//! The device kernel (`shaders/path_sampling.wgsl` and `shaders/path_trace.wgsl`) is
//! composed after the library exactly as a user's shader is (`GpuContext::shader_module`):
//! it calls `bvh_trace_closest`, `bvh_trace_any` and `bvh_hit_surface`, so it runs over
//! whatever the upload holds (buffers or textures, binary or wide layout, alpha masks) and
//! over the device's ray queries. Camera rays are made on the device, each pixel's sample
//! added to a sum kept on the device ([`GpuPathTracer`]); nothing is read back until
//! asked. The paths are followed in waves of one vertex per live path by default
//! ([`PathKernel::Wavefront`]), or each by one invocation to its end
//! ([`PathKernel::Megakernel`]): the same function per vertex, the same sums.
//!
//! Shading: glTF metallic-roughness (Lambert under GGX, sampled by lobe), emission, next
//! event estimation toward a sun, a constant environment and the emissive triangles (by
//! power), each with an any-hit shadow ray, combined by multiple importance sampling
//! (power heuristic); Russian roulette from the third bounce.
//!
//! [`CpuPathTracer`] traces the same paths on the CPU: the same random numbers
//! (counter-based, per pixel, sample and bounce), the same operations in the same order,
//! no transcendental function on either side. On lavapipe its sums equal the device's bit
//! for bit (`tests/twin.rs`).
//!
//! ```no_run
//! use bvhtrace_core::{BuildOptions, FlatBvh, Traversal};
//! use bvhtrace_gpu::GpuContext;
//! use bvhtrace_path::{GpuPathTracer, Lighting, PathParams, PathScene};
//!
//! let scene = bvhtrace_scene::load("builtin:cornell")?;
//! let tris = scene.flattened_triangles()?;
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let shading = PathScene::new(&scene, &tris)?;
//! let camera = scene.camera_or_frame(1.0);
//! let params = PathParams::new(&camera, (256, 256), &Lighting::default(), 8, &shading);
//! let ctx = GpuContext::new(bvhtrace_gpu::AdapterChoice::Auto)?;
//! let mut tracer = GpuPathTracer::new(&ctx, &bvh, &shading, Traversal::Stackless)?;
//! tracer.restart(params);
//! tracer.add_samples(64)?;
//! let (image, stats) = tracer.read()?;
//! assert_eq!(image.samples(), 64);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

mod device;
pub mod environment;
mod material;
pub mod sampling;
mod scene;
pub mod textures;
mod twin;
pub mod wavefront;

pub use device::{GpuPathTracer, PathWalk, kernel_source};
pub use environment::Environment;
pub use material::{NO_TEXTURE, PathMaterial};
pub use scene::{Lighting, MAX_EMISSION, NO_LIGHT, PathLight, PathParams, PathScene};
pub use twin::{CpuPathTracer, mean_luminance};
pub use wavefront::PathKernel;

/// Why a path tracer could not be made or run.
#[derive(Debug, thiserror::Error)]
pub enum PathError {
    /// The scene's shading data does not fit its triangles.
    #[error("{0}")]
    Scene(String),
    /// The device, the upload or the kernel failed.
    #[error(transparent)]
    Gpu(#[from] bvhtrace_gpu::GpuError),
    /// A setting out of range.
    #[error("{0}")]
    Setting(String),
}

/// What a frame's paths met that they could not trace as asked.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PathStats {
    /// Rays the walk gave up on (a CPU driver's trip budget): the path ends there, dark.
    pub incomplete: u64,
    /// Samples whose radiance was not finite (or above 3e38): dropped, so that no pixel is
    /// NaN.
    pub not_finite: u64,
    /// Rays traced: closest hits and shadow rays (on a device, modulo 2^32).
    pub rays: u64,
}

impl std::ops::Add for PathStats {
    type Output = PathStats;
    fn add(self, o: PathStats) -> PathStats {
        PathStats {
            incomplete: self.incomplete + o.incomplete,
            not_finite: self.not_finite + o.not_finite,
            rays: self.rays + o.rays,
        }
    }
}

/// The progressive sum of a frame: per pixel, row by row from the top, the sum of its
/// samples' linear RGB radiance and their count.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Accumulation {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Per pixel: red, green and blue sums, and the number of samples.
    pub sums: Vec<[f32; 4]>,
}

impl Accumulation {
    /// Sizes the sums for a `width` x `height` frame (new pixels zero).
    pub fn resize(&mut self, width: u32, height: u32) {
        self.width = width;
        self.height = height;
        self.sums.resize(width as usize * height as usize, [0.0; 4]);
    }

    /// Samples per pixel (those of the first pixel; all pixels have as many).
    pub fn samples(&self) -> u32 {
        self.sums.first().map_or(0, |s| s[3] as u32)
    }

    /// The mean radiance per pixel, linear RGB, row by row.
    pub fn linear(&self) -> Vec<[f32; 3]> {
        (self.sums.iter())
            .map(|s| {
                let n = s[3].max(1.0);
                [s[0] / n, s[1] / n, s[2] / n]
            })
            .collect()
    }

    /// The image as 8-bit sRGB: the mean radiance times `exposure`, tone mapped (Reinhard
    /// on each channel, `x / (1 + x)` of twice the value, so that 1 maps near white) and
    /// encoded with the sRGB curve.
    pub fn to_srgb8(&self, exposure: f32) -> Vec<u8> {
        let encode = |c: f32| {
            let x = (c * exposure).max(0.0);
            let t = 2.0 * x / (1.0 + 2.0 * x);
            let s = if t <= 0.003_130_8 {
                12.92 * t
            } else {
                1.055 * t.powf(1.0 / 2.4) - 0.055
            };
            (s * 255.0 + 0.5).clamp(0.0, 255.0) as u8
        };
        self.linear().iter().flat_map(|p| p.map(encode)).collect()
    }

    /// Pixels with a NaN or infinite mean.
    pub fn not_finite_pixels(&self) -> usize {
        (self.linear().iter())
            .filter(|p| p.iter().any(|c| !c.is_finite()))
            .count()
    }

    /// The image as a portable float map (PFM: linear RGB, 32-bit floats, bottom row
    /// first): a high-dynamic-range file that image tools read.
    pub fn to_pfm(&self) -> Vec<u8> {
        let mut out = format!("PF\n{} {}\n-1.0\n", self.width, self.height).into_bytes();
        let linear = self.linear();
        for row in (0..self.height as usize).rev() {
            let w = self.width as usize;
            for p in &linear[row * w..(row + 1) * w] {
                for c in p {
                    out.extend_from_slice(&c.to_le_bytes());
                }
            }
        }
        out
    }
}
