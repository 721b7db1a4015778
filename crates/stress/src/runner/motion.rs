//! The rows of a moving scene's case: the scene's moving tree (one mesh's, or moving
//! instances' two levels), built with each way of bounding time, traced at the case's time
//! on the CPU twin, in the CPU layout (`MovingCpuBvh`, `MovingInstancesCpuBvh`) and on each
//! device with a walk of moving scenes (the layout and the devices compared with the twin
//! bit for bit), and judged as the static scene the walks see at that time.

use std::sync::Arc;
use std::time::Instant;

use bvhtrace_core::motion::{MotionInstancedBvh, time_segment};
use bvhtrace_core::{FlatBvh, Hit, MotionBvh, MotionMesh, Query, Ray, TimeBounds};

use bvhtrace_cpu::{MovingCpuBvh, MovingInstancesCpuBvh};

use super::{
    Backends, CPU_LAYOUT_ROWS, CaseReport, Judge, MovingTree, RunReport, ms, note_no_walk,
    same_verdict, walk_row,
};
use crate::{Case, Motion, MovingScene};

/// The rows' traversal name for trees bounding time as `bounds` says.
fn walk_name(bounds: TimeBounds) -> &'static str {
    match bounds {
        TimeBounds::Linear => "motion-linear",
        TimeBounds::Merged => "motion-merged",
    }
}

fn row(backend: &str, bounds: TimeBounds, q: Query) -> RunReport {
    walk_row(backend, walk_name(bounds), q)
}

/// Moving instances' static twin at `m`'s time: each instance entered with the rows the
/// moving walks take a ray into it with ([`bvhtrace_core::motion::MovingInstance::world_to_object_at`]),
/// so the judging's oracle and brute force test what the walks test.
pub(super) fn place_at_time(bvh: &mut FlatBvh, m: &Motion) {
    let MovingScene::Instances { instances, .. } = &m.scene else {
        return;
    };
    let steps = (instances.iter()).map(|i| i.transforms.len()).max();
    let seg = time_segment(m.time, steps.unwrap_or(1).max(2));
    for (flat, inst) in bvh.parts_mut().instances.iter_mut().zip(instances) {
        flat.world_to_object = inst.world_to_object_at(seg);
    }
}

/// A moving tree built, and the CPU twin's trace of it.
struct Built {
    tree: MovingTree,
    nodes: usize,
    depth: u32,
}

impl Built {
    fn new(m: &Motion, case: &Case, bounds: TimeBounds) -> Result<Built, String> {
        let opts = &case.build;
        Ok(match &m.scene {
            MovingScene::Mesh(steps) => {
                let mesh = MotionMesh::new(steps.clone()).map_err(|e| e.to_string())?;
                let b = MotionBvh::build(&mesh, opts, bounds).map_err(|e| e.to_string())?;
                let (nodes, depth) = (b.nodes().len(), b.depth());
                let tree = MovingTree::Mesh(Arc::new(b));
                Built { tree, nodes, depth }
            }
            MovingScene::Instances { meshes, instances } => {
                let b = MotionInstancedBvh::build(meshes, instances.clone(), opts, bounds)
                    .map_err(|e| e.to_string())?;
                let layout = b.kernel_layout();
                let tree = MovingTree::Instances(Arc::new(b));
                let (nodes, depth) = (layout.nodes.len(), layout.depth);
                Built { tree, nodes, depth }
            }
        })
    }

    fn trace(&self, rays: &[Ray], times: &[f32], q: Query) -> Vec<Hit> {
        match &self.tree {
            MovingTree::Mesh(b) => b.trace_rays(rays, times, q),
            MovingTree::Instances(b) => b.trace_rays(rays, times, q),
        }
    }
}

/// Every row of `case` (whose rays all trace at `m.time`) into `rep`: per way of bounding
/// time and query, the CPU twin's (reported when `backends.cpu`) and each device's.
pub(super) fn run(
    case: &Case,
    m: &Motion,
    queries: &[Query],
    judge: &Judge<'_>,
    backends: &Backends,
    rep: &mut CaseReport,
) {
    let times = vec![m.time; case.rays.len()];
    rep.build_ms = 0.0;
    for bounds in [TimeBounds::Linear, TimeBounds::Merged] {
        let t = Instant::now();
        let built = match Built::new(m, case, bounds) {
            Ok(b) => b,
            Err(e) => {
                rep.error = Some(format!("build failed ({}): {e}", walk_name(bounds)));
                return;
            }
        };
        rep.build_ms += ms(t);
        (rep.nodes, rep.depth) = (built.nodes, built.depth);
        let mut twin = Vec::new();
        for &q in queries {
            let t = Instant::now();
            let hits = built.trace(&case.rays, &times, q);
            if backends.cpu {
                let r = RunReport {
                    trace_ms: ms(t),
                    ..row("cpu", bounds, q)
                };
                rep.runs.push(judge.evaluate(r, q, &hits, None));
            }
            twin.push(hits);
        }
        if backends.cpu {
            match layout_rows(&built, case, &times, queries, judge, (bounds, &twin)) {
                Ok(runs) => rep.runs.extend(runs),
                Err(note) => rep.notes.push(note),
            }
        }
        for device in backends.devices.iter().filter(|d| d.bit_for_bit) {
            let Some(open) = &device.open_motion else {
                note_no_walk(rep, &device.backend, "moving scenes");
                continue;
            };
            let traced = open(built.tree.clone());
            for (&q, cpu) in queries.iter().zip(&twin) {
                let r = row(&device.backend, bounds, q);
                let t = Instant::now();
                let hits = traced.as_ref().map_err(|e| format!("upload failed: {e}"));
                rep.runs.push(
                    match hits.and_then(|trace| {
                        trace(&case.rays, &times, q).map_err(|e| format!("trace failed: {e}"))
                    }) {
                        Ok(hits) => {
                            let r = RunReport {
                                trace_ms: ms(t),
                                ..r
                            };
                            judge.evaluate(r, q, &hits, Some(cpu))
                        }
                        Err(status) => RunReport { status, ..r },
                    },
                );
            }
        }
    }
}

/// The CPU layout's rows of `built` (bounding time as `bounds` says): each query traced
/// and judged like every row, closest hits compared with the twin's (`twin`, per query)
/// bit for bit, any hits on hit or miss. A tree the layout does not take gives a note.
fn layout_rows(
    built: &Built,
    case: &Case,
    times: &[f32],
    queries: &[Query],
    judge: &Judge<'_>,
    (bounds, twin): (TimeBounds, &[Vec<Hit>]),
) -> Result<Vec<RunReport>, String> {
    let note = |e: bvhtrace_cpu::ConvertError| format!("{CPU_LAYOUT_ROWS}: {e}");
    let trace: Box<dyn Fn(Query) -> Vec<Hit>> = match &built.tree {
        MovingTree::Mesh(b) => {
            let layout = MovingCpuBvh::from_motion(b).map_err(note)?;
            Box::new(move |q| layout.trace_rays(&case.rays, times, q))
        }
        MovingTree::Instances(b) => {
            let layout = MovingInstancesCpuBvh::from_motion(b).map_err(note)?;
            Box::new(move |q| layout.trace_rays(&case.rays, times, q))
        }
    };
    let mut runs = Vec::new();
    for (&q, cpu) in queries.iter().zip(twin) {
        let t = Instant::now();
        let hits = trace(q);
        let r = RunReport {
            trace_ms: ms(t),
            ..row(CPU_LAYOUT_ROWS, bounds, q)
        };
        runs.push(match q {
            Query::Closest => judge.evaluate(r, q, &hits, Some(cpu)),
            Query::Any => {
                let mut r = judge.evaluate(r, q, &hits, None);
                let differ = hits.iter().zip(cpu).filter(|(a, b)| !same_verdict(a, b));
                r.parity_mismatches = Some(differ.count());
                r
            }
        });
    }
    Ok(runs)
}
