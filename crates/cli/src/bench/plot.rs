//! What the plots of `bvhtrace bench` and `bench --converge` share (plotters; PNG and SVG):
//! the font, the two files of a figure, the marks of a log axis, the Pareto front, the error.

use anyhow::{Result, anyhow};
use plotters::prelude::*;

use crate::output::AtomicFile;

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

/// A plotting failure as this crate reports it.
pub(crate) fn plot_error<E: std::error::Error + Send + Sync>(
    e: DrawingAreaErrorKind<E>,
) -> anyhow::Error {
    anyhow!("plotting failed: {e}")
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
