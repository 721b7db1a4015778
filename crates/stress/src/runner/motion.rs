//! The rows of a moving mesh's case: the tree over its time steps, built with each way of
//! bounding time, traced at the case's time on the CPU twin and on each device with a
//! walk of moving meshes (compared with the twin bit for bit), and judged as the static
//! scene the walks see at that time.

use std::sync::Arc;
use std::time::Instant;

use bvhtrace_core::{MotionBvh, MotionMesh, Query, TimeBounds};

use super::{Backends, CaseReport, Judge, RunReport, ms, query_name};
use crate::{Case, Motion};

/// The rows' traversal name for trees bounding time as `bounds` says.
fn walk_name(bounds: TimeBounds) -> &'static str {
    match bounds {
        TimeBounds::Linear => "motion-linear",
        TimeBounds::Merged => "motion-merged",
    }
}

fn row(backend: &str, bounds: TimeBounds, q: Query) -> RunReport {
    RunReport {
        backend: backend.into(),
        traversal: walk_name(bounds).into(),
        query: query_name(q).into(),
        status: "ok".into(),
        ..Default::default()
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
    let mesh = match MotionMesh::new(m.steps.clone()) {
        Ok(mesh) => mesh,
        Err(e) => {
            rep.error = Some(format!("moving mesh: {e}"));
            return;
        }
    };
    let times = vec![m.time; case.rays.len()];
    for bounds in [TimeBounds::Linear, TimeBounds::Merged] {
        let t = Instant::now();
        let bvh = match MotionBvh::build(&mesh, &case.build, bounds) {
            Ok(b) => Arc::new(b),
            Err(e) => {
                rep.error = Some(format!("build failed ({}): {e}", walk_name(bounds)));
                return;
            }
        };
        rep.build_ms += ms(t);
        rep.nodes = bvh.nodes().len();
        rep.depth = bvh.depth();
        let mut twin = Vec::new();
        for &q in queries {
            let t = Instant::now();
            let hits = bvh.trace_rays(&case.rays, &times, q);
            if backends.cpu {
                let r = RunReport {
                    trace_ms: ms(t),
                    ..row("cpu", bounds, q)
                };
                rep.runs.push(judge.evaluate(r, q, &hits, None));
            }
            twin.push(hits);
        }
        for device in backends.devices.iter().filter(|d| d.bit_for_bit) {
            let Some(open) = &device.open_motion else {
                let note = format!("{}: no walk of moving meshes, not traced", device.backend);
                if !rep.notes.contains(&note) {
                    rep.notes.push(note);
                }
                continue;
            };
            let traced = open(bvh.clone());
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
