//! The persistent API of the npm package: a [`Bvh`] built once over a mesh, traced as
//! often as asked, refitted when its vertices move, freed when the page is done with it.
//! Rays go through the CPU layout's walks compiled to WebAssembly (SIMD128 lanes), or
//! through the kernels on the page's WebGPU when it is a real GPU; both give the same
//! answers as every other bvhtrace backend.

use bvhtrace_core::{BuildOptions, FlatBvh, Hit, Query, Ray, TraceOptions, Traversal};
use bvhtrace_cpu::{CpuBvh, Isa, RayScratch};
use bvhtrace_gpu::engine::walks::STACK_LANES;
use bvhtrace_gpu::engine::{LibraryShape, wgsl_library};
use bvhtrace_gpu::{BvhStorage, GpuBvh, GpuContext, Tracer, UploadOptions};
use glam::Vec3;
use js_sys::{Float32Array, Object, Reflect, Uint32Array};
use std::cell::RefCell;
use wasm_bindgen::prelude::*;

use crate::choice::{self, Backend};

#[wasm_bindgen(typescript_custom_section)]
const TYPES: &'static str = r#"
/** How `intersect` traces: closest hit (the default) or any hit, over `[near, far)`. */
export interface TraceOptions {
  /** Any hit (occlusion: stops at the first triangle found) instead of the closest. */
  anyHit?: boolean;
  /** The smallest accepted distance (default 0), in units of each ray's direction. */
  near?: number;
  /** The largest distance, exclusive (default Infinity). */
  far?: number;
}

/** One answer per ray, in ray order, as typed arrays. */
export interface Hits {
  /** Rays traced. */
  count: number;
  /** Rays that hit a triangle. */
  hitCount: number;
  /** Each ray's hit distance (`far` for a miss). */
  t: Float32Array;
  /** Each ray's triangle index in the input order, 0xffffffff for a miss. */
  primitive: Uint32Array;
  /** Barycentric weight of the hit triangle's second corner. */
  u: Float32Array;
  /** Barycentric weight of the hit triangle's third corner. */
  v: Float32Array;
  /** What traced them: `"wasm-simd128"`, `"wasm"` or `"webgpu"`. */
  backend: string;
  /** Milliseconds the trace took (wall time, with the upload and read back on WebGPU). */
  ms: number;
}

/** The closest hit of one ray. */
export interface Hit {
  /** Distance along the ray, in units of its direction. */
  t: number;
  /** The triangle's index in the input order. */
  primitive: number;
  /** Barycentric weight of the second corner. */
  u: number;
  /** Barycentric weight of the third corner. */
  v: number;
  /** `origin + t * direction`. */
  point: [number, number, number];
}

/** `Hits` over an `InstancedBvh`: which instance each ray hit, and the triangle in its mesh. */
export interface InstancedHits extends Hits {
  /** The instance hit (in the order added), 0xffffffff for a miss. */
  instance: Uint32Array;
  /** The triangle's index in its mesh's input order, 0xffffffff for a miss. */
  meshPrimitive: Uint32Array;
}

/** A `Hit` over an `InstancedBvh`. */
export interface InstancedHit extends Hit {
  /** The instance hit. */
  instance: number;
  /** The triangle's index in its mesh's input order (`primitive` numbers every instance's). */
  meshPrimitive: number;
}

/** The WGSL traversal library for a shader of your own, and what to bind for it. */
export interface Wgsl {
  /** Prepend it to your WGSL. */
  source: string;
  /** The bind group its arrays are declared in. */
  group: number;
  /** Each array: upload `data` into a storage buffer, bind it read-only at `binding`. */
  bindings: { binding: number; name: string; data: Uint8Array }[];
  /** The most invocations a workgroup may have (the walks' stacks are per lane). */
  stackLanes: number;
}

/** Where `Bvh.create` traces. */
export interface CreateOptions {
  /**
   * `"auto"` (the default): WebGPU when the page's adapter is a real GPU, the WebAssembly
   * walk when it is a CPU device (SwiftShader, lavapipe) or there is none; `"webgpu"`;
   * `"wasm"`.
   */
  backend?: "auto" | "webgpu" | "wasm";
}
"#;

#[wasm_bindgen]
extern "C" {
    /// [`TYPES`]' `TraceOptions`.
    #[wasm_bindgen(typescript_type = "TraceOptions")]
    pub type TraceOptionsArg;
    /// [`TYPES`]' `Hits`.
    #[wasm_bindgen(typescript_type = "Hits")]
    pub type HitsOut;
    /// [`TYPES`]' `Hit`, or undefined.
    #[wasm_bindgen(typescript_type = "Hit | undefined")]
    pub type HitOut;
    /// [`TYPES`]' `Wgsl`.
    #[wasm_bindgen(typescript_type = "Wgsl")]
    pub type WgslOut;
    /// [`TYPES`]' `CreateOptions`.
    #[wasm_bindgen(typescript_type = "CreateOptions")]
    pub type CreateOptionsArg;
}

// One call into JavaScript per hit: setting each field through `Reflect` took eight.
#[wasm_bindgen(inline_js = "export function hit_object(t, primitive, u, v, x, y, z) {
  return { t, primitive, u, v, point: [x, y, z] };
}")]
extern "C" {
    /// A `Hit` from its numbers.
    #[allow(clippy::too_many_arguments)]
    fn hit_object(t: f32, primitive: u32, u: f32, v: f32, x: f32, y: f32, z: f32) -> HitOut;
}

/// The `Hit` object of `ray`'s hit `h`, with its point.
pub(crate) fn hit_of(ray: &Ray, h: &Hit) -> HitOut {
    let p = Vec3::from(ray.origin) + h.t * Vec3::from(ray.dir);
    hit_object(h.t, h.prim, h.u, h.v, p.x, p.y, p.z)
}

/// An error for JavaScript: an `Error` with the library's message.
pub(crate) fn err(e: impl std::fmt::Display) -> JsError {
    JsError::new(&e.to_string())
}

/// `object[key]` when it is there and not undefined.
fn field(object: &JsValue, key: &str) -> Option<JsValue> {
    Reflect::get(object, &JsValue::from_str(key))
        .ok()
        .filter(|v| !v.is_undefined() && !v.is_null())
}

/// Sets `object[key] = value`.
pub(crate) fn set(object: &Object, key: &str, value: &JsValue) -> Result<(), JsError> {
    Reflect::set(object, &JsValue::from_str(key), value)
        .map(|_| ())
        .map_err(|_| err(format!("cannot set {key} on the result")))
}

/// The triangles of `positions` (three floats per vertex) and `indices` (three per
/// triangle), or, without indices, of every nine floats.
fn triangles(
    positions: &[f32],
    indices: Option<&[u32]>,
) -> Result<Vec<bvhtrace_core::Triangle>, JsError> {
    if !positions.len().is_multiple_of(3) {
        return Err(err(format!(
            "positions: {} floats is not a whole number of vertices (three floats each)",
            positions.len()
        )));
    }
    let vertices: Vec<Vec3> = positions.chunks_exact(3).map(Vec3::from_slice).collect();
    let indices: Vec<[u32; 3]> = match indices {
        Some(idx) if !idx.len().is_multiple_of(3) => {
            return Err(err(format!(
                "indices: {} is not a whole number of triangles (three indices each)",
                idx.len()
            )));
        }
        Some(idx) => idx.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect(),
        None if !vertices.len().is_multiple_of(3) => {
            return Err(err(format!(
                "positions: {} vertices without indices is not a whole number of triangles \
                 (three vertices each)",
                vertices.len()
            )));
        }
        // Without indices, every three vertices in turn.
        None => (0..vertices.len() as u32 / 3)
            .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
            .collect(),
    };
    let mesh = bvhtrace_core::TriangleMesh {
        positions: vertices,
        indices,
    };
    mesh.triangles().map_err(err)
}

/// What a trace was asked: the query and the interval.
#[derive(Clone, Copy)]
pub(crate) struct Asked {
    pub query: Query,
    pub near: f32,
    pub far: f32,
}

impl Asked {
    /// Reads `TraceOptions` (every field optional).
    pub(crate) fn of(options: Option<&TraceOptionsArg>) -> Result<Asked, JsError> {
        let o: Option<&JsValue> = options.map(|o| o.as_ref());
        let number = |key: &str, default: f32| -> Result<f32, JsError> {
            match o.and_then(|o| field(o, key)) {
                None => Ok(default),
                Some(v) => v
                    .as_f64()
                    .map(|x| x as f32)
                    .filter(|x| !x.is_nan())
                    .ok_or_else(|| err(format!("options.{key} must be a number"))),
            }
        };
        let any = o
            .and_then(|o| field(o, "anyHit"))
            .is_some_and(|v| v.is_truthy());
        Ok(Asked {
            query: if any { Query::Any } else { Query::Closest },
            near: number("near", 0.0)?,
            far: number("far", f32::INFINITY)?,
        })
    }
}

/// The rays from `origins` and `directions` (three floats each, as many of both).
pub(crate) fn rays(origins: &[f32], directions: &[f32], asked: Asked) -> Result<Vec<Ray>, JsError> {
    if origins.len() != directions.len() || !origins.len().is_multiple_of(3) {
        return Err(err(format!(
            "{} origin floats and {} direction floats: three per ray, as many of each",
            origins.len(),
            directions.len()
        )));
    }
    Ok(origins
        .chunks_exact(3)
        .zip(directions.chunks_exact(3))
        .map(|(o, d)| {
            Ray::with_interval(
                Vec3::from_slice(o),
                Vec3::from_slice(d),
                asked.near,
                asked.far,
            )
        })
        .collect())
}

/// The hits as [`TYPES`]' `Hits`.
pub(crate) fn hits_out(hits: &[Hit], backend: &str, ms: f64) -> Result<HitsOut, JsError> {
    let n = hits.len();
    let hit_count = hits.iter().filter(|h| h.is_hit()).count();
    let (mut t, mut prim, mut u, mut v) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    for h in hits {
        t.push(h.t);
        prim.push(h.prim);
        u.push(h.u);
        v.push(h.v);
    }
    let out = Object::new();
    set(&out, "count", &JsValue::from(n as u32))?;
    set(&out, "hitCount", &JsValue::from(hit_count as u32))?;
    set(&out, "t", &Float32Array::from(&t[..]))?;
    set(&out, "primitive", &Uint32Array::from(&prim[..]))?;
    set(&out, "u", &Float32Array::from(&u[..]))?;
    set(&out, "v", &Float32Array::from(&v[..]))?;
    set(&out, "backend", &JsValue::from_str(backend))?;
    set(&out, "ms", &JsValue::from(ms))?;
    Ok(out.unchecked_into())
}

/// The tree on the page's WebGPU, and the walk its kernels take.
struct Device {
    ctx: GpuContext,
    bvh: GpuBvh,
    walk: Traversal,
}

impl Device {
    /// Uploads `flat` to `ctx` for the full-stack walk, in buffers (split into pages where
    /// an array exceeds a storage binding).
    fn upload(ctx: GpuContext, flat: &FlatBvh) -> Result<Device, JsError> {
        let walk = Traversal::FullStack;
        let opts = UploadOptions::for_traversal(walk).with_storage(BvhStorage::Buffers);
        let bvh = GpuBvh::upload(&ctx, flat, &opts).map_err(err)?;
        Ok(Device { ctx, bvh, walk })
    }
}

/// A bounding volume hierarchy over one triangle mesh, built once and traced as often as
/// asked (the way three-mesh-bvh's `MeshBVH` is used). `new Bvh(...)` builds it and traces
/// with the WebAssembly walk; `await Bvh.create(...)` may also put it on the page's
/// WebGPU. Call `free()` when done: its memory is WebAssembly's, not the garbage
/// collector's.
#[wasm_bindgen]
pub struct Bvh {
    pub(crate) flat: FlatBvh,
    cpu: CpuBvh,
    indices: Option<Vec<u32>>,
    device: Option<Device>,
    note: String,
    /// The one-ray walks' stack, kept between calls.
    scratch: RefCell<RayScratch>,
}

impl Bvh {
    /// Builds the tree and its CPU layout over `tris`.
    fn over(tris: &[bvhtrace_core::Triangle], indices: Option<Vec<u32>>) -> Result<Bvh, JsError> {
        let flat = FlatBvh::build(tris, &BuildOptions::default()).map_err(err)?;
        Bvh::of(flat, indices)
    }

    /// `flat` with its CPU layout, traced by the WebAssembly walk.
    fn of(flat: FlatBvh, indices: Option<Vec<u32>>) -> Result<Bvh, JsError> {
        let cpu = CpuBvh::from_flat(&flat).map_err(err)?;
        Ok(Bvh {
            flat,
            cpu,
            indices,
            device: None,
            note: choice::wasm_note(),
            scratch: RefCell::default(),
        })
    }

    /// Puts the tree where `options` asks (see [`Bvh::create`]).
    async fn choose(&mut self, options: Option<CreateOptionsArg>) -> Result<(), JsError> {
        let asked = options
            .as_ref()
            .and_then(|o| field(o.as_ref(), "backend"))
            .map(|v| v.as_string().unwrap_or_default())
            .unwrap_or_else(|| "auto".into());
        let backend = Backend::parse(&asked).map_err(err)?;
        let (ctx, note) = choice::device_for(backend).await.map_err(err)?;
        self.note = note;
        if let Some(ctx) = ctx {
            self.device = Some(Device::upload(ctx, &self.flat)?);
        }
        Ok(())
    }

    /// One ray on the kept stack.
    fn trace_one(&self, ray: &Ray, query: Query) -> Hit {
        let mut scratch = self.scratch.borrow_mut();
        bvhtrace_cpu::trace_ray_in(&self.cpu, ray, query, &mut scratch)
    }

    /// The name of the WebAssembly walk this build has.
    pub(crate) fn wasm_name() -> &'static str {
        match Isa::detect() {
            Isa::Simd128 => "wasm-simd128",
            _ => "wasm",
        }
    }

    /// Traces `rays` with the WebAssembly walk: in packets when neighbouring rays go one
    /// way (camera rays, shadow rays toward one light), else one at a time, as the native
    /// front door does; closest hits are the same to the bit either way.
    fn trace_wasm(&self, rays: &[Ray], query: Query) -> Vec<Hit> {
        match bvhtrace_cpu::coherent(rays) {
            true => bvhtrace_cpu::trace_packets(&self.cpu, rays, query),
            false => bvhtrace_cpu::trace_rays(&self.cpu, rays, query),
        }
    }
}

#[wasm_bindgen]
impl Bvh {
    /// Builds a BVH over `positions` (x, y, z per vertex) and `indices` (three per
    /// triangle); without indices, every three vertices are a triangle. Triangle `i` of the
    /// input is primitive `i` in every answer. Throws on positions that are not whole
    /// vertices, indices out of range, and NaN or infinite coordinates, naming the
    /// triangle.
    #[wasm_bindgen(constructor)]
    pub fn new(positions: &[f32], indices: Option<Vec<u32>>) -> Result<Bvh, JsError> {
        let tris = triangles(positions, indices.as_deref())?;
        Bvh::over(&tris, indices)
    }

    /// Builds a BVH over every triangle of a glTF 2.0 scene (`.glb` or `.gltf` with
    /// embedded buffers), each node's transform applied, in the order the scene lists
    /// them. `label` names the source in errors (a name ending in `.glb` requires the
    /// binary container).
    #[wasm_bindgen(js_name = fromGltf)]
    pub fn from_gltf(bytes: &[u8], label: Option<String>) -> Result<Bvh, JsError> {
        let label = label.unwrap_or_else(|| "scene.glb".into());
        let scene = bvhtrace_scene::load_gltf_slice(bytes, &label, None).map_err(err)?;
        let tris = scene.flattened_triangles().map_err(err)?;
        Bvh::over(&tris, None)
    }

    /// The tree as bytes, for `Bvh.fromBytes` in another worker or a later visit (a
    /// 16-byte head: `BVHT`, the format's version, the depth, then the node and triangle
    /// counts; then the nodes, 32 bytes each, and the triangles, 48 bytes each). The
    /// WebAssembly walk's layout is made again from them, not stored.
    #[wasm_bindgen(js_name = toBytes)]
    pub fn to_bytes(&self) -> Vec<u8> {
        let (nodes, tris) = (self.flat.nodes(), self.flat.triangles());
        let mut out = Vec::with_capacity(20 + 32 * nodes.len() + 48 * tris.len());
        out.extend_from_slice(SERIAL_MAGIC);
        for x in [
            SERIAL_VERSION,
            self.flat.depth(),
            nodes.len() as u32,
            tris.len() as u32,
        ] {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(bytemuck::cast_slice(nodes));
        out.extend_from_slice(bytemuck::cast_slice(tris));
        out
    }

    /// A BVH from `toBytes`' bytes, checked (every node, box and triangle) before use:
    /// bytes that are not such a tree are an error, never a wrong answer.
    #[wasm_bindgen(js_name = fromBytes)]
    pub fn from_bytes(bytes: &[u8]) -> Result<Bvh, JsError> {
        let flat = parse_serial(bytes).map_err(|why| err(format!("Bvh.fromBytes: {why}")))?;
        Bvh::of(flat, None)
    }

    /// `new Bvh(positions, indices)`, then the backend `options.backend` asks for (see
    /// `CreateOptions`): resolves to the BVH, whose `backend` says where `intersectAsync`
    /// traces and `backendNote` why.
    pub async fn create(
        positions: Vec<f32>,
        indices: Option<Vec<u32>>,
        options: Option<CreateOptionsArg>,
    ) -> Result<Bvh, JsError> {
        let mut bvh = Bvh::new(&positions, indices)?;
        bvh.choose(options).await?;
        Ok(bvh)
    }

    /// `Bvh.fromGltf(bytes, label)`, then the backend `options.backend` asks for, as
    /// `create` does.
    #[wasm_bindgen(js_name = createFromGltf)]
    pub async fn create_from_gltf(
        bytes: Vec<u8>,
        label: Option<String>,
        options: Option<CreateOptionsArg>,
    ) -> Result<Bvh, JsError> {
        let mut bvh = Bvh::from_gltf(&bytes, label)?;
        bvh.choose(options).await?;
        Ok(bvh)
    }

    /// Where `intersectAsync` traces: `"webgpu"`, or the WebAssembly walk
    /// (`"wasm-simd128"`, or `"wasm"` in a build without SIMD).
    #[wasm_bindgen(getter)]
    pub fn backend(&self) -> String {
        match self.device {
            Some(_) => "webgpu".into(),
            None => Bvh::wasm_name().into(),
        }
    }

    /// Why that backend: the adapter seen, or its absence.
    #[wasm_bindgen(getter, js_name = backendNote)]
    pub fn backend_note(&self) -> String {
        self.note.clone()
    }

    /// Triangles in the tree.
    #[wasm_bindgen(getter, js_name = triangleCount)]
    pub fn triangle_count(&self) -> u32 {
        self.flat.triangle_count() as u32
    }

    /// Nodes of the binary tree.
    #[wasm_bindgen(getter, js_name = nodeCount)]
    pub fn node_count(&self) -> u32 {
        self.flat.nodes().len() as u32
    }

    /// Longest root-to-leaf path, in edges.
    #[wasm_bindgen(getter)]
    pub fn depth(&self) -> u32 {
        self.flat.depth()
    }

    /// The box around every triangle: min x, y, z, then max x, y, z.
    pub fn bounds(&self) -> Float32Array {
        let b = self.flat.bounds();
        Float32Array::from(&[b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z][..])
    }

    /// Traces rays from `origins` along `directions` (three floats per ray each) with the
    /// WebAssembly walk, now: closest hit, or any hit with `options.anyHit`.
    pub fn intersect(
        &self,
        origins: &[f32],
        directions: &[f32],
        options: Option<TraceOptionsArg>,
    ) -> Result<HitsOut, JsError> {
        let asked = Asked::of(options.as_ref())?;
        let rays = rays(origins, directions, asked)?;
        let start = web_time::Instant::now();
        let hits = self.trace_wasm(&rays, asked.query);
        let ms = start.elapsed().as_secs_f64() * 1e3;
        hits_out(&hits, Bvh::wasm_name(), ms)
    }

    /// `intersect` on the backend chosen at `create` (WebGPU or the WebAssembly
    /// walk): the same answers, bit for bit.
    #[wasm_bindgen(js_name = intersectAsync)]
    pub async fn intersect_async(
        &self,
        origins: Vec<f32>,
        directions: Vec<f32>,
        options: Option<TraceOptionsArg>,
    ) -> Result<HitsOut, JsError> {
        let Some(device) = &self.device else {
            return self.intersect(&origins, &directions, options);
        };
        let asked = Asked::of(options.as_ref())?;
        let rays = rays(&origins, &directions, asked)?;
        let opts = TraceOptions::new(device.walk, asked.query);
        let out = device.bvh.trace_async(&rays, &opts).await.map_err(err)?;
        hits_out(&out.hits, "webgpu", out.wall_ms)
    }

    /// The closest hit of one ray from origin `(ox, oy, oz)` along direction `(dx, dy, dz)`
    /// within `[near, far)` (default `[0, Infinity)`), or undefined: three-mesh-bvh's
    /// `raycastFirst`, with the ray as six numbers (no array crosses into WebAssembly).
    #[allow(clippy::too_many_arguments)]
    #[wasm_bindgen(js_name = raycastFirst)]
    pub fn raycast_first(
        &self,
        ox: f32,
        oy: f32,
        oz: f32,
        dx: f32,
        dy: f32,
        dz: f32,
        near: Option<f32>,
        far: Option<f32>,
    ) -> HitOut {
        let ray = one_ray([ox, oy, oz], [dx, dy, dz], near, far);
        let h = self.trace_one(&ray, Query::Closest);
        match h.is_hit() {
            true => hit_of(&ray, &h),
            false => JsValue::UNDEFINED.unchecked_into(),
        }
    }

    /// Whether any triangle lies on the ray from `(ox, oy, oz)` along `(dx, dy, dz)` within
    /// `[near, far)`: a shadow ray's question, answered by the any-hit walk.
    #[allow(clippy::too_many_arguments)]
    pub fn occluded(
        &self,
        ox: f32,
        oy: f32,
        oz: f32,
        dx: f32,
        dy: f32,
        dz: f32,
        near: Option<f32>,
        far: Option<f32>,
    ) -> bool {
        let ray = one_ray([ox, oy, oz], [dx, dy, dz], near, far);
        self.trace_one(&ray, Query::Any).is_hit()
    }

    /// The vertices moved: `positions` holds the same vertices in their new places (the
    /// indices given at build time still apply). The tree's boxes are refitted, its
    /// topology kept, and the WebGPU copy, if any, uploaded again. An error leaves the
    /// BVH as it was.
    pub fn refit(&mut self, positions: &[f32]) -> Result<(), JsError> {
        let tris = triangles(positions, self.indices.as_deref())?;
        let mut flat = self.flat.clone();
        flat.refit(&tris).map_err(err)?;
        let cpu = CpuBvh::from_flat(&flat).map_err(err)?;
        if let Some(d) = &mut self.device {
            *d = Device::upload(d.ctx.clone(), &flat)?;
        }
        (self.flat, self.cpu) = (flat, cpu);
        Ok(())
    }

    /// The WGSL traversal library for a compute shader of your own on your own WebGPU
    /// device, with what to bind: `source` (prepend it to your WGSL: it declares
    /// `bvh_trace_closest(ray: BvhRay, lane: u32)`, `bvh_trace_any`, `bvh_hit_surface` and
    /// their structs, every name starting with `bvh_`, `Bvh` or `BVH_`), and `bindings`:
    /// for each, its `binding` number in `@group(group)` and the `data` to upload into a
    /// storage buffer bound there read-only (the tree's nodes at 0, its triangles at 1).
    /// The walk is the full stack, its stacks in workgroup memory: workgroups of at most
    /// `stackLanes` invocations, `lane` each one's `local_invocation_index`. Each array
    /// must fit one of your device's storage bindings (`maxStorageBufferBindingSize`).
    pub fn wgsl(&self, group: Option<u32>) -> Result<WgslOut, JsError> {
        let shape = LibraryShape::new(BvhStorage::Buffers, false, Traversal::FullStack);
        let library = wgsl_library(shape, group.unwrap_or(0));
        let arrays: [(u32, &str, &[u8]); 2] = [
            (0, "nodes", bytemuck::cast_slice(self.flat.nodes())),
            (1, "triangles", bytemuck::cast_slice(self.flat.triangles())),
        ];
        let bindings = js_sys::Array::new();
        for (binding, name, bytes) in arrays {
            let entry = Object::new();
            set(&entry, "binding", &JsValue::from(binding))?;
            set(&entry, "name", &JsValue::from_str(name))?;
            set(&entry, "data", &js_sys::Uint8Array::from(bytes))?;
            bindings.push(&entry);
        }
        let out = Object::new();
        set(&out, "source", &JsValue::from_str(library.source()))?;
        set(&out, "group", &JsValue::from(library.group()))?;
        set(&out, "bindings", &bindings)?;
        set(&out, "stackLanes", &JsValue::from(STACK_LANES))?;
        Ok(out.unchecked_into())
    }
}

/// The first bytes of `Bvh.toBytes`.
const SERIAL_MAGIC: &[u8; 4] = b"BVHT";

/// The version of `Bvh.toBytes`' format.
const SERIAL_VERSION: u32 = 1;

/// The tree in `toBytes`' bytes, or what is wrong with them.
fn parse_serial(bytes: &[u8]) -> Result<FlatBvh, String> {
    if bytes.len() < 20 || &bytes[..4] != SERIAL_MAGIC {
        return Err("not a bvhtrace tree (no BVHT head)".into());
    }
    let word = |i: usize| u32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    let (version, depth, nodes, tris) = (word(4), word(8), word(12) as usize, word(16) as usize);
    if version != SERIAL_VERSION {
        return Err(format!(
            "format version {version}; this build reads {SERIAL_VERSION}"
        ));
    }
    let (node_bytes, tri_bytes) = (32 * nodes, 48 * tris);
    if bytes.len() != 20 + node_bytes + tri_bytes {
        return Err(format!(
            "{} bytes for {nodes} nodes and {tris} triangles ({} expected)",
            bytes.len(),
            20 + node_bytes + tri_bytes
        ));
    }
    let nodes = bytemuck::pod_collect_to_vec(&bytes[20..20 + node_bytes]);
    let tris = bytemuck::pod_collect_to_vec(&bytes[20 + node_bytes..]);
    let flat = FlatBvh::from_parts(nodes, tris, depth);
    flat.check_invariants()?;
    Ok(flat)
}

/// One ray from JavaScript's numbers.
pub(crate) fn one_ray(origin: [f32; 3], dir: [f32; 3], near: Option<f32>, far: Option<f32>) -> Ray {
    Ray::with_interval(
        Vec3::from(origin),
        Vec3::from(dir),
        near.unwrap_or(0.0),
        far.unwrap_or(f32::INFINITY),
    )
}
