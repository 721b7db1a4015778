//! The one-shot calls the browser test and the example page use: each builds a BVH,
//! traces and returns the hits with how they were made.

use bvhtrace_core::{
    BuildOptions, BvhStats, FlatBvh, Ray, TraceOptions, TraceOutput, Traversal, Triangle,
    trace_rays,
};
use bvhtrace_gpu::{
    AdapterChoice, BvhStorage, ContextOptions, GpuBuildOptions, GpuBuildTimes, GpuBuilderKind,
    GpuBvh, GpuContext, Tracer, UploadOptions,
};
use wasm_bindgen::prelude::*;

fn js(e: impl std::fmt::Display) -> JsValue {
    JsValue::from_str(&e.to_string())
}

/// The triangles in `floats` (nine each: three corners); an error when the count is
/// not a multiple of nine.
fn triangles(floats: &[f32]) -> Result<Vec<Triangle>, JsValue> {
    if !floats.len().is_multiple_of(9) {
        return Err(js(format!(
            "{} triangle floats: nine per triangle expected",
            floats.len()
        )));
    }
    Ok(floats
        .chunks_exact(9)
        .map(|t| {
            let v = |i: usize| glam::Vec3::new(t[i], t[i + 1], t[i + 2]);
            [v(0), v(3), v(6)]
        })
        .collect())
}

/// The rays in `floats` (eight each, the layout of [`Ray`]); an error when the count
/// is not a multiple of eight.
fn rays(floats: &[f32]) -> Result<Vec<Ray>, JsValue> {
    if !floats.len().is_multiple_of(8) {
        return Err(js(format!(
            "{} ray floats: eight per ray expected",
            floats.len()
        )));
    }
    Ok(bytemuck::pod_collect_to_vec::<f32, Ray>(floats))
}

/// The browser's WebGPU device.
async fn context() -> Result<GpuContext, JsValue> {
    context_with(&ContextOptions::default()).await
}

/// The browser's WebGPU device, made with `options`.
async fn context_with(options: &ContextOptions) -> Result<GpuContext, JsValue> {
    GpuContext::new_async(AdapterChoice::Auto, options)
        .await
        .map_err(js)
}

/// Uploads `bvh` with the BVH in buffers and traces `rays` with `walk`, closest hit,
/// twice: the first trace builds the pipeline, the second is returned, with how the
/// tree was bound (`""`, or its pages when it was larger than one of the device's
/// storage bindings).
async fn trace_twice(
    ctx: &GpuContext,
    bvh: &FlatBvh,
    rays: &[Ray],
    walk: Traversal,
) -> Result<(TraceOutput, String), JsValue> {
    let opts = UploadOptions::for_traversal(walk).with_storage(BvhStorage::Buffers);
    let gpu = GpuBvh::upload(ctx, bvh, &opts).map_err(js)?;
    let opts = TraceOptions::closest(walk);
    gpu.trace_async(rays, &opts).await.map_err(js)?;
    let out = gpu.trace_async(rays, &opts).await.map_err(js)?;
    let p = gpu.tree().pages;
    let pages = match !p.is_one() {
        true => format!(
            "; the tree in pages of {} MiB (nodes {}, triangles {}, escape links {}) under \
             a {} MiB storage binding",
            (1u64 << p.log2_bytes) >> 20,
            p.nodes,
            p.triangles,
            p.escapes,
            ctx.limits().max_storage_buffer_binding_size >> 20
        ),
        false => String::new(),
    };
    Ok((out, pages))
}

/// The hits (16 bytes each, the layout of [`bvhtrace_core::Hit`]) followed by the
/// trace's wall time in milliseconds (an f64).
fn hit_bytes(out: &TraceOutput) -> js_sys::Uint8Array {
    let mut bytes: Vec<u8> = bytemuck::cast_slice(&out.hits).to_vec();
    bytes.extend_from_slice(&out.wall_ms.to_le_bytes());
    js_sys::Uint8Array::from(&bytes[..])
}

/// The adapter in words, with what it leaves out ([`GpuContext::left_out`]).
fn adapter(ctx: &GpuContext) -> String {
    let info = ctx.adapter_info();
    let mut adapter = format!("{:?} adapter, {:?}", info.device_type, info.backend);
    for line in ctx.left_out() {
        adapter.push_str(&format!("; left out: {line}"));
    }
    adapter
}

/// Builds a BVH over `triangles` (nine floats each), uploads it to the browser's
/// WebGPU with the BVH in buffers, and traces `rays` (eight floats each: origin,
/// `t_min`, direction, `t_max`, the layout of [`Ray`]) with the stackless walk,
/// closest hit, twice: the first trace builds the pipeline, the second is timed and
/// returned. With `default_limits` the device gets WebGPU's default limits rather
/// than the adapter's (128 MiB storage bindings, 8 storage buffers per stage:
/// [`ContextOptions::webgpu_default_limits`]) and the walk is the full stack, which
/// binds the fewest buffers when a large tree goes in pages. Resolves to `[bytes, adapter]`: the hits (16 bytes each, the layout of
/// [`bvhtrace_core::Hit`]) followed by the second trace's wall time in milliseconds (an
/// f64), and a description of the adapter with what it leaves out
/// ([`GpuContext::left_out`]) and, for a tree larger than one storage binding, the
/// pages it was bound in. Float counts that are not whole triangles or rays are an
/// error.
#[wasm_bindgen]
pub async fn trace_closest(
    triangles: Vec<f32>,
    rays: Vec<f32>,
    default_limits: Option<bool>,
) -> Result<js_sys::Array, JsValue> {
    let tris = self::triangles(&triangles)?;
    let rays = self::rays(&rays)?;
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).map_err(js)?;
    let default_limits = default_limits.unwrap_or(false);
    let options = ContextOptions {
        webgpu_default_limits: default_limits,
        ..ContextOptions::default()
    };
    let ctx = context_with(&options).await?;
    let walk = match default_limits {
        true => Traversal::FullStack,
        false => Traversal::Stackless,
    };
    let (out, pages) = trace_twice(&ctx, &bvh, &rays, walk).await?;
    let result = js_sys::Array::new();
    result.push(&hit_bytes(&out));
    result.push(&JsValue::from_str(&(adapter(&ctx) + &pages)));
    Ok(result)
}

/// Compiles `source`, your own WGSL, after the traversal library on the browser's
/// WebGPU ([`GpuContext::shader_module_async`]): the library of the stackless walk over
/// a one-triangle upload in buffers, its bindings in `@group(0)`, so that `source` may
/// call `bvh_trace_closest(ray, lane)` and the rest. Resolves when it compiles; a
/// shader that does not is rejected with the compiler's first error, its line and
/// column counted in `source` (`label:line:column: message`).
#[wasm_bindgen]
pub async fn compile_with_library(source: String, label: String) -> Result<(), JsValue> {
    let tri = [glam::Vec3::ZERO, glam::Vec3::X, glam::Vec3::Y];
    let bvh = FlatBvh::build(&[tri], &BuildOptions::default()).map_err(js)?;
    let ctx = context().await?;
    let opts = UploadOptions::for_traversal(Traversal::Stackless).with_storage(BvhStorage::Buffers);
    let gpu = GpuBvh::upload(&ctx, &bvh, &opts).map_err(js)?;
    let library = gpu.wgsl_library(Traversal::Stackless, 0).map_err(js)?;
    ctx.shader_module_async(&library, &source, &label)
        .await
        .map(|_| ())
        .map_err(js)
}

/// The read-back tree as bytes: its depth, node count and triangle count (three
/// little-endian `u32`, then a zero one), then the nodes (32 bytes each) and the
/// triangles (48 bytes each), the layouts of [`bvhtrace_core::FlatNode`] and
/// [`bvhtrace_core::FlatTriangle`] ([`FlatBvh::from_parts`] takes them back).
fn tree_bytes(bvh: &FlatBvh) -> js_sys::Uint8Array {
    let head = [
        bvh.depth(),
        bvh.nodes().len() as u32,
        bvh.triangles().len() as u32,
        0,
    ];
    let mut bytes: Vec<u8> = bytemuck::cast_slice(&head).to_vec();
    bytes.extend_from_slice(bytemuck::cast_slice(bvh.nodes()));
    bytes.extend_from_slice(bytemuck::cast_slice(bvh.triangles()));
    js_sys::Uint8Array::from(&bytes[..])
}

/// A build's wall time: upload, dispatches and read back, in milliseconds.
fn total_ms(t: &GpuBuildTimes) -> f64 {
    t.upload_ms + t.build_ms + t.readback_ms
}

/// Sets `object[key] = value`.
fn set(object: &js_sys::Object, key: &str, value: &JsValue) -> Result<(), JsValue> {
    js_sys::Reflect::set(object, &JsValue::from_str(key), value).map(|_| ())
}

/// Builds a BVH over `triangles` (nine floats each) on the browser's WebGPU with
/// `builder` (`gpu-ploc` or `gpu-lbvh`, [`GpuContext::build_bvh_async`]), twice: the
/// first build compiles the builder's programs, the second is timed and its tree read
/// back, uploaded and used to trace `rays` (eight floats each, as for
/// [`trace_closest`]) with the stackless walk, closest hit (twice, the second
/// returned). The CPU walk over the same read-back tree answers the same rays in
/// WebAssembly. Resolves to an object:
/// * `hits`: the browser's GPU hits (16 bytes each) and the trace's milliseconds (an
///   f64), as [`trace_closest`] returns them; `cpuHits`: the CPU walk's, the same way;
/// * `tree`: the read-back tree (a 16-byte head of depth, node count and triangle
///   count, then its nodes and triangles in their storage layouts);
/// * `builder`, `adapter` (as [`trace_closest`] describes it), `nodes`, `sah` (the
///   tree's SAH cost, traversal and intersection 1), `depth`, `iterations` (the
///   clustering's; 0 for the linear BVH);
/// * `uploadMs`, `buildMs`, `readbackMs`: the timed build's steps, `firstBuildMs` the
///   first build's wall time (with the programs' compilation);
/// * `sameTree`: whether both builds gave the same tree (the builders are
///   deterministic); `invariants`: empty when the tree passes
///   [`FlatBvh::check_invariants`], else what fails.
///
/// An unknown builder, float counts that are not whole triangles or rays, and a
/// failed build or trace are errors.
#[wasm_bindgen]
pub async fn trace_closest_built_on_device(
    triangles: Vec<f32>,
    rays: Vec<f32>,
    builder: String,
) -> Result<js_sys::Object, JsValue> {
    let kind = GpuBuilderKind::ALL
        .into_iter()
        .find(|k| k.name() == builder)
        .ok_or_else(|| {
            js(format!(
                "unknown device builder {builder:?}: gpu-ploc or gpu-lbvh"
            ))
        })?;
    let tris = self::triangles(&triangles)?;
    let rays = self::rays(&rays)?;
    let ctx = context().await?;
    let opts = GpuBuildOptions::with_builder(kind);
    let (first, first_times) = ctx.build_bvh_async(&tris, &opts).await.map_err(js)?;
    let (bvh, times) = ctx.build_bvh_async(&tris, &opts).await.map_err(js)?;
    let same_tree = first.nodes() == bvh.nodes()
        && first.triangles() == bvh.triangles()
        && first.depth() == bvh.depth();
    let (gpu, _) = trace_twice(&ctx, &bvh, &rays, Traversal::Stackless).await?;
    let cpu = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::Stackless));
    let stats = BvhStats::of(&bvh);
    let invariants = bvh.check_invariants().err().unwrap_or_default();
    let out = js_sys::Object::new();
    set(&out, "hits", &hit_bytes(&gpu))?;
    set(&out, "cpuHits", &hit_bytes(&cpu))?;
    set(&out, "tree", &tree_bytes(&bvh))?;
    set(&out, "builder", &JsValue::from_str(kind.name()))?;
    set(&out, "adapter", &JsValue::from_str(&adapter(&ctx)))?;
    set(&out, "nodes", &JsValue::from(stats.nodes as u32))?;
    set(&out, "sah", &JsValue::from(stats.sah_cost))?;
    set(&out, "depth", &JsValue::from(bvh.depth()))?;
    set(&out, "iterations", &JsValue::from(times.iterations))?;
    set(&out, "uploadMs", &JsValue::from(times.upload_ms))?;
    set(&out, "buildMs", &JsValue::from(times.build_ms))?;
    set(&out, "readbackMs", &JsValue::from(times.readback_ms))?;
    set(&out, "firstBuildMs", &JsValue::from(total_ms(&first_times)))?;
    set(&out, "sameTree", &JsValue::from(same_tree))?;
    set(&out, "invariants", &JsValue::from_str(&invariants))?;
    Ok(out)
}
