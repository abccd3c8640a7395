//! A whole evaluation of two scan sets (what `veila eval` computes): every scan reduced once to
//! the summaries the requested metrics need ([`ScanSummary`], per region), then each metric over
//! the two sets ([`score_sets`]), named by its protocol. Errors name the scan by its label (a file
//! name, or `file[i]` for a sample of a peer's sample set).

use glam::Vec3;
use rayon::prelude::*;

use crate::bev::{BevConfig, BevHistogram, SparseBevHistogram, bev_histogram_sparse};
use crate::lidm::{self, LidmBevConfig};
use crate::metric::{MetricName, MetricReport, MetricValue, Protocol};
use crate::nn::PointIndex;
use crate::protocol::{PeerProtocol, PeerSummary};
use crate::{Error, Region, Result, chamfer, dist, filter_region};

/// What the summaries must hold for a set of metrics.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Needs {
    /// The raw points (mmd-cd, chamfer).
    pub points: bool,
    /// R2DM BEV histograms of the raw points.
    pub hist: bool,
    /// LiDM occupancy, 64-beam grid.
    pub occ: bool,
    /// LiDM occupancy, 32-beam grid.
    pub occ_nus: bool,
    /// The protocol's summary after its pipeline.
    pub peer: bool,
}

impl Needs {
    /// What `metrics` need.
    pub fn of(metrics: &[MetricName]) -> Self {
        use MetricName as M;
        let any = |f: &dyn Fn(MetricName) -> bool| metrics.iter().any(|m| f(*m));
        Needs {
            points: any(&|m| matches!(m, M::MmdCd | M::Chamfer)),
            hist: any(&|m| matches!(m, M::JsdRaw | M::MmdRaw | M::MmdLidargenRaw)),
            occ: metrics.contains(&M::MmdLidmRaw),
            occ_nus: metrics.contains(&M::MmdLidmNuscenesRaw),
            peer: any(&|m| matches!(m, M::Jsd | M::Mmd)),
        }
    }

    /// Whether anything but the protocol pipeline is asked for (sample sets have no raw points).
    pub fn raw(&self) -> bool {
        self.points || self.hist || self.occ || self.occ_nus
    }
}

/// What an evaluation keeps of each scan: per-region summaries are computed while loading, and
/// the points themselves only when a point metric (mmd-cd, chamfer) needs them, so memory stays
/// small for large sets.
#[derive(Debug, Clone)]
pub struct ScanSummary {
    /// `file` or `file[i]` for the i-th sample of a sample set.
    pub label: String,
    points: Option<Vec<Vec3>>,
    /// Sparse R2DM BEV histogram of the raw points per requested region.
    hist: Vec<SparseBevHistogram>,
    /// LiDM occupancy of the raw points per requested region (64-beam grid).
    occ: Vec<lidm::BevOccupancy>,
    /// LiDM occupancy of the raw points per requested region (32-beam grid).
    occ_nus: Vec<lidm::BevOccupancy>,
    /// The protocol's summary after its pipeline, per requested region.
    peer: Vec<PeerSummary>,
    /// Raw points in each requested region (`None` for a peer's sample, which has no raw points).
    in_region: Vec<Option<usize>>,
}

/// `err` with the scan's label in front.
fn at(label: &str, err: Error) -> Error {
    Error::Scan {
        label: label.to_string(),
        source: Box::new(err),
    }
}

impl ScanSummary {
    /// The summaries of one scan's raw points `xyz` for `regions`.
    pub fn of_points(
        xyz: Vec<Vec3>,
        label: String,
        regions: &[Region],
        needs: Needs,
        protocol: PeerProtocol,
    ) -> Result<Self> {
        let (bev, lcfg, lnus) = (
            BevConfig::r2dm(),
            LidmBevConfig::kitti(),
            LidmBevConfig::nuscenes(),
        );
        let prepared = if needs.peer {
            Some(
                protocol
                    .prepare_scan(&xyz, "scan")
                    .map_err(|e| at(&label, e))?,
            )
        } else {
            None
        };
        let mut s = ScanSummary {
            label,
            points: None,
            hist: Vec::new(),
            occ: Vec::new(),
            occ_nus: Vec::new(),
            peer: Vec::new(),
            in_region: regions
                .iter()
                .map(|r| Some(xyz.iter().filter(|&&p| r.contains(p)).count()))
                .collect(),
        };
        for &r in regions {
            if needs.hist {
                s.hist.push(
                    bev_histogram_sparse(&xyz, &bev, r, "scan").map_err(|e| at(&s.label, e))?,
                );
            }
            if needs.occ {
                s.occ.push(
                    lidm::lidm_bev_occupancy(&xyz, &lcfg, r, "scan")
                        .map_err(|e| at(&s.label, e))?,
                );
            }
            if needs.occ_nus {
                s.occ_nus.push(
                    lidm::lidm_bev_occupancy(&xyz, &lnus, r, "scan")
                        .map_err(|e| at(&s.label, e))?,
                );
            }
            if let Some(p) = &prepared {
                s.peer.push(
                    protocol
                        .summarise(p, r, "scan")
                        .map_err(|e| at(&s.label, e))?,
                );
            }
        }
        s.points = needs.points.then_some(xyz);
        Ok(s)
    }

    /// The samples of one array of a peer's sample set (`shape` and `data` as stored, read as the
    /// protocol's layout), each reduced by the protocol's pipeline; sample `i` is labelled
    /// `{label}[i]`.
    pub fn of_sample_array(
        label: &str,
        shape: &[usize],
        data: &[f32],
        regions: &[Region],
        protocol: PeerProtocol,
    ) -> Result<Vec<Self>> {
        let (n, c, h, w) = protocol.split_samples(shape).map_err(|e| at(label, e))?;
        let per = c * h * w;
        let mut out = Vec::with_capacity(n);
        for i in 0..n {
            let label = format!("{label}[{i}]");
            let pts = protocol
                .points_from_image(&data[i * per..(i + 1) * per], c, h, w, "sample")
                .map_err(|e| at(&label, e))?;
            let peer = regions
                .iter()
                .map(|&r| protocol.summarise(&pts, r, "sample"))
                .collect::<Result<Vec<_>>>()
                .map_err(|e| at(&label, e))?;
            out.push(ScanSummary {
                label,
                points: None,
                hist: Vec::new(),
                occ: Vec::new(),
                occ_nus: Vec::new(),
                peer,
                in_region: vec![None; regions.len()],
            });
        }
        Ok(out)
    }

    /// Keeps the summaries of the regions whose `keep` entry is true (`keep` in the order of the
    /// regions the summary was made for); [`score_sets`] then takes the kept regions.
    pub fn retain_regions(&mut self, keep: &[bool]) {
        fn retain<T>(v: &mut Vec<T>, keep: &[bool]) {
            if v.len() == keep.len() {
                let mut k = keep.iter();
                v.retain(|_| *k.next().unwrap_or(&true));
            }
        }
        retain(&mut self.hist, keep);
        retain(&mut self.occ, keep);
        retain(&mut self.occ_nus, keep);
        retain(&mut self.peer, keep);
        retain(&mut self.in_region, keep);
    }

    fn points(&self) -> &[Vec3] {
        self.points.as_deref().unwrap_or(&[])
    }
}

fn label_of(set: &[ScanSummary], i: usize) -> String {
    set.get(i)
        .map(|s| s.label.clone())
        .unwrap_or_else(|| format!("scan {i}"))
}

/// Turns the metrics' "generated scan 3" into the scan's label.
fn explain(err: Error, generated: &[ScanSummary], reference: &[ScanSummary]) -> Error {
    if let Error::NoPointsInWindow { what, window } = &err {
        for (prefix, set) in [
            ("generated scan ", generated),
            ("reference scan ", reference),
        ] {
            if let Some(i) = what
                .strip_prefix(prefix)
                .and_then(|s| s.parse::<usize>().ok())
            {
                return at(
                    &label_of(set, i),
                    Error::NoPointsInWindow {
                        what: "the scan (this metric normalises every scan on its own)".into(),
                        window: window.clone(),
                    },
                );
            }
        }
    }
    err
}

/// Up to this many scans per set the R2DM MMD uses dense histograms (GEMM, faster); above, sparse
/// ones (the same value up to rounding, ~9x less memory).
pub const DENSE_MMD_MAX_SCANS: usize = 2000;

/// The k-d trees of a set's points in `region` (every scan must have points there).
fn indexes(scans: &[ScanSummary], region: Region) -> Result<Vec<PointIndex>> {
    scans
        .par_iter()
        .map(|s| {
            let pts = filter_region(s.points(), region);
            if pts.is_empty() {
                return Err(at(
                    &s.label,
                    Error::Empty {
                        what: format!("the points in region {region}"),
                    },
                ));
            }
            PointIndex::build(&pts, "scan").map_err(|e| at(&s.label, e))
        })
        .collect()
}

/// The regions of `regions` (those the summaries were made for, in order) in which no scan of a
/// set has a raw point, with the set (`"generated"` or `"reference"`): scans cropped to a
/// camera's view have no `rear`. Their set metrics would compare empty histograms.
pub fn empty_regions(
    regions: &[Region],
    generated: &[ScanSummary],
    reference: &[ScanSummary],
) -> Vec<(Region, &'static str)> {
    let none_in = |set: &[ScanSummary], ri: usize| {
        !set.is_empty() && set.iter().all(|s| s.in_region.get(ri) == Some(&Some(0)))
    };
    let mut out = Vec::new();
    for (ri, &r) in regions.iter().enumerate() {
        for (set, what) in [(generated, "generated"), (reference, "reference")] {
            if none_in(set, ri) {
                out.push((r, what));
                break;
            }
        }
    }
    out
}

/// Every metric of `metrics` for every region of `regions` (the regions the summaries were made
/// for, in their order) between the generated and the reference summaries; `on_metric` is called
/// after each (metric, region). Every metric must be a set metric ([`MetricName::is_set_metric`]).
pub fn score_sets(
    metrics: &[MetricName],
    regions: &[Region],
    generated: &[ScanSummary],
    reference: &[ScanSummary],
    protocol: PeerProtocol,
    mut on_metric: impl FnMut(MetricName, Region),
) -> Result<MetricReport> {
    use MetricName as M;
    let mut report = MetricReport::default();
    let (ng, nr) = (generated.len(), reference.len());
    let value =
        |name: &str, protocol: Protocol, region: Region, v: f64, scale: Option<f64>| MetricValue {
            name: name.to_string(),
            protocol,
            region,
            value: v,
            generated: ng,
            reference: nr,
            paper_scale: scale,
        };
    let peer = metrics.iter().any(|m| matches!(m, M::Jsd | M::Mmd));
    for (ri, &region) in regions.iter().enumerate() {
        let sparse = |set: &[ScanSummary]| -> Vec<SparseBevHistogram> {
            set.iter().map(|s| s.hist[ri].clone()).collect()
        };
        let dense = |set: &[ScanSummary]| -> Vec<BevHistogram> {
            set.iter().map(|s| s.hist[ri].to_dense()).collect()
        };
        // the protocol's two metrics are computed together
        let peer_scores = if peer {
            let pg: Vec<PeerSummary> = generated.iter().map(|s| s.peer[ri].clone()).collect();
            let pr: Vec<PeerSummary> = reference.iter().map(|s| s.peer[ri].clone()).collect();
            Some(
                protocol
                    .score(&pg, &pr)
                    .map_err(|e| explain(e, generated, reference))?,
            )
        } else {
            None
        };
        for &m in metrics {
            let ex = |e| explain(e, generated, reference);
            let v = match m {
                M::Jsd | M::Mmd => {
                    let want = m.as_str();
                    let pm = peer_scores
                        .iter()
                        .flatten()
                        .find(|p| p.name == want)
                        .ok_or_else(|| Error::Empty {
                            what: format!("protocol {protocol}'s {want}"),
                        })?;
                    value(
                        want,
                        protocol.metric_protocol(),
                        region,
                        pm.value,
                        pm.paper_scale,
                    )
                }
                M::JsdRaw => value(
                    m.as_str(),
                    Protocol::R2dm,
                    region,
                    dist::jsd(&sparse(generated), &sparse(reference)).map_err(ex)?,
                    None,
                ),
                M::MmdRaw => {
                    let mmd = if ng.max(nr) <= DENSE_MMD_MAX_SCANS {
                        dist::mmd_r2dm_dense(&dense(generated), &dense(reference), dist::MMD_SIGMA)
                    } else {
                        dist::mmd_r2dm_sparse(
                            &sparse(generated),
                            &sparse(reference),
                            dist::MMD_SIGMA,
                        )
                    };
                    value(
                        m.as_str(),
                        Protocol::R2dm,
                        region,
                        mmd.map_err(ex)?,
                        Some(dist::MMD_PAPER_SCALE),
                    )
                }
                M::MmdLidargenRaw => value(
                    m.as_str(),
                    Protocol::Lidargen,
                    region,
                    dist::mmd_lidargen(&dense(generated), &dense(reference), dist::MMD_SIGMA)
                        .map_err(ex)?,
                    None,
                ),
                M::MmdLidmRaw | M::MmdLidmNuscenesRaw => {
                    let nus = m == M::MmdLidmNuscenesRaw;
                    let pick = |s: &ScanSummary| {
                        if nus {
                            s.occ_nus[ri].clone()
                        } else {
                            s.occ[ri].clone()
                        }
                    };
                    let og: Vec<_> = generated.iter().map(pick).collect();
                    let or: Vec<_> = reference.iter().map(pick).collect();
                    value(
                        m.as_str(),
                        if nus {
                            Protocol::LidmNuscenes
                        } else {
                            Protocol::Lidm
                        },
                        region,
                        lidm::mmd_lidm(&og, &or).map_err(ex)?,
                        Some(lidm::LIDM_PAPER_SCALE),
                    )
                }
                M::MmdCd => {
                    let ig = indexes(generated, region)?;
                    let ir = indexes(reference, region)?;
                    value(
                        m.as_str(),
                        Protocol::Pytorch3d,
                        region,
                        chamfer::minimum_matching_distance(&ig, &ir)?,
                        None,
                    )
                }
                M::Chamfer => {
                    let mut sum = 0.0;
                    for (g, r) in generated.iter().zip(reference) {
                        let gp = filter_region(g.points(), region);
                        let rp = filter_region(r.points(), region);
                        if gp.is_empty() || rp.is_empty() {
                            return Err(Error::Empty {
                                what: format!(
                                    "{} / {}: the points in region {region} (the Chamfer distance needs points on both sides)",
                                    g.label, r.label
                                ),
                            });
                        }
                        sum += chamfer::chamfer_distance(&gp, &rp)?.value();
                    }
                    value(
                        m.as_str(),
                        Protocol::Pytorch3d,
                        region,
                        sum / generated.len() as f64,
                        None,
                    )
                }
                M::Frd | M::Fpd | M::CmDc | M::CmSc => {
                    return Err(Error::InvalidParameter {
                        name: "metric",
                        reason: format!("{m} is not a set metric (computed beside score_sets)"),
                    });
                }
            };
            report.metrics.push(v);
            on_metric(m, region);
        }
    }
    Ok(report)
}
