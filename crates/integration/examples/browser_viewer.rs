//! The viewer in a browser, against the native render: serves web/dist (after
//! `web/build.sh`) to headless Chromium (WebGPU on the system's Vulkan driver, lavapipe
//! here: SwiftShader cannot present a canvas headless), opens `viewer.html` on a
//! scene with a fixed camera and `--screenshot`, and takes back the window's screenshot and
//! the traced image. Saves the screenshot (and the traced and native images beside it), and
//! checks the traced image pixel for pixel against `bvhtrace render`'s shading of the CPU
//! twin's hits for the same camera and size. Prints `browser viewer: N pixels, 0 differ`
//! and exits non-zero on any difference, page error, CPU fallback or timeout.
//! `web/test.sh` runs it.
//!
//! ```text
//! cargo run --release -p bvhtrace-integration --example browser_viewer -- DIST [--window WxH] [--out DIR] [--scene FILE.glb|.gltf] [--time T] [--play] [--cpu] [--flags FLAGS] [--expect-error TEXT]
//! ```
//!
//! The scene is `bunny_69k` from the shared scenes when that folder is there, else the
//! builtin icosphere (said in the output). `--scene` opens another file (a `.gltf` with
//! embedded buffers, or a `.glb`), `--time` poses an animated one at T seconds (in two
//! levels when it places meshes more than once, as the viewer does), and `--play` plays it
//! from there (each frame a new pose, written into the upload in place). `--cpu` has the
//! viewer trace with the CPU walks in WebAssembly instead of the GPU. `--flags` adds the
//! viewer's own flags; with `--expect-error TEXT` the page must fail and show an error
//! containing TEXT (a bad flag, a file that does not load) instead of an image.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use bvhtrace_core::{BuildOptions, TraceOptions, Traversal, trace_rays};
use bvhtrace_integration::browser::{self, Report, WebGpu};
use bvhtrace_scene::{Camera, shared_scenes_dir};
use bvhtrace_shade::args::parse_size;
use bvhtrace_shade::{Pixels, Shade, View, compose_rgb};
use glam::Vec3;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let usage = "usage: browser_viewer DIST [--window WxH] [--out DIR] [--scene FILE] [--time T] [--play] [--cpu] [--flags FLAGS] [--expect-error TEXT]";
    let dist = PathBuf::from(args.next().ok_or(usage)?);
    let (mut window, mut out) = ((960u32, 640u32), dist.clone());
    let (mut file, mut time, mut play) = (None::<PathBuf>, 0.0f32, false);
    let mut cpu = false;
    let (mut extra, mut expect_error) = (String::new(), None::<String>);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--window" => window = parse_size(&args.next().ok_or("--window needs WxH")?)?,
            "--out" => out = PathBuf::from(args.next().ok_or("--out needs a folder")?),
            "--scene" => file = Some(PathBuf::from(args.next().ok_or("--scene needs a file")?)),
            "--time" => time = args.next().ok_or("--time needs seconds")?.parse()?,
            "--play" => play = true,
            "--cpu" => cpu = true,
            "--flags" => extra = args.next().ok_or("--flags needs the viewer's flags")?,
            "--expect-error" => {
                expect_error = Some(args.next().ok_or("--expect-error needs a text")?);
            }
            other => return Err(format!("unknown argument {other}; {usage}").into()),
        }
    }
    let chromium = browser::chromium().ok_or("no chromium installed (apt-get install chromium)")?;
    let glb = file.or_else(|| shared_scenes_dir().map(|d| d.join("glb/bunny_69k.glb")));
    let (spec, scene_bytes) = match &glb {
        Some(path) => (
            path.to_string_lossy().into_owned(),
            Some(std::fs::read(path)?),
        ),
        None => {
            println!("no shared scenes folder: using builtin:icosphere:6 instead of bunny_69k");
            ("builtin:icosphere:6".to_string(), None)
        }
    };
    // A page expected to fail gets a file that need not load here either.
    let scene = match &expect_error {
        None => Some(bvhtrace_scene::load(&spec)?),
        Some(_) => None,
    };
    let (lo, hi) = scene
        .as_ref()
        .map_or((Vec3::splat(-1.0), Vec3::ONE), |s| s.bounds());
    let cam = Camera::frame(lo, hi, 1.0);
    let v = |p: Vec3| format!("{},{},{}", p.x, p.y, p.z);
    let mut flags = format!(
        "--screenshot viewer.png --frames 5 --scale 1 --eye {} --target {} --fov {} --time {time}",
        v(cam.eye),
        v(cam.target),
        cam.fov_y_deg
    );
    if play {
        flags.push_str(" --play");
    }
    if cpu {
        flags.push_str(" --cpu");
    }
    if !extra.is_empty() {
        flags = format!("{flags} {extra}");
    }
    let name = match spec.rsplit_once('.') {
        Some((_, ext)) if ext.eq_ignore_ascii_case("gltf") => "scene.gltf",
        _ => "scene.glb",
    };
    let query = match scene_bytes {
        Some(_) => format!("scene=/{name}&"),
        None => {
            flags = format!("{spec} {flags}");
            String::new()
        }
    };
    let path = format!(
        "/viewer.html?{query}report=1&args={}",
        flags.replace(' ', "+")
    );
    let files = {
        let serve = browser::folder(dist.clone());
        move |p: &str| match &scene_bytes {
            Some(b) if p.strip_prefix('/') == Some(name) => Some(b.clone()),
            _ => serve(p),
        }
    };
    let triangles = scene.as_ref().map_or(0, |s| s.triangle_count());
    println!("{spec}: {triangles} triangles; page {path}");
    let start = Instant::now();
    let report = browser::open_page(
        &chromium,
        WebGpu::Vulkan,
        files,
        &path,
        window,
        Duration::from_secs(600),
    )?;
    let body = match (report, expect_error) {
        (Report::Result(bytes), None) => bytes,
        (Report::Error(e), None) => return Err(format!("the page failed: {e}").into()),
        (Report::Error(e), Some(want)) if e.contains(&want) => {
            println!("browser viewer: the page shows the error, as expected: {e}");
            return Ok(());
        }
        (Report::Error(e), Some(want)) => {
            return Err(format!("the page failed without saying {want:?}: {e}").into());
        }
        (Report::Result(_), Some(want)) => {
            return Err(format!("the page ran, where it should have said {want:?}").into());
        }
    };
    let page_s = start.elapsed().as_secs_f64();
    let line = body
        .iter()
        .position(|&b| b == b'\n')
        .ok_or("no header in the result")?;
    let head: serde_json::Value = serde_json::from_slice(&body[..line])?;
    let num = |k: &str| head[k].as_u64().ok_or(format!("the result has no {k}"));
    let (w, h) = (num("width")? as u32, num("height")? as u32);
    let (png_len, traced_len) = (num("png_bytes")? as usize, num("traced_bytes")? as usize);
    let png = body
        .get(line + 1..line + 1 + png_len)
        .ok_or("the PNG is cut short")?;
    let traced = body
        .get(line + 1 + png_len..line + 1 + png_len + traced_len)
        .ok_or("the traced image is cut short")?;
    let vec3 = |k: &str| -> Result<Vec3, String> {
        let a: Vec<f32> = (head[k].as_array().ok_or(format!("no {k}"))?.iter())
            .filter_map(|x| x.as_f64().map(|f| f as f32))
            .collect();
        (a.len() == 3)
            .then(|| Vec3::new(a[0], a[1], a[2]))
            .ok_or(format!("{k} is not three numbers"))
    };
    let shown = Camera {
        eye: vec3("eye")?,
        target: vec3("target")?,
        fov_y_deg: head["fov"].as_f64().ok_or("no fov")? as f32,
    };
    println!(
        "browser viewer: {} ({:.1} s from page load to screenshot)",
        head["message"].as_str().unwrap_or_default(),
        page_s
    );
    std::fs::create_dir_all(&out)?;
    let shot = out.join("viewer-screenshot.png");
    std::fs::write(&shot, png)?;
    if head["on_gpu"].as_bool() != Some(true) && !cpu {
        return Err("the viewer traced on the CPU, not the browser's GPU".into());
    }
    if traced.len() != (w * h * 4) as usize || w == 0 {
        return Err(format!("the traced image has {} bytes for {w}x{h}", traced.len()).into());
    }

    // The native render of the same camera and time: the CPU twin's hits, shaded as
    // `bvhtrace render` shades them (the viewer's default mode, normals).
    // The time the viewer shows (it moves on from `--time` when `--play` is given).
    let shown_time = head["time"].as_f64().ok_or("no time")? as f32;
    let mut posed = scene.ok_or("no scene")?;
    posed.set_time(shown_time);
    let geometry = posed.tracing_bvh(&BuildOptions::default(), false)?;
    let rays = shown.rays(w, h);
    let hits = trace_rays(
        geometry.bvh(),
        &rays,
        &TraceOptions::closest(Traversal::Stackless),
    )
    .hits;
    let view = View::for_camera(Shade::Normal, &shown, (hi - lo).length());
    let pixels = Pixels {
        size: (w, h),
        rays: &rays,
        hits: &hits,
        counters: &[],
        owner: &[],
        secondary: &[],
        ao_samples: 1,
    };
    let native = compose_rgb(&view, &pixels, &|p| {
        geometry.triangle(p).unwrap_or_default()
    });
    let browser_rgb: Vec<u8> = traced
        .chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    let save = |name: &str, rgb: &[u8]| {
        image::save_buffer(out.join(name), rgb, w, h, image::ExtendedColorType::Rgb8)
    };
    save("viewer-traced.png", &browser_rgb)?;
    save("viewer-native.png", &native)?;
    let differ = browser_rgb
        .chunks_exact(3)
        .zip(native.chunks_exact(3))
        .filter(|(a, b)| a != b)
        .count();
    println!(
        "browser viewer: {} pixels, {differ} differ (screenshot {}; traced and native images beside it)",
        w * h,
        shot.display()
    );
    match differ {
        0 => Ok(()),
        n => Err(format!("{n} of {} pixels differ from the native render", w * h).into()),
    }
}
