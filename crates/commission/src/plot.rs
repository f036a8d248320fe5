//! The one way the commissioning tools draw charts: an SVG canvas, captioned panels
//! with labelled axes, line, dot and segment series with legend entries, and the
//! legend box. The tools (and the root package's scenario) say what to draw; the
//! plotting library stays behind this module, so its setup and its error type live in
//! one place. [`svg`] ties a drawing error to its file.

use std::ops::Range;
use std::path::Path;

use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

pub use plotters::chart::SeriesLabelPosition;
pub use plotters::style::colors::{BLACK, BLUE, RED, WHITE};
pub use plotters::style::{Color, Palette, Palette99, RGBAColor, RGBColor, ShapeStyle};

/// A drawing step failed; the message is the plotting library's. [`svg`] ties it to
/// its file as a [`PlotError`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct DrawError(pub String);

fn fail(e: impl std::fmt::Display) -> DrawError {
    DrawError(e.to_string())
}

/// Drawing or writing an SVG file failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{path}: {message}")]
pub struct PlotError {
    /// The SVG file.
    pub path: String,
    /// What went wrong.
    pub message: String,
}

/// A drawing area of an SVG file (the whole canvas or a panel of it).
pub type Area<'p> = DrawingArea<SVGBackend<'p>, Shift>;

/// A panel with f64 axes on an [`Area`].
pub type Chart<'a, 'p> =
    ChartContext<'a, SVGBackend<'p>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Draws an SVG of `size_px` (width, height) on a white canvas and writes it to
/// `path`, whole ([`compgate_core::outputs::write`]): a failed drawing leaves the
/// file as it was.
pub fn svg(
    path: &Path,
    size_px: (u32, u32),
    draw: impl FnOnce(&Area<'_>) -> Result<(), DrawError>,
) -> Result<(), PlotError> {
    render(size_px, draw)
        .and_then(|text| compgate_core::outputs::write(path, &text).map_err(fail))
        .map_err(|DrawError(message)| PlotError {
            path: path.display().to_string(),
            message,
        })
}

/// The SVG text [`svg`] would write, for a command that stages its files and writes
/// them together.
pub fn render(
    size_px: (u32, u32),
    draw: impl FnOnce(&Area<'_>) -> Result<(), DrawError>,
) -> Result<String, DrawError> {
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, size_px).into_drawing_area();
        root.fill(&WHITE)
            .map_err(fail)
            .and_then(|()| draw(&root))
            .and_then(|()| root.present().map_err(fail))?;
    }
    Ok(text)
}

/// How a panel is framed: caption, axis descriptions, margins. The defaults are
/// those most charts use; the builder methods change the rest.
#[derive(Debug, Clone)]
pub struct Frame {
    caption: Option<(String, u32)>,
    x_desc: String,
    y_desc: String,
    margin_px: u32,
    x_label_px: u32,
    y_label_px: u32,
}

impl Frame {
    /// A panel with these axis descriptions, no caption, a 10 px margin and label
    /// areas of 30 px (x) and 60 px (y).
    pub fn new(x_desc: impl Into<String>, y_desc: impl Into<String>) -> Self {
        Self {
            caption: None,
            x_desc: x_desc.into(),
            y_desc: y_desc.into(),
            margin_px: 10,
            x_label_px: 30,
            y_label_px: 60,
        }
    }

    /// The caption above the panel, in a sans-serif font of `font_px`.
    pub fn caption(mut self, text: impl Into<String>, font_px: u32) -> Self {
        self.caption = Some((text.into(), font_px));
        self
    }

    /// The margin around the panel.
    pub fn margin(mut self, px: u32) -> Self {
        self.margin_px = px;
        self
    }

    /// The sizes of the x and y label areas.
    pub fn label_areas(mut self, x_px: u32, y_px: u32) -> Self {
        self.x_label_px = x_px;
        self.y_label_px = y_px;
        self
    }

    /// Draws the frame and its mesh on `area` over the given ranges.
    pub fn draw<'a, 'p>(
        &self,
        area: &'a Area<'p>,
        x: Range<f64>,
        y: Range<f64>,
    ) -> Result<Chart<'a, 'p>, DrawError> {
        let (x, y) = (usable(x), usable(y));
        let mut builder = ChartBuilder::on(area);
        if let Some((text, font_px)) = &self.caption {
            builder.caption(text, ("sans-serif", *font_px));
        }
        let mut chart = builder
            .margin(self.margin_px)
            .x_label_area_size(self.x_label_px)
            .y_label_area_size(self.y_label_px)
            .build_cartesian_2d(x, y)
            .map_err(fail)?;
        chart
            .configure_mesh()
            .x_desc(self.x_desc.as_str())
            .y_desc(self.y_desc.as_str())
            .draw()
            .map_err(fail)?;
        Ok(chart)
    }
}

/// `r` if it is finite and not empty, else a unit range around what is finite of it:
/// the plotting library's tick search never ends on an infinite range (an empty
/// series' extent) and divides by zero on an empty one.
fn usable(r: Range<f64>) -> Range<f64> {
    match (r.start.is_finite(), r.end.is_finite()) {
        (true, true) if r.start < r.end => r,
        (true, _) => r.start..r.start + 1.0,
        (false, true) => r.end - 1.0..r.end,
        (false, false) => 0.0..1.0,
    }
}

/// A polyline; with a label it gets a legend entry in its own style.
pub fn line(
    chart: &mut Chart<'_, '_>,
    points: impl IntoIterator<Item = (f64, f64)>,
    style: impl Into<ShapeStyle>,
    label: Option<String>,
) -> Result<(), DrawError> {
    let style = style.into();
    let anno = chart
        .draw_series(LineSeries::new(points, style))
        .map_err(fail)?;
    if let Some(label) = label {
        anno.label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
    }
    Ok(())
}

/// A dot of `radius_px` at every point.
pub fn dots(
    chart: &mut Chart<'_, '_>,
    points: impl IntoIterator<Item = (f64, f64)>,
    radius_px: u32,
    style: impl Into<ShapeStyle>,
) -> Result<(), DrawError> {
    let style = style.into();
    chart
        .draw_series(points.into_iter().map(|p| Circle::new(p, radius_px, style)))
        .map_err(fail)?;
    Ok(())
}

/// One straight segment from `a` to `b`.
pub fn segment(
    chart: &mut Chart<'_, '_>,
    a: (f64, f64),
    b: (f64, f64),
    style: impl Into<ShapeStyle>,
) -> Result<(), DrawError> {
    let style = style.into();
    chart
        .draw_series(std::iter::once(PathElement::new(vec![a, b], style)))
        .map_err(fail)?;
    Ok(())
}

/// Text whose lower right corner sits at `at` (so a note at a panel's right edge
/// stays inside).
pub fn note(
    chart: &mut Chart<'_, '_>,
    text: String,
    at: (f64, f64),
    font_px: u32,
) -> Result<(), DrawError> {
    let style = TextStyle::from(("sans-serif", font_px).into_font())
        .pos(Pos::new(HPos::Right, VPos::Bottom));
    chart
        .draw_series(std::iter::once(Text::new(text, at, style)))
        .map_err(fail)?;
    Ok(())
}

/// Filled rectangles, each from one corner to the opposite one.
pub fn cells(
    chart: &mut Chart<'_, '_>,
    cells: impl IntoIterator<Item = ((f64, f64), (f64, f64), RGBColor)>,
) -> Result<(), DrawError> {
    chart
        .draw_series(
            cells
                .into_iter()
                .map(|(a, b, color)| Rectangle::new([a, b], color.filled())),
        )
        .map_err(fail)?;
    Ok(())
}

/// The legend of the labelled series, on a translucent white box with a black border.
pub fn legend<'a, 'p: 'a>(
    chart: &mut Chart<'a, 'p>,
    position: SeriesLabelPosition,
) -> Result<(), DrawError> {
    chart
        .configure_series_labels()
        .position(position)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(fail)
}

/// Smallest and largest finite value; `None` without one.
pub fn extent(values: impl IntoIterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values
        .into_iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    (lo <= hi).then_some((lo, hi))
}

/// An axis range around `values`: their extent widened by `fraction` of its span on
/// either side, by at least `min_pad`; `fallback` without a finite value.
pub fn padded(
    values: impl IntoIterator<Item = f64>,
    fraction: f64,
    min_pad: f64,
    fallback: (f64, f64),
) -> Range<f64> {
    let (lo, hi) = extent(values).unwrap_or(fallback);
    let pad = ((hi - lo) * fraction).max(min_pad);
    (lo - pad)..(hi + pad)
}

/// A colour from blue (`f` = 0) to red (`f` = 1) with a fixed green part.
pub fn blue_to_red(f: f64, green: u8) -> RGBColor {
    let f = f.clamp(0.0, 1.0);
    RGBColor((255.0 * f) as u8, green, (255.0 * (1.0 - f)) as u8)
}

/// At most `max` evenly spread indices of `0..n`: a plot of 100k rows stays a file a
/// browser opens.
pub fn thin(n: usize, max: usize) -> Vec<usize> {
    let step = n.div_ceil(max).max(1);
    (0..n).step_by(step).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_pad_and_fall_back() {
        assert_eq!(extent([3.0, f64::NAN, -1.0]), Some((-1.0, 3.0)));
        assert_eq!(extent([f64::NAN]), None);
        assert_eq!(padded([0.0, 10.0], 0.1, 0.5, (-1.0, 1.0)), -1.0..11.0);
        assert_eq!(padded([2.0], 0.1, 0.5, (-1.0, 1.0)), 1.5..2.5);
        assert_eq!(padded([], 0.1, 0.5, (-1.0, 1.0)), -1.5..1.5);
    }

    #[test]
    fn writes_a_valid_svg_with_every_series() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("chart.svg");
        svg(&path, (400, 300), |root| {
            let (upper, lower) = root.split_vertically(150);
            let mut chart = Frame::new("x (mm)", "y (um)").caption("upper", 14).draw(
                &upper,
                0.0..10.0,
                -1.0..1.0,
            )?;
            line(
                &mut chart,
                [(0.0, 0.0), (10.0, 0.5)],
                RED,
                Some("one".into()),
            )?;
            dots(&mut chart, [(5.0, 0.2)], 2, BLUE.filled())?;
            segment(&mut chart, (1.0, 0.1), (2.0, 0.1), BLACK.stroke_width(3))?;
            note(&mut chart, "a note".into(), (9.0, 0.5), 12)?;
            legend(&mut chart, SeriesLabelPosition::UpperLeft)?;
            let mut low = Frame::new("x", "y").draw(&lower, 0.0..1.0, 0.0..1.0)?;
            cells(&mut low, [((0.0, 0.0), (0.5, 0.5), blue_to_red(0.5, 64))])
        })
        .expect("svg");
        let svg = std::fs::read_to_string(&path).expect("read");
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        for text in [
            "upper",
            "x (mm)",
            "one",
            "a note",
            "<polyline",
            "<circle",
            "<rect",
        ] {
            assert!(svg.contains(text), "{text} missing");
        }
    }

    /// An empty series' extent (inf..inf) made the mesh's tick search loop for ever.
    #[test]
    fn a_panel_over_an_infinite_or_empty_range_is_drawn() {
        for (x, y) in [
            (f64::INFINITY..f64::INFINITY, 0.0..1.0),
            (f64::INFINITY..f64::NEG_INFINITY, f64::NAN..f64::NAN),
            (5.0..5.0, -1.0..f64::INFINITY),
        ] {
            let text = render((300, 200), |root| {
                let mut chart = Frame::new("x", "y").draw(root, x.clone(), y.clone())?;
                line(&mut chart, Vec::new(), RED, Some("none".into()))?;
                legend(&mut chart, SeriesLabelPosition::UpperLeft)
            })
            .expect("drawn");
            assert!(text.trim_end().ends_with("</svg>"), "{x:?} {y:?}");
        }
        assert_eq!(usable(f64::INFINITY..f64::INFINITY), 0.0..1.0);
        assert_eq!(usable(2.0..1.0), 2.0..3.0);
    }

    #[test]
    fn a_failed_write_names_its_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("no-such-dir").join("chart.svg");
        let e = svg(&path, (10, 10), |_| Ok(())).expect_err("no directory");
        assert_eq!(e.path, path.display().to_string());
        assert!(e.to_string().starts_with(&e.path), "{e}");
    }
}
