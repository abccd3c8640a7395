//! The augmentation benchmark's report: each run's result, each row's mean ± std over the
//! training seeds, and at each labelled fraction the verdict on the generated scans against the
//! supervised row and against the true-scan control.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::data::ScanSource;
use super::options::{AugmentOptions, pct};
use crate::app::bundle::Bundle;
use crate::app::report_files::write_report_files;
use crate::app::segment::LabelSpace;
use crate::error::Result;
use crate::sampler::SamplerConfig;

/// The row of the segmenter trained on the labelled frames alone.
pub const SUPERVISED: &str = "supervised only (the teacher)";
/// The row of the segmenter trained on the whole split's labels.
pub const WHOLE_SPLIT: &str =
    "supervised on the whole split (the whole-split teacher; every label)";
/// The row of the generated scans pseudo-labelled by the whole-split teacher.
pub const WHOLE_TEACHER: &str =
    "+ generated scans, whole-split teacher (the paper's variant; uses more labels)";

/// The row of `source`'s scans pseudo-labelled by the fraction's teacher.
pub fn source_row(source: ScanSource) -> String {
    format!("+ {}", source.title())
}

/// A mean-IoU difference smaller than this (in IoU, 0.5 points) is not called a change.
pub const MIN_EFFECT: f64 = 0.005;

/// One segmenter run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    /// Its folder under `work/runs/`.
    pub name: String,
    /// Its row.
    pub row: String,
    /// The labelled fraction (none: the whole split).
    pub fraction: Option<f64>,
    /// The training seed.
    pub seed: u64,
    /// Frames with their true labels.
    pub labelled_frames: usize,
    /// Pseudo-labelled frames.
    pub pseudo_frames: usize,
    /// mIoU over the included classes on the test frames.
    pub miou: f64,
    /// Mean IoU over the classes present in the test frames.
    pub miou_present: f64,
    /// Point accuracy.
    pub accuracy: f64,
    /// IoU of every class.
    pub iou: Vec<f64>,
    /// The classes present in the test frames.
    pub present: Vec<usize>,
    /// Seconds of training.
    pub train_seconds: f64,
    /// Seconds of the run (data, training, scoring) in the session that finished it.
    pub wall_seconds: f64,
}

/// A row's runs over the seeds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RowStats {
    /// The row.
    pub row: String,
    /// Frames with their true labels.
    pub labelled_frames: usize,
    /// Pseudo-labelled frames.
    pub pseudo_frames: usize,
    /// mIoU of each seed, in the options' seed order.
    pub miou_per_seed: Vec<f64>,
    /// Mean of the mIoU over seeds.
    pub miou: f64,
    /// Its standard deviation over seeds (n − 1; 0 for one seed).
    pub miou_std: f64,
    /// Mean over seeds of the mean IoU over the classes present.
    pub miou_present: f64,
    /// Mean accuracy.
    pub accuracy: f64,
    /// Mean IoU of every class.
    pub iou: Vec<f64>,
    /// Mean seconds of training a run.
    pub train_seconds: f64,
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn std(v: &[f64]) -> f64 {
    if v.len() < 2 {
        return 0.0;
    }
    let m = mean(v);
    (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

impl RowStats {
    fn of(row: &str, runs: &[&RunResult]) -> Option<RowStats> {
        let first = runs.first()?;
        let m: Vec<f64> = runs.iter().map(|r| r.miou).collect();
        let n = first.iou.len();
        Some(RowStats {
            row: row.to_string(),
            labelled_frames: first.labelled_frames,
            pseudo_frames: first.pseudo_frames,
            miou: mean(&m),
            miou_std: std(&m),
            miou_per_seed: m,
            miou_present: mean(&runs.iter().map(|r| r.miou_present).collect::<Vec<_>>()),
            accuracy: mean(&runs.iter().map(|r| r.accuracy).collect::<Vec<_>>()),
            iou: (0..n)
                .map(|c| mean(&runs.iter().map(|r| r.iou[c]).collect::<Vec<_>>()))
                .collect(),
            train_seconds: mean(&runs.iter().map(|r| r.train_seconds).collect::<Vec<_>>()),
        })
    }
}

/// Whether a row helps, hurts or does nothing against another.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    /// `row − against` of each seed's mIoU.
    pub differences: Vec<f64>,
    /// Their mean.
    pub mean: f64,
    /// "helps", "hurts" or "does nothing measurable".
    pub word: String,
}

/// The verdict on `row` against `against`, paired by seed (the same seed starts both runs from
/// the same weights): it helps (hurts) when every seed's difference is positive (negative) and
/// their mean is at least [`MIN_EFFECT`]; otherwise it does nothing measurable.
pub fn verdict(row: &[f64], against: &[f64]) -> Verdict {
    let differences: Vec<f64> = row.iter().zip(against).map(|(a, b)| a - b).collect();
    let m = mean(&differences);
    let word = if !differences.is_empty() && differences.iter().all(|d| *d > 0.0) && m >= MIN_EFFECT
    {
        "helps"
    } else if !differences.is_empty() && differences.iter().all(|d| *d < 0.0) && m <= -MIN_EFFECT {
        "hurts"
    } else {
        "does nothing measurable"
    };
    Verdict {
        differences,
        mean: m,
        word: word.into(),
    }
}

/// Every row at one labelled fraction, with the verdicts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FractionTable {
    /// The fraction.
    pub fraction: f64,
    /// The rows, in the report's order.
    pub rows: Vec<RowStats>,
    /// Generated scans against the supervised row.
    pub generated_vs_supervised: Option<Verdict>,
    /// The true-scan control against the supervised row.
    pub true_vs_supervised: Option<Verdict>,
    /// Generated scans against the true-scan control.
    pub generated_vs_true: Option<Verdict>,
    /// Generated scans against the mean network's.
    pub generated_vs_mean_network: Option<Verdict>,
    /// Generated scans against retrieved ones.
    pub generated_vs_retrieved: Option<Verdict>,
}

/// The whole report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AugmentReport {
    /// The command line.
    pub command: String,
    /// When it was written.
    pub date_utc: String,
    /// The machine.
    pub machine: String,
    /// The bundle and its identity.
    pub model: String,
    /// Lowercase hex SHA-256 of its manifest.
    pub model_manifest_sha256: String,
    /// The sampler of the generated scans.
    pub sampler: SamplerConfig,
    /// The split.
    pub split: String,
    /// The test list and its frames.
    pub test: String,
    /// The options (training settings, fractions, seeds).
    pub options: AugmentOptions,
    /// Seconds a scan of each source took to make when its set was made (0 for the true scans;
    /// none where a cached set does not record it).
    pub seconds_per_scan: Vec<(ScanSource, Option<f64>)>,
    /// The class names, by train id.
    pub classes: Vec<String>,
    /// The whole-split teacher's row.
    pub whole_split: Option<RowStats>,
    /// One table per fraction.
    pub fractions: Vec<FractionTable>,
    /// Every run done so far.
    pub runs: Vec<RunResult>,
    /// Runs the whole table takes (the report is partial while `runs` has fewer).
    pub planned_runs: usize,
    /// Seconds of training over every run.
    pub train_seconds: f64,
    /// Wall seconds of the session that wrote the report.
    pub session_seconds: f64,
}

impl AugmentReport {
    /// The report of `runs`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        opts: &AugmentOptions,
        bundle: &Bundle,
        sampler: &SamplerConfig,
        split: &str,
        test_list: &str,
        seconds_per_scan: Vec<(ScanSource, Option<f64>)>,
        runs: Vec<RunResult>,
        planned_runs: usize,
        session_seconds: f64,
    ) -> Self {
        let rows_of = |fraction: Option<f64>, row: &str| {
            let picked: Vec<&RunResult> = opts
                .seeds
                .iter()
                .filter_map(|s| {
                    runs.iter()
                        .find(|r| r.seed == *s && r.fraction == fraction && r.row == row)
                })
                .collect();
            RowStats::of(row, &picked)
        };
        let mut order = vec![SUPERVISED.to_string()];
        order.extend(ScanSource::ALL.iter().map(|s| source_row(*s)));
        order.push(WHOLE_TEACHER.to_string());
        let fractions = opts
            .fractions
            .iter()
            .map(|&f| {
                let rows: Vec<RowStats> = order
                    .iter()
                    .filter_map(|row| rows_of(Some(f), row))
                    .collect();
                let get = |row: &str| rows.iter().find(|r| r.row == row);
                let vs = |a: &str, b: &str| {
                    Some(verdict(&get(a)?.miou_per_seed, &get(b)?.miou_per_seed))
                };
                let generated = source_row(ScanSource::Generated);
                FractionTable {
                    fraction: f,
                    generated_vs_supervised: vs(&generated, SUPERVISED),
                    true_vs_supervised: vs(&source_row(ScanSource::True), SUPERVISED),
                    generated_vs_true: vs(&generated, &source_row(ScanSource::True)),
                    generated_vs_mean_network: vs(&generated, &source_row(ScanSource::MeanNetwork)),
                    generated_vs_retrieved: vs(&generated, &source_row(ScanSource::Retrieved)),
                    rows,
                }
            })
            .collect();
        let classes = LabelSpace::semantic_kitti()
            .classes()
            .into_iter()
            .map(|c| c.name)
            .collect();
        AugmentReport {
            command: opts.command.clone(),
            date_utc: veila_data::stamp::report_time(),
            machine: veila_nn::process::cpu_cores_phrase(),
            model: opts.model.display().to_string(),
            model_manifest_sha256: bundle.manifest_sha256.clone(),
            sampler: sampler.clone(),
            split: split.to_string(),
            test: format!("{test_list} frames 0..{}", opts.test_frames),
            options: opts.clone(),
            seconds_per_scan,
            classes,
            whole_split: rows_of(None, WHOLE_SPLIT),
            fractions,
            train_seconds: runs.iter().map(|r| r.train_seconds).sum(),
            runs,
            planned_runs,
            session_seconds,
        }
    }

    /// Writes `report.json` and `report.md` into `out`.
    pub fn write(&self, out: &Path) -> Result<()> {
        write_report_files(out, self, &self.markdown())
    }

    /// The report as Markdown: per fraction, the rows with mIoU (mean ± std over seeds) and
    /// training time, the verdicts, then the per-class IoU.
    pub fn markdown(&self) -> String {
        let o = &self.options;
        let t = &o.train;
        let mut s = format!(
            "# Augmentation benchmark: generated scans for LiDAR segmentation\n\n\
             `{}` on {} ({}). Bundle `{}` (manifest sha256 `{}`), {} x {} steps, guidance {}.\n\n\
             Split: {} ({} frames the bundle never trained on); test: {} ({} frames). Every scan \
             on the bundle's grid as points; mIoU over SemanticKITTI's 19 classes on the test \
             frames' points, mean ± std over training seeds {:?}. Each run: the bundled-grid \
             segmenter, {} updates of batch {}, lr {:.1e} (cosine to {:.1e}), {} warm-up updates, weight decay \
             {}, class weights {}, augmentation {}. Training time: {:.1} h over {} runs.\n\n",
            self.command,
            self.date_utc,
            self.machine,
            self.model,
            self.model_manifest_sha256,
            self.sampler.kind,
            self.sampler.steps,
            self.sampler.guidance_scale,
            self.split,
            o.split_frames,
            self.test,
            o.test_frames,
            o.seeds,
            t.steps,
            t.batch,
            t.lr,
            t.min_lr,
            t.warmup_steps,
            t.weight_decay,
            serde_json::to_string(&o.class_weighting).unwrap_or_default(),
            if t.augment { "on" } else { "off" },
            self.train_seconds / 3600.0,
            self.runs.len(),
        );
        if self.runs.len() < self.planned_runs {
            s += &format!(
                "**Partial: {} of {} runs done** (`cargo xtask bench-augment` with the same \
                 options, without `--report-only`, goes on from here; rows show the seeds done \
                 so far).\n\n",
                self.runs.len(),
                self.planned_runs
            );
        }
        s += "Seconds a scan to make: ";
        s += &self
            .seconds_per_scan
            .iter()
            .map(|(src, secs)| match secs {
                Some(secs) => format!("{} {secs:.2}", src.name()),
                None => format!("{} (not recorded)", src.name()),
            })
            .collect::<Vec<_>>()
            .join(", ");
        s += " (when the set was sampled; a resumed run reads it from the work folder).\n\n";
        if let Some(w) = &self.whole_split {
            s += &format!(
                "Whole split labelled ({} frames): mIoU {:.3} ± {:.3}, {:.0} s of training a run.\n\n",
                w.labelled_frames, w.miou, w.miou_std, w.train_seconds
            );
        }
        for f in &self.fractions {
            s += &format!(
                "## {}% labelled\n\n| row | labelled | pseudo-labelled | mIoU | per seed | over classes present | accuracy | training (s) |\n|---|---|---|---|---|---|---|---|\n",
                pct(f.fraction)
            );
            for r in &f.rows {
                s += &format!(
                    "| {} | {} | {} | {:.3} ± {:.3} | {} | {:.3} | {:.3} | {:.0} |\n",
                    r.row,
                    r.labelled_frames,
                    r.pseudo_frames,
                    r.miou,
                    r.miou_std,
                    r.miou_per_seed
                        .iter()
                        .map(|m| format!("{m:.3}"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    r.miou_present,
                    r.accuracy,
                    r.train_seconds
                );
            }
            s += "\n";
            let line = |what: &str, v: &Option<Verdict>| match v {
                Some(v) => format!(
                    "- {what}: **{}** ({:+.1} mIoU points; per seed {})\n",
                    v.word,
                    100.0 * v.mean,
                    v.differences
                        .iter()
                        .map(|d| format!("{:+.1}", 100.0 * d))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
                None => String::new(),
            };
            s += &line(
                "generated scans against supervised only",
                &f.generated_vs_supervised,
            );
            s += &line(
                "the true-scan control against supervised only",
                &f.true_vs_supervised,
            );
            s += &line(
                "generated scans against the true-scan control",
                &f.generated_vs_true,
            );
            s += &line(
                "generated scans against the mean network's",
                &f.generated_vs_mean_network,
            );
            s += &line(
                "generated scans against retrieved ones",
                &f.generated_vs_retrieved,
            );
            s += "\n";
        }
        s += &format!(
            "A row **helps** (hurts) another when every seed's mIoU difference is positive \
             (negative) and their mean is at least {:.1} points; otherwise it does nothing \
             measurable.\n\n## Per-class IoU (mean over seeds)\n\n| fraction | row |",
            100.0 * MIN_EFFECT
        );
        for c in self.classes.iter().skip(1) {
            s += &format!(" {c} |");
        }
        s += "\n|---|---|";
        s += &"---|".repeat(self.classes.len().saturating_sub(1));
        s += "\n";
        for f in &self.fractions {
            for r in &f.rows {
                s += &format!("| {}% | {} |", pct(f.fraction), r.row);
                for v in r.iou.iter().skip(1) {
                    s += &format!(" {v:.2} |");
                }
                s += "\n";
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_verdict_needs_every_seed_to_agree_and_half_a_point() {
        assert_eq!(verdict(&[0.50, 0.52], &[0.49, 0.50]).word, "helps");
        assert_eq!(verdict(&[0.48, 0.47], &[0.49, 0.50]).word, "hurts");
        // one seed disagrees
        assert_eq!(
            verdict(&[0.52, 0.49], &[0.49, 0.50]).word,
            "does nothing measurable"
        );
        // every seed agrees, but by less than half a point
        assert_eq!(
            verdict(&[0.502, 0.503], &[0.50, 0.50]).word,
            "does nothing measurable"
        );
        let v = verdict(&[0.6, 0.7], &[0.5, 0.5]);
        assert!((v.mean - 0.15).abs() < 1e-12);
        assert_eq!(v.differences.len(), 2);
    }

    #[test]
    fn stats_are_mean_and_sample_std_over_seeds() {
        let run = |seed, miou| RunResult {
            name: format!("seed-{seed}/x"),
            row: "r".into(),
            fraction: Some(0.1),
            seed,
            labelled_frames: 6,
            pseudo_frames: 594,
            miou,
            miou_present: miou,
            accuracy: 0.9,
            iou: vec![0.0, miou],
            present: vec![1],
            train_seconds: 10.0,
            wall_seconds: 12.0,
        };
        let (a, b) = (run(0, 0.4), run(1, 0.6));
        let s = RowStats::of("r", &[&a, &b]).unwrap();
        assert!((s.miou - 0.5).abs() < 1e-12);
        // sample std of {0.4, 0.6}: 0.1 * sqrt(2)
        assert!((s.miou_std - 0.1 * 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(s.miou_per_seed, vec![0.4, 0.6]);
        assert!(RowStats::of("r", &[]).is_none());
    }
}
