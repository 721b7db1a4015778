//! The conformance suite: every parity check runs on every tracer the factory opens
//! (`common::tracers`: the CPU twin, wgpu and ash; the next backend is one more line
//! there), ray by ray and bit for bit against the CPU twin's walks, and the device
//! tracers against each other (rays finished on the CPU). ash runs with the validation
//! layer on (when installed), and every test ends with no validation error. Without a
//! Vulkan device the device tracers print SKIP and the CPU is still checked.

use bvhtrace_core::{InstancedBvh, Precision, Query, Traversal};
use bvhtrace_gpu::{TraceOptions, Tracer};
use bvhtrace_vk::DriverTuning;

mod common;
mod support;
use common::{Devices, tracers};
use support::{
    SceneCase, cpu_counted, deep_wide_rays, deep_wide_tree, differences, load_scene, parity_rays,
    parity_scenes,
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

/// Traces `opts` on every tracer, counted and not, and lists how each differs from the CPU
/// twin's hits and counters; the device tracers finish the same number of rays on the CPU.
fn compare(
    label: &str,
    all: &[&dyn Tracer],
    bvh: &bvhtrace_core::FlatBvh,
    rays: &[bvhtrace_core::Ray],
    opts: &TraceOptions,
) -> Vec<String> {
    let (cpu_hits, cpu_counters) = cpu_counted(bvh, rays, opts);
    let mut failures = Vec::new();
    let mut incomplete = None;
    for t in all {
        let who = format!("{label} on {}", t.backend());
        let counted = t.trace(rays, &opts.with_counters(true)).expect("trace");
        let plain = t.trace(rays, opts).expect("trace");
        assert!(plain.counters.is_none(), "{who}: counters not asked for");
        if t.backend() != "cpu" {
            let n = *incomplete.get_or_insert(counted.incomplete);
            assert_eq!(counted.incomplete, n, "{who}: rays finished on the CPU");
        }
        let counters = counted.counters.as_deref().expect("counters asked for");
        failures.extend(differences(
            &who,
            rays,
            (&counted.hits, counters),
            &plain.hits,
            (&cpu_hits, &cpu_counters),
        ));
    }
    failures
}

/// The tracers, borrowed.
fn refs<'a>(all: &'a [Box<dyn Tracer + 'a>]) -> Vec<&'a dyn Tracer> {
    all.iter().map(|t| &**t as &dyn Tracer).collect()
}

#[test]
fn every_tracer_equals_the_cpu_bit_for_bit() {
    let devices = Devices::open("conformance");
    let traversals = [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(4),
        Traversal::Wide,
    ];
    let mut failures = Vec::new();
    // The built-in scenes always; the shared meshes when `../shared/scenes` is there.
    let scenes = scenes();
    assert!(scenes.len() >= 3, "only {} scenes loaded", scenes.len());
    for SceneCase { name, bvh, .. } in scenes {
        // With its wide layout: the ash upload takes it, the CPU twin walks it.
        let bvh = bvh.with_wide();
        let rays = parity_rays(&bvh);
        let all = tracers(&devices, &bvh);
        eprintln!(
            "{name}: {} nodes, depth {}, {} rays, {} tracers",
            bvh.nodes().len(),
            bvh.depth(),
            rays.len(),
            all.len()
        );
        for traversal in traversals {
            for query in [Query::Closest, Query::Any] {
                let label = format!("{name} {traversal} {query:?}");
                failures.extend(compare(
                    &label,
                    &refs(&all),
                    &bvh,
                    &rays,
                    &TraceOptions::new(traversal, query),
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    devices.check_validation();
}

/// The other triangle tests (Möller–Trumbore f32, watertight f64 where the device has it)
/// compose into the same kernels: every tracer that supports them equals the CPU twin.
#[test]
fn precisions_equal_the_cpu_on_every_tracer() {
    let devices = Devices::open("precisions");
    let mut failures = Vec::new();
    for SceneCase { name, bvh, .. } in ["builtin:degenerate", "builtin:cornell"]
        .into_iter()
        .filter_map(|spec| load_scene(spec, spec))
    {
        let bvh = bvh.with_wide();
        let rays = parity_rays(&bvh);
        let all = tracers(&devices, &bvh);
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
                            t.backend(),
                            t.supports(&opts)
                        );
                    }
                    let able: Vec<&dyn Tracer> = able.into_iter().map(|t| &**t).collect();
                    let label = format!("{name} {traversal} {query:?} {precision:?}");
                    failures.extend(compare(&label, &able, &bvh, &rays, &opts));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    devices.check_validation();
}

/// A wide tree deeper than the wide walk's stack: the rays that would overflow it come
/// back incomplete from the device tracers and are finished on the CPU (with the device's
/// tuning, and for ash with the GPU tuning too: no trip budget, the host copy kept for the
/// depth alone); hits and counters equal the CPU twin's.
#[test]
fn deep_wide_trees_finish_on_the_cpu() {
    let bvh = deep_wide_tree();
    let rays = deep_wide_rays();
    for tuning in [None, Some(DriverTuning::GPU)] {
        let devices = Devices::with_tuning("deep wide trees", tuning);
        let all = tracers(&devices, &bvh);
        for query in [Query::Closest, Query::Any] {
            let opts = TraceOptions::new(Traversal::Wide, query);
            for t in all.iter().filter(|t| t.backend() != "cpu") {
                let out = t.trace(&rays, &opts).expect("trace");
                assert!(
                    out.incomplete > 0,
                    "{query:?} {tuning:?} on {}: no ray overflowed the stack",
                    t.backend()
                );
            }
            let failures = compare(
                &format!("deep wide {query:?} {tuning:?}"),
                &refs(&all),
                &bvh,
                &rays,
                &opts,
            );
            assert!(failures.is_empty(), "{}", failures.join("\n"));
        }
        devices.check_validation();
    }
}

/// Every hit of a two-level scene carries its instance: `TraceOutput::instance_hit` gives
/// the instance, user id and mesh primitive `InstancedBvh::locate` gives, on every tracer
/// and walk; a one-mesh scene carries no instance table.
#[test]
fn every_tracer_locates_the_instance_of_a_hit() {
    let devices = Devices::open("instance hits");
    let scene = bvhtrace_scene::load("builtin:spheres").expect("builtin scene");
    let ib: InstancedBvh = scene
        .instanced_bvh(&bvhtrace_core::BuildOptions::default())
        .expect("two levels");
    let bvh = ib.bvh().clone().with_wide();
    let rays = parity_rays(&bvh);
    for t in tracers(&devices, &bvh) {
        for traversal in [Traversal::FullStack, Traversal::Stackless, Traversal::Wide] {
            let who = format!("{traversal} on {}", t.backend());
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
    let one = load_scene("builtin:cornell", "builtin:cornell")
        .expect("builtin scene")
        .bvh;
    for t in tracers(&devices, &one) {
        let out = t.trace(&rays, &TraceOptions::default()).expect("trace");
        assert!(
            out.instances.is_none(),
            "{}: one mesh has no instance table",
            t.backend()
        );
    }
    devices.check_validation();
}
