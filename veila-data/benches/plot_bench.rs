//! Plot rendering: a line plot (3 series x 1000 points, log y, error bars) and a grouped bar chart,
//! each rendered at 800 x 500 and encoded as PNG. No speed/quality knob: the output is exact.

use std::time::Duration;

use criterion::Criterion;
use veila_data::image_io::encode_png;
use veila_data::vis::plot::{BarChart, BarGroup, Plot, Series, SeriesStyle};

fn line_plot() -> Plot {
    let series = (0..3)
        .map(|s| {
            let pts: Vec<(f64, f64)> = (1..=1000)
                .map(|i| {
                    let x = i as f64 * 100.0;
                    (
                        x,
                        (1.0 + s as f64) * 0.05
                            + (-x / 20_000.0).exp() * (1.0 + 0.05 * (i as f64 * 0.3).sin()),
                    )
                })
                .collect();
            let n = pts.len();
            Series::new(format!("variant {s}"), pts, SeriesStyle::Line)
                .with_error_bars(vec![0.0; n])
        })
        .collect();
    Plot {
        title: "training loss".into(),
        x_label: "step".into(),
        y_label: "loss".into(),
        y_log: true,
        series,
        ..Plot::default()
    }
}

fn bar_chart() -> BarChart {
    BarChart {
        title: "metrics per region".into(),
        y_label: "JSD".into(),
        categories: vec!["all".into(), "front".into(), "rear".into()],
        groups: (0..4)
            .map(|g| BarGroup {
                name: format!("model {g}"),
                values: vec![0.08 + 0.01 * g as f64, 0.06, 0.1],
                errors: Some(vec![0.005; 3]),
            })
            .collect(),
    }
}

pub fn bench_plots(c: &mut Criterion) {
    let (plot, bars) = (line_plot(), bar_chart());
    let mut g = c.benchmark_group("veila_data_plot");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(500));
    g.bench_function("line_3x1000_800x500_render", |b| {
        b.iter(|| plot.render(800, 500))
    });
    g.bench_function("line_3x1000_800x500_render_png", |b| {
        b.iter(|| encode_png(&plot.render(800, 500)).unwrap())
    });
    g.bench_function("bars_3x4_800x500_render_png", |b| {
        b.iter(|| encode_png(&bars.render(800, 500)).unwrap())
    });
    g.finish();
    eprintln!(
        "plot PNG sizes: line {} bytes, bars {} bytes",
        plot.to_png(800, 500).unwrap().len(),
        bars.to_png(800, 500).unwrap().len()
    );
}
