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
//! cargo run --release -p bvhtrace-integration --example browser_viewer -- DIST [--window WxH] [--out DIR] [--scene FILE.glb|.gltf] [--time T] [--play] [--cpu] [--path] [--flags FLAGS] [--expect-error TEXT]
//! ```
//!
//! The scene is `bunny_69k` from the shared scenes when that folder is there, else the
//! builtin icosphere (said in the output). `--scene` opens another file (a `.gltf` with
//! embedded buffers, or a `.glb`), `--time` poses an animated one at T seconds (in two
//! levels when it places meshes more than once, as the viewer does), and `--play` plays it
//! from there (each frame a new pose, written into the upload in place). `--cpu` has the
//! viewer trace with the CPU walks in WebAssembly instead of the GPU. `--path` opens the
//! viewer's path mode: its sums, read back once with the screenshot, tone mapped, against
//! the path tracer's CPU twin at the same camera and samples per pixel. `--flags` adds the
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

/// What the command line asks for.
struct Args {
    /// The built web folder served to the browser.
    dist: PathBuf,
    /// The browser window, WxH.
    window: (u32, u32),
    /// Where the screenshot and the images go.
    out: PathBuf,
    /// `--scene`: a glTF file instead of the default scene.
    file: Option<PathBuf>,
    /// `--time`: the animation's pose, seconds.
    time: f32,
    /// `--play`: the animation plays from `time`.
    play: bool,
    /// `--cpu`: the viewer traces with the CPU walks in WebAssembly.
    cpu: bool,
    /// `--flags`: the viewer's own flags, added.
    extra: String,
    /// `--expect-error`: the page must fail with this text.
    expect_error: Option<String>,
    /// `--path`: the viewer's path mode, its sums against the CPU twin's.
    path: bool,
}

impl Args {
    fn parse() -> Result<Args, Box<dyn std::error::Error>> {
        let mut args = std::env::args().skip(1);
        let usage = "usage: browser_viewer DIST [--window WxH] [--out DIR] [--scene FILE] [--time T] [--play] [--cpu] [--path] [--flags FLAGS] [--expect-error TEXT]";
        let dist = PathBuf::from(args.next().ok_or(usage)?);
        let mut a = Args {
            out: dist.clone(),
            dist,
            window: (960, 640),
            file: None,
            time: 0.0,
            play: false,
            cpu: false,
            extra: String::new(),
            expect_error: None,
            path: false,
        };
        while let Some(arg) = args.next() {
            match arg.as_str() {
                "--window" => a.window = parse_size(&args.next().ok_or("--window needs WxH")?)?,
                "--out" => a.out = PathBuf::from(args.next().ok_or("--out needs a folder")?),
                "--scene" => {
                    a.file = Some(PathBuf::from(args.next().ok_or("--scene needs a file")?));
                }
                "--time" => a.time = args.next().ok_or("--time needs seconds")?.parse()?,
                "--play" => a.play = true,
                "--cpu" => a.cpu = true,
                "--path" => a.path = true,
                "--flags" => a.extra = args.next().ok_or("--flags needs the viewer's flags")?,
                "--expect-error" => {
                    a.expect_error = Some(args.next().ok_or("--expect-error needs a text")?);
                }
                other => return Err(format!("unknown argument {other}; {usage}").into()),
            }
        }
        Ok(a)
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let args = Args::parse()?;
    let chromium = browser::chromium().ok_or("no chromium installed (apt-get install chromium)")?;
    let glb =
        (args.file.clone()).or_else(|| shared_scenes_dir().map(|d| d.join("glb/bunny_69k.glb")));
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
    let scene = match &args.expect_error {
        None => Some(bvhtrace_scene::load(&spec)?),
        Some(_) => None,
    };
    let (lo, hi) = scene
        .as_ref()
        .map_or((Vec3::splat(-1.0), Vec3::ONE), |s| s.bounds());
    let (path, name) = page_path(&args, &spec, scene_bytes.is_some(), (lo, hi));
    let files = {
        let serve = browser::folder(args.dist.clone());
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
        args.window,
        Duration::from_secs(600),
    )?;
    let Some(body) = expected(report, args.expect_error.as_deref())? else {
        return Ok(());
    };
    let page_s = start.elapsed().as_secs_f64();
    let shown = Shown::parse(&body)?;
    let (w, h) = shown.size;
    println!(
        "browser viewer: {} ({:.1} s from page load to screenshot)",
        shown.head["message"].as_str().unwrap_or_default(),
        page_s
    );
    std::fs::create_dir_all(&args.out)?;
    let shot = args.out.join("viewer-screenshot.png");
    std::fs::write(&shot, shown.png)?;
    if shown.head["on_gpu"].as_bool() != Some(true) && !args.cpu {
        return Err("the viewer traced on the CPU, not the browser's GPU".into());
    }
    if shown.traced.len() != (w * h * 4) as usize || w == 0 {
        return Err(format!(
            "the traced image has {} bytes for {w}x{h}",
            shown.traced.len()
        )
        .into());
    }
    let scene = scene.ok_or("no scene")?;
    let native = match args.path {
        true => native_path(&scene, &shown)?,
        false => native_render(scene, &shown, (hi - lo).length())?,
    };
    compare(&args.out, &shown, &native, &shot)
}

/// What the page reported, as `--expect-error` expects it: the result's bytes, or `None`
/// for the error expected (said); an error for a failure not expected, or for a page that
/// ran where it should have failed.
fn expected(
    report: Report,
    expect_error: Option<&str>,
) -> Result<Option<Vec<u8>>, Box<dyn std::error::Error>> {
    match (report, expect_error) {
        (Report::Result(bytes), None) => Ok(Some(bytes)),
        (Report::Error(e), None) => Err(format!("the page failed: {e}").into()),
        (Report::Error(e), Some(want)) if e.contains(want) => {
            println!("browser viewer: the page shows the error, as expected: {e}");
            Ok(None)
        }
        (Report::Error(e), Some(want)) => {
            Err(format!("the page failed without saying {want:?}: {e}").into())
        }
        (Report::Result(_), Some(want)) => {
            Err(format!("the page ran, where it should have said {want:?}").into())
        }
    }
}

/// Saves the traced image and the `native` one in `out`, beside the screenshot `shot`, and
/// fails when any pixel differs.
fn compare(
    out: &std::path::Path,
    shown: &Shown,
    native: &[u8],
    shot: &std::path::Path,
) -> Result<(), Box<dyn std::error::Error>> {
    let (w, h) = shown.size;
    let browser_rgb: Vec<u8> = (shown.traced.chunks_exact(4))
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    let save = |name: &str, rgb: &[u8]| {
        image::save_buffer(out.join(name), rgb, w, h, image::ExtendedColorType::Rgb8)
    };
    save("viewer-traced.png", &browser_rgb)?;
    save("viewer-native.png", native)?;
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

/// The page to open, with the viewer's flags (a fixed camera framing `bounds`, the
/// screenshot, the time, and those asked for), and the name the scene file is served
/// under; a builtin scene (`served` false) is named in the flags instead.
fn page_path(
    args: &Args,
    spec: &str,
    served: bool,
    (lo, hi): (Vec3, Vec3),
) -> (String, &'static str) {
    let cam = Camera::frame(lo, hi, 1.0);
    let v = |p: Vec3| format!("{},{},{}", p.x, p.y, p.z);
    let mut flags = format!(
        "--screenshot viewer.png --frames 5 --scale 1 --eye {} --target {} --fov {} --time {}",
        v(cam.eye),
        v(cam.target),
        cam.fov_y_deg,
        args.time
    );
    if args.play {
        flags.push_str(" --play");
    }
    if args.cpu {
        flags.push_str(" --cpu");
    }
    if args.path {
        flags.push_str(" --shade path");
    }
    if !args.extra.is_empty() {
        flags = format!("{flags} {}", args.extra);
    }
    let name = match spec.rsplit_once('.') {
        Some((_, ext)) if ext.eq_ignore_ascii_case("gltf") => "scene.gltf",
        _ => "scene.glb",
    };
    let query = match served {
        true => format!("scene=/{name}&"),
        false => {
            flags = format!("{spec} {flags}");
            String::new()
        }
    };
    let path = format!(
        "/viewer.html?{query}report=1&args={}",
        flags.replace(' ', "+")
    );
    (path, name)
}

/// What the page sent back: a JSON header line (the size, the camera and time shown, the
/// lengths of what follows), the window's screenshot as PNG, and the traced image as RGBA8.
struct Shown<'a> {
    head: serde_json::Value,
    size: (u32, u32),
    png: &'a [u8],
    traced: &'a [u8],
    cam: Camera,
}

impl<'a> Shown<'a> {
    fn parse(body: &'a [u8]) -> Result<Shown<'a>, Box<dyn std::error::Error>> {
        let line = body
            .iter()
            .position(|&b| b == b'\n')
            .ok_or("no header in the result")?;
        let head: serde_json::Value = serde_json::from_slice(&body[..line])?;
        let num = |k: &str| head[k].as_u64().ok_or(format!("the result has no {k}"));
        let size = (num("width")? as u32, num("height")? as u32);
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
        let cam = Camera {
            eye: vec3("eye")?,
            target: vec3("target")?,
            fov_y_deg: head["fov"].as_f64().ok_or("no fov")? as f32,
        };
        Ok(Shown {
            head,
            size,
            png,
            traced,
            cam,
        })
    }
}

/// The path tracer's CPU twin at the camera, size and samples per pixel the page shows
/// (the viewer's walk and lighting), tone mapped as the page's image is, as RGB8.
fn native_path(
    scene: &bvhtrace_scene::Scene,
    shown: &Shown,
) -> Result<Vec<u8>, Box<dyn std::error::Error>> {
    use bvhtrace_path::{Accumulation, CpuPathTracer, Lighting, PathParams, PathScene};
    let samples = shown.head["samples"]
        .as_u64()
        .ok_or("the page reported no samples")? as u32;
    if samples == 0 {
        return Err("the page's path mode added no sample".into());
    }
    // Flattened with its alpha masks, as the viewer's path mode traces it.
    let bvhtrace_scene::SceneBvh::Flat { tris, bvh } =
        scene.tracing_bvh(&BuildOptions::default(), true)?
    else {
        return Err("a flattened scene traced in two levels".into());
    };
    let shading = PathScene::new(scene, &tris)?;
    let params = PathParams::new(&shown.cam, shown.size, &Lighting::default(), 8, &shading);
    let twin = CpuPathTracer::new(&bvh, &tris, &shading, Traversal::Stackless)?;
    let start = Instant::now();
    let mut sums = Accumulation::default();
    for sample in 0..samples {
        twin.add_sample(&PathParams { sample, ..params }, &mut sums);
    }
    println!(
        "browser viewer: the CPU twin traced the page's {samples} samples per pixel in {:.1} s",
        start.elapsed().as_secs_f64()
    );
    Ok(sums.to_srgb8(1.0))
}

/// The native render of the camera and time shown: the CPU twin's hits, shaded as
/// `bvhtrace render` shades them (the viewer's default mode, normals), as RGB8.
fn native_render(
    mut scene: bvhtrace_scene::Scene,
    shown: &Shown,
    diagonal: f32,
) -> Result<Vec<u8>, Box<dyn std::error::Error>> {
    // The time the viewer shows (it moves on from `--time` when `--play` is given).
    let shown_time = shown.head["time"].as_f64().ok_or("no time")? as f32;
    scene.set_time(shown_time);
    let geometry = scene.tracing_bvh(&BuildOptions::default(), false)?;
    let (w, h) = shown.size;
    let rays = shown.cam.rays(w, h);
    let hits = trace_rays(
        geometry.bvh(),
        &rays,
        &TraceOptions::closest(Traversal::Stackless),
    )
    .hits;
    let view = View::for_camera(Shade::Normal, &shown.cam, diagonal);
    let pixels = Pixels {
        size: (w, h),
        rays: &rays,
        hits: &hits,
        counters: &[],
        owner: &[],
        secondary: &[],
        ao_samples: 1,
    };
    Ok(compose_rgb(&view, &pixels, &|p| {
        geometry.triangle(p).unwrap_or_default()
    }))
}
