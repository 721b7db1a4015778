//! `bvhtrace render` and `bvhtrace info`.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace_core::palette;
use bvhtrace_core::{
    BuildOptions, BuilderKind, BvhStats, FlatBvh, Hit, Query, Ray, Traversal, Triangle,
};
use bvhtrace_gpu::{BvhStorage, PipelineFeatures, UploadStats, VertexAttributes};
use bvhtrace_scene::{Attributes, Camera, DEFAULT_SCENE, Scene, camera};
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::{Value, json};

use crate::output::{AtomicFile, JsonOut, write_png};
use crate::shade::{self, BACKGROUND, Shade};
use crate::tracer::{GpuSetup, Tracer};

/// Which backend traces.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Backend {
    /// WGSL kernels through wgpu (falls back to the CPU when there is no adapter).
    Gpu,
    /// The CPU reference traversal.
    Cpu,
    /// The same kernels on raw Vulkan through ash (`bvhtrace-vk`, BVH in storage
    /// buffers); an error when there is no Vulkan device.
    Vulkan,
}

/// An image size flag (`--size WxH`): [`camera::parse_size`], at most 16384 a side.
pub(crate) fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = camera::parse_size(s)?;
    if w > 16384 || h > 16384 {
        return Err(format!("size must be between 1x1 and 16384x16384, got {s}"));
    }
    Ok((w, h))
}

/// Scene and BVH choices shared by the commands.
#[derive(clap::Args, Clone)]
pub struct SceneArgs {
    /// A .gltf/.glb file or a `builtin:` name (see `bvhtrace info --list`); default: the
    /// Cornell box.
    pub scene: Option<String>,
    /// BVH builder.
    #[arg(long, default_value = "sah")]
    pub builder: BuilderKind,
    /// Bins per axis for the `sah` builder.
    #[arg(long, default_value_t = 32)]
    pub bins: usize,
    /// SAH traversal cost (intersection cost is 1); PBRT's 1/8 by default.
    #[arg(long, default_value_t = 0.125)]
    pub cost_traversal: f32,
}

impl SceneArgs {
    fn spec(&self) -> &str {
        self.scene.as_deref().unwrap_or(DEFAULT_SCENE)
    }
    fn build_options(&self) -> BuildOptions {
        BuildOptions {
            builder: self.builder,
            bins: self.bins,
            cost_traversal: self.cost_traversal,
            ..Default::default()
        }
    }
}

/// Loads, flattens and builds; prints scene warnings. Returns timings in ms.
pub fn load_and_build(args: &SceneArgs) -> Result<(Scene, Vec<Triangle>, FlatBvh, f64, f64)> {
    let t0 = Instant::now();
    let scene = bvhtrace_scene::load(args.spec())?;
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    let tris = scene
        .flatten()
        .triangles()
        .with_context(|| format!("{}: bad geometry", args.spec()))?;
    let load_ms = t0.elapsed().as_secs_f64() * 1e3;
    let t1 = Instant::now();
    let bvh = FlatBvh::build(&tris, &args.build_options())
        .with_context(|| format!("{}: BVH build failed", args.spec()))?;
    let build_ms = t1.elapsed().as_secs_f64() * 1e3;
    Ok((scene, tris, bvh, load_ms, build_ms))
}

/// Image size and camera.
#[derive(clap::Args, Clone)]
pub struct CameraArgs {
    /// Image size.
    #[arg(long, default_value = "1024x768", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Camera position X,Y,Z (with --target; default: the scene's camera or a framing one).
    #[arg(long, value_parser = camera::parse_vec3, requires = "target", allow_hyphen_values = true)]
    pub eye: Option<Vec3>,
    /// Point the camera looks at.
    #[arg(long, value_parser = camera::parse_vec3, requires = "eye", allow_hyphen_values = true)]
    pub target: Option<Vec3>,
    /// Vertical field of view in degrees.
    #[arg(long)]
    pub fov: Option<f32>,
}

/// `bvhtrace render`.
#[derive(clap::Args)]
pub struct RenderArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Output PNG.
    #[arg(short, long, default_value = "out.png")]
    pub output: PathBuf,
    #[command(flatten)]
    pub view: CameraArgs,
    /// gpu or cpu.
    #[arg(long, value_enum, default_value_t = Backend::Gpu)]
    pub backend: Backend,
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// stackless, short-stack, short-stack:K or full-stack.
    #[arg(long, default_value = "stackless")]
    pub traversal: Traversal,
    /// What to show.
    #[arg(long, value_enum, default_value_t = Shade::Normal)]
    pub shade: Shade,
    /// Ambient-occlusion rays per pixel.
    #[arg(long, default_value_t = 16)]
    pub ao_samples: u32,
    /// Write run statistics as JSON to this file (`-` for stdout).
    #[arg(long)]
    pub json: Option<String>,
    /// Rows per tile: each tile is one batch (keeps dispatches short).
    #[arg(long, default_value_t = 64)]
    pub tile_rows: u32,
}

/// The camera: explicit flags, else the scene's, else framing the bounds. Rays follow the
/// convention documented in `bvhtrace_scene::camera`.
pub fn camera_for(view: &CameraArgs, scene: &Scene) -> Result<Camera> {
    let (w, h) = view.size;
    let mut cam = match (view.eye, view.target) {
        (Some(eye), Some(target)) => Camera {
            eye,
            target,
            fov_y_deg: 45.0,
        },
        _ => scene.camera_or_frame(w as f32 / h as f32),
    };
    if let Some(f) = view.fov {
        if !(f > 0.0 && f < 180.0) {
            bail!("--fov must be between 0 and 180 degrees, got {f}");
        }
        cam.fov_y_deg = f;
    }
    if cam.eye == cam.target {
        bail!("--eye and --target are the same point");
    }
    Ok(cam)
}

struct Pass {
    rays: u64,
    wall_ms: f64,
    gpu_ms: Option<f64>,
}

impl Pass {
    fn add(&mut self, n: usize, t: &crate::tracer::Traced) {
        self.rays += n as u64;
        self.wall_ms += t.wall_ms;
        self.gpu_ms = match (self.gpu_ms, t.gpu_ms) {
            (Some(a), Some(b)) => Some(a + b),
            (None, Some(b)) if self.rays == n as u64 => Some(b),
            _ => None,
        };
    }
}

/// Traces rays in chunks with a progress bar.
#[allow(clippy::too_many_arguments)]
fn trace_chunked(
    tracer: &Tracer,
    rays: &[Ray],
    chunk: usize,
    traversal: Traversal,
    query: Query,
    counters: bool,
    pb: &ProgressBar,
    pass: &mut Pass,
) -> Result<(Vec<Hit>, Vec<bvhtrace_core::Counters>)> {
    let mut hits = Vec::with_capacity(rays.len());
    let mut cnt = Vec::new();
    for c in rays.chunks(chunk.max(1)) {
        let t = tracer.trace(c, traversal, query, counters)?;
        pass.add(c.len(), &t);
        hits.extend(t.hits);
        if let Some(k) = t.counters {
            cnt.extend(k);
        }
        pb.inc(c.len() as u64);
    }
    Ok((hits, cnt))
}

/// `bvhtrace render`.
pub fn render(args: RenderArgs) -> Result<()> {
    // Fail on bad output paths before any work.
    let png = AtomicFile::create(&args.output)?;
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let (w, h) = args.view.size;
    if args.shade == Shade::Ao && args.ao_samples == 0 {
        bail!("--ao-samples must be at least 1");
    }

    let (scene, tris, bvh, load_ms, build_ms) = load_and_build(&args.scene)?;
    let stats = BvhStats::of(&bvh);
    let cam = camera_for(&args.view, &scene)?;

    let (tracer, upload_ms) = match args.backend {
        Backend::Cpu => (Tracer::Cpu(&bvh), 0.0),
        Backend::Vulkan => Tracer::vulkan(&bvh, args.adapter.as_deref())?,
        Backend::Gpu => match Tracer::gpu(
            &bvh,
            &GpuSetup {
                adapter: args.adapter.as_deref(),
                traversal: args.traversal,
            },
        ) {
            Ok(t) => t,
            Err(e) => {
                eprintln!("note: no usable GPU ({e:#}); tracing on the CPU instead");
                (Tracer::Cpu(&bvh), 0.0)
            }
        },
    };

    let rays = cam.rays(w, h);
    let need_counters = args.shade == Shade::Heatmap || json_out.is_some();
    let secondary_per_px = match args.shade {
        Shade::Diffuse => 1,
        Shade::Ao => args.ao_samples as u64,
        _ => 0,
    };
    let pb = ProgressBar::new(rays.len() as u64 * (1 + secondary_per_px));
    pb.set_style(
        ProgressStyle::with_template("{spinner} {msg} [{bar:40}] {percent}% ({eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(format!(
        "tracing {} on {}",
        args.shade_name(),
        tracer.backend()
    ));
    let chunk = (w * args.tile_rows) as usize;
    let mut pass = Pass {
        rays: 0,
        wall_ms: 0.0,
        gpu_ms: None,
    };
    let (hits, counters) = trace_chunked(
        &tracer,
        &rays,
        chunk,
        args.traversal,
        Query::Closest,
        need_counters,
        &pb,
        &mut pass,
    )?;

    let (lo, hi) = (stats_bounds(&bvh).0, stats_bounds(&bvh).1);
    let diag = (hi - lo).length().max(f32::MIN_POSITIVE);
    // A point light up and to the right of the camera: it sees what the camera sees, so it
    // works for closed rooms as well as open scenes, and casts visible shadows.
    let (_, right, up) = cam.basis();
    let light = cam.eye + (right * 0.25 + up * 0.2) * (cam.target - cam.eye).length();
    let (sec_rays, owner) = shade::secondary_rays(
        args.shade,
        &tris,
        &rays,
        &hits,
        light,
        args.ao_samples,
        0.15 * diag,
    );
    let sec_hits = if sec_rays.is_empty() {
        Vec::new()
    } else {
        pb.set_length(rays.len() as u64 + sec_rays.len() as u64);
        trace_chunked(
            &tracer,
            &sec_rays,
            chunk * 4,
            args.traversal,
            Query::Any,
            false,
            &pb,
            &mut pass,
        )?
        .0
    };
    pb.finish_and_clear();

    let img = compose(
        &args, &tris, &rays, &hits, &counters, &sec_hits, &owner, light,
    );
    write_png(png, w, h, img)?;

    let n_hits = hits.iter().filter(|h| h.is_hit()).count();
    let t_sum: f64 = hits.iter().filter(|h| h.is_hit()).map(|h| h.t as f64).sum();
    let per_ray = |f: fn(&bvhtrace_core::Counters) -> u32| {
        if counters.is_empty() {
            serde_json::Value::Null
        } else {
            json!(counters.iter().map(|c| f(c) as f64).sum::<f64>() / counters.len() as f64)
        }
    };
    let mut features = vec!["closest-hit"];
    if !sec_rays.is_empty() {
        features.push("any-hit");
    }
    if need_counters {
        features.push("counters");
    }
    if args.traversal.needs_escapes() {
        features.push("escape-links");
    }
    // The GPU pipelines this job ran, each composed of only what it needs.
    let pipelines = match tracer.upload() {
        Some((_, storage)) => render_pipelines(
            storage,
            args.traversal,
            !sec_rays.is_empty(),
            need_counters,
            &scene.attributes,
        ),
        None => Vec::new(),
    };
    eprintln!(
        "wrote {} ({}x{}, {} triangles, {} on {}): {} rays in {:.1} ms, {:.2} Mrays/s",
        args.output.display(),
        w,
        h,
        tris.len(),
        args.traversal,
        tracer.adapter(),
        pass.rays,
        pass.wall_ms,
        pass.rays as f64 / pass.wall_ms.max(1e-9) / 1e3
    );
    if let Some(j) = json_out {
        j.write(&json!({
            "scene": args.scene.spec(),
            "width": w, "height": h,
            "triangles": tris.len(),
            "nodes": stats.nodes,
            "depth": stats.depth,
            "sah_cost": stats.sah_cost,
            "sah_cost_pbrt": stats.sah_cost_pbrt,
            "load_ms": load_ms,
            "build_ms": build_ms,
            "upload_ms": upload_ms,
            "trace_ms": pass.wall_ms,
            "gpu_ms": pass.gpu_ms,
            "rays": pass.rays,
            "mrays_per_s": pass.rays as f64 / pass.wall_ms.max(1e-9) / 1e3,
            "hits": n_hits,
            "t_sum": t_sum,
            "nodes_per_ray": per_ray(|c| c.nodes),
            "tris_per_ray": per_ray(|c| c.tris),
            "backend": tracer.backend(),
            "adapter": tracer.adapter(),
            "traversal": args.traversal.to_string(),
            "builder": args.scene.builder.name(),
            "shade": args.shade,
            "uploaded_bytes": tracer.uploaded_bytes(),
            "features": features,
            "pipelines": pipelines.iter().map(pipeline_json).collect::<Vec<_>>(),
            "upload": tracer.upload().map(|(s, storage)| upload_json(&s, storage, tris.len())),
            "left_out": left_out(&pipelines, &scene, args.traversal),
            "camera": { "eye": cam.eye.to_array(), "target": cam.target.to_array(), "fov": cam.fov_y_deg },
        }))?;
    }
    Ok(())
}

fn stats_bounds(bvh: &FlatBvh) -> (Vec3, Vec3) {
    let b = bvh.bounds();
    (b.min, b.max)
}

impl RenderArgs {
    fn shade_name(&self) -> &'static str {
        match self.shade {
            Shade::Normal => "normals",
            Shade::Depth => "depth",
            Shade::Diffuse => "diffuse",
            Shade::Ao => "ambient occlusion",
            Shade::Heatmap => "heatmap",
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn compose(
    args: &RenderArgs,
    tris: &[Triangle],
    rays: &[Ray],
    hits: &[Hit],
    counters: &[bvhtrace_core::Counters],
    sec_hits: &[Hit],
    owner: &[u32],
    light: Vec3,
) -> Vec<u8> {
    let (w, h) = args.view.size;
    let mut img = vec![0u8; (w * h * 3) as usize];
    let px = |img: &mut Vec<u8>, i: usize, c: [u8; 3]| img[i * 3..i * 3 + 3].copy_from_slice(&c);
    // Per-pixel secondary results: occluded counts.
    let mut occluded = vec![0u32; rays.len()];
    for (o, sh) in owner.iter().zip(sec_hits) {
        if sh.is_hit() {
            occluded[*o as usize] += 1;
        }
    }
    let range = palette::depth_range(hits);
    let max_nodes = {
        let mut v: Vec<u32> = counters.iter().map(|c| c.nodes).collect();
        v.sort_unstable();
        v.get(v.len().saturating_sub(1))
            .copied()
            .unwrap_or(1)
            .max(1)
    };
    for (i, (r, hit)) in rays.iter().zip(hits).enumerate() {
        if args.shade == Shade::Heatmap {
            let n = counters.get(i).map_or(0, |c| c.nodes);
            px(&mut img, i, palette::heat_ramp(n as f32 / max_nodes as f32));
            continue;
        }
        if !hit.is_hit() {
            px(&mut img, i, BACKGROUND);
            continue;
        }
        let tri = &tris[hit.prim as usize];
        let d = Vec3::from(r.dir);
        let n = shade::facing_normal(tri, d);
        let c = match args.shade {
            Shade::Normal => palette::normal_colour(n),
            Shade::Depth => palette::depth_grey(hit.t, range),
            Shade::Diffuse => {
                let p = shade::hit_point(tri, hit);
                let l = (light - p).normalize_or_zero();
                let lit = if occluded[i] == 0 {
                    n.dot(l).max(0.0)
                } else {
                    0.0
                };
                palette::diffuse_colour(lit)
            }
            Shade::Ao => palette::ao_grey(1.0 - occluded[i] as f32 / args.ao_samples as f32),
            Shade::Heatmap => unreachable!(),
        };
        px(&mut img, i, c);
    }
    if args.shade == Shade::Heatmap {
        shade::draw_legend(&mut img, w, h, max_nodes);
    }
    img
}

/// Per-vertex data the shading modes read on the GPU: none (shading runs on the host, from
/// the geometric normal), so a scene's normals, texture coordinates and colours are never
/// uploaded.
const JOB_ATTRIBUTES: VertexAttributes = VertexAttributes::NONE;

/// The GPU pipelines a render job runs: closest hit for the primary rays (with counters
/// when asked for), and any hit for the shadow or AO rays when there are any.
fn render_pipelines(
    storage: BvhStorage,
    traversal: Traversal,
    secondary: bool,
    counters: bool,
    scene_has: &Attributes,
) -> Vec<PipelineFeatures> {
    let has = VertexAttributes {
        normals: scene_has.normals,
    };
    let job = |query, counters| {
        PipelineFeatures::for_job(storage, traversal, query, counters, has, JOB_ATTRIBUTES)
    };
    let mut v = vec![job(Query::Closest, counters)];
    if secondary {
        v.push(job(Query::Any, false));
    }
    v
}

/// One pipeline as JSON: entry point, what it includes, its WGSL files and bindings.
fn pipeline_json(f: &PipelineFeatures) -> Value {
    json!({
        "entry_point": f.variant.entry_point(),
        "features": f.names(),
        "wgsl_files": f.module_set().files().iter().map(|(n, _)| *n).collect::<Vec<_>>(),
        "bindings": f.bindings().iter().map(|b| json!({
            "group": b.group,
            "binding": b.binding,
            "name": b.name,
            "bytes_per_element": b.element_bytes,
            "per": format!("{:?}", b.per).to_lowercase(),
        })).collect::<Vec<_>>(),
    })
}

/// Bytes uploaded, per buffer, in all and per triangle.
fn upload_json(s: &UploadStats, storage: BvhStorage, triangles: usize) -> Value {
    json!({
        "storage": format!("{storage:?}").to_lowercase(),
        "nodes": s.nodes_bytes,
        "triangles": s.triangles_bytes,
        "escapes": s.escapes_bytes,
        "total": s.total_bytes(),
        "bytes_per_triangle": s.total_bytes() as f64 / triangles.max(1) as f64,
    })
}

/// What the pipelines leave out, and why.
fn left_out(pipelines: &[PipelineFeatures], scene: &Scene, traversal: Traversal) -> Vec<String> {
    let mut v = Vec::new();
    if pipelines.is_empty() {
        return vec!["everything: traced on the CPU, nothing uploaded".into()];
    }
    if !pipelines.iter().any(|p| p.module_set().escapes) {
        v.push(format!(
            "escape links (the {traversal} walk does not read them)"
        ));
    }
    if !pipelines.iter().any(|p| p.variant.counters) {
        v.push("counters (asked for only by --shade heatmap or --json)".into());
    }
    if !pipelines.iter().any(|p| p.module_set().short_stack) {
        v.push("the stackless/short-stack walk".into());
    }
    if !pipelines.iter().any(|p| p.module_set().full_stack) {
        v.push("the full-stack walk".into());
    }
    let a = &scene.attributes;
    for (has, what) in [
        (a.normals, "vertex normals"),
        (a.texcoords, "texture coordinates"),
        (a.colors, "vertex colours"),
        (a.materials, "materials"),
    ] {
        v.push(if has {
            format!("{what} (the scene has them; no GPU job reads them)")
        } else {
            format!("{what} (the scene has none)")
        });
    }
    if scene.instance_count() > scene.meshes.len() {
        v.push(format!(
            "instances ({} placements, flattened to world-space triangles on the host)",
            scene.instance_count()
        ));
    }
    v
}

fn parse_storage(s: &str) -> Result<BvhStorage, String> {
    match s {
        "buffers" => Ok(BvhStorage::Buffers),
        "textures" => Ok(BvhStorage::Textures),
        _ => Err(format!("expected buffers or textures, got '{s}'")),
    }
}

/// `bvhtrace info`.
#[derive(clap::Args)]
pub struct InfoArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// The traversal of the job whose GPU pipeline and upload are listed.
    #[arg(long, default_value = "stackless")]
    pub traversal: Traversal,
    /// The shading mode of that job (diffuse and ao add an any-hit pipeline, heatmap
    /// counters).
    #[arg(long, value_enum, default_value_t = Shade::Normal)]
    pub shade: Shade,
    /// BVH storage of that upload: buffers (the exact flat layout) or textures (what CPU
    /// adapters such as lavapipe get).
    #[arg(long, default_value = "buffers", value_parser = parse_storage)]
    pub storage: BvhStorage,
    /// List the built-in scenes and exit.
    #[arg(long)]
    pub list: bool,
    /// Print as JSON.
    #[arg(long)]
    pub json: bool,
}

/// `bvhtrace info`.
pub fn info(args: InfoArgs) -> Result<()> {
    if args.list {
        for (name, what) in bvhtrace_scene::builtin_names() {
            println!("{name:28} {what}");
        }
        return Ok(());
    }
    let (scene, tris, bvh, load_ms, build_ms) = load_and_build(&args.scene)?;
    let s = BvhStats::of(&bvh);
    let (lo, hi) = scene.bounds();
    let a = &scene.attributes;
    let (nb, eb, tb) = bvh.byte_sizes();
    let pipelines = render_pipelines(
        args.storage,
        args.traversal,
        matches!(args.shade, Shade::Diffuse | Shade::Ao),
        args.shade == Shade::Heatmap,
        &scene.attributes,
    );
    // What `GpuBvh::upload` uploads for these pipelines (the same for each of them).
    let upload = pipelines[0].upload_bytes(bvh.nodes.len() as u64, bvh.triangles.len() as u64);
    let v = json!({
        "scene": args.scene.spec(),
        "name": scene.name,
        "description": scene.description,
        "synthetic": scene.synthetic,
        "meshes": scene.meshes.len(),
        "instances": scene.instance_count(),
        "triangles": tris.len(),
        "bounds": { "min": lo.to_array(), "max": hi.to_array() },
        "attributes": { "normals": a.normals, "texcoords": a.texcoords, "colors": a.colors, "materials": a.materials },
        "camera": scene.camera.map(|c| json!({"eye": c.eye.to_array(), "target": c.target.to_array(), "fov": c.fov_y_deg})),
        "builder": args.scene.builder.name(),
        "nodes": s.nodes, "leaves": s.leaves, "depth": s.depth,
        "sah_cost": s.sah_cost, "sah_cost_pbrt": s.sah_cost_pbrt,
        "leaf_sizes": s.leaf_sizes,
        "bytes": { "nodes": nb, "escapes": eb, "triangles": tb },
        "pipelines": pipelines.iter().map(pipeline_json).collect::<Vec<_>>(),
        "upload": upload_json(&upload, args.storage, tris.len()),
        "left_out": left_out(&pipelines, &scene, args.traversal),
        "load_ms": load_ms, "build_ms": build_ms,
        "warnings": scene.warnings,
    });
    if args.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    println!("scene       {} ({})", args.scene.spec(), scene.description);
    println!(
        "triangles   {} in {} meshes, {} instances{}",
        tris.len(),
        scene.meshes.len(),
        scene.instance_count(),
        if scene.synthetic { " (synthetic)" } else { "" }
    );
    println!("bounds      {:?} .. {:?}", lo.to_array(), hi.to_array());
    println!(
        "attributes  normals {} texcoords {} colors {} materials {}",
        a.normals, a.texcoords, a.colors, a.materials
    );
    println!(
        "bvh         {} ({} bins): {} nodes, {} leaves, depth {}",
        args.scene.builder, args.scene.bins, s.nodes, s.leaves, s.depth
    );
    println!(
        "sah cost    {:.3} (traversal 1, intersection 1)  {:.3} (PBRT 1/8, 1)",
        s.sah_cost, s.sah_cost_pbrt
    );
    let hist: Vec<String> = s
        .leaf_sizes
        .iter()
        .enumerate()
        .filter(|(_, n)| **n > 0)
        .map(|(k, n)| format!("{k}:{n}"))
        .collect();
    println!("leaf sizes  {}", hist.join(" "));
    println!("gpu bytes   nodes {nb}, escapes {eb} (stackless/short-stack only), triangles {tb}");
    for p in &pipelines {
        let bindings: Vec<String> = p
            .bindings()
            .iter()
            .map(|b| format!("{}.{} {}", b.group, b.binding, b.name))
            .collect();
        println!(
            "pipeline    {} [{}]: {}",
            p.variant.entry_point(),
            p.names().join(", "),
            bindings.join(", ")
        );
    }
    println!(
        "upload      {} bytes ({:?}: nodes {}, triangles {}, escapes {}) = {:.1} bytes/triangle",
        upload.total_bytes(),
        args.storage,
        upload.nodes_bytes,
        upload.triangles_bytes,
        upload.escapes_bytes,
        upload.total_bytes() as f64 / tris.len().max(1) as f64
    );
    for l in left_out(&pipelines, &scene, args.traversal) {
        println!("left out    {l}");
    }
    println!("timing      load {load_ms:.1} ms, build {build_ms:.1} ms");
    Ok(())
}

/// `bvhtrace dump`.
#[derive(clap::Args)]
pub struct DumpArgs {
    /// A .gltf/.glb file or a `builtin:` name.
    pub scene: Option<String>,
    #[command(flatten)]
    pub view: CameraArgs,
    /// Output file.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Writes the scene's triangles (world space, input order) and the camera's primary rays in
/// a flat binary form for other tracers (`crates/cli/embree/embree_trace.c`): "BVHD",
/// u32 version 1, u32 triangle count, u32 ray count, 9 f32 per triangle, 8 f32 per ray
/// (origin, t_min, dir, t_max), little endian.
pub fn dump(args: DumpArgs) -> Result<()> {
    let out = AtomicFile::create(&args.output)?;
    let spec = args.scene.as_deref().unwrap_or(DEFAULT_SCENE);
    let scene = bvhtrace_scene::load(spec)?;
    let tris = scene
        .flatten()
        .triangles()
        .with_context(|| format!("{spec}: bad geometry"))?;
    let cam = camera_for(&args.view, &scene)?;
    let (w, h) = args.view.size;
    let rays = cam.rays(w, h);
    let mut bytes = Vec::with_capacity(16 + tris.len() * 36 + rays.len() * 32);
    bytes.extend_from_slice(b"BVHD");
    for v in [1u32, tris.len() as u32, rays.len() as u32] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    for p in tris.iter().flatten() {
        for c in p.to_array() {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    for r in &rays {
        for c in r
            .origin
            .iter()
            .chain([&r.t_min])
            .chain(&r.dir)
            .chain([&r.t_max])
        {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    out.finish_with_bytes(&bytes)?;
    eprintln!(
        "wrote {}: {} triangles, {} rays ({w}x{h})",
        args.output.display(),
        tris.len(),
        rays.len()
    );
    Ok(())
}
