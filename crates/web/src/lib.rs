//! bvhtrace in a browser: the BVH built in WebAssembly and traced by the kernels on the
//! browser's WebGPU, through the same engine as every other backend
//! (`Tracer::trace_async`). Built for `wasm32-unknown-unknown` and bound to
//! JavaScript with `wasm-bindgen` (`web/build.sh`); on other targets this crate is empty.
#![warn(missing_docs)]

#[cfg(target_arch = "wasm32")]
mod web {
    use bvhtrace_core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal};
    use bvhtrace_gpu::{
        AdapterChoice, BvhStorage, ContextOptions, GpuBvh, GpuContext, UploadOptions,
    };
    use wasm_bindgen::prelude::*;

    fn js(e: impl std::fmt::Display) -> JsValue {
        JsValue::from_str(&e.to_string())
    }

    /// Builds a BVH over `triangles` (nine floats each), uploads it to the browser's
    /// WebGPU with the BVH in buffers, and traces `rays` (eight floats each: origin,
    /// `t_min`, direction, `t_max`, the layout of [`Ray`]) with the stackless walk,
    /// closest hit, twice: the first trace builds the pipeline, the second is timed and
    /// returned. Resolves to `[bytes, adapter]`: the hits (16 bytes each, the layout of
    /// [`bvhtrace_core::Hit`]) followed by the second trace's wall time in milliseconds (an
    /// f64), and a description of the adapter with what it leaves out
    /// ([`GpuContext::left_out`]).
    #[wasm_bindgen]
    pub async fn trace_closest(
        triangles: Vec<f32>,
        rays: Vec<f32>,
    ) -> Result<js_sys::Array, JsValue> {
        let tris: Vec<[glam::Vec3; 3]> = triangles
            .chunks_exact(9)
            .map(|t| {
                let v = |i: usize| glam::Vec3::new(t[i], t[i + 1], t[i + 2]);
                [v(0), v(3), v(6)]
            })
            .collect();
        let rays: Vec<Ray> = bytemuck::cast_slice::<f32, Ray>(&rays).to_vec();
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).map_err(js)?;
        let ctx = GpuContext::new_async(AdapterChoice::Auto, &ContextOptions::default())
            .await
            .map_err(js)?;
        let opts =
            UploadOptions::for_traversal(Traversal::Stackless).with_storage(BvhStorage::Buffers);
        let gpu = GpuBvh::upload(&ctx, &bvh, &opts).map_err(js)?;
        let opts = TraceOptions::closest(Traversal::Stackless);
        // The first trace builds the pipeline; the second is the one timed and returned.
        gpu.trace_async(&rays, &opts).await.map_err(js)?;
        let out = gpu.trace_async(&rays, &opts).await.map_err(js)?;
        let mut bytes: Vec<u8> = bytemuck::cast_slice(&out.hits).to_vec();
        bytes.extend_from_slice(&out.wall_ms.to_le_bytes());
        let result = js_sys::Array::new();
        result.push(&js_sys::Uint8Array::from(&bytes[..]));
        let info = ctx.adapter_info();
        let mut adapter = format!("{:?} adapter, {:?}", info.device_type, info.backend);
        for line in ctx.left_out() {
            adapter.push_str(&format!("; left out: {line}"));
        }
        result.push(&JsValue::from_str(&adapter));
        Ok(result)
    }
}
