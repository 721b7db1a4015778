//! The viewer's path mode: the scene path traced on eframe's own device
//! (`bvhtrace-path`), each frame's samples added on the device and tone mapped into a
//! texture egui draws; no frame reads anything back.

use bvhtrace_core::{BuildOptions, FlatBvh, Traversal};
use bvhtrace_gpu::GpuContext;
use bvhtrace_path::{GpuPathTracer, Lighting, PathParams, PathScene};
use bvhtrace_scene::{Camera, Scene};
use eframe::egui;
use eframe::egui_wgpu::RenderState;
use eframe::wgpu;

/// `scene` flattened and its tree built, with the scene's alpha masks on it (so that the
/// walks cut leaves as the other modes do): what the path tracer and its twin trace.
pub fn flattened_with_masks(
    scene: &Scene,
) -> Result<(Vec<bvhtrace_core::Triangle>, FlatBvh), String> {
    let traced = (scene.tracing_bvh(&BuildOptions::default(), true)).map_err(|e| e.to_string())?;
    match traced {
        bvhtrace_scene::SceneBvh::Flat { tris, bvh } => Ok((tris, bvh)),
        bvhtrace_scene::SceneBvh::Instanced(_) => {
            Err("the path mode traces the scene flattened".into())
        }
    }
}

/// Where the sums read back for a screenshot land.
pub type SumsSlot =
    std::rc::Rc<std::cell::RefCell<Option<Result<bvhtrace_path::Accumulation, String>>>>;

/// The path tracer over one pose of one scene, and the texture egui shows.
pub struct PathMode {
    tracer: GpuPathTracer,
    /// The scene's shading data, for each restart's parameters.
    shading: PathScene,
    /// The light besides the scene's emissive triangles: a constant sky, or the
    /// environment map's radiance as it is.
    lighting: Lighting,
    /// The scene generation and animation time it traces.
    made_for: (u64, f32),
    /// The camera and size the sums are for.
    view: Option<(Camera, [u32; 2])>,
    /// The display texture's registration with egui, and its size.
    shown: Option<(egui::TextureId, wgpu::Extent3d)>,
    /// Samples per second, smoothed, and when the last frame's samples were submitted.
    rate: Option<f64>,
    last: Option<web_time::Instant>,
}

impl PathMode {
    /// The tracer of `scene` flattened (an animated scene posed at its current time), its
    /// tree built on the CPU, walked by `traversal` on `ctx`'s device, its sky
    /// `environment`'s or a constant one; ready once the device has compiled its kernel
    /// (in a browser, on the page's event loop).
    pub async fn new(
        ctx: &GpuContext,
        (scene, environment): (&Scene, Option<bvhtrace_path::Environment>),
        traversal: Traversal,
        made_for: (u64, f32),
    ) -> Result<PathMode, String> {
        let (tris, mut bvh) = flattened_with_masks(scene)?;
        if traversal.is_wide() {
            bvh.build_wide();
        }
        let mut shading = PathScene::new(scene, &tris).map_err(|e| e.to_string())?;
        shading.set_environment(environment);
        let lighting = match shading.environment {
            Some(_) => Lighting {
                env: glam::Vec3::ONE,
                ..Lighting::default()
            },
            None => Lighting::default(),
        };
        let walk = bvhtrace_path::PathWalk::Walk(traversal);
        let tracer = (GpuPathTracer::with_walk_async(ctx, &bvh, &shading, walk).await)
            .map_err(|e| e.to_string())?;
        Ok(PathMode {
            tracer,
            shading,
            lighting,
            made_for,
            view: None,
            shown: None,
            rate: None,
            last: None,
        })
    }

    /// The scene generation and time it traces.
    pub fn made_for(&self) -> (u64, f32) {
        self.made_for
    }

    /// Samples per pixel so far.
    pub fn samples(&self) -> u32 {
        self.tracer.samples()
    }

    /// Samples per second over the last frames (`None` before two frames).
    pub fn samples_per_second(&self) -> Option<f64> {
        self.rate
    }

    /// The camera and size the sums are for (`None` before the first frame).
    pub fn view(&self) -> Option<(Camera, [u32; 2])> {
        self.view
    }

    /// Starts reading the sums back (a screenshot's one readback); the slot is filled when
    /// they arrive (natively, before this returns; in a browser, on the event loop).
    pub fn read_sums(&self) -> SumsSlot {
        let slot = SumsSlot::default();
        let into = slot.clone();
        let reading = self.tracer.read_async();
        let read = async move {
            let r = reading.await.map(|(sums, _)| sums);
            *into.borrow_mut() = Some(r.map_err(|e| e.to_string()));
        };
        crate::jobs::run_future(read);
        slot
    }

    /// The tracer, for tests and reports.
    pub fn tracer(&self) -> &GpuPathTracer {
        &self.tracer
    }

    /// One frame of `size` pixels seen by `camera`: the sums started over if either
    /// changed, `k` samples added while under `max_samples`, tone mapped into the display
    /// texture. Returns whether samples were added.
    pub fn advance(
        &mut self,
        camera: &Camera,
        size: [u32; 2],
        k: u32,
        max_samples: u32,
    ) -> Result<bool, String> {
        if self.view != Some((*camera, size)) {
            let (w, h) = (size[0], size[1]);
            let params = PathParams::new(camera, (w, h), &self.lighting, 8, &self.shading);
            self.tracer.restart(params);
            self.view = Some((*camera, size));
            self.rate = None;
            self.last = None;
        }
        let mut k = k.min(max_samples.saturating_sub(self.tracer.samples()));
        // At most one frame's samples waiting on the device: where frames outrun it (a page
        // without vsync) the queue, and the latency of what is shown, stay bounded.
        if self.tracer.samples_in_flight() > k {
            k = 0;
        }
        if k > 0 {
            self.tracer.add_samples(k).map_err(|e| e.to_string())?;
            let now = web_time::Instant::now();
            if let Some(last) = self.last {
                let r = f64::from(k) / now.duration_since(last).as_secs_f64().max(1e-6);
                self.rate = Some(self.rate.map_or(r, |old| 0.8 * old + 0.2 * r));
            }
            self.last = Some(now);
        }
        self.tracer.display(1.0).map_err(|e| e.to_string())?;
        Ok(k > 0)
    }

    /// The display texture registered with egui's renderer (again when its size changed).
    pub fn texture_id(&mut self, rs: &RenderState) -> Result<egui::TextureId, String> {
        let texture = self.tracer.display_texture().ok_or("no frame yet")?;
        let size = texture.size();
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let mut renderer = rs.renderer.write();
        let id = match self.shown {
            Some((id, s)) if s == size => id,
            Some((id, _)) => {
                renderer.update_egui_texture_from_wgpu_texture(
                    &rs.device,
                    &view,
                    wgpu::FilterMode::Linear,
                    id,
                );
                id
            }
            None => renderer.register_native_texture(&rs.device, &view, wgpu::FilterMode::Linear),
        };
        self.shown = Some((id, size));
        Ok(id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bvhtrace_gpu::{AdapterChoice, GpuError};

    /// The viewer's steady path-traced frames make no readback: samples added and shown
    /// on the device, `GpuContext::readbacks` unchanged; a new camera starts the sums over.
    #[test]
    fn a_steady_path_frame_reads_nothing_back() {
        let ctx = match GpuContext::new(AdapterChoice::Auto) {
            Ok(ctx) => ctx,
            Err(e @ GpuError::NoAdapter { .. }) => {
                eprintln!("SKIP: {e}");
                return;
            }
            Err(e) => panic!("{e}"),
        };
        let scene = bvhtrace_scene::load("builtin:cornell").expect("cornell");
        let made = PathMode::new(&ctx, (&scene, None), Traversal::Stackless, (1, 0.0));
        let mut mode = pollster::block_on(made).expect("mode");
        let cam = scene.camera_or_frame(1.0);
        assert!(mode.advance(&cam, [32, 32], 2, 100).expect("frame"));
        mode.tracer().wait().expect("wait");
        let before = ctx.readbacks();
        let start = web_time::Instant::now();
        for _ in 0..5 {
            mode.advance(&cam, [32, 32], 2, 100).expect("frame");
            // As a frame's present would: the device catches up (no readback).
            mode.tracer().wait().expect("wait");
        }
        let ms = start.elapsed().as_secs_f64() * 1e3 / 5.0;
        assert_eq!(ctx.readbacks(), before, "steady path frames read back");
        assert_eq!(mode.samples(), 12);
        println!("path mode: {ms:.1} ms a frame of 2 samples at 32x32");
        // At most `max_samples`, then frames only show.
        mode.advance(&cam, [32, 32], 64, 20).expect("frame");
        assert_eq!(mode.samples(), 20);
        assert!(!mode.advance(&cam, [32, 32], 2, 20).expect("frame"));
        // A moved camera starts over.
        let moved = Camera {
            eye: cam.eye + glam::Vec3::X * 0.1,
            ..cam
        };
        mode.advance(&moved, [32, 32], 2, 100).expect("frame");
        assert_eq!(mode.samples(), 2);
    }
}

#[cfg(test)]
mod mask_tests {
    /// The path mode traces an alpha-tested scene with its masks on the tree (the leaves
    /// cut, as the other modes cut them), one mesh, every triangle numbered once.
    #[test]
    fn the_path_mode_traces_with_the_alpha_masks() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/foliage.gltf");
        let scene = bvhtrace_scene::load(path).expect("foliage");
        let (tris, bvh) = super::flattened_with_masks(&scene).expect("flattened");
        assert!(
            bvh.masks().is_some(),
            "the foliage's masks are not on the tree"
        );
        assert_eq!(tris.len(), scene.flattened_triangles().expect("tris").len());
        let cornell = bvhtrace_scene::load("builtin:cornell").expect("cornell");
        let (_, plain) = super::flattened_with_masks(&cornell).expect("flattened");
        assert!(plain.masks().is_none(), "an opaque scene has no masks");
    }
}
