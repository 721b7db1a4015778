//! `bvhtrace tune`: every walk in every storage on the device the front door opens, timed
//! on a scene's primary rays (ranked by wall time; the device's own time beside it),
//! beside the walk and storage the device takes by default
//! (`DriverTuning::walk` and `DriverTuning::storage`, set per kind of device from
//! measurements): what a default for this adapter would be, measured here.

use anyhow::{Result, bail};
use bvhtrace::{BvhStorage, OpenOptions, TraceOptions, Traversal};
use serde_json::json;

use super::{load, median, primary_rays};
use crate::backend::{self, Backend};

/// `bvhtrace tune`.
#[derive(clap::Args)]
pub struct TuneArgs {
    /// The scene whose primary rays are traced (a .gltf/.glb file or a `builtin:` name;
    /// default: the Cornell box).
    pub scene: Option<String>,
    /// The device backend: gpu (wgpu) or vulkan (the same kernels through ash).
    #[arg(long, default_value = "gpu")]
    pub backend: Backend,
    /// Adapter name substring (overrides $BVHTRACE_ADAPTER).
    #[arg(long)]
    pub adapter: Option<String>,
    /// Timed traces of each walk (the median is kept; one untimed trace first).
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub runs: u32,
    /// Primary rays, WxH.
    #[arg(long, default_value = "1024x768", value_parser = crate::render::parse_size)]
    pub size: (u32, u32),
    /// Print as JSON.
    #[arg(long)]
    pub json: bool,
    /// Remember the fastest walk and storage for this adapter
    /// (`$XDG_CACHE_HOME/bvhtrace/tuned.json`): `render` then takes them there when no
    /// `--traversal` or `--storage` is given.
    #[arg(long)]
    pub save: bool,
}

/// One walk in one storage, timed.
struct Timed {
    walk: Traversal,
    storage: BvhStorage,
    /// Median milliseconds on the device (timestamps) when it measures them, and of wall.
    device_ms: Option<f64>,
    wall_ms: f64,
}

impl Timed {
    /// What the ranking goes by: the wall time a trace costs its caller (the rays up, the
    /// walk, the rays a CPU driver's trip budget leaves finished on the host, the hits
    /// back), which the device's own time can rank otherwise.
    fn ms(&self) -> f64 {
        self.wall_ms
    }
}

/// `bvhtrace tune`.
pub fn run(args: &TuneArgs) -> Result<()> {
    if !matches!(args.backend, Backend::Wgpu | Backend::Vulkan) {
        bail!("tune measures our walks on a device: --backend gpu or vulkan");
    }
    let spec = args
        .scene
        .as_deref()
        .unwrap_or(bvhtrace_scene::DEFAULT_SCENE);
    let (tris, scene, _) = load(spec)?;
    let bvh = bvhtrace_core::FlatBvh::build(&tris, &Default::default())?.with_wide();
    let (w, h) = args.size;
    let rays = primary_rays(&scene, w, h);
    let device = backend::device(&backend::options(
        args.backend,
        args.adapter.as_deref(),
        &[],
    ))?;
    let tuning = device.tuning().unwrap_or(bvhtrace::DriverTuning::GPU);
    let mut rows = Vec::new();
    for walk in Traversal::ALL {
        for storage in BvhStorage::ALL {
            let opts = OpenOptions {
                traversals: vec![walk],
                storage: Some(storage),
                ..OpenOptions::default()
            };
            let opened = device.open(&bvh, &opts)?;
            if opened.storage != Some(storage) {
                continue;
            }
            let trace = TraceOptions::closest(walk);
            opened.tracer.trace(&rays, &trace)?;
            let (mut device_ms, mut wall_ms) = (Vec::new(), Vec::new());
            for _ in 0..args.runs {
                let out = opened.tracer.trace(&rays, &trace)?;
                device_ms.extend(out.gpu_ms);
                wall_ms.push(out.wall_ms);
            }
            rows.push(Timed {
                walk,
                storage,
                device_ms: (!device_ms.is_empty()).then(|| median(device_ms)),
                wall_ms: median(wall_ms),
            });
        }
    }
    let Some(best) = rows.iter().min_by(|a, b| a.ms().total_cmp(&b.ms())) else {
        bail!("no walk opened on {}", device.name());
    };
    let default = rows
        .iter()
        .find(|r| r.walk == tuning.walk && r.storage == tuning.storage);
    let n = rays.len() as f64;
    if args.save {
        let tuned = crate::tuned::Tuned {
            walk: best.walk,
            storage: best.storage,
        };
        let detail = json!({ "scene": spec, "rays": rays.len(), "wall_ms": best.wall_ms });
        let path = crate::tuned::save(&device.name(), tuned, detail)?;
        eprintln!(
            "saved to {}: render takes them on this adapter",
            path.display()
        );
    }
    if args.json {
        let row = |r: &Timed| {
            json!({
                "walk": r.walk.to_string(), "storage": r.storage.name(),
                "device_ms": r.device_ms, "wall_ms": r.wall_ms,
                "mrays_per_s": n / r.ms() / 1e3,
                "device_mrays_per_s": r.device_ms.map(|ms| n / ms / 1e3),
            })
        };
        let v = json!({
            "device": device.name(), "scene": spec, "rays": rays.len(),
            "measured": rows.iter().map(row).collect::<Vec<_>>(),
            "fastest": row(best),
            "default": { "walk": tuning.walk.to_string(), "storage": tuning.storage.name() },
            "default_over_fastest": default.map(|d| d.ms() / best.ms()),
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    print_table(args, &device.name(), spec, &rows, n);
    let said = |r: &Timed| format!("{} in {} storage", r.walk, r.storage.name());
    println!("fastest here: {}", said(best));
    match default {
        Some(d) => println!(
            "this device's default: {} ({:.2}x the fastest's time){}",
            said(d),
            d.ms() / best.ms(),
            if d.walk == best.walk && d.storage == best.storage {
                ""
            } else {
                "; pass --traversal to take another, or tune --save"
            }
        ),
        None => println!(
            "this device's default: {} in {} storage (not opened here)",
            tuning.walk,
            tuning.storage.name()
        ),
    }
    Ok(())
}

/// The table of every walk and storage timed.
fn print_table(args: &TuneArgs, device: &str, spec: &str, rows: &[Timed], n: f64) {
    println!(
        "{spec}: {}x{} primary rays, median of {} on {device}",
        args.size.0, args.size.1, args.runs
    );
    println!(
        "{:14} {:8} {:>12} {:>12}",
        "walk", "storage", "device Mr/s", "wall Mr/s"
    );
    for r in rows {
        let device = r
            .device_ms
            .map_or("-".to_string(), |ms| format!("{:.2}", n / ms / 1e3));
        println!(
            "{:14} {:8} {:>12} {:>12.2}",
            r.walk.to_string(),
            r.storage.name(),
            device,
            n / r.wall_ms / 1e3
        );
    }
}
