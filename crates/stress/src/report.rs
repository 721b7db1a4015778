//! The text table: one row per case x backend x traversal (closest and any-hit together).

use std::fmt::Write;

use crate::runner::{CaseReport, Differences, PrecisionRow, RunReport};

fn wi(d: &Differences) -> String {
    format!("{}/{}", d.wrong, d.indeterminate)
}

fn sci(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else {
        format!("{x:.1e}")
    }
}

/// The column headings (and a rule under them). `a/b` columns are `wrong/f32-indeterminate`.
pub fn table_header() -> String {
    let h = format!(
        "{:<24} {:<9} {:<15} {:>7} {:>6} {:>6} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8} {:>5} {:>5} {:>4} {:>6} {:>13} {:>9} {:>8} {:>9}",
        "case",
        "backend",
        "traversal",
        "rays",
        "sample",
        "escape",
        "fmiss",
        "fhit",
        "wprim",
        "brute",
        "t-rel-md",
        "t-rel-mx",
        "known",
        "inval",
        "NaN",
        "parity",
        "self-hit 0/off",
        "any fm/fh",
        "build-ms",
        "trace-ms"
    );
    let rule = "-".repeat(h.len());
    format!("{h}\n{rule}")
}

fn row(case: &CaseReport, c: &RunReport, any: Option<&RunReport>) -> String {
    if c.status != "ok" {
        return format!(
            "{:<24} {:<9} {:<15} {}",
            case.name, c.backend, c.traversal, c.status
        );
    }
    let self_hits = if c.secondary_plain + c.secondary_offset > 0 {
        format!(
            "{}/{} {}/{}",
            c.self_hits_plain, c.secondary_plain, c.self_hits_offset, c.secondary_offset
        )
    } else {
        "-".into()
    };
    let any = match any {
        Some(a) if a.status == "ok" => format!("{} {}", wi(&a.false_misses), wi(&a.false_hits)),
        Some(a) => a.status.chars().take(9).collect(),
        None => "-".into(),
    };
    let escapes = if c.must_hit > 0 {
        let a = any_escapes(case, c);
        wi(&Differences {
            wrong: c.escapes.wrong + a.wrong,
            indeterminate: c.escapes.indeterminate + a.indeterminate,
        })
    } else {
        "-".into()
    };
    format!(
        "{:<24} {:<9} {:<15} {:>7} {:>6} {:>6} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8} {:>5} {:>5} {:>4} {:>6} {:>13} {:>9} {:>8.1} {:>9.1}",
        case.name,
        c.backend,
        c.traversal,
        c.rays,
        c.sample,
        escapes,
        wi(&c.false_misses),
        wi(&c.false_hits),
        wi(&c.wrong_prim),
        wi(&c.brute_mismatch),
        sci(c.t_rel_median),
        sci(c.t_rel_max),
        if c.known > 0 {
            format!("{}", c.known_wrong)
        } else {
            "-".into()
        },
        c.invalid_flagged,
        c.nan_outputs,
        c.parity_mismatches.map_or("-".into(), |p| p.to_string()),
        self_hits,
        any,
        case.build_ms,
        c.trace_ms
    )
}

/// Escapes of the any-hit run matching `closest` (same backend and traversal).
fn any_escapes(case: &CaseReport, closest: &RunReport) -> Differences {
    case.runs
        .iter()
        .find(|r| {
            r.query == "any" && r.backend == closest.backend && r.traversal == closest.traversal
        })
        .map_or(Differences::default(), |r| r.escapes)
}

/// The rows of one case, then its notes: input fidelity, depth, the full-stack upload,
/// precision-limit thresholds, and a few failing rays of any run that is not clean.
pub fn table_rows(case: &CaseReport) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(e) = case.error.as_ref().or(case.skipped.as_ref()) {
        out.push(format!("{:<24} {e}", case.name));
    }
    for c in case.runs.iter().filter(|r| r.query == "closest") {
        let any = case
            .runs
            .iter()
            .find(|r| r.query == "any" && r.backend == c.backend && r.traversal == c.traversal);
        out.push(row(case, c, any));
    }
    let mut notes = Vec::new();
    notes.push(format!(
        "{} triangles, {} rays ({} compared with the f64 oracle and the f32 brute force, {:.0} ms), BVH depth {}, {} nodes; input {}{}{}",
        case.triangles,
        case.rays,
        case.oracle_sample,
        case.oracle_ms,
        case.depth,
        case.nodes,
        if case.input.exact { "exact" } else { "rounded" },
        if case.input.merged_vertices > 0 {
            format!(", {} vertices merged", case.input.merged_vertices)
        } else {
            String::new()
        },
        if case.input.zero_area_triangles > 0 {
            format!(", {} zero-area triangles", case.input.zero_area_triangles)
        } else {
            String::new()
        },
    ));
    for (backend, what) in &case.full_stack {
        notes.push(format!("{backend} full-stack upload: {what}"));
    }
    let zero_area_hits: usize = case
        .runs
        .iter()
        .map(|r| r.zero_area_hits)
        .max()
        .unwrap_or(0);
    if zero_area_hits > 0 {
        notes.push(format!(
            "hits on zero-area triangles (most in one run): {zero_area_hits}"
        ));
    }
    let incomplete: u64 = case
        .runs
        .iter()
        .filter_map(|r| r.gpu_incomplete)
        .max()
        .unwrap_or(0);
    if incomplete > 0 {
        notes.push(format!(
            "GPU rays over the driver's loop-trip budget, finished on the CPU twin (most in one run): {incomplete}"
        ));
    }
    let phantom: usize = case.runs.iter().map(|r| r.phantom_hits).max().unwrap_or(0);
    if phantom > 0 {
        notes.push(format!(
            "phantom hits (hit point off its triangle's box; most in one run): {phantom}"
        ));
    }
    let beyond: usize = case
        .runs
        .iter()
        .map(|r| r.t_beyond_bound)
        .max()
        .unwrap_or(0);
    if beyond > 0 {
        notes.push(format!("same-primitive hits with a t error beyond f32_t_error_bound (most in one run): {beyond}"));
    }
    notes.extend(case.notes.iter().cloned());
    if let Some(r) = case.runs.iter().find(|r| !r.precision.is_empty()) {
        notes.extend(precision_summary(&r.precision));
    }
    if !case.guaranteed {
        notes.push("beyond the guaranteed range: accuracy measured, not required".into());
    }
    for r in case.runs.iter().filter(|r| {
        if case.guaranteed {
            !r.clean()
        } else {
            !r.sound()
        }
    }) {
        for e in &r.examples {
            notes.push(format!("{} {} {}: {e}", r.backend, r.traversal, r.query));
        }
    }
    for n in notes {
        out.push(format!("    {n}"));
    }
    out
}

fn first_offset(rows: &[&PrecisionRow], f: impl Fn(&PrecisionRow) -> bool) -> String {
    rows.iter()
        .find(|r| f(r))
        .map_or("never (to 1e8)".into(), |r| format!("{:.3e}", r.offset))
}

/// ulp of an f32 near `x`.
pub(crate) fn ulp(x: f64) -> f64 {
    let f = x as f32;
    (f32::from_bits(f.to_bits() + 1) - f) as f64
}

/// One line per gap and ray origin: the first offset at which the input merged, the
/// traversal hit the wrong surface, and the traversal disagreed with the oracle.
pub fn precision_summary(rows: &[PrecisionRow]) -> Vec<String> {
    let mut gaps: Vec<f64> = rows.iter().map(|r| r.gap).collect();
    gaps.sort_by(|a, b| b.total_cmp(a));
    gaps.dedup();
    let mut out = Vec::new();
    for g in gaps {
        for far in [false, true] {
            let rs: Vec<&PrecisionRow> =
                rows.iter().filter(|r| r.gap == g && r.far == far).collect();
            let merged = first_offset(&rs, |r| r.input_merged > 0);
            let all_merged = first_offset(&rs, |r| r.rays > 0 && r.input_merged == r.rays);
            let wrong = first_offset(&rs, |r| r.traced_wrong_surface > 0);
            let vs = first_offset(&rs, |r| r.traced_vs_oracle.wrong > 0);
            let lost = rs.iter().filter(|r| r.rays == 0).count();
            let mut s = format!(
                "precision gap {g:.0e} {}: input merged (oracle on the f32 input hits the wrong surface) from offset {merged} (every ray from {all_merged}); traversal on the wrong surface from {wrong}; traversal != oracle (determinate) from {vs}",
                if far {
                    "far (rays from `offset` away)"
                } else {
                    "near (rays from 1 away)"
                },
            );
            if let Some(r) = rs.iter().find(|r| r.input_merged > 0) {
                let _ = write!(s, "; ulp(f32) there {:.1e}", ulp(r.offset));
            }
            if lost > 0 {
                let _ = write!(s, "; {lost} offsets without an intended hit");
            }
            out.push(s);
        }
    }
    out
}

/// The whole table for these reports.
pub fn format_table(reports: &[CaseReport]) -> String {
    let mut s = table_header();
    s.push('\n');
    for r in reports {
        for line in table_rows(r) {
            s.push_str(&line);
            s.push('\n');
        }
    }
    s
}
