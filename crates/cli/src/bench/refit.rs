//! `bvhtrace bench-refit`: what moving things costs. A mesh whose every vertex moved is
//! refitted (its tree kept, its boxes recomputed) beside a full rebuild, with how much the
//! SAH cost and the rays' box tests grow; a top level of many instances is rebuilt after
//! every instance moved, beside building both levels anew.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace_core::instance::REFIT_REBUILD_ADVISED;
use bvhtrace_core::{
    BuildOptions, FlatBvh, Instance, InstancedBvh, Ray, TraceOptions, Triangle, trace_rays,
};
use glam::{Affine3A, Quat, Vec3};
use serde_json::json;

use super::{median, scene_specs};
use crate::embree::{self, Dump};
use crate::output::JsonOut;

/// `bvhtrace bench-refit`.
#[derive(clap::Args)]
pub struct BenchRefitArgs {
    /// The mesh to deform (all of a scene's triangles, flattened; default: igea from the
    /// shared scenes folder).
    pub scene: Option<String>,
    /// The many-instance scene whose top level is rebuilt (default: a 100x100 grid of
    /// the same mesh when it comes from the shared folder, `builtin:grid:icosphere:100x100`
    /// otherwise).
    #[arg(long)]
    pub instances: Option<String>,
    /// Timed repetitions (the median is printed).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Write the figures as JSON to this file (`-` for stdout).
    #[arg(long)]
    pub json: Option<String>,
    /// An `embree_trace` binary (`crates/cli/embree/embree_trace.c`): Embree 3's medium
    /// build and its refit (`RTC_BUILD_QUALITY_REFIT`) of the same deformation are timed
    /// in the same run, 2 threads.
    #[arg(long)]
    pub embree: Option<std::path::PathBuf>,
    /// Also refit on the GPU (`GpuRefit`, the BVH in buffers) after the same deformation,
    /// from the moved vertices uploaded there: the refit alone and with the upload; and
    /// rebuild the many instances' top level on the GPU (PLOC) beside the CPU's.
    #[arg(long)]
    pub gpu: bool,
    /// Vulkan adapter for `--gpu` (a substring of its name, e.g. `llvmpipe` or `NVIDIA`).
    #[arg(long)]
    pub adapter: Option<String>,
}

/// Embree's build and refit of `tris` deformed by amplitude `a` (median of `runs`), through
/// `exe`: `(build_ms, refit_ms)`.
fn embree_refit(
    exe: &std::path::Path,
    tris: &[Triangle],
    a: f32,
    runs: usize,
) -> Result<(f64, f64)> {
    // One dummy ray: the program times the build and the refit.
    let ray = Ray::with_interval(Vec3::ZERO, Vec3::Z, 0.0, f32::INFINITY);
    let dump = Dump::write("refit", tris, &[ray])?;
    let v = dump.run(exe, 2, runs, &[("BVHTRACE_REFIT", a.to_string())])?;
    let field = |k: &str| embree::field(&v, k, exe);
    Ok((field("build_ms")?, field("refit_ms")?))
}

/// A GPU refit's figures (medians).
struct GpuRefitFigures {
    adapter: String,
    refit_ms: f64,
    gpu_ms: Option<f64>,
    with_upload_ms: f64,
    host_copy_ms: f64,
    dispatches: usize,
}

/// The SAH tree of `tris` uploaded in buffers, and refitted on the device after every
/// vertex moved by amplitude `a` (the vertices uploaded once, unindexed), `runs` times;
/// then the upload and the refit together, alternating with the undeformed vertices.
fn gpu_refit(
    tris: &[Triangle],
    a: f32,
    runs: usize,
    adapter: Option<&str>,
) -> Result<GpuRefitFigures> {
    use bvhtrace_gpu::wgpu::{self, util::DeviceExt};
    use bvhtrace_gpu::{BvhStorage, GpuBvh, GpuContext, GpuRefit, RefitVertices, UploadOptions};
    let ctx = GpuContext::new(crate::backend::adapter_choice(adapter))
        .context("--gpu refits on a GPU")?;
    let tree = FlatBvh::build(tris, &BuildOptions::default())?;
    let opts = UploadOptions::all().with_storage(BvhStorage::Buffers);
    let mut bvh = GpuBvh::upload(&ctx, &tree, &opts)?;
    let soup =
        |t: &[Triangle]| -> Vec<f32> { t.iter().flatten().flat_map(|p| p.to_array()).collect() };
    let (still, moved) = (soup(tris), soup(&deform(tris, a)));
    let positions = ctx
        .device()
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("bench-refit positions"),
            contents: bytemuck::cast_slice(&moved),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        });
    let v = RefitVertices {
        positions: &positions,
        stride: 3,
        vertices: (moved.len() / 3) as u32,
        indices: None,
    };
    let refit = GpuRefit::new(&bvh, &tree, v)?;
    refit.refit(&mut bvh)?; // compiles nothing more, but warms the first submission
    let (mut walls, mut gpus, mut uploads, mut host_copies) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for _ in 0..runs {
        let t = refit.refit(&mut bvh)?;
        walls.push(t.wall_ms);
        gpus.extend(t.gpu_ms);
    }
    for run in 0..runs {
        let verts = if run % 2 == 0 { &still } else { &moved };
        let t = Instant::now();
        ctx.queue()
            .write_buffer(&positions, 0, bytemuck::cast_slice(verts));
        let r = refit.refit(&mut bvh)?;
        // The host copy's read back is a CPU driver's cost, reported apart.
        uploads.push(t.elapsed().as_secs_f64() * 1e3 - r.host_copy_ms);
        host_copies.push(r.host_copy_ms);
    }
    Ok(GpuRefitFigures {
        adapter: ctx.adapter_info().name.clone(),
        refit_ms: median(walls),
        gpu_ms: (!gpus.is_empty()).then(|| median(gpus)),
        with_upload_ms: median(uploads),
        host_copy_ms: median(host_copies),
        dispatches: refit.dispatches(),
    })
}

/// The median wall time, milliseconds, of moving `two`'s instances with the top level
/// rebuilt on the device (PLOC), alternating between `moves`, `runs` times after a first
/// run that compiles the pipelines.
fn gpu_top_level(
    two: &bvhtrace_core::InstancedBvh,
    moves: &[&Vec<Affine3A>; 2],
    runs: usize,
    adapter: Option<&str>,
) -> Result<f64> {
    use bvhtrace_gpu::{GpuBuildOptions, GpuContext};
    let ctx = GpuContext::new(crate::backend::adapter_choice(adapter))
        .context("--gpu builds the top level on a GPU")?;
    let (mut two, opts) = (two.clone(), GpuBuildOptions::default());
    ctx.set_transforms_on_device(&mut two, moves[1], &opts)?;
    let mut walls = Vec::new();
    for run in 0..runs {
        let (r, ms) = time(|| ctx.set_transforms_on_device(&mut two, moves[run % 2], &opts));
        r?;
        walls.push(ms);
    }
    Ok(median(walls))
}

/// Every vertex moved by a smooth field of amplitude `a` (a fraction of the extent): the
/// same function `crates/cli/embree/embree_trace.c` applies for Embree's refit.
pub fn deform(tris: &[Triangle], a: f32) -> Vec<Triangle> {
    let (lo, hi) = tris.iter().flatten().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(l, h), p| (l.min(*p), h.max(*p)),
    );
    let e = (hi - lo).max_element().max(f32::MIN_POSITIVE);
    let k = 6.0 / e;
    tris.iter()
        .map(|t| {
            t.map(|p| p + Vec3::new((k * p.y).sin(), (k * p.z).sin(), (k * p.x).sin()) * (a * e))
        })
        .collect()
}

fn time<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let out = f();
    (out, t.elapsed().as_secs_f64() * 1e3)
}

/// Mean box tests per ray of `rays` through `bvh`.
fn boxes_per_ray(bvh: &FlatBvh, rays: &[Ray]) -> f64 {
    let out = trace_rays(bvh, rays, &TraceOptions::default().with_counters(true));
    let c = out.counters.unwrap_or_default();
    c.iter().map(|c| f64::from(c.nodes)).sum::<f64>() / c.len().max(1) as f64
}

/// Where the tables go: standard error when the JSON takes standard output.
struct Out {
    to_stderr: bool,
}

impl Out {
    fn line(&self, line: std::fmt::Arguments) {
        if self.to_stderr {
            eprintln!("{line}")
        } else {
            println!("{line}")
        }
    }
}

/// Prints a line of the tables to `$out` ([`Out`]), formatted as `println!` formats.
macro_rules! say {
    ($out:expr, $($t:tt)*) => {
        $out.line(format_args!($($t)*))
    };
}

/// `bvhtrace bench-refit`.
pub fn run(args: BenchRefitArgs) -> Result<()> {
    let out = Out {
        to_stderr: args.json.as_deref() == Some("-"),
    };
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let spec = match &args.scene {
        Some(s) => s.clone(),
        None => scene_specs(&[])?
            .into_iter()
            .find(|s| s.contains("igea"))
            .context("igea.glb is not in the shared scenes folder: name a scene")?,
    };
    let scene = crate::geometry::load_triangle_scene(&spec)?;
    let tris = scene.flattened_triangles()?;
    let (lo, hi) = scene.bounds();
    let rays = bvhtrace_scene::Camera::frame(lo, hi, 4.0 / 3.0).rays(256, 192);
    let one = vec![Instance::new(0, Affine3A::IDENTITY)];
    let built = InstancedBvh::build(std::slice::from_ref(&tris), one, &BuildOptions::default())?;
    let rows = refit_against_rebuild(&out, &spec, &tris, &built, &rays, args.runs)?;
    let embree = match &args.embree {
        Some(exe) => {
            let (b, r) = embree_refit(exe, &tris, 0.1, args.runs)?;
            say!(
                out,
                "Embree 3 (2 threads), amplitude 0.1: medium build {b:.2} ms, refit {r:.2} ms"
            );
            Some(json!({ "amplitude": 0.1, "build_ms": b, "refit_ms": r }))
        }
        None => None,
    };
    let gpu = match args.gpu {
        true => Some(say_gpu_refit(&out, &tris, &args)?),
        false => None,
    };
    let top = top_level(&out, &spec, &args)?;
    if let Some(j) = json_out {
        j.write(&json!({
            "scene": spec, "triangles": tris.len(), "runs": args.runs,
            "refit": rows, "rebuild_advised_sah_ratio": REFIT_REBUILD_ADVISED, "embree": embree,
            "gpu_refit": gpu,
            "instances_scene": top.spec, "instances": top.instances,
            "meshes": top.meshes, "top_rebuild_ms": top.top_ms, "two_level_build_ms": top.full_ms,
            "top_level_bytes": top.top_bytes, "mesh_bytes": top.mesh_bytes,
            "gpu_top_rebuild_ms": top.gpu_top_ms,
        }))?;
    }
    Ok(())
}

/// Refit against rebuild, amplitude by amplitude (each refit starts from `built`, the
/// build of the undeformed mesh `tris`, as an animation's frames refit one tree): the table, and
/// its rows as JSON.
fn refit_against_rebuild(
    out: &Out,
    spec: &str,
    tris: &[Triangle],
    built: &InstancedBvh,
    rays: &[Ray],
    runs: usize,
) -> Result<Vec<serde_json::Value>> {
    let opts = BuildOptions::default();
    say!(
        out,
        "{spec}: {} triangles; refit after every vertex moved, against a full rebuild (median of {})",
        tris.len(),
        runs
    );
    say!(
        out,
        "{:>9} {:>10} {:>11} {:>9} {:>12} {:>12}",
        "amplitude",
        "refit ms",
        "rebuild ms",
        "SAH x",
        "boxes/ray",
        "rebuilt"
    );
    let mut rows = Vec::new();
    for a in [0.001f32, 0.01, 0.03, 0.1, 0.3] {
        let moved = deform(tris, a);
        let mut refits = Vec::new();
        let mut refitted = built.clone();
        for _ in 0..runs {
            refitted = built.clone();
            let (r, ms) = time(|| refitted.refit_mesh(0, &moved));
            r?;
            refits.push(ms);
        }
        let mut rebuilds = Vec::new();
        let mut rebuilt = None;
        for _ in 0..runs {
            let (b, ms) = time(|| FlatBvh::build(&moved, &opts));
            rebuilt = Some(b?);
            rebuilds.push(ms);
        }
        let rebuilt = rebuilt.context("no rebuild ran")?;
        let (q, br, bb) = (
            refitted.refit_quality(0),
            boxes_per_ray(refitted.bvh(), rays),
            boxes_per_ray(&rebuilt, rays),
        );
        let (rm, bm) = (median(refits), median(rebuilds));
        say!(
            out,
            "{a:>9} {rm:>10.2} {bm:>11.2} {q:>9.3} {br:>12.1} {bb:>12.1}"
        );
        rows.push(json!({
            "amplitude": a, "refit_ms": rm, "rebuild_ms": bm, "sah_ratio": q,
            "boxes_per_ray_refitted": br, "boxes_per_ray_rebuilt": bb,
        }));
    }
    say!(
        out,
        "a rebuild is advised past an SAH ratio of {REFIT_REBUILD_ADVISED}"
    );
    Ok(rows)
}

/// `--gpu`: the refit on the device after the deformation of amplitude 0.1, said and as
/// JSON.
fn say_gpu_refit(out: &Out, tris: &[Triangle], args: &BenchRefitArgs) -> Result<serde_json::Value> {
    let g = gpu_refit(tris, 0.1, args.runs, args.adapter.as_deref())?;
    say!(
        out,
        "GPU refit ({}), amplitude 0.1: {:.2} ms ({} of dispatches, {} dispatches), {:.2} ms \
         with the vertices' upload; the host copy read back {:.2} ms (CPU drivers only)",
        g.adapter,
        g.refit_ms,
        g.gpu_ms
            .map_or("no timestamps".into(), |ms| format!("{ms:.2} ms")),
        g.dispatches,
        g.with_upload_ms,
        g.host_copy_ms
    );
    Ok(json!({
        "amplitude": 0.1, "adapter": g.adapter, "refit_ms": g.refit_ms, "gpu_ms": g.gpu_ms,
        "with_upload_ms": g.with_upload_ms, "host_copy_ms": g.host_copy_ms,
        "dispatches": g.dispatches,
    }))
}

/// The figures of the many-instance scene's top level.
struct TopLevel {
    /// The scene, as given or chosen.
    spec: String,
    instances: usize,
    meshes: usize,
    /// Both levels built, milliseconds.
    full_ms: f64,
    /// The top level rebuilt after every instance moved (median), milliseconds.
    top_ms: f64,
    /// With `--gpu`: the same on the device, milliseconds.
    gpu_top_ms: Option<f64>,
    top_bytes: usize,
    mesh_bytes: usize,
}

/// The top level of many instances, rebuilt after every instance moved, beside building
/// both levels (and on the device with `--gpu`); the line said, and the figures.
fn top_level(out: &Out, spec: &str, args: &BenchRefitArgs) -> Result<TopLevel> {
    let inst_spec = match &args.instances {
        Some(s) => s.clone(),
        None => match std::path::Path::new(spec).file_stem() {
            Some(stem)
                if crate::geometry::shared_scenes_dir().is_some() && spec.ends_with(".glb") =>
            {
                format!("builtin:grid:{}:100x100", stem.to_string_lossy())
            }
            _ => "builtin:grid:icosphere:100x100".into(),
        },
    };
    let many = crate::geometry::load_triangle_scene(&inst_spec)?;
    let (two, full_ms) = time(|| many.instanced_bvh(&BuildOptions::default()));
    let mut two = two?;
    let moved: Vec<Affine3A> = two
        .instances()
        .iter()
        .enumerate()
        .map(|(k, i)| {
            Affine3A::from_rotation_translation(
                Quat::from_rotation_z(0.01 * (k % 7) as f32),
                Vec3::new(0.0, 0.0, 0.05 * (k % 3) as f32),
            ) * i.transform
        })
        .collect();
    let original: Vec<Affine3A> = two.instances().iter().map(|i| i.transform).collect();
    let mut tops = Vec::new();
    for run in 0..args.runs {
        let t = if run % 2 == 0 { &moved } else { &original };
        let (r, ms) = time(|| two.set_transforms(t));
        r?;
        tops.push(ms);
    }
    let top_ms = median(tops);
    let gpu_top_ms = match args.gpu {
        true => {
            let moves = [&moved, &original];
            Some(gpu_top_level(
                &two,
                &moves,
                args.runs,
                args.adapter.as_deref(),
            )?)
        }
        false => None,
    };
    let (top_bytes, mesh_bytes) = two.level_bytes();
    say!(
        out,
        "{inst_spec}: {} instances of {} meshes ({} triangles instanced): top-level rebuild \
         {top_ms:.2} ms, both levels built {full_ms:.1} ms; top level {top_bytes} bytes, meshes \
         {mesh_bytes} bytes",
        two.instances().len(),
        two.meshes().len(),
        two.instanced_primitives()
    );
    if let Some(ms) = gpu_top_ms {
        say!(
            out,
            "  the top level rebuilt on the device (PLOC, with upload and read back): {ms:.2} ms"
        );
    }
    Ok(TopLevel {
        spec: inst_spec,
        instances: two.instances().len(),
        meshes: two.meshes().len(),
        full_ms,
        top_ms,
        gpu_top_ms,
        top_bytes,
        mesh_bytes,
    })
}
