//! `bvhtrace stress`: arguments, the table, the JSON.

use std::io::Write;

use anyhow::{Context, Result, bail};
use bvhtrace_core::BuilderKind;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use crate::report::{table_header, table_rows};
use crate::runner::{Backends, CaseReport, DeviceTracers, run_case};
use crate::{CASE_GROUPS, Case, Size, select_cases};

/// Arguments of `bvhtrace stress`.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct StressArgs {
    /// Cases to run: a case name (`offset-1e5`), a group (`offset`, `watertight`, ...), or
    /// a comma list; repeatable. All cases when omitted (`--list` shows them).
    #[arg(long = "case", value_name = "NAME", value_delimiter = ',')]
    pub case: Vec<String>,
    /// Also write the full report as JSON to FILE (`-`: standard output; the table then
    /// goes to standard error).
    #[arg(long, value_name = "FILE")]
    pub json: Option<String>,
    /// Backends, comma-separated: `gpu` (the WGSL kernels through wgpu, when a Vulkan
    /// adapter exists), `vk` (the same kernels on raw Vulkan through ash), `cpu` (their CPU
    /// twins), `ray-query` (the device's own ray queries, when it has them: reported
    /// beside ours, never failing the run). The CPU twins are always traced to check the
    /// GPU against.
    #[arg(long, value_delimiter = ',', default_value = "gpu,cpu")]
    pub backends: Vec<String>,
    /// Small sizes (what the test suite runs): seconds instead of minutes.
    #[arg(long)]
    pub quick: bool,
    /// List the case groups and exit.
    #[arg(long)]
    pub list: bool,
    /// Optimise every case's trees by reinsertion (`BuildOptions::optimize`) before
    /// tracing.
    #[arg(long)]
    pub optimize: bool,
    /// Build every case's BVH with this builder (`sah`, `sweep-sah`, `median`, `midpoint`,
    /// `sbvh`); a case that picks its own (the deep midpoint chain) keeps it. Default:
    /// each case's own (binned SAH).
    #[arg(long, value_name = "NAME")]
    pub builder: Option<BuilderKind>,
}

#[derive(Serialize)]
struct JsonReport<'a> {
    size: Size,
    optimize: bool,
    builder: Option<String>,
    backends: Vec<String>,
    gpu: Option<String>,
    gpu_note: Option<String>,
    vk: Option<String>,
    vk_note: Option<String>,
    ray_query: Option<String>,
    ray_query_note: Option<String>,
    clean: bool,
    cases: &'a [CaseReport],
}

/// A device backend `bvhtrace stress` asks its caller for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StressDevice {
    /// The WGSL kernels through wgpu (rows `gpu`).
    Gpu,
    /// The same kernels on raw Vulkan through ash (rows `vk`).
    Vk,
    /// The device's own ray queries through wgpu (rows `ray-query`).
    RayQuery,
}

/// Runs the selected cases, prints the table (one row per case x backend x traversal,
/// closest-hit with the any-hit false misses/hits beside it, then notes per case), writes
/// the JSON, and fails when any run broke a guarantee (see `CaseReport::clean`). `devices`
/// opens each device backend `--backends` asks for (or says why it cannot): this crate
/// opens none itself.
pub fn run(
    args: StressArgs,
    devices: &dyn Fn(StressDevice) -> Result<DeviceTracers, String>,
) -> Result<()> {
    if args.list {
        list_groups();
        return Ok(());
    }
    let wanted = Wanted::parse(&args.backends)?;
    check_json_path(args.json.as_deref())?;
    let size = if args.quick { Size::Quick } else { Size::Full };
    let to_stdout = args.json.as_deref() == Some("-");
    let mut out: Box<dyn Write> = if to_stdout {
        Box::new(std::io::stderr())
    } else {
        Box::new(std::io::stdout())
    };
    let backends = open_backends(wanted, devices, &mut *out)?;
    let cases = prepare_cases(&args, size)?;
    write_preamble(&mut *out, &args, size, cases.len(), wanted.cpu, &backends)?;
    let reports = run_cases(&mut *out, &cases, &backends)?;
    let failed: Vec<&str> = reports
        .iter()
        .filter(|r| !r.clean())
        .map(|r| r.name.as_str())
        .collect();
    write_json(
        &mut *out,
        &args,
        size,
        &backends,
        &reports,
        failed.is_empty(),
    )?;
    if !failed.is_empty() {
        bail!(
            "{} case(s) broke a guarantee: {} (see the examples under their rows)",
            failed.len(),
            failed.join(", ")
        );
    }
    write_summary(&mut *out, &reports)
}

/// Prints the case groups, one a line with what it holds.
fn list_groups() {
    for (g, d) in CASE_GROUPS {
        println!("{g:<16} {d}");
    }
}

/// The backends `--backends` asks for.
#[derive(Clone, Copy)]
struct Wanted {
    cpu: bool,
    gpu: bool,
    vk: bool,
    rq: bool,
}

impl Wanted {
    /// Reads `--backends`; an error for an unknown name or when none is named.
    fn parse(names: &[String]) -> Result<Wanted> {
        let (mut cpu, mut gpu, mut vk, mut rq) = (false, false, false, false);
        for b in names {
            match b.trim() {
                "cpu" => cpu = true,
                "gpu" => gpu = true,
                "vk" | "vulkan" | "ash" => vk = true,
                "ray-query" | "rq" => rq = true,
                "" => {}
                other => bail!("unknown backend '{other}' (expected gpu, vk, cpu, ray-query)"),
            }
        }
        if !cpu && !gpu && !vk && !rq {
            bail!("--backends lists no backend (expected gpu, vk, cpu, ray-query)");
        }
        Ok(Wanted { cpu, gpu, vk, rq })
    }
}

/// Fails when the JSON report's file (other than `-`) cannot be written.
fn check_json_path(json: Option<&str>) -> Result<()> {
    // An unwritable JSON path fails now, not after minutes of work.
    if let Some(path) = json.filter(|p| *p != "-") {
        let tmp = format!("{path}.tmp");
        std::fs::write(&tmp, b"")
            .with_context(|| format!("cannot write the JSON report {path}"))?;
        let _ = std::fs::remove_file(&tmp);
    }
    Ok(())
}

/// Opens the wanted device backends through `devices`; one that cannot open is skipped
/// with a line on `out`, or fails the run when nothing else is left to trace on.
fn open_backends(
    wanted: Wanted,
    devices: &dyn Fn(StressDevice) -> Result<DeviceTracers, String>,
    out: &mut dyn Write,
) -> Result<Backends> {
    let Wanted { cpu, gpu, vk, rq } = wanted;
    let mut backends = Backends::new(cpu);
    if gpu {
        backends = backends.with_gpu(devices(StressDevice::Gpu));
    }
    if vk {
        backends = backends.with_vulkan(devices(StressDevice::Vk));
    }
    if rq {
        backends = backends.with_ray_queries(devices(StressDevice::RayQuery));
        if let Some(note) = &backends.rq_note {
            writeln!(out, "SKIP ray-query: {note}")?;
        }
    }
    if gpu && backends.gpu.is_none() {
        let note = backends.gpu_note.clone().unwrap_or_default();
        if !cpu && backends.vk.is_none() {
            bail!("no GPU: {note}");
        }
        writeln!(out, "SKIP gpu: {note}")?;
    }
    if vk && backends.vk.is_none() {
        let note = backends.vk_note.clone().unwrap_or_default();
        if !cpu && backends.gpu.is_none() {
            bail!("no Vulkan device for ash: {note}");
        }
        writeln!(out, "SKIP vk: {note}")?;
    }
    Ok(backends)
}

/// The selected cases at `size`, with `--optimize` and `--builder` applied.
fn prepare_cases(args: &StressArgs, size: Size) -> Result<Vec<Case>> {
    let mut cases = select_cases(&args.case, size).map_err(anyhow::Error::msg)?;
    for c in &mut cases {
        c.build.optimize |= args.optimize;
        // Only the cases built with the default builder: a deliberate choice stays.
        if let Some(b) = args.builder
            && c.build.builder == BuilderKind::default()
        {
            c.build.builder = b;
        }
    }
    Ok(cases)
}

/// Writes what runs on what, the legend and the table's header.
fn write_preamble(
    out: &mut dyn Write,
    args: &StressArgs,
    size: Size,
    cases: usize,
    cpu: bool,
    backends: &Backends,
) -> Result<()> {
    writeln!(
        out,
        "bvhtrace stress: {} cases ({:?} size{}{}), backends: {}{}{}",
        cases,
        size,
        if args.optimize {
            ", optimised trees"
        } else {
            ""
        },
        args.builder
            .map_or(String::new(), |b| format!(", builder {b}")),
        if cpu { "cpu " } else { "" },
        backends
            .gpu_name()
            .map_or(String::new(), |n| format!("gpu ({n}) ")),
        backends
            .vk_name()
            .map_or(String::new(), |n| format!("vk ({n})"))
    )?;
    writeln!(
        out,
        "a/b = wrong / f32-indeterminate (vs the f64 oracle; brute = vs the f32 brute force); escape = misses from inside a closed mesh (closest + any); self-hit 0/off = self-hits/rays without / with the origin offset"
    )?;
    writeln!(out, "{}", table_header())?;
    Ok(())
}

/// Runs each case on `backends` under a progress bar, writing its rows as it finishes.
fn run_cases(out: &mut dyn Write, cases: &[Case], backends: &Backends) -> Result<Vec<CaseReport>> {
    let pb = ProgressBar::new(cases.len() as u64);
    pb.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} {msg} ({elapsed})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut reports = Vec::with_capacity(cases.len());
    for case in cases {
        pb.set_message(case.name.clone());
        let rep = run_case(case, backends);
        pb.suspend(|| -> Result<()> {
            for line in table_rows(&rep) {
                writeln!(out, "{line}")?;
            }
            out.flush()?;
            Ok(())
        })?;
        reports.push(rep);
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(reports)
}

/// Writes the JSON report when `--json` asks for one: to standard output for `-`, else
/// to its file.
fn write_json(
    out: &mut dyn Write,
    args: &StressArgs,
    size: Size,
    backends: &Backends,
    reports: &[CaseReport],
    clean: bool,
) -> Result<()> {
    let Some(path) = &args.json else {
        return Ok(());
    };
    let j = JsonReport {
        size,
        optimize: args.optimize,
        builder: args.builder.map(|b| b.name().to_string()),
        backends: args.backends.clone(),
        gpu: backends.gpu_name(),
        gpu_note: backends.gpu_note.clone(),
        vk: backends.vk_name(),
        vk_note: backends.vk_note.clone(),
        ray_query: backends.rq_name(),
        ray_query_note: backends.rq_note.clone(),
        clean,
        cases: reports,
    };
    let text = serde_json::to_string_pretty(&j)?;
    if path == "-" {
        println!("{text}");
    } else {
        // Through a temporary file beside it, so a failed write leaves no half file.
        let tmp = format!("{path}.tmp");
        std::fs::write(&tmp, text).with_context(|| format!("writing {tmp}"))?;
        std::fs::rename(&tmp, path).with_context(|| format!("renaming {tmp} to {path}"))?;
        writeln!(out, "wrote {path}")?;
    }
    Ok(())
}

/// Writes the closing line for a clean run, naming the skipped cases.
fn write_summary(out: &mut dyn Write, reports: &[CaseReport]) -> Result<()> {
    let skipped: Vec<&str> = reports
        .iter()
        .filter(|r| r.skipped.is_some())
        .map(|r| r.name.as_str())
        .collect();
    if skipped.is_empty() {
        writeln!(out, "all cases clean")?;
    } else {
        writeln!(
            out,
            "all cases clean ({} skipped: {})",
            skipped.len(),
            skipped.join(", ")
        )?;
    }
    Ok(())
}
