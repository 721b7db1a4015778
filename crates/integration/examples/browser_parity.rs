//! The library in a browser, hit for hit: builds bvhtrace-web's page (from the
//! `wasm-bindgen` output in DIST), serves it on 127.0.0.1 to headless Chromium (WebGPU on
//! SwiftShader), has it build the BVH in WebAssembly and trace a fixed camera's rays on
//! the browser's WebGPU, and checks every hit against the CPU twin's (`trace_rays`, same
//! triangles, same rays, same walk) bit for bit. Prints `browser parity: N hits, 0 differ`
//! and exits non-zero on any difference, page error or timeout. Then opens the library's
//! example page (`index.html`) and checks the hits it prints. `web/test.sh` runs it.
//!
//! ```text
//! cargo run --release -p bvhtrace-integration --example browser_parity -- DIST [--size WxH]
//! ```
//!
//! The scene is `bunny_69k` from the shared scenes when that folder is there, else the
//! builtin icosphere (said in the output).

use std::path::PathBuf;
use std::time::Duration;

use bvhtrace_core::{BuildOptions, FlatBvh, Hit, TraceOptions, Traversal, trace_rays};
use bvhtrace_integration::browser::{self, Report};
use bvhtrace_scene::{Camera, shared_scenes_dir};
use bvhtrace_shade::args::parse_size;

/// The page: fetches the triangles and rays, traces them with the wasm, posts the hits.
const PAGE: &str = r#"<!doctype html><meta charset="utf-8"><pre id="out">running</pre>
<script type="module">
const post = (path, body) => fetch(path, { method: "POST", body });
addEventListener("error", (e) => post("/error", `${e.message} (${e.filename}:${e.lineno})`));
addEventListener("unhandledrejection", (e) => post("/error", String(e.reason)));
try {
  const start = performance.now();
  await post("/log", "loading the wasm");
  const { default: init, trace_closest } = await import("./bvhtrace_web.js");
  await init();
  await post("/log", "tracing");
  const get = async (p) => new Float32Array(await (await fetch(p)).arrayBuffer());
  const [hits, adapter] = await trace_closest(await get("/triangles.bin"), await get("/rays.bin"));
  document.getElementById("out").textContent = `${adapter}: ${hits.length} bytes`;
  const total = new Float64Array([performance.now() - start]);
  await post("/result", new Blob([hits, new Uint8Array(total.buffer), adapter]));
} catch (e) {
  await post("/error", String(e && e.stack || e));
}
</script>"#;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let dist = PathBuf::from(
        args.next()
            .ok_or("usage: browser_parity DIST [--size WxH]")?,
    );
    let (mut w, mut h) = (256u32, 192u32);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--size" => (w, h) = parse_size(&args.next().ok_or("--size needs WxH")?)?,
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let chromium = browser::chromium().ok_or("no chromium installed (apt-get install chromium)")?;
    let spec = match shared_scenes_dir() {
        Some(dir) => dir.join("glb/bunny_69k.glb").to_string_lossy().into_owned(),
        None => {
            println!("no shared scenes folder: using builtin:icosphere:6 instead of bunny_69k");
            "builtin:icosphere:6".to_string()
        }
    };
    let tris = bvhtrace_scene::load(&spec)?.flatten().triangles()?;
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
    let b = bvh.bounds();
    let rays = Camera::frame(b.min, b.max, w as f32 / h as f32).rays(w, h);
    let opts = TraceOptions::closest(Traversal::Stackless);
    let cpu = trace_rays(&bvh, &rays, &opts).hits;

    let flat: Vec<f32> = tris
        .iter()
        .flat_map(|t| t.iter().flat_map(|v| v.to_array()))
        .collect();
    let files = {
        let (tris, rays) = (
            bytemuck::cast_slice::<f32, u8>(&flat).to_vec(),
            bytemuck::cast_slice(&rays).to_vec(),
        );
        let read = |name: &str| {
            std::fs::read(dist.join(name))
                .map_err(|e| format!("{}: {e}", dist.join(name).display()))
        };
        let (js, wasm) = (read("bvhtrace_web.js")?, read("bvhtrace_web_bg.wasm")?);
        println!(
            "{spec}: {} triangles, {} rays; wasm {} bytes",
            bvh.triangles().len(),
            w * h,
            wasm.len()
        );
        move |path: &str| match path {
            "/" => Some(PAGE.as_bytes().to_vec()),
            "/bvhtrace_web.js" => Some(js.clone()),
            "/bvhtrace_web_bg.wasm" => Some(wasm.clone()),
            "/triangles.bin" => Some(tris.clone()),
            "/rays.bin" => Some(rays.clone()),
            _ => None,
        }
    };
    let bytes = match browser::run_page(&chromium, files, Duration::from_secs(600))? {
        Report::Result(bytes) => bytes,
        Report::Error(e) => return Err(format!("the page failed: {e}").into()),
    };
    let n = cpu.len() * std::mem::size_of::<Hit>();
    if bytes.len() < n + 16 {
        return Err(format!("the page sent {} bytes for {} hits", bytes.len(), cpu.len()).into());
    }
    let gpu: Vec<Hit> = bytemuck::pod_collect_to_vec(&bytes[..n]);
    let ms = |at: usize| f64::from_le_bytes(bytes[at..at + 8].try_into().unwrap_or_default());
    let (trace_ms, page_ms) = (ms(n), ms(n + 8));
    let adapter = String::from_utf8_lossy(&bytes[n + 16..]);
    let differ: Vec<usize> = (0..cpu.len())
        .filter(|&i| bytemuck::bytes_of(&gpu[i]) != bytemuck::bytes_of(&cpu[i]))
        .collect();
    println!(
        "browser: {adapter}; trace {trace_ms:.1} ms ({:.2} Mrays/s), page load to hits {page_ms:.0} ms (build, upload, two traces)",
        cpu.len() as f64 / trace_ms / 1e3
    );
    println!(
        "browser parity: {} hits, {} differ",
        cpu.len(),
        differ.len()
    );
    for &i in differ.iter().take(5) {
        println!(
            "  ray {i}: {:?}\n    browser {:?}\n    cpu     {:?}",
            rays[i], gpu[i], cpu[i]
        );
    }
    if !differ.is_empty() {
        return Err(format!(
            "{} of {} hits differ from the CPU twin's",
            differ.len(),
            cpu.len()
        )
        .into());
    }
    example_page(&chromium, &dist)
}

/// The library's example page (`index.html`): four rays over a unit quad of two triangles,
/// the hits printed on the page. Three hit at t = 5 (the ray on the shared diagonal hits
/// exactly one of the two triangles: the test is watertight), the fourth misses.
fn example_page(chromium: &str, dist: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
    let text = match browser::open_page(
        chromium,
        browser::WebGpu::SwiftShader,
        browser::folder(dist.to_path_buf()),
        "/index.html?report=1",
        (800, 600),
        Duration::from_secs(300),
    )? {
        Report::Result(bytes) => String::from_utf8_lossy(&bytes).into_owned(),
        Report::Error(e) => return Err(format!("the example page failed: {e}").into()),
    };
    let lines: Vec<&str> = text.lines().collect();
    let hit = |i: usize, tri: &str| {
        lines
            .get(i)
            .is_some_and(|l| l.contains(&format!("triangle {tri}")) && l.contains("t = 5"))
    };
    let ok = lines.len() == 6
        && hit(1, "0")
        && hit(2, "1")
        && (hit(3, "0") || hit(3, "1"))
        && lines[4].ends_with(": miss");
    println!("example page: {}", lines[1..].join(" | "));
    match ok {
        true => Ok(()),
        false => Err(format!("the example page printed:\n{text}").into()),
    }
}
