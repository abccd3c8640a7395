//! The rows without a model: the zero-skill baselines (the median training scan, retrieval for a
//! conditional bundle) and the data floor; and the real frames' section, which reuses the median
//! scan as its image-free baseline.

use veila_geom::RangeImage;

use super::bench::Bench;
use super::report::VariantResult;
use crate::app::real_frames::{RealOptions, RealReport, evaluate, real_root, reference_mean_scan};
use crate::app::scoring::data_floor;
use crate::app::sim_examples::{RenderStyle, render_split_shown, retrieval_baseline};
use crate::error::Result;

/// The baselines' and the floor's rows, with what the real-frame section reuses.
#[derive(Debug)]
pub(super) struct Baselines {
    pub(super) rows: Vec<VariantResult>,
    /// Frames the baselines were drawn from.
    pub(super) train_frames: usize,
    /// The per-pixel median of those frames' scans.
    median: RangeImage,
}

impl Bench<'_> {
    /// The zero-skill baselines and the data floor.
    pub(super) fn baselines(&self) -> Result<Baselines> {
        let base = &self.base;
        let fold_size = self.fold_size();
        let baseline_train = render_split_shown(
            &self.opts.root,
            &self.train_list,
            self.opts.baseline_frames,
            &base.config,
            &RenderStyle::default(),
            "simulating baseline train frames",
            self.progress,
        )?;
        let refs: Vec<&RangeImage> = baseline_train.iter().map(|e| &e.range).collect();
        let median = veila_metrics::baseline::median_scan(&refs)?;
        let mut rows = vec![VariantResult::new(
            "baseline",
            "mean-scan",
            &format!(
                "mean training scan (per-pixel median of {} train frames)",
                baseline_train.len()
            ),
            "-",
            &self.per_fold(base, &vec![median.clone(); self.tests.len()])?,
            fold_size,
        )];
        if base.is_conditional() {
            let retrieved = retrieval_baseline(base, &baseline_train, &self.tests)?;
            rows.push(VariantResult::new(
                "baseline",
                "retrieval",
                "retrieval (train scan with the nearest image in the frozen encoders' features)",
                "-",
                &self.per_fold(base, &retrieved)?,
                fold_size,
            ));
        }
        rows.push(VariantResult::new(
            "floor",
            "data-floor",
            "data floor (true scans of one fold vs another)",
            "-",
            &data_floor(&self.fold_judges, self.nets.as_ref()),
            fold_size,
        ));
        Ok(Baselines {
            rows,
            train_frames: baseline_train.len(),
            median,
        })
    }

    /// The bundle on the real frames (issue 18), their images written under `out/real/`; `None`
    /// with `no_real`.
    pub(super) fn real_frames(&self, baselines: &Baselines) -> Result<Option<RealReport>> {
        let (opts, base) = (&self.opts, &self.base);
        if opts.no_real {
            return Ok(None);
        }
        let sampler = opts
            .sampler
            .guided(opts.steps, base.config.sampler.guidance_scale);
        let street_scan = reference_mean_scan(
            &opts.root,
            &base.config,
            baselines.train_frames,
            self.progress,
        )?;
        Ok(Some(evaluate(
            base,
            &RealOptions {
                root: &real_root(&opts.root),
                sampler: &sampler,
                sampler_label: format!("{} {} steps", sampler.kind.title(), opts.steps),
                seeds: opts.real_seeds,
                mean_scan: &baselines.median,
                reference_mean_scan: street_scan.as_ref(),
            },
            &opts.out,
        )?))
    }
}
