//! The library in a browser, hit for hit: builds bvhtrace-web's page (from the
//! `wasm-bindgen` output in DIST), serves it on 127.0.0.1 to headless Chromium (WebGPU on
//! SwiftShader), has it build the BVH in WebAssembly and trace a fixed camera's rays on
//! the browser's WebGPU, and checks every hit against the CPU twin's (`trace_rays`, same
//! triangles, same rays, same walk) bit for bit. Prints `browser parity: N hits, 0 differ`
//! and exits non-zero on any difference, page error or timeout.
//!
//! Then the BVH built on the browser's WebGPU: for each device builder (`gpu-ploc` and
//! `gpu-lbvh`; `--device-builders LIST` names others, `none` skips them) the page builds
//! the tree with `trace_closest_built_on_device` (`GpuContext::build_bvh_async`), reads it
//! back, traces the rays over it on WebGPU and walks them over it on the CPU in
//! WebAssembly, and sends back the hits and the tree. The tree must pass
//! `FlatBvh::check_invariants` here too, hold each input triangle once with its corners
//! unchanged, and come out the same from both of the page's builds; the browser's GPU hits
//! and its CPU walk's must equal, bit for bit, the CPU walk here over the same tree. Prints
//! `browser device build (gpu-ploc): built in X ms ...; N hits, 0 differ from the CPU walks
//! over the read-back tree`.
//!
//! Then a user's shader with a mistake (an unknown function on line 6), compiled after the
//! traversal library on the browser's WebGPU (`compile_with_library`): the page must be
//! given an error naming `mine.wgsl:6:` and the identifier, where the corrected shader
//! compiles. Prints `browser shader error: mine.wgsl:6:...`.
//!
//! Last, opens the library's example page (`index.html`) and checks the hits it prints,
//! then the same page with the BVH built on the device (`?builder=gpu-ploc`).
//! `web/test.sh` runs it.
//!
//! ```text
//! cargo run --release -p bvhtrace-integration --example browser_parity -- DIST [--size WxH] [--device-builders gpu-ploc,gpu-lbvh|none] [--scene SPEC]
//! ```
//!
//! The scene is `bunny_69k` from the shared scenes when that folder is there, else the
//! builtin icosphere (said in the output); `--scene` names another (`builtin:grid` meshes
//! from the shared scenes), such as `builtin:grid:igea:5x5`, whose tree is larger than a
//! browser's 128 MiB storage binding. `--default-limits` has the page ask for WebGPU's
//! default limits (128 MiB bindings, 8 storage buffers per stage) and trace with the full
//! stack: a tree over 128 MiB must then go in pages, or the run fails.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use bvhtrace_core::{
    BuildOptions, BvhStats, FlatBvh, FlatNode, FlatTriangle, Hit, Ray, TraceOptions, Traversal,
    Triangle, trace_rays,
};
use bvhtrace_integration::browser::{self, Report};
use bvhtrace_scene::Camera;
use bvhtrace_shade::args::parse_size;

type Error = Box<dyn std::error::Error>;

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
  const defaultLimits = new URLSearchParams(location.search).get("limits") === "default";
  const [hits, adapter] = await trace_closest(
    await get("/triangles.bin"), await get("/rays.bin"), defaultLimits);
  document.getElementById("out").textContent = `${adapter}: ${hits.length} bytes`;
  const total = new Float64Array([performance.now() - start]);
  await post("/result", new Blob([hits, new Uint8Array(total.buffer), adapter]));
} catch (e) {
  await post("/error", String(e && e.stack || e));
}
</script>"#;

/// The device-build page (`/device.html?builder=NAME`): builds the BVH on the browser's
/// WebGPU, traces the rays over it there and on the CPU in WebAssembly, and posts a head
/// of f64 figures ([`DeviceReport::parse`] reads them in this order), the GPU hits, the
/// CPU walk's hits, the tree, then the invariant check's text.
const DEVICE_PAGE: &str = r#"<!doctype html><meta charset="utf-8"><pre id="out">running</pre>
<script type="module">
const post = (path, body) => fetch(path, { method: "POST", body });
addEventListener("error", (e) => post("/error", `${e.message} (${e.filename}:${e.lineno})`));
addEventListener("unhandledrejection", (e) => post("/error", String(e.reason)));
try {
  const builder = new URLSearchParams(location.search).get("builder");
  const { default: init, trace_closest_built_on_device } = await import("./bvhtrace_web.js");
  await init();
  await post("/log", `building with ${builder} on the device`);
  const get = async (p) => new Float32Array(await (await fetch(p)).arrayBuffer());
  const r = await trace_closest_built_on_device(
    await get("/triangles.bin"), await get("/rays.bin"), builder);
  document.getElementById("out").textContent = `${r.adapter}: ${r.nodes} nodes`;
  const head = new Float64Array([r.uploadMs, r.buildMs, r.readbackMs, r.firstBuildMs,
    r.iterations, r.sameTree ? 1 : 0, r.nodes, r.sah, r.hits.length, r.cpuHits.length,
    r.tree.length]);
  const text = new TextEncoder().encode(r.invariants);
  await post("/result", new Blob([head, r.hits, r.cpuHits, r.tree, text]));
} catch (e) {
  await post("/error", String(e && e.stack || e));
}
</script>"#;

/// The shader page (`/shader.html`): compiles [`shader_source`]'s corrected shader after
/// the traversal library on the browser's WebGPU, then the one with a mistake on line 6,
/// and posts what the second gave (`compiled` when it did).
const SHADER_PAGE: &str = r#"<!doctype html><meta charset="utf-8"><pre id="out">running</pre>
<script type="module">
const post = (path, body) => fetch(path, { method: "POST", body });
addEventListener("error", (e) => post("/error", `${e.message} (${e.filename}:${e.lineno})`));
addEventListener("unhandledrejection", (e) => post("/error", String(e.reason)));
try {
  const { default: init, compile_with_library } = await import("./bvhtrace_web.js");
  await init();
  const text = async (p) => (await fetch(p)).text();
  await compile_with_library(await text("/good.wgsl"), "good.wgsl");
  let answer = "compiled";
  try {
    await compile_with_library(await text("/mine.wgsl"), "mine.wgsl");
  } catch (e) {
    answer = String(e);
  }
  document.getElementById("out").textContent = answer;
  await post("/result", answer);
} catch (e) {
  await post("/error", String(e && e.stack || e));
}
</script>"#;

/// A user's shader over the traversal library, calling `call` on line 6 (the corrected
/// one calls `bvh_trace_closest`).
fn shader_source(call: &str) -> String {
    format!(
        "@group(1) @binding(0) var<storage, read_write> out: array<u32>;\n\
         \n\
         @compute @workgroup_size(64)\n\
         fn main(@builtin(local_invocation_index) lane: u32) {{\n\
         \x20   let ray = BvhRay(vec3<f32>(0.0), 0.0, vec3<f32>(0.0, 0.0, 1.0), 1e30);\n\
         \x20   let r = {call}(ray, lane);\n\
         \x20   out[lane] = r.hit.prim;\n\
         }}\n"
    )
}

/// What the pages are served: the wasm and its bindings, the triangles and the rays.
#[derive(Clone)]
struct Served {
    /// The rest of the wasm-bindgen output (its `snippets/`), by path.
    dist: PathBuf,
    js: Arc<Vec<u8>>,
    wasm: Arc<Vec<u8>>,
    triangles: Arc<Vec<u8>>,
    rays: Arc<Vec<u8>>,
}

impl Served {
    /// The files by URL path: `/` is [`PAGE`], `/device.html` [`DEVICE_PAGE`],
    /// `/shader.html` [`SHADER_PAGE`] with its two shaders.
    fn files(&self) -> impl Fn(&str) -> Option<Vec<u8>> + Send + Sync + 'static {
        let s = self.clone();
        move |path: &str| match path {
            "/" => Some(PAGE.as_bytes().to_vec()),
            "/device.html" => Some(DEVICE_PAGE.as_bytes().to_vec()),
            "/shader.html" => Some(SHADER_PAGE.as_bytes().to_vec()),
            "/good.wgsl" => Some(shader_source("bvh_trace_closest").into_bytes()),
            "/mine.wgsl" => Some(shader_source("bvh_trace_closestt").into_bytes()),
            "/bvhtrace_web.js" => Some(s.js.to_vec()),
            "/bvhtrace_web_bg.wasm" => Some(s.wasm.to_vec()),
            "/triangles.bin" => Some(s.triangles.to_vec()),
            "/rays.bin" => Some(s.rays.to_vec()),
            p => browser::folder(s.dist.clone())(p),
        }
    }
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

/// The command line: the folder, the image size, the device builders to check.
struct Args {
    dist: PathBuf,
    size: (u32, u32),
    builders: Vec<String>,
    scene: Option<String>,
    default_limits: bool,
}

fn parse_args() -> Result<Args, Error> {
    let usage = "usage: browser_parity DIST [--size WxH] [--device-builders LIST|none] [--scene SPEC] \
         [--default-limits]";
    let mut args = std::env::args().skip(1);
    let dist = PathBuf::from(args.next().ok_or(usage)?);
    let mut size = (256u32, 192u32);
    let mut builders = vec!["gpu-ploc".to_string(), "gpu-lbvh".to_string()];
    let mut scene = None;
    let mut default_limits = false;
    while let Some(a) = args.next() {
        match a.as_str() {
            "--size" => size = parse_size(&args.next().ok_or("--size needs WxH")?)?,
            "--device-builders" => {
                let list = args.next().ok_or("--device-builders needs a list")?;
                builders = match list.as_str() {
                    "none" => Vec::new(),
                    _ => list.split(',').map(str::to_string).collect(),
                };
            }
            "--scene" => scene = Some(args.next().ok_or("--scene needs a scene")?),
            "--default-limits" => default_limits = true,
            other => return Err(format!("unknown argument {other}\n{usage}").into()),
        }
    }
    Ok(Args {
        dist,
        size,
        builders,
        scene,
        default_limits,
    })
}

fn run() -> Result<(), Error> {
    let args = parse_args()?;
    let (dist, (w, h)) = (&args.dist, args.size);
    let chromium = browser::chromium().ok_or("no chromium installed (apt-get install chromium)")?;
    let (spec, tris) = browser::scene_or_bunny(args.scene.clone())?;
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
    let b = bvh.bounds();
    let rays = Camera::frame(b.min, b.max, w as f32 / h as f32).rays(w, h);
    let opts = TraceOptions::closest(Traversal::Stackless);
    let cpu = trace_rays(&bvh, &rays, &opts).hits;

    let flat: Vec<f32> = tris
        .iter()
        .flat_map(|t| t.iter().flat_map(|v| v.to_array()))
        .collect();
    let read = |name: &str| {
        std::fs::read(dist.join(name)).map_err(|e| format!("{}: {e}", dist.join(name).display()))
    };
    let served = Served {
        dist: dist.clone(),
        js: Arc::new(read("bvhtrace_web.js")?),
        wasm: Arc::new(read("bvhtrace_web_bg.wasm")?),
        triangles: Arc::new(bytemuck::cast_slice::<f32, u8>(&flat).to_vec()),
        rays: Arc::new(bytemuck::cast_slice(&rays).to_vec()),
    };
    println!(
        "{spec}: {} triangles ({} MB of nodes, {} MB of triangles), {} rays; wasm {} bytes",
        bvh.triangles().len(),
        std::mem::size_of_val(bvh.nodes()) >> 20,
        std::mem::size_of_val(bvh.triangles()) >> 20,
        w * h,
        served.wasm.len()
    );
    let page = match args.default_limits {
        true => "/?limits=default",
        false => "/",
    };
    let bytes = match browser::run_page(&chromium, served.files(), page, Duration::from_secs(600))?
    {
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
    println!(
        "browser: {adapter}; trace {trace_ms:.1} ms ({:.2} Mrays/s), page load to hits {page_ms:.0} ms (build, upload, two traces)",
        cpu.len() as f64 / trace_ms / 1e3
    );
    // WebGPU's default storage binding is 128 MiB; the adapter may offer more.
    let largest = std::mem::size_of_val(bvh.nodes()).max(std::mem::size_of_val(bvh.triangles()));
    if largest > 128 << 20 && !adapter.contains("in pages") {
        match args.default_limits {
            true => return Err("a tree over 128 MiB was not split under default limits".into()),
            false => println!("note: the tree was bound whole: the adapter's limit holds it"),
        }
    }
    let differ = differing(&gpu, &cpu);
    println!(
        "browser parity: {} hits, {} differ",
        cpu.len(),
        differ.len()
    );
    show_differences(&differ, &rays, &gpu, &cpu, "browser");
    if !differ.is_empty() {
        return Err(format!(
            "{} of {} hits differ from the CPU twin's",
            differ.len(),
            cpu.len()
        )
        .into());
    }
    let scene = Scene {
        tris: &tris,
        rays: &rays,
        cpu_built: &bvh,
        cpu_hits: &cpu,
    };
    for builder in &args.builders {
        device_build(&chromium, &served, &scene, builder)?;
    }
    shader_error(&chromium, &served)?;
    example_page(&chromium, dist, None)?;
    match args.builders.first() {
        Some(builder) => example_page(&chromium, dist, Some(builder)),
        None => Ok(()),
    }
}

/// The indices of the hits in `a` that differ from `b`'s, bit for bit (a length
/// mismatch counts each missing hit).
fn differing(a: &[Hit], b: &[Hit]) -> Vec<usize> {
    (0..a.len().max(b.len()))
        .filter(|&i| match (a.get(i), b.get(i)) {
            (Some(x), Some(y)) => bytemuck::bytes_of(x) != bytemuck::bytes_of(y),
            _ => true,
        })
        .collect()
}

/// Prints the first few differing hits, `name`'s beside the CPU's.
fn show_differences(differ: &[usize], rays: &[Ray], got: &[Hit], cpu: &[Hit], name: &str) {
    for &i in differ.iter().take(5) {
        println!(
            "  ray {i}: {:?}\n    {name:<8}{:?}\n    cpu     {:?}",
            rays.get(i),
            got.get(i),
            cpu.get(i)
        );
    }
}

/// The scene of the checks: its triangles, the camera's rays, the CPU's binned-SAH tree
/// over them and the CPU walk's hits over that tree.
struct Scene<'a> {
    tris: &'a [Triangle],
    rays: &'a [Ray],
    cpu_built: &'a FlatBvh,
    cpu_hits: &'a [Hit],
}

/// What the device-build page sent.
struct DeviceReport {
    upload_ms: f64,
    build_ms: f64,
    readback_ms: f64,
    first_build_ms: f64,
    iterations: f64,
    same_tree: bool,
    nodes: f64,
    sah: f64,
    /// The browser's GPU hits and its CPU walk's, each followed by the trace's time.
    gpu: Vec<Hit>,
    cpu: Vec<Hit>,
    tree: FlatBvh,
    invariants: String,
}

/// `len` bytes at `*at` of `bytes` (advancing `at`), or an error naming `what`.
fn take<'a>(bytes: &'a [u8], at: &mut usize, len: usize, what: &str) -> Result<&'a [u8], Error> {
    let got = at
        .checked_add(len)
        .and_then(|end| bytes.get(*at..end))
        .ok_or_else(|| format!("the page sent {} bytes: {what} is cut short", bytes.len()))?;
    *at += len;
    Ok(got)
}

/// Hits followed by an f64 of milliseconds, as the page's exports send them.
fn hits_of(bytes: &[u8]) -> Result<Vec<Hit>, Error> {
    let size = std::mem::size_of::<Hit>();
    if bytes.len() < 8 || !(bytes.len() - 8).is_multiple_of(size) {
        return Err(format!("{} bytes of hits and a time", bytes.len()).into());
    }
    Ok(bytemuck::pod_collect_to_vec(&bytes[..bytes.len() - 8]))
}

/// A read-back tree as `tree_bytes` (bvhtrace-web) lays it out.
fn tree_of(bytes: &[u8]) -> Result<FlatBvh, Error> {
    let mut at = 0;
    let head: Vec<u32> = bytemuck::pod_collect_to_vec(take(bytes, &mut at, 16, "the tree's head")?);
    let (depth, nodes, tris) = (head[0], head[1] as usize, head[2] as usize);
    let nodes: Vec<FlatNode> =
        bytemuck::pod_collect_to_vec(take(bytes, &mut at, nodes * 32, "nodes")?);
    let tris: Vec<FlatTriangle> =
        bytemuck::pod_collect_to_vec(take(bytes, &mut at, tris * 48, "triangles")?);
    if at != bytes.len() {
        return Err(format!("{} bytes after the tree", bytes.len() - at).into());
    }
    Ok(FlatBvh::from_parts(nodes, tris, depth))
}

impl DeviceReport {
    fn parse(bytes: &[u8]) -> Result<DeviceReport, Error> {
        let mut at = 0;
        let head: Vec<f64> =
            bytemuck::pod_collect_to_vec(take(bytes, &mut at, 11 * 8, "the head")?);
        let gpu = hits_of(take(bytes, &mut at, head[8] as usize, "the GPU hits")?)?;
        let cpu = hits_of(take(bytes, &mut at, head[9] as usize, "the CPU hits")?)?;
        let tree = tree_of(take(bytes, &mut at, head[10] as usize, "the tree")?)?;
        Ok(DeviceReport {
            upload_ms: head[0],
            build_ms: head[1],
            readback_ms: head[2],
            first_build_ms: head[3],
            iterations: head[4],
            same_tree: head[5] == 1.0,
            nodes: head[6],
            sah: head[7],
            gpu,
            cpu,
            tree,
            invariants: String::from_utf8_lossy(&bytes[at..]).into_owned(),
        })
    }
}

/// What is wrong with a read-back tree over `tris`, if anything: the invariants, each
/// input triangle held exactly once with its corners bit for bit, the figures the page
/// computed from it.
fn tree_problems(r: &DeviceReport, tris: &[Triangle]) -> Vec<String> {
    let mut problems = Vec::new();
    if !r.invariants.is_empty() {
        problems.push(format!("in the browser: {}", r.invariants));
    }
    if let Err(e) = r.tree.check_invariants() {
        problems.push(format!("check_invariants: {e}"));
    }
    let mut seen = vec![false; tris.len()];
    for t in r.tree.triangles() {
        let prim = t.prim as usize;
        let same = tris.get(prim).is_some_and(|src| {
            [t.v0, t.v1, t.v2]
                .iter()
                .zip(src)
                .all(|(a, b)| a.map(f32::to_bits) == b.to_array().map(f32::to_bits))
        });
        // `same` holds only for a prim within `tris`.
        if !same || std::mem::replace(&mut seen[prim], true) {
            problems.push(format!(
                "triangle {prim} is not the input's, or is held twice"
            ));
            break;
        }
    }
    if r.tree.triangles().len() != tris.len() {
        problems.push(format!(
            "{} triangles for {} input triangles",
            r.tree.triangles().len(),
            tris.len()
        ));
    }
    let stats = BvhStats::of(&r.tree);
    if r.nodes != stats.nodes as f64 || (r.sah - stats.sah_cost).abs() > 1e-9 * stats.sah_cost {
        problems.push(format!(
            "the page says {} nodes and SAH {}, the tree has {} and {}",
            r.nodes, r.sah, stats.nodes, stats.sah_cost
        ));
    }
    if !r.same_tree {
        problems.push("the page's two builds gave different trees".into());
    }
    problems
}

/// The device-build check for `builder` (see the module docs).
fn device_build(
    chromium: &str,
    served: &Served,
    scene: &Scene<'_>,
    builder: &str,
) -> Result<(), Error> {
    let bytes = match browser::run_page(
        chromium,
        served.files(),
        &format!("/device.html?builder={builder}"),
        Duration::from_secs(600),
    )? {
        Report::Result(bytes) => bytes,
        Report::Error(e) => {
            return Err(format!("the device-build page ({builder}) failed: {e}").into());
        }
    };
    let r = DeviceReport::parse(&bytes)?;
    let problems = tree_problems(&r, scene.tris);
    let stats = BvhStats::of(&r.tree);
    let cpu_stats = BvhStats::of(scene.cpu_built);
    let iterations = match r.iterations > 0.0 {
        true => format!(", {} clustering iterations", r.iterations),
        false => String::new(),
    };
    println!(
        "browser device build ({builder}): {} nodes, depth {}, SAH {:.2} (the CPU's binned SAH {:.2}){iterations}",
        stats.nodes,
        r.tree.depth(),
        stats.sah_cost,
        cpu_stats.sah_cost,
    );
    // The CPU walk here over the tree the browser read back: the reference both of the
    // browser's answers must equal.
    let here = trace_rays(
        &r.tree,
        scene.rays,
        &TraceOptions::closest(Traversal::Stackless),
    )
    .hits;
    let (gpu_differ, cpu_differ) = (differing(&r.gpu, &here), differing(&r.cpu, &here));
    // The hit rule does not depend on the tree: the CPU-built tree's hits, bit for bit.
    let other_tree = differing(&here, scene.cpu_hits);
    println!(
        "browser device build ({builder}): built in {:.1} ms (upload {:.1}, dispatches {:.1}, read back {:.1}; first build {:.0} ms with compilation); tree {}; {} hits, {} differ from the CPU walks over the read-back tree ({} in the browser's CPU walk; {} from the CPU-built tree's hits)",
        r.upload_ms + r.build_ms + r.readback_ms,
        r.upload_ms,
        r.build_ms,
        r.readback_ms,
        r.first_build_ms,
        if problems.is_empty() {
            "passes check_invariants, holds every triangle once, same from both builds"
        } else {
            "FAILS"
        },
        here.len(),
        gpu_differ.len(),
        cpu_differ.len(),
        other_tree.len()
    );
    show_differences(&gpu_differ, scene.rays, &r.gpu, &here, "browser");
    show_differences(&cpu_differ, scene.rays, &r.cpu, &here, "wasm cpu");
    show_differences(&other_tree, scene.rays, &here, scene.cpu_hits, "device");
    for p in &problems {
        println!("  {p}");
    }
    let differ = [&gpu_differ, &cpu_differ, &other_tree];
    if !problems.is_empty() || differ.iter().any(|d| !d.is_empty()) {
        return Err(format!(
            "the device-built tree ({builder}): {} problems; {} GPU hits and {} WebAssembly CPU-walk hits differ from the CPU walk here, which differs from the CPU-built tree's in {}",
            problems.len(),
            gpu_differ.len(),
            cpu_differ.len(),
            other_tree.len()
        )
        .into());
    }
    Ok(())
}

/// The shader check: a user's shader with a mistake, compiled after the traversal library
/// on the browser's WebGPU, is an error naming its own file, line and identifier (the
/// line counted in the user's source, not in the library before it), where the corrected
/// shader compiles.
fn shader_error(chromium: &str, served: &Served) -> Result<(), Error> {
    let answer = match browser::run_page(
        chromium,
        served.files(),
        "/shader.html",
        Duration::from_secs(300),
    )? {
        Report::Result(bytes) => String::from_utf8_lossy(&bytes).into_owned(),
        Report::Error(e) => return Err(format!("the shader page failed: {e}").into()),
    };
    println!("browser shader error: {answer}");
    match answer.starts_with("mine.wgsl:6:") && answer.contains("bvh_trace_closestt") {
        true => Ok(()),
        false => Err(format!(
            "the shader with a mistake on line 6 gave {answer:?}, not an error naming mine.wgsl:6"
        )
        .into()),
    }
}

/// The library's example page (`index.html`): four rays over a unit quad of two triangles,
/// the hits printed on the page. Three hit at t = 5 (the ray on the shared diagonal hits
/// exactly one of the two triangles: the test is watertight), the fourth misses. With
/// `builder`, the page builds the BVH on the device and says so on one more line.
fn example_page(chromium: &str, dist: &Path, builder: Option<&String>) -> Result<(), Error> {
    let query = builder.map(|b| format!("&builder={b}")).unwrap_or_default();
    let text = match browser::run_page(
        chromium,
        browser::folder(dist.to_path_buf()),
        &format!("/index.html?report=1{query}"),
        Duration::from_secs(300),
    )? {
        Report::Result(bytes) => String::from_utf8_lossy(&bytes).into_owned(),
        Report::Error(e) => return Err(format!("the example page failed: {e}").into()),
    };
    let lines: Vec<&str> = text.lines().collect();
    // With a device build, the line after the adapter's says so.
    let built = builder.is_none_or(|b| {
        lines
            .get(1)
            .is_some_and(|l| l.starts_with(&format!("BVH built on the device ({b})")))
    });
    let first = 1 + usize::from(builder.is_some());
    let hit = |i: usize, tri: &str| {
        lines
            .get(first + i)
            .is_some_and(|l| l.contains(&format!("triangle {tri}")) && l.contains("t = 5"))
    };
    let ok = built
        && lines.len() == first + 5
        && hit(0, "0")
        && hit(1, "1")
        && (hit(2, "0") || hit(2, "1"))
        && lines[first + 3].ends_with(": miss");
    let shown: Vec<&str> = lines.iter().skip(1).copied().collect();
    let name = builder.map(|b| format!(" (built on the device, {b})"));
    println!(
        "example page{}: {}",
        name.unwrap_or_default(),
        shown.join(" | ")
    );
    match ok {
        true => Ok(()),
        false => Err(format!("the example page printed:\n{text}").into()),
    }
}
