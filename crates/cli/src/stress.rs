//! `bvhtrace stress`: arguments, the devices (through the front door), the table, the
//! JSON. The cases and their judging are `bvhtrace-stress`'s.

use std::io::Write;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use bvhtrace::{Backend, Device, DriverTuning};
use bvhtrace_core::BuilderKind;
use bvhtrace_stress::{
    Backends, CASE_GROUPS, Case, CaseOptions, CaseReport, DeviceTracers, Size, run_case,
    select_cases, table_header, table_rows, wgpu_trees,
};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

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
    /// Backends, comma-separated (`bvhtrace render --help` lists them): our walks on a
    /// device are compared with their CPU twins bit for bit; the device's own ray queries
    /// (`ray-query`) are reported beside them, never failing the run. The CPU twins are
    /// always traced, to check the devices against; `cpu` reports their rows.
    #[arg(long, value_delimiter = ',', default_value = "wgpu,cpu")]
    pub backends: Vec<Backend>,
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
    /// Each device traced: `backend (adapter)`.
    devices: Vec<String>,
    /// Each backend asked for that did not open, and why.
    skipped: &'a [(String, String)],
    clean: bool,
    cases: &'a [CaseReport],
}

/// Runs the selected cases, prints the table (one row per case x backend x traversal,
/// closest-hit with the any-hit false misses/hits beside it, then notes per case), writes
/// the JSON, and fails when any run broke a guarantee (see `CaseReport::clean`).
pub fn run(args: StressArgs) -> Result<()> {
    if args.list {
        list_groups();
        return Ok(());
    }
    if args.backends.is_empty() {
        bail!("--backends lists no backend");
    }
    check_json_path(args.json.as_deref())?;
    let size = if args.quick { Size::Quick } else { Size::Full };
    let to_stdout = args.json.as_deref() == Some("-");
    let mut out: Box<dyn Write> = if to_stdout {
        Box::new(std::io::stderr())
    } else {
        Box::new(std::io::stdout())
    };
    let (backends, skipped) = open_backends(&args.backends, &mut *out)?;
    let cases = prepare_cases(&args, size)?;
    write_preamble(&mut *out, &args, size, cases.len(), &backends)?;
    let reports = run_cases(&mut *out, &cases, &backends)?;
    let failed: Vec<&str> = reports
        .iter()
        .filter(|r| !r.clean())
        .map(|r| r.name.as_str())
        .collect();
    let j = JsonReport {
        size,
        optimize: args.optimize,
        builder: args.builder.map(|b| b.name().to_string()),
        backends: args.backends.iter().map(ToString::to_string).collect(),
        devices: backends.devices.iter().map(DeviceTracers::label).collect(),
        skipped: &skipped,
        clean: failed.is_empty(),
        cases: &reports,
    };
    write_json(&mut *out, args.json.as_deref(), &j)?;
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

/// A device backend for the stress cases, opened through the front door (with the
/// environment): its adapter's name, its measures, and a factory of tracers on it.
pub fn device_tracers(backend: Backend) -> Result<DeviceTracers, String> {
    let opts = crate::backend::options(backend, None, &[]);
    let device = Device::new(&opts).map_err(|e| e.to_string())?;
    Ok(DeviceTracers {
        backend: device.backend().name().to_string(),
        name: device.name(),
        tuning: device.tuning().unwrap_or(DriverTuning::GPU),
        bit_for_bit: device.backend().bit_for_bit(),
        open: Arc::new(device.tracer_factory()),
        open_motion: device.wgpu_context().cloned().map(wgpu_trees::motion_on),
        open_curves: device.wgpu_context().cloned().map(wgpu_trees::curves_on),
    })
}

/// Opens the device backends `wanted` lists (`cpu` reports the CPU twins' rows); one that
/// cannot open is skipped with a line on `out` (and in the JSON), or fails the run when
/// nothing else is left to trace on.
fn open_backends(
    wanted: &[Backend],
    out: &mut dyn Write,
) -> Result<(Backends, Vec<(String, String)>)> {
    let mut backends = Backends::new(wanted.contains(&Backend::Cpu));
    let mut skipped = Vec::new();
    for &backend in wanted.iter().filter(|&&b| b != Backend::Cpu) {
        match device_tracers(backend) {
            Ok(d) => backends = backends.with(d),
            Err(note) => {
                writeln!(out, "SKIP {backend}: {note}")?;
                skipped.push((backend.to_string(), note));
            }
        }
    }
    if !backends.cpu && backends.devices.is_empty() {
        let why: Vec<String> = skipped.iter().map(|(b, n)| format!("{b}: {n}")).collect();
        bail!("no backend to trace on ({})", why.join("; "));
    }
    Ok((backends, skipped))
}

/// The selected cases at `size`, with `--optimize` and `--builder` applied.
fn prepare_cases(args: &StressArgs, size: Size) -> Result<Vec<Case>> {
    let opts = CaseOptions::new(size).with_scenes(crate::geometry::shared_scenes_dir());
    let mut cases = select_cases(&args.case, &opts).map_err(anyhow::Error::msg)?;
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
    backends: &Backends,
) -> Result<()> {
    let mut names: Vec<String> = backends.devices.iter().map(DeviceTracers::label).collect();
    if backends.cpu {
        names.insert(0, "cpu".into());
    }
    writeln!(
        out,
        "bvhtrace stress: {} cases ({:?} size{}{}), backends: {}",
        cases,
        size,
        if args.optimize {
            ", optimised trees"
        } else {
            ""
        },
        args.builder
            .map_or(String::new(), |b| format!(", builder {b}")),
        names.join(" ")
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
fn write_json(out: &mut dyn Write, path: Option<&str>, report: &JsonReport<'_>) -> Result<()> {
    let Some(path) = path else {
        return Ok(());
    };
    let text = serde_json::to_string_pretty(report)?;
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
