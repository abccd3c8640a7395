//! Line, scatter and grouped-bar plots rendered to PNG with [`plotters`] (bitmap backend) and an
//! embedded font, so no system fonts are needed.
//!
//! Plotters does the charting: `ChartBuilder` lays out the plot area and its label areas,
//! `configure_mesh` draws the grid, axes, ticks (1-2-5 steps), tick labels and axis labels,
//! `log_scale()` maps logarithmic axes, `ErrorBar` draws error bars and `configure_series_labels`
//! the legend. This module adds only what plotters lacks, each part saying why where it is: axis
//! ranges fitted to the data, tick labels written alike along an axis, log ticks on a range
//! holding fewer than two powers of ten, lines clipped at the plot area, and a legend placed where
//! it covers no data (a free corner, else a band above the plot area).
//!
//! Text is DejaVu Sans (`assets/DejaVuSans.ttf`, Bitstream Vera licence next to it), drawn by
//! plotters' `ab_glyph` font backend at a size that grows with the image. Non-finite points (and
//! points <= 0 on a logarithmic axis) are skipped and break a line, as in common plotting
//! libraries; a single point, equal values or no data at all render an ordinary frame rather than
//! failing.
//!
//! ```
//! use veila_data::vis::plot::{Plot, Series, SeriesStyle};
//!
//! let plot = Plot {
//!     title: "Denoiser loss".into(),
//!     x_label: "step".into(),
//!     y_label: "loss".into(),
//!     series: vec![
//!         Series::new("train", (1..=50).map(|i| (i as f64, 1.0 / i as f64)).collect(), SeriesStyle::Line),
//!         Series::new("val", vec![(10.0, 0.12), (20.0, 0.07), (40.0, 0.04)], SeriesStyle::LineMarkers)
//!             .with_error_bars(vec![0.02, 0.01, 0.01]),
//!     ],
//!     y_log: true,
//!     ..Plot::default()
//! };
//! let img = plot.render(640, 400);
//! assert_eq!(img.dimensions(), (640, 400));
//! let png: Vec<u8> = plot.to_png(640, 400)?; // or plot.write_png(path, 640, 400)
//! assert_eq!(&png[1..4], b"PNG");
//! # Ok::<(), veila_data::Error>(())
//! ```

use std::path::Path;

use image::{Rgb, RgbImage};
use plotters::backend::BitMapBackend;
use plotters::chart::{ChartBuilder, ChartContext, SeriesLabelPosition};
use plotters::coord::Shift;
use plotters::coord::cartesian::Cartesian2d;
use plotters::coord::combinators::{BindKeyPoints, IntoLogRange, LogCoord, WithKeyPoints};
use plotters::coord::ranged1d::{BoldPoints, LightPoints, Ranged, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::data::float::pretty_print_float;
use plotters::drawing::{DrawingArea, IntoDrawingArea};
use plotters::element::{
    EmptyElement, ErrorBar, MultiLineText, PathElement, Polygon, Rectangle, Text,
};
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{Color, FontDesc, FontStyle, IntoFont, RGBColor, TextStyle};

use crate::{Error, Result};

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SeriesStyle {
    /// Points joined by a line.
    #[default]
    Line,
    /// Markers only (scatter plot).
    Markers,
    /// A line with a marker at every point.
    LineMarkers,
}

/// One data series of a [`Plot`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Series {
    /// Legend entry; an empty name leaves the series out of the legend.
    pub name: String,
    /// `(x, y)` points in drawing order. Non-finite points are skipped and break the line.
    pub points: Vec<(f64, f64)>,
    /// Line, markers or both.
    pub style: SeriesStyle,
    /// Symmetric vertical error bar half-lengths, one per point (`y - e ..= y + e`); non-finite
    /// entries draw no bar. [`Plot::validate`] checks the length; drawing uses the entries present.
    pub error_bars: Option<Vec<f64>>,
}

impl Series {
    /// A series without error bars.
    pub fn new(name: impl Into<String>, points: Vec<(f64, f64)>, style: SeriesStyle) -> Self {
        Series {
            name: name.into(),
            points,
            style,
            error_bars: None,
        }
    }

    /// The same series with vertical error bars (half-lengths, one per point).
    pub fn with_error_bars(mut self, half_lengths: Vec<f64>) -> Self {
        self.error_bars = Some(half_lengths);
        self
    }
}

/// A line / scatter plot. Fields are public; [`Plot::default`] gives an empty, linear plot.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Plot {
    /// Title above the plot (empty: none).
    pub title: String,
    /// Label under the x axis (empty: none).
    pub x_label: String,
    /// Label left of the y axis, drawn vertically (empty: none).
    pub y_label: String,
    /// Logarithmic x axis (points with x <= 0 are skipped).
    pub x_log: bool,
    /// Logarithmic y axis (points with y <= 0 are skipped).
    pub y_log: bool,
    /// Fixed x range `(lo, hi)`; `None` (or an unusable range) fits the data with a 4 % margin.
    pub x_range: Option<(f64, f64)>,
    /// Fixed y range `(lo, hi)`; `None` (or an unusable range) fits the data with a 4 % margin.
    pub y_range: Option<(f64, f64)>,
    /// The data.
    pub series: Vec<Series>,
}

/// One group of bars of a [`BarChart`] (e.g. one model variant): one value per category.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BarGroup {
    /// Legend entry.
    pub name: String,
    /// Bar heights, one per category; non-finite values draw no bar.
    pub values: Vec<f64>,
    /// Symmetric error bar half-lengths, one per category.
    pub errors: Option<Vec<f64>>,
}

/// A grouped bar chart: categories along x, one bar per group within each category (e.g. metrics
/// as categories and model variants as groups).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BarChart {
    /// Title above the chart (empty: none).
    pub title: String,
    /// Label left of the value axis (empty: none).
    pub y_label: String,
    /// Category names along x.
    pub categories: Vec<String>,
    /// The groups, each with one value per category.
    pub groups: Vec<BarGroup>,
}

/// Series colours (the Okabe-Ito colour-blind-safe set with yellow replaced by brown, reordered);
/// series `i` uses `PALETTE[i % 8]` and a marker shape that cycles with a different period, so
/// series stay distinguishable in grey-scale print too.
pub const PALETTE: [[u8; 3]; 8] = [
    [0, 114, 178],
    [213, 94, 0],
    [0, 158, 115],
    [204, 121, 167],
    [230, 159, 0],
    [86, 180, 233],
    [64, 64, 64],
    [140, 86, 75],
];

/// The colour of series (or bar group) `i`.
pub fn series_color(i: usize) -> Rgb<u8> {
    Rgb(PALETTE[i % PALETTE.len()])
}

const BACKGROUND: [u8; 3] = [255, 255, 255];
const GRID: [u8; 3] = [229, 229, 229];
const MINOR_GRID: [u8; 3] = [243, 243, 243];
const FRAME: [u8; 3] = [90, 90, 90];
const TEXT: [u8; 3] = [34, 34, 34];
const ERROR_BAR: [u8; 3] = [40, 40, 40];
const LEGEND_BORDER: [u8; 3] = [200, 200, 200];

fn rgb(c: [u8; 3]) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

// ------------------------------------------------------------------------------------------------
// axes

/// A data axis: the value range shown and whether it is logarithmic.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Axis {
    /// Value at the low end (left or bottom).
    pub lo: f64,
    /// Value at the high end (right or top).
    pub hi: f64,
    /// Logarithmic scale.
    pub log: bool,
}

impl Axis {
    /// Position of `v` along the axis, 0 at `lo` and 1 at `hi` (outside [0, 1] beyond the range);
    /// `None` for non-finite values and, on a logarithmic axis, values <= 0.
    pub fn fraction(&self, v: f64) -> Option<f64> {
        let f = match self.log {
            true if v <= 0.0 => return None,
            true => (v.log10() - self.lo.log10()) / (self.hi.log10() - self.lo.log10()),
            false => (v - self.lo) / (self.hi - self.lo),
        };
        f.is_finite().then_some(f)
    }

    /// The value at fraction `f` (the inverse of [`Axis::fraction`]).
    fn value(&self, f: f64) -> f64 {
        match self.log {
            true => 10f64.powf(self.lo.log10() + f * (self.hi.log10() - self.lo.log10())),
            false => self.lo + f * (self.hi - self.lo),
        }
    }

    /// Whether plotters can draw `lo..hi`: its tick search steps through the span, so the span
    /// must be finite and not vanish next to the values (on a log axis: in decades, `lo > 0`).
    fn usable(lo: f64, hi: f64, log: bool) -> bool {
        let (a, b) = if log {
            (lo.log10(), hi.log10())
        } else {
            (lo, hi)
        };
        let span = b - a;
        (!log || lo > 0.0)
            && span.is_finite()
            && span > 1e-12 * a.abs().max(b.abs())
            && span > 1e-200
    }

    /// `fixed` where usable, else the range of `values` with a 4 % margin (in decades on a log
    /// axis) or a window around a single value: plotters takes a range, fitting it is ours.
    fn fit(values: impl Iterator<Item = f64>, log: bool, fixed: Option<(f64, f64)>) -> Axis {
        let (lo, hi) = match fixed {
            Some((lo, hi)) if Axis::usable(lo, hi, log) => (lo, hi),
            _ => {
                let t = |v: f64| if log { v.log10() } else { v };
                let kept = values
                    .filter(|v| v.is_finite() && (!log || *v > 0.0))
                    .map(t);
                let (lo, hi) = kept.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                    (lo.min(v), hi.max(v))
                });
                let (c, span) = (0.5 * lo + 0.5 * hi, hi - lo);
                let (lo, hi) = if lo > hi {
                    (f64::NAN, f64::NAN) // no data: the plain frame below
                } else if span <= 1e-12 * lo.abs().max(hi.abs()) {
                    // one value (or a range too narrow to show): a window around it
                    let d = match (log, c == 0.0) {
                        (true, _) => 0.5,
                        (false, true) => 1.0,
                        (false, false) => 0.1 * c.abs(),
                    };
                    (c - d, c + d)
                } else {
                    (lo - 0.04 * span, hi + 0.04 * span)
                };
                let v = |t: f64| if log { 10f64.powf(t) } else { t };
                (v(lo), v(hi))
            }
        };
        match (Axis::usable(lo, hi, log), log) {
            (true, _) => Axis { lo, hi, log },
            // no data, or values at the very ends of the floating-point range: a plain frame
            (false, false) => Axis {
                lo: 0.0,
                hi: 1.0,
                log,
            },
            (false, true) => Axis {
                lo: 1.0,
                hi: 10.0,
                log,
            },
        }
    }

    /// At most about `n` major ticks with their labels. Plotters picks them (1-2-5 steps; powers
    /// of ten on a log axis), except on a log range holding fewer than two powers of ten, where
    /// plotters finds one tick or none: there 1-2-5 multiples of powers of ten, or linear ticks.
    fn ticks(&self, n: usize) -> Vec<(f64, String)> {
        let linear = || RangedCoordf64::from(self.lo..self.hi).key_points(BoldPoints(n));
        let ticks = match self.log {
            false => linear(),
            true => {
                let decades = self.log_coord().key_points(BoldPoints(n));
                let (e0, e1) = (
                    self.lo.log10().floor() as i32,
                    self.hi.log10().ceil() as i32,
                );
                let steps = (e0..=e1).flat_map(|e| [1.0, 2.0, 5.0].map(|m| m * 10f64.powi(e)));
                let steps: Vec<f64> = steps.filter(|v| (self.lo..=self.hi).contains(v)).collect();
                if decades.len() >= 2 {
                    decades
                } else if (2..=n.max(2)).contains(&steps.len()) {
                    steps
                } else {
                    linear()
                }
            }
        };
        let format = LabelFormat::of(&ticks, self.log);
        ticks.into_iter().map(|t| (t, format.label(t))).collect()
    }

    /// Plotters' log coordinate for choosing ticks, a hair wider than the axis: plotters' decade
    /// search loses a power of ten at either end to rounding (log10 0.001 = -2.9999999999999996).
    fn log_coord(&self) -> LogCoord<f64> {
        let (lo, hi) = (self.lo * (1.0 - 1e-9), self.hi * (1.0 + 1e-9));
        (lo..hi).log_scale().into()
    }

    /// Plotters' log scale with this axis' ticks for hint `n` and its minor grid (plotters' light
    /// points: the multiples of each power of ten).
    fn log_scale(self, n: usize) -> WithKeyPoints<LogCoord<f64>> {
        let ticks = self.ticks(n).into_iter().map(|t| t.0).collect();
        let minor = self.log_coord().key_points(LightPoints::new(n, 10 * n));
        (self.lo..self.hi)
            .log_scale()
            .with_key_points(ticks)
            .with_light_points(minor)
    }
}

/// How an axis writes its tick labels. Plotters formats each value on its own (20000 as
/// "20000.0", 5e-6 as "0.00001"); these share their decimals and notation along a linear axis.
#[derive(Debug, Clone, Copy, PartialEq)]
enum LabelFormat {
    /// Fixed-point with this many decimals.
    Fixed(usize),
    /// `2.5e-5` (very large or very small values).
    Scientific,
    /// Each value on its own: plain from 0.001 to 10000, scientific otherwise.
    Log,
}

impl LabelFormat {
    fn of(ticks: &[f64], log: bool) -> LabelFormat {
        let max = ticks.iter().fold(0.0f64, |m, t| m.max(t.abs()));
        let decimals = |t: &f64| {
            let s = pretty_print_float(*t, false);
            s.split_once('.').map_or(0, |(_, d)| d.len())
        };
        match log {
            true => LabelFormat::Log,
            false if max >= 1e6 || (max > 0.0 && max < 1e-3) => LabelFormat::Scientific,
            false => LabelFormat::Fixed(ticks.iter().map(decimals).max().unwrap_or(0)),
        }
    }

    fn label(self, v: f64) -> String {
        match self {
            // plotters' ticks may miss zero by a rounding error: no "-0.0"
            LabelFormat::Fixed(d) if v.abs() < 0.5 * 10f64.powi(-(d as i32)) => {
                format!("{:.d$}", 0.0)
            }
            LabelFormat::Fixed(d) => format!("{v:.d$}"),
            LabelFormat::Log if (1e-3..1e5).contains(&v) => pretty_print_float(v, false),
            _ if v == 0.0 => "0".into(),
            _ => {
                let mut e = v.abs().log10().floor();
                let mut m = (v / 10f64.powf(e) * 1e6).round() / 1e6;
                if m.abs() >= 10.0 {
                    (m, e) = (m / 10.0, e + 1.0);
                }
                format!("{}e{e}", pretty_print_float(m, false))
            }
        }
    }
}

/// The plot area in image pixel coordinates: `left` / `top` are the first pixel column / row inside
/// it, `right` / `bottom` the last (`lo` of the x axis maps to `left`, `hi` to `right`; `lo` of the
/// y axis to `bottom`, `hi` to `top`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PixelRect {
    /// First column.
    pub left: f64,
    /// First row.
    pub top: f64,
    /// Last column.
    pub right: f64,
    /// Last row.
    pub bottom: f64,
}

/// Where a plot's data lands in the image: the plot area, the two axes and their ticks.
/// [`Plot::layout`] gives the layout [`Plot::render`] uses, so callers (and tests) can map data to
/// pixels: the point `(x, y)` is drawn in pixel `(floor(px), floor(py))` of
/// `(px, py) = (x_to_px(x), y_to_px(y))`, as plotters rounds.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PlotLayout {
    /// The plot area (inside the frame).
    pub area: PixelRect,
    /// The x axis.
    pub x: Axis,
    /// The y axis.
    pub y: Axis,
    /// Major x tick values with their labels (bar charts: category centres and names).
    pub x_ticks: Vec<(f64, String)>,
    /// Major y tick values with their labels.
    pub y_ticks: Vec<(f64, String)>,
    /// Font size of the tick labels in pixels, chosen for the image size.
    pub text_px: f64,
}

impl PlotLayout {
    /// Horizontal pixel coordinate of data value `x` (`None` if the axis cannot show it).
    pub fn x_to_px(&self, x: f64) -> Option<f64> {
        let a = self.area;
        self.x
            .fraction(x)
            .map(|f| a.left + f * (a.right - a.left) + 1e-3)
    }

    /// Vertical pixel coordinate of data value `y` (`None` if the axis cannot show it).
    pub fn y_to_px(&self, y: f64) -> Option<f64> {
        let a = self.area;
        // plotters counts whole pixels up from the bottom row
        let up = |f: f64| f * (a.bottom - a.top) + 1e-3;
        self.y.fraction(y).map(|f| a.bottom + 1.0 - up(f))
    }

    /// Pixel coordinates of a data point.
    pub fn to_px(&self, (x, y): (f64, f64)) -> Option<(f64, f64)> {
        Some((self.x_to_px(x)?, self.y_to_px(y)?))
    }
}

// ------------------------------------------------------------------------------------------------
// text

/// DejaVu Sans (Bitstream Vera licence, `assets/DejaVuSans-LICENSE.txt`), embedded so that plots
/// render the same everywhere and need no system fonts.
static FONT_TTF: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
/// The family name the font is registered under with plotters.
const FAMILY: &str = "veila-dejavu-sans";
/// DejaVu Sans's cap height as a fraction of the font size (plotters' size is ascent - descent:
/// 1493 of 2384 font units).
const CAP: f64 = 0.626;
/// plotters' `ab_glyph` text puts the baseline of top-anchored text half a font size below the
/// anchor, so capitals start `(CAP - BASELINE) * size` above it; text placed here compensates.
const BASELINE: f64 = 0.5;

/// The plot font at `px` pixels (registered with plotters on first use).
fn font(px: f64) -> FontDesc<'static> {
    static REGISTER: std::sync::Once = std::sync::Once::new();
    REGISTER.call_once(|| {
        if plotters::style::register_font(FAMILY, FontStyle::Normal, FONT_TTF).is_err() {
            tracing::error!("the embedded plot font does not parse: plots will fail to render");
        }
    });
    (FAMILY, px).into_font()
}

fn text_style(px: f64) -> TextStyle<'static> {
    font(px).color(&rgb(TEXT))
}

/// Width in pixels of `text` in the plot font at `size_px`.
pub fn text_width(text: &str, size_px: f64) -> u32 {
    font(size_px).box_size(text).map_or(0, |(w, _)| w)
}

/// Draw `text` onto `img` in the plot font at `size_px`, with the top-left corner of its capital
/// letters at `(x, y)`. Pixels outside the image are skipped.
pub fn draw_text(img: &mut RgbImage, x: i64, y: i64, text: &str, size_px: f64, color: Rgb<u8>) {
    let (w, h) = img.dimensions();
    if w == 0 || h == 0 || text.is_empty() || !(size_px > 0.0 && size_px.is_finite()) {
        return;
    }
    let root = BitMapBackend::with_buffer(img, (w, h)).into_drawing_area();
    let y = y.clamp(-1 << 24, 1 << 24) as f64 + (CAP - BASELINE) * size_px;
    let at = (x.clamp(-1 << 24, 1 << 24) as i32, y.round() as i32);
    let style = font(size_px).color(&rgb(color.0));
    let style = style.pos(Pos::new(HPos::Left, VPos::Top));
    if let Err(e) = root.draw(&Text::new(text, at, style)) {
        tracing::warn!("drawing text {text:?}: {e}");
    }
}

/// `text` shortened with ".." so that it fits `max_w` pixels at `px` (plotters draws text whole).
fn fit_text(text: &str, max_w: f64, px: f64) -> String {
    let chars: Vec<char> = text.chars().collect();
    let cut = |keep: usize| match keep == chars.len() {
        true => text.to_string(),
        false => chars[..keep].iter().chain(&['.', '.']).collect(),
    };
    let fits = |t: &String| text_width(t, px) as f64 <= max_w;
    (0..=chars.len())
        .rev()
        .map(cut)
        .find(fits)
        .unwrap_or_default()
}

// ------------------------------------------------------------------------------------------------
// marks

/// Sizes in pixels that follow the font size `s`: 3.6 % of the image's short side (18 px at
/// 800 x 500), at least 9.
#[derive(Debug, Clone, Copy)]
struct Metrics {
    s: f64,
    pad: f64,
    tick: i32,
    line_w: u32,
    marker_r: f64,
}

impl Metrics {
    fn new(width: u32, height: u32) -> Self {
        let s = (0.036 * width.min(height) as f64).clamp(9.0, 64.0);
        Metrics {
            s,
            pad: (0.6 * s).round(),
            tick: (0.3 * s).round().max(2.0) as i32,
            line_w: (s / 8.0).round().max(1.0) as u32,
            marker_r: (0.3 * s).max(2.5),
        }
    }
}

/// Marker shapes, cycled through by series index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Marker {
    Circle,
    Square,
    TriangleUp,
    Diamond,
    TriangleDown,
}

const MARKERS: [Marker; 5] = [
    Marker::Circle,
    Marker::Square,
    Marker::TriangleUp,
    Marker::Diamond,
    Marker::TriangleDown,
];

/// The corners of a marker of radius about `r` pixels around its centre, for plotters' polygon
/// (plotters' own markers are circles, triangles and crosses, not this set of five).
fn outline(shape: Marker, r: f64) -> Vec<(i32, i32)> {
    let circle: Vec<(f64, f64)>;
    let corners: &[(f64, f64)] = match shape {
        Marker::Circle => {
            circle = (0..16)
                .map(|k| (k as f64 * std::f64::consts::PI / 8.0).sin_cos())
                .collect();
            &circle
        }
        Marker::Square => &[(-0.85, -0.85), (0.85, -0.85), (0.85, 0.85), (-0.85, 0.85)],
        Marker::Diamond => &[(0.0, -1.2), (1.2, 0.0), (0.0, 1.2), (-1.2, 0.0)],
        Marker::TriangleUp => &[(0.0, -1.25), (1.1, 0.65), (-1.1, 0.65)],
        Marker::TriangleDown => &[(0.0, 1.25), (1.1, -0.65), (-1.1, -0.65)],
    };
    let px = |v: f64| (v * r).round() as i32;
    corners.iter().map(|&(x, y)| (px(x), px(y))).collect()
}

/// A rectangle `(x0, y0, x1, y1)` in fractions of the plot area (y up); [`UNIT`] is the area.
type Frac = (f64, f64, f64, f64);
const UNIT: Frac = (0.0, 0.0, 1.0, 1.0);

/// The parameters `(t0, t1)` of the part of segment `a`-`b` inside `r` (Liang-Barsky); `None` when
/// none is. Plotters clamps points outside the plot area onto its edge instead of clipping lines.
fn clip(a: (f64, f64), b: (f64, f64), r: Frac) -> Option<(f64, f64)> {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - r.0),
        (dx, r.2 - a.0),
        (-dy, a.1 - r.1),
        (dy, r.3 - a.1),
    ] {
        if !(p.is_finite() && q.is_finite()) || p == 0.0 && q < 0.0 {
            return None;
        } else if p < 0.0 {
            t0 = t0.max(q / p);
        } else if p > 0.0 {
            t1 = t1.min(q / p);
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

/// An error bar from `y - e` to `y + e` at `x` with caps reaching `cap` pixels to either side:
/// plotters' `ErrorBar` where `ring` allows its ring around the mean (a series' marker covers it).
/// A bar of a bar chart (whose top is the mean) and a bar leaving the plot area (plotters would
/// clamp its end onto the edge and cap it there) get a stem with caps on the ends inside instead.
fn error_bar<X, Y>(
    chart: &mut Chart<'_, '_, X, Y>,
    ya: &Axis,
    at: (f64, f64),
    e: f64,
    cap: f64,
    ring: bool,
) -> DrawResult
where
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    let ((x, y), style, half) = (at, rgb(ERROR_BAR).stroke_width(1), cap.round() as i32);
    // on a log axis a bar reaching zero or below runs out of the bottom
    let lo = ya.fraction(y - e).unwrap_or(f64::NEG_INFINITY);
    let hi = ya.fraction(y + e).unwrap_or(f64::NAN);
    if !(hi >= 0.0 && lo <= 1.0) {
        return Ok(());
    }
    if ring && lo >= 0.0 && hi <= 1.0 {
        let w = 2 * half as u32 + 1;
        chart.draw_series([ErrorBar::new_vertical(x, y - e, y, y + e, style, w)])?;
        return Ok(());
    }
    let (a, b) = (ya.value(lo.max(0.0)), ya.value(hi.min(1.0)));
    chart.draw_series([PathElement::new(vec![(x, a), (x, b)], style)])?;
    let caps = [(lo >= 0.0, a), (hi <= 1.0, b)].into_iter().filter(|c| c.0);
    let cap = |v: f64| EmptyElement::at((x, v)) + PathElement::new([(-half, 0), (half, 0)], style);
    chart.draw_series(caps.map(|(_, v)| cap(v)))?;
    Ok(())
}

// ------------------------------------------------------------------------------------------------
// charts

type Root<'b> = DrawingArea<BitMapBackend<'b>, Shift>;
type Chart<'a, 'b, X, Y> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<X, Y>>;
type DrawResult<T = ()> = std::result::Result<T, Box<dyn std::error::Error + Send + Sync>>;

/// A legend entry's key: a line across the key area and / or a shape (corners around its middle).
#[derive(Debug, Clone)]
struct Key {
    color: [u8; 3],
    line: bool,
    shape: Vec<(i32, i32)>,
}

/// What a chart shows besides its data. Bar charts have categories along x.
struct Spec<'a> {
    title: &'a str,
    x_label: &'a str,
    y_label: &'a str,
    x: Axis,
    categories: Option<&'a [String]>,
    y: Axis,
}

/// A kind of chart: its frame, legend and data (drawn on plotters' chart context).
trait Marks {
    fn spec(&self) -> Spec<'_>;
    fn legend(&self, m: &Metrics) -> Vec<(String, Key)>;
    /// Whether the data covers any part of `r`, for legend placement.
    fn covers(&self, x: &Axis, y: &Axis, r: Frac) -> bool;
    fn draw<X, Y>(&self, chart: &mut Chart<'_, '_, X, Y>, f: &Frame) -> DrawResult
    where
        X: Ranged<ValueType = f64>,
        Y: Ranged<ValueType = f64>;
}

/// The chart's layout before plotters places it: label area sizes, axes, ticks and fitted texts.
struct Frame {
    m: Metrics,
    x: Axis,
    y: Axis,
    /// Tick count hints handed to plotters (which then picks `x_ticks` / `y_ticks` again).
    x_n: usize,
    y_n: usize,
    x_ticks: Vec<(f64, String)>,
    y_ticks: Vec<(f64, String)>,
    categories: bool,
    x_area: u32,
    y_area: u32,
    /// ChartBuilder margins (top, bottom, left, right): the top one leaves room for the frame.
    margins: [u32; 4],
    x_label: String,
    y_label: String,
    /// Size of the plot area in pixels.
    plot: (f64, f64),
}

/// Of the tick sets for hints `n_max` down to 2, the first whose neighbouring ticks lie `gap`
/// pixels apart (plotters takes a tick count, not the room its labels need).
fn spaced_ticks(
    axis: &Axis,
    len: f64,
    n_max: usize,
    gap: impl Fn(&[(f64, String)]) -> f64,
) -> (usize, Vec<(f64, String)>) {
    let fits = |t: &[(f64, String)]| {
        let f: Vec<f64> = t.iter().filter_map(|t| axis.fraction(t.0)).collect();
        f.windows(2).all(|w| (w[1] - w[0]) * len >= gap(t))
    };
    let mut n = n_max.max(2);
    loop {
        let t = axis.ticks(n);
        if n == 2 || fits(&t) {
            return (n, t);
        }
        n -= 1;
    }
}

impl Frame {
    /// The layout in an area of `w` x `h` pixels; when that is too small for text, one without
    /// text whose plot area fills all of `full`.
    fn new(w: f64, h: f64, spec: &Spec<'_>, m: Metrics, full: (u32, u32)) -> Frame {
        let (s, tick) = (m.s, m.tick as f64);
        let room = |text: &str, px: f64| if text.is_empty() { 0.0 } else { px };
        let widest =
            |t: &[(f64, String)]| t.iter().map(|t| text_width(&t.1, s)).max().unwrap_or(0) as f64;
        // tick labels hang from twice the tick length below the axis (plotters' spacing); the axis
        // label sits at the bottom of the label area
        let x_area = 2.0 * tick + 0.75 * s + room(spec.x_label, 1.3 * s);
        let bottom = (0.4 * s).round();
        let plot_h = h - x_area - bottom;
        let n_y = ((plot_h / (2.0 * s)) as usize).clamp(2, 10);
        let (y_n, y_ticks) = spaced_ticks(&spec.y, plot_h, n_y, |_| 1.6 * s);
        let y_area = 2.0 * tick + widest(&y_ticks) + room(spec.y_label, 1.2 * s);
        let mut right = m.pad.max(0.5 * s);
        let plot_w = |right: f64| w - m.pad - y_area - right;
        let (x_n, x_ticks) = match spec.categories {
            None => {
                let mut out = (2, Vec::new());
                for _pass in 0..2 {
                    let n_x = ((plot_w(right) / (3.0 * s)) as usize).clamp(2, 12);
                    out = spaced_ticks(&spec.x, plot_w(right), n_x, |t| widest(t) + 1.2 * s);
                    // the last label is centred on its tick: keep it inside the image
                    let last = out.1.last().map_or(0, |(_, l)| text_width(l, s));
                    let need = last as f64 / 2.0 + 0.2 * s;
                    if need <= right {
                        break;
                    }
                    right = need;
                }
                out
            }
            Some(names) => {
                // category i sits on x = i: plotters' ticks with one per category
                let slot = plot_w(right) / names.len().max(1) as f64;
                let name = |(i, n): (usize, &String)| (i as f64, fit_text(n, slot - 0.3 * s, s));
                (
                    names.len().max(1),
                    names.iter().enumerate().map(name).collect(),
                )
            }
        };
        let plot = (plot_w(right), plot_h);
        let frame = Frame {
            m,
            x: spec.x,
            y: spec.y,
            x_n,
            y_n,
            x_ticks,
            y_ticks,
            categories: spec.categories.is_some(),
            x_area: x_area.round() as u32,
            y_area: y_area.round() as u32,
            margins: [1, bottom as u32, m.pad as u32, right.round() as u32],
            x_label: fit_text(spec.x_label, plot.0, s),
            y_label: fit_text(spec.y_label, plot.1, s),
            plot,
        };
        if plot.0 >= 4.0 * s && plot.1 >= 3.0 * s {
            return frame;
        }
        Frame {
            x_n: 0,
            y_n: 0,
            x_ticks: Vec::new(),
            y_ticks: Vec::new(),
            x_area: 0,
            y_area: 0,
            margins: [0; 4],
            x_label: String::new(),
            y_label: String::new(),
            plot: (full.0 as f64, full.1 as f64),
            ..frame
        }
    }

    fn has_text(&self) -> bool {
        self.x_area > 0
    }
}

/// A legend as plotters draws it: a box with a key area, then the names.
struct Legend {
    names: Vec<String>,
    keys: Vec<Key>,
    m: Metrics,
    key_w: f64,
    margin: u32,
    size: (f64, f64),
}

impl Legend {
    fn new(entries: Vec<(String, Key)>, max_w: f64, m: Metrics) -> DrawResult<Legend> {
        let (key_w, margin) = (1.8 * m.s, (0.5 * m.s).round() as u32);
        let max_text = max_w - key_w - 0.4 * m.s - 2.0 * margin as f64;
        let fit = |(n, k): (String, Key)| (fit_text(&n, max_text, m.s), k);
        let (names, keys): (Vec<String>, Vec<Key>) = entries.into_iter().map(fit).unzip();
        // the size of the box plotters draws: the names' block plus the key area and margins
        let mut block = MultiLineText::<(i32, i32), &str>::new((0, 0), text_style(m.s));
        names.iter().for_each(|n| block.push_line(n.as_str()));
        let (w, h) = block.estimate_dimension()?;
        let key_area = (key_w + 0.4 * m.s).round();
        let size = (
            w as f64 + key_area + 2.0 * margin as f64,
            h as f64 + 2.0 * margin as f64,
        );
        Ok(Legend {
            names,
            keys,
            m,
            key_w,
            margin,
            size,
        })
    }

    /// The top-left corner (pixels in the plot area) of the first corner of the plot area (top
    /// right, top left, bottom right, bottom left) where the legend covers no data: plotters
    /// places a legend where told, not where it is free.
    fn free_corner<M: Marks>(&self, marks: &M, f: &Frame) -> Option<SeriesLabelPosition> {
        let ((w, h), (pw, ph), inset) = (self.size, f.plot, 0.5 * self.m.s);
        if w + 2.0 * inset > pw || h + 2.0 * inset > ph {
            return None;
        }
        let (x0, x1, y0, y1) = (inset, pw - inset - w, inset, ph - inset - h);
        let margin = 0.25 * self.m.s;
        let corners = [(x1, y0), (x0, y0), (x1, y1), (x0, y1)].into_iter();
        corners
            .map(|(x, y)| (x.round() as i32, y.round() as i32))
            .find(|&(x, y)| {
                let (x, y) = (x as f64 - margin, y as f64 - margin);
                let (xe, ye) = (x + w + 2.0 * margin, y + h + 2.0 * margin);
                !marks.covers(&f.x, &f.y, (x / pw, 1.0 - ye / ph, xe / pw, 1.0 - y / ph))
            })
            .map(|(x, y)| SeriesLabelPosition::Coordinate(x, y))
    }

    /// Draw with plotters' series labels on `chart` at `at`, `boxed` or not.
    fn draw<'a, 'b: 'a, X, Y>(
        &self,
        chart: &mut Chart<'a, 'b, X, Y>,
        at: SeriesLabelPosition,
        boxed: bool,
    ) -> DrawResult
    where
        X: Ranged<ValueType = f64>,
        Y: Ranged<ValueType = f64>,
    {
        let m = self.m;
        // plotters hands a key the left end of its area at the middle of the name's box; the
        // capitals' middle is higher (see BASELINE)
        let dy = ((BASELINE - CAP / 2.0 - 0.5 / 1.24) * m.s).round() as i32;
        let (key_w, mid) = (self.key_w.round() as i32, (self.key_w / 2.0).round() as i32);
        for (name, key) in self.names.iter().zip(&self.keys) {
            let stroke = if key.line {
                vec![(0, 0), (key_w, 0)]
            } else {
                Vec::new()
            };
            let shape: Vec<(i32, i32)> = key.shape.iter().map(|&(x, y)| (x + mid, y)).collect();
            let (line, fill) = (
                rgb(key.color).stroke_width(m.line_w),
                rgb(key.color).filled(),
            );
            // plotters lists the series drawn with a label: an empty one per entry
            let anno = chart.draw_series(std::iter::empty::<PathElement<(f64, f64)>>())?;
            anno.label(name.as_str()).legend(move |(x, y)| {
                EmptyElement::at((x, y + dy))
                    + PathElement::new(stroke.clone(), line)
                    + Polygon::new(shape.clone(), fill)
            });
        }
        let mut labels = chart.configure_series_labels();
        labels
            .position(at)
            .label_font(text_style(m.s))
            .legend_area_size((self.key_w + 0.4 * m.s).round() as u32)
            .margin(self.margin);
        if boxed {
            labels
                .background_style(rgb(BACKGROUND).mix(0.9).filled())
                .border_style(rgb(LEGEND_BORDER).stroke_width(1));
        }
        labels.draw()?;
        Ok(())
    }
}

/// Draw the chart of `marks` on `root` and say where its plot area went.
fn paint<M: Marks>(marks: &M, root: &Root<'_>) -> DrawResult<PlotLayout> {
    root.fill(&rgb(BACKGROUND))?;
    let (w, h) = root.dim_in_pixel();
    let (m, spec) = (Metrics::new(w, h), marks.spec());
    let title_style = text_style(1.2 * m.s);
    let title = fit_text(spec.title, w as f64 - 2.0 * m.pad, 1.2 * m.s);
    // the height plotters' `titled` takes: the title is drawn once there is room for text
    let (_, th) = root.estimate_text_size(&title, &title_style)?;
    let title_h = if title.is_empty() {
        0
    } else {
        th + 2 * (th / 2).min(5)
    };
    let frame = Frame::new(
        w as f64,
        h as f64 - m.pad - title_h as f64,
        &spec,
        m,
        (w, h),
    );
    if !frame.has_text() {
        return build(marks, root, &frame, None);
    }
    let mut area = root.margin(m.pad as u32, 0, 0, 0);
    if !title.is_empty() {
        area = area.titled(&title, title_style)?;
    }
    let entries = marks.legend(&m);
    if entries.is_empty() {
        return build(marks, &area, &frame, None);
    }
    let legend = Legend::new(entries, w as f64 - 2.0 * m.pad, m)?;
    if let Some(at) = legend.free_corner(marks, &frame) {
        return build(marks, &area, &frame, Some((&legend, at)));
    }
    // no free corner: the legend goes into a band above the plot area, on a chart of its own
    // (plotters draws a legend only inside a chart's plot area); with no room for that either,
    // it covers the top right corner
    let (band_h, (aw, ah)) = (legend.size.1.round() as u32, area.dim_in_pixel());
    let below = (ah as f64 - band_h as f64, aw as f64);
    let rest = Frame::new(below.1, below.0, &spec, m, (w, h));
    if below.0 <= 0.0 || !rest.has_text() {
        return build(
            marks,
            &area,
            &frame,
            Some((&legend, SeriesLabelPosition::UpperRight)),
        );
    }
    let (band, area) = area.split_vertically(band_h);
    let mut band_chart = ChartBuilder::on(&band).build_cartesian_2d(0.0..1.0, 0.0..1.0)?;
    let x = ((aw as f64 - legend.size.0) / 2.0).max(m.pad) as i32;
    legend.draw(
        &mut band_chart,
        SeriesLabelPosition::Coordinate(x, 0),
        false,
    )?;
    build(marks, &area, &rest, None)
}

/// Plotters' chart on `area` laid out as `frame`: the axes on their scales (linear or
/// logarithmic, each pair a chart type of its own), then the data, the frame and the legend.
fn build<M: Marks>(
    marks: &M,
    area: &Root<'_>,
    frame: &Frame,
    legend: Option<(&Legend, SeriesLabelPosition)>,
) -> DrawResult<PlotLayout> {
    let [top, bottom, left, right] = frame.margins;
    let mut b = ChartBuilder::on(area);
    b.margin_top(top)
        .margin_bottom(bottom)
        .margin_left(left)
        .margin_right(right)
        .x_label_area_size(frame.x_area)
        .y_label_area_size(frame.y_area);
    let (x, y, xn, yn) = (frame.x, frame.y, frame.x_n, frame.y_n);
    let (xl, yl) = (x.lo..x.hi, y.lo..y.hi);
    let (b, f) = (&mut b, frame);
    match (x.log, y.log) {
        (false, false) => draw(marks, area, b.build_cartesian_2d(xl, yl)?, f, legend),
        (true, false) => draw(
            marks,
            area,
            b.build_cartesian_2d(x.log_scale(xn), yl)?,
            f,
            legend,
        ),
        (false, true) => draw(
            marks,
            area,
            b.build_cartesian_2d(xl, y.log_scale(yn))?,
            f,
            legend,
        ),
        (true, true) => {
            let chart = b.build_cartesian_2d(x.log_scale(xn), y.log_scale(yn))?;
            draw(marks, area, chart, f, legend)
        }
    }
}

/// The label of the tick nearest `v` (plotters asks for the ticks the frame was sized for).
fn tick_label(ticks: &[(f64, String)], v: f64) -> String {
    let d = |t: &&(f64, String)| (t.0 - v).abs();
    let nearest = ticks.iter().min_by(|a, b| d(a).total_cmp(&d(b)));
    nearest.map(|t| t.1.clone()).unwrap_or_default()
}

/// Plotters' mesh (grid, axes, ticks and their labels, axis labels), the data, a frame around the
/// plot area and the legend.
fn draw<'a, 'b: 'a, M, X, Y>(
    marks: &M,
    area: &Root<'_>,
    mut chart: Chart<'a, 'b, X, Y>,
    f: &Frame,
    legend: Option<(&Legend, SeriesLabelPosition)>,
) -> DrawResult<PlotLayout>
where
    M: Marks,
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let s = f.m.s;
    let (fx, fy) = (
        |v: &f64| tick_label(&f.x_ticks, *v),
        |v: &f64| tick_label(&f.y_ticks, *v),
    );
    let mut mesh = chart.configure_mesh();
    mesh.bold_line_style(rgb(GRID).stroke_width(1))
        .light_line_style(rgb(MINOR_GRID).stroke_width(1))
        .max_light_lines(0) // linear axes: no minor grid (log axes bring theirs)
        .axis_style(rgb(FRAME).stroke_width(1))
        .label_style(text_style(s))
        .axis_desc_style(text_style(s))
        .set_all_tick_mark_size(f.m.tick)
        // centre the capitals of the y tick labels on their ticks (see BASELINE)
        .y_label_offset(((1.0 / 2.48 + CAP / 2.0 - BASELINE) * s).round() as i32)
        .x_labels(f.x_n)
        .y_labels(f.y_n)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy);
    if !f.x_label.is_empty() {
        mesh.x_desc(f.x_label.as_str());
    }
    if !f.y_label.is_empty() {
        mesh.y_desc(f.y_label.as_str());
    }
    if f.categories {
        mesh.disable_x_mesh();
    }
    mesh.draw()?;
    marks.draw(&mut chart, f)?;
    let (xr, yr) = chart.plotting_area().get_pixel_range();
    let corners = [(xr.start - 1, yr.start - 1), (xr.end, yr.end)];
    area.use_screen_coord()
        .draw(&Rectangle::new(corners, rgb(FRAME).stroke_width(1)))?;
    if let Some((legend, at)) = legend {
        legend.draw(&mut chart, at, true)?;
    }
    let area = PixelRect {
        left: xr.start as f64,
        top: yr.start as f64,
        right: (xr.end - 1).max(xr.start) as f64,
        bottom: (yr.end - 1).max(yr.start) as f64,
    };
    let (x_ticks, y_ticks) = (f.x_ticks.clone(), f.y_ticks.clone());
    Ok(PlotLayout {
        area,
        x: f.x,
        y: f.y,
        x_ticks,
        y_ticks,
        text_px: s,
    })
}

/// The chart of `marks` on a white image of the given size (empty for a size of 0), with the
/// layout, or with a drawing error (and what was drawn).
fn render<M: Marks>(marks: &M, width: u32, height: u32) -> (RgbImage, DrawResult<PlotLayout>) {
    let (w, h) = (width.max(1), height.max(1));
    let mut img = RgbImage::from_pixel(w, h, Rgb(BACKGROUND));
    let res = {
        let root = BitMapBackend::with_buffer(&mut img, (w, h)).into_drawing_area();
        paint(marks, &root).and_then(|l| Ok((l, root.present()?)).map(|(l, ())| l))
    };
    match width == 0 || height == 0 {
        true => (RgbImage::new(width, height), res),
        false => (img, res),
    }
}

/// The image and the layout, a drawing error logged (the image keeps what was drawn, the layout
/// is empty).
fn render_logged<M: Marks>(marks: &M, title: &str, w: u32, h: u32) -> (RgbImage, PlotLayout) {
    let (img, res) = render(marks, w, h);
    let layout = res.unwrap_or_else(|e| {
        tracing::warn!("plot '{title}': {e}");
        PlotLayout::default()
    });
    (img, layout)
}

/// The image, after checking the size; a drawing error is the crate's error.
fn try_render<M: Marks>(marks: &M, width: u32, height: u32) -> Result<RgbImage> {
    if width == 0 || height == 0 || width > 16384 || height > 16384 {
        return Err(Error::Invalid {
            what: "plot size".into(),
            message: format!("{width} x {height} px is outside 1..=16384 per side"),
        });
    }
    let (img, res) = render(marks, width, height);
    let message = |e: Box<dyn std::error::Error + Send + Sync>| format!("drawing failed: {e}");
    res.map(|_| img).map_err(|e| Error::Invalid {
        what: "plot".into(),
        message: message(e),
    })
}

// ------------------------------------------------------------------------------------------------
// line / scatter plots

/// The usable error bar half-length of entry `i` (0 when absent, non-finite or not positive).
fn error_of(errors: &Option<Vec<f64>>, i: usize) -> f64 {
    let e = errors.as_ref().and_then(|e| e.get(i).copied());
    e.filter(|e| e.is_finite() && *e > 0.0).unwrap_or(0.0)
}

/// Per point: its position in plot-area fractions (`None`: not drawable).
fn fractions(s: &Series, x: &Axis, y: &Axis) -> Vec<Option<(f64, f64)>> {
    let frac = |&(px, py): &(f64, f64)| Some((x.fraction(px)?, y.fraction(py)?));
    s.points.iter().map(frac).collect()
}

fn has_line(s: &Series) -> bool {
    matches!(s.style, SeriesStyle::Line | SeriesStyle::LineMarkers)
}

impl Marks for Plot {
    fn spec(&self) -> Spec<'_> {
        let xs = self
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.0));
        let x = Axis::fit(xs, self.x_log, self.x_range);
        // y over the points x can show, error bars included (on a log axis not below the point
        // where the bar reaches zero)
        let ys = self.series.iter().flat_map(|s| {
            let shown = s
                .points
                .iter()
                .enumerate()
                .filter(|(_, p)| x.fraction(p.0).is_some());
            shown.flat_map(|(i, &(_, y))| {
                let e = error_of(&s.error_bars, i);
                [if self.y_log && y - e <= 0.0 { y } else { y - e }, y + e]
            })
        });
        let y = Axis::fit(ys, self.y_log, self.y_range);
        let (title, x_label, y_label) = (&*self.title, &*self.x_label, &*self.y_label);
        Spec {
            title,
            x_label,
            y_label,
            x,
            categories: None,
            y,
        }
    }

    fn legend(&self, m: &Metrics) -> Vec<(String, Key)> {
        let named = self
            .series
            .iter()
            .enumerate()
            .filter(|(_, s)| !s.name.is_empty());
        let key = |(i, s): (usize, &Series)| {
            let shape = match s.style {
                SeriesStyle::Line => Vec::new(),
                _ => outline(MARKERS[i % MARKERS.len()], m.marker_r),
            };
            let key = Key {
                color: series_color(i).0,
                line: has_line(s),
                shape,
            };
            (s.name.clone(), key)
        };
        named.map(key).collect()
    }

    fn covers(&self, x: &Axis, y: &Axis, r: Frac) -> bool {
        self.series.iter().any(|s| {
            let f = fractions(s, x, y);
            let points = f.iter().enumerate().filter_map(|(i, p)| Some((i, (*p)?)));
            let bar = |(i, p): (usize, (f64, f64))| {
                let (py, e) = (s.points[i].1, error_of(&s.error_bars, i));
                let lo = y.fraction(py - e).unwrap_or(-1.0).max(-1.0);
                let hi = y.fraction(py + e).unwrap_or(p.1);
                e > 0.0 && clip((p.0, lo), (p.0, hi), r).is_some()
            };
            let segment = |w: &[Option<(f64, f64)>]| match w {
                [Some(a), Some(b)] => clip(*a, *b, r).is_some(),
                _ => false,
            };
            points.clone().any(|(_, p)| clip(p, p, r).is_some())
                || points.clone().any(bar)
                || has_line(s) && f.windows(2).any(segment)
        })
    }

    fn draw<X, Y>(&self, chart: &mut Chart<'_, '_, X, Y>, f: &Frame) -> DrawResult
    where
        X: Ranged<ValueType = f64>,
        Y: Ranged<ValueType = f64>,
    {
        let m = f.m;
        for (si, s) in self.series.iter().enumerate() {
            let color = series_color(si).0;
            let frac = fractions(s, &f.x, &f.y);
            for (i, p) in frac.iter().enumerate() {
                let e = error_of(&s.error_bars, i);
                if e > 0.0 && p.is_some_and(|p| (0.0..=1.0).contains(&p.0)) {
                    error_bar(chart, &f.y, s.points[i], e, 0.25 * m.s, true)?;
                }
            }
            if has_line(s) {
                // runs of clipped segments, broken at skipped points and where the line leaves
                let (mut runs, mut open) = (Vec::<Vec<(f64, f64)>>::new(), false);
                for i in 1..frac.len() {
                    let seg = frac[i - 1].zip(frac[i]);
                    let Some(((a, b), (t0, t1))) =
                        seg.and_then(|(a, b)| Some(((a, b), clip(a, b, UNIT)?)))
                    else {
                        open = false;
                        continue;
                    };
                    let at = |t: f64| {
                        (
                            f.x.value(a.0 + t * (b.0 - a.0)),
                            f.y.value(a.1 + t * (b.1 - a.1)),
                        )
                    };
                    if !(open && t0 == 0.0) {
                        runs.push(vec![if t0 == 0.0 { s.points[i - 1] } else { at(t0) }]);
                    }
                    runs.last_mut().expect("a run").push(if t1 == 1.0 {
                        s.points[i]
                    } else {
                        at(t1)
                    });
                    open = t1 == 1.0;
                }
                let style = rgb(color).stroke_width(m.line_w);
                chart.draw_series(runs.into_iter().map(|r| PathElement::new(r, style)))?;
            }
            if s.style != SeriesStyle::Line {
                let shape = outline(MARKERS[si % MARKERS.len()], m.marker_r);
                let inside =
                    |p: &&Option<(f64, f64)>| p.is_some_and(|p| clip(p, p, UNIT).is_some());
                let shown = frac.iter().zip(&s.points).filter(|(p, _)| inside(p));
                let mark = |p: (f64, f64)| {
                    EmptyElement::at(p) + Polygon::new(shape.clone(), rgb(color).filled())
                };
                chart.draw_series(shown.map(|(_, &p)| mark(p)))?;
            }
        }
        Ok(())
    }
}

impl Plot {
    /// Check what [`Plot::render`] tolerates silently: error bars must have one entry per point and
    /// must not be negative.
    pub fn validate(&self) -> Result<()> {
        for (i, s) in self.series.iter().enumerate() {
            if let Some(e) = &s.error_bars {
                if e.len() != s.points.len() {
                    return Err(Error::Mismatch {
                        context: format!("plot series {i} ('{}')", s.name),
                        message: format!("{} error bars for {} points", e.len(), s.points.len()),
                    });
                }
                if let Some(k) = e.iter().position(|v| *v < 0.0) {
                    return Err(Error::Invalid {
                        what: format!("error bars of plot series {i} ('{}')", s.name),
                        message: format!("entry {k} is negative ({})", e[k]),
                    });
                }
            }
        }
        Ok(())
    }

    /// The layout [`Plot::render`] uses at this size (plot area, axes, ticks).
    pub fn layout(&self, width: u32, height: u32) -> PlotLayout {
        render_logged(self, &self.title, width, height).1
    }

    /// Render to an RGB image of the given size. Never fails: non-finite or out-of-domain points are
    /// skipped, degenerate ranges get a window around the data, and a size of 0 gives an empty image.
    pub fn render(&self, width: u32, height: u32) -> RgbImage {
        render_logged(self, &self.title, width, height).0
    }

    /// Render and encode as PNG bytes (after [`Plot::validate`]).
    pub fn to_png(&self, width: u32, height: u32) -> Result<Vec<u8>> {
        self.validate()?;
        crate::image_io::encode_png(&try_render(self, width, height)?)
    }

    /// Render and write as PNG, atomically (after [`Plot::validate`]).
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        self.validate()?;
        crate::image_io::write_png(path, &try_render(self, width, height)?)
    }
}

// ------------------------------------------------------------------------------------------------
// bar charts

impl BarChart {
    /// Check what [`BarChart::render`] tolerates silently: every group has one value (and error, if
    /// any) per category, and errors are not negative.
    pub fn validate(&self) -> Result<()> {
        let n = self.categories.len();
        for g in &self.groups {
            let context = format!("bar group '{}'", g.name);
            if g.values.len() != n {
                let message = format!("{} values for {n} categories", g.values.len());
                return Err(Error::Mismatch { context, message });
            }
            let Some(e) = &g.errors else { continue };
            if e.len() != n {
                let message = format!("{} errors for {n} categories", e.len());
                return Err(Error::Mismatch { context, message });
            }
            if let Some(k) = e.iter().position(|v| *v < 0.0) {
                return Err(Error::Invalid {
                    what: format!("errors of bar group '{}'", g.name),
                    message: format!("entry {k} is negative ({})", e[k]),
                });
            }
        }
        Ok(())
    }

    /// Every drawable bar: group, category, value and error half-length.
    fn bars(&self) -> impl Iterator<Item = (usize, usize, f64, f64)> + '_ {
        self.groups.iter().enumerate().flat_map(move |(gi, g)| {
            let values = g.values.iter().enumerate().take(self.categories.len());
            let values = values.filter(|(_, v)| v.is_finite());
            values.map(move |(ci, &v)| (gi, ci, v, error_of(&g.errors, ci)))
        })
    }

    /// Left and right end of a bar along x: category `ci` spans `ci - 0.5 .. ci + 0.5`, its bars
    /// the middle 80 %.
    fn bar_x(&self, gi: usize, ci: usize) -> (f64, f64) {
        let w = 0.8 / self.groups.len().max(1) as f64;
        let x0 = ci as f64 - 0.4 + gi as f64 * w;
        (x0, x0 + w)
    }
}

impl Marks for BarChart {
    fn spec(&self) -> Spec<'_> {
        let ends = self.bars().flat_map(|(_, _, v, e)| [v - e, v + e]);
        let (lo, hi) = ends.fold((0.0f64, 0.0f64), |(lo, hi), v| (lo.min(v), hi.max(v)));
        // bars stand on zero: margins only on the side(s) away from it
        let m = 0.06 * (hi - lo);
        let y = (
            if lo < 0.0 { lo - m } else { 0.0 },
            if hi > 0.0 { hi + m } else { 0.0 },
        );
        let n = self.categories.len().max(1) as f64;
        Spec {
            title: &self.title,
            x_label: "",
            y_label: &self.y_label,
            x: Axis {
                lo: -0.5,
                hi: n - 0.5,
                log: false,
            },
            categories: Some(&self.categories),
            y: Axis::fit(std::iter::empty(), false, Some(y)),
        }
    }

    fn legend(&self, m: &Metrics) -> Vec<(String, Key)> {
        let named = self
            .groups
            .iter()
            .enumerate()
            .filter(|(_, g)| !g.name.is_empty());
        let shape = outline(Marker::Square, CAP * m.s / 1.7);
        let key = |(i, g): (usize, &BarGroup)| {
            let key = Key {
                color: series_color(i).0,
                line: false,
                shape: shape.clone(),
            };
            (g.name.clone(), key)
        };
        named.map(key).collect()
    }

    fn covers(&self, x: &Axis, y: &Axis, r: Frac) -> bool {
        let f = |a: &Axis, v: f64| a.fraction(v).unwrap_or(0.0);
        self.bars().any(|(gi, ci, v, e)| {
            let (x0, x1) = self.bar_x(gi, ci);
            let (y0, y1) = (f(y, v.min(0.0).min(v - e)), f(y, v.max(0.0).max(v + e)));
            f(x, x0) <= r.2 && f(x, x1) >= r.0 && y0 <= r.3 && y1 >= r.1
        })
    }

    fn draw<X, Y>(&self, chart: &mut Chart<'_, '_, X, Y>, f: &Frame) -> DrawResult
    where
        X: Ranged<ValueType = f64>,
        Y: Ranged<ValueType = f64>,
    {
        let n = self.categories.len().max(1) * self.groups.len().max(1);
        let bar_px = 0.8 * f.plot.0 / n as f64;
        // a hairline gap between neighbouring bars (plotters' rectangle margin)
        let gap = u32::from(bar_px > 6.0);
        let bar = |(gi, ci, v, _): (usize, usize, f64, f64)| {
            let (x0, x1) = self.bar_x(gi, ci);
            let mut bar = Rectangle::new([(x0, 0.0), (x1, v)], rgb(series_color(gi).0).filled());
            bar.set_margin(0, 0, 0, gap);
            bar
        };
        chart.draw_series(self.bars().map(bar))?;
        let cap = (0.25 * bar_px).min(0.3 * f.m.s);
        for (gi, ci, v, e) in self.bars().filter(|b| b.3 > 0.0) {
            let (x0, x1) = self.bar_x(gi, ci);
            error_bar(chart, &f.y, (0.5 * (x0 + x1), v), e, cap, false)?;
        }
        if f.y.lo < 0.0 {
            let zero = PathElement::new([(f.x.lo, 0.0), (f.x.hi, 0.0)], rgb(FRAME).stroke_width(1));
            chart.draw_series([zero])?;
        }
        Ok(())
    }
}

impl BarChart {
    /// The layout [`BarChart::render`] uses (category `i` centred on x = `i`, spanning `i - 0.5 ..
    /// i + 0.5`).
    pub fn layout(&self, width: u32, height: u32) -> PlotLayout {
        render_logged(self, &self.title, width, height).1
    }

    /// Render to an RGB image of the given size. Never fails; non-finite values draw no bar.
    pub fn render(&self, width: u32, height: u32) -> RgbImage {
        render_logged(self, &self.title, width, height).0
    }

    /// Render and encode as PNG bytes (after [`BarChart::validate`]).
    pub fn to_png(&self, width: u32, height: u32) -> Result<Vec<u8>> {
        self.validate()?;
        crate::image_io::encode_png(&try_render(self, width, height)?)
    }

    /// Render and write as PNG, atomically (after [`BarChart::validate`]).
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        self.validate()?;
        crate::image_io::write_png(path, &try_render(self, width, height)?)
    }
}

#[cfg(test)]
mod tests;
