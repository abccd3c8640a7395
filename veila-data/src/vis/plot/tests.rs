use super::*;

fn values(t: &[(f64, String)]) -> Vec<f64> {
    t.iter().map(|t| t.0).collect()
}

fn labels(t: &[(f64, String)]) -> Vec<&str> {
    t.iter().map(|t| t.1.as_str()).collect()
}

fn close(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= 1e-9 * x.abs().max(1.0))
}

fn lin(lo: f64, hi: f64) -> Axis {
    Axis { lo, hi, log: false }
}

fn log(lo: f64, hi: f64) -> Axis {
    Axis { lo, hi, log: true }
}

#[test]
fn linear_ticks_are_plotters_1_2_5_steps_with_labels_alike() {
    let t = lin(0.0, 1.0).ticks(6);
    assert!(close(&values(&t), &[0.0, 0.2, 0.4, 0.6, 0.8, 1.0]), "{t:?}");
    // one decimal for all, even where plotters' sums drift (0.6000000000000001)
    assert_eq!(labels(&t), ["0.0", "0.2", "0.4", "0.6", "0.8", "1.0"]);
    // 6 ticks of 0.2 exceed 5: the next step, 0.5
    assert_eq!(labels(&lin(0.0, 1.0).ticks(5)), ["0.0", "0.5", "1.0"]);
    assert_eq!(
        labels(&lin(-3.7, 12.1).ticks(8)),
        ["-2", "0", "2", "4", "6", "8", "10", "12"]
    );
    assert_eq!(
        labels(&lin(0.013, 0.087).ticks(5)),
        ["0.02", "0.04", "0.06", "0.08"]
    );
    // very large and very small values: scientific notation
    assert_eq!(
        labels(&lin(0.0, 2.4e6).ticks(6)),
        ["0", "5e5", "1e6", "1.5e6", "2e6"]
    );
    assert_eq!(
        labels(&lin(1e-9, 9.9e-9).ticks(5)),
        ["2e-9", "4e-9", "6e-9", "8e-9"]
    );
    // no "-0.0" where a tick misses zero by a rounding error
    assert_eq!(LabelFormat::Fixed(1).label(-1.4e-17), "0.0");
    assert_eq!(LabelFormat::Fixed(2).label(-0.25), "-0.25");
    assert_eq!(LabelFormat::Scientific.label(-2.5e-5), "-2.5e-5");
    assert_eq!(LabelFormat::Scientific.label(9.9999999e-4), "1e-3");
    for (lo, hi, n) in [
        (0.0, 1.0, 11),
        (-5.0, 5.0, 3),
        (1e300, 2e300, 6),
        (7.0, 7.5, 2),
    ] {
        let t = values(&lin(lo, hi).ticks(n));
        assert!(
            t.len() >= 2 && t.len() <= n.max(2) && t.iter().all(|v| (lo..=hi).contains(v)),
            "{lo}..{hi} at most {n}: {t:?}"
        );
    }
}

#[test]
fn log_ticks_are_decades_or_a_fallback_on_short_ranges() {
    // plotters' decades (with multiples where there is room)
    assert_eq!(labels(&log(0.3, 3.0).ticks(10)), ["1", "2", "3"]);
    let t = log(0.5, 2000.0).ticks(10);
    assert!(close(&values(&t), &[1.0, 10.0, 100.0, 1000.0]), "{t:?}");
    assert_eq!(labels(&t), ["1", "10", "100", "1000"]);
    assert_eq!(labels(&log(1e-3, 1e-1).ticks(10)), ["0.001", "0.01", "0.1"]);
    // too many decades for 5 ticks: every other one
    let t = log(1e-6, 1e6).ticks(5);
    assert!(t.len() <= 7 && t.len() >= 4, "{t:?}");
    assert!(
        labels(&t).contains(&"1e-6") && labels(&t).contains(&"1"),
        "{t:?}"
    );
    // fewer than two powers of ten (plotters finds one or none): 1-2-5 multiples ...
    assert_eq!(labels(&log(0.15, 0.6).ticks(10)), ["0.2", "0.5"]);
    assert_eq!(labels(&log(0.04, 0.4).ticks(6)), ["0.05", "0.1", "0.2"]);
    // ... or, within one 1-2-5 gap, linear ticks
    assert!(close(
        &values(&log(3.0, 4.0).ticks(6)),
        &[3.0, 3.2, 3.4, 3.6, 3.8, 4.0]
    ));
    let t = log(0.2361, 0.2428).ticks(8);
    assert!(t.len() >= 2, "{t:?}");
    assert_eq!(t[0].1, "0.237");
    // labels outside 0.001..10000 are scientific
    assert_eq!(
        [1e-6, 1e-3, 0.5, 1.0, 20.0, 1e4, 1e5].map(|v| LabelFormat::Log.label(v)),
        ["1e-6", "0.001", "0.5", "1", "20", "10000", "1e5"]
    );
}

#[test]
fn fitted_axes_stay_drawable() {
    let fit = |v: &[f64], log: bool| Axis::fit(v.iter().copied(), log, None);
    // 4 % margins (in decades on a log axis)
    assert_eq!(fit(&[0.0, 1.0], false), lin(-0.04, 1.04));
    let l = fit(&[1.0, 100.0], true);
    assert!((l.lo.log10() + 0.08).abs() < 1e-12 && (l.hi.log10() - 2.08).abs() < 1e-12);
    // one value: a window around it; no value: a plain frame
    assert_eq!(fit(&[2.0, 2.0], false), lin(1.8, 2.2));
    assert_eq!(fit(&[0.0], false), lin(-1.0, 1.0));
    assert_eq!(fit(&[], false), lin(0.0, 1.0));
    assert_eq!(fit(&[-1.0, 0.0, f64::NAN], true), log(1.0, 10.0));
    // ranges plotters cannot step through fall back to a plain frame
    for v in [
        vec![-1e308, 1e308],
        vec![5e-324, 1e-323],
        vec![f64::MAX],
        vec![f64::MIN_POSITIVE, 2.0 * f64::MIN_POSITIVE],
    ] {
        for log in [false, true] {
            let a = fit(&v, log);
            assert!(Axis::usable(a.lo, a.hi, log), "{v:?} log {log}: {a:?}");
            assert!(!a.ticks(5).is_empty(), "{v:?} log {log}: {a:?}");
        }
    }
    // a usable fixed range is kept; an unusable one fits the data
    assert_eq!(
        Axis::fit([5.0].into_iter(), false, Some((0.0, 10.0))),
        lin(0.0, 10.0)
    );
    let a = Axis::fit([5.0].into_iter(), true, Some((0.0, 10.0)));
    let c = 5f64.log10();
    assert!((a.lo.log10() - (c - 0.5)).abs() < 1e-12 && (a.hi.log10() - (c + 0.5)).abs() < 1e-12);
}

/// Pixels dark enough to be text (the frame, grey 90, is lighter).
fn is_dark(p: &Rgb<u8>) -> bool {
    p.0.iter().all(|&v| v < 80)
}

/// Bounding box `(x0, y0, x1, y1)` (inclusive) of the dark pixels, if any.
fn dark_box(img: &RgbImage) -> Option<(u32, u32, u32, u32)> {
    let mut b: Option<(u32, u32, u32, u32)> = None;
    for (x, y, p) in img.enumerate_pixels() {
        if is_dark(p) {
            b = Some(match b {
                None => (x, y, x, y),
                Some((x0, y0, x1, y1)) => (x0.min(x), y0.min(y), x1.max(x), y1.max(y)),
            });
        }
    }
    b
}

#[test]
fn drawn_text_sits_where_asked() {
    // capitals without descenders: their dark pixels start at the requested corner and are one
    // cap height tall (DejaVu Sans: 0.626 of the font size)
    let size = 40.0;
    let mut img = RgbImage::from_pixel(300, 100, Rgb([255, 255, 255]));
    draw_text(&mut img, 20, 30, "HEH", size, Rgb([0, 0, 0]));
    let (x0, y0, x1, y1) = dark_box(&img).expect("text drawn");
    assert!((y0 as i64 - 30).abs() <= 1, "cap top at {y0}");
    let cap = (y1 - y0 + 1) as f64;
    assert!((cap - CAP * size).abs() <= 1.5, "cap height {cap}");
    // 'H' has a small left side bearing; the ink is about as wide as the advance says
    assert!((20..=25).contains(&x0), "left edge {x0}");
    let w = text_width("HEH", size) as f64;
    assert!(
        (x1 - x0) as f64 > 0.8 * w && ((x1 - x0) as f64) < w,
        "{x0}..{x1} vs {w}"
    );
    // wider text measures wider; nothing measures nothing
    assert!(text_width("HEHE", size) > text_width("HEH", size));
    assert_eq!(text_width("", size), 0);
    // a descender reaches below the baseline, i.e. below the capitals
    let mut g = RgbImage::from_pixel(300, 100, Rgb([255, 255, 255]));
    draw_text(&mut g, 20, 30, "Hg", size, Rgb([0, 0, 0]));
    assert!(dark_box(&g).unwrap().3 > y1 + 3);
    // off-image text is clipped, not a panic; a zero size draws nothing
    draw_text(&mut img, -100, 95, "clipped text", 30.0, Rgb([0, 0, 0]));
    draw_text(
        &mut img,
        i64::MAX,
        i64::MIN,
        "far away",
        30.0,
        Rgb([0, 0, 0]),
    );
    let mut blank = RgbImage::from_pixel(50, 50, Rgb([255, 255, 255]));
    draw_text(&mut blank, 5, 5, "none", 0.0, Rgb([0, 0, 0]));
    assert!(dark_box(&blank).is_none());
}

#[test]
fn the_embedded_font_has_the_characters_of_plot_labels() {
    // every printable ASCII character and the non-ASCII ones labels use draw ink of their own
    for c in (33u8..=126)
        .map(char::from)
        .chain(['±', 'µ', 'é', '°', '×'])
    {
        let mut img = RgbImage::from_pixel(40, 40, Rgb([255, 255, 255]));
        draw_text(&mut img, 8, 10, &c.to_string(), 20.0, Rgb([0, 0, 0]));
        let ink = img.pixels().filter(|p| p.0[0] < 128).count();
        assert!(ink >= 2, "{c:?} draws {ink} pixels");
    }
}

fn unnamed_line(points: Vec<(f64, f64)>, style: SeriesStyle) -> Series {
    Series::new("", points, style)
}

#[test]
fn horizontal_line_colours_the_predicted_row() {
    let plot = Plot {
        title: "Constant".into(),
        x_label: "x".into(),
        y_label: "y".into(),
        series: vec![
            unnamed_line(vec![(0.0, 1.0), (1.0, 1.0)], SeriesStyle::Line),
            unnamed_line(vec![(0.25, 0.5), (0.75, 0.5)], SeriesStyle::Markers),
        ],
        ..Plot::default()
    };
    let (w, h) = (640, 400);
    let img = plot.render(w, h);
    let layout = plot.layout(w, h);
    // y from 0.5 to 1.0 with the 4 % margin
    assert!((layout.y.lo - 0.48).abs() < 1e-12 && (layout.y.hi - 1.02).abs() < 1e-12);
    assert!((layout.x.lo + 0.04).abs() < 1e-12 && (layout.x.hi - 1.04).abs() < 1e-12);
    let c0 = series_color(0);
    let c1 = series_color(1);
    let row = layout.y_to_px(1.0).unwrap().floor() as u32;
    for xv in [0.05, 0.3, 0.5, 0.77, 0.95] {
        let col = layout.x_to_px(xv).unwrap().floor() as u32;
        assert_eq!(*img.get_pixel(col, row), c0, "x = {xv}");
        // well above and below the line: no series colour
        assert_ne!(*img.get_pixel(col, row - 12), c0);
        assert_ne!(*img.get_pixel(col, row + 12), c0);
    }
    // the line stops at its ends (x = 0 and 1), inside the margins
    let left_of = layout.x_to_px(-0.03).unwrap().floor() as u32;
    assert_ne!(*img.get_pixel(left_of, row), c0);
    // markers at their predicted centres, in the second colour
    for xv in [0.25, 0.75] {
        let (px, py) = layout.to_px((xv, 0.5)).unwrap();
        assert_eq!(*img.get_pixel(px as u32, py as u32), c1);
    }
    assert_ne!(c0, c1);
    // the whole row between the two ends is the line's colour
    let (a, b) = (
        layout.x_to_px(0.0).unwrap().ceil() as u32 + 2,
        layout.x_to_px(1.0).unwrap().floor() as u32 - 2,
    );
    assert!((a..b).all(|x| *img.get_pixel(x, row) == c0));
}

#[test]
fn every_series_gets_its_own_colour_and_legend() {
    let series: Vec<Series> = (0..4)
        .map(|i| {
            Series::new(
                format!("model {i}"),
                (0..20)
                    .map(|k| (k as f64, (k as f64 * 0.3 + i as f64).sin() + 3.0 * i as f64))
                    .collect(),
                SeriesStyle::LineMarkers,
            )
        })
        .collect();
    let plot = Plot {
        title: "Four series".into(),
        series,
        ..Plot::default()
    };
    let img = plot.render(800, 500);
    let layout = plot.layout(800, 500);
    for i in 0..4 {
        let c = series_color(i);
        let n = img.pixels().filter(|p| **p == c).count();
        assert!(n > 200, "series {i}: only {n} pixels of its colour");
        // a vertex of the series is drawn in its colour
        let (px, py) = layout.to_px(plot.series[i].points[10]).unwrap();
        assert_eq!(*img.get_pixel(px as u32, py as u32), c, "series {i}");
    }
    // palette colours are pairwise distinct
    for i in 0..PALETTE.len() {
        for j in 0..i {
            assert_ne!(PALETTE[i], PALETTE[j]);
        }
    }
    // the series cover every corner: the legend goes into a band above the plot area
    let mut nameless = plot.clone();
    for s in &mut nameless.series {
        s.name.clear();
    }
    let text_pixels = |img: &RgbImage| img.pixels().filter(|p| is_dark(p)).count();
    let plain = nameless.render(800, 500);
    assert!(
        text_pixels(&img) > text_pixels(&plain) + 200,
        "no legend text"
    );
    let l0 = nameless.layout(800, 500);
    let band = layout.area.top - l0.area.top;
    assert!(band >= layout.text_px, "no legend band: {band}");
    let band_text = (l0.area.top as u32..layout.area.top as u32)
        .flat_map(|y| (0..800).map(move |x| (x, y)))
        .filter(|&(x, y)| is_dark(img.get_pixel(x, y)))
        .count();
    assert!(band_text > 100, "legend text not in the band: {band_text}");
}

#[test]
fn legend_goes_into_a_free_corner() {
    // data in the lower half only: the legend sits inside, top right, and the area keeps its size
    let plot = Plot {
        y_range: Some((0.0, 2.0)),
        series: vec![Series::new(
            "lower half",
            (0..50)
                .map(|k| (k as f64, 0.5 + 0.3 * (k as f64 * 0.4).sin()))
                .collect(),
            SeriesStyle::Line,
        )],
        ..Plot::default()
    };
    let mut nameless = plot.clone();
    nameless.series[0].name.clear();
    let (l, l0) = (plot.layout(600, 400), nameless.layout(600, 400));
    assert_eq!(l.area, l0.area);
    let img = plot.render(600, 400);
    let a = l.area;
    let in_quadrant = |x0: f64, x1: f64| {
        (a.top as u32..(a.top + 0.3 * (a.bottom - a.top)) as u32)
            .flat_map(|y| (x0 as u32..x1 as u32).map(move |x| (x, y)))
            .filter(|&(x, y)| is_dark(img.get_pixel(x, y)))
            .count()
    };
    let mid = 0.5 * (a.left + a.right);
    assert!(in_quadrant(mid, a.right) > 50, "legend not top right");
    assert_eq!(in_quadrant(a.left, mid), 0);
    // the legend hides no data: every pixel of the line stays the line's colour
    let plain = nameless.render(600, 400);
    let c = series_color(0);
    let line = plain.enumerate_pixels().filter(|p| *p.2 == c);
    assert!(line.clone().count() > 200);
    assert!(line.clone().all(|(x, y, _)| *img.get_pixel(x, y) == c));
    // data in every corner but a legend that would fit: pushed above, hiding nothing either
    let full = Plot {
        series: vec![Series::new(
            "everywhere",
            (0..=40).map(|k| (k as f64, (k % 2) as f64)).collect(),
            SeriesStyle::Markers,
        )],
        ..Plot::default()
    };
    let (l, l0) = (full.layout(600, 400), {
        let mut f = full.clone();
        f.series[0].name.clear();
        f.layout(600, 400)
    });
    assert!(
        l.area.top > l0.area.top + l.text_px,
        "{:?} vs {:?}",
        l.area,
        l0.area
    );
    let img = full.render(600, 400);
    for p in &full.series[0].points {
        let (x, y) = l.to_px(*p).unwrap();
        assert_eq!(*img.get_pixel(x as u32, y as u32), c, "marker at {p:?}");
    }
}

#[test]
fn log_axis_error_bars_reaching_zero_run_out_of_the_bottom() {
    let plot = Plot {
        y_log: true,
        series: vec![
            unnamed_line(
                vec![(0.0, 1.0), (1.0, 10.0), (2.0, 100.0)],
                SeriesStyle::Markers,
            )
            .with_error_bars(vec![2.0, 1.0, 10.0]),
        ],
        ..Plot::default()
    };
    let (img, l) = (plot.render(400, 300), plot.layout(400, 300));
    let ink = |x: f64, y: f64| img.get_pixel(x as u32, y as u32).0 == ERROR_BAR;
    // the first bar (1 - 2 < 0) runs down to the bottom row, without a cap there ...
    let x = l.x_to_px(0.0).unwrap();
    let bottom = l.area.bottom + 0.5;
    assert!(ink(x, bottom) && ink(x, l.y_to_px(0.9).unwrap()));
    assert!(!ink(x + 3.0, bottom) && !ink(x - 3.0, bottom));
    // ... but has one at 1 + 2 = 3, like the bars inside the axes at both ends
    assert!(ink(x + 3.0, l.y_to_px(3.0).unwrap()));
    let x = l.x_to_px(1.0).unwrap();
    assert!(ink(x + 3.0, l.y_to_px(9.0).unwrap()) && ink(x + 3.0, l.y_to_px(11.0).unwrap()));
    // the axis spans the bars' tops and, below, the points themselves
    assert!(l.y.lo < 0.9 && l.y.lo > 0.5 && l.y.hi > 110.0, "{:?}", l.y);
}

#[test]
fn a_narrow_log_axis_still_gets_labelled_ticks() {
    // no power of ten between 0.236 and 0.243 (plotters' log ticks: none)
    let plot = Plot {
        x_log: true,
        series: vec![unnamed_line(
            vec![(0.2361, 0.324), (0.2372, 0.3241), (0.2428, 0.3131)],
            SeriesStyle::Markers,
        )],
        ..Plot::default()
    };
    let l = plot.layout(800, 500);
    assert!(l.x_ticks.len() >= 3, "{:?}", l.x_ticks);
    assert!(
        labels(&l.x_ticks).iter().all(|s| s.starts_with("0.2")),
        "{:?}",
        l.x_ticks
    );
    // and the labels are drawn: text below the plot area under the first tick
    let img = plot.render(800, 500);
    let x = l.x_to_px(l.x_ticks[0].0).unwrap() as u32;
    let below = (l.area.bottom as u32 + 5..l.area.bottom as u32 + 30)
        .flat_map(|y| (x - 12..x + 12).map(move |x| (x, y)))
        .filter(|&(x, y)| is_dark(img.get_pixel(x, y)))
        .count();
    assert!(below > 10, "{below} label pixels");
}

#[test]
fn non_finite_points_are_skipped_and_break_the_line() {
    let plot = Plot {
        series: vec![unnamed_line(
            vec![
                (0.0, 0.0),
                (1.0, f64::NAN),
                (2.0, 0.0),
                (3.0, 0.0),
                (f64::INFINITY, 5.0),
                (4.0, 1.0),
            ],
            SeriesStyle::Line,
        )],
        ..Plot::default()
    };
    let img = plot.render(500, 300);
    let l = plot.layout(500, 300);
    // x from 0 to 4 and y from 0 to 1: the infinite and NaN points did not stretch the axes
    assert!(
        (l.x.lo + 0.16).abs() < 1e-12 && (l.x.hi - 4.16).abs() < 1e-12,
        "{:?}",
        l.x
    );
    assert!((l.y.hi - 1.04).abs() < 1e-12, "{:?}", l.y);
    let c = series_color(0);
    let row = l.y_to_px(0.0).unwrap() as u32;
    // gap between x = 0 and x = 2 (the NaN point breaks the line) ...
    assert_ne!(*img.get_pixel(l.x_to_px(1.0).unwrap() as u32, row), c);
    // ... a segment from x = 2 to x = 3
    assert_eq!(*img.get_pixel(l.x_to_px(2.5).unwrap() as u32, row), c);
    // ... and no segment from 3 to 4 across the infinite point
    let mid = l.to_px((3.5, 0.5)).unwrap();
    assert_ne!(*img.get_pixel(mid.0 as u32, mid.1 as u32), c);
}

#[test]
fn degenerate_inputs_render_without_panicking() {
    let cases: Vec<Vec<(f64, f64)>> = vec![
        vec![],
        vec![(f64::NAN, f64::NAN)],
        vec![(1.0, 1.0)],
        vec![(0.0, 0.0)],
        vec![(2.0, 5.0), (2.0, 5.0), (2.0, 5.0)],
        vec![(-1e308, 1e308), (1e308, -1e308)],
        vec![
            (f64::MIN_POSITIVE, 1.0),
            (2.0 * f64::MIN_POSITIVE, 1.0 + 1e-15),
        ],
        vec![(5e-324, 5e-324), (1e-323, 1.5e-323)], // subnormal values and ranges
        vec![(1e300, -1e300), (1.0000001e300, -1.0000001e300)],
        vec![(f64::INFINITY, f64::NEG_INFINITY)],
        vec![(-5.0, -2.0), (-1.0, 0.0)], // nothing positive for the log axes
    ];
    for pts in cases {
        for (x_log, y_log) in [(false, false), (true, true), (false, true)] {
            for style in [
                SeriesStyle::Line,
                SeriesStyle::Markers,
                SeriesStyle::LineMarkers,
            ] {
                let plot = Plot {
                    title: "t".into(),
                    x_label: "x".into(),
                    y_label: "y".into(),
                    x_log,
                    y_log,
                    series: vec![
                        Series::new("s", pts.clone(), style)
                            .with_error_bars(vec![f64::NAN; pts.len()]),
                    ],
                    ..Plot::default()
                };
                for (w, h) in [(0, 0), (1, 1), (7, 300), (40, 20), (320, 200)] {
                    let img = plot.render(w, h);
                    assert_eq!(img.dimensions(), (w, h));
                }
                let l = plot.layout(320, 200);
                assert!(l.x.lo < l.x.hi && l.y.lo < l.y.hi, "{pts:?}: {l:?}");
                assert!(l.x.lo.is_finite() && l.y.hi.is_finite());
            }
        }
    }
    // a legend taller than the image: no free corner, a band above with no room left below
    let crowded = Plot {
        title: "t".into(),
        series: (0..30)
            .map(|i| {
                Series::new(
                    format!("series {i}"),
                    vec![(0.0, 0.0), (1.0, 1.0), (0.0, 1.0)],
                    SeriesStyle::LineMarkers,
                )
            })
            .collect(),
        ..Plot::default()
    };
    for (w, h) in [(320, 200), (120, 400), (900, 60)] {
        assert_eq!(crowded.render(w, h).dimensions(), (w, h));
        let l = crowded.layout(w, h);
        assert!(
            l.area.bottom < h as f64 && l.area.right < w as f64,
            "{w} x {h}: {l:?}"
        );
    }
    // unusable fixed ranges fall back to the data
    let plot = Plot {
        x_range: Some((1.0, 1.0)),
        y_range: Some((f64::NAN, 2.0)),
        series: vec![unnamed_line(
            vec![(0.0, 0.0), (1.0, 1.0)],
            SeriesStyle::Line,
        )],
        ..Plot::default()
    };
    let l = plot.layout(300, 200);
    assert!((l.x.lo + 0.04).abs() < 1e-12 && (l.y.hi - 1.04).abs() < 1e-12);
    plot.render(300, 200);
}

#[test]
fn log_axes_map_decades_evenly() {
    let plot = Plot {
        x_log: true,
        y_log: true,
        x_range: Some((1.0, 1000.0)),
        y_range: Some((1e-4, 1.0)),
        series: vec![unnamed_line(
            vec![
                (1.0, 1.0),
                (10.0, 0.1),
                (100.0, 0.01),
                (1000.0, 1e-3),
                (-1.0, 5.0),
            ],
            SeriesStyle::LineMarkers,
        )],
        ..Plot::default()
    };
    let l = plot.layout(600, 400);
    let xs: Vec<f64> = [1.0, 10.0, 100.0, 1000.0]
        .iter()
        .map(|&v| l.x_to_px(v).unwrap())
        .collect();
    assert!((xs[1] - xs[0] - (xs[3] - xs[2])).abs() < 1e-9);
    // the ends in the first and last column (plotters rounds up by 1e-3 px)
    assert!((xs[0] - l.area.left).abs() < 1e-2 && (xs[3] - l.area.right).abs() < 1e-2);
    assert_eq!(l.x_to_px(-1.0), None);
    assert_eq!(l.x_to_px(0.0), None);
    let labels: Vec<&str> = l.x_ticks.iter().map(|(_, s)| s.as_str()).collect();
    assert_eq!(labels, ["1", "10", "100", "1000"]);
    let ylabels: Vec<&str> = l.y_ticks.iter().map(|(_, s)| s.as_str()).collect();
    assert_eq!(ylabels, ["1e-4", "0.001", "0.01", "0.1", "1"]);
    let img = plot.render(600, 400);
    let (px, py) = l.to_px((10.0, 0.1)).unwrap();
    assert_eq!(*img.get_pixel(px as u32, py as u32), series_color(0));
}

#[test]
fn error_bars_extend_the_range_and_are_drawn() {
    let plot = Plot {
        series: vec![
            unnamed_line(vec![(0.0, 1.0), (1.0, 2.0)], SeriesStyle::Markers)
                .with_error_bars(vec![0.5, 1.0]),
        ],
        ..Plot::default()
    };
    let l = plot.layout(400, 300);
    // y from 0.5 to 3.0 plus the 4 % margin
    assert!(
        (l.y.lo - 0.4).abs() < 1e-12 && (l.y.hi - 3.1).abs() < 1e-12,
        "{:?}",
        l.y
    );
    let img = plot.render(400, 300);
    // the bar above the second point, beyond the marker
    let (px, _) = l.to_px((1.0, 2.0)).unwrap();
    let py = l.y_to_px(2.8).unwrap();
    assert_eq!(img.get_pixel(px as u32, py as u32).0, ERROR_BAR);
    // and its cap at y + e
    let cap_y = l.y_to_px(3.0).unwrap();
    assert_eq!(img.get_pixel(px as u32 + 3, cap_y as u32).0, ERROR_BAR);

    let bad = Plot {
        series: vec![Series::new("a", vec![(0.0, 1.0)], SeriesStyle::Line).with_error_bars(vec![])],
        ..Plot::default()
    };
    let e = bad.validate().unwrap_err().to_string();
    assert!(
        e.contains("0 error bars for 1 points") && e.contains("'a'"),
        "{e}"
    );
    assert!(bad.to_png(100, 100).is_err());
    let neg = Plot {
        series: vec![
            Series::new("b", vec![(0.0, 1.0)], SeriesStyle::Line).with_error_bars(vec![-1.0]),
        ],
        ..Plot::default()
    };
    assert!(neg.validate().unwrap_err().to_string().contains("negative"));
    bad.render(100, 100); // rendering tolerates it
}

#[test]
fn bar_chart_bars_land_where_the_layout_says() {
    let chart = BarChart {
        title: "Variants".into(),
        y_label: "JSD".into(),
        categories: vec!["all".into(), "front".into(), "rear".into()],
        groups: vec![
            BarGroup {
                name: "full".into(),
                values: vec![0.1, 0.2, 0.3],
                errors: Some(vec![0.01, 0.02, 0.03]),
            },
            BarGroup {
                name: "no CACM".into(),
                values: vec![0.15, f64::NAN, -0.1],
                errors: None,
            },
        ],
    };
    chart.validate().unwrap();
    let (w, h) = (600, 400);
    let img = chart.render(w, h);
    let l = chart.layout(w, h);
    // the axis spans the negative bar and the top error bar
    assert!(l.y.lo < -0.1 && l.y.hi > 0.33, "{:?}", l.y);
    // category i spans i - 0.5 .. i + 0.5; its bars fill the middle 80 %
    assert_eq!((l.x.lo, l.x.hi), (-0.5, 2.5));
    assert_eq!(labels(&l.x_ticks), ["all", "front", "rear"]);
    for (gi, g) in chart.groups.iter().enumerate() {
        for (ci, &v) in g.values.iter().enumerate() {
            let cx = l
                .x_to_px(ci as f64 - 0.4 + (gi as f64 + 0.25) * 0.4)
                .unwrap();
            let cy = 0.5
                * (l.y_to_px(0.0).unwrap()
                    + l.y_to_px(if v.is_finite() { v } else { 0.1 }).unwrap());
            let p = *img.get_pixel(cx as u32, cy as u32);
            if v.is_finite() {
                assert_eq!(p, series_color(gi), "group {gi} category {ci}");
            } else {
                assert_ne!(p, series_color(gi), "NaN bar drawn");
            }
        }
    }
    let bad = BarChart {
        categories: vec!["a".into()],
        groups: vec![BarGroup {
            name: "g".into(),
            values: vec![1.0, 2.0],
            errors: None,
        }],
        ..BarChart::default()
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("2 values for 1 categories")
    );
    bad.render(200, 100);
    BarChart::default().render(200, 100);
    BarChart {
        categories: vec!["x".into()],
        groups: vec![BarGroup {
            name: "zero".into(),
            values: vec![0.0],
            errors: Some(vec![f64::INFINITY]),
        }],
        ..BarChart::default()
    }
    .render(120, 80);
}

#[test]
fn png_output_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let plot = Plot {
        title: "Range (m) / density: 1e-3 + 5%".into(),
        series: vec![Series::new(
            "a",
            vec![(0.0, 0.0), (1.0, 2.0)],
            SeriesStyle::Line,
        )],
        ..Plot::default()
    };
    let path = dir.path().join("p.png");
    plot.write_png(&path, 320, 200).unwrap();
    let back = crate::image_io::read_rgb_image(&path).unwrap();
    assert_eq!(back, plot.render(320, 200));
    assert_eq!(
        plot.to_png(320, 200).unwrap(),
        std::fs::read(&path).unwrap()
    );
    assert!(plot.write_png(&path, 0, 10).is_err());
    let e = plot
        .write_png(&dir.path().join("missing/p.png"), 10, 10)
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing"), "{e}");
}

#[test]
fn data_outside_a_fixed_range_stays_inside_the_plot_area() {
    // a steep line and markers far beyond the fixed ranges: clipped at the frame, not drawn over
    // the labels or the title
    let plot = Plot {
        title: "Clipped".into(),
        x_label: "x".into(),
        y_label: "y".into(),
        x_range: Some((0.0, 1.0)),
        y_range: Some((0.0, 1.0)),
        series: vec![
            unnamed_line(
                vec![(-1.0, -4.0), (0.5, 0.5), (2.0, 5.0)],
                SeriesStyle::Line,
            ),
            unnamed_line(
                vec![(-0.5, 0.5), (0.5, 3.0), (0.25, 0.25)],
                SeriesStyle::Markers,
            ),
        ],
        ..Plot::default()
    };
    let (w, h) = (500, 400);
    let img = plot.render(w, h);
    let l = plot.layout(w, h);
    let a = l.area;
    let (c0, c1) = (series_color(0), series_color(1));
    let mut inside = 0;
    for (x, y, p) in img.enumerate_pixels() {
        if *p == c0 {
            let (x, y) = (x as f64, y as f64);
            assert!(
                x >= a.left && x <= a.right && y >= a.top && y <= a.bottom,
                "line pixel ({x}, {y}) outside {a:?}"
            );
            inside += 1;
        }
    }
    // the visible part, (0, 0)..(1, 1) on the line y = 3 x - 1 ... 0.5 -> (1/3, 0)..(2/3, 1)
    assert!(inside > 100, "{inside} line pixels");
    let (px, py) = l.to_px((0.5, 0.5)).unwrap();
    assert_eq!(*img.get_pixel(px as u32, py as u32), c0);
    // the marker inside is drawn, those outside are not
    let (mx, my) = l.to_px((0.25, 0.25)).unwrap();
    assert_eq!(*img.get_pixel(mx as u32, my as u32), c1);
    let marker_px = img.pixels().filter(|p| **p == c1).count();
    assert!(
        (20..100).contains(&marker_px),
        "{marker_px} marker pixels: not one marker"
    );
}

/// Writes sample pictures of every chart kind for looking at (not a check):
/// `VEILA_PLOT_DIR=/tmp/plots cargo test -p veila-data --features vis --lib -- --ignored sample_pictures`.
#[test]
#[ignore = "writes pictures for a person to look at"]
fn sample_pictures() {
    let Some(dir) = std::env::var_os("VEILA_PLOT_DIR") else {
        return;
    };
    let dir = std::path::PathBuf::from(dir);
    std::fs::create_dir_all(&dir).unwrap();
    let train = |decay: f64, floor: f64| -> Vec<(f64, f64)> {
        (0..=200)
            .map(|i| {
                let step = i as f64 * 500.0;
                let wiggle = 0.04 * ((i as f64) * 0.7).sin();
                let y = floor + (1.0 - floor) * (-step / decay).exp() * (1.0 + wiggle);
                (step, y)
            })
            .collect()
    };
    let val: Vec<(f64, f64)> = (1..=10)
        .map(|k| (k as f64 * 10_000.0, 0.05 + 0.6 * (-(k as f64) / 2.5).exp()))
        .collect();
    Plot {
        title: "Denoiser training (eps-prediction MSE)".into(),
        x_label: "optimizer step".into(),
        y_label: "loss".into(),
        y_log: true,
        series: vec![
            Series::new(
                "train, full model",
                train(15_000.0, 0.04),
                SeriesStyle::Line,
            ),
            Series::new("train, no CACM", train(22_000.0, 0.06), SeriesStyle::Line),
            Series::new("validation", val.clone(), SeriesStyle::LineMarkers)
                .with_error_bars(val.iter().map(|p| 0.15 * p.1).collect()),
        ],
        ..Plot::default()
    }
    .write_png(&dir.join("loss.png"), 800, 500)
    .unwrap();
    let scatter: Vec<(f64, f64)> = (0..150)
        .map(|i| {
            let r = 2.0 + 78.0 * ((i * 37 % 150) as f64 / 150.0);
            (r, -0.02 * r + 0.3 * (((i * 91) % 101) as f64 / 101.0 - 0.5))
        })
        .collect();
    Plot {
        title: "Range error vs. range".into(),
        x_label: "range (m)".into(),
        y_label: "error (m)".into(),
        series: vec![
            Series::new("points", scatter, SeriesStyle::Markers),
            Series::new(
                "fit: -0.02 x",
                vec![(0.0, 0.0), (80.0, -1.6)],
                SeriesStyle::Line,
            ),
        ],
        ..Plot::default()
    }
    .write_png(&dir.join("scatter.png"), 640, 400)
    .unwrap();
    let group = |name: &str, v: [f64; 3]| BarGroup {
        name: name.into(),
        values: v.to_vec(),
        errors: Some(v.iter().map(|x| 0.05 * x).collect()),
    };
    BarChart {
        title: "Ablation: JSD per region (lower is better)".into(),
        y_label: "JSD".into(),
        categories: vec!["all".into(), "front".into(), "rear".into()],
        groups: vec![
            group("Veila (full)", [0.081, 0.064, 0.097]),
            group("w/o CACM", [0.094, 0.071, 0.118]),
            group("w/o PFC", [0.089, 0.070, 0.108]),
        ],
    }
    .write_png(&dir.join("bars.png"), 640, 400)
    .unwrap();
    // the CLI's sampler trade-off: log x, markers and lines, legend placed by the data
    let sweep = |a: f64, b: f64| -> Vec<(f64, f64)> {
        [1.0, 2.0, 5.0, 10.0, 20.0]
            .iter()
            .map(|&t| (a * t, b / t.sqrt() + 0.02))
            .collect()
    };
    Plot {
        title: "Generation: quality vs time per scan (points: step counts)".into(),
        x_label: "seconds per scan (log)".into(),
        y_label: "BEV JSD (all)".into(),
        x_log: true,
        series: vec![
            Series::new("ddpm", sweep(0.8, 0.2), SeriesStyle::LineMarkers),
            Series::new("ddim", sweep(0.1, 0.25), SeriesStyle::LineMarkers),
            Series::new("dpm", sweep(0.05, 0.22), SeriesStyle::LineMarkers),
        ],
        ..Plot::default()
    }
    .write_png(&dir.join("sampler_tradeoff.png"), 800, 500)
    .unwrap();
    let mut img = RgbImage::from_pixel(560, 120, Rgb([255, 255, 255]));
    let chars: String = (32u8..=126).map(char::from).collect();
    for (i, line) in chars.as_bytes().chunks(32).enumerate() {
        let line = std::str::from_utf8(line).unwrap();
        draw_text(&mut img, 8, 12 + 36 * i as i64, line, 18.0, Rgb([0, 0, 0]));
    }
    crate::image_io::write_png(&dir.join("font.png"), &img).unwrap();
    let grid = crate::vis::density::BevGrid {
        half_extent_m: 20.0,
        cell_m: 0.5,
    };
    let n = grid.side();
    let a: Vec<f64> = (0..n * n)
        .map(|k| ((k % n) as f64 / n as f64) * 1e-3)
        .collect();
    let b = vec![0.4e-3; n * n];
    let (diff, _) = grid.difference_image(&a, &b);
    crate::image_io::write_png(&dir.join("bev_difference.png"), &diff).unwrap();
}
