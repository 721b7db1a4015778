//! Tracing on your own wgpu device, inside your own command encoders.
//!
//! ```text
//! cargo run --release -p bvhtrace-gpu --example user_device -- [SCENE] [-o out.png]
//! ```
//!
//! An application that already has a wgpu device (a renderer, a game, a viewer) hands it
//! to bvhtrace and records the traversal next to its own passes. This example creates the
//! device itself, loads SCENE (`builtin:cornell` by default, or any `.gltf`/`.glb` path),
//! traces one camera ray per pixel (closest hit), then one shadow ray per lit hit toward a
//! point light (any hit), and writes a Lambert-shaded PNG (`user_device.png` by default).
//!
//! `tests/examples.rs` runs it and recomputes the image on the CPU with the `pub`
//! functions below and `bvhtrace_core::trace_rays`: the two must agree byte for byte, since
//! the kernels give the CPU walk's hits bit for bit.
//!
//! `Ray` and `Hit` are `bytemuck::Pod` (GPU layout, 32 and 16 bytes): in your own crate add
//! `bytemuck` and `pollster` next to `bvhtrace-gpu`, as this example uses them.

mod common;

use std::error::Error;

use bvhtrace_gpu::core::surface::{facing_normal, hit_point};
use bvhtrace_gpu::core::{
    BuildOptions, FlatBvh, Hit, Query, Ray, TraceOptions, Traversal, Triangle,
};
use bvhtrace_gpu::engine::plan::{HIT_BYTES, RAY_BYTES};
use bvhtrace_gpu::glam::Vec3;
use bvhtrace_gpu::{GpuBvh, GpuContext, GpuError, RayBatch, UploadOptions, wgpu};
use bvhtrace_scene::Scene;
// The light and the colour rounding of `bvhtrace render` and the viewer.
use bvhtrace_shade::{palette, point_light};

/// The image size: small, so that CI renders it in a moment on lavapipe.
pub const WIDTH: u32 = 320;
/// See [`WIDTH`].
pub const HEIGHT: u32 = 240;
/// The colour of pixels whose camera ray hits nothing.
pub const BACKGROUND: [u8; 3] = [24, 26, 32];
/// Light every lit surface gets even in shadow, so that shadows are dark, not black.
const AMBIENT: f32 = 0.1;

fn main() -> Result<(), Box<dyn Error>> {
    // `main` would print an error with `Debug`; its message says more (how to install a
    // Vulkan driver, which limit is too low...).
    run().map_err(|e| e.to_string().into())
}

fn run() -> Result<(), Box<dyn Error>> {
    let Some(common::Args { spec, out, .. }) =
        common::parse_args("user_device [SCENE] [-o out.png]", "user_device.png", &[])?
    else {
        return Ok(());
    };

    // The scene: world-space triangles, in the order the BVH builder gets them. Hits name
    // triangles by that index (`Hit::prim`), so it also indexes the per-triangle colours.
    let scene = bvhtrace_scene::load(&spec)?;
    let tris = scene.flatten().triangles()?;
    let albedo = albedos(&scene);
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;

    // Your device. bvhtrace needs no feature and modest limits (`required_limits`);
    // `recommended_limits` adds what buys the fast path on this adapter (texture storage on
    // a CPU driver, larger scenes anywhere). It uses timestamps and f64 only when the
    // device has them, so offer what the adapter has.
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    let instance = wgpu::Instance::new(desc);
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        ..Default::default()
    }))
    .map_err(|e| GpuError::NoAdapter {
        details: format!(" ({e})"),
    })?;
    let info = adapter.get_info();
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("user_device"),
        required_features: GpuContext::required_features()
            | (adapter.features() & GpuContext::optional_features()),
        required_limits: GpuContext::recommended_limits(&adapter),
        ..Default::default()
    }))?;
    // bvhtrace keeps clones of the handles (they are reference counted): the application
    // goes on using its own. Anything missing would be an error here, not a failure later.
    // The storage follows the device: textures on a CPU driver such as lavapipe, buffers
    // on a GPU or with only the required limits; that is automatic.
    let ctx = GpuContext::from_device(device.clone(), queue.clone(), info.clone())?;
    let gpu = GpuBvh::upload(
        &ctx,
        &bvh,
        &UploadOptions::for_traversal(Traversal::Stackless),
    )?;
    println!(
        "adapter: {} ({:?}); {} triangles, BVH of {} nodes (depth {}) in {:?}",
        info.name,
        info.device_type,
        tris.len(),
        bvh.nodes().len(),
        bvh.depth(),
        gpu.tree().storage
    );

    // Your buffers: rays in, hits out, and a copy to read the hits back. One set serves
    // both batches (there are never more shadow rays than pixels).
    let capacity = u64::from(WIDTH * HEIGHT);
    let buffer = |label, size, usage| common::buffer(&device, label, size, usage);
    use wgpu::BufferUsages as U;
    let buffers = Buffers {
        rays: buffer("rays", capacity * RAY_BYTES, U::STORAGE | U::COPY_DST),
        hits: buffer("hits", capacity * HIT_BYTES, U::STORAGE | U::COPY_SRC),
        readback: buffer(
            "hits readback",
            capacity * HIT_BYTES,
            U::MAP_READ | U::COPY_DST,
        ),
    };

    // Camera rays: the scene's camera (or one framing it), one ray through each pixel.
    let camera = scene.camera_or_frame(WIDTH as f32 / HEIGHT as f32);
    let rays = camera.rays(WIDTH, HEIGHT);
    let closest = TraceOptions::closest(Traversal::Stackless);
    let (hits, finished) = trace(&ctx, &gpu, &buffers, &rays, &closest)?;

    // Shadow rays toward the light, traced for any hit: one blocker is enough.
    let light = point_light(&camera);
    let (shadow, owners) = shadow_rays(&tris, &rays, &hits, light);
    let any = TraceOptions::new(Traversal::Stackless, Query::Any);
    let (blocked, finished_shadow) = trace(&ctx, &gpu, &buffers, &shadow, &any)?;
    let mut in_shadow = vec![false; rays.len()];
    for (&pixel, b) in owners.iter().zip(&blocked) {
        in_shadow[pixel] = b.is_hit();
    }

    let image = shade(&tris, &albedo, &rays, &hits, light, &in_shadow);
    image.save(&out)?;
    println!(
        "{} camera rays, {} hits; {} shadow rays, {} in shadow; {} rays finished on the CPU",
        rays.len(),
        hits.iter().filter(|h| h.is_hit()).count(),
        shadow.len(),
        in_shadow.iter().filter(|&&s| s).count(),
        finished + finished_shadow,
    );
    println!("wrote {}", out.display());
    Ok(())
}

/// The application's buffers for one batch.
struct Buffers {
    rays: wgpu::Buffer,
    hits: wgpu::Buffer,
    readback: wgpu::Buffer,
}

/// Traces `rays` in an encoder of our own: upload, [`GpuBvh::record`], copy, submit, read
/// back. Returns the hits and how many rays were finished on the CPU.
fn trace(
    ctx: &GpuContext,
    gpu: &GpuBvh,
    buffers: &Buffers,
    rays: &[Ray],
    opts: &TraceOptions,
) -> Result<(Vec<Hit>, u64), Box<dyn Error>> {
    if rays.is_empty() {
        return Ok((Vec::new(), 0));
    }
    let (device, queue) = (ctx.device(), ctx.queue());
    queue.write_buffer(&buffers.rays, 0, bytemuck::cast_slice(rays));
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("user_device trace"),
    });
    // Your own passes can go before and after: `record` adds one compute pass, and checks
    // the buffers' usage and size first.
    let batch = RayBatch {
        rays: &buffers.rays,
        hits: &buffers.hits,
        counters: None,
        ray_count: rays.len() as u64,
    };
    gpu.record(&mut encoder, &batch, opts, None)?;
    let bytes = batch.ray_count * HIT_BYTES;
    encoder.copy_buffer_to_buffer(&buffers.hits, 0, &buffers.readback, 0, bytes);
    queue.submit([encoder.finish()]);

    let slice = buffers.readback.slice(..bytes);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    device.poll(wgpu::PollType::wait_indefinitely())?;
    rx.recv()??;
    let hits: Vec<Hit> = bytemuck::pod_collect_to_vec(&slice.get_mapped_range()?);
    buffers.readback.unmap();

    // A CPU driver (lavapipe) silently ends any invocation that loops too long, so on one
    // the context's tuning gives each ray a budget of loop trips; a ray that spends it
    // comes back `INCOMPLETE` rather than wrong. `GpuBvh::trace` finishes those itself;
    // with `record` the hits are in your buffer, so hand them to `finish_incomplete`,
    // which gives each the answer the kernel would have given. On GPUs
    // (`ctx.tuning().finishes_on_cpu()` is false) no ray is ever incomplete.
    let mut hits = hits;
    let finished = gpu.finish_incomplete(rays, opts, &mut hits, None);
    Ok((hits, finished))
}

/// The base colour of each triangle (the glTF material's, white without one).
pub fn albedos(scene: &Scene) -> Vec<Vec3> {
    let (mesh, attributes) = scene.flatten_with_attributes();
    (0..mesh.len())
        .map(|i| {
            let material = attributes.materials.get(i);
            material
                .and_then(|&m| scene.materials.get(m as usize))
                .map_or(Vec3::ONE, |m| m.base_color.truncate())
        })
        .collect()
}

/// One shadow ray from each hit that faces the light, with the pixel it belongs to.
///
/// `Hit::surface` gives the hit point moved off its triangle to the camera's side (so the
/// ray cannot hit its own triangle) and the normal on that side; `ray_toward` aims at the
/// light over `[0, 1)` of the way there, so a blocker behind the light does not count.
/// Surfaces facing away from the light are dark anyway and get no ray.
pub fn shadow_rays(
    tris: &[Triangle],
    rays: &[Ray],
    hits: &[Hit],
    light: Vec3,
) -> (Vec<Ray>, Vec<usize>) {
    let mut shadow = Vec::new();
    let mut owners = Vec::new();
    for (pixel, (ray, hit)) in rays.iter().zip(hits).enumerate() {
        if !hit.is_hit() {
            continue;
        }
        let surface = hit.surface(&tris[hit.prim as usize], Vec3::from(ray.dir));
        if surface.normal.dot(light - surface.origin) <= 0.0 {
            continue;
        }
        shadow.push(surface.ray_toward(light));
        owners.push(pixel);
    }
    (shadow, owners)
}

/// Lambert shading: `albedo * (ambient + (1 - ambient) * cos * visible)`, the background
/// colour where the camera ray hit nothing.
pub fn shade(
    tris: &[Triangle],
    albedo: &[Vec3],
    rays: &[Ray],
    hits: &[Hit],
    light: Vec3,
    in_shadow: &[bool],
) -> image::RgbImage {
    let mut image = image::RgbImage::new(WIDTH, HEIGHT);
    for (i, pixel) in image.pixels_mut().enumerate() {
        let hit = &hits[i];
        if !hit.is_hit() {
            pixel.0 = BACKGROUND;
            continue;
        }
        let tri = &tris[hit.prim as usize];
        let n = facing_normal(tri, Vec3::from(rays[i].dir));
        let l = (light - hit_point(tri, hit)).normalize_or_zero();
        let visible = if in_shadow[i] { 0.0 } else { 1.0 };
        let c =
            albedo[hit.prim as usize] * (AMBIENT + (1.0 - AMBIENT) * n.dot(l).max(0.0) * visible);
        pixel.0 = c.to_array().map(palette::to8);
    }
    image
}
