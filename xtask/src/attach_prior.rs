//! `cargo xtask attach-prior`: a direct-diffusion bundle given another bundle's mean network as
//! the prior its sampler starts from (`veila_diffusion::app::attach_prior`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use crate::progress::workspace_root;

/// Arguments of `cargo xtask attach-prior`.
#[derive(Debug, Args)]
pub struct AttachPriorArgs {
    /// The direct-diffusion bundle (its encoders, denoiser, process and sampler are kept).
    #[arg(long, value_name = "DIR")]
    bundle: PathBuf,
    /// The bundle whose mean network becomes the prior (a residual bundle's, or another prior's);
    /// it must share the first bundle's encoder weights, image size, grid and encoding.
    #[arg(long, value_name = "DIR")]
    mean_from: PathBuf,
    /// The level draws start from by default, above 0 and at most 1 (`--start-t` of
    /// `veila generate` and `bench-realism` override it).
    #[arg(long, value_name = "T")]
    start_t: f64,
    /// The new bundle folder (neither input).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

/// Writes the new bundle and says what it holds.
pub fn run(args: AttachPriorArgs) -> Result<()> {
    let root = workspace_root();
    let at = |p: &PathBuf| root.join(p);
    let cfg = veila_diffusion::app::attach_prior(
        &at(&args.bundle),
        &at(&args.mean_from),
        args.start_t,
        &at(&args.out),
    )
    .with_context(|| format!("attaching the mean network of {}", args.mean_from.display()))?;
    println!(
        "wrote {}: the denoiser of {}, the mean network of {} as its prior, draws start at t = {}",
        args.out.display(),
        args.bundle.display(),
        args.mean_from.display(),
        cfg.sampler.start_t.unwrap_or(1.0)
    );
    Ok(())
}
