//! Generated scans scored against simulated reference frames: the set metrics of `cargo xtask
//! bench-report` per fold of test frames (BEV JSD and MMD, FRD / FPD with the feature networks,
//! range MAE, CM-DC and CM-SC against a bundle's encoder heads), their mean and spread over
//! folds and seeds, and the data floor (one fold's true scans against another's). The metrics
//! themselves are `veila-metrics`'; this module runs the networks they are fed from.
//!
//! * [`encoder_maps`]: a small-CNN encoder's semantic and depth heads on one image.
//! * `Judges` (feature `sim`): everything about one fold's reference frames, computed once for
//!   every model scored against it; `set_metrics`: one set of generated scans against them;
//!   `data_floor`: the true scans of neighbouring folds against each other.
//! * [`Stat`] / [`metric_stats`]: a metric's mean and spread over sets.

use std::collections::BTreeMap;

use candle_core::Device;
use serde::Serialize;
use veila_geom::PinholeCamera;
use veila_nn::encoders::small_cnn::{DenseMaps, SmallCnn};

use crate::error::Result;

/// A small-CNN encoder's heads on an `h x w` RGB image seen by `camera` (an encoder with the
/// ground prior computes its input channel from it): labels and metric depth per pixel, each
/// `None` without its head.
pub fn encoder_maps(
    net: &SmallCnn,
    rgb: &[u8],
    camera: &PinholeCamera,
    h: usize,
    w: usize,
    device: &Device,
) -> Result<DenseMaps> {
    let img = net.config().input_tensor(rgb, h, w, Some(camera), device)?;
    let mut maps = net.predict_maps(&img)?;
    Ok(maps.swap_remove(0))
}

/// Metric values of one set of scans: metric name -> region (`all`, `front`, `rear`) -> value
/// (NaN where the metric could not be computed for the set).
pub type SetMetrics = BTreeMap<String, BTreeMap<String, f64>>;

/// A metric over several sets of scans (folds of the test frames, times sample seeds for a
/// model): mean and standard deviation over the sets where it is finite.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stat {
    /// Mean over the finite values (NaN when there is none).
    pub mean: f64,
    /// Sample standard deviation over them (0 for fewer than two).
    pub std: f64,
    /// Sets behind the values, the non-finite ones included.
    pub sets: usize,
    /// Scans in each set.
    pub scans_per_set: usize,
}

impl Stat {
    /// The [`Stat`] of `values`, one per set of `scans_per_set` scans.
    pub fn of(values: &[f64], scans_per_set: usize) -> Self {
        let finite: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
        let n = finite.len().max(1) as f64;
        let mean = finite.iter().sum::<f64>() / n;
        let var = if finite.len() > 1 {
            finite.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)
        } else {
            0.0
        };
        Stat {
            mean: if finite.is_empty() { f64::NAN } else { mean },
            std: var.sqrt(),
            sets: values.len(),
            scans_per_set,
        }
    }
}

/// Every metric and region of `per_set` (the first set's names; each set must have them) as a
/// [`Stat`] over the sets.
pub fn metric_stats(
    per_set: &[SetMetrics],
    scans_per_set: usize,
) -> BTreeMap<String, BTreeMap<String, Stat>> {
    let mut metrics: BTreeMap<String, BTreeMap<String, Stat>> = BTreeMap::new();
    if let Some(first) = per_set.first() {
        for (m, regions) in first {
            for region in regions.keys() {
                let vals: Vec<f64> = per_set
                    .iter()
                    .map(|x| x.get(m).and_then(|r| r.get(region)).copied())
                    .map(|v| v.unwrap_or(f64::NAN))
                    .collect();
                metrics
                    .entry(m.clone())
                    .or_default()
                    .insert(region.clone(), Stat::of(&vals, scans_per_set));
            }
        }
    }
    metrics
}

#[cfg(feature = "sim")]
pub use sets::{Judges, data_floor, distribution_metrics, set_metrics};

/// The set metrics on simulated frames.
#[cfg(feature = "sim")]
mod sets {
    use glam::Vec3;
    use veila_geom::{RangeImage, RayTable, Region};
    use veila_metrics::bev::{BevConfig, BevHistogram, bev_histogram};
    use veila_metrics::crossmodal::{
        DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency, cm_semantic_consistency,
    };
    use veila_metrics::dist;
    use veila_metrics::fd::{self, FeatureStats};
    use veila_nn::feature_nets::FeatureNets;

    use super::{Device, SetMetrics, encoder_maps};
    use crate::app::bundle::Bundle;
    use crate::app::sim_examples::SimExample;
    use crate::error::{Error, Result};

    /// Judges shared by every model scored on one fold: a bundle's encoder heads on the frames'
    /// images (depth for CM-DC, semantics for CM-SC) and everything about the reference scans,
    /// computed once for all models and seeds.
    #[derive(Debug)]
    pub struct Judges {
        depth_pred: Vec<Vec<f32>>,
        label_pred: Vec<Vec<u32>>,
        /// Per region, in `Region::ALL` order.
        reference: Vec<RegionReference>,
    }

    /// The reference side of the set metrics of one region.
    #[derive(Debug)]
    struct RegionReference {
        histograms: Vec<BevHistogram>,
        /// FRD and FPD feature rows (flattened), when the feature networks are present.
        features: Option<(Vec<f32>, Vec<f32>)>,
    }

    fn judge_error(what: &str) -> Error {
        Error::InvalidConfig {
            field: "encoders",
            reason: format!("the judge bundle {what}"),
        }
    }

    impl Judges {
        /// The judges of the fold `tests` with `bundle`'s small-CNN encoder heads (an error when
        /// it has no depth or no semantic head) and, when given, the feature networks.
        pub fn new(
            bundle: &Bundle,
            tests: &[SimExample],
            nets: Option<&FeatureNets>,
            device: &Device,
        ) -> Result<Self> {
            let (h, w) = (bundle.config.image_height, bundle.config.image_width);
            let depth = bundle.depth.as_ref().map(|n| n.as_small_cnn());
            let depth = depth
                .ok_or_else(|| judge_error("has no depth head"))?
                .ok_or_else(|| judge_error("'s depth encoder is not a small CNN"))?;
            let semantic = bundle.semantic.as_ref().map(|n| n.as_small_cnn());
            let semantic = semantic
                .ok_or_else(|| judge_error("has no semantic head"))?
                .ok_or_else(|| judge_error("'s semantic encoder is not a small CNN"))?;
            let rays = RayTable::new(&bundle.config.denoiser.sensor)?;
            let (mut depth_pred, mut label_pred) = (Vec::new(), Vec::new());
            let (mut points, mut intensity) = (Vec::new(), Vec::new());
            for ex in tests {
                let maps = |net| encoder_maps(net, &ex.rgb, &ex.camera, h, w, device);
                let d = maps(depth)?.depth_m;
                depth_pred.push(d.ok_or_else(|| judge_error("has no depth head"))?);
                let l = maps(semantic)?.labels;
                label_pred.push(l.ok_or_else(|| judge_error("has no semantic head"))?);
                let un = rays.unproject(&ex.range)?;
                points.push(un.points);
                intensity.push(un.intensity);
            }
            let cfg = BevConfig::r2dm();
            let reference = Region::ALL
                .into_iter()
                .map(|region| {
                    let histograms = points
                        .iter()
                        .map(|p| bev_histogram(p, &cfg, region, "reference scan"))
                        .collect::<std::result::Result<Vec<_>, _>>()?;
                    let features = nets
                        .map(|n| region_features(n, &points, &intensity, region))
                        .transpose()?;
                    Ok(RegionReference {
                        histograms,
                        features,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            Ok(Judges {
                depth_pred,
                label_pred,
                reference,
            })
        }
    }

    /// A metric's value, or NaN (reported as n/a) when it cannot be computed for this set, e.g.
    /// when a poorly trained model generates no return inside the BEV window.
    fn or_nan<E: std::fmt::Display>(what: &str, r: std::result::Result<f64, E>) -> f64 {
        r.unwrap_or_else(|e| {
            tracing::warn!("{what}: {e}; reported as n/a");
            f64::NAN
        })
    }

    /// Points of `region` (and their intensities).
    fn in_region(points: &[Vec3], intensity: &[f32], region: Region) -> (Vec<Vec3>, Vec<f32>) {
        points
            .iter()
            .zip(intensity)
            .filter(|(p, _)| region.contains(**p))
            .map(|(p, i)| (*p, *i))
            .unzip()
    }

    /// FRD and FPD feature rows (flattened) of the scans' points in `region`.
    fn region_features(
        nets: &FeatureNets,
        points: &[Vec<Vec3>],
        intensity: &[Vec<f32>],
        region: Region,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let scans: Vec<(Vec<Vec3>, Vec<f32>)> = points
            .iter()
            .zip(intensity)
            .map(|(p, i)| in_region(p, i, region))
            .filter(|(p, _)| !p.is_empty())
            .collect();
        let range_in: Vec<(&[Vec3], Option<&[f32]>)> = scans
            .iter()
            .map(|(p, i)| (p.as_slice(), Some(i.as_slice())))
            .collect();
        let rf = nets.scan_range_features(&range_in)?;
        let point_in: Vec<&[Vec3]> = scans.iter().map(|(p, _)| p.as_slice()).collect();
        let pf = nets.point_features(&point_in)?;
        Ok((rf.concat(), pf.concat()))
    }

    /// FRD and FPD of generated scans in `region` against the reference features of that
    /// region (NaN for fewer than two rows per feature dimension on a side).
    fn frd_fpd(
        nets: &FeatureNets,
        points: &[Vec<Vec3>],
        intensity: &[Vec<f32>],
        (rr, rpf): &(Vec<f32>, Vec<f32>),
        region: Region,
    ) -> Result<(f64, f64)> {
        let (gr, gpf) = region_features(nets, points, intensity, region)?;
        let rd = nets.rangenet().config().feature_dim();
        let pd = nets.pointnet().config().feature_dim();
        Ok((
            feature_distance(&gr, rr, rd)?,
            feature_distance(&gpf, rpf, pd)?,
        ))
    }

    /// The Fréchet distance of two sets of `d`-dimensional feature rows (flattened), NaN for
    /// fewer than two rows per dimension on a side.
    fn feature_distance(a: &[f32], b: &[f32], d: usize) -> Result<f64> {
        if a.len() < 2 * d || b.len() < 2 * d {
            return Ok(f64::NAN);
        }
        Ok(fd::frechet_distance(
            &FeatureStats::from_rows(a, d, "generated features")?,
            &FeatureStats::from_rows(b, d, "reference features")?,
        )?)
    }

    /// The metrics of one set of generated scans (one per frame of `tests`, on `bundle`'s grid)
    /// against the fold's [`Judges`], every region; CM-DC and CM-SC over the camera's view (the
    /// `front` entry), CM-SC and FRD / FPD only with the feature networks.
    pub fn set_metrics(
        bundle: &Bundle,
        generated: &[RangeImage],
        tests: &[SimExample],
        judges: &Judges,
        nets: Option<&FeatureNets>,
    ) -> Result<SetMetrics> {
        if generated.len() != tests.len() || tests.len() != judges.depth_pred.len() {
            return Err(Error::Shape {
                what: "scored scans",
                expected: format!("one per frame of the fold ({})", judges.depth_pred.len()),
                got: format!("{} scans of {} frames", generated.len(), tests.len()),
            });
        }
        let (gen_points, gen_intensity) = unproject_all(bundle, generated)?;
        let mut m = SetMetrics::new();
        distribution_into(&mut m, &gen_points, &gen_intensity, judges, nets)?;
        for region in Region::ALL {
            let mut sum = 0.0;
            let mut n = 0usize;
            for (g, ex) in generated.iter().zip(tests) {
                if let Some(v) = veila_metrics::range::range_mae(g, &ex.range, region) {
                    sum += v;
                    n += 1;
                }
            }
            m.entry("range mae (m)".into()).or_default().insert(
                region.name().into(),
                if n > 0 { sum / n as f64 } else { f64::NAN },
            );
        }
        // cross-modal consistency in the camera's field of view, against the encoder heads
        let filter = ProjectionFilter::default();
        let (mut dc, mut sc, mut nd, mut ns) = (0.0, 0.0, 0usize, 0usize);
        for (i, ex) in tests.iter().enumerate() {
            let (w, h) = (ex.camera.width, ex.camera.height);
            let depth = Map2d::new(w, h, &judges.depth_pred[i])?;
            if let Ok(c) = cm_depth_consistency(
                &gen_points[i],
                &ex.camera,
                &depth,
                DepthAlignment::None,
                &filter,
            ) && c.abs_rel.is_finite()
            {
                dc += c.abs_rel;
                nd += 1;
            }
            // CM-SC: the classes the range segmentation net gives the generated points against the
            // image semantic head's classes where they project
            if let Some(nets) = nets {
                let (pts, labels) = nets.segment_points(&gen_points[i], Some(&gen_intensity[i]))?;
                let pred = Map2d::new(w, h, &judges.label_pred[i])?;
                let filter = ProjectionFilter {
                    ignore_label: Some(0),
                    ..ProjectionFilter::default()
                };
                if let Ok(c) = cm_semantic_consistency(&pts, &labels, &ex.camera, &pred, &filter)
                    && c.percent.is_finite()
                {
                    sc += c.percent;
                    ns += 1;
                }
            }
        }
        let front = Region::Front.name().to_string();
        m.entry("cm-dc (abs rel)".into()).or_default().insert(
            front.clone(),
            if nd > 0 { dc / nd as f64 } else { f64::NAN },
        );
        m.entry("cm-sc (%)".into())
            .or_default()
            .insert(front, if ns > 0 { sc / ns as f64 } else { f64::NAN });
        Ok(m)
    }

    /// The distribution metrics alone (JSD, MMD, and FRD / FPD with the feature networks) of a
    /// set of scans on `bundle`'s grid against the fold's [`Judges`], every region: what compares
    /// the set with the fold's true scans as a whole, not scan by scan with their frames.
    pub fn distribution_metrics(
        bundle: &Bundle,
        scans: &[RangeImage],
        judges: &Judges,
        nets: Option<&FeatureNets>,
    ) -> Result<SetMetrics> {
        let (points, intensity) = unproject_all(bundle, scans)?;
        let mut m = SetMetrics::new();
        distribution_into(&mut m, &points, &intensity, judges, nets)?;
        Ok(m)
    }

    /// Per scan: its points and their intensities.
    type ScanPoints = (Vec<Vec<Vec3>>, Vec<Vec<f32>>);

    /// Every scan's points and intensities.
    fn unproject_all(bundle: &Bundle, scans: &[RangeImage]) -> Result<ScanPoints> {
        let rays = RayTable::new(&bundle.config.denoiser.sensor)?;
        let mut points = Vec::with_capacity(scans.len());
        let mut intensity = Vec::with_capacity(scans.len());
        for r in scans {
            let u = rays.unproject(r)?;
            points.push(u.points);
            intensity.push(u.intensity);
        }
        Ok((points, intensity))
    }

    /// JSD, MMD and (with the feature networks) FRD / FPD of the scans' points against the
    /// judges' reference, every region, into `m`.
    fn distribution_into(
        m: &mut SetMetrics,
        points: &[Vec<Vec3>],
        intensity: &[Vec<f32>],
        judges: &Judges,
        nets: Option<&FeatureNets>,
    ) -> Result<()> {
        let cfg = BevConfig::r2dm();
        for (region, reference) in Region::ALL.into_iter().zip(&judges.reference) {
            let hg = points
                .iter()
                .map(|p| bev_histogram(p, &cfg, region, "generated scan"))
                .collect::<std::result::Result<Vec<_>, _>>()?;
            let hr = &reference.histograms;
            let rn = region.name().to_string();
            m.entry("jsd".into())
                .or_default()
                .insert(rn.clone(), or_nan("jsd", dist::jsd(&hg, hr)));
            m.entry("mmd (x1e4)".into()).or_default().insert(
                rn.clone(),
                1e4 * or_nan("mmd", dist::mmd_r2dm_dense(&hg, hr, 0.5)),
            );
            if let (Some(nets), Some(reference)) = (nets, &reference.features) {
                let (frd, fpd) = frd_fpd(nets, points, intensity, reference, region)
                    .unwrap_or_else(|e| {
                        tracing::warn!("frd / fpd ({rn}): {e}; reported as n/a");
                        (f64::NAN, f64::NAN)
                    });
                m.entry("frd".into()).or_default().insert(rn.clone(), frd);
                m.entry("fpd".into()).or_default().insert(rn, fpd);
            }
        }
        Ok(())
    }

    /// The data floor: the set metrics (JSD, MMD, and FRD / FPD where the judges hold feature
    /// rows) between the true scans of neighbouring folds (fold `f` against fold `f + 1`, the last
    /// against the first): what a perfect generator of this many scans would score. One set per
    /// fold. The Fréchet distances are biased by the number of scans, so a floor is comparable
    /// with rows scored on folds of the same size.
    pub fn data_floor(judges: &[Judges], nets: Option<&FeatureNets>) -> Vec<SetMetrics> {
        let k = judges.len();
        (0..k)
            .map(|f| {
                let (a, b) = (&judges[f], &judges[(f + 1) % k]);
                let mut m = SetMetrics::new();
                for (region, (ra, rb)) in Region::ALL
                    .into_iter()
                    .zip(a.reference.iter().zip(&b.reference))
                {
                    let rn = region.name().to_string();
                    m.entry("jsd".into()).or_default().insert(
                        rn.clone(),
                        or_nan("jsd", dist::jsd(&ra.histograms, &rb.histograms)),
                    );
                    m.entry("mmd (x1e4)".into()).or_default().insert(
                        rn.clone(),
                        1e4 * or_nan(
                            "mmd",
                            dist::mmd_r2dm_dense(&ra.histograms, &rb.histograms, 0.5),
                        ),
                    );
                    if let (Some(nets), Some((ar, ap)), Some((br, bp))) =
                        (nets, &ra.features, &rb.features)
                    {
                        let rd = nets.rangenet().config().feature_dim();
                        let pd = nets.pointnet().config().feature_dim();
                        let frd = or_nan("frd", feature_distance(ar, br, rd));
                        let fpd = or_nan("fpd", feature_distance(ap, bp, pd));
                        m.entry("frd".into()).or_default().insert(rn.clone(), frd);
                        m.entry("fpd".into()).or_default().insert(rn, fpd);
                    }
                }
                m
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_skip_the_sets_a_metric_failed_on_and_say_how_many_there_were() {
        let s = Stat::of(&[1.0, f64::NAN, 3.0], 4);
        assert_eq!((s.mean, s.sets, s.scans_per_set), (2.0, 3, 4));
        assert!((s.std - 2f64.sqrt()).abs() < 1e-12);
        let none = Stat::of(&[f64::NAN], 4);
        assert!(none.mean.is_nan());
        assert_eq!(none.std, 0.0);
        let set = |v: f64| -> SetMetrics {
            [("jsd".to_string(), [("all".to_string(), v)].into())].into()
        };
        let stats = metric_stats(&[set(0.1), set(0.3)], 5);
        assert!((stats["jsd"]["all"].mean - 0.2).abs() < 1e-12);
        // a set without a metric the first has counts as a failed one, not a panic
        let stats = metric_stats(&[set(0.1), SetMetrics::new()], 5);
        assert_eq!(
            (stats["jsd"]["all"].mean, stats["jsd"]["all"].sets),
            (0.1, 2)
        );
        assert!(metric_stats(&[], 5).is_empty());
    }
}
