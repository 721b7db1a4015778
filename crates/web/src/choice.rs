//! Where a [`crate::bvh::Bvh`] traces: the page's WebGPU when its adapter is a real GPU,
//! else the WebAssembly walk, which outruns a CPU that emulates a GPU (SwiftShader,
//! lavapipe) and needs no adapter at all (Node, a browser without WebGPU).

use bvhtrace_gpu::{AdapterChoice, ContextOptions, GpuContext};
use js_sys::{Function, Promise, Reflect};
use wasm_bindgen::{JsCast, JsValue};
use wasm_bindgen_futures::JsFuture;

/// What `CreateOptions.backend` asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// WebGPU on a real GPU, else the WebAssembly walk.
    Auto,
    /// WebGPU whatever its adapter is; an error without one.
    WebGpu,
    /// The WebAssembly walk.
    Wasm,
}

impl Backend {
    /// `"auto"`, `"webgpu"` or `"wasm"`.
    pub fn parse(s: &str) -> Result<Backend, String> {
        match s {
            "auto" => Ok(Backend::Auto),
            "webgpu" => Ok(Backend::WebGpu),
            "wasm" => Ok(Backend::Wasm),
            other => Err(format!(
                "backend {other:?}: \"auto\", \"webgpu\" or \"wasm\" expected"
            )),
        }
    }
}

/// What the WebAssembly walk says of itself when nothing else was asked.
pub fn wasm_note() -> String {
    "the WebAssembly walk (no device asked for)".into()
}

/// `object[key]`, undefined when absent or not readable.
fn get(object: &JsValue, key: &str) -> JsValue {
    Reflect::get(object, &JsValue::from_str(key)).unwrap_or(JsValue::UNDEFINED)
}

/// The adapter the page's `navigator.gpu` offers, or why there is none.
async fn request_adapter() -> Result<JsValue, String> {
    let gpu = get(&get(&js_sys::global(), "navigator"), "gpu");
    if gpu.is_undefined() || gpu.is_null() {
        return Err("this page has no WebGPU (navigator.gpu)".into());
    }
    let request: Function = get(&gpu, "requestAdapter")
        .dyn_into()
        .map_err(|_| "navigator.gpu.requestAdapter is not a function".to_string())?;
    let promise: Promise = request
        .call0(&gpu)
        .map_err(|e| format!("requestAdapter threw {e:?}"))?
        .dyn_into()
        .map_err(|_| "requestAdapter did not return a promise".to_string())?;
    let adapter = JsFuture::from(promise)
        .await
        .map_err(|e| format!("requestAdapter failed: {e:?}"))?;
    if adapter.is_null() || adapter.is_undefined() {
        return Err("WebGPU offers no adapter".into());
    }
    Ok(adapter)
}

/// The adapter in words (vendor, architecture, description), and whether it is a CPU
/// device: a fallback adapter, or one whose words name a software rasteriser.
pub fn describe(adapter: &JsValue) -> (String, bool) {
    let info = get(adapter, "info");
    let text = |k: &str| get(&info, k).as_string().unwrap_or_default();
    let words: Vec<String> = ["vendor", "architecture", "device", "description"]
        .iter()
        .map(|k| text(k))
        .filter(|w| !w.is_empty())
        .collect();
    let fallback = get(adapter, "isFallbackAdapter").is_truthy()
        || get(&info, "isFallbackAdapter").is_truthy();
    let joined = words.join(" ").to_ascii_lowercase();
    let software = ["swiftshader", "llvmpipe", "lavapipe", "software", "warp"]
        .iter()
        .any(|s| joined.contains(s));
    let name = match words.is_empty() {
        true => "an adapter that does not describe itself".to_string(),
        false => words.join(" "),
    };
    (name, fallback || software)
}

/// The WebGPU device `backend` leads to (none for the WebAssembly walk), with a note
/// saying why.
pub async fn device_for(backend: Backend) -> Result<(Option<GpuContext>, String), String> {
    if backend == Backend::Wasm {
        return Ok((None, "the WebAssembly walk, as asked".into()));
    }
    let adapter = match request_adapter().await {
        Ok(a) => a,
        Err(why) if backend == Backend::Auto => {
            return Ok((None, format!("the WebAssembly walk: {why}")));
        }
        Err(why) => return Err(format!("backend \"webgpu\": {why}")),
    };
    let (name, cpu) = describe(&adapter);
    if cpu && backend == Backend::Auto {
        let note = format!(
            "the WebAssembly walk: the WebGPU adapter ({name}) is a CPU device, which the \
             walk outruns"
        );
        return Ok((None, note));
    }
    let ctx = GpuContext::new_async(AdapterChoice::Auto, &ContextOptions::default())
        .await
        .map_err(|e| format!("WebGPU ({name}): {e}"))?;
    let note = match backend {
        Backend::Auto => format!("WebGPU: the adapter ({name}) is a GPU"),
        _ => format!("WebGPU ({name}), as asked"),
    };
    Ok((Some(ctx), note))
}
