//! `bvhtrace`: render scenes through the BVH on the GPU or CPU, inspect them, benchmark.

mod backend;
mod bench;
mod cost;
mod embree;
mod geometry;
mod motion;
mod output;
mod path;
mod render;
mod shade;
mod stress;
mod tuned;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// Build a SAH BVH on the CPU and trace rays through it with WGSL kernels (wgpu/Vulkan)
/// or the CPU reference traversal.
#[derive(Parser)]
#[command(name = "bvhtrace", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene to a PNG (and optionally JSON stats).
    Render(render::RenderArgs),
    /// Print what a scene contains and the quality of its BVH.
    Info(render::InfoArgs),
    /// Write a scene's triangles and primary rays for another tracer (see crates/cli/embree).
    Dump(render::DumpArgs),
    /// Error against run time for every configuration (builder, traversal, backend, ray
    /// kind, precision), with a table, JSON/CSV and an error-vs-time plot.
    Bench(bench::BenchArgs),
    /// Benchmark the builders: build time, SAH cost in both conventions, box and triangle
    /// tests per ray (primary, shadow, diffuse), CPU traversal speed.
    #[command(long_about = bench::build::long_about())]
    BenchBuild(bench::build::BenchBuildArgs),
    /// Benchmark the traversals on the GPU beside the CPU reference, on the same rays.
    ///
    /// Columns: Mrays/s on the GPU (timestamp queries) and wall (upload and readback
    /// included), the CPU twin's Mrays/s, box tests and triangle tests per ray, box tests
    /// against the first traversal (`n/full`), and the GPU's speed against the first
    /// traversal on the GPU (`GPU/full`), against its own CPU twin (`GPU/twin`) and against
    /// the first traversal's CPU twin, the CPU reference when that is full-stack
    /// (`GPU/CPU`). The ratios are medians of per-round ratios.
    BenchTrace(bench::BenchTraceArgs),
    /// What moving things costs: a refit after every vertex of a mesh moved, beside a full
    /// rebuild (SAH cost and box tests per ray of both), and a top-level rebuild of many
    /// instances beside building both levels.
    BenchRefit(bench::refit::BenchRefitArgs),
    /// Time every walk in every storage on the device (primary rays of one scene, ranked
    /// by wall time) and print them beside the walk and storage the device takes by
    /// default.
    Tune(bench::tune::TuneArgs),
    /// Numerical stress cases (watertightness, huge offsets and scales, slivers,
    /// coincident and degenerate triangles, extreme rays, deep trees) on the CPU twins and
    /// the GPU kernels, against the f64 oracle; fails when a guarantee is broken.
    Stress(stress::StressArgs),
    /// A GPU cost model that needs no GPU: loop trips per warp, lane utilisation and bytes
    /// per ray of each walk, from the CPU walks over rays grouped in warps.
    #[command(long_about = cost::long_about())]
    Cost(cost::CostArgs),
}

fn main() {
    backend::private_runtime_dir();
    let cli = Cli::parse();
    let result: Result<()> = match cli.command {
        // The path tracer makes, shades and sums its rays on the device: a pipeline of its own.
        // Blurred renders and scenes with curves refuse it in `render`.
        Command::Render(a)
            if a.shade == bvhtrace_shade::Shade::Path
                && a.shutter.shutter.is_none()
                && !(a.scene.scene.as_deref()).is_some_and(bvhtrace_scene::has_curves) =>
        {
            path::render(a)
        }
        Command::Render(a) => render::render(a),
        Command::Info(a) => render::info(a),
        Command::Dump(a) => render::dump(a),
        Command::Bench(a) if a.converge.converge => bench::converge::run(&a),
        Command::Bench(a) => bench::matrix::run(&a),
        Command::BenchBuild(a) => bench::build::run(a),
        Command::BenchTrace(a) => a.check().and_then(|()| match a.cpu_only {
            true => bench::trace_cpu::run(&a),
            false => bench::trace::run(&a),
        }),
        Command::BenchRefit(a) => bench::refit::run(a),
        Command::Tune(a) => bench::tune::run(&a),
        Command::Stress(a) => stress::run(a),
        Command::Cost(a) => cost::cost(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
