//! Progressive frames shown without a readback: adding samples and tone mapping them into
//! the display texture reads nothing back (`GpuContext::readbacks` unchanged over steady
//! frames), and the texture shows what `Accumulation::to_srgb8` makes on the host.

mod support;

use bvhtrace_core::{BuildOptions, FlatBvh, Traversal};
use bvhtrace_gpu::{GpuContext, wgpu};
use bvhtrace_path::{GpuPathTracer, Lighting, PathParams, PathScene};

#[test]
fn steady_frames_read_nothing_back_and_show_the_sums() {
    let Some(ctx) = support::context("the path display") else {
        return;
    };
    let scene = bvhtrace_scene::load("builtin:cornell").expect("cornell");
    let tris = scene.flattened_triangles().expect("triangles");
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let shading = PathScene::new(&scene, &tris).expect("shading");
    let (w, h) = (40, 30);
    let camera = scene.camera_or_frame(w as f32 / h as f32);
    let params = PathParams::new(&camera, (w, h), &Lighting::default(), 6, &shading);
    let mut tracer =
        GpuPathTracer::new(&ctx, &bvh, &shading, Traversal::Stackless).expect("tracer");
    tracer.restart(params);
    // The first frame makes the display texture; the frames after it are the steady ones.
    tracer.add_samples(1).expect("samples");
    tracer.display(1.0).expect("display");
    tracer.wait().expect("wait");
    let before = ctx.readbacks();
    for _ in 0..4 {
        tracer.add_samples(1).expect("samples");
        tracer.display(1.0).expect("display");
    }
    tracer.wait().expect("wait");
    assert_eq!(ctx.readbacks(), before, "steady frames read back");
    assert_eq!(tracer.samples(), 5);

    // Reading is one readback; the texture is the host's tone mapping, within a level.
    let (sums, _) = tracer.read().expect("read");
    assert_eq!(ctx.readbacks(), before + 1);
    let host = sums.to_srgb8(1.0);
    let shown = texture_rgb(&ctx, tracer.display(1.0).expect("display"), w, h);
    let off = host
        .iter()
        .zip(&shown)
        .filter(|(a, b)| a.abs_diff(**b) > 1)
        .count();
    assert_eq!(off, 0, "texels more than one level from the host's image");
    assert!(host.iter().any(|&c| c > 40), "a dark image");
}

/// The RGB of an RGBA8 texture, row by row.
fn texture_rgb(ctx: &GpuContext, texture: &wgpu::Texture, w: u32, h: u32) -> Vec<u8> {
    let row = (w * 4).div_ceil(256) * 256;
    let buffer = ctx.device().create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: u64::from(row * h),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let mut encoder = ctx.device().create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: None,
            },
        },
        texture.size(),
    );
    ctx.queue().submit([encoder.finish()]);
    let bytes = ctx
        .read_buffers("reading the display", &[&buffer])
        .expect("read")[0]
        .clone();
    (0..h as usize)
        .flat_map(|y| {
            let start = y * row as usize;
            bytes[start..start + w as usize * 4]
                .chunks(4)
                .flat_map(|p| [p[0], p[1], p[2]])
                .collect::<Vec<u8>>()
        })
        .collect()
}
