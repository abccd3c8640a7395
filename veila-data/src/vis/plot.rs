//! Line, scatter and grouped-bar plots rendered to PNG, with no system fonts and no plotting
//! dependency: axes with "nice" ticks (1-2-5 steps, decades on logarithmic axes), grid, tick and
//! axis labels, a title, a legend placed in the emptiest corner, error bars, and a built-in 5 x 9
//! bitmap font ([`font`]).
//!
//! Drawing is anti-aliased (lines, markers), text is crisp pixel text scaled by an integer factor that
//! grows with the image size. Non-finite points (and points <= 0 on a logarithmic axis) are skipped
//! and break a line, as in common plotting libraries; a single point, equal values or no data at all
//! render an ordinary frame rather than failing.
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

pub mod font;

use std::path::Path;

use image::{Rgb, RgbImage};

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

    fn accepts(&self, v: f64) -> bool {
        v.is_finite() && (!self.log || v > 0.0)
    }
}

/// A rectangle in image pixel coordinates (continuous: pixel `(i, j)` covers `[i, i+1) x [j, j+1)`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelRect {
    /// Left edge.
    pub left: f64,
    /// Top edge.
    pub top: f64,
    /// Right edge.
    pub right: f64,
    /// Bottom edge.
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
        x >= self.left && x < self.right && y >= self.top && y < self.bottom
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
    /// Major x tick values with their labels.
    pub x_ticks: Vec<(f64, String)>,
    /// Major y tick values with their labels.
    pub y_ticks: Vec<(f64, String)>,
    /// Integer text / line scale chosen for the image size.
    pub scale: u32,
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

/// Text and line scale for an image: 1 up to ~375 px on the short side, 2 up to ~625, and so on.
fn scale_for(width: u32, height: u32) -> u32 {
    ((width.min(height) as f64 / 250.0).round() as u32).clamp(1, 4)
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

/// What goes along the x axis.
enum XSpec<'a> {
    Numeric(Axis),
    Categories(&'a [String]),
}

/// Shared layout of titles, margins and ticks.
struct Frame {
    layout: PlotLayout,
    /// Category label slots (bar charts): centre pixel x and label.
    categories: Vec<(f64, String)>,
    /// Scale of the title text.
    title_scale: u32,
    /// Top of the band reserved for a legend above the plot area (when one was asked for).
    legend_top: f64,
}

/// Everything [`compute_frame`] needs besides the size.
struct FrameSpec<'a> {
    title: &'a str,
    x_label: &'a str,
    y_label: &'a str,
    x: XSpec<'a>,
    y: Axis,
    /// Height to reserve above the plot area for the legend (0: none).
    legend_above: f64,
}

/// The title one step larger than the other text, unless it then does not fit the width.
fn title_scale(title: &str, width: u32, s: u32) -> u32 {
    let room = width as f64 - 12.0 * s as f64;
    if font::text_width(title, s + 1) as f64 <= room {
        s + 1
    } else {
        s
    }
}

fn text_h(scale: u32) -> u32 {
    font::GLYPH_HEIGHT * scale
}

fn cap_h(scale: u32) -> u32 {
    font::CAP_HEIGHT * scale
}

fn compute_frame(width: u32, height: u32, spec: FrameSpec<'_>) -> Frame {
    let FrameSpec {
        title,
        x_label,
        y_label,
        x,
        y,
        legend_above,
    } = spec;
    let s = scale_for(width, height);
    let sf = s as f64;
    let pad = 6.0 * sf;
    let tick_len = 4.0 * sf;
    let title_scale = title_scale(title, width, s);
    let mut top = pad;
    if !title.is_empty() {
        top += text_h(title_scale) as f64 + 4.0 * sf;
    }
    let legend_top = top;
    top += legend_above + 4.0 * sf;
    let mut bottom = pad + tick_len + 3.0 * sf + text_h(s) as f64;
    if !x_label.is_empty() {
        bottom += 4.0 * sf + text_h(s) as f64;
    }
    let plot_h = (height as f64 - top - bottom).max(1.0);
    let y_max_ticks = ((plot_h / (28.0 * sf)) as usize).clamp(2, 10);
    let mut y_ticks = axis_ticks(&y, y_max_ticks);
    // thin out labels that would overlap vertically
    while y_ticks.len() > 2 {
        let spacing = plot_h / (y_ticks.len() as f64);
        if spacing >= cap_h(s) as f64 * 1.8 {
            break;
        }
        let n = y_ticks.len() - 1;
        y_ticks = axis_ticks(&y, n);
    }
    let y_label_w = y_ticks
        .iter()
        .map(|(_, l)| font::text_width(l, s))
        .max()
        .unwrap_or(0) as f64;
    let mut left = pad + y_label_w + 3.0 * sf + tick_len;
    if !y_label.is_empty() {
        left += text_h(s) as f64 + 4.0 * sf;
    }
    let mut right = pad + 8.0 * sf;
    let area_for = |left: f64, right: f64| PixelRect {
        left: left.round(),
        top: top.round(),
        right: (width as f64 - right).round().max(left.round() + 1.0),
        bottom: (height as f64 - bottom).round().max(top.round() + 1.0),
    };
    match x {
        XSpec::Numeric(xa) => {
            let mut x_ticks = Vec::new();
            for _pass in 0..2 {
                let area = area_for(left, right);
                let mut max_ticks = ((area.width() / (40.0 * sf)) as usize).clamp(2, 12);
                loop {
                    x_ticks = axis_ticks(&xa, max_ticks);
                    let widest = x_ticks
                        .iter()
                        .map(|(_, l)| font::text_width(l, s))
                        .max()
                        .unwrap_or(0) as f64;
                    let spacing = area.width() / (x_ticks.len().max(1) as f64);
                    if max_ticks <= 2 || widest + 6.0 * sf * 2.0 <= spacing {
                        break;
                    }
                    max_ticks -= 1;
                }
                // the last label is centred on its tick: keep it inside the image
                let need = x_ticks
                    .last()
                    .map(|(_, l)| font::text_width(l, s) as f64 / 2.0 + 2.0 * sf)
                    .unwrap_or(0.0);
                if need <= right {
                    break;
                }
                right = need;
            }
            let area = area_for(left, right);
            Frame {
                layout: PlotLayout {
                    area,
                    x: xa,
                    y,
                    x_ticks,
                    y_ticks,
                    scale: s,
                },
                categories: Vec::new(),
                title_scale,
                legend_top,
            }
        }
        XSpec::Categories(names) => {
            let area = area_for(left, right);
            let n = names.len().max(1) as f64;
            let slot = area.width() / n;
            let categories = names
                .iter()
                .enumerate()
                .map(|(i, name)| {
                    (
                        area.left + (i as f64 + 0.5) * slot,
                        fit_text(name, (slot - 4.0 * sf).max(0.0), s),
                    )
                })
                .collect();
            Frame {
                layout: PlotLayout {
                    area,
                    x: Axis {
                        lo: 0.0,
                        hi: n,
                        log: false,
                    },
                    y,
                    x_ticks: Vec::new(),
                    y_ticks,
                    scale: s,
                },
                categories,
                title_scale,
                legend_top,
            }
        }
    }
}

/// `text` shortened with ".." so that it fits `max_w` pixels at `scale`.
fn fit_text(text: &str, max_w: f64, scale: u32) -> String {
    if font::text_width(text, scale) as f64 <= max_w {
        return text.to_string();
    }
    let chars: Vec<char> = text.chars().collect();
    for keep in (0..chars.len()).rev() {
        let t: String = chars[..keep].iter().chain(['.', '.'].iter()).collect();
        if font::text_width(&t, scale) as f64 <= max_w {
            return t;
        }
    }
    String::new()
}

// ------------------------------------------------------------------------------------------------
// canvas

/// Integer clip rectangle, end-exclusive.
#[derive(Debug, Clone, Copy)]
struct Clip {
    x0: i64,
    y0: i64,
    x1: i64,
    y1: i64,
}

struct Canvas<'a> {
    img: &'a mut RgbImage,
    clip: Clip,
}

impl Canvas<'_> {
    fn full_clip(img: &RgbImage) -> Clip {
        Clip {
            x0: 0,
            y0: 0,
            x1: img.width() as i64,
            y1: img.height() as i64,
        }
    }

    fn blend(&mut self, x: i64, y: i64, c: [u8; 3], alpha: f64) {
        let cl = self.clip;
        let (w, h) = (self.img.width() as i64, self.img.height() as i64);
        let outside =
            x < cl.x0.max(0) || y < cl.y0.max(0) || x >= cl.x1.min(w) || y >= cl.y1.min(h);
        if outside || alpha <= 0.0 {
            return;
        }
        let p = self.img.get_pixel_mut(x as u32, y as u32);
        if alpha >= 1.0 {
            p.0 = c;
        } else {
            for k in 0..3 {
                let v = p.0[k] as f64 * (1.0 - alpha) + c[k] as f64 * alpha;
                p.0[k] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }

    /// Fill whole pixels `x0..x1` x `y0..y1`.
    fn fill(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: [u8; 3], alpha: f64) {
        let cl = self.clip;
        for y in y0.max(cl.y0)..y1.min(cl.y1) {
            for x in x0.max(cl.x0)..x1.min(cl.x1) {
                self.blend(x, y, c, alpha);
            }
        }
    }

    /// Anti-aliased line segment of the given width with round caps.
    fn line(&mut self, a: (f64, f64), b: (f64, f64), width: f64, c: [u8; 3]) {
        if !(a.0.is_finite() && a.1.is_finite() && b.0.is_finite() && b.1.is_finite()) {
            return;
        }
        let hw = 0.5 * width;
        let reach = hw + 1.0;
        let cl = self.clip;
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let len2 = dx * dx + dy * dy;
        let ya = (a.1.min(b.1) - reach).floor().max(cl.y0 as f64);
        let yb = (a.1.max(b.1) + reach).ceil().min(cl.y1 as f64 - 1.0);
        if ya > yb {
            return;
        }
        for py in ya as i64..=yb as i64 {
            let yc = py as f64 + 0.5;
            let (xa, xb) = if dy.abs() < 1e-9 {
                (a.0.min(b.0), a.0.max(b.0))
            } else {
                let t0 = ((yc - reach - a.1) / dy).clamp(0.0, 1.0);
                let t1 = ((yc + reach - a.1) / dy).clamp(0.0, 1.0);
                let (u, v) = (a.0 + t0 * dx, a.0 + t1 * dx);
                (u.min(v), u.max(v))
            };
            let x0 = (xa - reach).floor().max(cl.x0 as f64);
            let x1 = (xb + reach).ceil().min(cl.x1 as f64 - 1.0);
            if x0 > x1 {
                continue;
            }
            for px in x0 as i64..=x1 as i64 {
                let p = (px as f64 + 0.5, yc);
                let t = if len2 > 0.0 {
                    (((p.0 - a.0) * dx + (p.1 - a.1) * dy) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let (qx, qy) = (a.0 + t * dx - p.0, a.1 + t * dy - p.1);
                let d = (qx * qx + qy * qy).sqrt();
                self.blend(px, py, c, (hw + 0.5 - d).clamp(0.0, 1.0));
            }
        }
    }

    /// Anti-aliased filled marker of "radius" `r` centred at `p`.
    fn marker(&mut self, p: (f64, f64), shape: Marker, r: f64, c: [u8; 3]) {
        if !(p.0.is_finite() && p.1.is_finite()) {
            return;
        }
        let reach = r * 1.3 + 1.0;
        let cl = self.clip;
        let x0 = (p.0 - reach).floor().max(cl.x0 as f64);
        let x1 = (p.0 + reach).ceil().min(cl.x1 as f64 - 1.0);
        let y0 = (p.1 - reach).floor().max(cl.y0 as f64);
        let y1 = (p.1 + reach).ceil().min(cl.y1 as f64 - 1.0);
        if x0 > x1 || y0 > y1 {
            return;
        }
        for py in y0 as i64..=y1 as i64 {
            for px in x0 as i64..=x1 as i64 {
                let (dx, dy) = (px as f64 + 0.5 - p.0, py as f64 + 0.5 - p.1);
                let sdf = shape.sdf(dx, dy, r);
                self.blend(px, py, c, (0.5 - sdf).clamp(0.0, 1.0));
            }
        }
    }

    /// Pixel text with its top-left corner at `(x, y)`.
    fn text(&mut self, x: i64, y: i64, text: &str, scale: u32, c: [u8; 3]) {
        let s = scale as i64;
        for (i, ch) in text.chars().enumerate() {
            let g = font::glyph(ch);
            let gx0 = x + i as i64 * font::ADVANCE as i64 * s;
            for (row, bits) in g.iter().enumerate() {
                for col in 0..font::GLYPH_WIDTH {
                    if bits >> (font::GLYPH_WIDTH - 1 - col) & 1 == 1 {
                        let px = gx0 + col as i64 * s;
                        let py = y + row as i64 * s;
                        self.fill(px, py, px + s, py + s, c, 1.0);
                    }
                }
            }
        }
    }

    /// Pixel text rotated 90 degrees counter-clockwise (reading upwards), with the top-left corner of
    /// its bounding box at `(x, y)`.
    fn text_up(&mut self, x: i64, y: i64, text: &str, scale: u32, c: [u8; 3]) {
        let s = scale as i64;
        let total = font::text_width(text, 1) as i64;
        for (i, ch) in text.chars().enumerate() {
            let g = font::glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..font::GLYPH_WIDTH {
                    if bits >> (font::GLYPH_WIDTH - 1 - col) & 1 == 1 {
                        let tx = i as i64 * font::ADVANCE as i64 + col as i64;
                        let px = x + row as i64 * s;
                        let py = y + (total - 1 - tx) * s;
                        self.fill(px, py, px + s, py + s, c, 1.0);
                    }
                }
            }
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

impl Marker {
    /// Signed distance (approximate for polygons) from the shape's edge; negative inside.
    fn sdf(self, dx: f64, dy: f64, r: f64) -> f64 {
        const C30: f64 = 0.866_025_403_784_438_6;
        match self {
            Marker::Circle => (dx * dx + dy * dy).sqrt() - r,
            Marker::Square => dx.abs().max(dy.abs()) - 0.85 * r,
            Marker::Diamond => (dx.abs() + dy.abs()) * std::f64::consts::FRAC_1_SQRT_2 - 0.85 * r,
            Marker::TriangleUp | Marker::TriangleDown => {
                let dy = if self == Marker::TriangleUp { dy } else { -dy };
                let e0 = dy;
                let e1 = C30 * dx - 0.5 * dy;
                let e2 = -C30 * dx - 0.5 * dy;
                e0.max(e1).max(e2) - 0.62 * r
            }
        }
    }
}

// ------------------------------------------------------------------------------------------------
// shared drawing of frames, grids, ticks, titles and legends

struct Style {
    s: u32,
    sf: f64,
    line_w: f64,
    marker_r: f64,
}

impl Style {
    fn new(s: u32) -> Style {
        let sf = s as f64;
        Style {
            s,
            sf,
            line_w: 1.5 * sf + 0.5,
            marker_r: 2.5 * sf + 0.5,
        }
    }
}

fn area_clip(a: &PixelRect) -> Clip {
    Clip {
        x0: a.left as i64,
        y0: a.top as i64,
        x1: a.right as i64,
        y1: a.bottom as i64,
    }
}

fn draw_grid(canvas: &mut Canvas<'_>, layout: &PlotLayout, vertical: bool) {
    let a = layout.area;
    let (l, t, r, b) = (a.left as i64, a.top as i64, a.right as i64, a.bottom as i64);
    for v in log_minor_ticks(&layout.y, &layout.y_ticks) {
        if let Some(py) = layout.y_to_px(v) {
            let py = py.floor() as i64;
            canvas.fill(l, py, r, py + 1, MINOR_GRID, 1.0);
        }
    }
    if vertical {
        for v in log_minor_ticks(&layout.x, &layout.x_ticks) {
            if let Some(px) = layout.x_to_px(v) {
                let px = px.floor() as i64;
                canvas.fill(px, t, px + 1, b, MINOR_GRID, 1.0);
            }
        }
        for (v, _) in &layout.x_ticks {
            if let Some(px) = layout.x_to_px(*v) {
                let px = px.floor() as i64;
                canvas.fill(px, t, px + 1, b, GRID, 1.0);
            }
        }
    }
    for (v, _) in &layout.y_ticks {
        if let Some(py) = layout.y_to_px(*v) {
            let py = py.floor() as i64;
            canvas.fill(l, py, r, py + 1, GRID, 1.0);
        }
    }
}

fn draw_frame_and_labels(
    canvas: &mut Canvas<'_>,
    frame: &Frame,
    title: &str,
    x_label: &str,
    y_label: &str,
    width: u32,
) {
    let layout = &frame.layout;
    let st = Style::new(layout.scale);
    let (s, sf) = (st.s, st.sf);
    let a = layout.area;
    let (l, t, r, b) = (a.left as i64, a.top as i64, a.right as i64, a.bottom as i64);
    let lw = (s as i64 / 2).max(1);
    // frame
    canvas.fill(l - lw, t - lw, r + lw, t, FRAME, 1.0);
    canvas.fill(l - lw, b, r + lw, b + lw, FRAME, 1.0);
    canvas.fill(l - lw, t, l, b, FRAME, 1.0);
    canvas.fill(r, t, r + lw, b, FRAME, 1.0);
    let tick_len = (4.0 * sf) as i64;
    // y ticks and labels
    let minor_len = (2.0 * sf) as i64;
    for v in log_minor_ticks(&layout.y, &layout.y_ticks) {
        if let Some(py) = layout.y_to_px(v) {
            let py = py.floor() as i64;
            canvas.fill(l - lw - minor_len, py, l - lw, py + 1, FRAME, 1.0);
        }
    }
    for (v, label) in &layout.y_ticks {
        if let Some(py) = layout.y_to_px(*v) {
            let py = py.floor() as i64;
            canvas.fill(l - lw - tick_len, py, l - lw, py + 1, FRAME, 1.0);
            let w = font::text_width(label, s) as i64;
            let x = l - lw - tick_len - (3.0 * sf) as i64 - w;
            canvas.text(x, py - cap_h(s) as i64 / 2, label, s, TEXT);
        }
    }
    let label_top = b + lw + tick_len + (3.0 * sf) as i64;
    // x ticks and labels
    for v in log_minor_ticks(&layout.x, &layout.x_ticks) {
        if let Some(px) = layout.x_to_px(v) {
            let px = px.floor() as i64;
            canvas.fill(px, b + lw, px + 1, b + lw + minor_len, FRAME, 1.0);
        }
    }
    for (v, label) in &layout.x_ticks {
        if let Some(px) = layout.x_to_px(*v) {
            let px = px.floor() as i64;
            canvas.fill(px, b + lw, px + 1, b + lw + tick_len, FRAME, 1.0);
            let w = font::text_width(label, s) as i64;
            canvas.text(px - w / 2, label_top, label, s, TEXT);
        }
    }
    for (cx, label) in &frame.categories {
        let w = font::text_width(label, s) as i64;
        let cx = cx.floor() as i64;
        canvas.fill(cx, b + lw, cx + 1, b + lw + tick_len / 2, FRAME, 1.0);
        canvas.text(cx - w / 2, label_top, label, s, TEXT);
    }
    // axis labels
    if !x_label.is_empty() {
        let text = fit_text(x_label, a.width().max(0.0), s);
        let w = font::text_width(&text, s) as f64;
        let x = (a.left + 0.5 * (a.width() - w)).round() as i64;
        let y = label_top + text_h(s) as i64 + (4.0 * sf) as i64;
        canvas.text(x, y, &text, s, TEXT);
    }
    if !y_label.is_empty() {
        let text = fit_text(y_label, a.height().max(0.0), s);
        let h = font::text_width(&text, s) as f64;
        let y = (a.top + 0.5 * (a.height() - h)).round() as i64;
        canvas.text_up((6.0 * sf) as i64, y, &text, s, TEXT);
    }
    if !title.is_empty() {
        let ts = frame.title_scale;
        let text = fit_text(title, width as f64 - 12.0 * sf, ts);
        let w = font::text_width(&text, ts) as f64;
        let centre = a.left + 0.5 * a.width();
        let x = (centre - 0.5 * w)
            .min(width as f64 - 6.0 * sf - w)
            .max(6.0 * sf)
            .round() as i64;
        canvas.text(x, (6.0 * sf) as i64, &text, ts, TEXT);
    }
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

/// Sizes shared by both legend forms.
struct LegendMetrics {
    s: u32,
    key_w: f64,
    gap: f64,
    pad: f64,
    row_h: f64,
}

impl LegendMetrics {
    fn new(s: u32) -> Self {
        let sf = s as f64;
        LegendMetrics {
            s,
            key_w: 22.0 * sf,
            gap: 4.0 * sf,
            pad: 5.0 * sf,
            row_h: text_h(s) as f64 + 3.0 * sf,
        }
    }

    /// Width of one entry (key, gap, name).
    fn entry_w(&self, name: &str) -> f64 {
        self.key_w + self.gap + font::text_width(name, self.s) as f64
    }

    /// Size of the boxed legend.
    fn box_size(&self, names: &[String]) -> (f64, f64) {
        let w = names.iter().map(|n| self.entry_w(n)).fold(0.0, f64::max) + 2.0 * self.pad;
        let h = 2.0 * self.pad + self.row_h * names.len() as f64 - 3.0 * self.s as f64;
        (w.round(), h.round())
    }

    /// Entries of the legend above the plot, wrapped into rows that fit `max_w`.
    fn rows(&self, names: &[String], max_w: f64) -> Vec<Vec<usize>> {
        let spacing = 12.0 * self.s as f64;
        let mut rows: Vec<Vec<usize>> = Vec::new();
        let mut used = 0.0;
        for (i, n) in names.iter().enumerate() {
            let w = self.entry_w(n);
            match rows.last_mut() {
                Some(row) if used + spacing + w <= max_w => {
                    row.push(i);
                    used += spacing + w;
                }
                _ => {
                    rows.push(vec![i]);
                    used = w;
                }
            }
        }
        rows
    }

    fn above_height(&self, names: &[String], width: u32) -> f64 {
        let rows = self.rows(names, self.above_width(width)).len();
        rows as f64 * self.row_h
    }

    fn above_width(&self, width: u32) -> f64 {
        width as f64 - 12.0 * self.s as f64
    }
}

/// Legend names shortened to fit the image.
fn legend_names(entries: &[(String, Key)], width: u32, s: u32) -> Vec<String> {
    let m = LegendMetrics::new(s);
    let max_text = (m.above_width(width) - m.key_w - m.gap - 2.0 * m.pad).max(0.0);
    entries
        .iter()
        .map(|(n, _)| fit_text(n, max_text, s))
        .collect()
}

/// The first corner of the plot area (top right, top left, bottom right, bottom left) where a boxed
/// legend covers none of the `occupied` points; `None` when every corner covers data.
fn free_corner(
    layout: &PlotLayout,
    names: &[String],
    occupied: &[(f64, f64)],
) -> Option<(f64, f64)> {
    let m = LegendMetrics::new(layout.scale);
    let sf = layout.scale as f64;
    let a = layout.area;
    let (w, h) = m.box_size(names);
    let inset = 6.0 * sf;
    if w + 2.0 * inset > a.width() || h + 2.0 * inset > a.height() {
        return None;
    }
    let corners = [
        (a.right - inset - w, a.top + inset),
        (a.left + inset, a.top + inset),
        (a.right - inset - w, a.bottom - inset - h),
        (a.left + inset, a.bottom - inset - h),
    ];
    corners.into_iter().find(|&(x, y)| {
        let r = PixelRect {
            left: x - 3.0 * sf,
            top: y - 3.0 * sf,
            right: x + w + 3.0 * sf,
            bottom: y + h + 3.0 * sf,
        };
        !occupied.iter().any(|p| r.contains(*p))
    })
}

fn draw_key(canvas: &mut Canvas<'_>, key: Key, kx: f64, cy: f64, m: &LegendMetrics) {
    let st = Style::new(m.s);
    match key {
        Key::Series {
            color,
            line,
            marker,
        } => {
            if line {
                canvas.line((kx, cy), (kx + m.key_w, cy), st.line_w, color);
            }
            if let Some(mk) = marker {
                canvas.marker((kx + m.key_w / 2.0, cy), mk, st.marker_r, color);
            }
        }
        Key::Bar(color) => {
            let side = cap_h(m.s) as f64;
            let bx = (kx + m.key_w / 2.0 - side / 2.0).round() as i64;
            let by = (cy - side / 2.0).round() as i64;
            canvas.fill(bx, by, bx + side as i64, by + side as i64, color, 1.0);
        }
    }
}

fn draw_legend(
    canvas: &mut Canvas<'_>,
    frame: &Frame,
    entries: &[(String, Key)],
    place: LegendPlace,
    width: u32,
) {
    if entries.is_empty() {
        return;
    }
    let s = frame.layout.scale;
    let m = LegendMetrics::new(s);
    let names = legend_names(entries, width, s);
    let cap = cap_h(s) as f64;
    match place {
        LegendPlace::Inside(x, y) => {
            let (w, h) = m.box_size(&names);
            let (x0, y0) = (x.round() as i64, y.round() as i64);
            let (x1, y1) = (x0 + w as i64, y0 + h as i64);
            let border = [200, 200, 200];
            canvas.fill(x0, y0, x1, y1, BACKGROUND, 0.9);
            canvas.fill(x0, y0, x1, y0 + 1, border, 1.0);
            canvas.fill(x0, y1 - 1, x1, y1, border, 1.0);
            canvas.fill(x0, y0, x0 + 1, y1, border, 1.0);
            canvas.fill(x1 - 1, y0, x1, y1, border, 1.0);
            for (i, ((_, key), name)) in entries.iter().zip(&names).enumerate() {
                let ty = y0 as f64 + m.pad + i as f64 * m.row_h;
                let kx = x0 as f64 + m.pad;
                draw_key(canvas, *key, kx, ty + cap / 2.0, &m);
                let tx = (kx + m.key_w + m.gap).round() as i64;
                canvas.text(tx, ty.round() as i64, name, s, TEXT);
            }
        }
        LegendPlace::Above => {
            let spacing = 12.0 * s as f64;
            for (r, row) in m.rows(&names, m.above_width(width)).iter().enumerate() {
                let total: f64 = row.iter().map(|&i| m.entry_w(&names[i])).sum::<f64>()
                    + spacing * (row.len().saturating_sub(1)) as f64;
                let a = frame.layout.area;
                let mut x = (a.left + 0.5 * (a.width() - total))
                    .min(width as f64 - 6.0 * s as f64 - total)
                    .max(6.0 * s as f64);
                let ty = frame.legend_top + r as f64 * m.row_h;
                for &i in row {
                    draw_key(canvas, entries[i].1, x, ty + cap / 2.0, &m);
                    let tx = (x + m.key_w + m.gap).round() as i64;
                    canvas.text(tx, ty.round() as i64, &names[i], s, TEXT);
                    x += m.entry_w(&names[i]) + spacing;
                }
            }
        }
    }
}

/// Lay out a chart: the frame without a legend band when a corner of the plot area is free of
/// data, otherwise with the legend above the plot area.
fn plan<'a>(
    width: u32,
    height: u32,
    spec: impl Fn(f64) -> FrameSpec<'a>,
    entries: &[(String, Key)],
    occupancy: impl Fn(&PlotLayout) -> Vec<(f64, f64)>,
) -> (Frame, Option<LegendPlace>) {
    let frame = compute_frame(width, height, spec(0.0));
    if entries.is_empty() {
        return (frame, None);
    }
    let s = frame.layout.scale;
    let names = legend_names(entries, width, s);
    if let Some((x, y)) = free_corner(&frame.layout, &names, &occupancy(&frame.layout)) {
        return (frame, Some(LegendPlace::Inside(x, y)));
    }
    let band = LegendMetrics::new(s).above_height(&names, width);
    (
        compute_frame(width, height, spec(band)),
        Some(LegendPlace::Above),
    )
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
        let ys = self.series.iter().flat_map(|s| {
            s.points.iter().enumerate().flat_map(move |(i, &(px, py))| {
                let e = error_of(s, i);
                let keep = x.accepts(px);
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
        let step = 6.0 * layout.scale as f64;
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

    fn plan(&self, width: u32, height: u32) -> (Frame, Option<LegendPlace>) {
        let (x, y) = self.axes();
        plan(
            width,
            height,
            |legend_above| FrameSpec {
                title: &self.title,
                x_label: &self.x_label,
                y_label: &self.y_label,
                x: XSpec::Numeric(x),
                y,
                legend_above,
            },
            &self.legend_entries(),
            |l| self.occupancy(l),
        )
    }

    /// The layout [`Plot::render`] uses at this size (plot area, axes, ticks).
    pub fn layout(&self, width: u32, height: u32) -> PlotLayout {
        self.plan(width, height).0.layout
    }

    /// Render to an RGB image of the given size. Never fails: non-finite or out-of-domain points are
    /// skipped, degenerate ranges get a window around the data, and a size of 0 gives an empty image.
    pub fn render(&self, width: u32, height: u32) -> RgbImage {
        let mut img = RgbImage::from_pixel(width, height, Rgb(BACKGROUND));
        if width == 0 || height == 0 {
            return img;
        }
        let (frame, place) = self.plan(width, height);
        let layout = &frame.layout;
        let st = Style::new(layout.scale);
        let full = Canvas::full_clip(&img);
        let area = area_clip(&layout.area);
        // markers may reach a few pixels beyond the area, so that those on the edge are whole
        let grow = (st.marker_r + 1.0).ceil() as i64;
        let marker_clip = Clip {
            x0: area.x0 - grow,
            y0: area.y0 - grow,
            x1: area.x1 + grow,
            y1: area.y1 + grow,
        };
        let mut canvas = Canvas {
            img: &mut img,
            clip: area,
        };
        draw_grid(&mut canvas, layout, true);
        for (si, series) in self.series.iter().enumerate() {
            let color = series_color(si).0;
            let px: Vec<Option<(f64, f64)>> =
                series.points.iter().map(|&p| layout.to_px(p)).collect();
            canvas.clip = area;
            // error bars (axis-aligned: snapped to pixel centres so that they are crisp)
            let snap = |v: f64| v.floor() + 0.5;
            let cap = 3.0 * st.sf;
            for (i, p) in px.iter().enumerate() {
                let (Some((cx, _)), e) = (*p, error_of(series, i)) else {
                    continue;
                };
                if e <= 0.0 {
                    continue;
                }
                let y = series.points[i].1;
                let bot = if self.y_log && y - e <= 0.0 {
                    Some(layout.area.bottom + 2.0 * cap)
                } else {
                    layout.y_to_px(y - e)
                };
                let (Some(top), Some(bot)) = (layout.y_to_px(y + e), bot) else {
                    continue;
                };
                let (cx, top, bot) = (snap(cx), snap(top), snap(bot));
                canvas.line((cx, top), (cx, bot), st.sf, ERROR_BAR);
                canvas.line((cx - cap, top), (cx + cap, top), st.sf, ERROR_BAR);
                canvas.line((cx - cap, bot), (cx + cap, bot), st.sf, ERROR_BAR);
            }
            if matches!(series.style, SeriesStyle::Line | SeriesStyle::LineMarkers) {
                for w in px.windows(2) {
                    if let [Some(a), Some(b)] = w {
                        canvas.line(*a, *b, st.line_w, color);
                    }
                }
            }
            if matches!(
                series.style,
                SeriesStyle::Markers | SeriesStyle::LineMarkers
            ) {
                canvas.clip = marker_clip;
                let marker = MARKERS[si % MARKERS.len()];
                let a = layout.area;
                for p in px.iter().flatten() {
                    let inside = p.0 >= a.left - 0.5
                        && p.0 <= a.right + 0.5
                        && p.1 >= a.top - 0.5
                        && p.1 <= a.bottom + 0.5;
                    if inside {
                        canvas.marker(*p, marker, st.marker_r, color);
                    }
                }
            }
        }
        canvas.clip = full;
        draw_frame_and_labels(
            &mut canvas,
            &frame,
            &self.title,
            &self.x_label,
            &self.y_label,
            width,
        );
        if let Some(place) = place {
            draw_legend(&mut canvas, &frame, &self.legend_entries(), place, width);
        }
        img
    }

    /// Render and encode as PNG bytes (after [`Plot::validate`]).
    pub fn to_png(&self, width: u32, height: u32) -> Result<Vec<u8>> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::encode_png(&self.render(width, height))
    }

    /// Render and write as PNG, atomically (after [`Plot::validate`]).
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::write_png(path, &self.render(width, height))
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

    fn plan(&self, width: u32, height: u32) -> (Frame, Option<LegendPlace>) {
        plan(
            width,
            height,
            |legend_above| FrameSpec {
                title: &self.title,
                x_label: "",
                y_label: &self.y_label,
                x: XSpec::Categories(&self.categories),
                y: self.value_axis(),
                legend_above,
            },
            &self.legend_entries(),
            |layout| {
                let step = 6.0 * layout.scale as f64;
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
            },
        )
    }

    /// The layout [`BarChart::render`] uses (the x axis runs from 0 to the number of categories).
    pub fn layout(&self, width: u32, height: u32) -> PlotLayout {
        self.plan(width, height).0.layout
    }

    /// Render to an RGB image of the given size. Never fails; non-finite values draw no bar.
    pub fn render(&self, width: u32, height: u32) -> RgbImage {
        let mut img = RgbImage::from_pixel(width, height, Rgb(BACKGROUND));
        if width == 0 || height == 0 {
            return img;
        }
        let (frame, place) = self.plan(width, height);
        let layout = &frame.layout;
        let st = Style::new(layout.scale);
        let full = Canvas::full_clip(&img);
        let mut canvas = Canvas {
            img: &mut img,
            clip: area_clip(&layout.area),
        };
        draw_grid(&mut canvas, layout, false);
        let bars = self.bars(layout);
        for b in &bars {
            // a hairline gap between neighbouring bars
            let gap = if b.x1 - b.x0 > 6.0 { 1.0 } else { 0.0 };
            let (ya, yb) = (b.value_px.min(b.zero_px), b.value_px.max(b.zero_px));
            canvas.fill(
                b.x0.round() as i64,
                ya.round() as i64,
                (b.x1.round() - gap) as i64,
                yb.round().max(ya.round() + 1.0) as i64,
                series_color(b.group).0,
                1.0,
            );
        }
        for b in &bars {
            if let Some((t, bot)) = b.error_px {
                let snap = |v: f64| v.floor() + 0.5;
                let gap = if b.x1 - b.x0 > 6.0 { 1.0 } else { 0.0 };
                let (cx, t, bot) = (snap(0.5 * (b.x0 + b.x1 - gap)), snap(t), snap(bot));
                let cap = (0.25 * (b.x1 - b.x0)).min(4.0 * st.sf);
                canvas.line((cx, t), (cx, bot), st.sf, ERROR_BAR);
                canvas.line((cx - cap, t), (cx + cap, t), st.sf, ERROR_BAR);
                canvas.line((cx - cap, bot), (cx + cap, bot), st.sf, ERROR_BAR);
            }
        }
        canvas.clip = full;
        if layout.y.lo < 0.0 {
            // the zero line
            if let Some(zero) = layout.y_to_px(0.0) {
                let zy = zero.floor() as i64;
                let a = layout.area;
                canvas.fill(a.left as i64, zy, a.right as i64, zy + 1, FRAME, 1.0);
            }
        }
        draw_frame_and_labels(&mut canvas, &frame, &self.title, "", &self.y_label, width);
        if let Some(place) = place {
            draw_legend(&mut canvas, &frame, &self.legend_entries(), place, width);
        }
        img
    }

    /// Render and encode as PNG bytes (after [`BarChart::validate`]).
    pub fn to_png(&self, width: u32, height: u32) -> Result<Vec<u8>> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::encode_png(&self.render(width, height))
    }

    /// Render and write as PNG, atomically (after [`BarChart::validate`]).
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        self.validate()?;
        check_size(width, height)?;
        crate::image_io::write_png(path, &self.render(width, height))
    }
}

/// Draw `text` with the built-in font onto `img`, top-left corner at `(x, y)`, at an integer scale
/// (each font pixel becomes `scale x scale` image pixels). Pixels outside the image are skipped.
pub fn draw_text(img: &mut RgbImage, x: i64, y: i64, text: &str, scale: u32, color: Rgb<u8>) {
    let clip = Canvas::full_clip(img);
    Canvas { img, clip }.text(x, y, text, scale.max(1), color.0);
}

#[cfg(test)]
mod tests;
