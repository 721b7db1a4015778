//! `bvhtrace bench-trace`: the walks on the device (wgpu) beside their CPU twins, the CPU
//! layout and the device's ray queries, on the same primary rays; and, with
//! `--everything-on`, each walk's specialised pipeline against the everything-on one.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use bvhtrace_core::{
    BuildOptions, FlatBvh, Query, Ray, TraceOptions, TracePhases, Traversal, trace_rays,
};
use bvhtrace_gpu::{
    Composition, ContextOptions, GpuBvh, GpuContext, KernelKey, Tracer, UploadOptions,
    VertexAttributes,
};

use super::{BenchTraceArgs, RayKind, load, median, primary_rays, scene_specs};
use crate::embree::{self, Dump};

/// Where a walk's wall time went on the device, medians over the rounds: the rays
/// written and submitted, the submission on the device (copies and kernels), the hits
/// read back.
fn print_phases(name: &str, query: &str, phases: &[TracePhases]) {
    let med = |f: fn(&TracePhases) -> f64| median(phases.iter().map(f).collect());
    println!(
        "{name:16} {query:8} wall: rays up {:.1} ms, on the device {:.1} ms, hits back {:.1} ms",
        med(|p| p.upload_ms),
        med(|p| p.device_ms),
        med(|p| p.readback_ms),
    );
}

/// The CPU layout's rows of `bench-trace`'s table: one per instruction set, its Mrays/s
/// over `n` rays (medians of `ms`) and its speed against Embree's (`embree_ms`, the same
/// rounds), the GPU columns empty.
fn print_cpu_layout_rows(
    isas: &[bvhtrace_cpu::Isa],
    q: Query,
    ms: &[Vec<f64>],
    embree_ms: &[f64],
    n: f64,
) {
    for (isa, ms) in isas.iter().zip(ms) {
        let vs_embree = if embree_ms.is_empty() {
            "-".to_string()
        } else {
            let ratios = embree_ms.iter().zip(ms).map(|(a, b)| a / b).collect();
            format!("{:.2}x", median(ratios))
        };
        println!(
            "{:16} {:8} {:>9} {:>9} {:>9.2} {:>7} {:>6} {:>7} {:>8} {:>8} {:>8} {:>10}",
            format!("cpu8 {isa}"),
            format!("{q:?}").to_lowercase(),
            "-",
            "-",
            n / median(ms.clone()) / 1e3,
            "-",
            "-",
            "-",
            "-",
            "-",
            "-",
            vs_embree,
        );
    }
}

/// The short stacks timed when `--traversals` names none (every other walk once).
const DEFAULT_SHORT_STACKS: [u32; 4] = [2, 4, 6, 8];

/// `bvhtrace bench-trace` (without `--cpu-only`).
pub fn run(args: &BenchTraceArgs) -> Result<()> {
    let (w, h) = args.size;
    // The automatic choice's device: wgpu, with its ray queries when it has them (they are
    // measured beside our walks whichever the choice would trace with).
    let device = crate::backend::device(&crate::backend::options(
        crate::backend::Backend::Auto,
        args.adapter.as_deref(),
        &[],
    ))?;
    let ctx = device
        .wgpu_context()
        .context("bench-trace measures the wgpu backend, and there is no Vulkan adapter")?;
    let info = ctx.adapter_info();
    println!(
        "adapter: {} ({:?}); CPU: {} threads",
        info.name,
        info.device_type,
        rayon::current_num_threads()
    );
    if args.everything_on {
        return compare_everything_on(ctx, args, w, h);
    }
    let traversals = if args.traversals.is_empty() {
        Traversal::all_with_short_stacks(&DEFAULT_SHORT_STACKS)
    } else {
        args.traversals.clone()
    };
    let queries: &[Query] = if args.any_hit {
        &[Query::Closest, Query::Any]
    } else {
        &[Query::Closest]
    };
    for spec in scene_specs(&args.scenes)? {
        let subject = Subject::prepare(ctx, args, &spec, &traversals)?;
        for &q in queries {
            let counts = subject.counts(q)?;
            let rounds = subject.rounds(args, q)?;
            subject.print_rows(q, &counts, &rounds);
        }
    }
    Ok(())
}

/// One scene made ready to time: its tree (binary, and wide where a walk is), the CPU
/// layout of it and the instruction sets to time that on, the primary rays, our walks on
/// the device, the device's ray queries where it has them, and Embree's dump with
/// `--embree`.
struct Subject<'a> {
    traversals: &'a [Traversal],
    bvh: FlatBvh,
    cpu_layout: bvhtrace_cpu::CpuBvh,
    isas: Vec<bvhtrace_cpu::Isa>,
    rays: Vec<Ray>,
    gpu: Box<dyn Tracer>,
    rq: Option<Box<dyn Tracer>>,
    dump: Option<Dump>,
}

/// The timings of one query's rounds, milliseconds, one entry per round: each walk on the
/// device (timestamps, and wall) and on the CPU, the CPU layout on each instruction set,
/// Embree's trace and build, and the ray queries' wall time.
struct Rounds {
    gpu_ms: Vec<Vec<f64>>,
    wall_ms: Vec<Vec<f64>>,
    cpu_ms: Vec<Vec<f64>>,
    cpu_layout_ms: Vec<Vec<f64>>,
    embree_ms: Vec<f64>,
    embree_build_ms: Vec<f64>,
    rq_ms: Vec<f64>,
    /// The Embree the helper ran (`Embree 4.4.0`), once it has.
    embree_version: String,
    /// Where each walk's wall time went on the device, and the ray queries'.
    phases: Vec<Vec<TracePhases>>,
    rq_phases: Vec<TracePhases>,
}

impl<'a> Subject<'a> {
    /// Loads `spec`, builds and uploads its tree, and prints its line and the table's head.
    fn prepare(
        ctx: &GpuContext,
        args: &BenchTraceArgs,
        spec: &str,
        traversals: &'a [Traversal],
    ) -> Result<Subject<'a>> {
        let (w, h) = args.size;
        let (tris, scene, _) = load(spec)?;
        let t = Instant::now();
        let mut bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
        let build_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        if traversals.iter().any(|t| t.is_wide()) {
            bvh.build_wide();
        }
        let wide_ms = t.elapsed().as_secs_f64() * 1e3;
        // The CPU layout (`bvhtrace-cpu`), timed beside the walks on each instruction set.
        let cpu_layout = bvhtrace_cpu::CpuBvh::from_flat(&bvh)?;
        let isas = bvhtrace_cpu::Isa::all_available();
        let rays = match args.rays {
            RayKind::Primary => primary_rays(&scene, w, h),
            kind => {
                let cam = scene.camera_or_frame(w as f32 / h as f32);
                let sets = super::ray_sets(&tris, &bvh, &cam, w, h);
                match kind {
                    RayKind::Shadow => sets.shadow,
                    _ => sets.diffuse,
                }
            }
        };
        let upload = bvhtrace::OpenOptions {
            traversals: traversals.to_vec(),
            ..Default::default()
        };
        let gpu = bvhtrace::Device::wgpu(ctx.clone())
            .open_owned(&bvh, &upload)?
            .tracer;
        // The device's ray queries on the same rays, when it has them.
        let rq = match ctx.has_ray_queries() {
            true => Some(
                bvhtrace::Device::ray_query(ctx.clone())?
                    .open_owned(&bvh, &upload)?
                    .tracer,
            ),
            false => None,
        };
        let dump = match &args.embree {
            Some(_) => Some(Dump::write("trace", &tris, &rays)?),
            None => None,
        };
        println!(
            "\n{spec}: {} triangles, depth {}, {} {} rays (from {w}x{h}); our build \
             {build_ms:.1} ms (+{wide_ms:.1} ms to the wide layout)",
            tris.len(),
            bvh.depth(),
            rays.len(),
            format!("{:?}", args.rays).to_lowercase()
        );
        if let Some(build) = rq.as_ref().and_then(|t| t.device_build_ms()) {
            println!(
                "ray queries: the driver's build {build:.1} ms (a BLAS over the triangles in \
                 our leaf order, a TLAS), beside our build {build_ms:.1} ms"
            );
        }
        println!(
            "{:16} {:8} {:>9} {:>9} {:>9} {:>7} {:>6} {:>7} {:>8} {:>8} {:>8} {:>10}",
            "traversal",
            "query",
            "GPU Mr/s",
            "GPU wall",
            "CPU Mr/s",
            "nodes",
            "tris",
            "n/full",
            "GPU/full",
            "GPU/twin",
            "GPU/CPU",
            "CPU/Embree"
        );
        Ok(Subject {
            traversals,
            bvh,
            cpu_layout,
            isas,
            rays,
            gpu,
            rq,
            dump,
        })
    }

    /// Box and triangle tests per ray of each walk on the device. The counters (and the
    /// counted pipelines) come first, then one untimed trace each, so that no timed run
    /// pays a pipeline's creation or first dispatch.
    fn counts(&self, q: Query) -> Result<Vec<(f64, f64)>> {
        let n = self.rays.len() as f64;
        let mut counts = Vec::new();
        for &tr in self.traversals {
            let opts = TraceOptions::new(tr, q);
            let c = self
                .gpu
                .trace(&self.rays, &opts.with_counters(true))?
                .counters
                .unwrap_or_default();
            let per_ray = |f: fn(&bvhtrace_core::Counters) -> u32| {
                c.iter().map(|c| f64::from(f(c))).sum::<f64>() / n.max(1.0)
            };
            counts.push((per_ray(|c| c.nodes), per_ray(|c| c.tris)));
            self.gpu.trace(&self.rays, &opts)?;
        }
        Ok(counts)
    }

    /// `args.runs` rounds of every walk on the device and its twin on the CPU, one after
    /// the other, then the CPU layout, Embree and the ray queries: lavapipe and the CPU
    /// swing by 10-20% from minute to minute, so the ratios are taken within each round
    /// (medians over the rounds).
    fn rounds(&self, args: &BenchTraceArgs, q: Query) -> Result<Rounds> {
        let (rays, walks) = (&self.rays, self.traversals);
        let mut r = Rounds {
            gpu_ms: vec![Vec::new(); walks.len()],
            wall_ms: vec![Vec::new(); walks.len()],
            cpu_ms: vec![Vec::new(); walks.len()],
            cpu_layout_ms: vec![Vec::new(); self.isas.len()],
            embree_ms: Vec::new(),
            embree_build_ms: Vec::new(),
            rq_ms: Vec::new(),
            embree_version: String::new(),
            phases: vec![Vec::new(); walks.len()],
            rq_phases: Vec::new(),
        };
        if let Some(rq) = &self.rq {
            rq.trace(rays, &TraceOptions::new(walks[0], q))?;
        }
        for _ in 0..args.runs {
            if let Some(rq) = &self.rq {
                let o = rq.trace(rays, &TraceOptions::new(walks[0], q))?;
                r.rq_ms.push(o.wall_ms);
                r.rq_phases.extend(o.phases);
            }
            for (i, &tr) in walks.iter().enumerate() {
                let opts = TraceOptions::new(tr, q);
                let o = self.gpu.trace(rays, &opts)?;
                r.wall_ms[i].push(o.wall_ms);
                r.gpu_ms[i].push(o.gpu_ms.unwrap_or(o.wall_ms));
                r.phases[i].extend(o.phases);
                let t = Instant::now();
                std::hint::black_box(trace_rays(&self.bvh, rays, &opts));
                r.cpu_ms[i].push(t.elapsed().as_secs_f64() * 1e3);
            }
            for (i, &isa) in self.isas.iter().enumerate() {
                let layout = &self.cpu_layout;
                let t = Instant::now();
                std::hint::black_box(bvhtrace_cpu::trace_rays_with(layout, rays, q, isa));
                r.cpu_layout_ms[i].push(t.elapsed().as_secs_f64() * 1e3);
            }
            if let (Some(exe), Some(dump), Query::Closest) = (&args.embree, &self.dump, q) {
                let v = dump.run(exe, 2, 1, &[])?;
                r.embree_ms.push(embree::field(&v, "trace_ms", exe)?);
                r.embree_build_ms.push(embree::field(&v, "build_ms", exe)?);
                r.embree_version = embree::version(&v);
            }
        }
        Ok(r)
    }

    /// The table's rows for query `q`: each walk, the CPU layout on each instruction set,
    /// the ray queries and Embree where they ran.
    fn print_rows(&self, q: Query, counts: &[(f64, f64)], r: &Rounds) {
        let n = self.rays.len() as f64;
        let ratio =
            |num: &[f64], den: &[f64]| median(num.iter().zip(den).map(|(a, b)| a / b).collect());
        let mrays = |ms: &[f64]| n / median(ms.to_vec()) / 1e3;
        let query = format!("{q:?}").to_lowercase();
        for (i, tr) in self.traversals.iter().enumerate() {
            let vs_embree = if r.embree_ms.is_empty() {
                "-".to_string()
            } else {
                format!("{:.2}x", ratio(&r.embree_ms, &r.cpu_ms[i]))
            };
            println!(
                "{:16} {:8} {:>9.2} {:>9.2} {:>9.2} {:>7.1} {:>6.2} {:>6.2}x {:>7.2}x {:>7.2}x {:>7.2}x {:>10}",
                tr.to_string(),
                query,
                mrays(&r.gpu_ms[i]),
                mrays(&r.wall_ms[i]),
                mrays(&r.cpu_ms[i]),
                counts[i].0,
                counts[i].1,
                counts[i].0 / counts[0].0,
                ratio(&r.gpu_ms[0], &r.gpu_ms[i]),
                ratio(&r.cpu_ms[i], &r.gpu_ms[i]),
                ratio(&r.cpu_ms[0], &r.gpu_ms[i]),
                vs_embree,
            );
        }
        print_cpu_layout_rows(&self.isas, q, &r.cpu_layout_ms, &r.embree_ms, n);
        if !r.rq_ms.is_empty() {
            // Wall time only (the driver's walk has no timestamps of ours); ratios
            // against the first walk's wall time and its CPU twin's.
            println!(
                "{:16} {:8} {:>9} {:>9.2} {:>9} {:>7} {:>6} {:>7} {:>7.2}x {:>8} {:>7.2}x {:>10}",
                bvhtrace::Backend::RayQuery.name(),
                query,
                "-",
                mrays(&r.rq_ms),
                "-",
                "-",
                "-",
                "-",
                ratio(&r.wall_ms[0], &r.rq_ms),
                "-",
                ratio(&r.cpu_ms[0], &r.rq_ms),
                "-",
            );
        }
        let walks = self.traversals.iter().map(|t| t.to_string());
        let phases = walks.zip(&r.phases).chain(
            (!r.rq_phases.is_empty())
                .then(|| (bvhtrace::Backend::RayQuery.name().to_string(), &r.rq_phases)),
        );
        for (name, p) in phases.filter(|(_, p)| !p.is_empty()) {
            print_phases(&name, &query, p);
        }
        if !r.embree_ms.is_empty() {
            println!(
                "{:16} {:8} {:>9} {:>9} {:>9.2}   ({} rtcIntersect1, 2 threads; build {:.1} ms)",
                "embree",
                "closest",
                "-",
                "-",
                mrays(&r.embree_ms),
                r.embree_version,
                median(r.embree_build_ms.clone()),
            );
        }
    }
}

/// One side of `bench-trace --everything-on`.
struct Side {
    name: &'static str,
    options: ContextOptions,
    gpu: GpuBvh,
    opts: TraceOptions,
    wgsl_bytes: usize,
    bindings: usize,
    create_ms: Vec<f64>,
    gpu_ms: Vec<f64>,
    wall_ms: Vec<f64>,
}

/// `bvhtrace bench-trace --everything-on`: per scene and traversal, the specialised
/// closest-hit pipeline against the everything-on one, on the same rays; the two sides'
/// runs are interleaved, and their hits must be equal.
fn compare_everything_on(ctx: &GpuContext, args: &BenchTraceArgs, w: u32, h: u32) -> Result<()> {
    println!(
        "storage: {:?}; {} runs per figure (medians)",
        ctx.tuning().storage,
        args.runs
    );
    for spec in scene_specs(&args.scenes)? {
        let (tris, scene, _) = load(&spec)?;
        let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
        let rays = primary_rays(&scene, w, h);
        println!(
            "\n{spec}: {} triangles, {} nodes, {} rays ({w}x{h})",
            tris.len(),
            bvh.nodes().len(),
            rays.len()
        );
        println!(
            "{:14} {:14} {:>8} {:>9} {:>10} {:>10} {:>9} {:>9} {:>9}",
            "traversal",
            "pipeline",
            "bindings",
            "WGSL KiB",
            "upload MB",
            "bytes/tri",
            "create ms",
            "GPU Mr/s",
            "wall Mr/s"
        );
        for tr in [
            Traversal::FullStack,
            Traversal::Stackless,
            Traversal::ShortStack(bvhtrace_core::traverse::DEFAULT_SHORT_STACK),
        ] {
            let sides = compare_sides(ctx, args, &spec, &bvh, &rays, tr)?;
            let n = rays.len() as f64;
            for s in &sides {
                let bytes = s.gpu.stats().total_bytes();
                println!(
                    "{:14} {:14} {:>8} {:>9.1} {:>10.2} {:>10.1} {:>9.1} {:>9.2} {:>9.2}",
                    tr.to_string(),
                    s.name,
                    s.bindings,
                    s.wgsl_bytes as f64 / 1024.0,
                    bytes as f64 / 1e6,
                    bytes as f64 / tris.len().max(1) as f64,
                    median(s.create_ms.clone()),
                    n / median(s.gpu_ms.clone()) / 1e3,
                    n / median(s.wall_ms.clone()) / 1e3
                );
            }
        }
    }
    Ok(())
}

/// A context of its own for `options`' composition, on `ctx`'s device.
fn context_with(ctx: &GpuContext, options: &ContextOptions) -> Result<GpuContext> {
    Ok(GpuContext::from_device_with(
        ctx.device().clone(),
        ctx.queue().clone(),
        ctx.adapter_info().clone(),
        options,
    )?)
}

/// The two sides of `tr`'s closest-hit job on `spec`, each with `bvh` uploaded in its own
/// context: their pipeline creation timed `args.runs` times (nothing cached), then their
/// traces of `rays` (after one untimed trace each, whose hits must agree), interleaved.
fn compare_sides(
    ctx: &GpuContext,
    args: &BenchTraceArgs,
    spec: &str,
    bvh: &FlatBvh,
    rays: &[Ray],
    tr: Traversal,
) -> Result<[Side; 2]> {
    let storage = ctx.tuning().storage;
    let plain = TraceOptions::closest(tr);
    let job = KernelKey::for_job(
        storage,
        &plain,
        VertexAttributes::NONE,
        VertexAttributes::NONE,
    );
    let all = job.with_composition(Composition::EverythingOn);
    let side = |name, composition, upload: &UploadOptions, opts, wgsl_bytes, bindings| {
        let options = ContextOptions {
            composition,
            ..ContextOptions::default()
        };
        anyhow::Ok(Side {
            name,
            options,
            gpu: GpuBvh::upload(&context_with(ctx, &options)?, bvh, upload)?,
            opts,
            wgsl_bytes,
            bindings,
            create_ms: Vec::new(),
            gpu_ms: Vec::new(),
            wall_ms: Vec::new(),
        })
    };
    let mut sides = [
        side(
            "specialised",
            Composition::Specialised,
            &UploadOptions::for_traversal(tr).with_storage(storage),
            plain,
            job.source().len(),
            job.bindings().len(),
        )?,
        side(
            "everything-on",
            Composition::EverythingOn,
            &UploadOptions::all().with_storage(storage),
            plain.with_counters(true),
            all.source().len(),
            all.bindings().len(),
        )?,
    ];
    // Pipeline creation (module + pipeline, nothing cached), interleaved.
    for _ in 0..args.runs {
        for s in sides.iter_mut() {
            let fresh = context_with(ctx, &s.options)?;
            let gpu = GpuBvh::upload(&fresh, bvh, &UploadOptions::all())?;
            let t = Instant::now();
            gpu.prepare(&s.opts)?;
            s.create_ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    // Both pipelines compiled once more and kept; one untimed trace each.
    let mut hits = Vec::new();
    for s in sides.iter_mut() {
        s.gpu.prepare(&s.opts)?;
        hits.push(s.gpu.trace(rays, &s.opts)?.hits);
    }
    if hits[0] != hits[1] {
        bail!("{spec} {tr}: the specialised and everything-on pipelines disagree");
    }
    for _ in 0..args.runs {
        for s in sides.iter_mut() {
            let o = s.gpu.trace(rays, &s.opts)?;
            s.wall_ms.push(o.wall_ms);
            s.gpu_ms.push(o.gpu_ms.unwrap_or(o.wall_ms));
        }
    }
    Ok(sides)
}
