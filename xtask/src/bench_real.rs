//! `cargo xtask bench-real`: a bundle on the real frames the tests can reach
//! (`../shared/data/real`) against their real scans, next to two image-free baselines; also the
//! real-frame section of `cargo xtask bench-report`. The frames, the scoring and the section's
//! Markdown are `veila_diffusion::app::real_frames`; this module simulates the mean-scan
//! baselines and writes the report.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use veila_diffusion::app::Bundle;
use veila_diffusion::app::BundleConfig;
use veila_diffusion::app::real_frames::{RealOptions, evaluate, real_root};
use veila_diffusion::app::sim_examples::{DEFAULT_SCENES, RenderStyle, train_split_of};
use veila_diffusion::{SamplerConfig, SamplerName, Spacing};
use veila_geom::RangeImage;

use crate::progress::{render_split, workspace_root};

/// The mean scan of the street list (`scenes/train.txt`, `frames` frames) and its row label, when
/// the bundle trained on another list; `None` when it trained on that one.
pub fn reference_mean_scan(
    cfg: &BundleConfig,
    frames: usize,
) -> Result<Option<(String, RangeImage)>> {
    let streets = PathBuf::from(DEFAULT_SCENES);
    if train_split_of(cfg) == streets {
        return Ok(None);
    }
    let train = render_split(
        &streets,
        frames,
        cfg,
        &RenderStyle::default(),
        "simulating the street list's baseline frames",
    )?;
    let refs: Vec<&RangeImage> = train.iter().map(|e| &e.range).collect();
    Ok(Some((
        format!("mean-scan ({})", streets.display()),
        veila_metrics::baseline::median_scan(&refs)?,
    )))
}

/// Arguments of `cargo xtask bench-real`.
#[derive(Debug, clap::Args)]
pub struct BenchRealArgs {
    /// Model bundle.
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    /// Output folder (report.md, report.json, real/*.png).
    #[arg(long, default_value = "target/bench-real")]
    out: PathBuf,
    /// Samples per frame.
    #[arg(long, default_value_t = 4)]
    seeds: usize,
    /// Sampler: ddpm, ddim or dpm.
    #[arg(long, default_value = "ddpm", value_parser = sampler_parser())]
    sampler: SamplerName,
    /// Sampler steps.
    #[arg(long, default_value_t = 4)]
    steps: usize,
    /// Simulated training frames behind the mean-scan baseline.
    #[arg(long, default_value_t = 96)]
    baseline_frames: usize,
}

/// `cargo xtask bench-real`.
pub fn run(args: BenchRealArgs) -> Result<()> {
    let t = std::time::Instant::now();
    let root = workspace_root();
    let abs = |p: &Path| crate::progress::in_workspace(p);
    let (model_dir, out) = (abs(&args.model), abs(&args.out));
    let bundle = Bundle::from_dir(&model_dir, &candle_core::Device::Cpu)
        .with_context(|| format!("loading {}", model_dir.display()))?;
    let train = render_split(
        &train_split_of(&bundle.config),
        args.baseline_frames,
        &bundle.config,
        &RenderStyle::default(),
        "simulating baseline train frames",
    )?;
    let refs: Vec<&RangeImage> = train.iter().map(|e| &e.range).collect();
    let median = veila_metrics::baseline::median_scan(&refs)?;
    let streets = reference_mean_scan(&bundle.config, args.baseline_frames)?;
    let sampler = sampler_for(
        args.sampler,
        args.steps,
        bundle.config.sampler.guidance_scale,
    );
    let report = evaluate(
        &bundle,
        &RealOptions {
            root: &real_root(&root),
            sampler: &sampler,
            sampler_label: format!("{} {} steps", sampler.kind.title(), args.steps),
            seeds: args.seeds,
            mean_scan: &median,
            reference_mean_scan: streets.as_ref(),
        },
        &out,
    )?;
    for m in &report.missing {
        println!("  real frames: skipped {m}");
    }
    let md = format!(
        "# Real frames: {}\n\n{}",
        args.model.display(),
        report.markdown()
    );
    veila_data::atomic::write_atomic(&out.join("report.md"), md.as_bytes())?;
    veila_data::atomic::write_atomic(
        &out.join("report.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    print!("{}", report.markdown());
    println!(
        "wrote {} in {:.0} s",
        out.display(),
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The sampler a benchmark's `--sampler` names ([`SamplerName::config`]), with `steps` steps and
/// the guidance scale `guidance`.
pub fn sampler_for(name: SamplerName, steps: usize, guidance: f64) -> SamplerConfig {
    let mut s = name.config(steps);
    s.guidance_scale = guidance;
    s
}

/// A benchmark's `--sampler` parser: the choices are the library's list, [`SamplerName::ALL`].
pub fn sampler_parser() -> impl clap::builder::TypedValueParser<Value = SamplerName> {
    use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
    PossibleValuesParser::new(
        SamplerName::ALL.map(|n| PossibleValue::new(n.as_str()).help(n.help())),
    )
    .try_map(|name| name.parse::<SamplerName>())
}

/// A benchmark's `--spacing` parser: the choices are the library's list, [`Spacing::ALL`].
pub fn spacing_parser() -> impl clap::builder::TypedValueParser<Value = Spacing> {
    use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
    PossibleValuesParser::new(Spacing::ALL.map(|s| PossibleValue::new(s.as_str()).help(s.help())))
        .try_map(|name| name.parse::<Spacing>())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every benchmark's `--sampler` and `--spacing` offer exactly the library's lists, in order.
    #[test]
    fn every_benchmark_sampler_option_offers_the_librarys_samplers() {
        use clap::CommandFactory;
        let samplers: Vec<String> = SamplerName::ALL.iter().map(|n| n.to_string()).collect();
        let spacings: Vec<String> = Spacing::ALL.iter().map(|s| s.to_string()).collect();
        for (flag, library, at_least) in [("sampler", samplers, 3), ("spacing", spacings, 1)] {
            let mut doors = 0;
            for sub in crate::Cli::command().get_subcommands() {
                for arg in sub.get_arguments().filter(|a| a.get_long() == Some(flag)) {
                    let offered: Vec<String> = arg
                        .get_possible_values()
                        .iter()
                        .map(|v| v.get_name().to_string())
                        .collect();
                    assert_eq!(offered, library, "`xtask {} --{flag}`", sub.get_name());
                    doors += 1;
                }
            }
            assert!(doors >= at_least, "--{flag}: {doors} benchmarks take it");
        }
    }

    #[test]
    fn the_street_mean_scan_joins_only_for_a_bundle_trained_on_another_list() {
        use veila_diffusion::app::bundle::Variant;
        let mut cfg = BundleConfig::cpu_default(Variant::Full);
        cfg.provenance = serde_json::json!({ "train_split": "scenes/train.txt" });
        assert!(reference_mean_scan(&cfg, 3).unwrap().is_none());
        // a bundle without a recorded list was trained on the street list
        cfg.provenance = serde_json::Value::Null;
        assert!(reference_mean_scan(&cfg, 3).unwrap().is_none());
        cfg.provenance = serde_json::json!({ "train_split": "scenes/train-v5.txt" });
        let (label, scan) = reference_mean_scan(&cfg, 4).unwrap().unwrap();
        assert_eq!(label, "mean-scan (scenes/train.txt)");
        // the per-pixel median of the street list's first frames, not of the bundle's own list (whose
        // fourth frame is a T junction)
        let median = |list: &str| {
            let frames =
                render_split(Path::new(list), 4, &cfg, &RenderStyle::default(), "").unwrap();
            let refs: Vec<&RangeImage> = frames.iter().map(|e| &e.range).collect();
            veila_metrics::baseline::median_scan(&refs).unwrap()
        };
        assert_eq!(scan.range_m, median("scenes/train.txt").range_m);
        assert_ne!(scan.range_m, median("scenes/train-v5.txt").range_m);
    }
}
