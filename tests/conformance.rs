//! The conformance suite: every parity check runs on every tracer the factory opens
//! (`common::tracers`: the CPU twin, wgpu with the BVH in buffers and in textures, and
//! ash; the next backend is one more line there), ray by ray and bit for bit against the
//! CPU twin's walks (hits, counters, hits traced without counters), and the device
//! tracers against each other (rays finished on the CPU). ash runs with the validation
//! layer on (when installed), and every test ends with no validation error. Without a
//! Vulkan device the device tracers print SKIP and the CPU is still checked.
//!
//! Closest hits also equal the CPU full-stack reference (same primitive, same `t` bits),
//! except where f32 cannot decide between two triangles (see [`f32_departure`]); any-hit
//! queries agree with it on hit/miss. A failing ray is printed in full so it can be
//! replayed. What is particular to one backend's API is in `tests/wgpu_api.rs` and
//! `crates/vk/tests/vk_api.rs`.

use bvhtrace_core::{
    BuildOptions, Counters, FlatBvh, Hit, INVALID_RAY, InstancedBvh, Precision, Query, Ray,
    TraceOutput, Traversal, Triangle, oracle, trace_rays,
};
use bvhtrace_gpu::{TraceOptions, Tracer};
use bvhtrace_vk::DriverTuning;
use glam::Vec3;

mod common;
mod support;
use common::{Devices, name, tracers};
use support::{
    SceneCase, deep_tree, deep_tree_rays, deep_wide_rays, deep_wide_tree, differ, differences,
    load_instanced_scene, load_scene, one_triangle, parity_rays, parity_scenes, ray_set,
};

/// The parity scenes, and the Cornell box at 1e-4 scale.
fn scenes() -> Vec<SceneCase> {
    let mut out = parity_scenes();
    out.extend(load_scene(
        "builtin:cornell#scale=1e-4",
        "builtin:cornell#scale=1e-4",
    ));
    out
}

/// The builtin Cornell box.
fn cornell() -> FlatBvh {
    load_scene("builtin:cornell", "builtin:cornell")
        .expect("builtin scene")
        .bvh
}

/// True for a tracer of our WGSL kernels, which give a ray up under a trip budget or on a
/// wide stack's overflow (the same rays on every such tracer) for the host to finish.
fn wgsl(t: &dyn Tracer) -> bool {
    bvhtrace::Backend::of(t).is_some_and(|b| b.kernels() == bvhtrace::Kernels::Wgsl)
}

/// What [`compare`] found: the differences from the CPU twin, the twin's hits and
/// counters, and each tracer's counted output (in the factory's order).
struct Compared {
    failures: Vec<String>,
    cpu: (Vec<Hit>, Vec<Counters>),
    outs: Vec<TraceOutput>,
}

/// Traces `opts` on every tracer, counted, and on a sample without counters (every
/// [`PLAIN_SAMPLE`]th ray and every [`unusual`] one), and lists how each differs from the CPU twin's hits and counters (`all[0]`,
/// the factory's first tracer); the device tracers finish the same number of rays on the
/// CPU.
fn compare(label: &str, all: &[&dyn Tracer], rays: &[Ray], opts: &TraceOptions) -> Compared {
    compare_with(label, all, rays, opts, true)
}

/// [`compare`], the uncounted sample traced only when `plain`.
fn compare_with(
    label: &str,
    all: &[&dyn Tracer],
    rays: &[Ray],
    opts: &TraceOptions,
    plain: bool,
) -> Compared {
    assert_eq!(all[0].backend(), "cpu", "the CPU twin comes first");
    let outs: Vec<TraceOutput> = all
        .iter()
        .map(|t| t.trace(rays, &opts.with_counters(true)).expect("trace"))
        .collect();
    let cpu = (
        outs[0].hits.clone(),
        outs[0].counters.clone().expect("counters asked for"),
    );
    let picked: Vec<usize> = (0..rays.len())
        .filter(|&i| i % PLAIN_SAMPLE == 0 || unusual(&rays[i]))
        .collect();
    let sample: Vec<Ray> = picked.iter().map(|&i| rays[i]).collect();
    let sample_cpu: (Vec<Hit>, Vec<Counters>) = (
        picked.iter().map(|&i| cpu.0[i]).collect(),
        picked.iter().map(|&i| cpu.1[i]).collect(),
    );
    let mut failures = Vec::new();
    let mut incomplete = None;
    for (t, counted) in all.iter().zip(&outs) {
        let who = format!("{label} on {}", name(*t));
        assert_eq!(counted.hits.len(), rays.len(), "{who}: hit count");
        if wgsl(*t) {
            let n = *incomplete.get_or_insert(counted.incomplete);
            assert_eq!(counted.incomplete, n, "{who}: rays finished on the CPU");
        }
        let counters = counted.counters.as_deref().expect("counters asked for");
        failures.extend(differences(
            &who,
            rays,
            (&counted.hits, counters),
            &counted.hits,
            (&cpu.0, &cpu.1),
        ));
        if !plain {
            continue;
        }
        let plain = t.trace(&sample, opts).expect("trace");
        assert!(plain.counters.is_none(), "{who}: counters not asked for");
        failures.extend(differences(
            &format!("{who}, uncounted sample"),
            &sample,
            (&plain.hits, &sample_cpu.1),
            &plain.hits,
            (&sample_cpu.0, &sample_cpu.1),
        ));
    }
    Compared {
        failures,
        cpu,
        outs,
    }
}

/// [`compare`] traces every this many rays without counters too, and every [`unusual`]
/// one.
const PLAIN_SAMPLE: usize = 8;

/// A ray off the common path: a zero direction component (axis-parallel, in a box face),
/// something not finite, or an interval that is empty, starts behind the origin or ends
/// at `f32::MAX`.
fn unusual(r: &Ray) -> bool {
    let finite = r
        .origin
        .iter()
        .chain(&r.dir)
        .chain([&r.t_min])
        .all(|x| x.is_finite());
    r.dir.contains(&0.0)
        || !finite
        || r.t_min.is_nan()
        || r.t_max.is_nan()
        || r.t_min < 0.0
        || r.t_min >= r.t_max
        || r.t_max == f32::MAX
}

/// The tracers, borrowed.
fn refs<'a>(all: &'a [Box<dyn Tracer + 'a>]) -> Vec<&'a dyn Tracer> {
    all.iter().map(|t| &**t as &dyn Tracer).collect()
}

/// Rays that differ bit for bit between two hit lists; a line naming the first, or none.
fn hit_differences(who: &str, rays: &[Ray], got: &[Hit], cpu: &[Hit]) -> Option<String> {
    let bad = differ(got, cpu);
    bad.first().map(|&i| {
        format!(
            "{who}: {} rays differ; first {i}: ray {:?}, got {:?}, cpu {:?}",
            bad.len(),
            rays[i],
            got[i],
            cpu[i]
        )
    })
}

/// The one documented exception to "a closest hit is the same whatever the traversal":
/// the f32 watertight test is indeterminate for a triangle involved (the ray passes within
/// rounding of one of its edges), or the two answers' `t` are within the f32 `t` error
/// bounds of their triangles. The box test's culling slack (`intersect::BOX_CULL_SLACK`)
/// covers the rounding of the test's `T` and `det`; what remains is the edge functions'
/// own error, which these oracle bounds measure. `tris` is indexed by primitive.
fn f32_departure(tris: &[Triangle], ray: &Ray, a: &Hit, b: &Hit) -> bool {
    let tri = |p: u32| tris.get(p as usize);
    let terr = |p: u32| tri(p).map_or(0.0, |t| oracle::f32_t_error_bound(t, ray));
    [a.prim, b.prim]
        .iter()
        .any(|&p| tri(p).is_some_and(|t| oracle::f32_indeterminate(t, ray)))
        || (f64::from(a.t) - f64::from(b.t)).abs() <= terr(a.prim) + terr(b.prim)
}

fn f(x: f32) -> String {
    format!("{x:e} (0x{:08x})", x.to_bits())
}

/// A ray and two answers in full (bits and decimals), to replay it.
fn describe(i: usize, r: &Ray, what: &str, want: &Hit, got: &Hit) -> String {
    format!(
        "ray {i}: {what}\n  origin = [{}, {}, {}]\n  dir    = [{}, {}, {}]\n  t_min  = {}\n  \
         t_max  = {}\n  reference: prim {:#x} t {} u {} v {}\n  got:       prim {:#x} t {} u {} v {}",
        f(r.origin[0]),
        f(r.origin[1]),
        f(r.origin[2]),
        f(r.dir[0]),
        f(r.dir[1]),
        f(r.dir[2]),
        f(r.t_min),
        f(r.t_max),
        want.prim,
        f(want.t),
        f(want.u),
        f(want.v),
        got.prim,
        f(got.t),
        f(got.u),
        f(got.v),
    )
}

/// Counts `hits` departing from the full-stack `reference` (closest: another primitive or
/// `t`; any: another hit/miss or invalid verdict): the documented f32 departures (where
/// the CPU twin, `twin`, departs too) and the others, printing the first few.
#[allow(clippy::too_many_arguments)]
fn reference_mismatches(
    label: &str,
    bvh: &FlatBvh,
    tris: &[Triangle],
    rays: &[Ray],
    query: Query,
    hits: &[Hit],
    twin: &[Hit],
    reference: &[Hit],
) -> (usize, usize) {
    let differs = |g: &Hit, r: &Hit| match query {
        Query::Closest => g.prim != r.prim || g.t.to_bits() != r.t.to_bits(),
        Query::Any => {
            g.is_hit() != r.is_hit() || (g.prim == INVALID_RAY) != (r.prim == INVALID_RAY)
        }
    };
    let (mut bad, mut exceptions) = (0, 0);
    for (i, (g, r)) in hits.iter().zip(reference).enumerate() {
        if !differs(g, r) {
            continue;
        }
        let twin_differs = differs(&twin[i], r);
        if twin_differs && query == Query::Closest && f32_departure(tris, &rays[i], g, r) {
            exceptions += 1;
        } else {
            bad += 1;
        }
        if exceptions + bad <= 3 {
            let bf = bvhtrace_core::brute_force(bvh, &rays[i], Precision::WatertightF32);
            eprintln!(
                "{label}: differs from the full-stack reference{} (brute force: prim {:#x} t {})\n{}",
                if twin_differs {
                    ", as the CPU twin does"
                } else {
                    ""
                },
                bf.prim,
                f(bf.t),
                describe(i, &rays[i], "full-stack reference, got", r, g)
            );
        }
    }
    (bad, exceptions)
}

/// Every scene, every walk (the short stacks at k = 1 and 2 to force overflows), both
/// queries, the large ray set (rays in the faces of node boxes and of wide child boxes
/// too): every tracer equals the CPU twin, finishes no ray on the CPU, and agrees with the
/// full-stack reference but for the documented f32 departures.
#[test]
fn every_tracer_equals_the_cpu_bit_for_bit() {
    let devices = Devices::open("conformance");
    let traversals = [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(6),
        Traversal::ShortStack(4),
        Traversal::ShortStack(2),
        Traversal::ShortStack(1),
        Traversal::Wide,
    ];
    let mut failures = Vec::new();
    let mut total_exceptions = 0;
    // Wide configurations each tracer ran, by name.
    let mut wide_checked = std::collections::BTreeMap::<String, usize>::new();
    // The built-in scenes always; the shared meshes when `../shared/scenes` is there.
    let scenes = scenes();
    assert!(scenes.len() >= 3, "only {} scenes loaded", scenes.len());
    for (
        s,
        SceneCase {
            name: scene,
            bvh,
            tris,
        },
    ) in scenes.into_iter().enumerate()
    {
        // With its wide layout: the ash upload takes it, the CPU twin walks it.
        let bvh = bvh.with_wide();
        let rays = ray_set(&bvh, 0x5eed + s as u64);
        let all = tracers(devices, &bvh);
        eprintln!(
            "{scene}: {} triangles, {} nodes, depth {}, {} rays, {} tracers",
            bvh.triangles().len(),
            bvh.nodes().len(),
            bvh.depth(),
            rays.len(),
            all.len()
        );
        let reference = [Query::Closest, Query::Any]
            .map(|q| trace_rays(&bvh, &rays, &TraceOptions::new(Traversal::FullStack, q)).hits);
        for traversal in traversals {
            for query in [Query::Closest, Query::Any] {
                let label = format!("{scene} {traversal} {query:?}");
                let opts = TraceOptions::new(traversal, query);
                // The uncounted kernels on the walks that differ in their bookkeeping (the
                // short stacks' ring is one kernel whatever its size up to 8).
                let plain = !matches!(traversal, Traversal::ShortStack(k) if k != 4);
                let c = compare_with(&label, &refs(&all), &rays, &opts, plain);
                failures.extend(c.failures);
                for (t, out) in all.iter().zip(&c.outs) {
                    let who = format!("{label} on {}", name(&**t));
                    // Parity must be the kernel's own: no ray finished on the CPU twin.
                    assert_eq!(out.incomplete, 0, "{who}: rays over the trip budget");
                    if traversal == Traversal::Wide {
                        *wide_checked.entry(name(&**t)).or_default() += 1;
                    }
                    let reference = &reference[usize::from(query == Query::Any)];
                    let (bad, exceptions) = reference_mismatches(
                        &who, &bvh, &tris, &rays, query, &out.hits, &c.cpu.0, reference,
                    );
                    total_exceptions += exceptions;
                    if bad > 0 {
                        failures.push(format!(
                            "{who}: {bad} mismatches with the full-stack reference \
                             (+{exceptions} documented)"
                        ));
                    }
                }
            }
        }
    }
    eprintln!(
        "documented f32 departures from the full-stack reference (the CPU twin's too): \
         {total_exceptions}"
    );
    // Every scene (at least the builtins, one and two levels) ran the wide walk, both
    // queries, on every tracer.
    assert!(
        wide_checked.values().all(|&n| n >= 4 * 2),
        "{wide_checked:?} wide configurations"
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    devices.check_validation();
}

/// The other triangle tests (Möller–Trumbore f32, watertight f64 where the device has it)
/// compose into the same kernels, the wide one too: every tracer that supports them
/// equals the CPU twin, for one mesh and two levels (whose wide nodes span several rows
/// of a node texture).
#[test]
fn precisions_equal_the_cpu_on_every_tracer() {
    let devices = Devices::open("precisions");
    let mut failures = Vec::new();
    let mut checked = std::collections::BTreeMap::<String, usize>::new();
    let scenes = [
        load_scene("builtin:degenerate", "builtin:degenerate"),
        load_scene("builtin:cornell", "builtin:cornell"),
        load_instanced_scene("builtin:spheres", "builtin:spheres"),
    ];
    for SceneCase {
        name: scene, bvh, ..
    } in scenes.into_iter().flatten()
    {
        let bvh = bvh.with_wide();
        if bvh.is_instanced() {
            let w = bvh.wide().map(|w| &**w).expect("wide layout");
            let texels = (std::mem::size_of::<bvhtrace_core::WideNode>() / 16) as u64;
            let row = u64::from(bvhtrace_gpu::engine::storage::TEXEL_ROW);
            assert!(
                w.nodes.len() as u64 * texels > row,
                "{scene}: the wide nodes fit one texture row"
            );
        }
        // The parity rays, and a sample of every kind of ray of the large set.
        let mut rays = parity_rays(&bvh);
        rays.extend(ray_set(&bvh, 0x9ec).into_iter().step_by(8));
        let all = tracers(devices, &bvh);
        for precision in [Precision::MollerTrumboreF32, Precision::WatertightF64] {
            for traversal in [
                Traversal::FullStack,
                Traversal::ShortStack(4),
                Traversal::Wide,
            ] {
                for query in [Query::Closest, Query::Any] {
                    let opts = TraceOptions::new(traversal, query).with_precision(precision);
                    let (able, unable): (Vec<_>, Vec<_>) =
                        all.iter().partition(|t| t.supports(&opts).is_ok());
                    for t in unable {
                        eprintln!(
                            "SKIP {precision:?} on {}: {:?}",
                            name(&**t),
                            t.supports(&opts)
                        );
                    }
                    let able: Vec<&dyn Tracer> = able.into_iter().map(|t| &**t).collect();
                    let label = format!("{scene} {traversal} {query:?} {precision:?}");
                    let c = compare(&label, &able, &rays, &opts);
                    failures.extend(c.failures);
                    for (t, out) in able.iter().zip(&c.outs) {
                        let who = format!("{label} on {}", name(*t));
                        assert_eq!(out.incomplete, 0, "{who}");
                        assert!(out.hits.iter().any(|h| h.is_hit()), "{who}: nothing hit");
                        if traversal == Traversal::Wide {
                            *checked.entry(name(*t)).or_default() += 1;
                        }
                    }
                }
            }
        }
    }
    // Möller–Trumbore at least, both queries, on each scene, on each tracer.
    assert!(
        checked.len() == tracers(devices, &one_triangle()).len()
            && checked.values().all(|&n| n >= 3 * 2),
        "{checked:?} wide configurations"
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    devices.check_validation();
}

/// A tree deeper than the full stack's 64 entries (triangles at exponentially spaced
/// positions, midpoint splits): the stackless and short-stack walks equal the CPU twin's
/// ray by ray, hits and counters, and closest hits equal brute force. Rays through every
/// box that miss every triangle overflow every ring, so the short stacks follow escape
/// links from deep in the tree. k <= 8: the ring in registers, its empty entries marked;
/// each k puts the last entry (the full test) and the entry past it (emptied after a push)
/// at its own place in the two registers: 1, 2 in the first; 4 ends it, 7 ends one short
/// of the second, 8 fills both. k = 12: the ring in workgroup memory, counted.
#[test]
fn deep_trees_equal_the_cpu() {
    let devices = Devices::open("deep trees");
    let bvh = deep_tree();
    assert!(bvh.depth() > 64, "depth {}", bvh.depth());
    let rays = deep_tree_rays(120);
    let all = tracers(devices, &bvh);
    let mut failures = Vec::new();
    for traversal in [
        Traversal::Stackless,
        Traversal::ShortStack(1),
        Traversal::ShortStack(2),
        Traversal::ShortStack(4),
        Traversal::ShortStack(6),
        Traversal::ShortStack(7),
        Traversal::ShortStack(8),
        Traversal::ShortStack(12),
    ] {
        for query in [Query::Closest, Query::Any] {
            let label = format!("deep {traversal} {query:?}");
            let c = compare(
                &label,
                &refs(&all),
                &rays,
                &TraceOptions::new(traversal, query),
            );
            failures.extend(c.failures);
            for (t, out) in all.iter().zip(&c.outs) {
                let who = format!("{label} on {}", name(&**t));
                assert_eq!(out.incomplete, 0, "{who}: rays over the trip budget");
                if query == Query::Closest {
                    let bad = rays
                        .iter()
                        .zip(&out.hits)
                        .filter(|(r, h)| {
                            bvhtrace_core::brute_force(&bvh, r, Precision::WatertightF32) != **h
                        })
                        .count();
                    if bad > 0 {
                        failures.push(format!("{who}: {bad} brute-force mismatches"));
                    }
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    devices.check_validation();
}

/// A wide tree deeper than the wide walk's stack: the rays whose stack of node groups
/// would overflow come back incomplete from the device tracers and are finished on the
/// CPU with the same walk (with the device's tuning, a trip budget on a CPU driver, and
/// with the GPU tuning too: no trip budget, the host copy kept for the depth alone); hits
/// and counters equal the CPU twin's and, for closest hits, brute force.
#[test]
fn deep_wide_trees_finish_on_the_cpu() {
    let bvh = deep_wide_tree();
    let w = bvh
        .wide()
        .map(|w| &**w)
        .expect("built with its wide layout");
    assert!(
        bvhtrace_gpu::engine::walks::may_overflow(Traversal::Wide, w.depth),
        "wide depth {} fits the stack of {} groups",
        w.depth,
        bvhtrace_gpu::engine::walks::WIDE_STACK_GROUPS
    );
    let rays = deep_wide_rays();
    for tuning in [None, Some(DriverTuning::GPU)] {
        let devices = Devices::with_tuning("deep wide trees", tuning);
        let all = tracers(&devices, &bvh);
        for query in [Query::Closest, Query::Any] {
            let label = format!("deep wide {query:?} {tuning:?}");
            let opts = TraceOptions::new(Traversal::Wide, query);
            let c = compare(&label, &refs(&all), &rays, &opts);
            assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
            for (t, out) in all.iter().zip(&c.outs) {
                let who = format!("{label} on {}", name(&**t));
                if wgsl(&**t) {
                    assert!(out.incomplete > 0, "{who}: no ray overflowed the stack");
                }
                assert!(
                    out.hits.iter().all(|h| h.prim != bvhtrace_core::INCOMPLETE),
                    "{who}: a ray left incomplete"
                );
                if query == Query::Closest {
                    let bad = rays
                        .iter()
                        .zip(&out.hits)
                        .filter(|(r, h)| {
                            bvhtrace_core::brute_force(&bvh, r, Precision::WatertightF32) != **h
                        })
                        .count();
                    assert_eq!(bad, 0, "{who}: brute-force mismatches");
                }
                eprintln!(
                    "{who}: wide depth {}, {} of {} rays finished on the CPU",
                    w.depth,
                    out.incomplete,
                    rays.len()
                );
            }
        }
        devices.check_validation();
    }
}

/// A driver tuning with a tiny trip budget leaves rays incomplete on the device tracers,
/// and they are finished on the CPU with the same answers and counters; the GPU tuning
/// (no budget) finishes every ray on the device.
#[test]
fn tight_trip_budgets_finish_on_the_cpu() {
    let bvh = cornell();
    let rays = parity_rays(&bvh);
    let tight = DriverTuning {
        trip_limit: 4,
        ..DriverTuning::cpu_driver(2)
    };
    for tuning in [DriverTuning::GPU, tight] {
        let devices = Devices::with_tuning("trip budgets", Some(tuning));
        let all = tracers(&devices, &bvh);
        for traversal in [Traversal::FullStack, Traversal::ShortStack(4)] {
            let label = format!("cornell {traversal} {tuning:?}");
            let opts = TraceOptions::closest(traversal);
            let c = compare(&label, &refs(&all), &rays, &opts);
            assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
            for (t, out) in all
                .iter()
                .zip(&c.outs)
                .filter(|(t, _)| t.backend() != "cpu")
            {
                let who = format!("{label} on {}", name(&**t));
                if tuning.finishes_on_cpu() && wgsl(&**t) {
                    assert!(out.incomplete > 0, "{who}: a 4-trip budget finishes no ray");
                } else {
                    assert_eq!(out.incomplete, 0, "{who}");
                }
            }
        }
        devices.check_validation();
    }
}

/// Rays that run exactly in the plane of a face of the root box, parallel to it, entering
/// the box from outside: only the box test's parallel path (`PARALLEL_RAYS`, kept because
/// these rays have zero direction components) sees that they pass through the box. Every
/// tracer's hits and counters equal the CPU twin's.
#[test]
fn rays_along_box_faces_equal_the_cpu() {
    let devices = Devices::open("box faces");
    let bvh = cornell();
    let b = bvh.bounds();
    let (lo, hi) = (b.min, b.max);
    let mid = (lo + hi) * 0.5;
    let mut rays = Vec::new();
    for plane_axis in 0..3 {
        for on in [lo[plane_axis], hi[plane_axis]] {
            for travel in (0..3).filter(|&a| a != plane_axis) {
                for s in [0.25f32, 0.5, 0.75] {
                    for dir_sign in [1.0f32, -1.0] {
                        let mut o = mid;
                        let third = 3 - plane_axis - travel;
                        o[third] = lo[third] + s * (hi[third] - lo[third]);
                        o[plane_axis] = on;
                        // Outside the box along `travel`, heading in.
                        o[travel] = if dir_sign > 0.0 {
                            lo[travel] - 1.0
                        } else {
                            hi[travel] + 1.0
                        };
                        let mut d = Vec3::ZERO;
                        d[travel] = dir_sign;
                        rays.push(Ray::new(o, d));
                    }
                }
            }
        }
    }
    let all = tracers(devices, &bvh);
    for traversal in [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(6),
    ] {
        let label = format!("face rays {traversal}");
        let c = compare(
            &label,
            &refs(&all),
            &rays,
            &TraceOptions::closest(traversal),
        );
        assert!(
            c.cpu.1.iter().any(|c| c.nodes > 1),
            "{label}: no face ray goes into the box"
        );
        assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
    }
    devices.check_validation();
}

/// The wide nodes whose five texels straddle two rows of a node texture (node `i` with
/// `5i % TEXEL_ROW > TEXEL_ROW - 5`): rays from inside each of their children, which every
/// closest-hit walk enters (the box's entry distance is 0), equal the CPU twin's on every
/// tracer, hits and counters.
#[test]
fn wide_nodes_across_texture_rows_equal_the_cpu() {
    let devices = Devices::open("wide nodes across rows");
    let bvh = load_scene("builtin:icosphere:5", "builtin:icosphere:5")
        .expect("builtin scene")
        .bvh
        .with_wide();
    let w = bvh.wide().map(|w| &**w).expect("wide layout");
    let row = u64::from(bvhtrace_gpu::engine::storage::TEXEL_ROW);
    let texels = (std::mem::size_of::<bvhtrace_core::WideNode>() / 16) as u64;
    let straddling: Vec<usize> = (0..w.nodes.len())
        .filter(|&i| texels * i as u64 % row > row - texels)
        .collect();
    assert!(straddling.len() >= 2, "{} wide nodes", w.nodes.len());
    let mut dirs: Vec<Vec3> = [Vec3::X, Vec3::Y, Vec3::Z]
        .iter()
        .flat_map(|&d| [d, -d])
        .collect();
    for k in 0..8 {
        let s = |b: usize| if k >> b & 1 == 0 { 1.0 } else { -1.0 };
        dirs.push(Vec3::new(s(0), s(1), s(2) * 0.7));
    }
    let mut rays = Vec::new();
    for &i in &straddling {
        let n = &w.nodes[i];
        for s in (0..8).filter(|&s| n.is_used(s)) {
            let (lo, hi) = n.child_box(s);
            rays.extend(dirs.iter().map(|&d| Ray::new((lo + hi) * 0.5, d)));
        }
    }
    let all = tracers(devices, &bvh);
    for query in [Query::Closest, Query::Any] {
        let label = format!("straddling wide nodes {query:?}");
        let opts = TraceOptions::new(Traversal::Wide, query);
        let c = compare(&label, &refs(&all), &rays, &opts);
        assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
        for (t, out) in all.iter().zip(&c.outs) {
            let who = format!("{label} on {}", name(&**t));
            assert_eq!(out.incomplete, 0, "{who}");
            assert!(out.hits.iter().any(|h| h.is_hit()), "{who}: nothing hit");
        }
    }
    devices.check_validation();
}

/// Batches smaller than a ray-texture row (4096 rays), of whole rows and of whole rows
/// plus a part come back ray for ray as the CPU twin's on every tracer.
#[test]
fn batches_of_any_size_equal_the_cpu() {
    let devices = Devices::open("batch sizes");
    let bvh = cornell();
    let set = ray_set(&bvh, 7);
    let all = tracers(devices, &bvh);
    for n in [1, 63, 1536, 4096, 4097, 3 * 4096 + 5] {
        let rays = &set[set.len() - n..];
        let label = format!("{n} rays");
        let opts = TraceOptions::closest(Traversal::FullStack);
        let c = compare(&label, &refs(&all), rays, &opts);
        // An invalid ray's answer counts: the one-ray batch is one.
        assert!(
            c.cpu.0.iter().any(|h| h.prim != bvhtrace_core::MISS),
            "{label}: nothing answered"
        );
        assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
    }
    devices.check_validation();
}

/// With submissions in flight (a GPU's tuning: the next batch's rays written and walked
/// while the last one's hits are read back), a trace goes in several submissions on
/// scratches taken in turn: every tracer's hits and counters equal the CPU twin's, in
/// order, whatever the batch size.
#[test]
fn submissions_in_flight_equal_the_cpu() {
    let devices = Devices::open("submissions in flight");
    let flying = devices.retuned(|t| DriverTuning {
        in_flight: 2,
        submission_rays: 1000,
        ..t
    });
    let bvh = cornell();
    let set = ray_set(&bvh, 13);
    let all = tracers(&flying, &bvh);
    for n in [999, 2001, 4097] {
        let rays = &set[set.len() - n..];
        let label = format!("{n} rays, two submissions in flight");
        for query in [Query::Closest, Query::Any] {
            let opts = TraceOptions::new(Traversal::FullStack, query);
            let c = compare(&label, &refs(&all), rays, &opts);
            assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
        }
    }
    flying.check_validation();
}

/// Whatever number of threads the workgroups are dealt out to (`DISPATCH_THREADS`), every
/// ray of a batch is traced once, by its own invocation: every tracer's hits equal the
/// CPU twin's for batch sizes that leave partial workgroups and a remainder of workgroups.
#[test]
fn interleaved_workgroups_trace_every_ray() {
    let devices = Devices::open("interleaved workgroups");
    let bvh = cornell();
    let set = ray_set(&bvh, 11);
    for threads in [1, 2, 3, 5] {
        let dealt = devices.retuned(|t| DriverTuning {
            dispatch_threads: threads,
            ..t
        });
        for tuning in dealt.devices.iter().filter_map(|d| d.tuning()) {
            assert_eq!(tuning.dispatch_threads, threads);
        }
        let all = tracers(&dealt, &bvh);
        for n in [63, 64 * 7 + 5, 4097] {
            let t = threads as usize;
            let rays = &set[set.len() - n - t..set.len() - t];
            let label = format!("{threads} threads, {n} rays");
            let opts = TraceOptions::closest(Traversal::FullStack);
            let c = compare(&label, &refs(&all), rays, &opts);
            assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
        }
        dealt.check_validation();
    }
}

/// A batch larger than one dispatch (more rays than `MAX_RAYS_PER_DISPATCH` and than one
/// storage binding holds; the first chunk on a 2D grid where 65,536 workgroups of 64
/// exceed the 65,535 per dimension) is split as `plan_dispatches` says; every ray lands in
/// its slot with the CPU twin's answer.
#[test]
fn batches_larger_than_a_dispatch_are_split() {
    use bvhtrace_gpu::engine::plan::{MAX_RAYS_PER_DISPATCH, plan_dispatches, rays_per_dispatch};
    let devices = Devices::open("split batches");
    let bvh = one_triangle();
    let limits: Vec<_> = devices.devices.iter().filter_map(|d| d.limits()).collect();
    let n = limits
        .iter()
        .map(|l| rays_per_dispatch(l) + 1000)
        .chain([MAX_RAYS_PER_DISPATCH + 4099])
        .max()
        .expect("a size") as usize;
    for l in &limits {
        let plan = plan_dispatches(n as u64, l);
        assert!(plan.len() >= 2, "{plan:?}");
    }
    // Ray i starts at distance 1 + (i % 1000) / 1000 from the triangle; every fifth misses.
    let rays: Vec<Ray> = (0..n)
        .map(|i| {
            let x = if i % 5 == 4 { 3.0 } else { 0.0 };
            Ray::new(
                Vec3::new(x, 0.0, 1.0 + (i % 1000) as f32 / 1000.0),
                Vec3::NEG_Z,
            )
        })
        .collect();
    let opts = TraceOptions::closest(Traversal::Stackless);
    let cpu = trace_rays(&bvh, &rays, &opts).hits;
    for (i, h) in cpu.iter().enumerate() {
        if i % 5 == 4 {
            assert_eq!(h.prim, u32::MAX, "ray {i}");
        } else {
            let t = 1.0 + (i % 1000) as f32 / 1000.0;
            assert_eq!((h.prim, h.t), (0, t), "ray {i}");
        }
    }
    for t in tracers(devices, &bvh) {
        let out = t.trace(&rays, &opts).expect("trace");
        if let Some(bad) = hit_differences(
            &format!("{n} rays on {}", name(&*t)),
            &rays,
            &out.hits,
            &cpu,
        ) {
            panic!("{bad}");
        }
        eprintln!(
            "{n} rays on {}: {:.1} ms device, {:.1} ms wall",
            name(&*t),
            out.gpu_ms.unwrap_or(f64::NAN),
            out.wall_ms
        );
    }
    devices.check_validation();
}

/// Every tracer of `all` traces `rays` as the CPU twin of `bvh` does, bit for bit, every
/// walk (the wide one on `bvh`'s own wide layout) and query.
fn check_updated(all: &[Box<dyn Tracer + '_>], bvh: &FlatBvh, rays: &[Ray], what: &str) {
    let bvh = &bvh.clone().with_wide();
    let mut failures = Vec::new();
    for traversal in [
        Traversal::Stackless,
        Traversal::ShortStack(4),
        Traversal::FullStack,
        Traversal::Wide,
    ] {
        for query in [Query::Closest, Query::Any] {
            let opts = TraceOptions::new(traversal, query);
            let cpu = trace_rays(bvh, rays, &opts).hits;
            for t in all {
                let got = t.trace(rays, &opts).expect("trace").hits;
                let who = format!("{what} {traversal} {query:?} on {}", name(&**t));
                failures.extend(hit_differences(&who, rays, &got, &cpu));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A two-level tracer updated in place (`Tracer::update`) after the instances moved (the
/// top level rebuilt: only it is written) and after meshes' vertices moved (refitted, one
/// flattened so that the wide collapse comes out with another number of nodes and the
/// update makes new wide arrays) traces as the CPU twin of the changed BVH does, bit for
/// bit, every walk (the wide one on the layout collapsed again by the update); it then
/// holds as many bytes as a fresh upload of the changed tree; another shape is refused.
#[test]
fn two_level_updates_in_place_equal_the_cpu() {
    let devices = Devices::open("two-level updates");
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    let mut ib = scene
        .instanced_bvh(&BuildOptions::default())
        .expect("two levels");
    let first = ib.bvh().clone().with_wide();
    // Every other ray of the large set: every kind of ray, on each of the four trees.
    let rays: Vec<Ray> = ray_set(&first, 0x70b).into_iter().step_by(2).collect();
    let mut all = tracers(devices, &first);
    check_updated(&all, ib.bvh(), &rays, "as uploaded");
    let before = trace_rays(ib.bvh(), &rays, &TraceOptions::default()).hits;
    ib.set_transforms(&support::moved_transforms(&ib))
        .expect("new transforms");
    let updated = ib.bvh().clone().with_wide();
    for t in &mut all {
        t.update(&updated).expect("top-level update");
    }
    check_updated(&all, ib.bvh(), &rays, "after new transforms");
    let after = trace_rays(ib.bvh(), &rays, &TraceOptions::default()).hits;
    assert_ne!(before, after, "moving the instances changed no hit");

    ib.refit_mesh(0, &support::swollen_mesh(&ib, 0))
        .expect("refit");
    let updated = ib.bvh().clone().with_wide();
    for t in &mut all {
        t.update(&updated).expect("update after refit");
    }
    check_updated(&all, ib.bvh(), &rays, "after a refit");

    // A mesh flattened to a twentieth of its height: the boxes' areas change enough for
    // the wide collapse to come out with another number of nodes.
    let old_wide_nodes = bvhtrace_core::WideBvh::collapse(ib.bvh()).nodes.len();
    let mut tris: Vec<_> = ib.mesh_bvh(1).triangles().to_vec();
    tris.sort_by_key(|t| t.prim);
    let flat: Vec<Triangle> = tris
        .iter()
        .map(|t| t.corners().map(|p| p * Vec3::new(1.0, 0.05, 1.0)))
        .collect();
    ib.refit_mesh(1, &flat).expect("refit");
    let updated = ib.bvh().clone().with_wide();
    for t in &mut all {
        t.update(&updated).expect("update after flattening");
    }
    let wide = bvhtrace_core::WideBvh::collapse(ib.bvh());
    assert_ne!(
        wide.nodes.len(),
        old_wide_nodes,
        "the wide layout kept its size"
    );
    // What a fresh upload of the changed tree holds (textures: whole rows).
    let changed = ib.bvh().clone().with_wide();
    let fresh = tracers(devices, &changed);
    for (t, f) in all.iter().zip(&fresh) {
        assert_eq!(name(&**t), name(&**f));
        assert_eq!(
            t.upload_stats().map(|s| (s.nodes_bytes, s.total_bytes())),
            f.upload_stats().map(|s| (s.nodes_bytes, s.total_bytes())),
            "{}: bytes after the update",
            name(&**t)
        );
    }
    check_updated(&all, ib.bvh(), &rays, "after flattening");

    let other = one_triangle();
    for t in &mut all {
        let who = name(&**t);
        assert!(
            matches!(
                t.update(&other),
                Err(bvhtrace_gpu::TraceError::BadBuffer { .. })
            ),
            "{who}: an update of another shape"
        );
    }
    devices.check_validation();
}

/// Every hit of a two-level scene carries its instance: `TraceOutput::instance_hit` gives
/// the instance, user id and mesh primitive `InstancedBvh::locate` gives, on every tracer
/// and walk; a one-mesh scene carries no instance table.
#[test]
fn every_tracer_locates_the_instance_of_a_hit() {
    let devices = Devices::open("instance hits");
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    let ib: InstancedBvh = scene
        .instanced_bvh(&BuildOptions::default())
        .expect("two levels");
    let bvh = ib.bvh().clone().with_wide();
    let rays = parity_rays(&bvh);
    for t in tracers(devices, &bvh) {
        for traversal in [Traversal::FullStack, Traversal::Stackless, Traversal::Wide] {
            let who = format!("{traversal} on {}", name(&*t));
            let out = t
                .trace(&rays, &TraceOptions::closest(traversal))
                .expect("trace");
            let mut located = 0;
            for (i, hit) in out.hits.iter().enumerate() {
                let Some((instance, prim)) = ib.locate(hit.prim) else {
                    assert_eq!(out.instance_hit(i), None, "{who}: ray {i} missed");
                    continue;
                };
                let got = out
                    .instance_hit(i)
                    .unwrap_or_else(|| panic!("{who}: hit {i} has no instance"));
                let user_id = ib.instances()[instance as usize].user_id;
                assert_eq!(
                    (got.instance, got.user_id, got.prim),
                    (instance, user_id, prim),
                    "{who}: ray {i}"
                );
                located += 1;
            }
            assert!(located > 100, "{who}: {located} hits located");
        }
    }
    let one = cornell();
    for t in tracers(devices, &one) {
        let out = t.trace(&rays, &TraceOptions::default()).expect("trace");
        assert!(
            out.instances.is_none(),
            "{}: one mesh has no instance table",
            name(&*t)
        );
    }
    devices.check_validation();
}

/// A tree larger than one storage binding (devices opened with `max_binding_bytes` below
/// its arrays) is split into pages, one binding each (`bvhtrace::engine::pages`): every
/// walk, one mesh and two levels, in buffers on every device equals the CPU twin bit for
/// bit, and the kernels that ran were the split ones. A device with WebGPU's 8 storage
/// buffers per stage (the mock) refuses the upload when its walks would bind more, naming
/// the limit.
#[test]
fn trees_over_one_binding_trace_in_pages_equal_to_the_cpu() {
    use bvhtrace::{AdapterChoice, Backend, BvhStorage, Device, OpenOptions, TraceError};
    let one = load_scene("builtin:icosphere:4", "icosphere:4").expect("builtin scene");
    let two = load_instanced_scene("builtin:spheres", "spheres").expect("builtin scene");
    for (scene, bvh) in [("icosphere:4", one.bvh), ("spheres", two.bvh)] {
        // Two or three pages of each array: few, as a split kernel compiles several times
        // slower than a whole one on lavapipe, the more so the more pages.
        let smaller =
            std::mem::size_of_val(bvh.nodes()).min(std::mem::size_of_val(bvh.triangles()));
        let binding = (smaller as u64).next_power_of_two() / 2;
        let mut all: Vec<Box<dyn Tracer + '_>> = vec![Box::new(bvhtrace::CpuTracer::new(&bvh))];
        for backend in common::BACKENDS {
            let device = Device::new(&OpenOptions {
                adapter: AdapterChoice::Auto,
                validation: true,
                max_binding_bytes: Some(binding),
                ..OpenOptions::new(backend)
            });
            let device = match device {
                Ok(d) => d,
                Err(e @ TraceError::NoAdapter { .. }) => {
                    eprintln!("SKIP pages on {backend}: {e}");
                    continue;
                }
                Err(e) => panic!("pages: cannot open {backend}: {e}"),
            };
            let opts = OpenOptions {
                traversals: Traversal::ALL.to_vec(),
                storage: Some(BvhStorage::Buffers),
                ..OpenOptions::default()
            };
            match device.open_owned(&bvh, &opts) {
                Ok(opened) => all.push(opened.tracer),
                Err(TraceError::LimitTooLow { limit, needs, .. }) if backend == Backend::Mock => {
                    assert_eq!(limit, "max_storage_buffers_per_shader_stage", "{scene}");
                    assert!(needs > 8, "{scene}: {needs}");
                }
                Err(e) => panic!("{scene} on {backend}: {e}"),
            }
        }
        let rays = ray_set(&bvh, 11);
        // Every walk once, each query, on both scenes; the hits-only kernels on one.
        let cases: &[(Traversal, Query)] = match scene {
            "icosphere:4" => &[
                (Traversal::FullStack, Query::Closest),
                (Traversal::Stackless, Query::Any),
                (Traversal::ShortStack(4), Query::Closest),
                (Traversal::Wide, Query::Closest),
            ],
            _ => &[
                (Traversal::Stackless, Query::Closest),
                (Traversal::FullStack, Query::Any),
            ],
        };
        for (i, &(t, query)) in cases.iter().enumerate() {
            let label = format!("{scene} in pages, {t:?} {query:?}");
            let on: Vec<&dyn Tracer> = all.iter().map(|x| &**x).collect();
            let opts = TraceOptions::new(t, query);
            let c = compare_with(&label, &on, &rays, &opts, i == 0);
            assert!(c.failures.is_empty(), "{}", c.failures.join("\n"));
            assert!(c.cpu.0.iter().any(|h| h.is_hit()), "{label}: nothing hit");
        }
        for t in &all[1..] {
            let used = t.kernels_used();
            assert!(!used.is_empty(), "{scene} on {}", name(&**t));
            for k in used {
                assert!(!k.pages.is_one(), "{scene} on {}: {k:?}", name(&**t));
            }
        }
    }
}

/// Each device opens a tree with its tuning's walk when none is asked for
/// (`DriverTuning::walk`: the full stack with a GPU's tuning, the stackless walk with a CPU
/// driver's), and its tracer says so; a tree deeper than the full stack's stack takes the
/// stackless walk instead, and the front door says why.
#[test]
fn each_device_takes_its_tunings_walk() {
    use bvhtrace::OpenOptions;
    let (box_, deep) = (cornell(), deep_tree());
    for tuning in [DriverTuning::GPU, DriverTuning::cpu_driver(2)] {
        let devices = Devices::with_tuning("default walks", Some(tuning));
        for d in &devices.devices {
            let want = tuning.walk;
            let who = format!("{} with {tuning:?}", d.backend());
            let opened = d.open(&box_, &OpenOptions::default()).expect("open");
            assert_eq!(opened.traversal, want, "{who}");
            assert_eq!(opened.tracer.default_traversal(), want, "{who}");
            let opened = d.open(&deep, &OpenOptions::default()).expect("open deep");
            assert_eq!(opened.traversal, Traversal::Stackless, "{who}: deep");
            if want == Traversal::FullStack {
                let why = opened.fallback.as_deref().unwrap_or_default();
                assert!(why.contains("full-stack"), "{who}: {why:?}");
            }
        }
        devices.check_validation();
    }
    assert_eq!(DriverTuning::GPU.walk, Traversal::FullStack);
}
