//! The ray-query tracer (the device's own acceleration structures, walked by `rayQuery`)
//! against the CPU walks, ray by ray, under the rule of `bvhtrace_core::oracle::agreement`:
//! the same primitive, or distances f32 cannot tell apart, or a silhouette edge. Ray
//! queries cannot start behind the origin, so the reference traces each ray with `t_min`
//! raised to 0 (the tracer's stated rule). Every test prints how many rays fell in each
//! class, and fails on any ray outside the rule.
//!
//! Alpha-tested trees (`FlatBvh::masks`) are held to one more clause: the driver decides a
//! masked candidate at its own barycentrics, so where the answers differ otherwise, the
//! nearer of the two hits must lie on a masked triangle whose mask changes its verdict
//! within [`BORDER_STEP`] of that hit's barycentrics (a texel border, which the two tests'
//! barycentrics may straddle), and such rays must stay a tiny fraction.
//!
//! Needs a device with wgpu's `EXPERIMENTAL_RAY_QUERY` (Mesa 25's lavapipe does; Mesa 22's
//! does not). Without one the tests print SKIP, unless `BVHTRACE_REQUIRE_RAY_QUERIES=1`
//! (set by `.ci/run` when it installed Mesa 25), which makes that a failure.

use bvhtrace_core::oracle::{Agreement, agreement};
use bvhtrace_core::{
    BuildOptions, FlatBvh, Instance, InstancedBvh, MaskTables, Precision, Query, Ray, TraceOptions,
    TraceOutput, Traversal, Triangle, trace_rays,
};
use bvhtrace_gpu::{
    AdapterChoice, ContextOptions, GpuContext, GpuError, RayQueryBvh, TraceError, Tracer,
};
use glam::{Affine3A, Vec3};

mod support;
use support::masked::{edge_cases, masked_rays};
use support::{parity_rays, parity_scenes, ray_set};

/// Set to 1 when a device with ray queries must be there.
const REQUIRE_ENV: &str = "BVHTRACE_REQUIRE_RAY_QUERIES";

/// A device with ray queries, or `None` after SKIP.
fn context(test: &str) -> Option<GpuContext> {
    let required = std::env::var(REQUIRE_ENV).is_ok_and(|v| v == "1");
    let options = ContextOptions {
        ray_queries: true,
        ..ContextOptions::default()
    };
    let why = match GpuContext::new_with(AdapterChoice::Auto, &options) {
        Ok(ctx) if ctx.has_ray_queries() => {
            let i = ctx.adapter_info();
            eprintln!("ray queries on {} ({})", i.name, i.driver_info);
            return Some(ctx);
        }
        Ok(ctx) => format!(
            "{} ({}) has no EXPERIMENTAL_RAY_QUERY",
            ctx.adapter_info().name,
            ctx.adapter_info().driver_info
        ),
        Err(e) => e.to_string(),
    };
    assert!(!required, "{REQUIRE_ENV}=1 but {why}");
    eprintln!("SKIP {test}: {why}");
    None
}

/// Rays in each [`Agreement`] class.
#[derive(Default, Debug)]
struct Tally {
    same: usize,
    same_primitive: usize,
    within_f32: usize,
    silhouette: usize,
    /// Masked trees only: rays the agreement rule does not explain but a texel border does.
    texel_border: usize,
    differs: Vec<String>,
}

impl Tally {
    fn report(&self, label: &str, rays: usize) -> String {
        format!(
            "{label}: {rays} rays, {} identical, {} same primitive, {} within f32, {} silhouette, \
             {} texel border, {} outside the rule",
            self.same,
            self.same_primitive,
            self.within_f32,
            self.silhouette,
            self.texel_border,
            self.differs.len()
        )
    }
}

/// The ray as the reference traces it: `t_min` raised to 0.
fn from_origin(r: &Ray) -> Ray {
    Ray {
        // Only a negative start is raised: a NaN stays, for the ray to stay invalid.
        t_min: if r.t_min < 0.0 { 0.0 } else { r.t_min },
        ..*r
    }
}

/// The step in barycentrics within which a mask's verdict may change between the CPU's
/// barycentrics and the driver's: far above how far apart the two tests put the same hit
/// (the masked test prints and checks the largest gap), far below a texel.
const BORDER_STEP: f32 = 1e-3;

/// True when `masks`' verdict on a candidate at `(u, v)` on mesh primitive `prim` of an
/// instance with `base` changes within [`BORDER_STEP`]: a texel border (or a triangle's edge
/// in texture space) runs that close.
fn near_texel_border(masks: &MaskTables, base: u32, prim: u32, u: f32, v: f32) -> bool {
    let at = masks.accept(base, prim, u, v);
    let d = BORDER_STEP;
    [(d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d), (d, -d), (-d, d)]
        .iter()
        .any(|&(du, dv)| masks.accept(base, prim, u + du, v + dv) != at)
}

/// Ray `i`'s hit in `out` as the masks index it: its instance's base and mesh primitive.
fn masked_place(masks: &MaskTables, out: &TraceOutput, i: usize) -> (u32, u32) {
    match out.instance_hit(i) {
        Some(h) => (masks.base(Some(h.instance)), h.prim),
        None => (masks.base(None), out.hits[i].prim),
    }
}

/// Whether a texel border explains ray `i`'s answers `want` (CPU) and `got` (ray queries)
/// disagreeing on a masked tree: the nearer hit (the one the other side's test cut) lies on
/// one.
fn texel_border(masks: &MaskTables, want: &TraceOutput, got: &TraceOutput, i: usize) -> bool {
    let (a, b) = (&want.hits[i], &got.hits[i]);
    let out = if b.is_hit() && (!a.is_hit() || b.t < a.t) {
        got
    } else {
        want
    };
    let h = &out.hits[i];
    let (base, prim) = masked_place(masks, out, i);
    h.is_hit() && near_texel_border(masks, base, prim, h.u, h.v)
}

/// Compares `got` with the CPU walks over `bvh` for `rays` under the rule (with the texel
/// border clause for a masked tree).
fn tally(
    tris: &[Triangle],
    bvh: &FlatBvh,
    rays: &[Ray],
    opts: &TraceOptions,
    got: &TraceOutput,
) -> Tally {
    let clamped: Vec<Ray> = rays.iter().map(from_origin).collect();
    let want = trace_rays(bvh, &clamped, opts);
    assert_eq!(want.hits.len(), got.hits.len());
    let mut t = Tally::default();
    for (i, ((r, a), b)) in clamped.iter().zip(&want.hits).zip(&got.hits).enumerate() {
        match agreement(tris, r, a, b, opts.query == Query::Any) {
            Agreement::Same => t.same += 1,
            Agreement::SamePrimitive => t.same_primitive += 1,
            Agreement::WithinF32 => t.within_f32 += 1,
            Agreement::Silhouette => t.silhouette += 1,
            Agreement::Differs if bvh.masks().is_some_and(|m| texel_border(m, &want, got, i)) => {
                t.texel_border += 1
            }
            Agreement::Differs => t
                .differs
                .push(format!("ray {i}: {r:?}\n  cpu {a:?}\n  ray query {b:?}")),
        }
    }
    t
}

/// Traces `rays` both ways on a fresh upload and on `rq` when given; panics (listing the
/// first rays) on any ray outside the rule.
fn check(label: &str, tris: &[Triangle], bvh: &FlatBvh, rays: &[Ray], rq: &RayQueryBvh) {
    for opts in [
        TraceOptions::closest(Traversal::FullStack),
        TraceOptions::any(Traversal::FullStack),
    ] {
        // A smaller batch first, then the whole: each answers as alone.
        let half = rq
            .trace(&rays[..rays.len() / 2], &opts)
            .expect("half the rays");
        let got = rq.trace(rays, &opts).expect("ray-query trace");
        assert_eq!(half.hits, got.hits[..rays.len() / 2], "{label}");
        assert!(got.phases.is_some_and(|p| p.device_ms > 0.0), "{label}");
        let t = tally(tris, bvh, rays, &opts, &got);
        let label = format!("{label}, {:?}", opts.query);
        eprintln!("{}", t.report(&label, rays.len()));
        assert!(
            t.differs.is_empty(),
            "{}\n{}",
            t.report(&label, rays.len()),
            t.differs[..t.differs.len().min(4)].join("\n")
        );
        // The border clause explains a sliver of rays, not a whole mask decided otherwise.
        assert!(
            t.texel_border <= rays.len() / MAX_BORDER_RAYS_PER,
            "{}",
            t.report(&label, rays.len())
        );
    }
}

/// At most one ray in this many may be explained only by a texel border.
const MAX_BORDER_RAYS_PER: usize = 200;

#[test]
fn the_parity_scenes_agree_with_the_cpu_walks_under_the_rule() {
    let Some(ctx) = context("ray-query parity") else {
        return;
    };
    for scene in parity_scenes() {
        let rq = RayQueryBvh::upload(&ctx, &scene.bvh)
            .unwrap_or_else(|e| panic!("{}: upload: {e}", scene.name));
        let rays = parity_rays(&scene.bvh);
        check(&scene.name, &scene.tris, &scene.bvh, &rays, &rq);
    }
}

/// Every triangle of a two-level BVH in world space, by primitive id.
fn world_triangles(ib: &InstancedBvh) -> Vec<Triangle> {
    let mut out = Vec::new();
    for inst in ib.instances() {
        let mut tris = ib.mesh_bvh(inst.mesh as usize).triangles().to_vec();
        tris.sort_by_key(|t| t.prim);
        out.extend(
            tris.iter()
                .map(|t| t.corners().map(|p| inst.transform.transform_point3(p))),
        );
    }
    out
}

#[test]
fn two_levels_agree_after_moving_instances_and_after_a_refit() {
    let Some(ctx) = context("ray-query updates") else {
        return;
    };
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    let mut ib = scene
        .instanced_bvh(&BuildOptions::default())
        .expect("two levels");
    let rays: Vec<Ray> = ray_set(ib.bvh(), 0x70b).into_iter().step_by(3).collect();
    let mut rq = RayQueryBvh::upload(&ctx, ib.bvh()).expect("upload");
    let (meshes, instances) = rq.counts();
    assert_eq!(instances, ib.instances().len());
    assert!(meshes >= 2 && meshes <= instances, "{meshes} BLASes");
    check(
        "spheres as uploaded",
        &world_triangles(&ib),
        ib.bvh(),
        &rays,
        &rq,
    );
    let before = rq
        .trace(&rays, &TraceOptions::default())
        .expect("trace")
        .hits;

    ib.set_transforms(&support::moved_transforms(&ib))
        .expect("new transforms");
    rq.update(ib.bvh()).expect("TLAS rebuilt");
    check("spheres moved", &world_triangles(&ib), ib.bvh(), &rays, &rq);
    let after = rq
        .trace(&rays, &TraceOptions::default())
        .expect("trace")
        .hits;
    assert_ne!(
        before, after,
        "moving the instances changed no ray-query hit"
    );

    ib.refit_mesh(0, &support::swollen_mesh(&ib, 0))
        .expect("refit");
    rq.update(ib.bvh()).expect("BLASes updated");
    check(
        "spheres refitted",
        &world_triangles(&ib),
        ib.bvh(),
        &rays,
        &rq,
    );

    let other = bvhtrace_scene::load("builtin:cornell")
        .expect("builtin")
        .instanced_bvh(&BuildOptions::default())
        .expect("two levels");
    let err = rq.update(other.bvh()).expect_err("another shape");
    assert!(matches!(err, TraceError::BadBuffer { .. }), "{err}");
}

#[test]
fn ids_masks_and_user_ids_are_the_walks() {
    let Some(ctx) = context("ray-query ids") else {
        return;
    };
    let scene = bvhtrace_scene::load("builtin:grid:icosphere:4x3").expect("builtin scene");
    let meshes: Vec<Vec<Triangle>> = scene
        .meshes
        .iter()
        .map(|m| m.triangle_mesh().triangles().expect("triangles"))
        .collect();
    // Masks 1, 2, 4 by instance; user ids 100 + k.
    let instances: Vec<Instance> = scene
        .instances
        .iter()
        .enumerate()
        .map(|(k, i)| Instance {
            mask: 1 << (k % 3),
            user_id: 100 + k as u32,
            ..Instance::new(i.mesh as u32, Affine3A::from_mat4(i.transform))
        })
        .collect();
    let ib = InstancedBvh::build(&meshes, instances, &BuildOptions::default()).expect("two levels");
    let bvh = ib.bvh();
    let rays = parity_rays(bvh);
    let rq = RayQueryBvh::upload(&ctx, bvh).expect("upload");
    let tris = world_triangles(&ib);
    for mask in [0xffu8, 1, 2, 6, 0] {
        let opts = TraceOptions {
            mask,
            ..TraceOptions::closest(Traversal::FullStack)
        };
        let got = rq.trace(&rays, &opts).expect("trace");
        let want = trace_rays(
            bvh,
            &rays.iter().map(from_origin).collect::<Vec<_>>(),
            &opts,
        );
        let t = tally(&tris, bvh, &rays, &opts, &got);
        eprintln!("{}", t.report(&format!("mask {mask:#x}"), rays.len()));
        assert!(
            t.differs.is_empty(),
            "mask {mask:#x}: {}",
            t.differs.join("\n")
        );
        let mut same_place = 0;
        for (i, (a, b)) in want.hits.iter().zip(&got.hits).enumerate() {
            if a.prim == b.prim {
                assert_eq!(want.instance_hit(i), got.instance_hit(i), "ray {i}");
                same_place += usize::from(a.is_hit());
            }
        }
        if mask == 0 {
            assert!(got.hits.iter().all(|h| !h.is_hit()), "mask 0 hits nothing");
        } else {
            assert!(same_place > 0, "mask {mask:#x}: no hit to compare");
        }
    }
}

#[test]
fn what_ray_queries_do_not_offer_is_an_error() {
    let Some(ctx) = context("ray-query errors") else {
        return;
    };
    let bvh = support::one_triangle();
    let rq = RayQueryBvh::upload(&ctx, &bvh).expect("upload");
    assert_eq!(rq.backend(), "ray-query");
    let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
    let counted = TraceOptions::closest(Traversal::FullStack).with_counters(true);
    let err = rq.trace(&rays, &counted).expect_err("no counters");
    assert!(err.to_string().contains("counters"), "{err}");
    let f64_test =
        TraceOptions::closest(Traversal::FullStack).with_precision(Precision::WatertightF64);
    assert!(matches!(
        rq.trace(&rays, &f64_test),
        Err(GpuError::Unsupported { .. })
    ));
    let out = rq
        .trace(&rays, &TraceOptions::closest(Traversal::Stackless))
        .expect("any walk name traces: the driver walks");
    assert!(out.hits[0].is_hit(), "{:?}", out.hits[0]);
    assert!(matches!(
        RayQueryBvh::upload(&ctx, &FlatBvh::default()),
        Err(GpuError::EmptyBvh)
    ));
    // A device opened without ray queries refuses the upload, naming the feature.
    let plain = GpuContext::new(AdapterChoice::Auto).expect("device");
    let err = RayQueryBvh::upload(&plain, &bvh).expect_err("no ray queries asked for");
    assert!(err.to_string().contains("EXPERIMENTAL_RAY_QUERY"), "{err}");
}

/// The largest gap between the CPU's barycentrics and the driver's on rays that hit the
/// same primitive: what [`BORDER_STEP`] must stay far above.
fn barycentric_gap(want: &TraceOutput, got: &TraceOutput) -> f32 {
    (want.hits.iter().zip(&got.hits))
        .filter(|(a, b)| a.is_hit() && a.prim == b.prim)
        .map(|(a, b)| (a.u - b.u).abs().max((a.v - b.v).abs()))
        .fold(0.0, f32::max)
}

#[test]
fn masked_scenes_cut_as_the_walks_do_but_at_texel_borders() {
    let Some(ctx) = context("ray-query alpha masks") else {
        return;
    };
    let foliage = bvhtrace_scene::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/foliage.gltf"
    ))
    .expect("scenes/foliage.gltf");
    for (label, scene) in [("edge cases", edge_cases()), ("foliage", foliage)] {
        for flatten in [true, false] {
            let traced = scene
                .tracing_bvh(&BuildOptions::default(), flatten)
                .unwrap_or_else(|e| panic!("{label}: {e}"));
            let label = format!(
                "{label}, {}",
                if flatten { "flattened" } else { "two levels" }
            );
            let bvh = traced.bvh();
            let masks = bvh.masks().expect("masks attached");
            let tris: Vec<Triangle> = (0..traced.triangle_count() as u32)
                .map(|p| traced.triangle(p).expect("a triangle per primitive"))
                .collect();
            let rays = masked_rays(bvh);
            let rq = RayQueryBvh::upload(&ctx, bvh).unwrap_or_else(|e| panic!("{label}: {e}"));
            assert!(rq.has_masks(), "{label}");
            let stats = rq.upload_stats().expect("stats");
            assert_eq!(stats.masks_bytes, masks.device_bytes() as u64, "{label}");
            check(&label, &tris, bvh, &rays, &rq);

            let closest = TraceOptions::closest(Traversal::FullStack);
            let got = rq.trace(&rays, &closest).expect("trace");
            let clamped: Vec<Ray> = rays.iter().map(from_origin).collect();
            let gap = barycentric_gap(&trace_rays(bvh, &clamped, &closest), &got);
            eprintln!("{label}: barycentrics at most {gap:e} apart on the same primitive");
            assert!(gap * 10.0 < BORDER_STEP, "{label}: {gap:e}");

            // The masks cut: the same tree with its masks dropped stops elsewhere.
            let mut opaque = bvh.clone();
            opaque.set_masks(None).expect("dropped");
            let plain = RayQueryBvh::upload(&ctx, &opaque).expect("upload");
            assert!(!plain.has_masks());
            assert_eq!(plain.upload_stats().map(|s| s.masks_bytes), Some(0));
            let whole = plain.trace(&rays, &closest).expect("trace");
            let changed = (got.hits.iter().zip(&whole.hits))
                .filter(|(a, b)| a.prim != b.prim)
                .count();
            eprintln!(
                "{label}: the masks changed {changed} of {} hits",
                rays.len()
            );
            assert!(changed > rays.len() / 50, "{label}: only {changed} cut");

            // A library for this upload composes the masks; one without them is refused.
            assert!(rq.wgsl_library(0).shape().masks);
            rq.bind_group_for(&rq.wgsl_library(0))
                .expect("its own library");
            let unmasked = plain.wgsl_library(0);
            assert!(matches!(
                rq.bind_group_for(&unmasked),
                Err(GpuError::LibraryMismatch { .. })
            ));
        }
    }
}

#[test]
fn an_update_keeps_the_masks_and_refuses_a_tree_that_lost_them() {
    let Some(ctx) = context("ray-query masked updates") else {
        return;
    };
    let traced = edge_cases()
        .tracing_bvh(&BuildOptions::default(), false)
        .expect("two levels");
    let bvh = traced.bvh();
    let rays = masked_rays(bvh);
    let tris: Vec<Triangle> = (0..traced.triangle_count() as u32)
        .map(|p| traced.triangle(p).expect("a triangle per primitive"))
        .collect();
    let mut rq = RayQueryBvh::upload(&ctx, bvh).expect("upload");
    rq.update(bvh).expect("the same tree");
    assert!(rq.has_masks());
    check("edge cases updated", &tris, bvh, &rays, &rq);
    let mut opaque = bvh.clone();
    opaque.set_masks(None).expect("dropped");
    let err = rq.update(&opaque).expect_err("no masks now");
    assert!(
        matches!(err, TraceError::BadBuffer { .. }) && err.to_string().contains("masks"),
        "{err}"
    );
}

/// Triangles over one binding (a context capped at a third of them) are bound in pages,
/// ranges of the one buffer the BLASes read: the answers are the same device's with them
/// in one binding, ray for ray and bit for bit, one mesh and two levels.
#[test]
fn triangles_over_one_binding_answer_as_in_one() {
    let Some(whole) = context("ray queries in pages") else {
        return;
    };
    let one = support::load_scene("builtin:icosphere:4", "icosphere:4").expect("builtin");
    let two = support::load_instanced_scene("builtin:spheres", "spheres").expect("builtin");
    for (name, bvh) in [("icosphere:4", one.bvh), ("spheres", two.bvh)] {
        let third = std::mem::size_of_val(bvh.triangles()) as u64 / 3;
        let options = ContextOptions {
            ray_queries: true,
            max_binding_bytes: Some(third),
            ..ContextOptions::default()
        };
        let split = GpuContext::new_with(AdapterChoice::Auto, &options).expect("the same device");
        let a = RayQueryBvh::upload(&whole, &bvh).expect("upload");
        let b = RayQueryBvh::upload(&split, &bvh).expect("upload in pages");
        let library = b.wgsl_library(0);
        assert!(
            library.source().contains("bvh_triangles_2"),
            "{name}: not split"
        );
        let rays = ray_set(&bvh, 5);
        for query in [Query::Closest, Query::Any] {
            let opts = TraceOptions::new(Traversal::FullStack, query);
            let want = a.trace(&rays, &opts).expect("trace");
            let got = b.trace(&rays, &opts).expect("trace in pages");
            assert!(want.hits.iter().any(|h| h.is_hit()), "{name}: nothing hit");
            // Bit for bit: an invalid ray's NaN distance too.
            let bits = |h: &[bvhtrace_core::Hit]| bytemuck::cast_slice::<_, u32>(h).to_vec();
            let differ = (got.hits.iter().zip(&want.hits))
                .filter(|(a, b)| bits(&[**a]) != bits(&[**b]))
                .count();
            assert_eq!(
                differ,
                0,
                "{name} {query:?}: {differ} of {} rays",
                rays.len()
            );
        }
    }
}

/// With submissions in flight (a GPU's tuning), the ray queries go in chunks on buffers of
/// their own, kept from trace to trace: the hits are those of one chunk at a time, bit for
/// bit, in order, on the first trace and the next.
#[test]
fn submissions_in_flight_answer_as_one_at_a_time() {
    let Some(one) = context("ray queries in flight") else {
        return;
    };
    let tuning = bvhtrace_gpu::DriverTuning {
        in_flight: 2,
        submission_rays: 1000,
        ..*one.tuning()
    };
    let options = ContextOptions {
        ray_queries: true,
        tuning: Some(tuning),
        ..ContextOptions::default()
    };
    let flying = GpuContext::new_with(AdapterChoice::Auto, &options).expect("the same device");
    let bvh = support::load_scene("builtin:icosphere:4", "icosphere:4")
        .expect("builtin")
        .bvh;
    let a = RayQueryBvh::upload(&one, &bvh).expect("upload");
    let b = RayQueryBvh::upload(&flying, &bvh).expect("upload");
    let rays = ray_set(&bvh, 9);
    assert!(rays.len() > 3000, "{} rays: too few chunks", rays.len());
    let bits = |h: &[bvhtrace_core::Hit]| bytemuck::cast_slice::<_, u32>(h).to_vec();
    for query in [Query::Closest, Query::Any, Query::Closest] {
        let opts = TraceOptions::new(Traversal::FullStack, query);
        let want = a.trace(&rays, &opts).expect("trace");
        let got = b.trace(&rays, &opts).expect("trace in flight");
        assert!(want.hits.iter().any(|h| h.is_hit()), "nothing hit");
        assert!(
            bits(&got.hits) == bits(&want.hits),
            "{query:?}: hits differ"
        );
        // Fewer rays than one chunk: one submission, on the kept buffers.
        let few = b.trace(&rays[..10], &opts).expect("trace a few");
        assert!(
            bits(&few.hits) == bits(&want.hits[..10]),
            "{query:?}: a few"
        );
    }
}
