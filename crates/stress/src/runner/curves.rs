//! The rows of a case of curves: one tree over its triangles and segments, traced on the
//! CPU twin, in the CPU layout (compared with the twin bit for bit) and on each device
//! with a walk of curves, judged against the known answers,
//! the output contract and the tree's own brute force (there is no f64 oracle for
//! curves), each device compared with the twin: linear curves bit for bit, cubic curves
//! under the kernels' stated rule.

use std::sync::Arc;
use std::time::Instant;

use bvhtrace_core::{CurveBvh, Curves, Hit, Query};
use bvhtrace_cpu::CurveCpuBvh;
use rayon::prelude::*;

use super::{
    Backends, CPU_LAYOUT_ROWS, CaseReport, Examples, Geometry, Judge, RunReport, as_traced,
    hit_bits, ms, note_no_walk, same_verdict, walk_row,
};
use crate::Case;
use crate::geom::is_zero_area;

/// The rows' traversal name: the tree's full-stack walk.
const WALK: &str = "curves";

fn row(backend: &str, q: Query) -> RunReport {
    walk_row(backend, WALK, q)
}

/// A device's hit of a cubic curve as its CPU twin's, under the kernels' rule: the shader
/// compiler may reassociate the curve's evaluation, so Newton's method can end an ulp
/// away; the same answer with `t` within `1e-5` of the twin's (of 1 below 1) and `u`
/// within `1e-5`.
fn cubic_alike(g: &Hit, c: &Hit) -> bool {
    hit_bits(g) == hit_bits(c)
        || (g.is_hit()
            && g.prim == c.prim
            && (g.t - c.t).abs() <= 1e-5 * c.t.max(1.0)
            && (g.u - c.u).abs() <= 1e-5)
}

/// Every row of `case` into `rep`.
pub(super) fn run(case: &Case, curves: &Curves, backends: &Backends, rep: &mut CaseReport) {
    let t = Instant::now();
    let bvh = match CurveBvh::build(&case.tris, curves.clone(), &case.build) {
        Ok(b) => Arc::new(b),
        Err(e) => {
            rep.error = Some(format!("build failed: {e}"));
            return;
        }
    };
    rep.build_ms = ms(t);
    rep.depth = bvh.depth();
    rep.nodes = bvh.nodes().len();
    let judge = Judge {
        case,
        geo: Geometry::Flat(&case.tris),
        sample: Vec::new(),
        position: vec![usize::MAX; case.rays.len()],
        oracle: Vec::new(),
        brute: Vec::new(),
        zero_area: case.tris.iter().map(is_zero_area).collect(),
        traced: case.rays.iter().map(as_traced).collect(),
    };
    let t = Instant::now();
    let brute: Vec<Hit> = case.rays.par_iter().map(|r| bvh.brute_force(r)).collect();
    rep.oracle_ms = ms(t);
    rep.notes.push(format!(
        "{} {} segments beside the triangles; every ray compared with the tree's brute force ({:.0} ms; no f64 oracle for curves)",
        curves.len(),
        curves.kind.name(),
        rep.oracle_ms
    ));
    let queries: &[Query] = if case.any_hit {
        &[Query::Closest, Query::Any]
    } else {
        &[Query::Closest]
    };
    let cubic = curves.kind.degree() == 3;
    let times = vec![0.0; case.rays.len()];
    let layout = match CurveCpuBvh::from_curves(bvh.clone()) {
        Ok(l) => Some(l),
        Err(e) => {
            rep.notes.push(format!("{CPU_LAYOUT_ROWS}: {e}"));
            None
        }
    };
    for &q in queries {
        let t = Instant::now();
        let twin = bvh.trace_rays(&case.rays, q);
        if backends.cpu {
            let r = RunReport {
                trace_ms: ms(t),
                ..row("cpu", q)
            };
            let r = judge.evaluate(r, q, &twin, None);
            rep.runs.push(against_brute(&judge, r, q, &twin, &brute));
            if let Some(layout) = &layout {
                rep.runs.push(layout_row(&judge, layout, q, &twin, &brute));
            }
        }
        for device in backends.devices.iter().filter(|d| d.bit_for_bit) {
            let Some(open) = &device.open_curves else {
                note_no_walk(rep, &device.backend, "curves");
                continue;
            };
            let r = row(&device.backend, q);
            let t = Instant::now();
            let traced = open(bvh.clone())
                .map_err(|e| format!("upload failed: {e}"))
                .and_then(|trace| {
                    trace(&case.rays, &times, q).map_err(|e| format!("trace failed: {e}"))
                });
            let hits = match traced {
                Ok(hits) => hits,
                Err(status) => {
                    rep.runs.push(RunReport { status, ..r });
                    continue;
                }
            };
            let r = RunReport {
                trace_ms: ms(t),
                ..r
            };
            let r = if cubic {
                let mut r = judge.evaluate(r, q, &hits, None);
                r.parity_mismatches = Some(cubic_parity(&judge, &mut r, q, &hits, &twin));
                r
            } else {
                judge.evaluate(r, q, &hits, Some(&twin))
            };
            rep.runs.push(against_brute(&judge, r, q, &hits, &brute));
        }
    }
}

/// The CPU layout's row of `q`: closest hits compared with the twin's (`twin`) bit for
/// bit, any hits on hit or miss, and every answer with the brute force's.
fn layout_row(
    judge: &Judge<'_>,
    layout: &CurveCpuBvh,
    q: Query,
    twin: &[Hit],
    brute: &[Hit],
) -> RunReport {
    let t = Instant::now();
    let hits = layout.trace_rays(&judge.case.rays, q);
    let r = RunReport {
        trace_ms: ms(t),
        ..row(CPU_LAYOUT_ROWS, q)
    };
    let r = match q {
        Query::Closest => judge.evaluate(r, q, &hits, Some(twin)),
        Query::Any => {
            let mut r = judge.evaluate(r, q, &hits, None);
            let differ = hits.iter().zip(twin).filter(|(a, b)| !same_verdict(a, b));
            r.parity_mismatches = Some(differ.count());
            r
        }
    };
    against_brute(judge, r, q, &hits, brute)
}

/// Counts the rays whose answer is not the brute force's (closest: bit for bit; any: hit
/// or miss alike) as determinate differences from it; every answer is compared.
fn against_brute(
    judge: &Judge<'_>,
    mut r: RunReport,
    q: Query,
    hits: &[Hit],
    brute: &[Hit],
) -> RunReport {
    let mut examples = Examples(std::mem::take(&mut r.examples));
    let alike = |h: &Hit, b: &Hit| match q {
        Query::Closest => hit_bits(h) == hit_bits(b),
        Query::Any => same_verdict(h, b),
    };
    let what = "differs from the brute force's";
    let n = judge.count_unlike(&mut examples, (hits, brute), what, alike);
    r.brute_mismatch.wrong += n;
    r.sample = hits.len();
    r.examples = examples.0;
    r
}

/// The rays on which a device's cubic-curve answers differ from the twin's beyond
/// [`cubic_alike`] (closest), or on hit or miss (any), with examples in `r`.
fn cubic_parity(
    judge: &Judge<'_>,
    r: &mut RunReport,
    q: Query,
    hits: &[Hit],
    twin: &[Hit],
) -> usize {
    let mut examples = Examples(std::mem::take(&mut r.examples));
    let alike = |g: &Hit, c: &Hit| match q {
        Query::Closest => cubic_alike(g, c),
        Query::Any => same_verdict(g, c),
    };
    let what = "GPU differs from the CPU twin's beyond the cubic rule";
    let n = judge.count_unlike(&mut examples, (hits, twin), what, alike);
    r.examples = examples.0;
    n
}
