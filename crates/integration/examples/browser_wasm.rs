//! The npm package's WebAssembly walk in a browser, hit for hit and against three-mesh-bvh:
//! serves the package (DIST: `web/package.sh`'s `web/dist/packed/package`, as `npm
//! install` unpacks it) to headless Chromium,
//! whose page builds a `Bvh` over the scene's triangles and traces a camera's rays with
//! it on one thread, in a batch (`intersect`) and one ray at a time (`raycastFirst`).
//! Both answers must equal the CPU walk's here (`trace_rays`, same triangles, same rays)
//! bit for bit. Where three.js and three-mesh-bvh are installed (`--modules DIR`, by
//! default `web/node_modules`: `npm ci` in `web/`), the same page builds a `MeshBVH` over the same triangles and
//! traces the same rays with its `raycastFirst` (both sides of each triangle), and the
//! two libraries' hits are compared ray for ray (the rule of `web/tests/three.mjs`: the
//! same triangle, or a tie at a shared edge, at distances within 1e-5 relative).
//!
//! `Bvh.create` must choose the WebAssembly walk on SwiftShader (a CPU device), saying so,
//! and the WebGPU backend asked for must give the WebAssembly walk's hits, bit for bit, as
//! must a compute shader of the page's own on a WebGPU device of its own, composed after
//! the library `bvh.wgsl()` gives and bound to the arrays it gives.
//! The tree built in a worker (`buildInWorker`) must be the page's, byte for byte.
//! The same rays go over web workers too (`bvhtrace/workers`' `BvhWorkers`, as many as the
//! page's hardware concurrency), whose hits must be the one thread's.
//!
//! With `--example DIR`, also opens the three.js example page (DIR/three.html, which
//! `web/package.sh` puts in `web/dist`) and checks that bvhtrace's `acceleratedRaycast`
//! gave the same closest hit as three.js's own `Mesh.raycast` for every one of its rays.
//!
//! Prints the rays per second of each on the page's one thread, and the page load to
//! first hits (the wasm fetched and compiled, the scene fetched, the BVH built and the
//! rays traced); exits non-zero on any difference, page error or timeout.
//!
//! ```text
//! cargo run --release -p bvhtrace-integration --example browser_wasm -- DIST [--size WxH] [--scene SPEC] [--modules DIR] [--example DIR]
//! ```
//!
//! The scene is `bunny_69k` from the shared scenes when that folder is there, else the
//! builtin icosphere (said in the output).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use bvhtrace_core::{BuildOptions, FlatBvh, Hit, TraceOptions, Traversal, trace_rays};
use bvhtrace_integration::browser::{self, Report};
use bvhtrace_scene::Camera;
use bvhtrace_shade::args::parse_size;

type Error = Box<dyn std::error::Error>;

/// The page: builds the Bvh, traces, and posts the hits of both calls, the figures
/// ([`Figures`], f64 each) and a line on three-mesh-bvh.
const PAGE: &str = r#"<!doctype html><meta charset="utf-8"><pre id="out">running</pre>
<script type="importmap">{"imports": {
  "three": "/node_modules/three/build/three.module.js",
  "three-mesh-bvh": "/node_modules/three-mesh-bvh/src/index.js"}}</script>
<script type="module">
const post = (path, body) => fetch(path, { method: "POST", body });
addEventListener("error", (e) => post("/error", `${e.message} (${e.filename}:${e.lineno})`));
addEventListener("unhandledrejection", (e) => post("/error", String(e.reason)));
const best = (runs, f) => {
  let ms = Infinity, out;
  for (let k = 0; k < runs; k++) {
    const t0 = performance.now();
    out = f();
    ms = Math.min(ms, performance.now() - t0);
  }
  return [ms, out];
};
// A compute shader of the page's own, on a WebGPU device of its own (no wgpu): the
// library and arrays `bvh.wgsl()` gives, one ray per invocation; the hits it reads back
// that differ from `want` (the WebAssembly walk's, in the layout of Hit), bit for bit.
async function ownShader(bvh, rays, want) {
  const adapter = await navigator.gpu.requestAdapter();
  const device = await adapter.requestDevice();
  const lib = bvh.wgsl(0);
  const code = lib.source + `
@group(1) @binding(0) var<storage, read> my_rays: array<BvhRay>;
@group(1) @binding(1) var<storage, read_write> my_hits: array<BvhHit>;
@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
  if (id.x < arrayLength(&my_rays)) {
    my_hits[id.x] = bvh_trace_closest(my_rays[id.x], lane).hit;
  }
}`;
  const buffer = (data, usage) => {
    const b = device.createBuffer({ size: data.byteLength, usage, mappedAtCreation: true });
    new Uint8Array(b.getMappedRange()).set(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
    b.unmap();
    return b;
  };
  const S = GPUBufferUsage.STORAGE;
  const pipeline = device.createComputePipeline({
    layout: "auto", compute: { module: device.createShaderModule({ code }), entryPoint: "main" } });
  const bvhGroup = device.createBindGroup({ layout: pipeline.getBindGroupLayout(lib.group),
    entries: lib.bindings.map((b) => ({ binding: b.binding, resource: { buffer: buffer(b.data, S) } })) });
  const n = rays.length / 8;
  const out = device.createBuffer({ size: 16 * n, usage: S | GPUBufferUsage.COPY_SRC });
  const read = device.createBuffer({ size: 16 * n, usage: GPUBufferUsage.MAP_READ | GPUBufferUsage.COPY_DST });
  const mine = device.createBindGroup({ layout: pipeline.getBindGroupLayout(1), entries: [
    { binding: 0, resource: { buffer: buffer(rays, S) } }, { binding: 1, resource: { buffer: out } }] });
  const start = performance.now();
  const enc = device.createCommandEncoder();
  const pass = enc.beginComputePass();
  pass.setPipeline(pipeline);
  pass.setBindGroup(lib.group, bvhGroup);
  pass.setBindGroup(1, mine);
  pass.dispatchWorkgroups(Math.ceil(n / 64));
  pass.end();
  enc.copyBufferToBuffer(out, 0, read, 0, 16 * n);
  device.queue.submit([enc.finish()]);
  await read.mapAsync(GPUMapMode.READ);
  const got = new Uint32Array(read.getMappedRange());
  let differ = 0;
  for (let i = 0; i < 4 * n; i += 4) {
    differ += got[i] !== want[i] || got[i + 1] !== want[i + 1] || got[i + 2] !== want[i + 2]
      || got[i + 3] !== want[i + 3];
  }
  const ms = performance.now() - start;
  device.destroy();
  return { differ, ms };
}
try {
  const { default: init, Bvh } = await import("./bvhtrace_web.js");
  const get = async (p) => new Float32Array(await (await fetch(p)).arrayBuffer());
  let compiled = 0;
  const [, tris, rays] = await Promise.all([init().then(() => (compiled = performance.now())),
    get("/triangles.bin"), get("/rays.bin")]);
  const n = rays.length / 8;
  const origins = new Float32Array(3 * n), dirs = new Float32Array(3 * n);
  for (let i = 0; i < n; i++) {
    origins.set(rays.subarray(8 * i, 8 * i + 3), 3 * i);
    dirs.set(rays.subarray(8 * i + 4, 8 * i + 7), 3 * i);
  }
  const [near, far] = [rays[3], rays[7]];
  const buildStart = performance.now();
  const bvh = new Bvh(tris);
  const buildMs = performance.now() - buildStart;
  bvh.intersect(origins, dirs, { near, far });
  const firstHits = performance.now();
  const [batchMs, hits] = best(3, () => bvh.intersect(origins, dirs, { near, far }));
  // Hits in the layout of bvhtrace_core::Hit: t, prim, u, v (16 bytes each).
  const packed = new Uint32Array(4 * n), asFloat = new Float32Array(packed.buffer);
  for (let i = 0; i < n; i++) {
    asFloat[4 * i] = hits.t[i]; packed[4 * i + 1] = hits.primitive[i];
    asFloat[4 * i + 2] = hits.u[i]; asFloat[4 * i + 3] = hits.v[i];
  }
  const single = new Uint32Array(4 * n), singleF = new Float32Array(single.buffer);
  const [singleMs] = best(3, () => {
    for (let i = 0, j = 0; i < n; i++, j += 3) {
      const h = bvh.raycastFirst(origins[j], origins[j + 1], origins[j + 2], dirs[j], dirs[j + 1],
        dirs[j + 2], near, far);
      if (h) { singleF[4 * i] = h.t; single[4 * i + 1] = h.primitive; singleF[4 * i + 2] = h.u; singleF[4 * i + 3] = h.v; }
      else { singleF[4 * i] = far; single[4 * i + 1] = 0xffffffff; }
    }
  });
  // The same rays over web workers, each with a copy of the tree.
  const { BvhWorkers, buildInWorker } = await import("./workers.js");
  // The same tree built off the page's thread.
  const elsewhere = await buildInWorker(tris);
  const [a, b] = [bvh.toBytes(), elsewhere.toBytes()];
  const sameTree = a.length === b.length && a.every((x, i) => x === b[i]);
  elsewhere.free();
  // The rays whose hit in `x` is not the WebAssembly walk's, bit for bit.
  const differing = (x) => {
    let d = 0;
    for (let i = 0; i < n; i++) {
      d += x.primitive[i] !== hits.primitive[i] || !Object.is(x.t[i], hits.t[i])
        || !Object.is(x.u[i], hits.u[i]) || !Object.is(x.v[i], hits.v[i]);
    }
    return d;
  };
  const pool = await BvhWorkers.create(bvh);
  let workersMs = Infinity, workersDiffer = 0;
  for (let k = 0; k < 3; k++) {
    const w = await pool.intersect(origins, dirs, { near, far });
    workersMs = Math.min(workersMs, w.ms);
    workersDiffer = differing(w);
  }
  const workers = pool.count;
  pool.terminate();
  // The automatic choice on this page's adapter, and the WebGPU backend asked for: its
  // kernels' hits must be the WebAssembly walk's.
  const auto = await Bvh.create(new Float32Array([0, 0, 0, 1, 0, 0, 0, 1, 0]));
  const choice = `${auto.backend}: ${auto.backendNote}`;
  auto.free();
  const gpu = await Bvh.create(tris, undefined, { backend: "webgpu" });
  const g = await gpu.intersectAsync(origins, dirs, { near, far });
  const gpuDiffer = differing(g);
  gpu.free();
  const own = await ownShader(bvh, rays, packed);
  const gpuNote = `${g.backend} (asked for): ${gpuDiffer} of ` +
    `${n} hits differ from the WebAssembly walk's, ${g.ms.toFixed(0)} ms; a shader of the page's ` +
    `own on its own device (bvh.wgsl()): ${own.differ} differ, ${own.ms.toFixed(0)} ms; the tree ` +
    `built in a worker (buildInWorker) ${sameTree ? "the same" : "a different one"}`;
  let threeMs = 0, threeHits = -1, same = 0, tie = 0, differ = 0, three = "three-mesh-bvh: not installed";
  try {
    const THREE = await import("three");
    const { MeshBVH } = await import("three-mesh-bvh");
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(tris, 3));
    const mesh = new MeshBVH(geometry);
    // MeshBVH indexes a non-indexed geometry and reorders that index: triangle
    // index[3 f] / 3 is its face f.
    const index = geometry.index.array;
    const ray = new THREE.Ray();
    const t = new Float64Array(n), prim = new Int32Array(n);
    [threeMs] = best(3, () => {
      for (let i = 0; i < n; i++) {
        ray.origin.fromArray(origins, 3 * i);
        ray.direction.fromArray(dirs, 3 * i);
        const h = mesh.raycastFirst(ray, THREE.DoubleSide, near, far);
        t[i] = h ? h.distance : Infinity;
        prim[i] = h ? Math.floor(index[3 * h.faceIndex] / 3) : -1;
      }
    });
    threeHits = 0;
    for (let i = 0; i < n; i++) {
      const ours = hits.primitive[i] !== 0xffffffff, theirs = prim[i] >= 0;
      threeHits += theirs;
      // Directions are not unit here: three's distance is t times the direction's length.
      const len = Math.hypot(dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]);
      if (!ours && !theirs) same++;
      else if (ours && theirs && Math.abs(hits.t[i] * len - t[i]) <= 1e-5 * t[i]) {
        if (hits.primitive[i] === prim[i]) same++; else tie++;
      } else differ++;
    }
    three = `three ${THREE.REVISION}`;
  } catch (e) {
    if (!String(e).includes("Failed to fetch") && !String(e).includes("resolve")) throw e;
  }
  const figures = new Float64Array([buildMs, firstHits, batchMs, singleMs, threeMs, threeHits,
    same, tie, differ, compiled, workersMs, workers, workersDiffer]);
  document.getElementById("out").textContent = "done";
  await post("/result", new Blob([figures, packed, single,
    [`${hits.backend}; ${three}`, choice, gpuNote, gpuDiffer + own.differ + (sameTree ? 0 : 1)]
      .join("\n")]));
} catch (e) {
  await post("/error", String(e && e.stack || e));
}
</script>"#;

/// The page's figures, in the order it posts them.
struct Figures {
    build_ms: f64,
    first_hits_ms: f64,
    batch_ms: f64,
    single_ms: f64,
    three_ms: f64,
    three_hits: f64,
    same: f64,
    tie: f64,
    differ: f64,
    compiled_ms: f64,
    workers_ms: f64,
    workers: f64,
    workers_differ: f64,
}

impl Figures {
    const COUNT: usize = 13;

    fn parse(bytes: &[u8]) -> Figures {
        let f =
            |i: usize| f64::from_le_bytes(bytes[8 * i..8 * i + 8].try_into().unwrap_or_default());
        Figures {
            build_ms: f(0),
            first_hits_ms: f(1),
            batch_ms: f(2),
            single_ms: f(3),
            three_ms: f(4),
            three_hits: f(5),
            same: f(6),
            tie: f(7),
            differ: f(8),
            compiled_ms: f(9),
            workers_ms: f(10),
            workers: f(11),
            workers_differ: f(12),
        }
    }
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Error> {
    let usage =
        "usage: browser_wasm DIST [--size WxH] [--scene SPEC] [--modules DIR] [--example DIR]";
    let mut args = std::env::args().skip(1);
    let dist = PathBuf::from(args.next().ok_or(usage)?);
    let (mut size, mut scene) = ((1024u32, 768u32), None);
    let mut modules = PathBuf::from("web/node_modules");
    let mut example = None;
    while let Some(a) = args.next() {
        match a.as_str() {
            "--size" => size = parse_size(&args.next().ok_or("--size needs WxH")?)?,
            "--scene" => scene = Some(args.next().ok_or("--scene needs a scene")?),
            "--modules" => modules = PathBuf::from(args.next().ok_or("--modules needs a folder")?),
            "--example" => {
                example = Some(PathBuf::from(
                    args.next().ok_or("--example needs a folder")?,
                ))
            }
            other => return Err(format!("unknown argument {other}\n{usage}").into()),
        }
    }
    let chromium = browser::chromium().ok_or("no chromium installed (apt-get install chromium)")?;
    let (spec, tris) = browser::scene_or_bunny(scene)?;
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
    let b = bvh.bounds();
    let (w, h) = size;
    let rays = Camera::frame(b.min, b.max, w as f32 / h as f32).rays(w, h);
    let cpu = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::Stackless)).hits;
    let flat: Vec<f32> = tris
        .iter()
        .flat_map(|t| t.iter().flat_map(|v| v.to_array()))
        .collect();
    let triangles = Arc::new(bytemuck::cast_slice::<f32, u8>(&flat).to_vec());
    let ray_bytes = Arc::new(bytemuck::cast_slice(&rays).to_vec());
    let package = browser::folder(dist.clone());
    let modules = browser::folder(modules);
    let files = move |path: &str| match path {
        "/" => Some(PAGE.as_bytes().to_vec()),
        "/triangles.bin" => Some(triangles.to_vec()),
        "/rays.bin" => Some(ray_bytes.to_vec()),
        p if p.starts_with("/node_modules/") => modules(&p["/node_modules".len()..]),
        p => package(p),
    };
    let bytes = match browser::run_page(&chromium, files, "/", Duration::from_secs(600))? {
        Report::Result(bytes) => bytes,
        Report::Error(e) => return Err(format!("the page failed: {e}").into()),
    };
    let n = cpu.len() * std::mem::size_of::<Hit>();
    let head = 8 * Figures::COUNT;
    if bytes.len() < head + 2 * n {
        return Err(format!("the page sent {} bytes for {} hits", bytes.len(), cpu.len()).into());
    }
    let f = Figures::parse(&bytes);
    let batch: Vec<Hit> = bytemuck::pod_collect_to_vec(&bytes[head..head + n]);
    let single: Vec<Hit> = bytemuck::pod_collect_to_vec(&bytes[head + n..head + 2 * n]);
    let text = String::from_utf8_lossy(&bytes[head + 2 * n..]).into_owned();
    let lines: Vec<&str> = text.lines().collect();
    let [note, choice, gpu, gpu_differ] = lines[..] else {
        return Err(format!("the page's notes: {text:?}").into());
    };
    report(&spec, tris.len(), &cpu, &batch, &single, &f, note)?;
    println!("browser automatic choice: {choice}");
    println!("browser WebGPU backend: {gpu}");
    if !choice.starts_with("wasm") || gpu_differ != "0" || !gpu.starts_with("webgpu") {
        return Err(
            "the automatic choice took WebGPU on SwiftShader, or the WebGPU backend's \
                    hits or the page's own shader's differ from the WebAssembly walk's"
                .into(),
        );
    }
    match example {
        Some(dir) => example_page(&chromium, dir),
        None => Ok(()),
    }
}

/// The three.js example page: every ray's closest hit the same with bvhtrace's
/// `acceleratedRaycast` as with three.js's own raycast.
fn example_page(chromium: &str, dir: PathBuf) -> Result<(), Error> {
    let page = "/three.html?report=1";
    let text = match browser::run_page(
        chromium,
        browser::folder(dir),
        page,
        Duration::from_secs(300),
    )? {
        Report::Result(bytes) => String::from_utf8_lossy(&bytes).into_owned(),
        Report::Error(e) => return Err(format!("the three.js example failed: {e}").into()),
    };
    println!("three.js example page: {}", text.replace('\n', " | "));
    let rays = text
        .split(" rays")
        .next()
        .and_then(|s| s.rsplit(' ').next());
    let same =
        rays.is_some_and(|n| text.contains(&format!("{n} of {n} rays: the same closest hit")));
    match same && !text.starts_with("error") {
        true => Ok(()),
        false => Err(format!("the three.js example page printed:\n{text}").into()),
    }
}

/// Prints the comparison and the rates; an error when any hit differs.
fn report(
    spec: &str,
    triangles: usize,
    cpu: &[Hit],
    batch: &[Hit],
    single: &[Hit],
    f: &Figures,
    note: &str,
) -> Result<(), Error> {
    let differ = |got: &[Hit]| {
        got.iter()
            .zip(cpu)
            .filter(|(a, b)| bytemuck::bytes_of(*a) != bytemuck::bytes_of(*b))
            .count()
    };
    let (db, ds) = (differ(batch), differ(single));
    let n = cpu.len();
    let hits = cpu.iter().filter(|h| h.is_hit()).count();
    let rate = |ms: f64| n as f64 / ms / 1e3;
    println!(
        "browser wasm walk ({spec}, {triangles} triangles; {note}): {n} rays, {hits} hits; \
         {db} differ from the CPU walk (intersect), {ds} (raycastFirst)"
    );
    println!(
        "browser wasm walk: Mrays/s on the page's one thread: intersect {:.2}, raycastFirst {:.2}; \
         page load to first hits {:.0} ms (the wasm compiled at {:.0} ms, the BVH built in {:.0} ms)",
        rate(f.batch_ms),
        rate(f.single_ms),
        f.first_hits_ms,
        f.compiled_ms,
        f.build_ms
    );
    println!(
        "browser wasm walk over {} web workers (BvhWorkers): {:.2} Mrays/s ({:.2}x one thread), \
         {} hits differ from one thread's",
        f.workers,
        rate(f.workers_ms),
        f.batch_ms / f.workers_ms,
        f.workers_differ
    );
    if f.three_hits >= 0.0 {
        println!(
            "three-mesh-bvh raycastFirst on the same rays: {:.2} Mrays/s (intersect {:.2}x, \
             raycastFirst {:.2}x it); hits {} (ours {hits}): same {}, a tie at a shared edge {}, \
             {} differ",
            rate(f.three_ms),
            f.three_ms / f.batch_ms,
            f.three_ms / f.single_ms,
            f.three_hits,
            f.same,
            f.tie,
            f.differ
        );
    } else {
        println!("SKIP: three-mesh-bvh beside it: not installed (npm ci in web/)");
    }
    if db + ds > 0 || f.differ > 0.0 || f.workers_differ > 0.0 {
        return Err(format!(
            "{db} (intersect) and {ds} (raycastFirst) of {n} hits differ from the CPU walk's; \
             {} from three-mesh-bvh's; {} over the workers from one thread's",
            f.differ, f.workers_differ
        )
        .into());
    }
    Ok(())
}
