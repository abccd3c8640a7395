//! The realism benchmark (feature `sim`): a generator judged as a generator, on held-out simulated
//! frames split into folds of equal size. `cargo xtask bench-realism` drives it: a whole run is
//! [`run`] (`run.rs`, the rows of [`RealismOptions`]), its report [`RealismReport`] (`report.rs`).
//!
//! Every row (a baseline, the data floor, a model at one sampler setting) is scored per fold and
//! sample seed as a [`SetMetrics`] (metric → region → value), so rows share one table format:
//!
//! * **realism**: FRD, FPD, JSD, MMD in every region ([`super::scoring::set_metrics`]);
//! * **texture**: the distribution of relative range steps between neighbouring pixels along and
//!   across rows as a 1-Wasserstein distance (decades) to the fold's true scans, inside the
//!   camera's view (`view`) and outside it (`outside`); the share of depth edges (a step of more
//!   than 100 % of the nearer range) and of smooth pairs (below 0.03 %); the ray drop per row as
//!   a mean absolute difference of the per-row drop shares ([`veila_metrics::texture`]);
//! * **faithfulness**: range MAE in the camera's view, CM-DC, CM-SC;
//! * **memorisation**: each scan's distance to its nearest training scan
//!   ([`veila_metrics::texture::nearest_scan`]), averaged over the set;
//! * **diversity** ([`RealismBench::diversity`]): range MAE between two sample seeds of one frame,
//!   front and rear; the floor's counterpart is the range MAE between the true scans of the two
//!   test frames nearest each other in the judge's image features ("similar frames").
//!
//! The data floor ([`RealismBench::floor`]) scores the true scans of fold `f + 1` as if they had
//! been generated for fold `f`, on every distribution metric: what a perfect generator of this
//! many scans would score. Calibration rows ([`Degradation`], `calibrate.rs`) put those true
//! scans through a known degradation (range noise, a blur) and score them the same way: what a
//! realism figure means in pixels.

use veila_geom::{RangeImage, RayTable, Region};
use veila_metrics::texture::{
    Direction, RowBand, StepHistogram, nearest_scan, pairwise_range_mae, raydrop_per_row,
    raydrop_row_distance, step_histogram, texture_distance,
};
use veila_nn::feature_nets::FeatureNets;

use super::bundle::Bundle;
use super::generate::CameraView;
use super::scoring::{Judges, SetMetrics, data_floor, set_metrics};
use super::sim_examples::SimExample;
use crate::error::{Error, Result, invalid};
use candle_core::Device;

mod calibrate;
mod report;
mod run;

pub use calibrate::Degradation;
pub use report::{RealismReport, Row};
pub use run::{RealismOptions, run};

/// The texture regions: inside the camera's view and outside it.
pub const TEXTURE_REGIONS: [&str; 2] = ["view", "outside"];

/// One fold: its frames, judges, and the true scans' texture statistics.
#[derive(Debug)]
struct Fold {
    frames: Vec<SimExample>,
    /// The frames' true scans.
    scans: Vec<RangeImage>,
    /// Per texture region, per direction: the true scans' step histogram.
    true_steps: Vec<[StepHistogram; 2]>,
    true_raydrop: Vec<f64>,
}

/// The benchmark's fixed side: folds of test frames, their judges, the training scans that
/// memorisation is measured against, and the pixel masks of the regions.
#[derive(Debug)]
pub struct RealismBench {
    folds: Vec<Fold>,
    /// Per fold.
    judges: Vec<Judges>,
    train_scans: Vec<RangeImage>,
    nets: Option<FeatureNets>,
    /// Per pixel, in [`TEXTURE_REGIONS`] order: inside the camera's view (the first test
    /// frame's camera: the simulator's frames share one rig), and outside it.
    view: [Vec<bool>; 2],
    /// Per pixel: the ray points ahead (`x > 0`), and behind.
    front_rear: [Vec<bool>; 2],
}

/// A mask and its complement.
fn and_not(mask: Vec<bool>) -> [Vec<bool>; 2] {
    let other = mask.iter().map(|m| !m).collect();
    [mask, other]
}

impl RealismBench {
    /// Splits `tests` into `folds` contiguous folds of `tests.len() / folds` frames each (the
    /// remainder is left out so every fold, and the floor, has the same size), builds each fold's
    /// judges with `judge`'s encoder heads and the feature networks, and keeps `train` as the
    /// memorisation pool.
    pub fn new(
        judge: &Bundle,
        tests: Vec<SimExample>,
        folds: usize,
        train: &[SimExample],
        nets: Option<FeatureNets>,
        device: &Device,
    ) -> Result<Self> {
        let per_fold = tests.len() / folds.max(1);
        if folds < 2 || per_fold < 2 {
            return Err(invalid(
                "folds",
                format!(
                    "{} test frames cannot make {folds} folds of at least 2 frames (the floor needs two folds)",
                    tests.len()
                ),
            ));
        }
        let first = tests.first().ok_or_else(|| invalid("tests", "no frame"))?;
        let rays = RayTable::new(&judge.config.denoiser.sensor)?;
        let view = and_not(first.camera.frustum_mask(&rays));
        let front_rear = and_not(rays.dirs().iter().map(|d| d.x > 0.0).collect());
        let mut out = Vec::with_capacity(folds);
        let mut all_judges = Vec::with_capacity(folds);
        let mut rest = tests;
        for _ in 0..folds {
            let tail = rest.split_off(per_fold);
            let frames = std::mem::replace(&mut rest, tail);
            all_judges.push(Judges::new(judge, &frames, nets.as_ref(), device)?);
            let scans: Vec<RangeImage> = frames.iter().map(|f| f.range.clone()).collect();
            let true_steps = view
                .iter()
                .map(|m| steps_of(&scans, m))
                .collect::<Result<Vec<_>>>()?;
            let true_raydrop = raydrop_per_row(&scans, None)?;
            out.push(Fold {
                frames,
                scans,
                true_steps,
                true_raydrop,
            });
        }
        Ok(Self {
            folds: out,
            judges: all_judges,
            train_scans: train.iter().map(|e| e.range.clone()).collect(),
            nets,
            view,
            front_rear,
        })
    }

    /// The number of folds.
    pub fn num_folds(&self) -> usize {
        self.folds.len()
    }

    /// Frames per fold.
    pub fn fold_size(&self) -> usize {
        self.folds[0].frames.len()
    }

    /// The frames of fold `f`.
    pub fn frames(&self, f: usize) -> &[SimExample] {
        &self.folds[f].frames
    }

    /// Every test frame in fold order.
    pub fn all_frames(&self) -> impl Iterator<Item = &SimExample> {
        self.folds.iter().flat_map(|f| &f.frames)
    }

    fn fold(&self, f: usize) -> Result<&Fold> {
        self.folds
            .get(f)
            .ok_or_else(|| invalid("fold", format!("no fold {f} of {}", self.folds.len())))
    }

    /// Every metric of one set of scans generated for fold `f` (one per frame, in order), scored
    /// on `bundle`'s grid.
    pub fn score(&self, bundle: &Bundle, f: usize, generated: &[RangeImage]) -> Result<SetMetrics> {
        let fold = self.fold(f)?;
        let mut m = set_metrics(
            bundle,
            generated,
            &fold.frames,
            &self.judges[f],
            self.nets.as_ref(),
        )?;
        let mut sum = 0.0;
        let mut n = 0usize;
        for (g, ex) in generated.iter().zip(&fold.frames) {
            let (mae, _) = veila_metrics::view::masked_range_mae(&self.view[0], g, &ex.range)?;
            if mae.is_finite() {
                sum += mae;
                n += 1;
            }
        }
        m.entry("range mae (m)".into())
            .or_default()
            .insert("view".into(), if n > 0 { sum / n as f64 } else { f64::NAN });
        self.texture_into(&mut m, fold, generated)?;
        self.memorisation_into(&mut m, generated)?;
        Ok(m)
    }

    /// The texture metrics of `scans` against fold `fold`'s true scans.
    fn texture_into(&self, m: &mut SetMetrics, fold: &Fold, scans: &[RangeImage]) -> Result<()> {
        for ((name, mask), truth) in TEXTURE_REGIONS.iter().zip(&self.view).zip(&fold.true_steps) {
            let [along, across] = steps_of(scans, mask)?;
            let mut put = |metric: &str, v: f64| {
                m.entry(metric.into())
                    .or_default()
                    .insert((*name).into(), v);
            };
            put(
                "texture along rows (w1, decades)",
                texture_distance(&along, &truth[0]),
            );
            put(
                "texture across rows (w1, decades)",
                texture_distance(&across, &truth[1]),
            );
            put("depth edges (%)", 100.0 * along.edge_share());
            put("smooth pairs (%)", 100.0 * along.smooth_share());
        }
        let rows = raydrop_per_row(scans, None)?;
        m.entry("ray drop per row (abs diff)".into())
            .or_default()
            .insert(
                "all".into(),
                raydrop_row_distance(&rows, &fold.true_raydrop)?,
            );
        Ok(())
    }

    /// The mean distance of each scan to its nearest training scan.
    fn memorisation_into(&self, m: &mut SetMetrics, scans: &[RangeImage]) -> Result<()> {
        if self.train_scans.is_empty() {
            return Ok(());
        }
        let mut sum = 0.0;
        for s in scans {
            sum += nearest_scan(s, &self.train_scans)?.1;
        }
        m.entry("nearest train scan (log2 m)".into())
            .or_default()
            .insert("all".into(), sum / scans.len().max(1) as f64);
        Ok(())
    }

    /// The data floor, one set per fold: the true scans of fold `f + 1` scored against fold `f`
    /// on every distribution metric (JSD, MMD, FRD, FPD, texture, ray drop), and the true test
    /// scans' own distance to their nearest training scan.
    pub fn floor(&self) -> Result<Vec<SetMetrics>> {
        let mut sets = data_floor(&self.judges, self.nets.as_ref());
        let k = self.folds.len();
        for (f, m) in sets.iter_mut().enumerate() {
            self.texture_into(m, &self.folds[f], &self.folds[(f + 1) % k].scans)?;
            self.memorisation_into(m, &self.folds[f].scans)?;
        }
        Ok(sets)
    }

    /// Diversity of one fold's samples: the mean range MAE between two sample seeds' scans of
    /// each frame, front and rear (`a` and `b`: one scan per frame of fold `f`).
    pub fn diversity(&self, f: usize, a: &[RangeImage], b: &[RangeImage]) -> Result<SetMetrics> {
        let n = self.fold(f)?.frames.len();
        if a.len() != n || b.len() != n {
            return Err(Error::Shape {
                what: "diversity sets",
                expected: format!("{n} scans each"),
                got: format!("{} and {}", a.len(), b.len()),
            });
        }
        self.spread(a.iter().zip(b))
    }

    /// The diversity floor of fold `f`: the range MAE between the true scans of each frame and
    /// of the other frame of the fold whose image is nearest in `judge`'s image descriptor.
    pub fn diversity_floor(&self, judge: &Bundle, f: usize) -> Result<SetMetrics> {
        let fold = self.fold(f)?;
        let frames = &fold.frames;
        let keys = frames
            .iter()
            .map(|e| {
                judge.image_descriptor(CameraView {
                    rgb: &e.rgb,
                    camera: &e.camera,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let mut pairs = Vec::with_capacity(frames.len());
        for (i, k) in keys.iter().enumerate() {
            let others: Vec<Vec<f32>> = keys
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, o)| o.clone())
                .collect();
            let j = veila_metrics::baseline::nearest(k, &others)?;
            let j = if j >= i { j + 1 } else { j };
            pairs.push((&fold.scans[i], &fold.scans[j]));
        }
        self.spread(pairs.into_iter())
    }

    fn spread<'a>(
        &self,
        pairs: impl Iterator<Item = (&'a RangeImage, &'a RangeImage)>,
    ) -> Result<SetMetrics> {
        let [front, rear] = &self.front_rear;
        let (mut sf, mut sr, mut nf, mut nr) = (0.0, 0.0, 0usize, 0usize);
        for (a, b) in pairs {
            let f = pairwise_range_mae(a, b, Some(front))?;
            if f.is_finite() {
                sf += f;
                nf += 1;
            }
            let r = pairwise_range_mae(a, b, Some(rear))?;
            if r.is_finite() {
                sr += r;
                nr += 1;
            }
        }
        let mean = |s: f64, n: usize| if n > 0 { s / n as f64 } else { f64::NAN };
        let mut m = SetMetrics::new();
        let e = m.entry("diversity (range mae, m)".into()).or_default();
        e.insert(Region::Front.name().into(), mean(sf, nf));
        e.insert(Region::Rear.name().into(), mean(sr, nr));
        Ok(m)
    }
}

/// The along-row and across-row step histograms of `scans` over `mask`.
fn steps_of(scans: &[RangeImage], mask: &[bool]) -> Result<[StepHistogram; 2]> {
    Ok([
        step_histogram(scans, Some(mask), Direction::AlongRow, RowBand::All)?,
        step_histogram(scans, Some(mask), Direction::AcrossRows, RowBand::All)?,
    ])
}

/// How a model row samples.
#[derive(Debug, Clone, PartialEq)]
pub struct RowSpec {
    /// Sampler, steps and guidance.
    pub sampler: crate::SamplerConfig,
    /// Sample seeds per frame (at least 2 gives the diversity).
    pub seeds: usize,
    /// Residual bundles: the residual weight (1: full samples; 0: the mean network alone).
    pub residual_weight: f64,
}

/// A model row: one [`SetMetrics`] per fold and seed, the diversity per fold, and its time.
#[derive(Debug, Clone)]
pub struct RowResult {
    /// Fold-major: `sets[f * seeds + s]`.
    pub sets: Vec<SetMetrics>,
    /// Per fold, between seeds 0 and 1 (empty for one seed).
    pub diversity: Vec<SetMetrics>,
    /// Wall seconds of generation per scan.
    pub seconds_per_scan: f64,
    /// The scans of seed 0, every test frame in fold order (for pictures).
    pub first_seed: Vec<RangeImage>,
}

impl RealismBench {
    /// Samples `spec.seeds` scans for every test frame with `bundle` (an unconditional bundle
    /// draws them in batches of 16, as it ignores the frames) and scores them.
    /// `on_scan(done, total)` after each frame.
    pub fn run_model(
        &self,
        bundle: &Bundle,
        spec: &RowSpec,
        mut on_scan: impl FnMut(usize, usize),
    ) -> Result<RowResult> {
        use super::generate::GenerateOptions;
        let seeds = spec.seeds.max(1);
        let total = self.folds.len() * self.fold_size();
        let t = std::time::Instant::now();
        // per seed, per frame (fold order)
        let mut scans: Vec<Vec<RangeImage>> = vec![Vec::with_capacity(total); seeds];
        let options = |samples: usize, seed: u64| GenerateOptions {
            sampler: spec.sampler.clone(),
            samples,
            seed,
            unconditional: false,
            residual_weight: spec.residual_weight,
        };
        if bundle.is_conditional() {
            for (i, ex) in self.all_frames().enumerate() {
                let views = ex.views(bundle.config.num_views());
                let drawn = bundle.generate(&views, &options(seeds, i as u64), |_, _| {})?;
                for (s, scan) in drawn.into_iter().enumerate() {
                    scans[s].push(scan);
                }
                on_scan(i + 1, total);
            }
        } else {
            const BATCH: usize = 16;
            for s in 0..seeds {
                let mut b = 0u64;
                while scans[s].len() < total {
                    let n = BATCH.min(total - scans[s].len());
                    let seed = (s as u64) << 32 | b;
                    scans[s].extend(bundle.generate(&[], &options(n, seed), |_, _| {})?);
                    b += 1;
                    on_scan(s * total + scans[s].len(), seeds * total);
                }
            }
        }
        let seconds_per_scan = t.elapsed().as_secs_f64() / (seeds * total) as f64;
        let k = self.fold_size();
        let mut sets = Vec::with_capacity(self.folds.len() * seeds);
        let mut diversity = Vec::new();
        for f in 0..self.folds.len() {
            for seed_scans in &scans {
                sets.push(self.score(bundle, f, &seed_scans[f * k..(f + 1) * k])?);
            }
            if seeds >= 2 {
                let range = f * k..(f + 1) * k;
                diversity.push(self.diversity(f, &scans[0][range.clone()], &scans[1][range])?);
            }
        }
        Ok(RowResult {
            sets,
            diversity,
            seconds_per_scan,
            first_seed: scans.swap_remove(0),
        })
    }

    /// The zero-skill baselines on every fold: the per-pixel median of `pool`'s scans (no image
    /// used), and retrieval (the scan of `pool`'s frame whose image is nearest in `judge`'s
    /// frozen features). One set per fold each.
    pub fn baselines(
        &self,
        judge: &Bundle,
        pool: &[SimExample],
    ) -> Result<(Vec<SetMetrics>, Vec<SetMetrics>)> {
        let refs: Vec<&RangeImage> = pool.iter().map(|e| &e.range).collect();
        let median = veila_metrics::baseline::median_scan(&refs)?;
        let mut mean_sets = Vec::new();
        let mut retrieval_sets = Vec::new();
        for f in 0..self.folds.len() {
            let frames = &self.folds[f].frames;
            mean_sets.push(self.score(judge, f, &vec![median.clone(); frames.len()])?);
            let retrieved = super::sim_examples::retrieval_baseline(judge, pool, frames)?;
            retrieval_sets.push(self.score(judge, f, &retrieved)?);
        }
        Ok((mean_sets, retrieval_sets))
    }

    /// The diversity floor of every fold ([`Self::diversity_floor`]).
    pub fn diversity_floors(&self, judge: &Bundle) -> Result<Vec<SetMetrics>> {
        (0..self.folds.len())
            .map(|f| self.diversity_floor(judge, f))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::app::sim_examples::render_split;

    /// The bundled model, its feature networks and a few test and training frames (`None`, with
    /// a message, where the workspace's models are absent, as in a packaged crate).
    fn fixture(tests: usize) -> Option<(Bundle, RealismBench)> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let (model, nets) = (
            root.join("models/default"),
            root.join("models/feature-nets"),
        );
        if !model.is_dir() || !nets.is_dir() {
            eprintln!("skipped: no {} or {}", model.display(), nets.display());
            return None;
        }
        let device = Device::Cpu;
        let bundle = Bundle::from_dir(&model, &device).unwrap();
        let nets = FeatureNets::from_dir(&nets, &device).unwrap();
        let list = |name: &str| root.join("scenes").join(name);
        let frames = render_split(&list("test-v5.txt"), tests, &bundle.config, &|| {}).unwrap();
        let pool = render_split(&list("train-v5.txt"), 4, &bundle.config, &|| {}).unwrap();
        let bench = RealismBench::new(&bundle, frames, 2, &pool, Some(nets), &device).unwrap();
        Some((bundle, bench))
    }

    fn value(m: &SetMetrics, metric: &str, region: &str) -> f64 {
        m[metric][region]
    }

    #[test]
    fn true_scans_score_as_their_own_fold_and_the_floor_compares_two_folds() {
        let Some((bundle, bench)) = fixture(9) else {
            return;
        };
        // 9 frames make 2 folds of 4: the ninth is left out so the floor's sets are equal
        assert_eq!((bench.num_folds(), bench.fold_size()), (2, 4));
        let truth: Vec<RangeImage> = bench.frames(0).iter().map(|e| e.range.clone()).collect();
        let own = bench.score(&bundle, 0, &truth).unwrap();
        for region in TEXTURE_REGIONS {
            for metric in [
                "texture along rows (w1, decades)",
                "texture across rows (w1, decades)",
            ] {
                assert_eq!(value(&own, metric, region), 0.0, "{metric} {region}");
            }
        }
        assert_eq!(value(&own, "ray drop per row (abs diff)", "all"), 0.0);
        assert_eq!(value(&own, "range mae (m)", "view"), 0.0);
        assert_eq!(value(&own, "jsd", "all"), 0.0);
        // the Fréchet distance of a set with itself is zero up to the matrix square root's error
        assert!(value(&own, "fpd", "all").abs() < 1e-6, "{own:?}");
        let floor = bench.floor().unwrap();
        assert_eq!(floor.len(), 2);
        for m in &floor {
            for metric in ["fpd", "frd", "jsd"] {
                for region in ["all", "front", "rear"] {
                    let v = value(m, metric, region);
                    assert!(v.is_finite() && v > 0.0, "floor {metric} {region}: {v}");
                }
            }
            let t = value(m, "texture along rows (w1, decades)", "view");
            assert!(t.is_finite() && t > 0.0, "{t}");
        }
        // a calibration row is the floor's scans degraded: a vanishing noise scores as the floor,
        // without the metrics that compare a scan with its own frame; a blur loses the edges.
        // (Not FRD: the range net projects a 256-column scan onto its 512 columns, whose edges
        // the ray centres lie on, so a rounding decides each point's column, and on a set of 4
        // scans that moves FRD by about 10 %.)
        let faint = bench
            .calibration(&bundle, "noise:0.0001".parse().unwrap())
            .unwrap();
        let blur = bench
            .calibration(&bundle, "blur:5".parse().unwrap())
            .unwrap();
        assert_eq!((faint.len(), blur.len()), (2, 2));
        for ((c, b), fl) in faint.iter().zip(&blur).zip(&floor) {
            for metric in ["fpd", "jsd", "mmd (x1e4)"] {
                let (v, w) = (value(c, metric, "all"), value(fl, metric, "all"));
                assert!(
                    (v - w).abs() <= 1e-3 * w.max(1.0),
                    "{metric}: {v} against {w}"
                );
            }
            assert!(!c.contains_key("range mae (m)") && !c.contains_key("cm-dc (abs rel)"));
            let edges = |m: &SetMetrics| value(m, "depth edges (%)", "view");
            assert!(
                edges(b) < 0.5 * edges(fl),
                "{} against {}",
                edges(b),
                edges(fl)
            );
            let smooth = |m: &SetMetrics| value(m, "smooth pairs (%)", "view");
            assert!(
                smooth(b) > smooth(fl),
                "{} against {}",
                smooth(b),
                smooth(fl)
            );
        }
        // the floor's memorisation row is the true scans' own distance to the pool
        assert_eq!(
            value(&floor[0], "nearest train scan (log2 m)", "all"),
            value(&own, "nearest train scan (log2 m)", "all")
        );
        // a set against itself has no diversity; the true scans of similar frames have some
        let none = bench.diversity(0, &truth, &truth).unwrap();
        assert_eq!(value(&none, "diversity (range mae, m)", "rear"), 0.0);
        let df = bench.diversity_floor(&bundle, 0).unwrap();
        assert!(value(&df, "diversity (range mae, m)", "rear") > 0.0);
        // sizes that do not match the fold are errors, not panics
        assert!(bench.score(&bundle, 0, &truth[..3]).is_err());
        assert!(bench.diversity(0, &truth, &truth[..3]).is_err());
        assert!(bench.score(&bundle, 2, &truth).is_err());
    }

    #[test]
    fn a_model_row_has_a_set_per_fold_and_seed_and_two_seeds_differ() {
        let Some((bundle, bench)) = fixture(4) else {
            return;
        };
        let spec = RowSpec {
            sampler: bundle.config.sampler.clone(),
            seeds: 2,
            residual_weight: 1.0,
        };
        let mut calls = 0;
        let r = bench.run_model(&bundle, &spec, |_, _| calls += 1).unwrap();
        assert_eq!((r.sets.len(), r.diversity.len(), calls), (4, 2, 4));
        assert_eq!(r.first_seed.len(), 4);
        for d in &r.diversity {
            let v = value(d, "diversity (range mae, m)", "rear");
            assert!(v.is_finite() && v > 0.0, "{v}");
        }
        // seed 0 of the row is what the bundle draws for the frame as the first of two samples
        let ex = &bench.frames(1)[0];
        let opts = crate::app::GenerateOptions {
            samples: 2,
            seed: 2,
            ..crate::app::GenerateOptions::new(spec.sampler.clone())
        };
        let again = bundle
            .generate(&ex.views(1), &opts, |_, _| {})
            .unwrap()
            .swap_remove(0);
        assert_eq!(again.range_m, r.first_seed[2].range_m);
        // one fold of a shape the bench does not have
        assert!(
            RealismBench::new(
                &bundle,
                bench.frames(0).to_vec(),
                3,
                &[],
                None,
                &Device::Cpu
            )
            .is_err()
        );
    }
}
