//! The error-vs-time plot of `bvhtrace bench` (plotters; PNG and SVG).

use anyhow::{Result, anyhow};
use plotters::prelude::*;

use crate::bench_matrix::{RayKind, Row};
use crate::output::AtomicFile;

/// Where exact configurations (error 0) are drawn on the log axis.
const FLOOR: f64 = 1e-9;

/// Registers DejaVu Sans (from the system, `fonts-dejavu-core`) for the PNG's text.
/// Returns false when no font is found: the PNG is then drawn without text.
fn register_font() -> bool {
    const PATHS: [&str; 2] = [
        "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
        "/usr/share/fonts/TTF/DejaVuSans.ttf",
    ];
    static ONCE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ONCE.get_or_init(|| {
        PATHS.iter().any(|p| {
            std::fs::read(p).ok().is_some_and(|bytes| {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok()
            })
        })
    })
}

/// Indices of the rows on the Pareto front: no other row is both faster and more exact.
pub fn pareto(points: &[(f64, f64)]) -> Vec<usize> {
    (0..points.len())
        .filter(|&i| {
            !points.iter().enumerate().any(|(j, q)| {
                j != i
                    && q.0 <= points[i].0
                    && q.1 <= points[i].1
                    && (q.0 < points[i].0 || q.1 < points[i].1)
            })
        })
        .collect()
}

fn label(r: &Row) -> String {
    let c = &r.config;
    let b = if c.builder == "sah" && c.bins != 32 {
        format!("sah{}", c.bins)
    } else {
        c.builder.clone()
    };
    format!(
        "{b}/{}/{}/{}",
        c.traversal,
        c.backend,
        match c.precision.as_str() {
            "watertight-f32" => "wt",
            "moller-trumbore-f32" => "mt",
            "watertight-f64" => "wt64",
            other => other,
        }
    )
}

/// A plotting failure as this crate reports it.
pub(crate) fn plot_error<E: std::error::Error + Send + Sync>(
    e: DrawingAreaErrorKind<E>,
) -> anyhow::Error {
    anyhow!("plotting failed: {e}")
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    rows: &[Row],
    text: bool,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(plot_error)?;
    // x: nanoseconds per ray; y: the headline error.
    let pts: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| {
            (
                1e6 * r.trace_ms / r.ray_count.max(1) as f64,
                r.error.headline().max(FLOOR),
            )
        })
        .collect();
    let (xmin, xmax) = pts
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let ymax = pts.iter().fold(FLOOR * 10.0, |a, p| a.max(p.1));
    let mut chart = ChartBuilder::on(&root);
    chart.margin(20);
    if text {
        chart
            .caption(title, ("sans-serif", 20))
            .x_label_area_size(40)
            .y_label_area_size(70);
    }
    let mut chart = chart
        .build_cartesian_2d(
            (xmin * 0.8..xmax * 1.25)
                .log_scale()
                .with_key_points(one_two_five(xmin * 0.8, xmax * 1.25)),
            (FLOOR * 0.5..ymax * 2.0).log_scale(),
        )
        .map_err(plot_error)?;
    if text {
        chart
            .configure_mesh()
            .x_desc("trace time per ray (ns, median)")
            .x_label_formatter(&|x| format!("{x:.0}"))
            .y_desc("error vs f64 oracle (wrong-answer rate; else max rel. t error; floor = exact)")
            .draw()
            .map_err(plot_error)?;
    }
    let colour = |k: RayKind| match k {
        RayKind::Primary => BLUE,
        RayKind::Shadow => GREEN,
        RayKind::Diffuse => RED,
    };
    for (r, p) in rows.iter().zip(&pts) {
        let c = colour(r.config.rays);
        if r.config.backend != "cpu" {
            chart
                .draw_series(std::iter::once(TriangleMarker::new(*p, 6, c.filled())))
                .map_err(plot_error)?;
        } else {
            chart
                .draw_series(std::iter::once(Circle::new(*p, 4, c.filled())))
                .map_err(plot_error)?;
        }
    }
    // One Pareto front per ray kind: the kinds are different workloads.
    for kind in [RayKind::Primary, RayKind::Shadow, RayKind::Diffuse] {
        let ids: Vec<usize> = (0..rows.len())
            .filter(|&i| rows[i].config.rays == kind)
            .collect();
        let sub: Vec<(f64, f64)> = ids.iter().map(|&i| pts[i]).collect();
        let mut front: Vec<usize> = pareto(&sub).into_iter().map(|k| ids[k]).collect();
        front.sort_by(|&a, &b| pts[a].0.total_cmp(&pts[b].0));
        chart
            .draw_series(LineSeries::new(
                front.iter().map(|&i| pts[i]),
                colour(kind).stroke_width(2),
            ))
            .map_err(plot_error)?;
        if text {
            for &i in &front {
                chart
                    .draw_series(std::iter::once(Text::new(
                        format!(" {}", label(&rows[i])),
                        pts[i],
                        ("sans-serif", 12).into_font(),
                    )))
                    .map_err(plot_error)?;
            }
        }
    }
    if text {
        chart
            .draw_series(std::iter::once(Text::new(
                "exact (0 wrong, 0 t error)".to_string(),
                (xmin * 0.85, FLOOR * 0.75),
                ("sans-serif", 12).into_font(),
            )))
            .map_err(plot_error)?;
        chart
            .draw_series(std::iter::once(Text::new(
                "blue primary, green shadow, red diffuse; triangles GPU, circles CPU; lines = Pareto fronts, labelled".to_string(),
                (xmin * 0.85, ymax * 1.6),
                ("sans-serif", 12).into_font(),
            )))
            .map_err(plot_error)?;
    }
    root.present().map_err(plot_error)?;
    Ok(())
}

/// Writes the plot for one scene's rows as PNG and SVG.
pub fn error_vs_time(title: &str, rows: &[Row], png: AtomicFile, svg: AtomicFile) -> Result<()> {
    if rows.is_empty() {
        return Ok(());
    }
    write_png_and_svg(
        (1100, 750),
        png,
        svg,
        |area, text| draw(area, title, rows, text),
        |area| draw(area, title, rows, true),
    )
}

/// Writes one figure as a `w` x `h` PNG (with text where a font is found; a note says
/// so when none is) and as an SVG, drawn by `png_draw` and `svg_draw` (the same drawing
/// on the two backends).
pub(crate) fn write_png_and_svg(
    (w, h): (u32, u32),
    png: AtomicFile,
    svg: AtomicFile,
    png_draw: impl FnOnce(DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>, bool) -> Result<()>,
    svg_draw: impl FnOnce(DrawingArea<SVGBackend<'_>, plotters::coord::Shift>) -> Result<()>,
) -> Result<()> {
    {
        let text = register_font();
        if !text {
            eprintln!(
                "note: no DejaVu Sans font found (apt-get install fonts-dejavu-core): the PNG plot has no text; the SVG has"
            );
        }
        let mut buf = vec![0u8; (w * h * 3) as usize];
        png_draw(
            BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area(),
            text,
        )?;
        crate::output::write_png(png, w, h, buf)?;
    }
    let mut s = String::new();
    svg_draw(SVGBackend::with_string(&mut s, (w, h)).into_drawing_area())?;
    svg.finish_with_bytes(s.as_bytes())
}

/// The 1-2-5 values of each decade within `lo..=hi`: the time axis's marks. plotters' own
/// marks for a log axis start at the first power of ten in the range (none left of it),
/// with nine a decade that run into each other ("900.0" on "1000.0").
pub(crate) fn one_two_five(lo: f64, hi: f64) -> Vec<f64> {
    let mut marks = Vec::new();
    if !(lo > 0.0 && hi.is_finite()) {
        return marks;
    }
    let mut decade = 10f64.powf(lo.log10().floor());
    while decade <= hi {
        for m in [1.0, 2.0, 5.0] {
            let v = decade * m;
            if (lo..=hi).contains(&v) {
                marks.push(v);
            }
        }
        decade *= 10.0;
    }
    marks
}

#[cfg(test)]
mod tests {
    #[test]
    fn pareto_front_keeps_only_undominated_points() {
        let pts = [
            (1.0, 5.0),
            (2.0, 1.0),
            (3.0, 1.0),
            (0.5, 10.0),
            (2.0, 3.0),
            (4.0, 0.5),
        ];
        assert_eq!(super::pareto(&pts), vec![0, 1, 3, 5]);
    }

    #[test]
    fn time_marks_are_one_two_five_from_the_left_end() {
        assert_eq!(
            super::one_two_five(80.0, 1400.0),
            vec![100.0, 200.0, 500.0, 1000.0]
        );
        assert_eq!(
            super::one_two_five(230.0, 4100.0),
            vec![500.0, 1000.0, 2000.0]
        );
        assert!(super::one_two_five(0.0, 10.0).is_empty());
        assert!(super::one_two_five(f64::NAN, 10.0).is_empty());
    }
}
