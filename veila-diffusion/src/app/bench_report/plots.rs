//! The report's plots: `variants.png` (every row's BEV JSD by region) and `sampler_tradeoff.png`
//! (quality against time per scan, one line per sampler).

use std::path::Path;

use veila_data::vis::plot::{BarChart, BarGroup, Plot, Series, SeriesStyle};

use super::report::{Report, VariantResult};
use crate::SamplerName;
use crate::app::scoring::Stat;
use crate::error::Result;

/// `variants.png`: every row's BEV JSD by region, the spread over seeds as error bars.
pub(super) fn plot_variants(path: &Path, r: &Report) -> Result<()> {
    let categories: Vec<String> = ["all", "front", "rear"].map(String::from).to_vec();
    let jsd = |v: &VariantResult, part: fn(&Stat) -> f64| -> Vec<f64> {
        categories
            .iter()
            .map(|c| {
                v.metrics
                    .get("jsd")
                    .and_then(|m| m.get(c))
                    .map_or(f64::NAN, part)
            })
            .collect()
    };
    let groups: Vec<BarGroup> = r
        .variants
        .iter()
        .map(|v| BarGroup {
            name: v.label.clone(),
            values: jsd(v, |s| s.mean),
            errors: Some(jsd(v, |s| s.std)),
        })
        .collect();
    BarChart {
        title: "BEV JSD by region (lower is better; bars: seed std)".into(),
        y_label: "JSD".into(),
        categories,
        groups,
    }
    .write_png(path, 960, 480)?;
    Ok(())
}

/// `sampler_tradeoff.png`: quality against time per scan, one line per sampler (its step
/// counts as points; full samples only).
pub(super) fn plot_sweep(path: &Path, r: &Report) -> Result<()> {
    let series = SamplerName::ALL
        .map(SamplerName::as_str)
        .into_iter()
        .map(|name| {
            let pts: Vec<(f64, f64)> = r
                .sweep
                .iter()
                .filter(|p| p.sampler == name && p.residual_weight == 1.0)
                .map(|p| (p.seconds_per_scan, p.jsd_all))
                .collect();
            Series::new(name, pts, SeriesStyle::LineMarkers)
        })
        .collect();
    Plot {
        title: "Generation: quality vs time per scan (points: step counts)".into(),
        x_label: "seconds per scan (log)".into(),
        y_label: "BEV JSD (all)".into(),
        x_log: true,
        series,
        ..Plot::default()
    }
    .write_png(path, 800, 500)?;
    Ok(())
}
