//! `bvhtrace stress` without the CLI crate:
//! `cargo run --release -p bvhtrace-stress --example stress -- --quick --case offset`.

use clap::Parser;

/// Numerical stress cases on the CPU twins and the GPU kernels.
#[derive(Parser)]
#[command(name = "stress")]
struct Cli {
    #[command(flatten)]
    args: bvhtrace_stress::StressArgs,
}

fn main() {
    if let Err(e) = bvhtrace_stress::run(Cli::parse().args) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
