//! `bvhtrace render --shade path`: the scene path traced on the device (`bvhtrace-path`),
//! its samples summed there and read back once, or on the CPU twin with `--backend cpu`.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace_core::{FlatBvh, Traversal};
use bvhtrace_path::{
    Accumulation, CpuPathTracer, GpuPathTracer, PathError, PathKernel, PathParams, PathScene,
    PathStats, PathWalk,
};
use bvhtrace_scene::SceneBvh;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use crate::backend::{self, Backend, Device};
use crate::output::{AtomicFile, JsonOut, write_png};
use crate::render::{RenderArgs, camera_for, load_and_build};

/// Where a path tracer's samples are traced, for `render` and `bench --converge` alike: the
/// kernel on a wgpu device (its sums stay there until read), or the CPU twin with its sums,
/// the next sample's parameters and what its paths met.
pub enum Engine<'a> {
    /// The kernel on a wgpu device: our walk or its ray queries.
    Device(Box<GpuPathTracer>),
    /// The CPU twin.
    Cpu(
        CpuPathTracer<'a>,
        Box<(Accumulation, PathParams, PathStats)>,
    ),
}

impl<'a> Engine<'a> {
    /// The path tracer over `bvh` on `device`: `kernel` walked by `walk` (the device's
    /// ray queries on the ray-query backend), or on the CPU the twin `twin` makes; `None`
    /// on a backend without a path tracer (raw Vulkan, the mock).
    pub fn open(
        device: &Device,
        bvh: &'a FlatBvh,
        shading: &PathScene,
        (walk, kernel): (Traversal, PathKernel),
        twin: impl FnOnce() -> Result<CpuPathTracer<'a>, PathError>,
    ) -> Result<Option<Engine<'a>>> {
        Ok(Some(match device.backend() {
            Backend::Cpu => Engine::Cpu(twin()?, Box::default()),
            b @ (Backend::Wgpu | Backend::RayQuery) => {
                let ctx = (device.wgpu_context()).context("a wgpu backend without its context")?;
                let walk = match b {
                    Backend::RayQuery => PathWalk::RayQueries,
                    _ => PathWalk::Walk(walk),
                };
                let t = GpuPathTracer::with_kernel(ctx, bvh, shading, walk, kernel)?;
                Engine::Device(Box::new(t))
            }
            _ => return Ok(None),
        }))
    }

    /// Starts the sums over at sample 0.
    pub fn restart(&mut self, params: PathParams) {
        match self {
            Engine::Device(t) => t.restart(params),
            Engine::Cpu(_, state) => {
                **state = (Accumulation::default(), params, PathStats::default())
            }
        }
    }

    /// Adds `n` samples and returns once they are done (the device waited for).
    pub fn add(&mut self, n: u32) -> Result<()> {
        match self {
            Engine::Device(t) => {
                t.add_samples(n)?;
                t.wait()?;
            }
            Engine::Cpu(twin, state) => {
                let (sums, params, stats) = &mut **state;
                for _ in 0..n {
                    *stats = *stats + twin.add_sample(params, sums);
                    params.sample += 1;
                }
            }
        }
        Ok(())
    }

    /// The sums so far and what the paths met (read back from a device).
    pub fn read(&self) -> Result<(Accumulation, PathStats)> {
        match self {
            Engine::Device(t) => Ok(t.read()?),
            Engine::Cpu(_, state) => Ok((state.0.clone(), state.2)),
        }
    }
}

/// `render --shade path`: the image and, when asked, its linear radiance.
pub fn render(args: RenderArgs) -> Result<()> {
    // Fail on bad flags and output paths before any work.
    let png = AtomicFile::create(&args.output)?;
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let args = &args;
    let p = &args.path;
    let lighting = p.lighting()?;
    let environment = p.environment()?;
    let hdr = p.hdr.as_deref().map(AtomicFile::create).transpose()?;
    let walk = args.walk()?;
    let opts = backend::options(args.backend, args.adapter.as_deref(), &Vec::from_iter(walk));
    let device = backend::device(&opts)?;
    // One mesh, or two levels when the scene places meshes more than once (not with
    // --flatten): either numbers the flattened scene's triangles, as the shading data does.
    let mut built = load_and_build(&args.scene, Some(&device))?;
    if args.opaque {
        (built.geometry)
            .set_masks(None)
            .map_err(anyhow::Error::msg)?;
    }
    let tris = match &built.geometry {
        SceneBvh::Flat { tris, .. } => tris.clone(),
        SceneBvh::Instanced(_) => built.scene.flattened_triangles()?,
    };
    let mut shading = PathScene::new(&built.scene, &tris)?;
    shading.set_environment(environment);
    let cam = camera_for(&args.view, &built.scene)?;
    let (w, h) = args.view.size;
    let params = PathParams::new(&cam, (w, h), &lighting, p.max_depth, &shading);
    let params = PathParams {
        seed: p.seed,
        ..params
    };
    let traversal = walk.unwrap_or(match device.backend() {
        Backend::Cpu => Traversal::FullStack,
        _ => Traversal::Stackless,
    });
    if traversal.is_wide() {
        built.geometry.build_wide();
    }
    let kernel = p.kernel.into();
    let mut engine = open(&device, &built.geometry, &shading, (traversal, kernel))?;
    eprintln!(
        "path tracing {} ({} triangles, {} emissive) at {w}x{h}, {} spp, {} bounces at most, on {} ({})",
        built.scene.name,
        tris.len(),
        shading.lights.len(),
        p.spp,
        p.max_depth,
        device.name(),
        walk_name(&engine, traversal),
    );
    let start = Instant::now();
    let (image, stats) = trace(&mut engine, params, p.spp)?;
    let seconds = start.elapsed().as_secs_f64();
    if image.not_finite_pixels() > 0 {
        bail!(
            "{} pixels are not finite (a bug: samples that are not are dropped)",
            image.not_finite_pixels()
        );
    }
    write_png(png, w, h, image.to_srgb8(p.exposure))?;
    if let Some(f) = hdr {
        f.finish_with_bytes(&image.to_pfm())?;
    }
    let paths = f64::from(w) * f64::from(h) * f64::from(p.spp);
    eprintln!(
        "{} spp in {seconds:.2} s: {:.1} samples per second, {:.2} Mpaths/s, {:.2} Mrays/s ({} rays{}{})",
        p.spp,
        f64::from(p.spp) / seconds,
        paths / seconds / 1e6,
        stats.rays as f64 / seconds / 1e6,
        stats.rays,
        note(stats.incomplete, "given up by the walk's trip budget"),
        note(stats.not_finite, "samples dropped as not finite"),
    );
    eprintln!("wrote {}", args.output.display());
    if let Some(j) = json_out {
        j.write(&json!({
            "scene": built.scene.name,
            "shade": "path",
            "backend": format!("{:?}", device.backend()).to_lowercase(),
            "device": device.name(),
            "walk": walk_name(&engine, traversal),
            "size": [w, h],
            "spp": p.spp,
            "max_depth": p.max_depth,
            "seconds": seconds,
            "samples_per_s": f64::from(p.spp) / seconds,
            "mpaths_per_s": paths / seconds / 1e6,
            "rays": stats.rays,
            "mrays_per_s": stats.rays as f64 / seconds / 1e6,
            "incomplete": stats.incomplete,
            "not_finite": stats.not_finite,
            "load_ms": built.load_ms,
            "build_ms": built.build_ms,
        }))?;
    }
    Ok(())
}

fn note(n: u64, what: &str) -> String {
    if n == 0 {
        String::new()
    } else {
        format!("; {n} {what}")
    }
}

fn walk_name(engine: &Engine<'_>, traversal: Traversal) -> String {
    match engine {
        Engine::Device(t) if t.walk() == PathWalk::RayQueries => "the device's ray queries".into(),
        Engine::Device(_) => format!("{} walk, WGSL", traversal.name()),
        Engine::Cpu(..) => format!("{} walk, the CPU twin", traversal.name()),
    }
}

/// The path tracer of `geometry` on `device`: the kernel on a wgpu device, the twin on the
/// CPU (over one mesh or two levels).
fn open<'a>(
    device: &Device,
    geometry: &'a SceneBvh,
    shading: &'a PathScene,
    (traversal, kernel): (Traversal, PathKernel),
) -> Result<Engine<'a>> {
    let twin = || match geometry {
        SceneBvh::Flat { tris, bvh } => CpuPathTracer::new(bvh, tris, shading, traversal),
        SceneBvh::Instanced(ib) => CpuPathTracer::instanced(ib, shading, traversal),
    };
    match Engine::open(device, geometry.bvh(), shading, (traversal, kernel), twin)? {
        Some(engine) => Ok(engine),
        None => bail!(
            "--shade path runs on wgpu (--backend gpu or ray-query) or the CPU twin (--backend \
             cpu), not on {:?}",
            device.backend()
        ),
    }
}

/// `spp` samples of `params`, with a progress bar; the sums and what the paths met.
fn trace(
    engine: &mut Engine<'_>,
    params: PathParams,
    spp: u32,
) -> Result<(Accumulation, PathStats)> {
    let pb = ProgressBar::new(u64::from(spp));
    pb.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} samples {elapsed_precise} (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    engine.restart(params);
    // Each sample waited for, so that the bar tells the truth; nothing read back.
    for _ in 0..spp {
        engine.add(1)?;
        pb.inc(1);
    }
    let out = engine.read()?;
    pb.finish_and_clear();
    Ok(out)
}
