//! `bvhtrace bench-trace --cpu-only`: every CPU path (the core walks, the CPU layout of
//! `bvhtrace-cpu` on each instruction set) beside Embree 3 in its default and robust
//! modes, on primary (closest-hit), shadow (any-hit) and diffuse-bounce (closest-hit,
//! incoherent: one cosine-weighted bounce from each primary hit, seeded) rays, same rays,
//! same run; and the packet walk on the same rays put in 8x8 screen tiles (the diffuse
//! rays in the primary hits' order: their origins are coherent, their directions not).
//! A scene the front door traces in two levels or with alpha masks also gets rows of the
//! CPU layout over that tree (named `two-level`, `masked`), on the same rays, checked
//! against the full stack over the same tree; Embree traces the flattened triangles
//! without masks.

use std::time::Instant;

use anyhow::Result;
use bvhtrace_core::{BuildOptions, FlatBvh, Hit, Query, Ray, TraceOptions, Traversal, trace_rays};
use bvhtrace_cpu::{CpuBvh, Isa};

use super::{BenchTraceArgs, median, ray_sets, scene_specs};
use crate::embree::{self, Dump};

/// A CPU path's batch trace.
type TraceFn<'a> = Box<dyn Fn(&[Ray], Query) -> Vec<Hit> + 'a>;

/// A path timed: its name, its trace, whether it takes the rays in 8x8 tiles, and the tree
/// whose full-stack answers it is checked against (0: the flattened triangles', 1: the
/// scene as traced, with two levels or masks).
type Path<'a> = (String, TraceFn<'a>, bool, usize);

/// The scene as the front door traces it when that is not one mesh without masks: its
/// name in the rows (`two-level`, `masked`), its tree and the tree's CPU layout.
type Traced<'a> = Option<(&'static str, &'a FlatBvh, &'a CpuBvh)>;

/// The paths timed: the core walks asked for, then the CPU layout on each instruction set
/// this CPU has, one ray at a time and in packets (on the rays in tiles), then the CPU
/// layout of the scene as traced (two levels, masks) one ray at a time.
fn paths<'a>(
    flat: &'a FlatBvh,
    cpu: &'a CpuBvh,
    walks: &[Traversal],
    traced: Traced<'a>,
) -> Vec<Path<'a>> {
    let mut out: Vec<Path<'a>> = Vec::new();
    for &tr in walks {
        let f = move |rays: &[Ray], q| trace_rays(flat, rays, &TraceOptions::new(tr, q)).hits;
        out.push((format!("core {tr}"), Box::new(f), false, 0));
    }
    for isa in Isa::all_available() {
        let f = move |rays: &[Ray], q| bvhtrace_cpu::trace_rays_with(cpu, rays, q, isa);
        out.push((format!("cpu8 {isa}"), Box::new(f), false, 0));
    }
    for isa in Isa::all_available() {
        let f = move |rays: &[Ray], q| bvhtrace_cpu::trace_packets_with(cpu, rays, q, isa);
        out.push((format!("cpu8 {isa} packets"), Box::new(f), true, 0));
    }
    if let Some((name, _, cpu)) = traced {
        for isa in Isa::all_available() {
            let f = move |rays: &[Ray], q| bvhtrace_cpu::trace_rays_with(cpu, rays, q, isa);
            out.push((format!("cpu8 {isa} {name}"), Box::new(f), false, 1));
        }
    }
    out
}

/// The primary and shadow rays in 8x8 tiles of the `w` x `h` image: the same rays, the
/// primary rays in [`bvhtrace_cpu::tile_order`], the shadow rays one tile per packet
/// ([`bvhtrace_cpu::Tiles::packets`]: a pixel without one holds a ray with an empty
/// interval, which every tracer answers with a miss; tiles without any are left out).
fn tiled_sets(
    tris: &[bvhtrace_core::Triangle],
    flat: &FlatBvh,
    cam: &bvhtrace_scene::Camera,
    primary: &[Ray],
    shadow: &[Ray],
    (w, h): (u32, u32),
) -> Result<(Vec<Ray>, Vec<Ray>)> {
    let tiles = bvhtrace_cpu::Tiles::new(w, h);
    let hits = trace_rays(flat, primary, &TraceOptions::closest(Traversal::FullStack)).hits;
    let b = flat.bounds();
    let (again, owner) = crate::shade::secondary_rays(
        crate::shade::Shade::Diffuse,
        &|p| tris[p as usize],
        primary,
        &hits,
        crate::shade::point_light(cam),
        1,
        (b.max - b.min).length(),
    );
    anyhow::ensure!(
        again.len() == shadow.len(),
        "the shadow rays could not be matched"
    );
    // One tile's shadow rays per packet, pixels without one holding idle rays.
    Ok((tiles.gather(primary), tiles.packets(shadow, &owner).0))
}

/// The two Embree modes timed: its default (not watertight) and `RTC_SCENE_FLAG_ROBUST`.
const EMBREE_MODES: [(&str, &str); 2] = [("embree fast", "fast"), ("embree robust", "robust")];

/// Embree 4's rows (`--embree4`), after Embree 3's.
const EMBREE4_MODES: [(&str, &str); 2] = [("embree4 fast", "fast"), ("embree4 robust", "robust")];

/// Rays whose answer differs from the reference's: closest hits to the bit (primitive
/// and `t`), any hits on hit or miss.
fn differences(got: &[Hit], want: &[Hit], q: Query) -> usize {
    got.iter()
        .zip(want)
        .filter(|(g, w)| match q {
            Query::Closest => g.prim != w.prim || g.t.to_bits() != w.t.to_bits(),
            Query::Any => g.is_hit() != w.is_hit(),
        })
        .count()
}

/// `bvhtrace bench-trace --cpu-only`.
pub fn run(args: &BenchTraceArgs) -> Result<()> {
    let counts = match args.threads.is_empty() {
        true => vec![rayon::current_num_threads()],
        false => args.threads.clone(),
    };
    let mut sweep = Sweep::default();
    for &n in &counts {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(n).build()?;
        pool.install(|| run_scenes(args, &mut sweep))?;
    }
    if counts.len() > 1 {
        sweep.print(&counts);
    }
    Ok(())
}

/// Mrays/s per scene, ray kind and path, one entry per thread count swept.
#[derive(Default)]
struct Sweep {
    rows: Vec<((String, String, String), Vec<f64>)>,
}

impl Sweep {
    fn add(&mut self, key: (String, String, String), mrays: f64) {
        match self.rows.iter_mut().find(|(k, _)| *k == key) {
            Some((_, v)) => v.push(mrays),
            None => self.rows.push((key, vec![mrays])),
        }
    }

    /// Each path's rate per count and its efficiency at each count against the first.
    fn print(&self, counts: &[usize]) {
        println!(
            "\nthread sweep: Mrays/s (scaling efficiency against {} threads)",
            counts[0]
        );
        for ((spec, kind, path), rates) in &self.rows {
            let cells: Vec<String> = (counts.iter().zip(rates))
                .map(|(&n, r)| {
                    let per = rates[0] / counts[0] as f64;
                    format!("{n}: {r:.2} ({:.0}%)", 100.0 * r / (per * n as f64))
                })
                .collect();
            println!("{spec} {kind} {path:28} {}", cells.join("  "));
        }
    }
}

/// Every scene at the current pool's thread count: its sizes, then each ray kind's table.
fn run_scenes(args: &BenchTraceArgs, sweep: &mut Sweep) -> Result<()> {
    let (w, h) = args.size;
    let threads = rayon::current_num_threads();
    println!(
        "\nCPU only: {threads} threads; {} rounds, medians; ratios are medians of per-round ratios",
        args.runs
    );
    let walks = if args.traversals.is_empty() {
        vec![Traversal::FullStack, Traversal::Wide]
    } else {
        args.traversals.clone()
    };
    for spec in scene_specs(&args.scenes)? {
        let scene = crate::geometry::load_triangle_scene(&spec)?;
        let tris = scene.flattened_triangles()?;
        let t = Instant::now();
        let mut flat = FlatBvh::build(&tris, &BuildOptions::default())?;
        let build_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        if walks.iter().any(|t| t.is_wide()) {
            flat.build_wide();
        }
        let wide_ms = t.elapsed().as_secs_f64() * 1e3;
        let mut convert_ms = Vec::new();
        let mut cpu = CpuBvh::default();
        for _ in 0..args.runs {
            let t = Instant::now();
            cpu = CpuBvh::from_flat(&flat)?;
            convert_ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let n_tris = tris.len().max(1) as f64;
        let (bn, _, bt) = flat.byte_sizes();
        let wide_bytes = flat.wide().map(|wd| {
            let (a, b) = wd.byte_sizes();
            format!(", wide {:.1}", (a + b) as f64 / n_tris)
        });
        println!(
            "\n{spec}: {} triangles; build {build_ms:.1} ms, +{wide_ms:.1} ms wide, +{:.1} ms CPU \
             layout (median of {}); bytes/triangle: binary {:.1}{}, CPU layout {:.1} ({} nodes, {} blocks)",
            tris.len(),
            median(convert_ms.clone()),
            args.runs,
            (bn + bt) as f64 / n_tris,
            wide_bytes.unwrap_or_default(),
            cpu.bytes_per_triangle(),
            cpu.nodes().len(),
            cpu.blocks().len(),
        );
        // The scene as the front door traces it (two levels where it places meshes more
        // than once, its alpha masks), built and timed beside the flattened triangles only
        // when it differs from them.
        let traced_name = match (scene.traces_in_two_levels(false), scene.has_alpha_masks()) {
            (false, false) => None,
            (true, false) => Some("two-level"),
            (false, true) => Some("masked"),
            (true, true) => Some("two-level masked"),
        };
        let traced_bvh = match traced_name {
            Some(_) => Some(scene.tracing_bvh(&BuildOptions::default(), false)?),
            None => None,
        };
        let traced_cpu = match &traced_bvh {
            Some(t) => Some(CpuBvh::from_flat(t.bvh())?),
            None => None,
        };
        let traced = (traced_name
            .zip(traced_bvh.as_ref())
            .zip(traced_cpu.as_ref()))
        .map(|((name, t), c)| (name, t.bvh(), c));
        if let Some((name, t, c)) = traced {
            println!(
                "as traced ({name}): {} nodes, {} instances; CPU layout {} nodes, {} blocks",
                t.nodes().len(),
                t.instances().len(),
                c.nodes().len(),
                c.blocks().len()
            );
        }
        let cam = scene.camera_or_frame(w as f32 / h as f32);
        let sets = ray_sets(&tris, &flat, &cam, w, h);
        let (primary_tiled, shadow_tiled) =
            tiled_sets(&tris, &flat, &cam, &sets.primary, &sets.shadow, (w, h))?;
        let kinds = [
            ("primary", [sets.primary, primary_tiled], Query::Closest),
            ("shadow", [sets.shadow, shadow_tiled], Query::Any),
            (
                "diffuse",
                [sets.diffuse.clone(), sets.diffuse],
                Query::Closest,
            ),
        ];
        let paths = paths(&flat, &cpu, &walks, traced);
        let trees = [&flat, traced.map_or(&flat, |t| t.1)];
        for (kind, rays, q) in kinds {
            let rates = bench_kind(args, &spec, kind, &tris, trees, &paths, &rays, q)?;
            for (path, mrays) in rates {
                sweep.add((spec.clone(), kind.to_string(), path), mrays);
            }
        }
    }
    Ok(())
}

/// One ray kind: rounds of every path and of Embree, then the table; each path's Mrays/s.
/// `sets` holds the rays as the image has them (Embree's) and the same rays in 8x8 tiles
/// (the packet paths').
#[allow(clippy::too_many_arguments)]
fn bench_kind(
    args: &BenchTraceArgs,
    spec: &str,
    kind: &str,
    tris: &[bvhtrace_core::Triangle],
    trees: [&FlatBvh; 2],
    paths: &[Path<'_>],
    sets: &[Vec<Ray>; 2],
    q: Query,
) -> Result<Vec<(String, f64)>> {
    let rays = &sets[0];
    let opts = TraceOptions::new(Traversal::FullStack, q);
    // Each tree's full-stack answers, on the rays in order and in tiles.
    let refs = trees.map(|t| [0, 1].map(|k| trace_rays(t, &sets[k], &opts).hits));
    let dump = match args.embree.is_some() || args.embree4.is_some() {
        true => Some(Dump::write(kind, tris, rays)?),
        false => None,
    };
    let query_env = if q == Query::Any { "any" } else { "closest" };
    // Our paths, then Embree 3's modes, then Embree 4's.
    let helpers = [(&args.embree, EMBREE_MODES), (&args.embree4, EMBREE4_MODES)];
    let mut ms = vec![Vec::new(); paths.len() + 4];
    let mut diffs = vec![0; paths.len()];
    // Untimed warm-up, which also checks the answers.
    for (i, (_, f, tiled, tree)) in paths.iter().enumerate() {
        let k = usize::from(*tiled);
        diffs[i] = differences(&f(&sets[k], q), &refs[*tree][k], q);
    }
    for _ in 0..args.runs {
        for (i, (_, f, tiled, _)) in paths.iter().enumerate() {
            let rays = &sets[usize::from(*tiled)];
            let t = Instant::now();
            std::hint::black_box(f(rays, q));
            ms[i].push(t.elapsed().as_secs_f64() * 1e3);
        }
        for (h, (exe, modes)) in helpers.iter().enumerate() {
            let (Some(exe), Some(dump)) = (exe, &dump) else {
                continue;
            };
            for (k, (_, mode)) in modes.iter().enumerate() {
                let env = [
                    ("BVHTRACE_EMBREE_MODE", mode.to_string()),
                    ("BVHTRACE_EMBREE_QUERY", query_env.to_string()),
                ];
                let v = dump.run(exe, rayon::current_num_threads(), 1, &env)?;
                ms[paths.len() + 2 * h + k].push(embree::field(&v, "trace_ms", exe)?);
            }
        }
    }
    let n = rays.len() as f64;
    let mrays = |v: &[f64]| n / median(v.to_vec()) / 1e3;
    let ratio = |num: &[f64], den: &[f64]| {
        if num.is_empty() || den.is_empty() {
            "-".to_string()
        } else {
            format!(
                "{:.2}x",
                median(num.iter().zip(den).map(|(a, b)| a / b).collect())
            )
        }
    };
    println!(
        "{spec} {kind} ({} rays, {q:?}):\n{:28} {:>9} {:>9} {:>12} {:>13} {:>13} {:>7}",
        rays.len(),
        "path",
        "Mrays/s",
        "/full",
        "/embree fast",
        "/embree robust",
        "/embree4 fast",
        "differ"
    );
    let (fast, robust) = (&ms[paths.len()], &ms[paths.len() + 1]);
    let fast4 = &ms[paths.len() + 2];
    let names = paths
        .iter()
        .map(|(s, _, _, _)| s.as_str())
        .chain(EMBREE_MODES.iter().chain(&EMBREE4_MODES).map(|m| m.0));
    let mut rates = Vec::new();
    for (i, name) in names.enumerate() {
        if ms[i].is_empty() {
            continue;
        }
        rates.push((name.to_string(), mrays(&ms[i])));
        println!(
            "{:28} {:>9.2} {:>9} {:>12} {:>13} {:>13} {:>7}",
            name,
            mrays(&ms[i]),
            ratio(&ms[0], &ms[i]),
            ratio(fast, &ms[i]),
            ratio(robust, &ms[i]),
            ratio(fast4, &ms[i]),
            diffs.get(i).map_or("-".to_string(), |d| d.to_string()),
        );
    }
    Ok(rates)
}
