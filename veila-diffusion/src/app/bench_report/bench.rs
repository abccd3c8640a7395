//! What every part of the benchmark shares ([`Bench`]): the bundled model, the held-out test
//! frames, their folds and judges; and how a bundle's scans of them are made and scored.

use std::ops::Range;
use std::path::PathBuf;
use std::time::Instant;

use candle_core::Device;
use veila_geom::RangeImage;
use veila_nn::feature_nets::FeatureNets;

use super::options::BenchReportOptions;
use crate::SamplerConfig;
use crate::app::bundle::{Bundle, BundleConfig, Variant};
use crate::app::generate::GenerateOptions;
use crate::app::progress::Progress;
use crate::app::scoring::{Judges, SetMetrics, set_metrics};
use crate::app::sim_examples::{
    RenderStyle, SimExample, render_split_shown, test_list_for, train_split_of,
};
use crate::error::{Error, Result, invalid};

/// The benchmark's fixed side.
pub(super) struct Bench<'p> {
    pub(super) opts: BenchReportOptions,
    pub(super) device: Device,
    pub(super) base: Bundle,
    /// The bundle's own training list: the baselines' and every fine-tuned variant's frames.
    pub(super) train_list: PathBuf,
    pub(super) test_list: PathBuf,
    /// The bundle's config with as many views as the most-viewed variant takes.
    pub(super) rig_config: BundleConfig,
    pub(super) tests: Vec<SimExample>,
    pub(super) nets: Option<FeatureNets>,
    /// Contiguous folds of the test frames: the test list interleaves its scene files, so every
    /// fold holds all of them.
    folds: Vec<Range<usize>>,
    pub(super) fold_judges: Vec<Judges>,
    pub(super) progress: &'p dyn Progress,
}

impl std::fmt::Debug for Bench<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bench")
            .field("model", &self.opts.model)
            .field("tests", &self.tests.len())
            .field("folds", &self.folds)
            .finish_non_exhaustive()
    }
}

/// The bundle's config with as many views as the most-viewed variant takes (three-cameras: 3):
/// the frames carry that many cameras, and every other model reads the first.
fn rig_config(opts: &BenchReportOptions, base: &Bundle) -> BundleConfig {
    let rig_views = if opts.shipped_only {
        1
    } else {
        opts.variants
            .clone()
            .unwrap_or_else(|| Variant::ALL.to_vec())
            .iter()
            .map(|v| v.views())
            .max()
            .unwrap_or(1)
    };
    let mut rig_config = base.config.clone();
    if let Some(c) = rig_config.denoiser.conditioning.as_mut() {
        c.num_views = c.num_views.max(rig_views);
    }
    rig_config
}

impl<'p> Bench<'p> {
    /// Loads the bundle and the feature networks, simulates the test frames and splits them into
    /// folds.
    pub(super) fn prepare(opts: BenchReportOptions, progress: &'p dyn Progress) -> Result<Self> {
        let device = Device::Cpu;
        let base = Bundle::from_dir(&opts.model, &device)?;
        let train_list = train_split_of(&base.config);
        let test_list = opts
            .test_scenes
            .clone()
            .unwrap_or_else(|| test_list_for(&opts.root, &train_list));
        let rig_config = rig_config(&opts, &base);
        let tests = render_split_shown(
            &opts.root,
            &test_list,
            opts.test_frames,
            &rig_config,
            &RenderStyle::default(),
            "simulating test frames",
            progress,
        )?;
        let nets = match FeatureNets::from_dir(&opts.root.join("models/feature-nets"), &device) {
            Ok(n) => Some(n),
            Err(e) => {
                progress.line(&format!("FRD / FPD / CM-SC skipped: {e}"));
                None
            }
        };
        if opts.folds == 0 || tests.len() < 2 * opts.folds {
            return Err(invalid(
                "folds",
                format!(
                    "{} test frames cannot make {} folds of at least 2 frames",
                    tests.len(),
                    opts.folds
                ),
            ));
        }
        let folds: Vec<Range<usize>> = (0..opts.folds)
            .map(|f| f * tests.len() / opts.folds..(f + 1) * tests.len() / opts.folds)
            .collect();
        let fold_judges = folds
            .iter()
            .map(|r| Judges::new(&base, &tests[r.clone()], nets.as_ref(), &device))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            opts,
            device,
            base,
            train_list,
            test_list,
            rig_config,
            tests,
            nets,
            folds,
            fold_judges,
            progress,
        })
    }

    /// Test frames per fold (the first fold's; the others differ by at most one).
    pub(super) fn fold_size(&self) -> usize {
        self.folds[0].len()
    }

    /// The metrics of `generated` (one scan per test frame), fold by fold.
    pub(super) fn per_fold(
        &self,
        bundle: &Bundle,
        generated: &[RangeImage],
    ) -> Result<Vec<SetMetrics>> {
        self.folds
            .iter()
            .zip(&self.fold_judges)
            .map(|(r, j)| {
                let (g, t) = (&generated[r.clone()], &self.tests[r.clone()]);
                set_metrics(bundle, g, t, j, self.nets.as_ref())
            })
            .collect()
    }

    /// One scan of each of `tests` by `bundle` with `sampler` and `seed`, shown as a bar named
    /// `label`; with the seconds spent.
    pub(super) fn generate_all(
        &self,
        bundle: &Bundle,
        tests: &[SimExample],
        sampler: &SamplerConfig,
        (unconditional, residual_weight): (bool, f64),
        seed: u64,
        label: &str,
    ) -> Result<(Vec<RangeImage>, f64)> {
        let bar = self.progress.bar(label, tests.len() as u64);
        let t = Instant::now();
        let mut out = Vec::with_capacity(tests.len());
        for (i, ex) in tests.iter().enumerate() {
            let opts = GenerateOptions {
                sampler: sampler.clone(),
                samples: 1,
                seed: seed.wrapping_mul(1_000_003).wrapping_add(i as u64),
                unconditional,
                residual_weight,
            };
            let views = ex.views(bundle.config.num_views());
            let scan = bundle
                .generate(&views, &opts, |_, _| {})?
                .into_iter()
                .next();
            out.push(scan.ok_or_else(|| Error::Data("generation gave no scan".into()))?);
            bar.inc();
        }
        Ok((out, t.elapsed().as_secs_f64()))
    }

    /// `bundle`'s scans of every test frame for `seeds` seeds, scored fold by fold; with the
    /// seconds per scan.
    pub(super) fn score_seeds(
        &self,
        bundle: &Bundle,
        sampler: &SamplerConfig,
        switches: (bool, f64),
        seeds: u64,
        name: &str,
    ) -> Result<(Vec<SetMetrics>, f64)> {
        let mut per_set = Vec::new();
        let mut secs = 0.0;
        for seed in 0..seeds {
            let label = format!("{name} seed {seed}");
            let (generated, s) =
                self.generate_all(bundle, &self.tests, sampler, switches, seed, &label)?;
            secs += s;
            per_set.extend(self.per_fold(bundle, &generated)?);
        }
        Ok((per_set, secs / (seeds as f64 * self.tests.len() as f64)))
    }
}
