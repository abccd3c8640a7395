//! Line, scatter and grouped-bar plots rendered to PNG with [`plotters`] (bitmap backend) and an
//! embedded font, so no system fonts are needed: axes with "nice" ticks (1-2-5 steps, decades on
//! logarithmic axes), grid, tick and axis labels, a title, a legend placed in a corner free of data
//! (else in a band above the plot), markers and error bars.
//!
//! Text is DejaVu Sans (`assets/DejaVuSans.ttf`, Bitstream Vera licence next to it), drawn by
//! plotters' `ab_glyph` font backend at a size that grows with the image. Non-finite points (and
//! points <= 0 on a logarithmic axis) are skipped and break a line, as in common plotting
//! libraries; a single point, equal values or no data at all render an ordinary frame rather than
//! failing.
//!
//! Plotters draws what it is given; this module chooses what: axis ranges, tick values and labels,
//! layout, and where the legend goes.
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

use std::ops::Range;
use std::path::Path;

use image::{Rgb, RgbImage};
use plotters::backend::BitMapBackend;
use plotters::chart::{ChartBuilder, ChartContext};
use plotters::coord::Shift;
use plotters::coord::cartesian::Cartesian2d;
use plotters::coord::ranged1d::{KeyPointHint, NoDefaultFormatting, Ranged, ValueFormatter};
use plotters::drawing::{DrawingArea, IntoDrawingArea};
use plotters::element::{Circle, PathElement, Polygon, Rectangle, Text};
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{Color, FontDesc, FontStyle, IntoFont, RGBColor, ShapeStyle, TextStyle};

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
// ticks

/// A "nice" step `m * 10^e` with `m` in {1, 2, 5}.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Step {
    m: i64,
    e: i32,
}

impl Step {
    /// The smallest nice step >= `raw` (`raw` positive and finite).
    fn at_least(raw: f64) -> Step {
        let mut e = raw.log10().floor() as i32;
        // guard the floor against rounding (log10(1000) may come out as 2.9999...)
        if pow10(e + 1) <= raw {
            e += 1;
        }
        if pow10(e) > raw {
            e -= 1;
        }
        let mut s = Step { m: 1, e };
        while s.value() < raw * (1.0 - 1e-12) {
            s = s.next();
        }
        s
    }

    fn next(self) -> Step {
        match self.m {
            1 => Step { m: 2, e: self.e },
            2 => Step { m: 5, e: self.e },
            _ => Step {
                m: 1,
                e: self.e + 1,
            },
        }
    }

    fn value(self) -> f64 {
        self.m as f64 * pow10(self.e)
    }

    /// `k * step`, rounded like the decimal it stands for (0.1 * 3 is 0.3, not 0.30000000000000004).
    fn multiple(self, k: i64) -> f64 {
        let n = (k * self.m) as f64;
        if self.e >= 0 {
            n * pow10(self.e)
        } else {
            n / pow10(-self.e)
        }
    }
}

/// 10^e, exact for every power of ten a double can hold (parsed from its decimal form).
fn pow10(e: i32) -> f64 {
    format!("1e{e}").parse().unwrap_or(f64::NAN)
}

/// At most `max_ticks` (at least 2) tick values on a linear axis from `lo` to `hi`: multiples of the
/// smallest step of the form 1, 2 or 5 times a power of ten that keeps the count within the limit.
/// Values are exact decimals (0.3, not 0.30000000000000004). Returns `[lo]` when `lo == hi` and
/// nothing for non-finite or reversed bounds.
///
/// ```
/// use veila_data::vis::plot::linear_ticks;
/// assert_eq!(linear_ticks(0.0, 1.0, 6), [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]);
/// assert_eq!(linear_ticks(0.0, 1.0, 5), [0.0, 0.5, 1.0]);
/// ```
pub fn linear_ticks(lo: f64, hi: f64, max_ticks: usize) -> Vec<f64> {
    linear_ticks_step(lo, hi, max_ticks)
        .map(|(t, _)| t)
        .unwrap_or_else(|| {
            if lo == hi && lo.is_finite() {
                vec![lo]
            } else {
                Vec::new()
            }
        })
}

fn linear_ticks_step(lo: f64, hi: f64, max_ticks: usize) -> Option<(Vec<f64>, Step)> {
    let span = hi - lo;
    if !(lo.is_finite() && hi.is_finite() && span.is_finite() && span > 0.0) {
        return None;
    }
    let max_ticks = max_ticks.max(2);
    let raw = span / max_ticks as f64;
    if !(raw.is_normal() && raw > 0.0) {
        // a range so narrow that its step underflows
        return None;
    }
    let mut step = Step::at_least(raw);
    loop {
        let v = step.value();
        let (k0, k1) = ((lo / v - 1e-9).ceil(), (hi / v + 1e-9).floor());
        if !(k0.is_finite() && k1.is_finite()) || k0.abs() > 1e15 || k1.abs() > 1e15 {
            return None;
        }
        if k1 - k0 + 1.0 <= max_ticks as f64 {
            let ticks = (k0 as i64..=k1 as i64).map(|k| step.multiple(k)).collect();
            return Some((ticks, step));
        }
        step = step.next();
    }
}

/// At most `max_ticks` (at least 2) tick values on a logarithmic axis from `lo` to `hi` (both > 0):
/// powers of ten (every n-th decade when there are too many); when fewer than two decades lie in the
/// range, 1-2-5 multiples of powers of ten; when even those are fewer than two, linear ticks.
///
/// ```
/// use veila_data::vis::plot::log_ticks;
/// assert_eq!(log_ticks(0.5, 2000.0, 10), [1.0, 10.0, 100.0, 1000.0]);
/// assert_eq!(log_ticks(2.0, 60.0, 10), [2.0, 5.0, 10.0, 20.0, 50.0]);
/// ```
pub fn log_ticks(lo: f64, hi: f64, max_ticks: usize) -> Vec<f64> {
    if !(lo > 0.0 && hi >= lo && hi.is_finite()) {
        return Vec::new();
    }
    let max_ticks = max_ticks.max(2);
    let (d0, d1) = decade_bounds(lo, hi);
    let decades = d1 - d0 + 1;
    if decades >= 2 {
        let stride = (decades as usize).div_ceil(max_ticks) as i32;
        return (d0..=d1)
            .filter(|k| k.rem_euclid(stride) == 0)
            .map(pow10)
            .collect();
    }
    let (e0, e1) = (lo.log10().floor() as i32 - 1, hi.log10().floor() as i32 + 1);
    let mut v: Vec<f64> = (e0..=e1)
        .flat_map(|e| [1, 2, 5].map(|m| Step { m, e }.multiple(1)))
        .filter(|&t| t >= lo * (1.0 - 1e-12) && t <= hi * (1.0 + 1e-12))
        .collect();
    if v.len() >= 2 && v.len() <= max_ticks {
        return v;
    }
    v = linear_ticks(lo, hi, max_ticks);
    v.retain(|&t| t > 0.0);
    v
}

/// First and last power-of-ten exponent inside `[lo, hi]` (robust to log10 rounding).
fn decade_bounds(lo: f64, hi: f64) -> (i32, i32) {
    let mut d0 = lo.log10().ceil() as i32;
    if pow10(d0 - 1) >= lo * (1.0 - 1e-12) {
        d0 -= 1;
    }
    let mut d1 = hi.log10().floor() as i32;
    if pow10(d1 + 1) <= hi * (1.0 + 1e-12) {
        d1 += 1;
    }
    (d0, d1)
}

/// Tick labels for linear ticks with the given step: fixed decimals as the step needs them, or
/// scientific notation (`2.5e-5`) for very large or very small values.
fn linear_labels(ticks: &[f64], step: Step) -> Vec<String> {
    let max_abs = ticks.iter().fold(0.0f64, |m, t| m.max(t.abs()));
    let scientific = max_abs >= 1e6 || (max_abs > 0.0 && max_abs < 1e-3);
    ticks
        .iter()
        .map(|&t| {
            if t == 0.0 && scientific {
                "0".to_string()
            } else if scientific {
                let digits = (t.abs().log10().floor() as i32 - step.e).clamp(0, 8) as usize;
                trim_scientific(&format!("{t:.digits$e}"))
            } else {
                let decimals = (-step.e).max(0) as usize;
                // `t + 0.0` turns -0.0 into 0.0
                format!("{:.decimals$}", t + 0.0)
            }
        })
        .collect()
}

/// Tick labels on a logarithmic axis: plain decimals from 0.001 to 10000, scientific otherwise.
fn log_labels(ticks: &[f64]) -> Vec<String> {
    ticks
        .iter()
        .map(|&t| {
            if (1e-3..1e5).contains(&t) {
                format!("{t}")
            } else {
                trim_scientific(&format!("{t:e}"))
            }
        })
        .collect()
}

/// `1.50e-5` -> `1.5e-5`, `2.0e3` -> `2e3`.
fn trim_scientific(s: &str) -> String {
    match s.split_once('e') {
        Some((mant, exp)) if mant.contains('.') => {
            let mant = mant.trim_end_matches('0').trim_end_matches('.');
            format!("{mant}e{exp}")
        }
        _ => s.to_string(),
    }
}

// ------------------------------------------------------------------------------------------------
// axes and layout

/// A data axis: the value range shown and whether it is logarithmic.
#[derive(Debug, Clone, Copy, PartialEq)]
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
        let f = if self.log {
            if v <= 0.0 {
                return None;
            }
            (v.log10() - self.lo.log10()) / (self.hi.log10() - self.lo.log10())
        } else {
            (v - self.lo) / (self.hi - self.lo)
        };
        f.is_finite().then_some(f)
    }
}

/// The plot area in image pixel coordinates: `left` / `top` are the first pixel column / row inside
/// it, `right` / `bottom` the last (`lo` of the x axis maps to `left`, `hi` to `right`; `lo` of the
/// y axis to `bottom`, `hi` to `top`).
#[derive(Debug, Clone, Copy, PartialEq)]
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

impl PixelRect {
    fn width(&self) -> f64 {
        self.right - self.left
    }
    fn height(&self) -> f64 {
        self.bottom - self.top
    }
    fn contains(&self, (x, y): (f64, f64)) -> bool {
        x >= self.left && x <= self.right && y >= self.top && y <= self.bottom
    }
}

/// Where a plot's data lands in the image: the plot area, the two axes and their ticks.
/// [`Plot::layout`] gives the layout [`Plot::render`] uses, so callers (and tests) can map data to
/// pixels: the point `(x, y)` is drawn at `(x_to_px(x), y_to_px(y))` in continuous pixel
/// coordinates, i.e. in pixel `(floor(px), floor(py))`.
#[derive(Debug, Clone, PartialEq)]
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
        self.x
            .fraction(x)
            .map(|f| self.area.left + f * self.area.width())
    }

    /// Vertical pixel coordinate of data value `y` (`None` if the axis cannot show it).
    pub fn y_to_px(&self, y: f64) -> Option<f64> {
        self.y
            .fraction(y)
            .map(|f| self.area.bottom - f * self.area.height())
    }

    /// Pixel coordinates of a data point.
    pub fn to_px(&self, (x, y): (f64, f64)) -> Option<(f64, f64)> {
        Some((self.x_to_px(x)?, self.y_to_px(y)?))
    }
}

/// Font size in pixels for an image: 3.6 % of the short side (18 px at 800 x 500), at least 9.
fn text_px_for(width: u32, height: u32) -> f64 {
    (0.036 * width.min(height) as f64).clamp(9.0, 64.0)
}

/// Fit a range to the given values with a 4 % margin (in log10 space on logarithmic axes); a fixed
/// range is used as given when it is usable.
fn fit_axis(values: impl Iterator<Item = f64>, log: bool, fixed: Option<(f64, f64)>) -> Axis {
    if let Some((lo, hi)) = fixed {
        let usable = lo.is_finite() && hi.is_finite() && hi > lo && (!log || lo > 0.0);
        if usable {
            return Axis { lo, hi, log };
        }
    }
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        if v.is_finite() && (!log || v > 0.0) {
            let t = if log { v.log10() } else { v };
            lo = lo.min(t);
            hi = hi.max(t);
        }
    }
    if lo > hi {
        // no data
        return if log {
            Axis {
                lo: 1.0,
                hi: 10.0,
                log,
            }
        } else {
            Axis {
                lo: 0.0,
                hi: 1.0,
                log,
            }
        };
    }
    let span = hi - lo;
    if !span.is_finite() || span <= 1e-12 * lo.abs().max(hi.abs()) {
        // one value (or a range too small or too large to show): a window around it
        let c = if span.is_finite() {
            0.5 * (lo + hi)
        } else {
            lo
        };
        let d = if log {
            0.5
        } else if c == 0.0 {
            1.0
        } else {
            0.1 * c.abs()
        };
        (lo, hi) = (c - d, c + d);
        if !(hi - lo).is_finite() {
            (lo, hi) = (c * 0.9, c * 1.1);
            if lo > hi {
                std::mem::swap(&mut lo, &mut hi);
            }
        }
    } else {
        let m = 0.04 * span;
        (lo, hi) = (lo - m, hi + m);
        if !(hi - lo).is_finite() {
            (lo, hi) = (lo + m, hi - m);
        }
    }
    let (lo, hi) = if log {
        (10f64.powf(lo), 10f64.powf(hi).min(f64::MAX))
    } else {
        (lo, hi)
    };
    let usable = lo.is_finite() && hi.is_finite() && hi > lo && (!log || lo > 0.0);
    match (usable, log) {
        (true, _) => Axis { lo, hi, log },
        // values at the very ends of the floating-point range: a plain frame
        (false, true) => Axis {
            lo: 1.0,
            hi: 10.0,
            log,
        },
        (false, false) => Axis {
            lo: 0.0,
            hi: 1.0,
            log,
        },
    }
}

/// Ticks within the axis with labels, at most `max_ticks`.
fn axis_ticks(axis: &Axis, max_ticks: usize) -> Vec<(f64, String)> {
    if axis.log {
        let t = log_ticks(axis.lo, axis.hi, max_ticks);
        let l = log_labels(&t);
        t.into_iter().zip(l).collect()
    } else {
        match linear_ticks_step(axis.lo, axis.hi, max_ticks) {
            Some((t, step)) => {
                let l = linear_labels(&t, step);
                t.into_iter().zip(l).collect()
            }
            None => Vec::new(),
        }
    }
}

/// Minor ticks on a logarithmic axis (2..9 times each shown decade) when every decade is labelled.
fn log_minor_ticks(axis: &Axis, major: &[(f64, String)]) -> Vec<f64> {
    if !axis.log || major.len() < 2 {
        return Vec::new();
    }
    let ratio = major[1].0 / major[0].0;
    if (ratio - 10.0).abs() > 1e-6 {
        return Vec::new();
    }
    let (d0, d1) = (
        axis.lo.log10().floor() as i32,
        axis.hi.log10().floor() as i32,
    );
    if d1 - d0 > 40 {
        return Vec::new();
    }
    (d0..=d1)
        .flat_map(|e| (2..=9).map(move |m| Step { m, e }.multiple(1)))
        .filter(|&v| v > axis.lo && v < axis.hi)
        .collect()
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

fn text_style(px: f64, color: [u8; 3]) -> TextStyle<'static> {
    font(px).color(&rgb(color))
}

/// Width in pixels of `text` in the plot font at `size_px`.
pub fn text_width(text: &str, size_px: f64) -> u32 {
    font(size_px).box_size(text).map_or(0, |(w, _)| w)
}

type Root<'b> = DrawingArea<BitMapBackend<'b>, Shift>;
type DrawResult<T = ()> = std::result::Result<T, Box<dyn std::error::Error + Send + Sync>>;

/// Draw `text` with the top of its capitals at `y`; `x` is its left end, centre or right end as
/// `h` says.
fn put_text(
    root: &Root<'_>,
    text: &str,
    px: f64,
    color: [u8; 3],
    (x, y): (f64, f64),
    h: HPos,
) -> DrawResult {
    if text.is_empty() {
        return Ok(());
    }
    let anchor = (x.round() as i32, (y + (CAP - BASELINE) * px).round() as i32);
    let style = text_style(px, color).pos(Pos::new(h, VPos::Top));
    root.draw(&Text::new(text.to_string(), anchor, style))?;
    Ok(())
}

/// Draw `text` onto `img` in the plot font at `size_px`, with the top-left corner of its capital
/// letters at `(x, y)`. Pixels outside the image are skipped.
pub fn draw_text(img: &mut RgbImage, x: i64, y: i64, text: &str, size_px: f64, color: Rgb<u8>) {
    let (w, h) = img.dimensions();
    if w == 0 || h == 0 || !(size_px > 0.0 && size_px.is_finite()) {
        return;
    }
    let root = BitMapBackend::with_buffer(img, (w, h)).into_drawing_area();
    let at = (
        x.clamp(-1 << 24, 1 << 24) as f64,
        y.clamp(-1 << 24, 1 << 24) as f64,
    );
    if let Err(e) = put_text(&root, text, size_px, color.0, at, HPos::Left) {
        tracing::warn!("drawing text {text:?}: {e}");
    }
}

/// `text` shortened with ".." so that it fits `max_w` pixels at `px`.
fn fit_text(text: &str, max_w: f64, px: f64) -> String {
    if text_width(text, px) as f64 <= max_w {
        return text.to_string();
    }
    let chars: Vec<char> = text.chars().collect();
    for keep in (0..chars.len()).rev() {
        let t: String = chars[..keep].iter().chain(['.', '.'].iter()).collect();
        if text_width(&t, px) as f64 <= max_w {
            return t;
        }
    }
    String::new()
}

// ------------------------------------------------------------------------------------------------
// frames: sizes, ticks and the plotters chart

/// One axis as a plotters coordinate: the range mapping of [`Axis`], with our ticks and labels.
#[derive(Debug, Clone)]
struct AxisCoord {
    axis: Axis,
    ticks: Vec<(f64, String)>,
    minor: Vec<f64>,
}

impl Ranged for AxisCoord {
    type FormatOption = NoDefaultFormatting;
    type ValueType = f64;

    fn map(&self, v: &f64, limit: (i32, i32)) -> i32 {
        let f = self.axis.fraction(*v).unwrap_or(0.0);
        let px = limit.0 as f64 + f * (limit.1 - limit.0) as f64;
        px.floor().clamp(-1e6, 1e6) as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.minor.clone()
        } else {
            self.ticks.iter().map(|t| t.0).collect()
        }
    }

    fn range(&self) -> Range<f64> {
        self.axis.lo..self.axis.hi
    }
}

impl ValueFormatter<f64> for AxisCoord {
    fn format_ext(&self, v: &f64) -> String {
        self.ticks
            .iter()
            .find(|t| t.0 == *v)
            .map(|t| t.1.clone())
            .unwrap_or_default()
    }
}

type Chart<'a, 'b> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<AxisCoord, AxisCoord>>;

/// Sizes in pixels that follow the font size `s`.
#[derive(Debug, Clone, Copy)]
struct Metrics {
    s: f64,
    pad: f64,
    tick: i32,
    line_w: u32,
    marker_r: f64,
}

impl Metrics {
    fn new(s: f64) -> Self {
        Metrics {
            s,
            pad: (0.6 * s).round(),
            tick: (0.3 * s).round().max(2.0) as i32,
            line_w: (s / 8.0).round().max(1.0) as u32,
            marker_r: (0.3 * s).max(2.5),
        }
    }
}

/// What goes along the x axis.
enum XSpec<'a> {
    Numeric(Axis),
    Categories(&'a [String]),
}

/// What a chart shows besides its data.
struct ChartSpec<'a> {
    title: &'a str,
    x_label: &'a str,
    y_label: &'a str,
    x: XSpec<'a>,
    y: Axis,
}

/// The chart's layout before plotters places it: margins, label areas, axes and (fitted) texts.
struct Frame {
    m: Metrics,
    /// ChartBuilder margins (top, right, bottom, left) and label area sizes (x below, y left).
    margins: [u32; 4],
    x_area: u32,
    y_area: u32,
    x: AxisCoord,
    y: AxisCoord,
    title: String,
    x_label: String,
    y_label: String,
    /// Top of the band reserved for a legend above the plot area (when one was asked for).
    legend_top: f64,
    vertical_grid: bool,
}

fn widest(ticks: &[(f64, String)], s: f64) -> f64 {
    ticks
        .iter()
        .map(|(_, l)| text_width(l, s))
        .max()
        .unwrap_or(0) as f64
}

fn compute_frame(width: u32, height: u32, spec: &ChartSpec<'_>, legend_band: f64) -> Frame {
    let m = Metrics::new(text_px_for(width, height));
    let (s, pad, tick) = (m.s, m.pad, m.tick as f64);
    let (w, h) = (width as f64, height as f64);
    let title_px = 1.2 * s;
    let title = fit_text(spec.title, w - 2.0 * pad, title_px);
    let mut top = pad;
    if !title.is_empty() {
        top += (CAP + 0.2) * title_px + 0.6 * s;
    }
    let legend_top = top;
    top += legend_band;
    // tick labels hang from twice the tick length below the axis (plotters' spacing); the axis
    // label sits at the bottom of the label area
    let mut x_area = 2.0 * tick + 0.75 * s;
    if !spec.x_label.is_empty() {
        x_area += 1.3 * s;
    }
    let bottom = (0.4 * s).round();
    let plot_h = h - top - x_area - bottom;
    let y_axis = spec.y;
    let mut y_ticks = axis_ticks(&y_axis, ((plot_h / (2.0 * s)) as usize).clamp(2, 10));
    while y_ticks.len() > 2 && plot_h / (y_ticks.len() as f64) < 1.6 * s {
        let n = y_ticks.len() - 1;
        y_ticks = axis_ticks(&y_axis, n);
    }
    let mut y_area = 2.0 * tick + widest(&y_ticks, s);
    if !spec.y_label.is_empty() {
        y_area += 1.2 * s;
    }
    let mut right = pad.max(0.5 * s);
    let (x_coord, vertical_grid) = match spec.x {
        XSpec::Numeric(xa) => {
            let mut x_ticks = Vec::new();
            for _pass in 0..2 {
                let plot_w = w - pad - y_area - right;
                let mut max_ticks = ((plot_w / (3.0 * s)) as usize).clamp(2, 12);
                loop {
                    x_ticks = axis_ticks(&xa, max_ticks);
                    let spacing = plot_w / (x_ticks.len().max(1) as f64);
                    if max_ticks <= 2 || widest(&x_ticks, s) + 1.2 * s <= spacing {
                        break;
                    }
                    max_ticks -= 1;
                }
                // the last label is centred on its tick: keep it inside the image
                let need = x_ticks
                    .last()
                    .map_or(0.0, |(_, l)| text_width(l, s) as f64 / 2.0 + 0.2 * s);
                if need <= right {
                    break;
                }
                right = need;
            }
            let minor = log_minor_ticks(&xa, &x_ticks);
            let coord = AxisCoord {
                axis: xa,
                ticks: x_ticks,
                minor,
            };
            (coord, true)
        }
        XSpec::Categories(names) => {
            let n = names.len().max(1) as f64;
            let slot = (w - pad - y_area - right) / n;
            let ticks = names
                .iter()
                .enumerate()
                .map(|(i, name)| (i as f64 + 0.5, fit_text(name, slot - 0.3 * s, s)))
                .collect();
            let axis = Axis {
                lo: 0.0,
                hi: n,
                log: false,
            };
            let coord = AxisCoord {
                axis,
                ticks,
                minor: Vec::new(),
            };
            (coord, false)
        }
    };
    let plot_w = w - pad - y_area - right;
    let y_minor = log_minor_ticks(&y_axis, &y_ticks);
    let mut frame = Frame {
        m,
        margins: [top, right, bottom, pad].map(|v| v.round().max(0.0) as u32),
        x_area: x_area.round() as u32,
        y_area: y_area.round() as u32,
        x: x_coord,
        y: AxisCoord {
            axis: y_axis,
            ticks: y_ticks,
            minor: y_minor,
        },
        title,
        x_label: fit_text(spec.x_label, plot_w.max(0.0), s),
        y_label: fit_text(spec.y_label, plot_h.max(0.0), s),
        legend_top,
        vertical_grid,
    };
    if plot_w < 4.0 * s || plot_h < 3.0 * s {
        // too small for text: the plot area fills the image
        frame.margins = [0; 4];
        frame.x_area = 0;
        frame.y_area = 0;
        frame.title.clear();
        frame.x_label.clear();
        frame.y_label.clear();
        frame.x.ticks.clear();
        frame.y.ticks.clear();
    }
    frame
}

fn build<'a, 'b>(root: &'a Root<'b>, f: &Frame) -> DrawResult<Chart<'a, 'b>> {
    let [top, right, bottom, left] = f.margins;
    let mut b = ChartBuilder::on(root);
    b.margin_top(top)
        .margin_right(right)
        .margin_bottom(bottom)
        .margin_left(left)
        .x_label_area_size(f.x_area)
        .y_label_area_size(f.y_area);
    Ok(b.build_cartesian_2d(f.x.clone(), f.y.clone())?)
}

fn layout_of(chart: &Chart<'_, '_>, f: &Frame) -> PlotLayout {
    let (xr, yr) = chart.plotting_area().get_pixel_range();
    PlotLayout {
        area: PixelRect {
            left: xr.start as f64,
            top: yr.start as f64,
            right: (xr.end - 1).max(xr.start) as f64,
            bottom: (yr.end - 1).max(yr.start) as f64,
        },
        x: f.x.axis,
        y: f.y.axis,
        x_ticks: f.x.ticks.clone(),
        y_ticks: f.y.ticks.clone(),
        text_px: f.m.s,
    }
}

/// Grid, axes, ticks and their labels, axis labels (plotters' mesh).
fn draw_axes(chart: &mut Chart<'_, '_>, f: &Frame) -> DrawResult {
    let s = f.m.s;
    let mut mesh = chart.configure_mesh();
    mesh.bold_line_style(rgb(GRID).stroke_width(1))
        .light_line_style(rgb(MINOR_GRID).stroke_width(1))
        .axis_style(rgb(FRAME).stroke_width(1))
        .label_style(text_style(s, TEXT))
        .axis_desc_style(text_style(s, TEXT))
        .set_all_tick_mark_size(f.m.tick)
        // centre the capitals of the y tick labels on their ticks (see BASELINE)
        .y_label_offset(((1.0 / 2.48 + CAP / 2.0 - BASELINE) * s).round() as i32);
    if !f.x_label.is_empty() {
        mesh.x_desc(f.x_label.as_str());
    }
    if !f.y_label.is_empty() {
        mesh.y_desc(f.y_label.as_str());
    }
    if !f.vertical_grid {
        mesh.disable_x_mesh();
    }
    mesh.draw()?;
    Ok(())
}

/// The frame around the plot area, and the title.
fn draw_frame_and_title(root: &Root<'_>, layout: &PlotLayout, f: &Frame) -> DrawResult {
    let a = layout.area;
    let (l, t, r, b) = (a.left as i32, a.top as i32, a.right as i32, a.bottom as i32);
    root.draw(&Rectangle::new(
        [(l - 1, t - 1), (r + 1, b + 1)],
        rgb(FRAME).stroke_width(1),
    ))?;
    if !f.title.is_empty() {
        let px = 1.2 * f.m.s;
        let (w, _) = root.dim_in_pixel();
        let tw = text_width(&f.title, px) as f64;
        let x = (a.left + 0.5 * a.width() - 0.5 * tw)
            .min(w as f64 - f.m.pad - tw)
            .max(f.m.pad);
        put_text(root, &f.title, px, TEXT, (x, f.m.pad), HPos::Left)?;
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------------
// marks

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

fn px_i((x, y): (f64, f64)) -> (i32, i32) {
    (
        x.floor().clamp(-1e6, 1e6) as i32,
        y.floor().clamp(-1e6, 1e6) as i32,
    )
}

fn draw_marker(root: &Root<'_>, p: (f64, f64), shape: Marker, r: f64, c: [u8; 3]) -> DrawResult {
    let (x, y) = px_i(p);
    let style = rgb(c).filled();
    let pt = |dx: f64, dy: f64| (x + (dx * r).round() as i32, y + (dy * r).round() as i32);
    match shape {
        Marker::Circle => root.draw(&Circle::new((x, y), r.round() as i32, style))?,
        Marker::Square => root.draw(&Rectangle::new([pt(-0.85, -0.85), pt(0.85, 0.85)], style))?,
        Marker::Diamond => root.draw(&Polygon::new(
            vec![pt(0.0, -1.2), pt(1.2, 0.0), pt(0.0, 1.2), pt(-1.2, 0.0)],
            style,
        ))?,
        Marker::TriangleUp => root.draw(&Polygon::new(
            vec![pt(0.0, -1.25), pt(1.1, 0.65), pt(-1.1, 0.65)],
            style,
        ))?,
        Marker::TriangleDown => root.draw(&Polygon::new(
            vec![pt(0.0, 1.25), pt(1.1, -0.65), pt(-1.1, -0.65)],
            style,
        ))?,
    }
    Ok(())
}

/// The part of segment `a`-`b` inside `r` (Liang-Barsky); `None` when none is.
fn clip_segment(a: (f64, f64), b: (f64, f64), r: &PixelRect) -> Option<((f64, f64), (f64, f64))> {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    if !(dx.is_finite() && dy.is_finite()) {
        return None;
    }
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - r.left),
        (dx, r.right - a.0),
        (-dy, a.1 - r.top),
        (dy, r.bottom - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else if p < 0.0 {
            t0 = t0.max(q / p);
        } else {
            t1 = t1.min(q / p);
        }
    }
    (t0 <= t1).then_some((
        (a.0 + t0 * dx, a.1 + t0 * dy),
        (a.0 + t1 * dx, a.1 + t1 * dy),
    ))
}

/// A polyline through the given pixel points (`None` breaks it), clipped to `area`.
fn draw_polyline(
    root: &Root<'_>,
    pts: &[Option<(f64, f64)>],
    area: &PixelRect,
    style: ShapeStyle,
) -> DrawResult {
    let mut path: Vec<(i32, i32)> = Vec::new();
    let mut last: Option<(f64, f64)> = None;
    let flush = |path: &mut Vec<(i32, i32)>| -> DrawResult {
        if path.len() >= 2 {
            root.draw(&PathElement::new(std::mem::take(path), style))?;
        }
        path.clear();
        Ok(())
    };
    for w in pts.windows(2) {
        let (Some(a), Some(b)) = (w[0], w[1]) else {
            continue;
        };
        let Some((ca, cb)) = clip_segment(a, b, area) else {
            continue;
        };
        if last != Some(ca) {
            flush(&mut path)?;
            path.push(px_i(ca));
        }
        path.push(px_i(cb));
        last = Some(cb);
    }
    flush(&mut path)
}

/// A vertical error bar from `top` to `bot` at `x` with caps `cap` pixels to either side, clipped
/// to `area` (caps only where the bar ends inside).
fn draw_error_bar(
    root: &Root<'_>,
    x: f64,
    (top, bot): (f64, f64),
    cap: f64,
    area: &PixelRect,
) -> DrawResult {
    let style = rgb(ERROR_BAR).stroke_width(1);
    if !(x >= area.left && x <= area.right) {
        return Ok(());
    }
    let (t, b) = (top.max(area.top), bot.min(area.bottom));
    if t > b {
        return Ok(());
    }
    let xi = x.floor() as i32;
    let (ti, bi) = (t.floor() as i32, b.floor() as i32);
    root.draw(&PathElement::new(vec![(xi, ti), (xi, bi)], style))?;
    let c = cap.round() as i32;
    for (end, inside) in [(ti, top >= area.top), (bi, bot <= area.bottom)] {
        if inside {
            root.draw(&PathElement::new(vec![(xi - c, end), (xi + c, end)], style))?;
        }
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------------
// legends

/// A legend entry's key.
#[derive(Debug, Clone, Copy)]
enum Key {
    Series {
        color: [u8; 3],
        line: bool,
        marker: Option<Marker>,
    },
    Bar([u8; 3]),
}

/// Where the legend goes.
#[derive(Debug, Clone, Copy)]
enum LegendPlace {
    /// A boxed legend with its top-left corner here, inside the plot area.
    Inside(f64, f64),
    /// Rows of entries in the band above the plot area.
    Above,
}

/// Legend sizes, following the font size.
struct LegendMetrics {
    m: Metrics,
    key_w: f64,
    gap: f64,
    pad: f64,
    row_h: f64,
    spacing: f64,
}

impl LegendMetrics {
    fn new(m: Metrics) -> Self {
        let s = m.s;
        LegendMetrics {
            m,
            key_w: 1.8 * s,
            gap: 0.4 * s,
            pad: 0.5 * s,
            row_h: 1.3 * s,
            spacing: 1.2 * s,
        }
    }

    /// Width of one entry (key, gap, name).
    fn entry_w(&self, name: &str) -> f64 {
        self.key_w + self.gap + text_width(name, self.m.s) as f64
    }

    /// Size of the boxed legend.
    fn box_size(&self, names: &[String]) -> (f64, f64) {
        let w = names.iter().map(|n| self.entry_w(n)).fold(0.0, f64::max) + 2.0 * self.pad;
        let rows = names.len().max(1) as f64;
        let h = 2.0 * self.pad + (rows - 1.0) * self.row_h + 0.85 * self.m.s;
        (w.round(), h.round())
    }

    /// Entries of the legend above the plot, wrapped into rows that fit `max_w`.
    fn rows(&self, names: &[String], max_w: f64) -> Vec<Vec<usize>> {
        let mut rows: Vec<Vec<usize>> = Vec::new();
        let mut used = 0.0;
        for (i, n) in names.iter().enumerate() {
            let w = self.entry_w(n);
            match rows.last_mut() {
                Some(row) if used + self.spacing + w <= max_w => {
                    row.push(i);
                    used += self.spacing + w;
                }
                _ => {
                    rows.push(vec![i]);
                    used = w;
                }
            }
        }
        rows
    }

    fn above_width(&self, width: u32) -> f64 {
        width as f64 - 2.0 * self.m.pad
    }
}

/// Legend names shortened to fit the image.
fn legend_names(entries: &[(String, Key)], width: u32, lm: &LegendMetrics) -> Vec<String> {
    let max_text = (lm.above_width(width) - lm.key_w - lm.gap - 2.0 * lm.pad).max(0.0);
    entries
        .iter()
        .map(|(n, _)| fit_text(n, max_text, lm.m.s))
        .collect()
}

/// The first corner of the plot area (top right, top left, bottom right, bottom left) where a boxed
/// legend covers none of the `occupied` points; `None` when every corner covers data.
fn free_corner(
    layout: &PlotLayout,
    lm: &LegendMetrics,
    names: &[String],
    occupied: &[(f64, f64)],
) -> Option<(f64, f64)> {
    let a = layout.area;
    let (w, h) = lm.box_size(names);
    let inset = 0.5 * lm.m.s;
    if w + 2.0 * inset > a.width() || h + 2.0 * inset > a.height() {
        return None;
    }
    let corners = [
        (a.right - inset - w, a.top + inset),
        (a.left + inset, a.top + inset),
        (a.right - inset - w, a.bottom - inset - h),
        (a.left + inset, a.bottom - inset - h),
    ];
    let margin = 0.25 * lm.m.s;
    corners.into_iter().find(|&(x, y)| {
        let r = PixelRect {
            left: x - margin,
            top: y - margin,
            right: x + w + margin,
            bottom: y + h + margin,
        };
        !occupied.iter().any(|p| r.contains(*p))
    })
}

/// One entry: its key from `kx` and its name after it, capitals centred on `cy`.
fn draw_entry(
    root: &Root<'_>,
    lm: &LegendMetrics,
    key: Key,
    name: &str,
    kx: f64,
    cy: f64,
) -> DrawResult {
    let s = lm.m.s;
    match key {
        Key::Series {
            color,
            line,
            marker,
        } => {
            if line {
                let y = cy.floor() as i32;
                let pts = vec![(kx.round() as i32, y), ((kx + lm.key_w).round() as i32, y)];
                root.draw(&PathElement::new(pts, rgb(color).stroke_width(lm.m.line_w)))?;
            }
            if let Some(mk) = marker {
                draw_marker(root, (kx + lm.key_w / 2.0, cy), mk, lm.m.marker_r, color)?;
            }
        }
        Key::Bar(color) => {
            let side = CAP * s;
            let (x0, y0) = (kx + lm.key_w / 2.0 - side / 2.0, cy - side / 2.0);
            root.draw(&Rectangle::new(
                [px_i((x0, y0)), px_i((x0 + side, y0 + side))],
                rgb(color).filled(),
            ))?;
        }
    }
    let tx = kx + lm.key_w + lm.gap;
    put_text(root, name, s, TEXT, (tx, cy - CAP * s / 2.0), HPos::Left)
}

fn draw_legend(
    root: &Root<'_>,
    frame: &Frame,
    layout: &PlotLayout,
    entries: &[(String, Key)],
    place: LegendPlace,
) -> DrawResult {
    if entries.is_empty() {
        return Ok(());
    }
    let (width, _) = root.dim_in_pixel();
    let lm = LegendMetrics::new(frame.m);
    let names = legend_names(entries, width, &lm);
    // capitals of the first row: centred this far below the top of the first row
    let first = 0.4 * lm.m.s;
    match place {
        LegendPlace::Inside(x, y) => {
            let (w, h) = lm.box_size(&names);
            let (x0, y0) = (x.round() as i32, y.round() as i32);
            let (x1, y1) = (x0 + w as i32, y0 + h as i32);
            root.draw(&Rectangle::new(
                [(x0, y0), (x1, y1)],
                rgb(BACKGROUND).mix(0.9).filled(),
            ))?;
            root.draw(&Rectangle::new(
                [(x0, y0), (x1, y1)],
                rgb(LEGEND_BORDER).stroke_width(1),
            ))?;
            for (i, ((_, key), name)) in entries.iter().zip(&names).enumerate() {
                let cy = y0 as f64 + lm.pad + first + i as f64 * lm.row_h;
                draw_entry(root, &lm, *key, name, x0 as f64 + lm.pad, cy)?;
            }
        }
        LegendPlace::Above => {
            let a = layout.area;
            for (r, row) in lm.rows(&names, lm.above_width(width)).iter().enumerate() {
                let total: f64 = row.iter().map(|&i| lm.entry_w(&names[i])).sum::<f64>()
                    + lm.spacing * (row.len().saturating_sub(1)) as f64;
                let mut x = (a.left + 0.5 * (a.width() - total))
                    .min(width as f64 - lm.m.pad - total)
                    .max(lm.m.pad);
                let cy = frame.legend_top + first + r as f64 * lm.row_h;
                for &i in row {
                    draw_entry(root, &lm, entries[i].1, &names[i], x, cy)?;
                    x += lm.entry_w(&names[i]) + lm.spacing;
                }
            }
        }
    }
    Ok(())
}

/// Lay out a chart: the frame without a legend band when a corner of the plot area is free of
/// data, otherwise with the legend above the plot area.
fn plan<'a, 'b>(
    root: &'a Root<'b>,
    spec: &ChartSpec<'_>,
    entries: &[(String, Key)],
    occupancy: impl Fn(&PlotLayout) -> Vec<(f64, f64)>,
) -> DrawResult<(Frame, Chart<'a, 'b>, PlotLayout, Option<LegendPlace>)> {
    let (width, height) = root.dim_in_pixel();
    let frame = compute_frame(width, height, spec, 0.0);
    let chart = build(root, &frame)?;
    let layout = layout_of(&chart, &frame);
    if entries.is_empty() || frame.title.is_empty() && frame.x_area == 0 && frame.y_area == 0 {
        return Ok((frame, chart, layout, None));
    }
    let lm = LegendMetrics::new(frame.m);
    let names = legend_names(entries, width, &lm);
    if let Some((x, y)) = free_corner(&layout, &lm, &names, &occupancy(&layout)) {
        return Ok((frame, chart, layout, Some(LegendPlace::Inside(x, y))));
    }
    let band = lm.rows(&names, lm.above_width(width)).len() as f64 * lm.row_h;
    let frame = compute_frame(width, height, spec, band);
    let chart = build(root, &frame)?;
    let layout = layout_of(&chart, &frame);
    Ok((frame, chart, layout, Some(LegendPlace::Above)))
}

/// Render with `paint` onto a white image of the given size; drawing errors are logged and leave
/// what was drawn (use [`try_render`] to see them).
fn render_with(
    width: u32,
    height: u32,
    paint: impl FnOnce(&Root<'_>) -> DrawResult,
) -> std::result::Result<RgbImage, String> {
    let mut img = RgbImage::from_pixel(width, height, Rgb(BACKGROUND));
    if width == 0 || height == 0 {
        return Ok(img);
    }
    let res = {
        let root = BitMapBackend::with_buffer(&mut img, (width, height)).into_drawing_area();
        paint(&root).and_then(|()| Ok(root.present()?))
    };
    res.map(|()| img).map_err(|e| e.to_string())
}

/// `render_with`, turning a drawing error into the crate's error.
fn try_render(
    width: u32,
    height: u32,
    paint: impl FnOnce(&Root<'_>) -> DrawResult,
) -> Result<RgbImage> {
    render_with(width, height, paint).map_err(|message| Error::Invalid {
        what: "plot".into(),
        message: format!("drawing failed: {message}"),
    })
}

/// A layout without drawing: the chart planned on a scratch image of the size (at least 1 x 1).
fn layout_only(
    width: u32,
    height: u32,
    plan_of: impl FnOnce(&Root<'_>) -> DrawResult<PlotLayout>,
) -> PlotLayout {
    let (w, h) = (width.max(1), height.max(1));
    let mut buf = vec![0u8; w as usize * h as usize * 3];
    let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
    plan_of(&root).unwrap_or_else(|e| {
        tracing::warn!("plot layout: {e}");
        let unit = Axis {
            lo: 0.0,
            hi: 1.0,
            log: false,
        };
        PlotLayout {
            area: PixelRect {
                left: 0.0,
                top: 0.0,
                right: (w - 1) as f64,
                bottom: (h - 1) as f64,
            },
            x: unit,
            y: unit,
            x_ticks: Vec::new(),
            y_ticks: Vec::new(),
            text_px: text_px_for(w, h),
        }
    })
}
// ------------------------------------------------------------------------------------------------
// line / scatter plots

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

    fn axes(&self) -> (Axis, Axis) {
        let xs = self
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.0));
        let x = fit_axis(xs, self.x_log, self.x_range);
        let accepts = |v: f64| v.is_finite() && (!x.log || v > 0.0);
        let ys = self.series.iter().flat_map(|s| {
            s.points.iter().enumerate().flat_map(move |(i, &(px, py))| {
                let e = error_of(s, i);
                let keep = accepts(px);
                let lo = if self.y_log && py - e <= 0.0 {
                    py
                } else {
                    py - e
                };
                [(keep, lo), (keep, py + e)]
            })
        });
        let ys = ys.filter(|(k, _)| *k).map(|(_, v)| v);
        let y = fit_axis(ys, self.y_log, self.y_range);
        (x, y)
    }

    fn spec(&self) -> ChartSpec<'_> {
        let (x, y) = self.axes();
        ChartSpec {
            title: &self.title,
            x_label: &self.x_label,
            y_label: &self.y_label,
            x: XSpec::Numeric(x),
            y,
        }
    }

    fn legend_entries(&self) -> Vec<(String, Key)> {
        self.series
            .iter()
            .enumerate()
            .filter(|(_, s)| !s.name.is_empty())
            .map(|(i, s)| {
                let line = matches!(s.style, SeriesStyle::Line | SeriesStyle::LineMarkers);
                let marker = matches!(s.style, SeriesStyle::Markers | SeriesStyle::LineMarkers)
                    .then_some(MARKERS[i % MARKERS.len()]);
                (
                    s.name.clone(),
                    Key::Series {
                        color: series_color(i).0,
                        line,
                        marker,
                    },
                )
            })
            .collect()
    }

    /// Pixels the data covers (points, samples along lines and error bars), for legend placement.
    fn occupancy(&self, layout: &PlotLayout) -> Vec<(f64, f64)> {
        let step = 0.3 * layout.text_px;
        let mut out = Vec::new();
        let mut sample = |a: (f64, f64), b: (f64, f64)| {
            let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
            let n = (len / step).ceil().clamp(1.0, 500.0) as usize;
            for k in 0..=n {
                let t = k as f64 / n as f64;
                out.push((a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1)));
            }
        };
        for s in &self.series {
            let px: Vec<Option<(f64, f64)>> = s.points.iter().map(|&p| layout.to_px(p)).collect();
            for (i, p) in px.iter().enumerate() {
                let Some(p) = *p else { continue };
                sample(p, p);
                let e = error_of(s, i);
                if e > 0.0 {
                    let y = s.points[i].1;
                    let top = layout.y_to_px(y + e).unwrap_or(p.1);
                    let bot = layout.y_to_px(y - e).unwrap_or(layout.area.bottom);
                    sample((p.0, top), (p.0, bot));
                }
            }
            if matches!(s.style, SeriesStyle::Line | SeriesStyle::LineMarkers) {
                for w in px.windows(2) {
                    if let [Some(a), Some(b)] = w {
                        sample(*a, *b);
                    }
                }
            }
        }
        out
    }

    /// The layout [`Plot::render`] uses at this size (plot area, axes, ticks).
    pub fn layout(&self, width: u32, height: u32) -> PlotLayout {
        let entries = self.legend_entries();
        layout_only(width, height, |root| {
            Ok(plan(root, &self.spec(), &entries, |l| self.occupancy(l))?.2)
        })
    }

    /// Render to an RGB image of the given size. Never fails: non-finite or out-of-domain points are
    /// skipped, degenerate ranges get a window around the data, and a size of 0 gives an empty image.
    pub fn render(&self, width: u32, height: u32) -> RgbImage {
        match render_with(width, height, |root| self.paint(root)) {
            Ok(img) => img,
            Err(e) => {
                tracing::warn!("plot '{}': {e}", self.title);
                RgbImage::from_pixel(width, height, Rgb(BACKGROUND))
            }
        }
    }

    fn paint(&self, root: &Root<'_>) -> DrawResult {
        root.fill(&rgb(BACKGROUND))?;
        let entries = self.legend_entries();
        let (frame, mut chart, layout, place) =
            plan(root, &self.spec(), &entries, |l| self.occupancy(l))?;
        draw_axes(&mut chart, &frame)?;
        let m = frame.m;
        let area = layout.area;
        for (si, series) in self.series.iter().enumerate() {
            let color = series_color(si).0;
            let px: Vec<Option<(f64, f64)>> =
                series.points.iter().map(|&p| layout.to_px(p)).collect();
            let cap = 0.25 * m.s;
            for (i, p) in px.iter().enumerate() {
                let (Some((cx, _)), e) = (*p, error_of(series, i)) else {
                    continue;
                };
                if e <= 0.0 {
                    continue;
                }
                let y = series.points[i].1;
                let bot = if self.y_log && y - e <= 0.0 {
                    Some(area.bottom + 2.0 * cap)
                } else {
                    layout.y_to_px(y - e)
                };
                if let (Some(top), Some(bot)) = (layout.y_to_px(y + e), bot) {
                    draw_error_bar(root, cx, (top, bot), cap, &area)?;
                }
            }
            if matches!(series.style, SeriesStyle::Line | SeriesStyle::LineMarkers) {
                draw_polyline(root, &px, &area, rgb(color).stroke_width(m.line_w))?;
            }
            if matches!(
                series.style,
                SeriesStyle::Markers | SeriesStyle::LineMarkers
            ) {
                let marker = MARKERS[si % MARKERS.len()];
                for p in px.iter().flatten() {
                    // markers on the edge of the area are drawn whole
                    let inside = p.0 >= area.left - 0.5
                        && p.0 <= area.right + 0.5
                        && p.1 >= area.top - 0.5
                        && p.1 <= area.bottom + 0.5;
                    if inside {
                        draw_marker(root, *p, marker, m.marker_r, color)?;
                    }
                }
            }
        }
        draw_frame_and_title(root, &layout, &frame)?;
        if let Some(place) = place {
            draw_legend(root, &frame, &layout, &entries, place)?;
        }
        Ok(())
    }

    /// Render and encode as PNG bytes (after [`Plot::validate`]).
    pub fn to_png(&self, width: u32, height: u32) -> Result<Vec<u8>> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::encode_png(&try_render(width, height, |root| self.paint(root))?)
    }

    /// Render and write as PNG, atomically (after [`Plot::validate`]).
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::write_png(path, &try_render(width, height, |root| self.paint(root))?)
    }
}

/// The usable error bar half-length of point `i` (0 when absent, non-finite or not positive).
fn error_of(s: &Series, i: usize) -> f64 {
    s.error_bars
        .as_ref()
        .and_then(|e| e.get(i).copied())
        .filter(|e| e.is_finite() && *e > 0.0)
        .unwrap_or(0.0)
}

fn check_size(width: u32, height: u32) -> Result<()> {
    if width == 0 || height == 0 || width > 16384 || height > 16384 {
        return Err(Error::Invalid {
            what: "plot size".into(),
            message: format!("{width} x {height} px is outside 1..=16384 per side"),
        });
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------------
// bar charts

/// One bar in pixels: left, right, value end, zero end, error bar ends.
struct BarGeom {
    group: usize,
    x0: f64,
    x1: f64,
    value_px: f64,
    zero_px: f64,
    error_px: Option<(f64, f64)>,
}

impl BarChart {
    /// Check what [`BarChart::render`] tolerates silently: every group has one value (and error, if
    /// any) per category, and errors are not negative.
    pub fn validate(&self) -> Result<()> {
        for g in &self.groups {
            if g.values.len() != self.categories.len() {
                return Err(Error::Mismatch {
                    context: format!("bar group '{}'", g.name),
                    message: format!(
                        "{} values for {} categories",
                        g.values.len(),
                        self.categories.len()
                    ),
                });
            }
            if let Some(e) = &g.errors {
                if e.len() != self.categories.len() {
                    return Err(Error::Mismatch {
                        context: format!("bar group '{}'", g.name),
                        message: format!(
                            "{} errors for {} categories",
                            e.len(),
                            self.categories.len()
                        ),
                    });
                }
                if let Some(k) = e.iter().position(|v| *v < 0.0) {
                    return Err(Error::Invalid {
                        what: format!("errors of bar group '{}'", g.name),
                        message: format!("entry {k} is negative ({})", e[k]),
                    });
                }
            }
        }
        Ok(())
    }

    fn error(&self, g: &BarGroup, i: usize) -> f64 {
        g.errors
            .as_ref()
            .and_then(|e| e.get(i).copied())
            .filter(|e| e.is_finite() && *e > 0.0)
            .unwrap_or(0.0)
    }

    fn value_axis(&self) -> Axis {
        let (mut lo, mut hi) = (0.0f64, 0.0f64);
        for g in &self.groups {
            for (i, v) in g.values.iter().enumerate().take(self.categories.len()) {
                if !v.is_finite() {
                    continue;
                }
                let e = self.error(g, i);
                lo = lo.min(v - e);
                hi = hi.max(v + e);
            }
        }
        let span = hi - lo;
        if !span.is_finite() || span <= 0.0 {
            return Axis {
                lo: 0.0,
                hi: 1.0,
                log: false,
            };
        }
        // bars stand on zero: margins only on the side(s) away from it
        let m = 0.06 * span;
        Axis {
            lo: if lo < 0.0 { lo - m } else { 0.0 },
            hi: if hi > 0.0 { hi + m } else { 0.0 },
            log: false,
        }
    }

    fn spec(&self) -> ChartSpec<'_> {
        ChartSpec {
            title: &self.title,
            x_label: "",
            y_label: &self.y_label,
            x: XSpec::Categories(&self.categories),
            y: self.value_axis(),
        }
    }

    fn legend_entries(&self) -> Vec<(String, Key)> {
        self.groups
            .iter()
            .enumerate()
            .filter(|(_, g)| !g.name.is_empty())
            .map(|(i, g)| (g.name.clone(), Key::Bar(series_color(i).0)))
            .collect()
    }

    fn bars(&self, layout: &PlotLayout) -> Vec<BarGeom> {
        let n_cat = self.categories.len().max(1) as f64;
        let n_grp = self.groups.len().max(1) as f64;
        let slot = layout.area.width() / n_cat;
        let bar_w = 0.8 * slot / n_grp;
        let zero_px = layout.y_to_px(0.0).unwrap_or(layout.area.bottom);
        let mut out = Vec::new();
        for (gi, g) in self.groups.iter().enumerate() {
            for (ci, &v) in g.values.iter().enumerate().take(self.categories.len()) {
                let Some(value_px) = layout.y_to_px(v) else {
                    continue;
                };
                let x0 = layout.area.left + ci as f64 * slot + 0.1 * slot + gi as f64 * bar_w;
                let e = self.error(g, ci);
                let error_px = if e > 0.0 {
                    layout.y_to_px(v + e).zip(layout.y_to_px(v - e))
                } else {
                    None
                };
                out.push(BarGeom {
                    group: gi,
                    x0,
                    x1: x0 + bar_w,
                    value_px,
                    zero_px,
                    error_px,
                });
            }
        }
        out
    }

    fn occupancy(&self, layout: &PlotLayout) -> Vec<(f64, f64)> {
        let step = 0.3 * layout.text_px;
        let mut out = Vec::new();
        for b in self.bars(layout) {
            let (ya, yb) = (b.value_px.min(b.zero_px), b.value_px.max(b.zero_px));
            let top = b.error_px.map_or(ya, |(t, _)| t.min(ya));
            let ny = ((yb - top) / step).ceil().clamp(1.0, 200.0) as usize;
            let nx = ((b.x1 - b.x0) / step).ceil().clamp(1.0, 200.0) as usize;
            for i in 0..=nx {
                for j in 0..=ny {
                    let x = b.x0 + (b.x1 - b.x0) * i as f64 / nx as f64;
                    out.push((x, top + (yb - top) * j as f64 / ny as f64));
                }
            }
        }
        out
    }

    /// The layout [`BarChart::render`] uses (the x axis runs from 0 to the number of categories,
    /// category `i` centred on `i + 0.5`).
    pub fn layout(&self, width: u32, height: u32) -> PlotLayout {
        let entries = self.legend_entries();
        layout_only(width, height, |root| {
            Ok(plan(root, &self.spec(), &entries, |l| self.occupancy(l))?.2)
        })
    }

    /// Render to an RGB image of the given size. Never fails; non-finite values draw no bar.
    pub fn render(&self, width: u32, height: u32) -> RgbImage {
        match render_with(width, height, |root| self.paint(root)) {
            Ok(img) => img,
            Err(e) => {
                tracing::warn!("bar chart '{}': {e}", self.title);
                RgbImage::from_pixel(width, height, Rgb(BACKGROUND))
            }
        }
    }

    fn paint(&self, root: &Root<'_>) -> DrawResult {
        root.fill(&rgb(BACKGROUND))?;
        let entries = self.legend_entries();
        let (frame, mut chart, layout, place) =
            plan(root, &self.spec(), &entries, |l| self.occupancy(l))?;
        draw_axes(&mut chart, &frame)?;
        let area = layout.area;
        let bars = self.bars(&layout);
        for b in &bars {
            // a hairline gap between neighbouring bars
            let gap = if b.x1 - b.x0 > 6.0 { 1.0 } else { 0.0 };
            let ya = b.value_px.min(b.zero_px).max(area.top);
            let yb = b.value_px.max(b.zero_px).min(area.bottom);
            let (x0, x1) = (b.x0.round(), (b.x1.round() - gap - 1.0).max(b.x0.round()));
            root.draw(&Rectangle::new(
                [px_i((x0, ya)), px_i((x1, yb))],
                rgb(series_color(b.group).0).filled(),
            ))?;
        }
        for b in &bars {
            if let Some((t, bot)) = b.error_px {
                let gap = if b.x1 - b.x0 > 6.0 { 1.0 } else { 0.0 };
                let cap = (0.25 * (b.x1 - b.x0)).min(0.3 * frame.m.s);
                draw_error_bar(root, 0.5 * (b.x0 + b.x1 - gap), (t, bot), cap, &area)?;
            }
        }
        if layout.y.lo < 0.0 {
            // the zero line
            if let Some(zero) = layout.y_to_px(0.0) {
                let zy = zero.floor() as i32;
                root.draw(&PathElement::new(
                    vec![(area.left as i32, zy), (area.right as i32, zy)],
                    rgb(FRAME).stroke_width(1),
                ))?;
            }
        }
        draw_frame_and_title(root, &layout, &frame)?;
        if let Some(place) = place {
            draw_legend(root, &frame, &layout, &entries, place)?;
        }
        Ok(())
    }

    /// Render and encode as PNG bytes (after [`BarChart::validate`]).
    pub fn to_png(&self, width: u32, height: u32) -> Result<Vec<u8>> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::encode_png(&try_render(width, height, |root| self.paint(root))?)
    }

    /// Render and write as PNG, atomically (after [`BarChart::validate`]).
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::write_png(path, &try_render(width, height, |root| self.paint(root))?)
    }
}

#[cfg(test)]
mod tests;
