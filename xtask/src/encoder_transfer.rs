//! `cargo xtask encoder-transfer`: which training recipe of the depth encoder carries over from
//! simulated to real images (issue 18's ablation at the level where the images enter the model).
//!
//! The frozen image encoders are the only part of Veila that sees pixels; the denoiser sees their
//! features and the rig's geometry. So the sim-to-real gap is first a gap of the encoders, and
//! it can be measured without training a whole model: train the depth encoder on simulated
//! frames under each recipe, then score its depth head (AbsRel, MAE) on held-out simulated
//! frames (ground-truth depth per pixel) and on every real frame the tests can reach (the real
//! LiDAR points projected into the image). Every recipe trains from the same seed for the same
//! updates; each row says what its training cost.
//!
//! The `ground*` recipes give the encoder the flat-ground prior as a fourth input channel
//! (`veila_nn::encoders::ground`, the default `GroundPrior`: the LiDAR 1.73 m above the ground),
//! computed from each image's own camera: the simulated frames', the crop-zoomed camera under
//! augmentation, each real frame's calibration when scored. The plane's height is the model's
//! one assumption (nuScenes' LiDAR sits at 1.84 m; the prior then puts its ground 6 % too near).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::Device;
use clap::{Args, ValueEnum};
use glam::Vec3;
use serde::Serialize;
use veila_data::augment::{CropZoomRange, Photometric};
use veila_diffusion::app::bundle::{BundleConfig, Variant};
use veila_diffusion::app::rig::{load_view, prepare_views};
use veila_diffusion::app::{EncoderAugment, train_small_cnn};
use veila_geom::PinholeCamera;
use veila_nn::encoders::ground::GroundPrior;
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig};

use crate::bench_real::{DepthScore, predict_depth, real_frames, real_root};
use crate::simdata::{SimExample, render_split, workspace_root};

/// Arguments of `cargo xtask encoder-transfer`.
#[derive(Debug, Args)]
pub struct EncoderTransferArgs {
    /// Recipes to compare (comma-separated): plain, augment, photometric, crop, appearance, both,
    /// and with the flat-ground prior channel: ground, ground-augment, ground-appearance,
    /// ground-both.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "plain,augment,appearance,both"
    )]
    recipes: Vec<Recipe>,
    /// Simulated training frames.
    #[arg(long, default_value_t = 960)]
    frames: usize,
    /// Training updates of the depth encoder (batch 8).
    #[arg(long, default_value_t = 1500)]
    steps: usize,
    /// Held-out simulated frames for the sim score.
    #[arg(long, default_value_t = 48)]
    test_frames: usize,
    /// Seed of the training.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Training split list (scene files and seeds; `scenes/train-v2.txt` adds the open-road and
    /// suburban scenes with rig variation).
    #[arg(long, default_value = "scenes/train.txt")]
    train_list: PathBuf,
    /// Output folder (report.md, report.json).
    #[arg(long, default_value = "target/encoder-transfer")]
    out: PathBuf,
}

/// A training recipe of the encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Recipe {
    /// The simulator's images as they are (the shipped recipe).
    Plain,
    /// Plus image augmentation during training (crop-and-zoom and photometric).
    Augment,
    /// Plus the photometric half of the augmentation only.
    Photometric,
    /// Plus the crop-and-zoom half of the augmentation only.
    Crop,
    /// Training images rendered with appearance and sensor randomisation.
    Appearance,
    /// Both.
    Both,
    /// `plain` with the flat-ground prior as an input channel.
    Ground,
    /// `augment` with the flat-ground prior (computed from the crop-zoomed camera).
    GroundAugment,
    /// `appearance` with the flat-ground prior.
    GroundAppearance,
    /// `both` with the flat-ground prior.
    GroundBoth,
}

impl Recipe {
    fn randomized_appearance(self) -> bool {
        matches!(
            self,
            Recipe::Appearance | Recipe::Both | Recipe::GroundAppearance | Recipe::GroundBoth
        )
    }
    fn ground_prior(self) -> Option<GroundPrior> {
        matches!(
            self,
            Recipe::Ground | Recipe::GroundAugment | Recipe::GroundAppearance | Recipe::GroundBoth
        )
        .then(GroundPrior::default)
    }
    fn augment(self) -> Option<EncoderAugment> {
        let full = EncoderAugment::default();
        match self {
            Recipe::Augment | Recipe::Both | Recipe::GroundAugment | Recipe::GroundBoth => {
                Some(full)
            }
            Recipe::Photometric => Some(EncoderAugment {
                crop_zoom: CropZoomRange::identity(),
                ..full
            }),
            Recipe::Crop => Some(EncoderAugment {
                photometric: Photometric::identity(),
                ..full
            }),
            Recipe::Plain | Recipe::Appearance | Recipe::Ground | Recipe::GroundAppearance => None,
        }
    }
}

fn row(
    recipe: Option<Recipe>,
    train_seconds: f64,
    final_loss: f32,
    sim: DepthScore,
    real: Vec<(String, Option<DepthScore>)>,
) -> Row {
    let scored: Vec<f64> = real
        .iter()
        .filter_map(|(_, s)| s.map(|s| s.abs_rel))
        .collect();
    let real_mean_abs_rel = scored.iter().sum::<f64>() / scored.len().max(1) as f64;
    let r = Row {
        recipe,
        train_seconds,
        final_loss,
        sim,
        real,
        real_mean_abs_rel,
    };
    println!(
        "  {}: {:.0} s, final loss {:.4}, sim AbsRel {:.3}, real AbsRel {:.3} ({})",
        r.name(),
        r.train_seconds,
        r.final_loss,
        r.sim.abs_rel,
        r.real_mean_abs_rel,
        r.real
            .iter()
            .map(|(n, s)| format!(
                "{}: {}",
                n.split_whitespace().next().unwrap_or(n),
                s.map_or("-".into(), |s| format!("{:.3}", s.abs_rel))
            ))
            .collect::<Vec<_>>()
            .join(", ")
    );
    r
}

#[derive(Debug, Serialize)]
struct Row {
    /// `None`: the shipped bundle's encoder.
    recipe: Option<Recipe>,
    train_seconds: f64,
    final_loss: f32,
    sim: DepthScore,
    real: Vec<(String, Option<DepthScore>)>,
    real_mean_abs_rel: f64,
}

impl Row {
    fn name(&self) -> String {
        self.recipe
            .and_then(|r| r.to_possible_value())
            .map_or("shipped (models/default)".to_string(), |v| {
                v.get_name().to_string()
            })
    }
}

/// Depth-head AbsRel / MAE on simulated frames against their per-pixel ground truth.
fn sim_score(net: &SmallCnn, tests: &[SimExample], h: usize, w: usize) -> Result<DepthScore> {
    let (mut rel, mut abs, mut n, mut total) = (0.0f64, 0.0f64, 0usize, 0usize);
    for ex in tests {
        let pred = predict_depth(net, &ex.rgb, &ex.camera, h, w)?
            .context("the encoder has no depth head")?;
        for (p, t) in pred.iter().zip(&ex.depth_m) {
            if *t >= 1.0 && *t <= 80.0 {
                total += 1;
                rel += ((p - t).abs() / t) as f64;
                abs += (p - t).abs() as f64;
                n += 1;
            }
        }
    }
    if n == 0 {
        bail!("no simulated pixel with ground-truth depth");
    }
    Ok(DepthScore {
        abs_rel: rel / n as f64,
        mae_m: abs / n as f64,
        coverage: n as f64 / total.max(1) as f64,
    })
}

pub fn run(args: EncoderTransferArgs) -> Result<()> {
    let root = workspace_root();
    let cfg = BundleConfig::cpu_default(Variant::Full);
    let enc_cfg = cfg
        .depth_encoder
        .as_ref()
        .and_then(|e| e.small_cnn_config())
        .context("the default bundle's depth encoder is not a small CNN")?
        .clone();
    let (h, w) = (cfg.image_height, cfg.image_width);
    let tests = render_split(
        &root.join("scenes/test.txt"),
        args.test_frames,
        &cfg,
        "simulating test frames",
    )?;
    let (frames, missing) = real_frames(&real_root(&root))?;
    for m in &missing {
        println!("  skipped {m}");
    }
    // the real frames at the encoder's input size, with their points in the LiDAR frame
    let mut real = Vec::new();
    for f in &frames {
        let view = load_view(&f.image, &f.calib, f.camera.as_deref())?;
        let prepared = prepare_views(&cfg, std::slice::from_ref(&view))?;
        let (rgb, cam) = prepared.into_iter().next().context("no view")?;
        let pts: Vec<Vec3> = veila_data::scan::read_points(&f.scan)?.cloud.xyz;
        real.push((f.name.clone(), rgb, cam, pts));
    }
    let mut rows = Vec::new();
    let score_real = |net: &SmallCnn| -> Result<Vec<(String, Option<DepthScore>)>> {
        real.iter()
            .map(|(name, rgb, cam, pts)| {
                let pred =
                    predict_depth(net, rgb, cam, h, w)?.context("the encoder has no depth head")?;
                let pred: Vec<Option<f32>> = pred.into_iter().map(Some).collect();
                Ok((
                    name.clone(),
                    crate::bench_real::depth_score(&pred, cam, pts),
                ))
            })
            .collect()
    };
    let shipped_dir = root.join("models/default");
    match veila_diffusion::app::Bundle::from_dir(&shipped_dir, &Device::Cpu) {
        Ok(b) => {
            if let Some(net) = b.depth.as_ref().and_then(|d| d.as_small_cnn()) {
                let real = score_real(net)?;
                rows.push(row(
                    None,
                    f64::NAN,
                    f32::NAN,
                    sim_score(net, &tests, h, w)?,
                    real,
                ));
            }
        }
        Err(e) => println!("  shipped encoder skipped: {e}"),
    }
    let mut plain_frames: Option<Vec<SimExample>> = None;
    let mut random_frames: Option<Vec<SimExample>> = None;
    for recipe in args.recipes.iter().copied() {
        let slot = if recipe.randomized_appearance() {
            &mut random_frames
        } else {
            &mut plain_frames
        };
        if slot.is_none() {
            *slot = Some(crate::simdata::render_split_styled(
                &root.join(&args.train_list),
                args.frames,
                &cfg,
                &crate::simdata::RenderStyle::randomized(recipe.randomized_appearance()),
                "simulating train frames",
            )?);
        }
        let train = slot.as_ref().context("rendered above")?;
        let images: Vec<Vec<u8>> = train.iter().map(|e| e.rgb.clone()).collect();
        let depths: Vec<Vec<f32>> = train.iter().map(|e| e.depth_m.clone()).collect();
        let cameras: Vec<PinholeCamera> = train.iter().map(|e| e.camera).collect();
        let recipe_cfg = SmallCnnConfig {
            ground_prior: recipe.ground_prior(),
            ..enc_cfg.clone()
        };
        let bar = crate::progress::progress_bar(args.steps as u64, "depth encoder");
        let mut last = f32::NAN;
        let t = Instant::now();
        let augment = recipe.augment();
        let (net, _) = train_small_cnn(
            &recipe_cfg,
            &images,
            None,
            Some(&depths),
            Some(&cameras),
            (h, w),
            args.steps,
            8,
            2e-3,
            args.seed,
            augment.as_ref(),
            &Device::Cpu,
            |s| {
                bar.set_position(s.step as u64);
                last = s.loss;
            },
        )?;
        bar.finish_and_clear();
        let train_seconds = t.elapsed().as_secs_f64();
        let sim = sim_score(&net, &tests, h, w)?;
        rows.push(row(
            Some(recipe),
            train_seconds,
            last,
            sim,
            score_real(&net)?,
        ));
    }
    let out = if args.out.is_absolute() {
        args.out.clone()
    } else {
        root.join(&args.out)
    };
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let mut md = format!(
        "# Depth encoder: simulated to real\n\n`cargo xtask encoder-transfer` ({} simulated training frames of `{}`, {} updates of batch 8, seed {}; sim score on {} held-out simulated frames, real score on the real LiDAR points in each real image; AbsRel = mean |pred - true| / true, lower is better).\n\n| recipe | train s | sim AbsRel | real AbsRel (mean) |",
        args.frames,
        args.train_list.display(),
        args.steps,
        args.seed,
        tests.len()
    );
    for (name, ..) in &real {
        md.push_str(&format!(
            " {} |",
            name.split_whitespace().next().unwrap_or(name)
        ));
    }
    md.push_str("\n|---|---|---|---|");
    for _ in &real {
        md.push_str("---|");
    }
    md.push('\n');
    for r in &rows {
        md.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} |",
            r.name(),
            if r.train_seconds.is_finite() {
                format!("{:.0}", r.train_seconds)
            } else {
                "-".to_string()
            },
            r.sim.abs_rel,
            r.real_mean_abs_rel
        ));
        for (_, s) in &r.real {
            md.push_str(&format!(
                " {} |",
                s.map_or("-".into(), |s| format!("{:.3}", s.abs_rel))
            ));
        }
        md.push('\n');
    }
    veila_data::atomic::write_atomic(&out.join("report.md"), md.as_bytes())?;
    veila_data::atomic::write_atomic(
        &out.join("report.json"),
        serde_json::to_string_pretty(&rows)?.as_bytes(),
    )?;
    println!("{md}\nwrote {}", out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ground_recipes_add_the_prior_to_their_base_recipe_and_nothing_else() {
        let pairs = [
            (Recipe::Plain, Recipe::Ground),
            (Recipe::Augment, Recipe::GroundAugment),
            (Recipe::Appearance, Recipe::GroundAppearance),
            (Recipe::Both, Recipe::GroundBoth),
        ];
        for (base, ground) in pairs {
            assert_eq!(base.ground_prior(), None);
            assert_eq!(ground.ground_prior(), Some(GroundPrior::default()));
            assert_eq!(base.augment(), ground.augment());
            assert_eq!(base.randomized_appearance(), ground.randomized_appearance());
        }
        for r in [Recipe::Photometric, Recipe::Crop] {
            assert_eq!(r.ground_prior(), None);
        }
        let row = Row {
            recipe: Some(Recipe::GroundAugment),
            train_seconds: 1.0,
            final_loss: 0.0,
            sim: DepthScore {
                abs_rel: 0.1,
                mae_m: 1.0,
                coverage: 1.0,
            },
            real: Vec::new(),
            real_mean_abs_rel: 0.0,
        };
        assert_eq!(row.name(), "ground-augment");
    }
}
