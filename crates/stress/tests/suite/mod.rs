//! The stress cases at quick size, on the backends the including test gives
//! (`super::backends()` for every case, `super::two_level_backends()` for the
//! `instances-*` cases): the CPU twins (`crates/stress/tests/stress.rs`), and the devices
//! of our walks from the front door's tracer factories, each row named after its backend
//! (`tests/stress_devices.rs` in the workspace; `bvhtrace stress --backends
//! cpu,wgpu,vulkan` runs every case there): the guarantees `GUARANTEES.md` states.
//!
//! Every case runs once (shared by the tests below), each on its own thread with a time
//! limit, so a hang fails the run instead of stalling it.

use std::sync::OnceLock;
use std::time::{Duration, Instant};

use bvhtrace_core::{BuildOptions, Instance, InstanceError, InstancedBvh, Ray};
use bvhtrace_stress::geom::{IndexedMesh, unit_icosphere};
use bvhtrace_stress::{
    Backends, CPU_LAYOUT_ROWS, Case, CaseOptions, CaseReport, Expect, RunReport, Size, cases_sized,
    format_table, run_case, run_case_with_timeout, select_cases,
};
use glam::{Affine3A, Vec3};

/// Generous: the slowest quick case takes a few seconds on two cores.
const CASE_LIMIT: Duration = Duration::from_secs(120);

struct Suite {
    reports: Vec<CaseReport>,
    /// Cases that hung or panicked.
    failures: Vec<String>,
    /// The devices of our walks on every case, by row name.
    devices: Vec<String>,
    /// Those on the two-level cases only.
    two_level_devices: Vec<String>,
    /// Those with walks of moving meshes and of curves.
    timed_devices: Vec<String>,
}

/// The names of `b`'s devices of our walks (the device's own ray queries are reported,
/// not judged here).
fn our_walks(b: &Backends) -> Vec<String> {
    (b.devices.iter())
        .filter(|d| d.bit_for_bit)
        .map(|d| d.backend.clone())
        .collect()
}

/// The names of `b`'s devices with our walks of moving meshes and of curves.
fn timed_walks(b: &Backends) -> Vec<String> {
    (b.devices.iter())
        .filter(|d| d.bit_for_bit && d.open_motion.is_some() && d.open_curves.is_some())
        .map(|d| d.backend.clone())
        .collect()
}

/// The cases at quick size, with the shared scenes' real meshes when the folder is there.
fn options() -> CaseOptions {
    CaseOptions::new(Size::Quick).with_scenes(bvhtrace_scene::shared_scenes_dir())
}

fn suite() -> &'static Suite {
    static SUITE: OnceLock<Suite> = OnceLock::new();
    SUITE.get_or_init(|| {
        let start = Instant::now();
        let backends = super::backends();
        // Some devices only on the two-level cases (the kernels' instanced variants): the
        // one-mesh kernels' parity with wgpu is their crates' own tests.
        let two_level = super::two_level_backends();
        let devices = our_walks(&backends);
        let two_level_devices: Vec<String> = (our_walks(&two_level).into_iter())
            .filter(|d| !devices.contains(d))
            .collect();
        println!(
            "every case on: cpu {devices:?}; the two-level cases also on: {two_level_devices:?}"
        );
        let mut reports = Vec::new();
        let mut failures = Vec::new();
        for case in cases_sized(&options()) {
            let b = if case.instancing.is_some() {
                &two_level
            } else {
                &backends
            };
            match run_case_with_timeout(&case, b, CASE_LIMIT) {
                Ok(r) => reports.push(r),
                Err(e) => failures.push(e),
            }
        }
        println!("{}", format_table(&reports));
        let two_levels: f64 = reports
            .iter()
            .filter(|r| r.name.starts_with("instances-"))
            .map(|r| r.elapsed_ms)
            .sum();
        println!(
            "suite: {:.1} s ({:.1} s of it the instances-* cases)",
            start.elapsed().as_secs_f64(),
            two_levels / 1e3
        );
        Suite {
            reports,
            failures,
            timed_devices: timed_walks(&backends),
            devices,
            two_level_devices,
        }
    })
}

/// Every run that happened, with its case.
fn all_runs() -> impl Iterator<Item = (&'static CaseReport, &'static RunReport)> {
    suite().reports.iter().flat_map(|c| {
        c.runs
            .iter()
            .filter(|r| r.status == "ok")
            .map(move |r| (c, r))
    })
}

/// Every run of a case within the guaranteed range (`scale-limit-*` are measured only).
fn runs() -> impl Iterator<Item = (&'static CaseReport, &'static RunReport)> {
    all_runs().filter(|(c, _)| c.guaranteed)
}

/// A run of our walks on a device, not of a CPU walk.
fn on_device(r: &RunReport) -> bool {
    let s = suite();
    s.devices.contains(&r.backend) || s.two_level_devices.contains(&r.backend)
}

fn label(c: &CaseReport, r: &RunReport) -> String {
    format!("{} {} {} {}", c.name, r.backend, r.traversal, r.query)
}

/// Fails with every violation listed (and a few example rays), not just the first.
fn check(what: &str, bad: Vec<String>) {
    assert!(
        bad.is_empty(),
        "{what}: {} violation(s):\n{}",
        bad.len(),
        bad.join("\n")
    );
}

fn with_examples(c: &CaseReport, r: &RunReport, msg: String) -> String {
    let mut s = format!("{}: {msg}", label(c, r));
    for e in r.examples.iter().take(2) {
        s.push_str(&format!("\n    {e}"));
    }
    s
}

#[test]
fn every_case_runs_without_crash_or_hang() {
    let s = suite();
    check("cases that hung or panicked", s.failures.clone());
    let mut bad = Vec::new();
    for c in &s.reports {
        // The only case allowed not to run: real meshes when the shared folder is absent.
        if let Some(s) = &c.skipped {
            if c.name == "watertight-real" {
                println!("SKIP {}: {s} {:?}", c.name, c.notes);
            } else {
                bad.push(format!("{}: {s}", c.name));
            }
            continue;
        }
        match &c.error {
            Some(e) => bad.push(format!("{}: {e}", c.name)),
            None => {
                for r in &c.runs {
                    let refused_deep = r.backend != "cpu"
                        && r.traversal == "full-stack"
                        && r.status.starts_with("refused");
                    if r.status != "ok" && !refused_deep {
                        bad.push(format!("{}: {}", label(c, r), r.status));
                    }
                }
            }
        }
    }
    check("runs that did not complete", bad);
    assert!(s.reports.len() >= 20, "only {} cases ran", s.reports.len());
}

#[test]
fn no_ray_escapes_a_closed_mesh() {
    let mut bad = Vec::new();
    for (c, r) in runs() {
        // Slivers 1e3 long around an origin 1e-3 from their surface: the f32 distance's
        // error (1e1..1e3 there) exceeds the distance, so an escape through t < t_min is
        // f32-indeterminate; a crack (determinate escape) is never allowed.
        let allowed = if c.name == "slivers" {
            r.escapes.indeterminate
        } else {
            0
        };
        if r.escapes.total() > allowed {
            bad.push(with_examples(
                c,
                r,
                format!(
                    "{} escapes (wrong/indeterminate {}/{}) of {} rays from inside",
                    r.escapes.total(),
                    r.escapes.wrong,
                    r.escapes.indeterminate,
                    r.must_hit
                ),
            ));
        }
        if (c.name.starts_with("watertight") || c.name.starts_with("instances-")) && r.must_hit == 0
        {
            bad.push(format!("{}: no ray from inside", label(c, r)));
        }
    }
    check("escapes", bad);
}

#[test]
fn no_output_is_nan_and_every_hit_keeps_the_contract() {
    let mut bad = Vec::new();
    for (c, r) in all_runs() {
        if r.nan_outputs > 0 || r.contract_violations > 0 {
            bad.push(with_examples(
                c,
                r,
                format!(
                    "{} NaN outputs, {} contract violations",
                    r.nan_outputs, r.contract_violations
                ),
            ));
        }
    }
    check("NaN or contract", bad);
}

#[test]
fn gpu_kernels_equal_their_cpu_twins_bit_for_bit() {
    let s = suite();
    if s.devices.is_empty() && s.two_level_devices.is_empty() {
        println!("SKIP: no device, the kernels were not run");
        return;
    }
    let mut bad = Vec::new();
    let mut by_backend = std::collections::BTreeMap::<&str, usize>::new();
    for (c, r) in all_runs().filter(|(_, r)| on_device(r)) {
        *by_backend.entry(&r.backend).or_default() += 1;
        match r.parity_mismatches {
            Some(0) => {}
            Some(n) => bad.push(with_examples(
                c,
                r,
                format!("{n} of {} rays differ from the CPU twin", r.rays),
            )),
            None => bad.push(format!("{}: not compared", label(c, r))),
        }
    }
    check("device/CPU parity", bad);
    for d in &s.devices {
        let n = by_backend.get(d.as_str()).copied().unwrap_or(0);
        assert!(n >= 100, "only {n} {d} runs");
    }
    for d in &s.two_level_devices {
        let n = by_backend.get(d.as_str()).copied().unwrap_or(0);
        assert!(n >= 50, "only {n} {d} runs");
    }
}

#[test]
fn no_false_miss_where_f32_can_decide() {
    // The oracle answers for the f32 input itself (its corners converted exactly), so this
    // holds for every case, exact input or not; f32-indeterminate rays are counted apart.
    let mut bad = Vec::new();
    let mut indeterminate = 0;
    for (c, r) in runs() {
        indeterminate += r.false_misses.indeterminate;
        if r.false_misses.wrong > 0 {
            bad.push(with_examples(
                c,
                r,
                format!(
                    "{} false misses of {} sampled rays (input {})",
                    r.false_misses.wrong,
                    r.sample,
                    if c.input.exact { "exact" } else { "rounded" }
                ),
            ));
        }
    }
    println!("f32-indeterminate false misses over all runs: {indeterminate}");
    check("false misses", bad);
}

#[test]
fn no_determinate_difference_from_the_oracle_or_the_brute_force() {
    let mut bad = Vec::new();
    for (c, r) in runs() {
        let (fh, wp, bf) = (
            r.false_hits.wrong,
            r.wrong_prim.wrong,
            r.brute_mismatch.wrong,
        );
        if fh + wp + bf > 0 {
            bad.push(with_examples(
                c,
                r,
                format!("{fh} false hits, {wp} wrong primitives, {bf} differences from the f32 brute force"),
            ));
        }
    }
    check("determinate differences", bad);
}

#[test]
fn known_answers_are_given() {
    let mut bad = Vec::new();
    for (c, r) in runs() {
        if r.known_wrong > 0 {
            bad.push(with_examples(
                c,
                r,
                format!("{} of {} known answers wrong", r.known_wrong, r.known),
            ));
        }
    }
    check("known answers", bad);
    let ext = suite()
        .reports
        .iter()
        .find(|c| c.name == "extreme-rays")
        .expect("the extreme-rays case ran");
    for r in &ext.runs {
        assert_eq!(
            r.invalid_flagged,
            13,
            "{}: every invalid ray flagged",
            label(ext, r)
        );
    }
}

#[test]
fn deep_trees_stay_correct_without_a_full_stack() {
    let s = suite();
    let deep = s
        .reports
        .iter()
        .find(|c| c.name == "deep")
        .expect("the deep case ran");
    assert!(
        deep.depth > 64,
        "depth {} is not deeper than the kernel's stack",
        deep.depth
    );
    for d in &s.devices {
        let msg = (deep.full_stack.iter())
            .find(|(b, _)| b == d)
            .map_or("not tried", |(_, m)| m.as_str());
        assert!(
            msg.starts_with("refused"),
            "{d}: full-stack upload of a tree {} deep: {msg}",
            deep.depth
        );
        let runs: Vec<&RunReport> = deep.runs.iter().filter(|r| r.backend == *d).collect();
        for walk in ["stackless", "short-stack(1)"] {
            let ran = runs.iter().any(|r| r.traversal == walk && r.status == "ok");
            assert!(ran, "{d}: {walk} on the deep tree");
        }
    }
    if s.devices.is_empty() {
        println!("SKIP the device upload check: no device");
    }
    for r in deep.runs.iter().filter(|r| r.status == "ok") {
        assert!(
            r.known > 0 && r.known_wrong == 0,
            "{}: {:?}",
            label(deep, r),
            r.examples
        );
        assert!(r.clean(), "{}: {:?}", label(deep, r), r.examples);
    }
}

#[test]
fn the_origin_offset_removes_self_hits() {
    let c = suite()
        .reports
        .iter()
        .find(|c| c.name == "self-hits")
        .expect("the self-hits case ran");
    for r in c
        .runs
        .iter()
        .filter(|r| r.status == "ok" && r.query == "closest")
    {
        assert!(r.secondary_offset > 0 && r.secondary_plain > 0);
        assert_eq!(r.self_hits_offset, 0, "{}", label(c, r));
        // Without the offset the measure sees them (about half the rays): it works.
        assert!(
            r.self_hits_plain > r.secondary_plain / 10,
            "{}: {}",
            label(c, r),
            r.self_hits_plain
        );
    }
}

#[test]
fn near_rays_separate_surfaces_until_the_input_merges() {
    let c = suite()
        .reports
        .iter()
        .find(|c| c.name == "precision-limit")
        .expect("the precision-limit case ran");
    for r in c
        .runs
        .iter()
        .filter(|r| r.status == "ok" && r.query == "closest")
    {
        assert!(!r.precision.is_empty());
        for row in &r.precision {
            assert_eq!(row.traced_vs_oracle.wrong, 0, "{}: {row:?}", label(c, r));
            if row.offset <= 1.0 {
                assert_eq!(row.input_merged + row.traced_wrong_surface, 0, "{row:?}");
            }
            // Rays from 1 unit away: wrong only where the f32 input itself merged.
            if !row.far {
                assert!(
                    row.traced_wrong_surface <= row.input_merged,
                    "{}: {row:?}",
                    label(c, r)
                );
            }
        }
    }
}

/// The CPU layout (`bvhtrace-cpu`), one ray at a time and in packets, on every case it
/// takes: the CPU full stack's answers (closest hits bit for bit, any hits on hit or
/// miss) in the guaranteed range. The tests above hold its rows to every guarantee (escapes, contract, oracle,
/// brute force, known answers) as they hold every walk's.
#[test]
fn the_cpu_layout_gives_the_full_stacks_answers() {
    let s = suite();
    let mut bad = Vec::new();
    let mut taken = 0;
    for c in s
        .reports
        .iter()
        .filter(|c| c.skipped.is_none() && c.error.is_none())
    {
        let rows: Vec<&RunReport> = c
            .runs
            .iter()
            .filter(|r| r.backend == CPU_LAYOUT_ROWS)
            .collect();
        if rows.is_empty() {
            println!(
                "{}: no {CPU_LAYOUT_ROWS} rows: {:?}",
                c.name,
                c.notes.last()
            );
            continue;
        }
        taken += 1;
        // Per query: a static tree's single-ray and packet rows; a moving tree's one row
        // per way of bounding time, as the twin's; a tree of curves' one row.
        let cpu = |walk: &dyn Fn(&str) -> bool| {
            (c.runs.iter())
                .filter(|r| r.backend == "cpu" && walk(&r.traversal))
                .count()
        };
        let queries = cpu(&|t| t == "full-stack");
        let moving = cpu(&|t| t.starts_with("motion-"));
        let curves = cpu(&|t| t == "curves");
        if rows.len() != 2 * queries + moving + curves {
            bad.push(format!(
                "{}: {} rows for {queries} queries, {moving} moving rows and {curves} of curves",
                c.name,
                rows.len()
            ));
        }
        for r in rows {
            // Past the guaranteed range (`scale-limit-*`: products underflow, ties at
            // `t = 0` that the full stack itself settles by its order) only measured.
            if !c.guaranteed && r.status == "ok" {
                println!(
                    "{}: {:?} rays differ from the full stack (measured only)",
                    label(c, r),
                    r.parity_mismatches
                );
                continue;
            }
            if r.status != "ok" || r.parity_mismatches != Some(0) {
                bad.push(with_examples(
                    c,
                    r,
                    format!(
                        "{} of {} rays differ from the full stack ({})",
                        r.parity_mismatches.unwrap_or(usize::MAX),
                        r.rays,
                        r.status
                    ),
                ));
            }
        }
    }
    check("the CPU layout against the full stack", bad);
    assert!(taken >= 20, "the CPU layout took only {taken} cases");
}

/// The loop-trip budget (`TRIP_LIMIT`): on an adapter that bounds the kernels' loops
/// (lavapipe), the rays through the 70,000-deep stack of duplicates in `coincident` spend
/// it and are finished on the CPU twin (their answers are checked by the parity and
/// known-answer tests); no ray of an ordinary case comes near it.
#[test]
fn only_the_long_walks_spend_the_trip_budget() {
    let bounded = (super::backends().devices.iter())
        .any(|d| d.bit_for_bit && d.tuning.trip_limit != u32::MAX);
    let mut bad = Vec::new();
    let mut long_walks = 0;
    for (c, r) in all_runs().filter(|(_, r)| on_device(r)) {
        let n = r.gpu_incomplete.unwrap_or(0);
        if c.name == "coincident" {
            long_walks += n;
        } else if n > 0 {
            bad.push(format!("{}: {n} rays spent the trip budget", label(c, r)));
        }
    }
    check("ordinary rays over the trip budget", bad);
    if bounded {
        assert!(
            long_walks > 0,
            "no ray of `coincident` spent the trip budget: the 70,000-triangle walks were truncated or the budget is not applied"
        );
    } else {
        println!("SKIP the trip-budget check: no GPU, or its loops are unbounded");
    }
}

/// The `instances` group: a closed icosphere instanced rotated, scaled by 1e-6 and 1e6,
/// non-uniformly, mirrored, translated by 1e5, and all at once. Every ray starts inside an
/// instance and is aimed at one of its world-space vertices or edge points: none may
/// escape, on any backend, traversal or query, and every run is clean (oracle, brute
/// force, GPU = CPU bit for bit).
#[test]
fn instanced_closed_meshes_let_no_ray_escape_on_any_backend() {
    let s = suite();
    let cases: Vec<&CaseReport> = s
        .reports
        .iter()
        .filter(|c| c.name.starts_with("instances-"))
        .collect();
    let names: Vec<&str> = cases.iter().map(|c| c.name.as_str()).collect();
    for want in [
        "instances-rotated",
        "instances-scale-1e-6",
        "instances-scale-1e6",
        "instances-nonuniform",
        "instances-mirrored",
        "instances-offset-1e5",
        "instances-mixed",
    ] {
        assert!(names.contains(&want), "{want} did not run: {names:?}");
    }
    let mut backends = vec!["cpu"];
    backends.extend(
        s.devices
            .iter()
            .chain(&s.two_level_devices)
            .map(String::as_str),
    );
    println!("the instanced cases on {backends:?}");
    let mut bad = Vec::new();
    for c in &cases {
        assert!(c.guaranteed, "{}", c.name);
        if let Some(e) = &c.error {
            bad.push(format!("{}: {e}", c.name));
            continue;
        }
        for b in &backends {
            let runs: Vec<&RunReport> = c.runs.iter().filter(|r| r.backend == *b).collect();
            // Every traversal, closest and any-hit: the trees are shallow, nothing refused.
            if runs.len() != 2 * bvhtrace_stress::traversals().len()
                || runs.iter().any(|r| r.status != "ok")
            {
                bad.push(format!(
                    "{} {b}: runs {:?}",
                    c.name,
                    runs.iter()
                        .map(|r| format!("{} {} {}", r.traversal, r.query, r.status))
                        .collect::<Vec<_>>()
                ));
                continue;
            }
            let escapes: usize = runs.iter().map(|r| r.escapes.total()).sum();
            let must_hit = runs[0].must_hit;
            println!(
                "{} {b}: {escapes} escapes of {must_hit} rays from inside x {} runs",
                c.name,
                runs.len()
            );
            for r in runs {
                // Every ray of these cases starts verified inside its instance.
                if r.must_hit == 0 || r.must_hit != r.rays {
                    bad.push(format!(
                        "{}: {} of {} rays from inside (notes: {:?})",
                        label(c, r),
                        r.must_hit,
                        r.rays,
                        c.notes
                    ));
                }
                if r.escapes.total() > 0 || !r.clean() {
                    bad.push(with_examples(
                        c,
                        r,
                        format!(
                            "{} escapes, {}/{} wrong primitives, {}/{} vs brute force, parity {:?}",
                            r.escapes.total(),
                            r.wrong_prim.wrong,
                            r.wrong_prim.indeterminate,
                            r.brute_mismatch.wrong,
                            r.brute_mismatch.indeterminate,
                            r.parity_mismatches
                        ),
                    ));
                }
                if *b != "cpu" && r.parity_mismatches != Some(0) {
                    bad.push(format!("{}: parity {:?}", label(c, r), r.parity_mismatches));
                }
            }
        }
    }
    check("instanced closed meshes", bad);
}

/// A case with three instances of a closed icosphere, instance `bad` placed by `m`, and a
/// few rays from inside the first.
fn case_with_transform(bad: usize, m: Affine3A) -> Case {
    let mesh: IndexedMesh = unit_icosphere(1);
    let mut instances: Vec<Instance> = [0.0, 4.0, 8.0]
        .iter()
        .map(|&x| Instance::new(0, Affine3A::from_translation(Vec3::new(x, 0.0, 0.0))))
        .collect();
    instances[bad].transform = m;
    let mut c = Case::instanced(
        "instances-unusable",
        "an unusable transform",
        vec![mesh.triangles()],
        instances,
    );
    c.push_rays(
        [Vec3::X, Vec3::Y, Vec3::NEG_Z].map(|d| Ray::new(Vec3::new(0.1, 0.0, 0.0), d)),
        Expect::MustHit,
    );
    c
}

/// Singular (a zero scale), NaN and infinite transforms, and one whose inverse overflows
/// f32, are `InstanceError::BadInstance` naming the instance, and the stress runner
/// reports that as the case's error (no panic, no runs, not clean).
#[test]
fn unusable_transforms_are_errors_naming_the_instance() {
    let mut nan = Affine3A::IDENTITY;
    nan.matrix3.y_axis.z = f32::NAN;
    let transforms = [
        ("singular", Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0))),
        ("singular", Affine3A::from_scale(Vec3::ZERO)),
        ("NaN", nan),
        (
            "NaN",
            Affine3A::from_translation(Vec3::new(0.0, f32::NAN, 0.0)),
        ),
        (
            "infinite",
            Affine3A::from_translation(Vec3::new(f32::INFINITY, 0.0, 0.0)),
        ),
        (
            "infinite",
            Affine3A::from_scale(Vec3::new(1.0, f32::NEG_INFINITY, 1.0)),
        ),
        // Finite and invertible in f64, but its inverse (1e40) is not an f32.
        ("overflows", Affine3A::from_scale(Vec3::splat(1e-40))),
    ];
    let backends = Backends::cpu_only();
    for bad in [1, 2] {
        for (what, m) in transforms {
            let case = case_with_transform(bad, m);
            let inst = case.instancing.as_ref().expect("two levels");
            match InstancedBvh::build(
                &inst.meshes,
                inst.instances.clone(),
                &BuildOptions::default(),
            ) {
                Err(InstanceError::BadInstance { index, problem }) => {
                    assert_eq!(index, bad, "{what}: {problem}");
                    let word = match what {
                        "NaN" | "infinite" => "NaN or infinite",
                        w => w,
                    };
                    assert!(problem.contains(word), "{what}: {problem}");
                }
                other => panic!("{what} transform at instance {bad}: {other:?}"),
            }
            let rep = run_case(&case, &backends);
            let err = rep.error.clone().unwrap_or_default();
            assert!(
                err.contains(&format!("instance {bad}:")),
                "{what}: the runner said {:?}",
                rep.error
            );
            assert!(rep.runs.is_empty() && !rep.clean(), "{what}: {rep:?}");
        }
    }
    // The same case with a usable transform runs clean.
    let ok = run_case(
        &case_with_transform(1, Affine3A::from_scale(Vec3::new(-1.0, 2.0, 1e-3))),
        &backends,
    );
    assert!(ok.error.is_none() && ok.clean(), "{ok:?}");
    assert!(
        ok.runs
            .iter()
            .all(|r| r.must_hit == 3 && r.escapes.total() == 0)
    );
    // And a group selection names every instance case.
    let sel = select_cases(&["instances".into()], &options()).expect("the group exists");
    assert!(sel.len() >= 7 && sel.iter().all(|c| c.instancing.is_some()));
}

/// Checks the `want` cases named `prefix...`: each ran without error, and on the CPU twin
/// and every device with walks of moving scenes and curves it has its rows (`walks` x
/// closest and any), each ran, clean, on a device equal to the twin, and passing `also`
/// (a violation's description, or `None`). Fails with every violation as `what`.
fn check_timed_rows(
    (prefix, want): (&str, usize),
    walks: usize,
    what: &str,
    also: impl Fn(&CaseReport, &RunReport) -> Option<String>,
) {
    let s = suite();
    let cases: Vec<&CaseReport> = (s.reports.iter())
        .filter(|c| c.name.starts_with(prefix))
        .collect();
    assert_eq!(cases.len(), want, "{prefix}* cases ran");
    let mut backends = vec!["cpu".to_string()];
    backends.extend(s.timed_devices.iter().cloned());
    println!("the {prefix}* cases on {backends:?}");
    let mut bad = Vec::new();
    for c in &cases {
        assert!(
            c.error.is_none() && c.skipped.is_none(),
            "{}: {:?}",
            c.name,
            c.error
        );
        for b in &backends {
            let runs: Vec<&RunReport> = c.runs.iter().filter(|r| r.backend == *b).collect();
            if runs.len() != 2 * walks || runs.iter().any(|r| r.status != "ok") {
                bad.push(format!(
                    "{} {b}: {} runs: {:?}",
                    c.name,
                    runs.len(),
                    c.notes
                ));
            }
            for r in runs {
                if !r.clean() || (b != "cpu" && r.parity_mismatches != Some(0)) {
                    let msg = format!("not clean (parity {:?})", r.parity_mismatches);
                    bad.push(with_examples(c, r, msg));
                }
                if let Some(msg) = also(c, r) {
                    bad.push(with_examples(c, r, msg));
                }
            }
        }
    }
    check(what, bad);
}

/// The `motion-*` cases: a moving, turning, growing sphere at the shutter's ends, a step,
/// between steps and outside the shutter, a sphere turning inside out, and spheres placed
/// by moving instances (still, moving and stretching, mirrored). At every time,
/// with either way of bounding time, on the CPU twin and the devices: no ray from inside
/// escapes, the f64 oracle and the brute force of the mesh at that time agree, and the
/// devices equal the twin bit for bit. A time outside the shutter is its end.
#[test]
fn moving_meshes_stay_closed_at_every_time_on_every_walk() {
    check_timed_rows(("motion-", 14), 2, "moving meshes", |c, r| {
        // Flat at mid-shutter: no inside; everywhere else rays from inside.
        let wrong_inside_count = (r.must_hit == 0) != (c.name == "motion-flip-t0.5");
        (wrong_inside_count || r.escapes.total() > 0).then(|| {
            format!(
                "{} escapes of {} rays from inside",
                r.escapes.total(),
                r.must_hit
            )
        })
    });
    let names = ["motion-before", "motion-t0", "motion-after", "motion-t1"].map(String::from);
    let picked = select_cases(&names, &options()).expect("the motion cases");
    let tris = |n: &str| {
        let c = picked.iter().find(|c| c.name == n).expect("picked");
        c.tris.clone()
    };
    assert!(
        tris("motion-before") == tris("motion-t0"),
        "before the shutter is its start"
    );
    assert!(
        tris("motion-after") == tris("motion-t1"),
        "after the shutter is its end"
    );
    assert!(tris("motion-t0") != tris("motion-t1"), "the mesh moves");
}

/// The `curves-*` cases, one per kind: every ray with a known answer (a segment hit from
/// beside it, a miss at 2.5 radii, the triangles under the strands, the huge radius) gets
/// it, degenerate strands (zero length, radius 0) break no contract, every walk equals
/// the tree's brute force, and the devices equal the twin (cubic curves under the
/// kernels' rule).
#[test]
fn curves_give_their_known_answers_on_every_walk() {
    check_timed_rows(("curves-", 4), 1, "curves", |_, r| {
        (r.known < 100 || r.brute_mismatch.total() > 0 || r.sample != r.rays).then(|| {
            format!(
                "{} known answers, {} differences from the brute force on {} of {} rays",
                r.known,
                r.brute_mismatch.total(),
                r.sample,
                r.rays
            )
        })
    });
}

/// The judging of moving meshes and curves can fail: a known answer changed, or a case
/// traced at a time other than the one its scene was made at, is caught.
#[test]
fn wrong_answers_of_moving_meshes_and_curves_are_caught() {
    let names = ["curves-round-bezier", "motion-t0.3"].map(String::from);
    let mut picked = select_cases(&names, &options()).expect("the cases");
    picked.sort_by(|a, b| a.name.cmp(&b.name));
    let cpu = Backends::cpu_only();
    let curves = &mut picked[0];
    let k = (curves.expect.iter())
        .position(|e| matches!(e, Expect::Prim(p) if *p >= 2))
        .expect("a known curve hit");
    curves.expect[k] = Expect::Miss;
    let rep = run_case(curves, &cpu);
    assert!(
        !rep.clean() && rep.runs.iter().all(|r| r.known_wrong == 1),
        "{rep:?}"
    );
    let moving = &mut picked[1];
    moving.motion.as_mut().expect("a moving mesh").time = 0.7;
    let rep = run_case(moving, &cpu);
    assert!(
        !rep.runs.is_empty() && rep.runs.iter().all(|r| !r.clean()),
        "{}",
        format_table(std::slice::from_ref(&rep))
    );
}
