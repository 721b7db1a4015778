//! Calling the traversal from your own WGSL compute shader.
//!
//! ```text
//! cargo run --release -p bvhtrace-gpu --example own_shader -- [SCENE] [--two-level] [--ray-queries] [-o out.png]
//! ```
//!
//! With `--ray-queries`, the same shader runs on the device's ray queries where it has them
//! (wgpu's `EXPERIMENTAL_RAY_QUERY`; Mesa 25's lavapipe has them): the library is then
//! composed over the device's acceleration structures (`RayQueryBvh::wgsl_library`) with
//! the same calls, and our walk is the fallback where the device has none.
//!
//! The shader below ([`SHADER`]) is composed after bvhtrace's traversal library, composed
//! for the upload (`GpuBvh::wgsl_library`): it makes each pixel's camera ray itself, traces
//! it with `bvh_trace_closest` (here the stackless walk), and writes a colour per triangle,
//! shaded by how squarely the ray meets it (`bvh_hit_surface`'s normal), into a buffer of
//! RGBA8 pixels. The host loads SCENE (`builtin:cornell` by default, or any `.gltf`/`.glb`
//! path), builds one BVH over its triangles or, with `--two-level`, one per mesh under a
//! top level over its instances (the same shader: the library carries the instance walk),
//! uploads it, binds it in group 0 (`GpuBvh::bind_group_for`) and its own resources in
//! group 1, dispatches once and writes the PNG (`own_shader.png` by default).
//!
//! `tests/examples.rs` runs it and compares the image with one made on the CPU from
//! `bvhtrace_core::trace_rays` (pixel colours within a small tolerance, a few triangle
//! edges where the shader's rays differ from the CPU's in the last bit).

mod common;

use std::error::Error;

use bvhtrace_gpu::core::{BuildOptions, FlatBvh, Traversal};
use bvhtrace_gpu::wgpu::util::DeviceExt;
use bvhtrace_gpu::{
    AdapterChoice, ContextOptions, GpuBvh, GpuContext, RayQueryBvh, UploadOptions, wgpu,
};

/// The image size: small, so that CI renders it in a moment on lavapipe.
pub const WIDTH: u32 = 320;
/// See [`WIDTH`].
pub const HEIGHT: u32 = 240;

/// The user's shader. Everything it declares is its own; every name starting with `bvh_`,
/// `Bvh` or `BVH_` comes from the library composed before it.
const SHADER: &str = r#"
// The camera: what `bvhtrace_scene::Camera::ray` computes per pixel, with the basis and
// the field of view's tangent worked out on the host.
struct Camera {
    eye: vec3<f32>,
    tan_half_fov: f32,
    forward: vec3<f32>,
    aspect: f32,
    right: vec3<f32>,
    width: u32,
    up: vec3<f32>,
    height: u32,
}

@group(1) @binding(0) var<uniform> camera: Camera;
// RGBA8 pixels, row-major, top row first.
@group(1) @binding(1) var<storage, read_write> pixels: array<u32>;
// Pixels whose ray spent the trip budget (see `BVH_TRIP_LIMIT` on the host).
@group(1) @binding(2) var<storage, read_write> incomplete: atomic<u32>;

const BACKGROUND = vec3<f32>(24.0, 26.0, 32.0) / 255.0;
const FLAGGED = vec3<f32>(1.0, 0.0, 1.0);

// `bvhtrace_core::surface::hash` (PCG): a repeatable colour for each triangle.
fn hash(x0: u32) -> u32 {
    let x = x0 * 747796405u + 2891336453u;
    let w = ((x >> ((x >> 28u) + 4u)) ^ x) * 277803737u;
    return (w >> 22u) ^ w;
}

fn triangle_colour(prim: u32) -> vec3<f32> {
    let h = hash(prim);
    let bytes = vec3<f32>(vec3<u32>(h, h >> 8u, h >> 16u) & vec3<u32>(255u));
    return 0.35 + 0.65 * bytes / 255.0;
}

// 8 x 8 = 64 invocations: the traversal's stacks are laid out for at most STACK_LANES (64)
// lanes per workgroup, and each invocation passes its `local_invocation_index` as `lane`.
@compute @workgroup_size(8, 8)
fn main(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    if (id.x >= camera.width || id.y >= camera.height) {
        return;
    }
    let size = vec2<f32>(f32(camera.width), f32(camera.height));
    let px = (2.0 * (f32(id.x) + 0.5) / size.x - 1.0) * camera.tan_half_fov * camera.aspect;
    let py = (1.0 - 2.0 * (f32(id.y) + 0.5) / size.y) * camera.tan_half_fov;
    let dir = normalize(camera.forward + camera.right * px + camera.up * py);
    let ray = BvhRay(camera.eye, 0.0, dir, 1e30);

    // The closest hit, by the walk the library was composed for, in one mesh or through
    // the instances.
    let hit = bvh_trace_closest(ray, lane).hit;

    var colour = BACKGROUND;
    if (hit.prim == BVH_INCOMPLETE) {
        // Only under a trip budget (CPU drivers): finish such rays on the CPU, or re-trace
        // them; here they are counted and flagged.
        atomicAdd(&incomplete, 1u);
        colour = FLAGGED;
    } else if (hit.prim < BVH_INVALID_RAY) {
        // A hit: `BVH_MISS` and `BVH_INVALID_RAY` are above every triangle index.
        // `hit.prim` numbers the scene's triangles (instance by instance for two levels:
        // `bvh_hit_user_id()` and `bvh_hit_mesh_prim(hit)` split it), so it can index your
        // own per-triangle data. The world-space normal facing the ray, and the origin for
        // a secondary ray off the surface:
        let surface = bvh_hit_surface(ray, hit);
        let facing = abs(dot(surface.normal, dir));
        colour = triangle_colour(hit.prim) * (0.3 + 0.7 * facing);
    }
    pixels[id.y * camera.width + id.x] = pack4x8unorm(vec4<f32>(colour, 1.0));
}
"#;

fn main() -> Result<(), Box<dyn Error>> {
    // `main` would print an error with `Debug`; its message says more.
    run().map_err(|e| e.to_string().into())
}

fn run() -> Result<(), Box<dyn Error>> {
    let Some(common::Args { spec, out, flags }) = common::parse_args(
        "own_shader [SCENE] [--two-level] [--ray-queries] [-o out.png]",
        "own_shader.png",
        &["--two-level", "--ray-queries"],
    )?
    else {
        return Ok(());
    };
    let two_level = flags.iter().any(|f| f == "--two-level");
    let ray_queries = flags.iter().any(|f| f == "--ray-queries");

    let scene = bvhtrace_scene::load(&spec)?;
    let tris = scene.flatten().triangles()?;
    let bvh = if two_level {
        scene.instanced_bvh(&BuildOptions::default())?.bvh().clone()
    } else {
        FlatBvh::build(&tris, &BuildOptions::default())?
    };

    // The library's own device setup (the best adapter, or `$BVHTRACE_ADAPTER`); see the
    // `user_device` example for bringing your own.
    let options = ContextOptions {
        ray_queries,
        ..ContextOptions::default()
    };
    let ctx = GpuContext::new_with(AdapterChoice::Auto, &options)?;
    // Either upload holds the tree and composes the library for it, the BVH in group 0;
    // the shader below is the same for both.
    let (walk, rq);
    let (library, bvh_group) = if ctx.has_ray_queries() {
        // The device's acceleration structures, walked by its ray queries.
        rq = RayQueryBvh::upload(&ctx, &bvh)?;
        let library = rq.wgsl_library(0);
        (library.clone(), rq.bind_group_for(&library)?)
    } else {
        // Our stackless walk, in the context's storage (textures on a CPU driver, buffers
        // on GPUs), with the escape links it reads. A library composed for another upload
        // would be an error here, not a black image.
        let upload = UploadOptions::for_traversal(Traversal::Stackless);
        walk = GpuBvh::upload(&ctx, &bvh, &upload)?;
        let library = walk.wgsl_library(Traversal::Stackless, 0)?;
        (library.clone(), walk.bind_group_for(&library)?)
    };
    let device = ctx.device();
    println!(
        "adapter: {}; {} triangles, BVH of {} nodes; library: {}",
        ctx.adapter_info().name,
        tris.len(),
        bvh.nodes().len(),
        library.shape()
    );

    // The shader: the traversal library, then ours. A mistake in ours is an error naming
    // its line in SHADER, not a panic inside wgpu.
    let module = ctx.shader_module(&library, SHADER, "own_shader.wgsl")?;

    // Group 1: our resources.
    let camera = scene.camera_or_frame(WIDTH as f32 / HEIGHT as f32);
    let (forward, right, up) = camera.basis();
    let tan_half_fov = (camera.fov_y_deg.to_radians() * 0.5).tan();
    let aspect = WIDTH as f32 / HEIGHT as f32;
    let mut words: Vec<u32> = Vec::with_capacity(16);
    for (v, w) in [
        (camera.eye, tan_half_fov.to_bits()),
        (forward, aspect.to_bits()),
        (right, WIDTH),
        (up, HEIGHT),
    ] {
        words.extend(v.to_array().map(f32::to_bits));
        words.push(w);
    }
    let pixel_bytes = u64::from(WIDTH * HEIGHT) * 4;
    use wgpu::BufferUsages as U;
    let init = |label, contents: &[u8], usage| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage,
        })
    };
    let camera_buffer = init("camera", bytemuck::cast_slice(&words), U::UNIFORM);
    let counter = init("incomplete", &[0; 4], U::STORAGE | U::COPY_SRC);
    let buffer = |label, size, usage| common::buffer(device, label, size, usage);
    let pixels = buffer("pixels", pixel_bytes, U::STORAGE | U::COPY_SRC);
    // Pixels, then the counter.
    let readback = buffer("readback", pixel_bytes + 4, U::MAP_READ | U::COPY_DST);

    let entry = layout_entry;
    let storage = |read_only| wgpu::BufferBindingType::Storage { read_only };
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("own_shader group 1"),
        entries: &[
            entry(0, wgpu::BufferBindingType::Uniform),
            entry(1, storage(false)),
            entry(2, storage(false)),
        ],
    });
    let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("own_shader group 1"),
        layout: &layout,
        entries: &[bind(0, &camera_buffer), bind(1, &pixels), bind(2, &counter)],
    });

    let pipeline = pipeline(&ctx, "own_shader", &module, bvh_group.layout(), &layout);
    let mut encoder = encode_pass(
        device,
        &pipeline,
        bvh_group.group(),
        &group,
        [WIDTH.div_ceil(8), HEIGHT.div_ceil(8), 1],
    );
    encoder.copy_buffer_to_buffer(&pixels, 0, &readback, 0, pixel_bytes);
    encoder.copy_buffer_to_buffer(&counter, 0, &readback, pixel_bytes, 4);
    ctx.queue().submit([encoder.finish()]);

    let (tx, rx) = std::sync::mpsc::channel();
    readback.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    device.poll(wgpu::PollType::wait_indefinitely())?;
    rx.recv()??;
    let bytes = readback.get_mapped_range(..)?.to_vec();
    readback.unmap();

    let (rgba, count) = bytes.split_at(pixel_bytes as usize);
    let incomplete = u32::from_le_bytes([count[0], count[1], count[2], count[3]]);
    let image = image::RgbaImage::from_raw(WIDTH, HEIGHT, rgba.to_vec())
        .ok_or("the pixel buffer does not match the image size")?;
    image.save(&out)?;
    println!("incomplete: {incomplete} pixels (flagged magenta)");
    println!("wrote {}", out.display());
    Ok(())
}

/// A compute-stage buffer binding of type `ty` at `binding` (group 1 is ours).
pub fn layout_entry(binding: u32, ty: wgpu::BufferBindingType) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// The pipeline of `module`'s entry point `main`: the BVH's bind group (`bvh_layout`) at
/// group 0, ours (`layout`) at group 1.
pub fn pipeline(
    ctx: &GpuContext,
    label: &str,
    module: &wgpu::ShaderModule,
    bvh_layout: &wgpu::BindGroupLayout,
    layout: &wgpu::BindGroupLayout,
) -> wgpu::ComputePipeline {
    let device = ctx.device();
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &[Some(bvh_layout), Some(layout)],
        immediate_size: 0,
    });
    // The trip budget of this device (unbounded on GPUs; on a CPU driver, which ends any
    // invocation that loops too long, a ray that spends it answers `BVH_INCOMPLETE`
    // instead of a wrong hit). Workgroup memory is not zeroed: the walks write every stack
    // entry before reading it.
    let constants = [("BVH_TRIP_LIMIT", f64::from(ctx.tuning().trip_limit))];
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: Some(&pipeline_layout),
        module,
        entry_point: Some("main"),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants: &constants,
            zero_initialize_workgroup_memory: false,
        },
        cache: None,
    })
}

/// A command encoder holding one pass of `pipeline` over `workgroups`, with the BVH's
/// bind group at group 0 and ours (`group`) at group 1.
pub fn encode_pass(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    bvh_group: &wgpu::BindGroup,
    group: &wgpu::BindGroup,
    [x, y, z]: [u32; 3],
) -> wgpu::CommandEncoder {
    let mut encoder = device.create_command_encoder(&Default::default());
    {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bvh_group, &[]);
        pass.set_bind_group(1, group, &[]);
        pass.dispatch_workgroups(x, y, z);
    }
    encoder
}

/// The whole of `buffer` at `binding`.
pub fn bind(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}
