//! The model rows: the bundled model as shipped, and every ablation variant trained under the
//! benchmark's protocol (kept in the work folder between runs) and scored.

use std::path::{Path, PathBuf};

use super::bench::Bench;
use super::options::Protocol;
use super::report::VariantResult;
use crate::app::bundle::{Bundle, BundleConfig, Variant};
use crate::app::sim_examples::{RenderStyle, SimExample, TrainImages, render_split_shown};
use crate::app::sim_recipe::{SimRecipe, SimRun};
use crate::error::Result;

impl Bench<'_> {
    /// A model row of `per_set` (from [`Bench::score_seeds`]) of the bundle in `dir`.
    fn model_row(
        &self,
        (name, label, dir): (&str, &str, &Path),
        per_set: &[crate::app::scoring::SetMetrics],
        seconds_per_scan: f64,
        train_steps: u64,
    ) -> VariantResult {
        self.progress
            .line(&format!("  {label}: {seconds_per_scan:.2} s/scan"));
        let dir = dir.display().to_string();
        VariantResult {
            train_steps,
            seconds_per_scan,
            ..VariantResult::new("model", name, label, &dir, per_set, self.fold_size())
        }
    }

    /// The bundled model as shipped: its own sampler settings, no further training (and a
    /// residual bundle's mean network alone).
    pub(super) fn shipped(&self) -> Result<Vec<VariantResult>> {
        let (opts, base) = (&self.opts, &self.base);
        let sampler = opts
            .sampler
            .guided(opts.steps, base.config.sampler.guidance_scale);
        let mut shipped: Vec<(&str, String, f64, u64)> = vec![(
            "shipped",
            format!(
                "Veila, the bundled model as shipped ({} {} steps)",
                opts.steps,
                sampler.kind.title()
            ),
            1.0,
            opts.seeds,
        )];
        if base.config.residual.is_some() {
            // deterministic: one seed
            shipped.push((
                "shipped-mean-net",
                "its mean network alone (residual weight 0: the smooth conditional mean)".into(),
                0.0,
                1,
            ));
        }
        let mut rows = Vec::new();
        for (name, label, weight, seeds) in shipped {
            let (per_set, per_scan) =
                self.score_seeds(base, &sampler, (false, weight), seeds, name)?;
            let row = (name, label.as_str(), opts.model.as_path());
            rows.push(self.model_row(row, &per_set, per_scan, 0));
        }
        Ok(rows)
    }

    /// Every variant trained (unless its bundle is in the work folder already) and scored.
    pub(super) fn variants(&self) -> Result<Vec<VariantResult>> {
        let opts = &self.opts;
        let variants = opts.variant_list(self.base.is_conditional());
        let needs_training = variants
            .iter()
            .any(|v| !(opts.protocol == Protocol::Finetune && *v == Variant::Unconditional));
        // the variants train on images drawn as the bundle's own were (its provenance)
        let train_style = TrainImages::style_of_bundle(&self.base.config);
        let train_frames = if needs_training {
            render_split_shown(
                &opts.root,
                &self.train_list,
                opts.train_frames,
                &self.rig_config,
                &train_style,
                "simulating train frames",
                self.progress,
            )?
        } else {
            Vec::new()
        };
        variants
            .into_iter()
            .map(|v| self.variant(v, &train_style, &train_frames))
            .collect()
    }

    /// One variant: its bundle (trained from `train_frames` when not there yet), scored.
    fn variant(
        &self,
        v: Variant,
        train_style: &RenderStyle,
        train_frames: &[SimExample],
    ) -> Result<VariantResult> {
        let opts = &self.opts;
        // under fine-tuning the unconditional baseline is the bundled network's own unconditional
        // branch (trained by condition dropout): no extra training
        let drop_condition = opts.protocol == Protocol::Finetune && v == Variant::Unconditional;
        let dir = if drop_condition {
            opts.model.clone()
        } else {
            opts.work.join(format!(
                "{}-{}-{}steps",
                v.name(),
                opts.protocol.tag(),
                opts.train_steps
            ))
        };
        if !drop_condition && Bundle::from_dir(&dir, &self.device).is_err() {
            self.train_variant(v, &dir, train_style, train_frames)?;
        }
        let bundle = Bundle::from_dir(&dir, &self.device)?;
        let guidance = if bundle.is_conditional() && !drop_condition {
            self.base.config.sampler.guidance_scale
        } else {
            1.0
        };
        let sampler = opts.sampler.guided(opts.steps, guidance);
        let (per_set, per_scan) = self.score_seeds(
            &bundle,
            &sampler,
            (drop_condition, 1.0),
            opts.seeds,
            v.name(),
        )?;
        let row = (v.name(), v.label(), dir.as_path());
        Ok(self.model_row(row, &per_set, per_scan, opts.train_steps))
    }

    /// Trains variant `v` into `dir` with the benchmark's budget, from the bundled model's
    /// encoders (and weights, under fine-tuning).
    fn train_variant(
        &self,
        v: Variant,
        dir: &Path,
        train_style: &RenderStyle,
        train_frames: &[SimExample],
    ) -> Result<()> {
        let opts = &self.opts;
        let tag = opts.protocol.tag();
        let model_dir = &opts.model;
        let base = &self.base.config;
        self.progress.line(&format!(
            "training variant {} ({} steps, {tag})",
            v.name(),
            opts.train_steps
        ));
        let recipe = SimRecipe {
            variant: v,
            method: base.method(),
            frames: opts.train_frames,
            scenes: self.train_list.clone(),
            encoder_steps: 0,
            steps: opts.train_steps,
            batch: 2,
            lr: match opts.protocol {
                Protocol::Finetune => 2e-4,
                Protocol::Scratch => 1e-3,
            },
            checkpoint_every: 250,
            encoders_from: Some(model_dir.clone()),
            init_from: (opts.protocol == Protocol::Finetune).then(|| model_dir.clone()),
            images: TrainImages::of_bundle(base),
            randomize_share: train_style.share,
            wide_facades: (train_style.wide_facade_share > 0.0)
                .then_some(train_style.wide_facade_share),
            // with the bundle's depth features wherever a variant has the depth encoder
            depth_features: base.depth_features()
                && BundleConfig::cpu_default(v).depth_encoder.is_some(),
            // seed 0, min-SNR weighting, the recipe's EMA decay and network sizes
            ..SimRecipe::shipped()
        };
        let work: PathBuf = opts
            .work
            .join(format!("ckpt-{}-{tag}-{}", v.name(), opts.train_steps));
        let run = SimRun {
            root: &opts.root,
            out: dir,
            work: &work,
            device: &self.device,
            device_name: "cpu",
            snapshot_every: None,
            frames: Some(train_frames),
        };
        recipe.train(&run, self.progress)?;
        Ok(())
    }
}
