//! `cargo xtask bench-real`: a bundle on the real frames the tests can reach
//! (`../shared/data/real`) against their real scans, next to two image-free baselines; also the
//! real-frame section of `cargo xtask bench-report`. The frames, the scoring and the section's
//! Markdown, and the mean-scan baselines, are `veila_diffusion::app::real_frames`; this module
//! writes the report. Also the benchmarks' parsers of the libraries' lists (`--sampler`,
//! `--spacing`, `--protocol`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use veila_diffusion::app::Bundle;
use veila_diffusion::app::bench_report::Protocol;
use veila_diffusion::app::real_frames::{
    RealOptions, evaluate, mean_scan_of, real_root, reference_mean_scan,
};
use veila_diffusion::app::report_files::write_report_files;
use veila_diffusion::app::sim_examples::train_split_of;
use veila_diffusion::{SamplerName, Spacing};

use crate::progress::{Terminal, workspace_root};

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
    let cfg = &bundle.config;
    let progress = Terminal::default();
    let label = "simulating baseline train frames";
    let list = train_split_of(cfg);
    let median = mean_scan_of(&root, &list, args.baseline_frames, cfg, label, &progress)?;
    let streets = reference_mean_scan(&root, cfg, args.baseline_frames, &progress)?;
    let sampler = args.sampler.guided(args.steps, cfg.sampler.guidance_scale);
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
    write_report_files(&out, &report, &md)?;
    print!("{}", report.markdown());
    println!(
        "wrote {} in {:.0} s",
        out.display(),
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// A benchmark's parser of a flag whose choices are a library's list (`ALL`), by name with help.
fn list_parser<T>(
    all: impl IntoIterator<Item = (&'static str, &'static str)>,
) -> impl clap::builder::TypedValueParser<Value = T>
where
    T: std::str::FromStr + Clone + Send + Sync + 'static,
    T::Err: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
    PossibleValuesParser::new(all.into_iter().map(|(n, h)| PossibleValue::new(n).help(h)))
        .try_map(|name| name.parse::<T>())
}

/// A benchmark's `--sampler` parser: the choices are the library's list, [`SamplerName::ALL`].
pub fn sampler_parser() -> impl clap::builder::TypedValueParser<Value = SamplerName> {
    list_parser(SamplerName::ALL.map(|n| (n.as_str(), n.help())))
}

/// A benchmark's `--spacing` parser: the choices are the library's list, [`Spacing::ALL`].
pub fn spacing_parser() -> impl clap::builder::TypedValueParser<Value = Spacing> {
    list_parser(Spacing::ALL.map(|s| (s.as_str(), s.help())))
}

/// `bench-report --protocol`: the choices are the library's list, [`Protocol::ALL`].
pub fn protocol_parser() -> impl clap::builder::TypedValueParser<Value = Protocol> {
    list_parser(Protocol::ALL.map(|p| (p.as_str(), p.help())))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every benchmark's `--sampler`, `--spacing` and `--protocol` offer exactly the library's
    /// lists, in order.
    #[test]
    fn every_benchmark_sampler_option_offers_the_librarys_samplers() {
        use clap::CommandFactory;
        let samplers: Vec<String> = SamplerName::ALL.iter().map(|n| n.to_string()).collect();
        let spacings: Vec<String> = Spacing::ALL.iter().map(|s| s.to_string()).collect();
        let protocols: Vec<String> = Protocol::ALL.iter().map(|p| p.to_string()).collect();
        for (flag, library, at_least) in [
            ("sampler", samplers, 3),
            ("spacing", spacings, 1),
            ("protocol", protocols, 1),
        ] {
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
}
