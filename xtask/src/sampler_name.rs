//! Samplers by their command-line name (`ddpm`, `ddim`, `dpm`), shared by the benchmark commands.

use anyhow::{Result, bail};
use veila_diffusion::SamplerConfig;

/// How the report names a sampler.
pub fn sampler_label(name: &str) -> &'static str {
    match name {
        "ddpm" => "DDPM",
        "ddim" => "DDIM (η = 0)",
        _ => "DPM-Solver++(2M)",
    }
}

pub fn sampler_for(name: &str, steps: usize, guidance: f64) -> Result<SamplerConfig> {
    let mut s = match name {
        "ddpm" => SamplerConfig::ddpm(steps),
        "ddim" => SamplerConfig::ddim(steps, 0.0),
        "dpm" => SamplerConfig::dpm_solver_pp_2m(steps),
        other => bail!("unknown sampler {other}"),
    };
    s.guidance_scale = guidance;
    Ok(s)
}
