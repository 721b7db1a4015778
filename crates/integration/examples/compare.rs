//! ash against wgpu on the same scene and the same rays: dispatch time from timestamp
//! queries and wall time per batch, medians of `--runs` runs after one warm-up.
//!
//! ```sh
//! LP_NUM_THREADS=2 cargo run --release -p bvhtrace-integration --example compare -- \
//!     [SCENE ...] [--runs 5] [--size 1024x768] [--traversal full-stack]...
//! ```
//!
//! Scenes default to `bunny_69k` and `igea` from the shared scenes folder. Rays: primary
//! rays from `bvhtrace render`'s default camera (the scene's camera, else the framing one).
//! Both backends use the BVH in storage buffers (the same kernel); wgpu with textures (its
//! default on CPU adapters) is listed too. The hits of all three are checked to be equal.
//! Both contexts use their device's [`bvhtrace_vk::DriverTuning`]: on lavapipe,
//! `DISPATCH_THREADS` is the CPU count (lavapipe's own default thread count; no
//! environment variable is read). With `LP_NUM_THREADS` set to another count the hits are
//! the same; only the sharing of ray blocks among lavapipe's threads is less even.

use std::error::Error;

use bvhtrace_core::{BuildOptions, FlatBvh, Traversal};
use bvhtrace_gpu::{BvhStorage, GpuBvh, GpuContext, UploadOptions};
use bvhtrace_vk::core::TraceOptions;
use bvhtrace_vk::{AdapterChoice, Tracer, UploadOptions as VkUploadOptions, VkBvh, VkContext};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn Error>> {
    let mut scenes = Vec::new();
    let mut runs = 5usize;
    let (mut w, mut h) = (1024u32, 768u32);
    let mut traversals = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--runs" => runs = args.next().ok_or("--runs needs a value")?.parse()?,
            "--size" => {
                let s = args.next().ok_or("--size needs WxH")?;
                let (a, b) = s.split_once('x').ok_or("--size needs WxH")?;
                (w, h) = (a.parse()?, b.parse()?);
            }
            "--traversal" => {
                let t = args.next().ok_or("--traversal needs a value")?;
                traversals.push(t.parse::<Traversal>().map_err(|e| format!("{t}: {e}"))?);
            }
            _ => scenes.push(a),
        }
    }
    if scenes.is_empty() {
        let dir = bvhtrace_scene::shared_scenes_dir()
            .ok_or("no scene given and no shared scenes folder found")?
            .join("glb");
        for f in ["bunny_69k.glb", "igea.glb"] {
            scenes.push(dir.join(f).to_string_lossy().into_owned());
        }
    }
    if traversals.is_empty() {
        traversals = vec![Traversal::FullStack, Traversal::Stackless];
    }
    let runs = runs.max(1);

    let vk = VkContext::new(AdapterChoice::Auto)?;
    let wg = GpuContext::new(AdapterChoice::Auto)?;
    eprintln!(
        "ash: {} (timestamps {}, {:?}); wgpu: {} (timestamps {}, {:?}); LP_NUM_THREADS={}",
        vk.device_info().name,
        vk.has_timestamps(),
        vk.tuning(),
        wg.adapter_info().name,
        wg.has_timestamps(),
        wg.tuning(),
        std::env::var("LP_NUM_THREADS").unwrap_or_else(|_| "unset".into())
    );
    println!(
        "| scene | traversal | backend | rays | dispatch ms (timestamps) | wall ms per batch | wall - dispatch ms |"
    );
    println!("|---|---|---|---:|---:|---:|---:|");
    for spec in &scenes {
        let scene = bvhtrace_scene::load(spec).map_err(|e| format!("{spec}: {e}"))?;
        let tris = scene
            .flatten()
            .triangles()
            .map_err(|e| format!("{spec}: {e}"))?;
        let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
        let rays = scene.camera_or_frame(w as f32 / h as f32).rays(w, h);
        let name = std::path::Path::new(spec.split('#').next().unwrap_or(spec))
            .file_stem()
            .map_or(spec.clone(), |s| s.to_string_lossy().into_owned());
        let ash_bvh = VkBvh::upload(&vk, &bvh, &VkUploadOptions::all())?;
        let wgpu_buffers = GpuBvh::upload(
            &wg,
            &bvh,
            &UploadOptions::all().with_storage(BvhStorage::Buffers),
        )?;
        let wgpu_textures = GpuBvh::upload(
            &wg,
            &bvh,
            &UploadOptions::all().with_storage(BvhStorage::Textures),
        )?;
        for &traversal in &traversals {
            let opts = TraceOptions::closest(traversal);
            // Runs interleaved (ash, wgpu buffers, wgpu textures, ash, ...) so that load
            // from other processes falls on all backends alike.
            let labels = ["ash (buffers)", "wgpu (buffers)", "wgpu (textures)"];
            let mut gpu = vec![Vec::new(); 3];
            let mut wall = vec![Vec::new(); 3];
            let mut hits = vec![Vec::new(); 3];
            for i in 0..=runs {
                let a = ash_bvh.trace(&rays, &opts)?;
                let (g, t, hh) = (a.gpu_ms.unwrap_or(f64::NAN), a.wall_ms, a.hits);
                let mut results = vec![(g, t, hh)];
                for g in [&wgpu_buffers, &wgpu_textures] {
                    let out = g.trace(&rays, &opts)?;
                    results.push((out.gpu_ms.unwrap_or(f64::NAN), out.wall_ms, out.hits));
                }
                for (b, (g, t, hh)) in results.into_iter().enumerate() {
                    if i > 0 {
                        gpu[b].push(g);
                        wall[b].push(t);
                    }
                    hits[b] = hh;
                }
            }
            let rows: Vec<_> = (0..3)
                .map(|b| {
                    (
                        labels[b],
                        median(std::mem::take(&mut gpu[b])),
                        median(std::mem::take(&mut wall[b])),
                        std::mem::take(&mut hits[b]),
                    )
                })
                .collect();
            for (label, gpu, wall, hits) in &rows {
                if bytemuck::cast_slice::<_, u8>(hits) != bytemuck::cast_slice::<_, u8>(&rows[0].3)
                {
                    return Err(
                        format!("{name} {traversal}: {label} hits differ from ash's").into(),
                    );
                }
                println!(
                    "| {name} | {traversal} | {label} | {} | {gpu:.1} | {wall:.1} | {:.1} |",
                    rays.len(),
                    wall - gpu
                );
            }
        }
    }
    eprintln!("hits identical across backends; medians of {runs} runs after one warm-up");
    Ok(())
}
