//! Renders the kinds of pictures `veila_data::vis` draws (plots, the plot font, range and intensity
//! previews, the BEV density-difference image of the reports) into a folder, as PNG:
//! `cargo run -p veila-data --features vis --example plot_gallery -- OUT_DIR`.

use std::path::PathBuf;

use veila_data::vis::plot::{BarChart, BarGroup, Plot, Series, SeriesStyle};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = PathBuf::from(std::env::args().nth(1).unwrap_or_else(|| ".".into()));
    std::fs::create_dir_all(&out)?;

    // training curves on a logarithmic loss axis, validation points with error bars
    let train = |decay: f64, floor: f64| -> Vec<(f64, f64)> {
        (0..=200)
            .map(|i| {
                let step = i as f64 * 500.0;
                let wiggle = 0.04 * ((i as f64) * 0.7).sin();
                (
                    step,
                    floor + (1.0 - floor) * (-step / decay).exp() * (1.0 + wiggle),
                )
            })
            .collect()
    };
    let val: Vec<(f64, f64)> = (1..=10)
        .map(|k| (k as f64 * 10_000.0, 0.05 + 0.6 * (-(k as f64) / 2.5).exp()))
        .collect();
    let loss = Plot {
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
    };
    loss.write_png(&out.join("loss.png"), 800, 500)?;

    // a scatter plot with linear axes and negative values
    let mut s = 12345u32;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        s as f64 / u32::MAX as f64
    };
    let scatter: Vec<(f64, f64)> = (0..150)
        .map(|_| {
            let r = 2.0 + 78.0 * next();
            (r, -0.02 * r + 0.3 * (next() - 0.5))
        })
        .collect();
    let fit: Vec<(f64, f64)> = vec![(0.0, 0.0), (80.0, -1.6)];
    Plot {
        title: "Range error vs. range".into(),
        x_label: "range (m)".into(),
        y_label: "error (m)".into(),
        series: vec![
            Series::new("points", scatter, SeriesStyle::Markers),
            Series::new("fit: -0.02 x", fit, SeriesStyle::Line),
        ],
        ..Plot::default()
    }
    .write_png(&out.join("scatter.png"), 640, 400)?;

    // model variants per metric
    BarChart {
        title: "Ablation: JSD per region (lower is better)".into(),
        y_label: "JSD".into(),
        categories: vec!["all".into(), "front".into(), "rear".into()],
        groups: vec![
            BarGroup {
                name: "Veila (full)".into(),
                values: vec![0.081, 0.064, 0.097],
                errors: Some(vec![0.004, 0.003, 0.006]),
            },
            BarGroup {
                name: "w/o CACM".into(),
                values: vec![0.094, 0.071, 0.118],
                errors: Some(vec![0.005, 0.004, 0.007]),
            },
            BarGroup {
                name: "w/o PFC".into(),
                values: vec![0.089, 0.070, 0.108],
                errors: Some(vec![0.004, 0.004, 0.006]),
            },
        ],
    }
    .write_png(&out.join("bars.png"), 640, 400)?;

    // the printable ASCII characters in the plot font
    let mut img =
        veila_data::image::RgbImage::from_pixel(560, 120, veila_data::image::Rgb([255, 255, 255]));
    let chars: String = (32u8..=126).map(char::from).collect();
    for (i, line) in chars.as_bytes().chunks(32).enumerate() {
        let line = std::str::from_utf8(line)?;
        veila_data::vis::plot::draw_text(
            &mut img,
            8,
            12 + 36 * i as i64,
            line,
            18.0,
            veila_data::image::Rgb([0, 0, 0]),
        );
    }
    veila_data::image_io::write_png(&out.join("font.png"), &img)?;
    // range and intensity previews (viridis, magma) of a synthetic 32 x 512 scan: a ring of walls
    let (rows, cols) = (32usize, 512usize);
    let mut scan = veila_geom::RangeImage::new_empty(rows as u32, cols as u32);
    for r in 0..rows {
        for c in 0..cols {
            let k = r * cols + c;
            let az = c as f32 / cols as f32 * std::f32::consts::TAU;
            scan.mask[k] = (r + c) % 17 != 0;
            scan.range_m[k] = 3.0 + 40.0 * (0.5 + 0.5 * (3.0 * az).sin()) + r as f32;
            scan.intensity[k] = (0.5 + 0.5 * (7.0 * az).cos()) * (1.0 - r as f32 / rows as f32);
        }
    }
    let range = veila_data::vis::render::render_range(&scan, &Default::default());
    veila_data::image_io::write_png(&out.join("range.png"), &range)?;
    let intensity = veila_data::vis::render::render_intensity(&scan, 1.0, 4);
    veila_data::image_io::write_png(&out.join("intensity.png"), &intensity)?;

    // the reports' BEV density difference: a generated set shifted 2 m forward of the reference
    let ring = |dx: f32| veila_data::PointCloud {
        xyz: (0..20_000)
            .map(|i| {
                let a = i as f32 * 0.01;
                let r = 5.0 + (i % 40) as f32;
                glam::Vec3::new(r * a.cos() + dx, r * a.sin(), -1.5)
            })
            .collect(),
        intensity: vec![0.5; 20_000],
        ring: None,
        label: None,
    };
    let grid = veila_data::vis::density::BevGrid {
        half_extent_m: 50.0,
        cell_m: 0.5,
    };
    let (diff, _) = grid.difference_image(&grid.density(&[ring(2.0)]), &grid.density(&[ring(0.0)]));
    veila_data::image_io::write_png(&out.join("bev_difference.png"), &diff)?;
    eprintln!(
        "wrote loss.png, scatter.png, bars.png, font.png, range.png, intensity.png, \
         bev_difference.png to {}",
        out.display()
    );
    Ok(())
}
