//! `bvhtrace cost`: a GPU cost model that needs no GPU.
//!
//! Each walk runs on the CPU over the rays `bvhtrace bench` traces (primary, shadow and
//! diffuse), grouped in warps as a GPU groups them ([`bvhtrace_core::cost`]); the table
//! gives each walk's loop trips per warp, lane utilisation, tests and bytes per ray, and
//! its ratios against the first walk listed.

use std::fmt::Write as _;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use bvhtrace_core::cost::{WARP, WarpCost, warp_cost};
use bvhtrace_core::{Query, Ray, TraceOptions, Traversal};
use serde::Serialize;

use crate::bench::ray_sets;
use crate::output::JsonOut;

/// What the model assumes, in one paragraph: the `--help` text and the JSON's
/// `assumptions` field (the core module's docs say it at length).
pub const ASSUMPTIONS: &str = "The model runs each walk on the CPU, step for step as the \
kernels do, over rays grouped as a GPU runs them: warps of 32 lanes, one ray per lane, \
32 consecutive rays per warp (for primary rays, 32 neighbouring pixels of a row). A warp \
runs in lock step until its slowest lane is done, so it costs that lane's loop trips \
(trips/warp); lane utilisation is the share of lane-trips doing work. Trips of different \
walks differ in cost (a full-stack trip tests two boxes, a stackless one one, a wide one up \
to eight), so a lane's work is its trips plus 0.65 trips per box it tests, a weight fitted \
to an NVIDIA H200's walks; the warp's work is its slowest lane's (work/warp), the model's \
estimate of its time. Every load is \
counted as going to memory, with no cache and no coalescing: 32 bytes per binary box \
tested, 80 per wide node, 4 per escape link followed, 48 per triangle tested. So the \
bytes rank walks by the traffic they cause rather than predicting bandwidth. See the docs \
of bvhtrace_core::cost (crates/core/src/cost.rs).";

/// The subcommand's long help: what it does, then [`ASSUMPTIONS`].
pub fn long_about() -> String {
    format!(
        "The GPU cost model, without a GPU: for each scene, ray kind (primary; shadow, \
         any hit; diffuse) and walk, loop trips and work per warp, trips per ray, lane \
         utilisation, box and triangle tests per ray and the bytes of nodes and triangles \
         loaded per ray, with the work/warp and bytes/ray ratios against the first walk \
         listed.\n\n\
         {ASSUMPTIONS}"
    )
}

/// `bvhtrace cost`.
#[derive(clap::Args)]
pub struct CostArgs {
    /// Scenes: .gltf/.glb files or `builtin:` names (default: bunny_69k and igea from
    /// ../shared/scenes).
    pub scenes: Vec<String>,
    #[command(flatten)]
    pub primary: crate::render::PrimarySize,
    /// Walks to compare, comma-separated (`full-stack`, `stackless`, `short-stack:K`,
    /// `wide`); the ratio columns divide by the first.
    #[arg(
        long,
        value_name = "WALK,...",
        value_delimiter = ',',
        default_value = "full-stack,stackless,short-stack:8,wide"
    )]
    pub walks: Vec<Traversal>,
    /// Write the figures as JSON (`-` for stdout; the table then goes to stderr).
    #[arg(long, value_name = "FILE|-")]
    pub json: Option<String>,
    #[command(flatten)]
    pub build: crate::render::BuildArgs,
}

/// The whole JSON document.
#[derive(Serialize)]
struct Report {
    /// Lanes per warp.
    warp: usize,
    /// [`ASSUMPTIONS`].
    assumptions: &'static str,
    /// One entry per scene, in the order given.
    scenes: Vec<SceneReport>,
}

/// One scene's figures.
#[derive(Serialize)]
struct SceneReport {
    /// The scene as given on the command line.
    scene: String,
    /// Triangles after flattening the scene.
    triangles: usize,
    /// Binary upload for the full-stack walk (nodes and triangles) per triangle.
    binary_bytes_per_triangle: f64,
    /// Wide upload (nodes and triangles) per triangle.
    wide_bytes_per_triangle: f64,
    /// Ray kinds in order (primary, shadow, diffuse), walks in the order given.
    rows: Vec<CostRow>,
}

/// One walk on one ray kind.
#[derive(Serialize)]
struct CostRow {
    /// `primary`, `shadow` or `diffuse`.
    rays: &'static str,
    /// The walk (as the other commands print it, e.g. `short-stack(8)`).
    walk: String,
    /// Rays traced.
    ray_count: usize,
    /// Warps of [`WARP`] rays.
    warps: usize,
    /// Mean over warps of the slowest lane's loop trips.
    trips_per_warp: f64,
    /// Mean over warps of the slowest lane's work (trips plus `BOX_TEST_TRIPS` per box
    /// test): the model's time per warp.
    work_per_warp: f64,
    /// Mean loop trips per ray.
    trips_per_ray: f64,
    /// Lane-trips doing work over lane-trips spent (0..=1).
    lane_utilisation: f64,
    /// Box tests per ray.
    nodes_per_ray: f64,
    /// Triangle tests per ray.
    tris_per_ray: f64,
    /// Bytes of nodes and escape links loaded per ray.
    node_bytes_per_ray: f64,
    /// Bytes of triangles loaded per ray.
    triangle_bytes_per_ray: f64,
    /// `node_bytes_per_ray + triangle_bytes_per_ray`.
    bytes_per_ray: f64,
    /// `trips_per_warp` over the first walk's on the same rays (null when that is 0).
    trips_per_warp_ratio: Option<f64>,
    /// `work_per_warp` over the first walk's on the same rays (null when that is 0).
    work_per_warp_ratio: Option<f64>,
    /// `bytes_per_ray` over the first walk's on the same rays (null when that is 0).
    bytes_per_ray_ratio: Option<f64>,
}

impl CostRow {
    /// The row for `walk` on `kind` rays, with ratios against `first` (the first walk's
    /// cost on the same rays).
    fn new(kind: &'static str, walk: Traversal, c: &WarpCost, first: &WarpCost) -> Self {
        // An empty ray set (no primary hits, so no diffuse rays) costs 0: no ratio then.
        let ratio = |a: f64, b: f64| (b > 0.0).then(|| a / b);
        CostRow {
            rays: kind,
            walk: walk.to_string(),
            ray_count: c.rays,
            warps: c.warps,
            trips_per_warp: c.trips_per_warp,
            work_per_warp: c.work_per_warp,
            trips_per_ray: c.trips_per_ray,
            lane_utilisation: c.lane_utilisation,
            nodes_per_ray: c.nodes_per_ray,
            tris_per_ray: c.tris_per_ray,
            node_bytes_per_ray: c.node_bytes_per_ray,
            triangle_bytes_per_ray: c.triangle_bytes_per_ray,
            bytes_per_ray: c.bytes_per_ray(),
            trips_per_warp_ratio: ratio(c.trips_per_warp, first.trips_per_warp),
            work_per_warp_ratio: ratio(c.work_per_warp, first.work_per_warp),
            bytes_per_ray_ratio: ratio(c.bytes_per_ray(), first.bytes_per_ray()),
        }
    }
}

/// `bvhtrace cost`.
pub fn cost(args: CostArgs) -> Result<()> {
    let (w, h) = args.primary.size;
    if args.walks.is_empty() {
        bail!("--walks: give at least one walk");
    }
    // Reserve the JSON destination before any work, so a bad path fails at once.
    let json_out = args.json.as_deref().map(JsonOut::create).transpose()?;
    let to_stderr = matches!(json_out, Some(JsonOut::Stdout));
    let specs = crate::bench::scene_specs(&args.scenes)?;
    let mut report = Report {
        warp: WARP,
        assumptions: ASSUMPTIONS,
        scenes: Vec::new(),
    };
    let device = args.build.build_device(None)?;
    let builder = args.build.tree_builder(device.as_ref())?;
    for spec in &specs {
        let (scene_report, text) = cost_scene(spec, w, h, &args.walks, &builder)?;
        // Each scene's table as soon as it is done: the big scenes take a while.
        if to_stderr {
            eprint!("{text}");
        } else {
            print!("{text}");
        }
        report.scenes.push(scene_report);
    }
    if let Some(j) = json_out {
        j.write(&serde_json::to_value(&report)?)?;
    }
    Ok(())
}

/// Loads one scene, builds its BVH as `opts` say (and its wide layout), makes the rays and
/// runs every walk on every ray kind; returns the figures and the printed table.
fn cost_scene(
    spec: &str,
    w: u32,
    h: u32,
    walks: &[Traversal],
    builder: &crate::geometry::TreeBuilder,
) -> Result<(SceneReport, String)> {
    let pb = crate::output::progress_bar(
        (3 * walks.len()) as u64,
        "{msg:48} [{bar:30}] {pos}/{len} ({elapsed})",
    );
    pb.enable_steady_tick(Duration::from_millis(200));
    pb.set_message(format!("{spec}: loading"));
    // The scene error already names the file (or builtin spec).
    let scene = crate::geometry::load_triangle_scene(spec)?;
    let tris = scene
        .flattened_triangles()
        .with_context(|| format!("{spec}: cannot flatten the scene's triangles"))?;
    pb.set_message(format!("{spec}: building the BVH"));
    let mut bvh = builder
        .build(&tris)
        .map_err(|e| anyhow::anyhow!("{spec}: cannot build a BVH: {e}"))?;
    // Always built: the header prints the wide upload size whichever walks run.
    bvh.build_wide();
    pb.set_message(format!("{spec}: making rays"));
    let cam = scene.camera_or_frame(w as f32 / h as f32);
    let sets = ray_sets(&tris, &bvh, &cam, w, h);
    let kinds: [(&'static str, &[Ray], Query); 3] = [
        ("primary", &sets.primary, Query::Closest),
        ("shadow", &sets.shadow, Query::Any),
        ("diffuse", &sets.diffuse, Query::Closest),
    ];

    let mut rows = Vec::new();
    for (kind, rays, query) in kinds {
        let mut first = None;
        for &walk in walks {
            pb.set_message(format!("{spec}: {kind} {walk}"));
            let c = warp_cost(&bvh, rays, &TraceOptions::new(walk, query));
            let base = *first.get_or_insert(c);
            rows.push(CostRow::new(kind, walk, &c, &base));
            pb.inc(1);
        }
    }
    pb.finish_and_clear();

    let n = tris.len().max(1) as f64;
    let (nodes, _, triangles) = bvh.byte_sizes();
    let (wide_nodes, wide_tris) = bvh
        .wide()
        .map(|wb| wb.byte_sizes())
        .context("the wide layout was not built")?;
    let report = SceneReport {
        scene: spec.to_string(),
        triangles: tris.len(),
        binary_bytes_per_triangle: (nodes + triangles) as f64 / n,
        wide_bytes_per_triangle: (wide_nodes + wide_tris) as f64 / n,
        rows,
    };
    let text = table(
        &report,
        w,
        h,
        [&sets.primary, &sets.shadow, &sets.diffuse].map(|r| r.len()),
        walks[0],
    );
    Ok((report, text))
}

/// One scene's header and table.
fn table(r: &SceneReport, w: u32, h: u32, counts: [usize; 3], first: Traversal) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\n{}: {} triangles; rays: {} primary ({w}x{h}), {} shadow, {} diffuse; warps of {WARP}",
        r.scene, r.triangles, counts[0], counts[1], counts[2]
    );
    let _ = writeln!(
        s,
        "upload: binary (full-stack: nodes + triangles) {:.1} B/triangle, wide {:.1} B/triangle; ratios against {first}",
        r.binary_bytes_per_triangle, r.wide_bytes_per_triangle
    );
    let _ = writeln!(
        s,
        "{:8} {:16} {:>10} {:>9} {:>9} {:>6} {:>9} {:>8} {:>10} {:>9} {:>9} {:>9} {:>9}",
        "rays",
        "walk",
        "trips/warp",
        "work/warp",
        "trips/ray",
        "lanes%",
        "boxes/ray",
        "tris/ray",
        "node B/ray",
        "tri B/ray",
        "B/ray",
        "work/1st",
        "B/1st"
    );
    let ratio = |x: Option<f64>| x.map_or("-".to_string(), |x| format!("{x:.2}x"));
    for row in &r.rows {
        let _ = writeln!(
            s,
            "{:8} {:16} {:>10.1} {:>9.1} {:>9.1} {:>6.1} {:>9.1} {:>8.2} {:>10.0} {:>9.0} {:>9.0} {:>9} {:>9}",
            row.rays,
            row.walk,
            row.trips_per_warp,
            row.work_per_warp,
            row.trips_per_ray,
            row.lane_utilisation * 100.0,
            row.nodes_per_ray,
            row.tris_per_ray,
            row.node_bytes_per_ray,
            row.triangle_bytes_per_ray,
            row.bytes_per_ray,
            ratio(row.work_per_warp_ratio),
            ratio(row.bytes_per_ray_ratio)
        );
    }
    s
}
