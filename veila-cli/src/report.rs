//! The HTML report of `veila eval --report`: the metric table, bird's-eye views, the BEV density
//! difference, range and height distributions of the two scan sets, built with
//! `veila_data::vis::html` (self-contained pages: inline CSS, images as `data:` URLs).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use veila_data::image::RgbImage;
use veila_data::vis::density::{BevGrid, histogram};
use veila_data::vis::html::{Cell, HtmlReport, format_value};
use veila_data::vis::plot::{Plot, Series, SeriesStyle};
use veila_data::vis::render::{BevOptions, render_bev};
use veila_metrics::{MetricReport, Region};

/// The metric table of a report: one row per (metric, protocol), one column per region (in the
/// order all, front, rear, of those present). Values raw; where papers print a scaled value, it is
/// shown underneath.
pub(crate) fn metric_table(report: &MetricReport) -> (Vec<String>, Vec<Vec<Cell>>) {
    let regions: Vec<Region> = [Region::All, Region::Front, Region::Rear]
        .into_iter()
        .filter(|r| report.metrics.iter().any(|m| m.region == *r))
        .collect();
    let mut keys: Vec<(String, veila_metrics::Protocol)> = Vec::new();
    for m in &report.metrics {
        if !keys.iter().any(|(n, p)| *n == m.name && *p == m.protocol) {
            keys.push((m.name.clone(), m.protocol));
        }
    }
    let mut header = vec!["metric".to_string(), "protocol".to_string()];
    header.extend(regions.iter().map(|r| r.name().to_string()));
    let rows = keys
        .iter()
        .map(|(name, protocol)| {
            let mut row = vec![Cell::Text(name.clone()), Cell::Text(protocol.name().into())];
            for r in &regions {
                let m = report
                    .metrics
                    .iter()
                    .find(|m| m.name == *name && m.protocol == *protocol && m.region == *r);
                row.push(match m {
                    Some(m) => Cell::Num {
                        value: format_value(m.value),
                        note: m
                            .paper_scale
                            .map(|s| format!("×{s:.0e}: {}", format_value(m.value * s))),
                    },
                    None => Cell::Empty,
                });
            }
            row
        })
        .collect();
    (header, rows)
}

/// The command line, with arguments quoted where a shell would need it. An argument that is not
/// UTF-8 (a path of another encoding) is shown with U+FFFD for its invalid bytes: `args()` would
/// panic on it.
pub(crate) fn command_line() -> String {
    std::env::args_os()
        .map(|a| a.to_string_lossy().into_owned())
        .map(|a| {
            let plain = !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c));
            if plain {
                a
            } else {
                format!("'{}'", a.replace('\'', "'\\''"))
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// Fail early (before an expensive evaluation) when a report could not be written.
pub(crate) fn check_output_dir(path: &Path) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        anyhow::bail!(
            "{}: the report's folder {} does not exist",
            path.display(),
            dir.display()
        );
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------------
// the report of `veila eval`

/// BEV preview options of the report (stated in the captions).
pub(crate) const PREVIEW_BEV: BevOptions = BevOptions {
    half_extent_m: 50.0,
    resolution_m: 0.2,
    z_min_m: -2.5,
    z_max_m: 1.5,
};

/// At most this many scans per set feed the distribution figures (evenly spaced over the set).
pub(crate) const FIGURE_SAMPLE: usize = 64;

/// Cell size (m) of the BEV density-difference image and its half extent.
const DIFF_CELL_M: f64 = 0.5;
const DIFF_HALF_EXTENT_M: f64 = 50.0;
const DIFF_GRID: BevGrid = BevGrid {
    half_extent_m: DIFF_HALF_EXTENT_M,
    cell_m: DIFF_CELL_M,
};

/// Inputs of the `veila eval` report.
pub(crate) struct EvalReportInputs<'a> {
    pub generated_dir: &'a Path,
    pub reference_dir: &'a Path,
    pub generated: &'a [PathBuf],
    pub reference: &'a [PathBuf],
    pub metrics: &'a MetricReport,
    pub date: String,
    pub command: String,
}

/// Evenly spaced sample of at most `n` items, the first always included.
fn sample<T>(items: &[T], n: usize) -> Vec<&T> {
    if items.len() <= n {
        return items.iter().collect();
    }
    (0..n).map(|i| &items[i * items.len() / n]).collect()
}

fn read_cloud(path: &Path) -> Result<veila_data::PointCloud> {
    Ok(veila_data::scan::read_points(path)
        .with_context(|| format!("reading {} for the report", path.display()))?
        .cloud)
}

/// Build the report of a `veila eval` run.
pub(crate) fn eval_report(inp: &EvalReportInputs<'_>) -> Result<HtmlReport> {
    let mut rep = HtmlReport::new("veila eval report");
    let n_scans =
        |dir: &Path, files: &[PathBuf]| format!("{} ({} scans)", dir.display(), files.len());
    let mut metric_names: Vec<String> = Vec::new();
    for m in &inp.metrics.metrics {
        let label = format!("{} ({})", m.name, m.protocol.name());
        if !metric_names.contains(&label) {
            metric_names.push(label);
        }
    }
    rep.key_values(vec![
        ("command".into(), inp.command.clone()),
        (
            "generated".into(),
            n_scans(inp.generated_dir, inp.generated),
        ),
        (
            "reference".into(),
            n_scans(inp.reference_dir, inp.reference),
        ),
        ("metrics".into(), metric_names.join(", ")),
        ("date".into(), inp.date.clone()),
        (
            "version".into(),
            format!(
                "veila {} ({} build)",
                env!("CARGO_PKG_VERSION"),
                if cfg!(debug_assertions) {
                    "debug"
                } else {
                    "release"
                }
            ),
        ),
    ]);

    rep.section("Metrics");
    let (header, rows) = metric_table(inp.metrics);
    rep.table(
        Some(
            "Lower is better. Raw values; where papers print a scaled value (MMD x 1e4), it is shown \
             under the raw one. Regions: all = whole panorama, front = x > 0, rear = x <= 0."
                .into(),
        ),
        header,
        rows,
    );
    rep.paragraph(
        "Protocols: r2dm = BEV histograms of R2DM / LiDARGen (JSD; MMD with a Gaussian kernel, \
         Frobenius distance); lidargen = spectral-norm MMD; lidm = minimum matching distance over \
         0.5 m BEV occupancy (LiDAR-Diffusion); pytorch3d = Chamfer distance with squared distances, \
         means summed; frechet = Fréchet distance of feature statistics.",
    );

    // previews of the first scans
    rep.section("Bird's-eye views");
    let (g0, r0) = (&inp.generated[0], &inp.reference[0]);
    let (gc, rc) = (read_cloud(g0)?, read_cloud(r0)?);
    let name = |p: &Path| {
        p.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let bev_caption = |what: &str, p: &Path| {
        format!(
            "{what} scan {}: bird's-eye view, ±{} m, {} m per pixel, forward (+x) up, coloured by \
             height ({} m dark to {} m bright)",
            name(p),
            PREVIEW_BEV.half_extent_m,
            PREVIEW_BEV.resolution_m,
            PREVIEW_BEV.z_min_m,
            PREVIEW_BEV.z_max_m
        )
    };
    let png = |img: &RgbImage| veila_data::image_io::encode_png(img).context("encoding a PNG");
    rep.figures(vec![
        (
            bev_caption("First generated", g0),
            png(&render_bev(&gc, &PREVIEW_BEV)?)?,
        ),
        (
            bev_caption("First reference", r0),
            png(&render_bev(&rc, &PREVIEW_BEV)?)?,
        ),
    ]);

    // distributions over a sample of each set
    let gen_sample = sample(inp.generated, FIGURE_SAMPLE);
    let ref_sample = sample(inp.reference, FIGURE_SAMPLE);
    let load = |files: &[&PathBuf]| -> Result<Vec<veila_data::PointCloud>> {
        files.iter().map(|f| read_cloud(f)).collect()
    };
    let (gen_clouds, ref_clouds) = (load(&gen_sample)?, load(&ref_sample)?);
    let sample_note = |k: usize, n: usize| {
        if k == n {
            format!("{n} scan{}", if n == 1 { "" } else { "s" })
        } else {
            format!("{k} of {n} scans, evenly spaced")
        }
    };
    let (gs, rs) = (
        sample_note(gen_sample.len(), inp.generated.len()),
        sample_note(ref_sample.len(), inp.reference.len()),
    );
    let (gd, rd) = (
        DIFF_GRID.density(&gen_clouds),
        DIFF_GRID.density(&ref_clouds),
    );
    let (diff, max) = DIFF_GRID.difference_image(&gd, &rd);
    rep.image(
        format!(
            "BEV point density, generated minus reference ({gs} / {rs}; {DIFF_CELL_M} m cells, \
             ±{DIFF_HALF_EXTENT_M} m, each set normalised to sum 1). Red: the generated scans put \
             more points there, blue: fewer; signed square-root colour scale up to ±{max:.2e}."
        ),
        png(&diff)?,
    );

    rep.section("Distributions");
    let ranges = |clouds: &[veila_data::PointCloud]| -> Vec<f64> {
        clouds
            .iter()
            .flat_map(|c| c.xyz.iter().map(|p| p.length() as f64))
            .collect()
    };
    let heights = |clouds: &[veila_data::PointCloud]| -> Vec<f64> {
        clouds
            .iter()
            .flat_map(|c| c.xyz.iter().map(|p| p.z as f64))
            .collect()
    };
    let dist_plot = |title: &str, x_label: &str, g: Vec<(f64, f64)>, r: Vec<(f64, f64)>| Plot {
        title: title.into(),
        x_label: x_label.into(),
        y_label: "density".into(),
        series: vec![
            Series::new(format!("generated ({gs})"), g, SeriesStyle::Line),
            Series::new(format!("reference ({rs})"), r, SeriesStyle::Line),
        ],
        ..Plot::default()
    };
    let range_plot = dist_plot(
        "Point range",
        "range (m)",
        histogram(ranges(&gen_clouds).into_iter(), 0.0, 100.0, 100),
        histogram(ranges(&ref_clouds).into_iter(), 0.0, 100.0, 100),
    );
    let height_plot = dist_plot(
        "Point height",
        "z (m)",
        histogram(heights(&gen_clouds).into_iter(), -4.0, 4.0, 80),
        histogram(heights(&ref_clouds).into_iter(), -4.0, 4.0, 80),
    );
    rep.figures(vec![
        (
            "Distribution of point ranges (1 m bins, 0-100 m).".into(),
            range_plot.to_png(720, 450).context("plotting ranges")?,
        ),
        (
            "Distribution of point heights in the LiDAR frame (0.1 m bins, -4 to 4 m).".into(),
            height_plot.to_png(720, 450).context("plotting heights")?,
        ),
    ]);
    Ok(rep)
}
