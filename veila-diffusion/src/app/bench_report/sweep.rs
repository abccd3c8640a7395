//! What accuracy costs in time: the sampler sweep on the bundled model (every sampler at every
//! step count, then for a residual bundle the texture's price in pixel error).

use super::bench::Bench;
use super::report::SweepPoint;
use crate::SamplerName;
use crate::app::scoring::{Judges, SetMetrics, set_metrics};
use crate::error::Result;

/// The value of `metric` in `region` (NaN where the set has none).
fn value(m: &SetMetrics, metric: &str, region: &str) -> f64 {
    m.get(metric)
        .and_then(|r| r.get(region))
        .copied()
        .unwrap_or(f64::NAN)
}

impl Bench<'_> {
    /// The sweep's points, on the first `sweep_frames` test frames, at the variants' step count
    /// for the residual weights.
    pub(super) fn sweep(&self) -> Result<Vec<SweepPoint>> {
        let (opts, base) = (&self.opts, &self.base);
        let sweep_tests = &self.tests[..opts.sweep_frames.min(self.tests.len())];
        let sweep_judges = Judges::new(base, sweep_tests, self.nets.as_ref(), &self.device)?;
        // (sampler, steps, residual weight, label)
        let mut points: Vec<(SamplerName, usize, f64, String)> = Vec::new();
        for name in SamplerName::ALL {
            for &steps in &opts.sweep_steps {
                points.push((name, steps, 1.0, format!("{name:>4} x {steps:>3}")));
            }
        }
        if base.config.residual.is_some() {
            for &weight in &opts.sweep_residual_weights {
                let label = format!("residual weight {weight}");
                points.push((opts.sampler, opts.steps, weight, label));
            }
        }
        let mut sweep = Vec::new();
        for (name, steps, weight, label) in points {
            let sampler = name.guided(steps, base.config.sampler.guidance_scale);
            let (generated, secs) =
                self.generate_all(base, sweep_tests, &sampler, (false, weight), 0, &label)?;
            let m = set_metrics(
                base,
                &generated,
                sweep_tests,
                &sweep_judges,
                self.nets.as_ref(),
            )?;
            let p = SweepPoint {
                sampler: name.to_string(),
                steps: if weight == 0.0 { 0 } else { steps },
                residual_weight: weight,
                seconds_per_scan: secs / sweep_tests.len() as f64,
                jsd_all: value(&m, "jsd", "all"),
                range_mae_front_m: value(&m, "range mae (m)", "front"),
                scans: sweep_tests.len(),
            };
            self.progress.line(&format!(
                "  {label}: {:.2} s/scan, jsd {:.4}, range mae front {:.2} m",
                p.seconds_per_scan, p.jsd_all, p.range_mae_front_m
            ));
            sweep.push(p);
        }
        Ok(sweep)
    }
}
