//! The refit on the device (`GpuRefit`): after the vertices move on the device, the boxes
//! and corners read back equal the CPU refit's (`FlatBvh::refit`), and the GPU walks
//! answer as the CPU walks do on the CPU-refitted tree; indexed and packed vertices, a bad
//! vertex refused with the tree left as it was, a tree split over several bindings, and the
//! uploads it cannot refit refused by name; skins and morph targets applied on the device as the CPU applies them. Without a
//! Vulkan adapter the tests print SKIP.

use bvhtrace_core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal, Triangle};
use bvhtrace_gpu::wgpu::{self, util::DeviceExt};
use bvhtrace_gpu::{
    BvhStorage, GpuBvh, GpuContext, GpuError, GpuMorph, GpuRefit, GpuSkin, RefitVertices, Tracer,
    UploadOptions,
};
use glam::Vec3;

mod support;

/// A wavy indexed grid of `n` x `n` quads: positions and three indices per triangle.
fn grid(n: u32) -> (Vec<Vec3>, Vec<u32>) {
    let mut pos = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            let (x, y) = (i as f32 / n as f32, j as f32 / n as f32);
            pos.push(Vec3::new(x, y, 0.1 * (7.0 * x).sin() * (5.0 * y).cos()));
        }
    }
    let mut idx = Vec::new();
    let at = |i: u32, j: u32| j * (n + 1) + i;
    for j in 0..n {
        for i in 0..n {
            idx.extend([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
            idx.extend([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
        }
    }
    (pos, idx)
}

fn triangles(pos: &[Vec3], idx: &[u32]) -> Vec<Triangle> {
    idx.chunks(3)
        .map(|c| [pos[c[0] as usize], pos[c[1] as usize], pos[c[2] as usize]])
        .collect()
}

/// Every vertex moved by a smooth field, far enough that the boxes change a lot.
fn moved(pos: &[Vec3]) -> Vec<Vec3> {
    pos.iter()
        .map(|p| {
            *p + Vec3::new(
                (3.0 * p.y).sin(),
                (2.0 * p.x).cos(),
                0.5 * (4.0 * p.x).sin(),
            ) * 0.2
        })
        .collect()
}

/// 48 x 48 rays from in front of (+z) the box of `bvh`, aimed across it.
fn rays(bvh: &FlatBvh) -> Vec<Ray> {
    let b = bvh.bounds();
    let size = (b.max - b.min).max(Vec3::splat(1e-3));
    let eye = (b.min + b.max) * 0.5 + Vec3::new(0.1, 0.05, 3.0) * size.max_element();
    let mut out = Vec::new();
    for i in 0..48 {
        for j in 0..48 {
            let f = Vec3::new(
                i as f32 / 47.0 * 1.2 - 0.1,
                j as f32 / 47.0 * 1.2 - 0.1,
                0.5,
            );
            out.push(Ray::new(eye, b.min + size * f - eye));
        }
    }
    out
}

fn storage_buffer(ctx: &GpuContext, label: &str, bytes: &[u8]) -> wgpu::Buffer {
    ctx.device()
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        })
}

/// `pos` packed `xyz` and `idx`, as storage buffers.
fn indexed(ctx: &GpuContext, pos: &[Vec3], idx: &[u32]) -> (wgpu::Buffer, wgpu::Buffer) {
    let packed: Vec<f32> = pos.iter().flat_map(|p| p.to_array()).collect();
    (
        storage_buffer(ctx, "positions", bytemuck::cast_slice(&packed)),
        storage_buffer(ctx, "indices", bytemuck::cast_slice(idx)),
    )
}

/// `vertices` packed `xyz` positions, read through `indices`.
fn packed<'a>(
    positions: &'a wgpu::Buffer,
    vertices: usize,
    indices: &'a wgpu::Buffer,
) -> RefitVertices<'a> {
    RefitVertices {
        positions,
        stride: 3,
        vertices: vertices as u32,
        indices: Some(indices),
    }
}

fn upload(ctx: &GpuContext, bvh: &FlatBvh) -> GpuBvh {
    upload_in(ctx, bvh, BvhStorage::Buffers)
}

fn upload_in(ctx: &GpuContext, bvh: &FlatBvh, storage: BvhStorage) -> GpuBvh {
    let opts = UploadOptions::all().with_storage(storage);
    GpuBvh::upload(ctx, bvh, &opts).expect("upload")
}

/// The device's tree equals `want` box for box and corner for corner, and every GPU walk
/// answers on it as on `want` uploaded afresh (the same device's arithmetic: a GPU that
/// fuses multiply-adds answers the CPU's walks only within f32 bounds).
fn assert_same(refit: &GpuRefit, gpu: &GpuBvh, want: &FlatBvh, what: &str) {
    let got = refit.read_back().expect("read back");
    for (i, (g, w)) in got.nodes().iter().zip(want.nodes()).enumerate() {
        // `==` on the floats: a box's zero may come back with either sign.
        assert!(
            g.min == w.min && g.max == w.max,
            "{what}: node {i}: {g:?} != {w:?}"
        );
    }
    assert_eq!(got.triangles(), want.triangles(), "{what}: corners");
    let rays = rays(want);
    let fresh = upload_in(gpu.context(), want, BvhStorage::Buffers);
    for walk in [Traversal::FullStack, Traversal::Stackless] {
        let opts = TraceOptions::closest(walk);
        let g = gpu.trace(&rays, &opts).expect("trace").hits;
        let c = fresh.trace(&rays, &opts).expect("trace").hits;
        assert_eq!(g, c, "{what}: {walk}");
        assert!(
            c.iter().filter(|h| h.is_hit()).count() > 200,
            "{what}: the rays hit"
        );
    }
}

#[test]
fn a_device_refit_equals_the_cpu_refit() {
    let Some(ctx) = support::context("device refit") else {
        return;
    };
    let (pos, idx) = grid(40);
    let tree = FlatBvh::build(&triangles(&pos, &idx), &BuildOptions::default()).expect("build");
    let after = moved(&pos);
    let mut want = tree.clone();
    want.refit(&triangles(&after, &idx)).expect("CPU refit");
    assert_ne!(want.nodes(), tree.nodes(), "the boxes moved");

    // Indexed, packed xyz.
    let mut gpu = upload(&ctx, &tree);
    let (positions, indices) = indexed(&ctx, &after, &idx);
    let v = packed(&positions, after.len(), &indices);
    let refit = GpuRefit::new(&gpu, &tree, v).expect("prepare");
    let times = refit.refit(&mut gpu).expect("refit");
    assert_eq!(times.dispatches, refit.dispatches());
    assert_same(&refit, &gpu, &want, "indexed");

    // In textures: refitted in buffers of its own, copied over them (the nodes as
    // texels). One texel row (8192 texels) and several: the copies of whole rows and of
    // the last one.
    for n in [20, 90] {
        let (pos, idx) = grid(n);
        let tree = FlatBvh::build(&triangles(&pos, &idx), &BuildOptions::default()).expect("build");
        let after = moved(&pos);
        let mut want = tree.clone();
        want.refit(&triangles(&after, &idx)).expect("CPU refit");
        let mut gpu = upload_in(&ctx, &tree, BvhStorage::Textures);
        let (positions, indices) = indexed(&ctx, &after, &idx);
        let v = packed(&positions, after.len(), &indices);
        let refit = GpuRefit::new(&gpu, &tree, v).expect("prepare");
        refit.refit(&mut gpu).expect("refit");
        let what = format!("textures, {} nodes", tree.nodes().len());
        assert_same(&refit, &gpu, &want, &what);
    }

    // Unindexed (three vertices per triangle), vec4 positions, a fresh upload.
    let mut gpu = upload(&ctx, &tree);
    let soup: Vec<f32> = triangles(&after, &idx)
        .iter()
        .flatten()
        .flat_map(|p| [p.x, p.y, p.z, 1.0])
        .collect();
    let positions = storage_buffer(&ctx, "soup", bytemuck::cast_slice(&soup));
    let v = RefitVertices {
        positions: &positions,
        stride: 4,
        vertices: (soup.len() / 4) as u32,
        indices: None,
    };
    let refit = GpuRefit::new(&gpu, &tree, v).expect("prepare");
    refit.refit(&mut gpu).expect("refit");
    assert_same(&refit, &gpu, &want, "unindexed");

    // Back to the start: the vertices written again and refitted anew.
    let start: Vec<f32> = triangles(&pos, &idx)
        .iter()
        .flatten()
        .flat_map(|p| [p.x, p.y, p.z, 1.0])
        .collect();
    ctx.queue()
        .write_buffer(&positions, 0, bytemuck::cast_slice(&start));
    refit.refit(&mut gpu).expect("refit");
    assert_same(&refit, &gpu, &tree, "moved back");
}

/// A tree split over several bindings (a device whose bindings hold a third of its nodes)
/// is refitted in place page by page: the CPU refit's boxes and corners, and its hits.
#[test]
fn a_tree_split_into_pages_refits_as_the_cpu_does() {
    let (pos, idx) = grid(40);
    let tree = FlatBvh::build(&triangles(&pos, &idx), &BuildOptions::default()).expect("build");
    let third = std::mem::size_of_val(tree.nodes()) as u64 / 3;
    let options = bvhtrace_gpu::ContextOptions {
        max_binding_bytes: Some(third),
        ..Default::default()
    };
    let Some(ctx) = support::context_with("device refit in pages", &options) else {
        return;
    };
    let after = moved(&pos);
    let mut want = tree.clone();
    want.refit(&triangles(&after, &idx)).expect("CPU refit");
    let mut gpu = upload(&ctx, &tree);
    let pages = gpu.tree().pages;
    assert!(pages.nodes >= 3 && pages.triangles >= 2, "{pages:?}");
    let (positions, indices) = indexed(&ctx, &after, &idx);
    let refit = GpuRefit::new(&gpu, &tree, packed(&positions, after.len(), &indices))
        .expect("prepare in pages");
    refit.refit(&mut gpu).expect("refit in pages");
    assert_same(&refit, &gpu, &want, "in pages");
}

#[test]
fn a_bad_vertex_is_refused_and_the_tree_kept() {
    let Some(ctx) = support::context("device refit") else {
        return;
    };
    let (pos, idx) = grid(12);
    let tree = FlatBvh::build(&triangles(&pos, &idx), &BuildOptions::default()).expect("build");
    let mut gpu = upload(&ctx, &tree);
    let mut after = moved(&pos);
    let bad_vertex = idx[3 * 57 + 1] as usize;
    after[bad_vertex].y = f32::NAN;
    let (positions, indices) = indexed(&ctx, &after, &idx);
    let v = packed(&positions, pos.len(), &indices);
    let refit = GpuRefit::new(&gpu, &tree, v).expect("prepare");
    let first_bad = idx
        .chunks(3)
        .position(|c| c.contains(&(bad_vertex as u32)))
        .expect("used");
    match refit.refit(&mut gpu) {
        Err(GpuError::BadBuffer { problem, .. }) => {
            assert!(
                problem.contains(&format!("triangle {first_bad}:")),
                "{problem}"
            );
            assert!(problem.contains("NaN"), "{problem}");
        }
        other => panic!("a NaN vertex was refitted: {other:?}"),
    }
    assert_same(&refit, &gpu, &tree, "after the refused refit");

    // An index past the vertices.
    let mut wrong = idx.clone();
    wrong[3 * 30 + 2] = pos.len() as u32 + 5;
    let indices = storage_buffer(&ctx, "wrong indices", bytemuck::cast_slice(&wrong));
    let v = packed(&positions, pos.len(), &indices);
    match GpuRefit::new(&gpu, &tree, v)
        .expect("prepare")
        .refit(&mut gpu)
    {
        Err(GpuError::BadBuffer { problem, .. }) => {
            assert!(problem.contains("out of range"), "{problem}")
        }
        other => panic!("an index out of range was refitted: {other:?}"),
    }
}

#[test]
fn uploads_it_cannot_refit_are_refused_by_name() {
    let Some(ctx) = support::context("device refit") else {
        return;
    };
    let (pos, idx) = grid(6);
    let tris = triangles(&pos, &idx);
    let tree = FlatBvh::build(&tris, &BuildOptions::default()).expect("build");
    let (positions, indices) = indexed(&ctx, &pos, &idx);
    let v = packed(&positions, pos.len(), &indices);
    let refused =
        |gpu: &GpuBvh, tree: &FlatBvh, v: RefitVertices<'_>, what: &str| match GpuRefit::new(
            gpu, tree, v,
        ) {
            Err(e) => assert!(e.to_string().contains(what), "{e}"),
            Ok(_) => panic!("refit prepared; expected an error naming {what}"),
        };
    let wide = UploadOptions::all()
        .with_storage(BvhStorage::Buffers)
        .with_traversal(Traversal::Wide);
    refused(
        &GpuBvh::upload(&ctx, &tree, &wide).expect("upload"),
        &tree,
        v,
        "wide layout",
    );
    let gpu = upload(&ctx, &tree);
    let other = FlatBvh::build(&tris[..20], &BuildOptions::default()).expect("build");
    refused(&gpu, &other, v, "shape");
    refused(&gpu, &tree, RefitVertices { stride: 2, ..v }, "stride");
    refused(
        &gpu,
        &tree,
        RefitVertices {
            vertices: 1000,
            ..v
        },
        "bytes for 1000 vertices",
    );
}

/// `scenes/skinned.gltf`'s tube skinned where it is traced: at two times the device's
/// positions equal the CPU twin's (`Scene::set_time`, `skin_vertex`) and the device's refit
/// equals the CPU refit over them, box for box, with the same hits; the two poses differ.
#[test]
fn a_skin_skinned_and_refitted_on_the_device_equals_the_cpu() {
    let Some(ctx) = support::context("device refit") else {
        return;
    };
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/skinned.gltf");
    let mut scene = bvhtrace_scene::load(path).expect("loads");
    let anim = scene.animation.clone().expect("animated");
    let skin = &anim.skins()[0];
    let mesh = scene.instances[skin.instance()].mesh;
    let tris = |s: &bvhtrace_scene::Scene| -> Vec<Triangle> {
        let m = &s.meshes[mesh];
        m.indices
            .iter()
            .map(|t| t.map(|i| m.positions[i as usize]))
            .collect()
    };
    let tree = FlatBvh::build(&tris(&scene), &BuildOptions::default()).expect("build");
    let mut gpu = upload(&ctx, &tree);
    let indices: Vec<u32> = scene.meshes[mesh]
        .indices
        .iter()
        .flatten()
        .copied()
        .collect();
    let indices = storage_buffer(&ctx, "tube indices", bytemuck::cast_slice(&indices));
    let joints = skin.joint_count() as u32;
    let on_device = GpuSkin::new(
        &ctx,
        skin.bind_positions(),
        skin.vertex_joints(),
        skin.vertex_weights(),
        joints,
    )
    .expect("skin uploaded");
    let refit = GpuRefit::new(&gpu, &tree, on_device.vertices(Some(&indices))).expect("prepare");
    let mut poses = Vec::new();
    for t in [0.25f32, 1.0] {
        let world = anim.node_transforms_at(t);
        let matrices = skin.joint_matrices(&world, anim.global_transform());
        on_device.set_matrices(&matrices).expect("matrices");
        let skinned = on_device.skin_and_read().expect("skinned");
        scene.set_time(t);
        assert_eq!(
            skinned, scene.meshes[mesh].positions,
            "t = {t}: device skin != CPU skin"
        );
        let mut want = tree.clone();
        want.refit(&tris(&scene)).expect("CPU refit");
        refit.refit(&mut gpu).expect("device refit");
        assert_same(&refit, &gpu, &want, &format!("skinned at t = {t}"));
        poses.push(want);
    }
    assert_ne!(
        poses[0].nodes(),
        poses[1].nodes(),
        "the two times gave one pose"
    );
    assert!(
        on_device.set_matrices(&[glam::Mat4::IDENTITY]).is_err(),
        "one matrix for two joints"
    );
}

/// `scenes/morph.gltf` deformed where it is traced: the sphere's two morph targets, and the
/// tube's target morphed then skinned, give at two times the CPU twin's positions
/// (`Animation::deformed_at`) bit for bit, and the refit over them the CPU refit; the two
/// poses differ. Bad weights are refused by name.
#[test]
fn morph_targets_applied_on_the_device_equal_the_cpu() {
    let Some(ctx) = support::context("device morph") else {
        return;
    };
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/morph.gltf");
    let scene = bvhtrace_scene::load(path).expect("loads");
    let anim = scene.animation.clone().expect("animated");
    assert_eq!(anim.morphs().len(), 2, "the tube and the sphere");
    for morph in anim.morphs() {
        let i = morph.instance();
        let skin = anim.skins().iter().find(|s| s.instance() == i);
        let mesh = &scene.meshes[scene.instances[i].mesh];
        let on_device =
            GpuMorph::new(&ctx, morph.base_positions(), morph.position_deltas()).expect("upload");
        let skinned = skin.map(|s| {
            let joints = s.joint_count() as u32;
            GpuSkin::after_morph(&on_device, s.vertex_joints(), s.vertex_weights(), joints)
                .expect("skin after the morph")
        });
        let tris = |p: &[Vec3]| -> Vec<Triangle> {
            (mesh.indices.iter())
                .map(|t| t.map(|k| p[k as usize]))
                .collect()
        };
        let tree = FlatBvh::build(&tris(&mesh.positions), &BuildOptions::default()).expect("build");
        let mut gpu = upload(&ctx, &tree);
        let idx: Vec<u32> = mesh.indices.iter().flatten().copied().collect();
        let indices = storage_buffer(&ctx, "indices", bytemuck::cast_slice(&idx));
        let vertices = match &skinned {
            Some(s) => s.vertices(Some(&indices)),
            None => on_device.vertices(Some(&indices)),
        };
        let refit = GpuRefit::new(&gpu, &tree, vertices).expect("prepare");
        let mut poses = Vec::new();
        for t in [0.25f32, 1.0] {
            on_device
                .set_weights(&anim.morph_weights_at(morph, Some(t)))
                .expect("weights");
            let got = match (&skinned, skin) {
                (Some(gs), Some(s)) => {
                    let world = anim.node_transforms_at(t);
                    let m = s.joint_matrices(&world, anim.global_transform());
                    gs.set_matrices(&m).expect("matrices");
                    let mut enc = ctx.device().create_command_encoder(&Default::default());
                    on_device.record(&mut enc);
                    gs.record(&mut enc);
                    gs.read_after(enc).expect("morphed and skinned")
                }
                _ => on_device.morph_and_read().expect("morphed"),
            };
            let want = anim.deformed_at(Some(t));
            let want = want.iter().find(|d| d.instance == i).expect("deformed");
            assert_eq!(
                got, want.positions,
                "instance {i} at t = {t}: device != CPU"
            );
            let mut cpu = tree.clone();
            cpu.refit(&tris(&want.positions)).expect("CPU refit");
            refit.refit(&mut gpu).expect("device refit");
            assert_same(&refit, &gpu, &cpu, &format!("instance {i} at t = {t}"));
            poses.push(cpu);
        }
        assert_ne!(poses[0].nodes(), poses[1].nodes(), "instance {i}: one pose");
        let n = morph.target_count();
        assert!(
            on_device.set_weights(&vec![0.0; n + 1]).is_err(),
            "too many weights"
        );
        assert!(
            on_device.set_weights(&vec![f32::NAN; n]).is_err(),
            "a NaN weight"
        );
    }
    let bad = GpuMorph::new(&ctx, &[Vec3::ZERO; 3], &[Vec3::ZERO; 4]);
    assert!(bad.is_err(), "4 deltas for 3 vertices");
}
