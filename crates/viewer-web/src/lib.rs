//! The bvhtrace viewer in a browser: eframe's web runner draws the viewer
//! (`bvhtrace_viewer::app::ViewerApp`) into a canvas with its wgpu renderer on the page's
//! WebGPU, and the rays are traced on that same device. Built for `wasm32-unknown-unknown`
//! and bound to JavaScript with `wasm-bindgen` (`web/build.sh`); `web/viewer.html` is the
//! page. On other targets this crate is empty.
#![warn(missing_docs)]

#[cfg(target_arch = "wasm32")]
mod web {
    use std::cell::RefCell;
    use std::rc::Rc;

    use bvhtrace_viewer::app::{Shared, ViewerApp};
    use bvhtrace_viewer::cli::Args;
    use clap::Parser;
    use eframe::egui;
    use wasm_bindgen::JsCast;
    use wasm_bindgen::prelude::*;

    fn js(e: impl std::fmt::Display) -> JsValue {
        JsValue::from_str(&e.to_string())
    }

    /// The viewer running on a page.
    #[wasm_bindgen]
    pub struct Viewer {
        runner: eframe::WebRunner,
        shared: Shared,
        ctx: Rc<RefCell<Option<egui::Context>>>,
    }

    #[wasm_bindgen]
    impl Viewer {
        /// Starts the viewer in the canvas whose id is `canvas_id`. `args` are the native
        /// viewer's flags (`bvhtrace-viewer --help`: `--shade`, `--eye`/`--target`,
        /// `--screenshot NAME`, ...); a bad flag rejects with clap's message. `scene_name`
        /// and `scene_bytes`, when given, are a glTF file to open first (else the flags'
        /// scene, or the default builtin one).
        pub async fn start(
            canvas_id: String,
            args: Vec<String>,
            scene_name: Option<String>,
            scene_bytes: Option<Vec<u8>>,
        ) -> Result<Viewer, JsValue> {
            // eframe's and wgpu's messages, to the browser's console.
            let _ = eframe::WebLogger::init(log::LevelFilter::Warn);
            let args =
                Args::try_parse_from(std::iter::once("bvhtrace-viewer".to_string()).chain(args))
                    .map_err(|e| js(e.render()))?;
            let canvas = web_sys::window()
                .and_then(|w| w.document())
                .and_then(|d| d.get_element_by_id(&canvas_id))
                .ok_or_else(|| js(format!("the page has no element with id {canvas_id}")))?
                .dyn_into::<web_sys::HtmlCanvasElement>()
                .map_err(|_| js(format!("#{canvas_id} is not a canvas")))?;
            let shared = Shared::default();
            if let (Some(name), Some(bytes)) = (scene_name, scene_bytes)
                && let Ok(mut q) = shared.inbox.lock()
            {
                q.push((name, Ok(bytes)));
            }
            let options = eframe::WebOptions {
                wgpu_options: bvhtrace_viewer::setup::wgpu_configuration(args.adapter.clone()),
                ..Default::default()
            };
            let runner = eframe::WebRunner::new();
            let ctx = Rc::new(RefCell::new(None));
            let (app_shared, app_ctx) = (shared.clone(), ctx.clone());
            runner
                .start(
                    canvas,
                    options,
                    Box::new(move |cc| {
                        *app_ctx.borrow_mut() = Some(cc.egui_ctx.clone());
                        Ok(Box::new(ViewerApp::new(cc, &args, app_shared)))
                    }),
                )
                .await?;
            Ok(Viewer {
                runner,
                shared,
                ctx,
            })
        }

        /// Opens a glTF file's bytes: from the page's file picker, or fetched from a URL.
        pub fn open(&self, name: String, bytes: Vec<u8>) {
            if let Ok(mut q) = self.shared.inbox.lock() {
                q.push((name, Ok(bytes)));
            }
            if let Some(ctx) = self.ctx.borrow().as_ref() {
                ctx.request_repaint();
            }
        }

        /// The viewer's panic message, if it has panicked (the page shows it instead of
        /// the canvas).
        pub fn panic_message(&self) -> Option<String> {
            self.runner.panic_summary().map(|p| p.message())
        }

        /// How a `--screenshot` run ended: `undefined` while it runs, else an object with
        /// `message` (or `error`), and when it ended well `window_png` (the window as a
        /// PNG file), `traced` (the traced image, RGBA8), `width`, `height`, `eye`,
        /// `target`, `fov` (its camera), `time` (the animation time it shows), `on_gpu` and
        /// `samples` (per pixel, in the path mode).
        pub fn screenshot(&self) -> Result<JsValue, JsValue> {
            let outcome = self.shared.outcome.lock().ok().and_then(|o| o.clone());
            let Some(outcome) = outcome else {
                return Ok(JsValue::UNDEFINED);
            };
            let o = js_sys::Object::new();
            let set = |k: &str, v: JsValue| js_sys::Reflect::set(&o, &k.into(), &v);
            match outcome {
                Ok(message) => set("message", message.into())?,
                Err(error) => set("error", error.into())?,
            };
            let images = self.shared.shot.lock().ok().and_then(|s| s.clone());
            if let Some(s) = images {
                let v3 = |v: glam::Vec3| js_sys::Float32Array::from(&v.to_array()[..]).into();
                set(
                    "window_png",
                    js_sys::Uint8Array::from(&s.window_png[..]).into(),
                )?;
                set(
                    "traced",
                    js_sys::Uint8Array::from(&s.traced_rgba[..]).into(),
                )?;
                set("width", s.size[0].into())?;
                set("height", s.size[1].into())?;
                set("eye", v3(s.camera.eye))?;
                set("target", v3(s.camera.target))?;
                set("fov", s.camera.fov_y_deg.into())?;
                set("on_gpu", s.on_gpu.into())?;
                set("time", s.time.into())?;
                set("samples", s.samples.into())?;
            }
            Ok(o.into())
        }
    }
}
