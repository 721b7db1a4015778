//! The path tracer's side of `bench --converge`: its settings from the flags, its reference
//! (the CPU twin at many samples, kept on disk between runs) and one configuration's
//! progressive image, timed level by level.
//!
//! It imports from the benchmarks' `mod.rs` only, never from `converge` itself, so that the
//! two files do not import each other in a circle.

use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace::Backend;
use bvhtrace_core::masks::MaskTables;
use bvhtrace_core::{FlatBvh, Traversal, Triangle};
use bvhtrace_path::{Accumulation, CpuPathTracer, Lighting, PathParams, PathScene};
use bvhtrace_scene::{Camera, Scene, SceneBvh};
use glam::Vec3;

use crate::bench::{BenchBackend, ConvergeArgs, median};
use crate::output::AtomicFile;
use crate::path::Engine;

/// The measured images' seed: `render --shade path`'s default.
const SEED: u32 = 0;
/// The reference's seed. Sample `s` of seed 1 draws the numbers of sample
/// `s ^ 0xaf05c5de` of seed 0 (`Rng::new` hashes `sample ^ hash(seed)`), so below 2^31
/// samples the reference shares none with the measured images.
const REFERENCE_SEED: u32 = 1;
/// The walk and builder of the reference: the CPU twin's full stack over the default tree.
const REFERENCE_WALK: Traversal = Traversal::FullStack;
/// Changed whenever the cache file's layout or what a reference means changes, so that an
/// old file is never read as a new one.
const CACHE_VERSION: &str = "bvhtrace bench --converge path reference, layout 1";
/// The first bytes of a cache file.
const MAGIC: &[u8; 8] = b"BVHTPRF1";
/// Header bytes: the magic, the key (u64), width, height and samples (u32 each).
const HEADER: usize = 8 + 8 + 12;

/// What every path-traced image of a run shares besides the scene: lights and depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct PathSettings {
    pub(super) lighting: Lighting,
    pub(super) max_depth: u32,
}

impl PathSettings {
    /// The settings `--sun`, `--sky` and `--max-depth` ask for (`render --shade path`'s
    /// defaults otherwise: sky 0.5, no sun, 8 bounces), checked.
    pub(super) fn from_args(c: &ConvergeArgs) -> Result<PathSettings> {
        let mut lighting = Lighting::default();
        if let Some(sky) = c.sky {
            if !(sky.is_finite() && sky.min_element() >= 0.0) {
                bail!("--sky must be three finite numbers of at least 0, got {sky}");
            }
            lighting.env = sky;
        }
        if let Some(sun) = c.sun {
            if !(sun.is_finite() && sun.length_squared() > 0.0) {
                bail!("--sun must be a direction (finite, not zero), got {sun}");
            }
            lighting.sun_dir = sun;
            // `render --shade path`'s default --sun-power.
            lighting.sun = Vec3::splat(3.0);
        }
        Ok(PathSettings {
            lighting,
            max_depth: c.max_depth.unwrap_or(8),
        })
    }
}

/// The folder `--reference-cache` defaults to: `bvhtrace-cache/converge` in the cargo
/// `target` folder the binary runs from, else in the system's temporary folder.
pub(super) fn default_cache_dir() -> PathBuf {
    let exe = std::env::current_exe().ok();
    let target = exe.as_deref().and_then(|e| {
        e.ancestors()
            .find(|a| a.file_name().is_some_and(|n| n == "target"))
            .map(Path::to_path_buf)
    });
    (target.unwrap_or_else(std::env::temp_dir))
        .join("bvhtrace-cache")
        .join("converge")
}

/// True when `backend` runs the path tracer: the kernel on wgpu (our walks or the device's
/// ray queries), the twin on the CPU.
pub(super) fn runs_on(backend: &BenchBackend) -> bool {
    matches!(
        backend.device.backend(),
        Backend::Cpu | Backend::Wgpu | Backend::RayQuery
    )
}

/// What every path-traced image of a scene shares: its triangles, shading data, alpha
/// masks (the scene's look: foliage is cut by them) and the first sample's parameters.
pub(super) struct PathFrame<'a> {
    tris: &'a [Triangle],
    shading: PathScene,
    masks: Option<Arc<MaskTables>>,
    params: PathParams,
}

impl<'a> PathFrame<'a> {
    /// The frame of `scene` (flattened to `tris`, `bvh` built over them) seen by `cam` at
    /// `size` under `settings`.
    pub(super) fn new(
        scene: &Scene,
        tris: &'a [Triangle],
        bvh: &FlatBvh,
        cam: &Camera,
        size: (u32, u32),
        settings: &PathSettings,
    ) -> Result<PathFrame<'a>> {
        let shading = PathScene::new(scene, tris)?;
        // The masks number primitive ids, so they fit every tree over these triangles.
        let flat = SceneBvh::Flat {
            tris: tris.to_vec(),
            bvh: bvh.clone(),
        };
        let masks = scene.alpha_masks(&flat).map(Arc::new);
        let params = PathParams::new(cam, size, &settings.lighting, settings.max_depth, &shading);
        Ok(PathFrame {
            tris,
            shading,
            masks,
            params: PathParams {
                seed: SEED,
                ..params
            },
        })
    }

    /// `bvh` with the scene's alpha masks: a copy where there are some.
    pub(super) fn tree<'b>(&self, bvh: &'b FlatBvh) -> Result<Cow<'b, FlatBvh>> {
        let Some(m) = &self.masks else {
            return Ok(Cow::Borrowed(bvh));
        };
        let mut masked = bvh.clone();
        masked
            .set_masks(Some(m.clone()))
            .map_err(anyhow::Error::msg)?;
        Ok(Cow::Owned(masked))
    }

    /// Emissive triangles, for the log.
    pub(super) fn lights(&self) -> usize {
        self.shading.lights.len()
    }
}

/// The reference image of a scene: tone mapped (for FLIP) and linear (for RMSE).
pub(super) struct PathReference {
    /// 8-bit sRGB, `Accumulation::to_srgb8(1.0)`.
    pub(super) srgb: Vec<u8>,
    /// The mean radiance per pixel.
    pub(super) linear: Vec<[f32; 3]>,
    /// True when read from the cache rather than rendered.
    pub(super) cached: bool,
}

impl PathReference {
    fn of(image: &Accumulation, cached: bool) -> PathReference {
        PathReference {
            srgb: image.to_srgb8(1.0),
            linear: image.linear(),
            cached,
        }
    }
}

/// The reference of `frame`: `spp` samples of the CPU twin (full stack over `bvh`, the
/// default builder's tree, masked as the scene says) under [`REFERENCE_SEED`], read from
/// `dir` when an earlier run left it there, else rendered and left there (`stem` names
/// the file for people; the key in its name and header is what matters).
pub(super) fn reference(
    spec: &str,
    stem: &str,
    frame: &PathFrame,
    bvh: &FlatBvh,
    spp: u32,
    dir: &Path,
) -> Result<PathReference> {
    let params = PathParams {
        seed: REFERENCE_SEED,
        ..frame.params
    };
    let (w, h) = (params.width, params.height);
    let key = cache_key(frame, &params, spp);
    let file = dir.join(format!("{stem}-{w}x{h}-{spp}spp-{key:016x}.bin"));
    match load(&file, key, (w, h), spp) {
        Ok(Some(image)) => {
            eprintln!(
                "{spec}: path reference ({w}x{h}, {spp} spp) read from {}",
                file.display()
            );
            return Ok(PathReference::of(&image, true));
        }
        Ok(None) => {}
        Err(e) => eprintln!("note: {}: {e:#}; rendering it again", file.display()),
    }
    let tree = frame.tree(bvh)?;
    let twin = CpuPathTracer::new(&tree, frame.tris, &frame.shading, REFERENCE_WALK)?;
    let pb = crate::output::progress_bar(u64::from(spp), "{msg} [{bar:30}] {pos}/{len} ({eta})");
    pb.set_message(format!("{spec}: path reference on the CPU twin"));
    let t = Instant::now();
    let mut image = Accumulation::default();
    for sample in 0..spp {
        twin.add_sample(&PathParams { sample, ..params }, &mut image);
        pb.inc(1);
    }
    pb.finish_and_clear();
    eprintln!(
        "{spec}: {} triangles, {} emissive; path reference ({w}x{h}, {spp} spp, CPU twin) in {:.1} s",
        frame.tris.len(),
        frame.lights(),
        t.elapsed().as_secs_f64()
    );
    match store(&file, key, &image) {
        Ok(()) => eprintln!("{spec}: path reference kept in {}", file.display()),
        Err(e) => eprintln!("note: the path reference is not kept: {e:#}"),
    }
    Ok(PathReference::of(&image, false))
}

/// FNV-1a, 64 bits: a key that is the same from build to build (std's hasher promises no
/// such thing), over a few megabytes at most.
struct Fnv(u64);

impl Fnv {
    fn add(&mut self, bytes: &[u8]) -> &mut Fnv {
        // The length first, so that no two lists of pieces run into the same bytes.
        for b in (bytes.len() as u64).to_le_bytes().iter().chain(bytes) {
            self.0 = (self.0 ^ u64::from(*b)).wrapping_mul(0x0100_0000_01b3);
        }
        self
    }
}

/// What the reference depends on, hashed: the cache's version, the tracer (its WGSL, of
/// which the twin is the copy), the triangles, materials, lights and masks, the camera,
/// size, lighting, depth and seed (all in `params`), the samples, walk and builder.
fn cache_key(frame: &PathFrame, params: &PathParams, spp: u32) -> u64 {
    let mut h = Fnv(0xcbf2_9ce4_8422_2325);
    h.add(CACHE_VERSION.as_bytes())
        .add(bvhtrace_path::kernel_source().as_bytes())
        .add(bytemuck::cast_slice(frame.tris))
        .add(bytemuck::cast_slice(&frame.shading.materials))
        .add(bytemuck::cast_slice(&frame.shading.prims))
        .add(bytemuck::cast_slice(&frame.shading.lights))
        .add(bytemuck::bytes_of(params))
        .add(&spp.to_le_bytes())
        .add(REFERENCE_WALK.name().as_bytes())
        .add(bvhtrace_core::BuilderKind::default().name().as_bytes());
    if let Some(m) = &frame.masks {
        h.add(bytemuck::cast_slice(&m.states))
            .add(bytemuck::cast_slice(&m.triangles))
            .add(bytemuck::cast_slice(&m.materials))
            .add(&m.texels);
    }
    h.0
}

/// The sums `file` holds when it is the reference of `key`; `None` when there is no such
/// file; an error when it is damaged or another's.
fn load(file: &Path, key: u64, (w, h): (u32, u32), spp: u32) -> Result<Option<Accumulation>> {
    let bytes = match std::fs::read(file) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).context("cannot read the cached path reference"),
    };
    let pixels = w as usize * h as usize;
    let word = |i: usize| u32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    let fits = bytes.len() == HEADER + pixels * 16
        && bytes.starts_with(MAGIC)
        && bytes[8..16] == key.to_le_bytes()
        && (word(16), word(20), word(24)) == (w, h, spp);
    if !fits {
        bail!("not the cached path reference it is named after (damaged, or of another version)");
    }
    let floats: Vec<f32> = (bytes[HEADER..].chunks_exact(4))
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let sums = floats
        .chunks_exact(4)
        .map(|c| [c[0], c[1], c[2], c[3]])
        .collect();
    Ok(Some(Accumulation {
        width: w,
        height: h,
        sums,
    }))
}

/// Writes `image` as the reference of `key` to `file` (whole or not at all).
fn store(file: &Path, key: u64, image: &Accumulation) -> Result<()> {
    if let Some(dir) = file.parent() {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create the folder", dir.display()))?;
    }
    let mut bytes = Vec::with_capacity(HEADER + image.sums.len() * 16);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&key.to_le_bytes());
    for v in [image.width, image.height, image.samples()] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    for c in image.sums.iter().flatten() {
        bytes.extend_from_slice(&c.to_le_bytes());
    }
    AtomicFile::create(file)?.finish_with_bytes(&bytes)
}

/// The path tracer of `frame` over `bvh` (masked as the frame says) on `backend`, walked by
/// `walk` (the device's ray queries on the ray-query backend), and the time opening took
/// (the upload and the kernel's compilation on a device).
pub(super) fn open<'a>(
    backend: &BenchBackend,
    bvh: &'a FlatBvh,
    frame: &'a PathFrame,
    walk: Traversal,
) -> Result<(Engine<'a>, f64)> {
    let t = Instant::now();
    let twin = || CpuPathTracer::new(bvh, frame.tris, &frame.shading, walk);
    let engine = match Engine::open(
        &backend.device,
        bvh,
        &frame.shading,
        (walk, Default::default()),
        twin,
    )? {
        Some(engine) => engine,
        None => bail!(
            "the path tracer runs on wgpu and the CPU, not on {}",
            backend.device.backend()
        ),
    };
    Ok((engine, t.elapsed().as_secs_f64() * 1e3))
}

/// One level of a progressive image.
pub(super) struct Level {
    /// The sums at this level's samples per pixel.
    pub(super) image: Accumulation,
    /// Rays traced from the first sample (modulo 2^32 on a device).
    pub(super) rays: u64,
    /// The samples from the first to this level's last, done (median of the runs); the
    /// readbacks of earlier levels are not in it.
    pub(super) image_ms: f64,
    /// Reading the sums back at this level (a copy on the CPU; median of the runs).
    pub(super) readback_ms: f64,
}

/// `engine`'s image of `frame` grown to each of `levels` (increasing samples per pixel),
/// `runs` times: at each level the clock stops, the sums are read, the clock goes on. A
/// first sample and readback, untimed, does what a renderer does once (the driver's first
/// dispatch, the readback's buffers).
pub(super) fn progressive(
    engine: &mut Engine,
    frame: &PathFrame,
    levels: &[u32],
    runs: usize,
) -> Result<Vec<Level>> {
    engine.restart(frame.params);
    engine.add(1)?;
    engine.read()?;
    let mut image_ms = vec![Vec::new(); levels.len()];
    let mut readback_ms = vec![Vec::new(); levels.len()];
    let mut last = Vec::new();
    for _ in 0..runs.max(1) {
        engine.restart(frame.params);
        let (mut spent, mut done) = (0.0, 0);
        last.clear();
        for (i, &spp) in levels.iter().enumerate() {
            let t = Instant::now();
            engine.add(spp - done)?;
            spent += t.elapsed().as_secs_f64() * 1e3;
            done = spp;
            image_ms[i].push(spent);
            let t = Instant::now();
            let (image, stats) = engine.read()?;
            readback_ms[i].push(t.elapsed().as_secs_f64() * 1e3);
            last.push((image, stats.rays));
        }
    }
    Ok((last.into_iter().zip(image_ms).zip(readback_ms))
        .map(|(((image, rays), t), r)| Level {
            image,
            rays,
            image_ms: median(t),
            readback_ms: median(r),
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cornell_frame<'a>(
        scene: &Scene,
        tris: &'a [Triangle],
        bvh: &FlatBvh,
        size: (u32, u32),
        settings: &PathSettings,
    ) -> PathFrame<'a> {
        let cam = scene.camera_or_frame(size.0 as f32 / size.1 as f32);
        PathFrame::new(scene, tris, bvh, &cam, size, settings).unwrap()
    }

    #[test]
    fn the_key_follows_what_the_reference_depends_on() {
        let scene = bvhtrace_scene::load("builtin:cornell").unwrap();
        let tris = scene.flattened_triangles().unwrap();
        let bvh = FlatBvh::build(&tris, &Default::default()).unwrap();
        let base = PathSettings::from_args(&ConvergeArgs::default()).unwrap();
        let key = |size, settings: &PathSettings, spp| {
            let frame = cornell_frame(&scene, &tris, &bvh, size, settings);
            let params = PathParams {
                seed: REFERENCE_SEED,
                ..frame.params
            };
            cache_key(&frame, &params, spp)
        };
        let k = key((16, 12), &base, 8);
        assert_eq!(
            k,
            key((16, 12), &base, 8),
            "the same reference, the same key"
        );
        let deeper = PathSettings {
            max_depth: 3,
            ..base
        };
        let mut sunny = base;
        sunny.lighting.sun = Vec3::ONE;
        let mut dark = base;
        dark.lighting.env = Vec3::ZERO;
        for other in [
            key((16, 13), &base, 8),
            key((16, 12), &base, 9),
            key((16, 12), &deeper, 8),
            key((16, 12), &sunny, 8),
            key((16, 12), &dark, 8),
        ] {
            assert_ne!(k, other);
        }
    }

    #[test]
    fn a_stored_reference_reads_back_and_nothing_else_does() {
        let dir = std::env::temp_dir().join(format!("bvhtrace-path-ref-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let file = dir.join("sub").join("r.bin");
        assert!(load(&file, 7, (3, 2), 4).unwrap().is_none(), "no file yet");
        let image = Accumulation {
            width: 3,
            height: 2,
            sums: (0..6)
                .map(|i| [i as f32, 0.5, -1.0, 4.0])
                .collect::<Vec<_>>(),
        };
        store(&file, 7, &image).unwrap();
        assert_eq!(load(&file, 7, (3, 2), 4).unwrap(), Some(image));
        // Another key, size or sample count is another reference.
        assert!(load(&file, 8, (3, 2), 4).is_err());
        assert!(load(&file, 7, (2, 3), 4).is_err());
        assert!(load(&file, 7, (3, 2), 5).is_err());
        // A file cut short is damaged, not read.
        let bytes = std::fs::read(&file).unwrap();
        std::fs::write(&file, &bytes[..bytes.len() - 1]).unwrap();
        assert!(load(&file, 7, (3, 2), 4).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn lighting_flags_out_of_range_are_errors() {
        let bad_sky = ConvergeArgs {
            sky: Some(Vec3::new(0.5, -0.1, 0.5)),
            ..Default::default()
        };
        let no_sun = ConvergeArgs {
            sun: Some(Vec3::ZERO),
            ..Default::default()
        };
        for args in [bad_sky, no_sun] {
            assert!(PathSettings::from_args(&args).is_err());
        }
        let s = PathSettings::from_args(&ConvergeArgs {
            sun: Some(Vec3::Y),
            max_depth: Some(3),
            ..Default::default()
        })
        .unwrap();
        assert_eq!((s.lighting.sun, s.max_depth), (Vec3::splat(3.0), 3));
        assert_eq!(s.lighting.env, Lighting::default().env);
    }
}
