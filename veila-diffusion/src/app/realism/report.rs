//! The realism benchmark's report: its rows ([`Row`]) and what was run ([`RealismReport`]), as
//! `report.json`, `report.md` (one table per group of metrics) and `frontier.png` (realism
//! against faithfulness).

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;
use veila_data::vis::plot::{Plot, Series, SeriesStyle};

use crate::app::report_files::write_report_files;
use crate::app::scoring::{SetMetrics, Stat, metric_stats};
use crate::error::Result;

/// One row: a baseline, the floor or a model at one sampler setting.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// Its label in the tables.
    pub label: String,
    /// `model`, `baseline`, `floor` or `calibration`.
    pub kind: &'static str,
    /// Seconds per generated scan (model rows).
    pub seconds_per_scan: Option<f64>,
    /// metric -> region -> stat over folds (x seeds)
    pub metrics: BTreeMap<String, BTreeMap<String, Stat>>,
}

impl Row {
    /// A row of the per-set metrics `sets` and, where there are any, the diversity sets
    /// `extra`; `n` scans per set.
    pub(super) fn new(
        label: String,
        kind: &'static str,
        seconds_per_scan: Option<f64>,
        (sets, extra): (&[SetMetrics], &[SetMetrics]),
        n: usize,
    ) -> Self {
        let mut metrics = metric_stats(sets, n);
        if !extra.is_empty() {
            metrics.extend(metric_stats(extra, n));
        }
        Row {
            label,
            kind,
            seconds_per_scan,
            metrics,
        }
    }

    /// The mean of `metric` in `region`, where the row has it.
    fn mean(&self, metric: &str, region: &str) -> Option<f64> {
        self.metrics.get(metric)?.get(region).map(|s| s.mean)
    }
}

/// The whole report (`report.json`).
#[derive(Debug, Clone, Serialize)]
pub struct RealismReport {
    /// The command line that ran it.
    pub command: String,
    /// When (UTC).
    pub date_utc: String,
    /// Where.
    pub machine: String,
    /// The test frames' scene list.
    pub test_split: String,
    /// Folds of the test frames.
    pub folds: usize,
    /// Frames per fold.
    pub fold_size: usize,
    /// Sample seeds per frame.
    pub seeds: usize,
    /// Training frames in the pool.
    pub train_frames: usize,
    /// The rows.
    pub rows: Vec<Row>,
}

/// A metric and the regions it is shown for.
type Column = (&'static str, &'static [&'static str]);

/// The report's groups of metrics: a table each, a column per metric and region.
const GROUPS: [(&str, &[Column]); 4] = [
    (
        "Realism",
        &[
            ("fpd", &["all", "front", "rear"]),
            ("frd", &["all", "front", "rear"]),
            ("jsd", &["all", "front", "rear"]),
            ("mmd (x1e4)", &["all", "front", "rear"]),
        ],
    ),
    (
        "Texture",
        &[
            ("texture along rows (w1, decades)", &["view", "outside"]),
            ("texture across rows (w1, decades)", &["view", "outside"]),
            ("depth edges (%)", &["view", "outside"]),
            ("smooth pairs (%)", &["view", "outside"]),
            ("ray drop per row (abs diff)", &["all"]),
        ],
    ),
    (
        "Faithfulness",
        &[
            ("range mae (m)", &["view", "front", "rear"]),
            ("cm-dc (abs rel)", &["front"]),
            ("cm-sc (%)", &["front"]),
        ],
    ),
    (
        "Diversity and memorisation",
        &[
            ("diversity (range mae, m)", &["front", "rear"]),
            ("nearest train scan (log2 m)", &["all"]),
        ],
    ),
];

/// `mean ± std` with as many digits as the mean's size asks for (`n/a` when not finite).
fn fmt_stat(st: &Stat) -> String {
    if !st.mean.is_finite() {
        return "n/a".into();
    }
    let d = match st.mean.abs() {
        a if a >= 100.0 => 1,
        a if a >= 1.0 => 2,
        a if a >= 0.01 => 3,
        _ => 4,
    };
    format!("{:.d$} ± {:.d$}", st.mean, st.std)
}

impl RealismReport {
    /// Writes `report.json`, `report.md` and `frontier.png` into `out` (created if need be).
    pub fn write(&self, out: &Path) -> Result<()> {
        write_report_files(out, self, &self.markdown())?;
        // a legend that fits no free corner stacks above the axes: grow the canvas with the rows
        // so the axes keep their height either way
        let plot = self.frontier();
        let height = 420 + 26 * plot.series.len() as u32;
        plot.write_png(&out.join("frontier.png"), 900, height)?;
        Ok(())
    }

    /// The report's tables: one per group of metrics, a column per metric and region.
    pub fn markdown(&self) -> String {
        let r = self;
        let mut s = format!(
            "# Realism benchmark\n\n`{}` on {} ({}): {} folds of {} frames of `{}`, {} sample seeds per frame; baselines and the memorisation pool from the first {} frames of the training list. Mean ± std over folds (x seeds). Lower is better except the shares and the diversity, which should match the floor.\n\n",
            r.command,
            r.date_utc,
            r.machine,
            r.folds,
            r.fold_size,
            r.test_split,
            r.seeds,
            r.train_frames
        );
        for (title, cols) in GROUPS {
            s += &format!("## {title}\n\n| row | s / scan |");
            for (m, regions) in cols {
                for reg in *regions {
                    s += &format!(" {m} {reg} |");
                }
            }
            s += "\n|---|---|";
            for (_, regions) in cols {
                s += &"---|".repeat(regions.len());
            }
            s += "\n";
            for row in &r.rows {
                let name = if row.kind == "model" {
                    row.label.clone()
                } else {
                    format!("*{}*", row.label)
                };
                let secs = row.seconds_per_scan.map(|t| format!("{t:.3}"));
                s += &format!("| {name} | {} |", secs.unwrap_or_default());
                for (m, regions) in cols {
                    for reg in *regions {
                        let cell = row
                            .metrics
                            .get(*m)
                            .and_then(|x| x.get(*reg))
                            .map(fmt_stat)
                            .unwrap_or_else(|| "–".into());
                        s += &format!(" {cell} |");
                    }
                }
                s += "\n";
            }
            s += "\n";
        }
        s += "![realism against faithfulness](frontier.png)\n";
        s
    }

    /// FPD (all) against the range MAE in the camera's view, every row that has both.
    fn frontier(&self) -> Plot {
        let series = self
            .rows
            .iter()
            .filter_map(|row| {
                let x = row.mean("range mae (m)", "view")?;
                let y = row.mean("fpd", "all")?;
                let points = vec![(x, y)];
                Some(Series::new(row.label.clone(), points, SeriesStyle::Markers))
            })
            .collect();
        Plot {
            title: "Realism against faithfulness (every row)".into(),
            x_label: "range MAE in the camera's view (m)".into(),
            y_label: "FPD, whole panorama (log)".into(),
            y_log: true,
            series,
            ..Plot::default()
        }
    }
}
