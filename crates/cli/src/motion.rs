//! Motion blur in `bvhtrace render --shutter` and `bvhtrace dump --shutter`: the scene's
//! animation over the shutter (`Scene::motion`, or `Scene::moving_instances` in two
//! levels), its moving tree, and rays that each carry a time. Scenes with curves
//! (`builtin:hair`) render through the same samples, shading and image, on the CPU tree
//! that holds their triangles and curve segments ([`CurveBvh`]).
//!
//! Each traces through the front door (`bvhtrace::open_timed`): on the device (our walks in
//! WGSL) or on the CPU (a moving mesh in the CPU layout, the others on the core walks),
//! which answer alike; the heatmap counts the CPU twin's tests. Each pixel
//! takes `--shutter-samples` samples, sample `s` at a time in the `s`-th of as many equal
//! parts of the shutter (stratified, jittered by a hash of the pixel), so the samples of
//! one pixel cover the shutter evenly. A sample's secondary rays (shadow, AO) leave at its
//! time and meet the scene at that time.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace::{TimedScene, TimedTracer};
use bvhtrace_core::motion::{MotionBvh, MotionInstancedBvh, MotionMesh, TimeBounds};
use bvhtrace_core::{Counters, CurveBvh, Hit, Query, Ray, Triangle};
use bvhtrace_scene::Scene;
use glam::Vec3;
use rayon::prelude::*;
use serde_json::json;

use crate::backend::{self, Backend};
use crate::geometry::Builder;
use crate::output::{AtomicFile, JsonOut, write_png};
use crate::render::{RenderArgs, camera_for};
use crate::shade::{self, Pixels, Shade, View};

/// The shutter flags of `render` and `dump`.
#[derive(clap::Args, Clone)]
pub struct ShutterArgs {
    /// Open the shutter from OPEN to CLOSE seconds of the scene's animation and blur what
    /// moves: each pixel's samples spread over the shutter, each meeting the scene where
    /// it is at its time (node animations, skins and morphs, followed in as many time
    /// steps as keep the motion between them straight). Traced by our walks through wgpu
    /// or on the CPU.
    #[arg(long, value_name = "OPEN,CLOSE", value_parser = parse_shutter, allow_hyphen_values = true)]
    pub shutter: Option<(f32, f32)>,
    /// Samples per pixel over the shutter (with --shutter).
    #[arg(long, value_name = "N", default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub shutter_samples: u32,
    /// With --shutter: two levels, the meshes under their instances' moving transforms
    /// (for a scene whose animation moves instances without deforming meshes), instead of
    /// the flattened moving triangles.
    #[arg(long, requires = "shutter")]
    pub instances: bool,
}

/// `--time-bounds`: [`TimeBounds`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TimeBoundsArg {
    /// A box per time step, interpolated at the ray's time.
    Linear,
    /// One box over the whole shutter.
    Merged,
}

impl From<TimeBoundsArg> for TimeBounds {
    fn from(b: TimeBoundsArg) -> Self {
        match b {
            TimeBoundsArg::Linear => TimeBounds::Linear,
            TimeBoundsArg::Merged => TimeBounds::Merged,
        }
    }
}

fn parse_shutter(s: &str) -> Result<(f32, f32), String> {
    let parsed = s
        .split_once(',')
        .and_then(|(a, b)| Some((a.trim().parse().ok()?, b.trim().parse().ok()?)));
    match parsed {
        Some((open, close)) if f32::is_finite(open) && f32::is_finite(close) && open < close => {
            Ok((open, close))
        }
        _ => Err(format!(
            "expected OPEN,CLOSE in seconds with OPEN before CLOSE (e.g. 0.5,0.55), got {s}"
        )),
    }
}

/// Sample `sample` of `samples` of pixel `pixel`: its time in `[0, 1]`, the shutter's
/// fraction (stratified: the `sample`-th part of the shutter, jittered by a hash).
pub fn ray_time(pixel: u32, sample: u32, samples: u32) -> f32 {
    let mut h = pixel.wrapping_mul(0x9E37_79B1) ^ sample.wrapping_mul(0x85EB_CA77) ^ 0x2545_F491;
    h ^= h >> 16;
    h = h.wrapping_mul(0x7FEB_352D);
    h ^= h >> 15;
    h = h.wrapping_mul(0x846C_A68B);
    h ^= h >> 16;
    let jitter = (h >> 8) as f32 / (1u32 << 24) as f32;
    ((sample as f32 + jitter) / samples as f32).min(1.0)
}

/// Every sample's rays and times: the camera's rays once per sample, sample 0 first.
pub fn sample_rays(camera_rays: &[Ray], samples: u32) -> (Vec<Ray>, Vec<f32>) {
    let rays = (0..samples)
        .flat_map(|_| camera_rays.iter().copied())
        .collect();
    let times = (0..samples)
        .flat_map(|s| (0..camera_rays.len() as u32).map(move |p| ray_time(p, s, samples)))
        .collect();
    (rays, times)
}

/// The flags a blurred render (or one with curves, `shutter` `None`) cannot honour yet,
/// refused before any work.
fn check_flags(args: &RenderArgs, shutter: Option<(f32, f32)>) -> Result<()> {
    let what = if shutter.is_some() {
        "--shutter"
    } else {
        "a scene with curves"
    };
    if args.backend == Backend::Vulkan || args.backend == Backend::Mock {
        bail!(
            "{what} traces with our walks through wgpu or on the CPU: use --backend gpu, cpu or auto"
        );
    }
    if args.shade == Shade::Heatmap && args.backend != Backend::Cpu {
        bail!("{what} counts the heatmap's box tests on the CPU: use --backend cpu");
    }
    let unsupported = [
        (args.walk()?.is_some(), "--traversal and --layout"),
        (args.storage.is_some(), "--storage"),
        (args.max_binding_mib.is_some(), "--max-binding-mib"),
        (args.scene.time.is_some(), "--time"),
        (
            args.scene.flatten,
            "--flatten (a blurred scene is always flattened)",
        ),
        (args.shade == Shade::Path, "--shade path"),
        (
            matches!(args.scene.build.builder, Builder::Device(_)),
            "a device --builder",
        ),
    ];
    if let Some((_, flag)) = unsupported.iter().find(|(on, _)| *on) {
        bail!("{what} does not take {flag}");
    }
    Ok(())
}

/// What a blurred render traces, and where: one moving mesh, moving instances in two
/// levels, or a scene's triangles and curves ([`TimedScene`]), traced through the front
/// door ([`bvhtrace::open_timed`]: wgpu, or the CPU); for the heatmap, the CPU twin, which
/// counts its tests.
struct Walker {
    scene: TimedScene,
    /// The moving triangles a hit is shaded on (one moving mesh).
    mesh: Option<MotionMesh>,
    tracer: Box<dyn TimedTracer>,
    backend: bvhtrace::Backend,
    /// The heatmap's closest hits come from the CPU twin, with its counters.
    counted: bool,
}

impl Walker {
    /// The scene over the shutter as the flags say, built, and opened on the backend
    /// `--backend` names (the best one for auto, which falls back to the CPU, saying why,
    /// where the device cannot take the tree).
    fn build(args: &RenderArgs, scene: &Scene, shutter: Option<(f32, f32)>) -> Result<Walker> {
        let opts = args.scene.build.options();
        let bounds = TimeBounds::from(args.time_bounds);
        let (timed, mesh) = match shutter {
            None => {
                let Some(curves) = scene.curves.clone() else {
                    bail!("the scene has no curves");
                };
                let tris = scene.flattened_triangles()?;
                let bvh = CurveBvh::build(&tris, curves, &opts)?;
                (TimedScene::Curves(Arc::new(bvh)), None)
            }
            Some((open, close)) if args.shutter.instances => {
                let (meshes, instances) = scene.moving_instances(open, close)?;
                let bvh = MotionInstancedBvh::build(&meshes, instances, &opts, bounds)?;
                (TimedScene::MovingInstances(Arc::new(bvh)), None)
            }
            Some((open, close)) => {
                let mesh = scene.motion(open, close)?;
                let bvh = MotionBvh::build(&mesh, &opts, bounds)?;
                (TimedScene::Moving(Arc::new(bvh)), Some(mesh))
            }
        };
        let device = backend::device(&backend::options(
            args.backend,
            args.adapter.as_deref(),
            &[],
        ))?;
        let opened = device.open_timed(timed.clone())?;
        if let Some(why) = opened
            .fallback
            .as_deref()
            .filter(|w| Some(*w) != device.fallback())
        {
            eprintln!("note: {why}");
        }
        Ok(Walker {
            scene: timed,
            mesh,
            tracer: opened.tracer,
            backend: opened.backend,
            counted: args.shade == Shade::Heatmap,
        })
    }

    fn name(&self) -> &'static str {
        match self.backend {
            bvhtrace::Backend::Cpu => "cpu",
            _ => "wgpu",
        }
    }

    /// The curves it traces, if any.
    fn curves(&self) -> Option<&bvhtrace_core::Curves> {
        match &self.scene {
            TimedScene::Curves(b) => Some(b.curves()),
            _ => None,
        }
    }

    /// `(triangles, time steps, tree bytes, depth)`.
    fn sizes(&self) -> (usize, usize, usize, u32) {
        match &self.scene {
            TimedScene::Moving(b) => (b.triangle_count(), b.time_steps(), b.byte_size(), b.depth()),
            TimedScene::MovingInstances(b) => {
                (b.triangle_count(), b.time_steps(), b.byte_size(), b.depth())
            }
            TimedScene::Curves(b) => (b.triangle_count(), 1, b.byte_size(), b.depth()),
        }
    }

    /// The box around everything over the shutter.
    fn bounds(&self) -> bvhtrace_core::Aabb {
        match &self.scene {
            TimedScene::Moving(b) => b.bounds(),
            TimedScene::MovingInstances(b) => b.bounds(),
            TimedScene::Curves(b) => b.bounds(),
        }
    }

    /// The triangle `hit` of `ray` is on where it is at `time` (for a curve, the triangle
    /// in its tangent plane that shades it: [`CurveBvh::shading_triangle`]).
    fn triangle_at(&self, hit: &Hit, ray: &Ray, time: f32) -> Triangle {
        match (&self.scene, &self.mesh) {
            (TimedScene::Moving(_), Some(m)) => m.triangle_at(hit.prim as usize, time),
            (TimedScene::MovingInstances(b), _) => {
                b.triangle_at(hit.prim, time).unwrap_or_default()
            }
            (TimedScene::Curves(b), _) => b.shading_triangle(hit, ray),
            (TimedScene::Moving(_), None) => Triangle::default(),
        }
    }

    /// Closest hits, with the twin's counters for the heatmap (none otherwise).
    fn closest(&self, rays: &[Ray], times: &[f32]) -> Result<(Vec<Hit>, Vec<Counters>)> {
        if !self.counted {
            return Ok((self.tracer.trace(rays, times, Query::Closest)?, Vec::new()));
        }
        let on_cpu = |trace: &(dyn Fn(&Ray, f32) -> (Hit, Counters) + Sync)| {
            rays.par_iter()
                .zip(times)
                .with_min_len(64)
                .map(|(r, &time)| trace(r, time))
                .unzip()
        };
        Ok(match &self.scene {
            TimedScene::Moving(b) => on_cpu(&|r, t| b.trace(r, t, Query::Closest)),
            TimedScene::MovingInstances(b) => on_cpu(&|r, t| b.trace(r, t, Query::Closest)),
            TimedScene::Curves(b) => on_cpu(&|r, _| b.trace(r, Query::Closest)),
        })
    }

    fn any(&self, rays: &[Ray], times: &[f32]) -> Result<Vec<Hit>> {
        Ok(self.tracer.trace(rays, times, Query::Any)?)
    }
}

/// What the samples traced, summed.
#[derive(Default)]
struct Totals {
    rays: u64,
    hits: u64,
    t_sum: f64,
    primary_ms: f64,
    secondary_rays: u64,
    trace_ms: f64,
}

/// `bvhtrace render --shutter`: the samples of every pixel over the shutter, each shaded
/// as `--shade` says, averaged.
///
/// Without a shutter (`None`), the scene's curves and triangles, one sample per pixel.
pub fn render(args: &RenderArgs, shutter: Option<(f32, f32)>) -> Result<()> {
    check_flags(args, shutter)?;
    let png = AtomicFile::create(&args.output)?;
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let spec = args
        .scene
        .scene
        .as_deref()
        .unwrap_or(bvhtrace_scene::DEFAULT_SCENE);
    let t0 = Instant::now();
    let scene = crate::geometry::load_scene(spec)?;
    let load_ms = t0.elapsed().as_secs_f64() * 1e3;
    let t1 = Instant::now();
    let bounds = TimeBounds::from(args.time_bounds);
    let walker = Walker::build(args, &scene, shutter).with_context(|| match shutter {
        Some((open, close)) => format!("{spec} over the shutter {open}..{close} s"),
        None => format!("{spec} with its curves"),
    })?;
    // Sampling the animation into steps, the build and the upload.
    let build_ms = t1.elapsed().as_secs_f64() * 1e3;
    let (triangles, steps, bytes, depth) = walker.sizes();
    let cam = camera_for(&args.view, &scene)?;
    let b = walker.bounds();
    let view = View {
        shade: args.shade,
        ao_radius: shade::ao_radius_of((b.max - b.min).length().max(f32::MIN_POSITIVE)),
        light: shade::point_light(&cam),
        light_radius: 0.0,
    };
    let (w, h) = args.view.size;
    let rays = cam.rays(w, h);
    let samples = if shutter.is_some() {
        args.shutter.shutter_samples
    } else {
        1
    };
    let pb = crate::output::progress_bar(
        u64::from(samples),
        "{spinner} blurring over the shutter [{bar:40}] {pos}/{len} samples ({eta})",
    );
    let mut sum = vec![0u32; rays.len() * 3];
    let mut totals = Totals::default();
    for s in 0..samples {
        let times: Vec<f32> = (0..rays.len() as u32)
            .map(|p| ray_time(p, s, samples))
            .collect();
        let img = trace_sample(args, &view, &walker, (&rays, &times), s, &mut totals)?;
        for (a, v) in sum.iter_mut().zip(img) {
            *a += u32::from(v);
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let img = sum
        .iter()
        .map(|&a| ((a + samples / 2) / samples) as u8)
        .collect();
    write_png(png, w, h, img)?;
    let mrays = |n: u64, ms: f64| n as f64 / ms.max(1e-9) / 1e3;
    let what = match (shutter, &walker) {
        (Some((open, close)), _) => format!(
            "{triangles} triangles in {steps} time steps, {samples} samples over {open}..{close} s, {} bounds",
            bounds_name(bounds)
        ),
        (None, _) => match walker.curves() {
            Some(c) => format!(
                "{triangles} triangles and {} {} curve segments",
                c.len(),
                c.kind.name()
            ),
            None => format!("{triangles} triangles"),
        },
    };
    eprintln!(
        "wrote {} ({w}x{h}, {what} on {}): {} rays in {:.1} ms, {:.2} Mrays/s (primary {:.2})",
        args.output.display(),
        walker.name(),
        totals.rays + totals.secondary_rays,
        totals.trace_ms,
        mrays(totals.rays + totals.secondary_rays, totals.trace_ms),
        mrays(totals.rays, totals.primary_ms),
    );
    if let Some(j) = json_out {
        j.write(&json!({
            "scene": spec,
            "width": w, "height": h,
            "triangles": triangles,
            "shutter": shutter.map(|(open, close)| [open, close]),
            "curves": walker.curves().map(|c| json!({ "kind": c.kind.name(), "segments": c.len() })),
            "time_steps": steps,
            "levels": if args.shutter.instances { 2 } else { 1 },
            "time_bounds": bounds_name(bounds),
            "samples": samples,
            "depth": depth,
            "bvh_bytes": bytes,
            "load_ms": load_ms,
            "build_ms": build_ms,
            "rays": totals.rays,
            "hits": totals.hits,
            "t_sum": totals.t_sum,
            "primary_ms": totals.primary_ms,
            "primary_mrays_per_s": mrays(totals.rays, totals.primary_ms),
            "secondary_rays": totals.secondary_rays,
            "trace_ms": totals.trace_ms,
            "mrays_per_s": mrays(totals.rays + totals.secondary_rays, totals.trace_ms),
            "backend": walker.name(),
            "traversal": "full-stack",
            "shade": args.shade,
            "builder": args.scene.build.builder.name(),
            "camera": { "eye": cam.eye.to_array(), "target": cam.target.to_array(), "fov": cam.fov_y_deg },
        }))?;
    }
    Ok(())
}

fn bounds_name(b: TimeBounds) -> &'static str {
    match b {
        TimeBounds::Linear => "linear",
        TimeBounds::Merged => "merged",
    }
}

/// One sample of every pixel, at `times`: primary rays, the secondary rays the shading
/// asks for at the same times, the image. Adds what it traced to `totals`.
fn trace_sample(
    args: &RenderArgs,
    view: &View,
    walker: &Walker,
    (rays, times): (&[Ray], &[f32]),
    sample: u32,
    totals: &mut Totals,
) -> Result<Vec<u8>> {
    let t = Instant::now();
    let (hits, counters) = walker.closest(rays, times)?;
    let primary_ms = t.elapsed().as_secs_f64() * 1e3;
    // The shading asks for a hit's triangle by primitive; a blurred hit's triangle is
    // where it was at its ray's time (a curve's, in its tangent plane at the hit), so each
    // hit names its ray and `posed` holds them.
    let posed: Vec<Triangle> = (hits.iter().zip(rays).zip(times))
        .map(|((h, r), &time)| match h.is_hit() {
            true => walker.triangle_at(h, r, time),
            false => [Vec3::ZERO; 3],
        })
        .collect();
    let by_ray: Vec<Hit> = (hits.iter().enumerate())
        .map(|(i, h)| match h.is_hit() {
            true => Hit {
                prim: i as u32,
                ..*h
            },
            false => *h,
        })
        .collect();
    let triangle = |p: u32| posed[p as usize];
    let ao = args.ao_samples;
    let (sec_rays, owner) = shade::secondary_rays_from(
        args.shade,
        &triangle,
        rays,
        &by_ray,
        view.light,
        sample.saturating_mul(ao)..(sample + 1).saturating_mul(ao),
        view.ao_radius,
    );
    let t = Instant::now();
    let sec_times: Vec<f32> = owner.iter().map(|&o| times[o as usize]).collect();
    let secondary = walker.any(&sec_rays, &sec_times)?;
    let secondary_ms = t.elapsed().as_secs_f64() * 1e3;
    let hit = hits.iter().filter(|h| h.is_hit());
    totals.rays += rays.len() as u64;
    totals.hits += hit.clone().count() as u64;
    totals.t_sum += hit.map(|h| f64::from(h.t)).sum::<f64>();
    totals.primary_ms += primary_ms;
    totals.secondary_rays += sec_rays.len() as u64;
    totals.trace_ms += primary_ms + secondary_ms;
    let pixels = Pixels {
        size: args.view.size,
        rays,
        hits: &by_ray,
        counters: &counters,
        owner: &owner,
        secondary: &secondary,
        ao_samples: ao,
    };
    Ok(shade::compose_rgb(view, &pixels, &triangle))
}
