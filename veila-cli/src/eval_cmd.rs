//! `veila eval` (distribution and point metrics between two folders of scans) and `veila fd` (Fréchet
//! distance between two feature matrices stored as `.npy`). Both print a table and optionally write JSON
//! `{"metrics": [...]}` atomically.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::eval_features;
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use glam::Vec3;
use rayon::prelude::*;

use veila_metrics::{
    MetricReport, MetricValue, Protocol, Region,
    bev::{BevConfig, BevHistogram, SparseBevHistogram, bev_histogram_sparse},
    chamfer, dist,
    fd::{self, FeatureStats, SqrtMethod},
    lidm::{self, LidmBevConfig},
    nn::PointIndex,
};

/// Evaluation commands.
#[derive(Debug, Subcommand)]
pub(crate) enum EvalCmd {
    /// Score generated scans against reference scans (JSD, MMD, MMD-CD, Chamfer, FRD, FPD), each metric
    /// named by its protocol, for the whole panorama and its front (x > 0) and rear (x <= 0) halves
    /// (FRD and FPD: whole panorama only; their built-in networks are simulator-trained, so the values
    /// are not comparable with published FRD / FPD numbers).
    Eval(EvalArgs),
    /// Fréchet distance between two feature matrices (.npy, f32 or f64, one row per sample).
    Fd(FdArgs),
}

/// Metrics `veila eval` can compute.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, ValueEnum)]
pub(crate) enum MetricName {
    /// Jensen-Shannon distance of summed BEV histograms (R2DM / LiDARGen protocol).
    Jsd,
    /// Gaussian-kernel BEV MMD, Frobenius distance, sigma 0.5 (R2DM protocol; papers print x 1e4).
    Mmd,
    /// Gaussian-kernel BEV MMD with the spectral-norm distance (LiDARGen protocol; O(N^2) SVDs).
    MmdLidargen,
    /// Minimum matching distance, 2-D Chamfer over 0.5 m BEV occupancy (LiDM protocol; printed x 1e4).
    MmdLidm,
    /// Minimum matching distance with the 3-D Chamfer distance (PyTorch3D convention).
    MmdCd,
    /// Chamfer distance of scans paired by file name, averaged over pairs (PyTorch3D convention).
    Chamfer,
    /// Fréchet Range Distance: Fréchet distance of RangeNet features (global average of the deepest
    /// encoder map) of each scan's range image, whole panorama only. With the built-in simulator-trained
    /// net, NOT comparable with published FRD values (different weights and feature layer).
    Frd,
    /// Fréchet Point Distance: Fréchet distance of PointNet max-pooled features of each scan (points
    /// / 80 m), whole panorama only. With the built-in simulator-trained net, NOT comparable with
    /// published FPD values (different weights and feature layer).
    Fpd,
}

/// Regions to report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum RegionArg {
    /// The whole panorama.
    All,
    /// x > 0.
    Front,
    /// x <= 0.
    Rear,
}

impl From<RegionArg> for Region {
    fn from(r: RegionArg) -> Self {
        match r {
            RegionArg::All => Region::All,
            RegionArg::Front => Region::Front,
            RegionArg::Rear => Region::Rear,
        }
    }
}

#[derive(Debug, Args)]
pub(crate) struct EvalArgs {
    /// Folder of generated scans (.bin, .pcd.bin, .ply or range .exr; format detected per file).
    #[arg(long)]
    generated: PathBuf,
    /// Folder of reference scans (same formats).
    #[arg(long)]
    reference: PathBuf,
    /// Comma-separated metrics.
    #[arg(long, value_delimiter = ',', default_value = "jsd,mmd")]
    metrics: Vec<MetricName>,
    /// Comma-separated regions.
    #[arg(long, value_delimiter = ',', default_value = "all,front,rear")]
    regions: Vec<RegionArg>,
    /// Also write the results as JSON `{"metrics": [...]}` (written atomically).
    #[arg(long)]
    json: Option<PathBuf>,
    /// FRD / FPD networks: a folder with rangenet.json, rangenet.safetensors, pointnet.json,
    /// pointnet.safetensors and manifest.json (e.g. converted official weights; see the veila-nn
    /// `feature_nets` docs). Default: the simulator-trained nets built into this binary.
    #[arg(long)]
    feature_nets: Option<PathBuf>,
    /// Also write a self-contained HTML report (metric table, bird's-eye views, BEV density
    /// difference, range and height distributions), atomically, when the evaluation succeeds.
    #[arg(long)]
    report: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub(crate) struct FdArgs {
    /// First feature matrix (.npy, 2-D, f32 or f64, C or Fortran order), e.g. reference features.
    a: PathBuf,
    /// Second feature matrix (same number of columns), e.g. generated features.
    b: PathBuf,
    /// Also write the result as JSON `{"metrics": [...]}` (written atomically).
    #[arg(long)]
    json: Option<PathBuf>,
    /// Newton-Schulz iterations instead of the exact eigendecomposition (approximate; for comparison).
    #[arg(long)]
    newton_schulz: Option<usize>,
}

pub(crate) fn run(cmd: EvalCmd) -> Result<()> {
    match cmd {
        EvalCmd::Eval(a) => run_eval(a),
        EvalCmd::Fd(a) => run_fd(a),
    }
}

fn is_scan_file(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    name.ends_with(".bin") || name.ends_with(".ply") || name.ends_with(".exr")
}

/// Scan files of a folder, sorted by name.
fn list_scans(dir: &Path, what: &str) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir)
        .with_context(|| format!("{what} folder {}: cannot read", dir.display()))?;
    let mut files = Vec::new();
    for e in entries {
        let e = e.with_context(|| format!("{what} folder {}: cannot list", dir.display()))?;
        let p = e.path();
        if p.is_file() && is_scan_file(&p) {
            files.push(p);
        }
    }
    files.sort();
    if files.is_empty() {
        bail!(
            "{what} folder {} has no scans (.bin, .pcd.bin, .ply, .exr)",
            dir.display()
        );
    }
    Ok(files)
}

/// What `veila eval` keeps of each scan: per-region summaries are computed while loading, and the points
/// themselves only when a point metric (mmd-cd, chamfer) needs them, so memory stays small for large sets.
struct ScanSummary {
    points: Option<Vec<Vec3>>,
    /// Sparse R2DM BEV histogram per requested region (empty when no histogram metric is requested).
    hist: Vec<SparseBevHistogram>,
    /// LiDM occupancy per requested region (empty when mmd-lidm is not requested).
    occ: Vec<lidm::BevOccupancy>,
}

#[derive(Debug, Clone, Copy)]
struct Needs {
    points: bool,
    hist: bool,
    occ: bool,
}

fn load_scans(
    files: &[PathBuf],
    what: &str,
    regions: &[Region],
    needs: Needs,
) -> Result<Vec<ScanSummary>> {
    let pb = crate::progress::bar(files.len() as u64, what);
    let (bev, lcfg) = (BevConfig::r2dm(), LidmBevConfig::kitti());
    let out: Result<Vec<ScanSummary>> = files
        .par_iter()
        .map(|f| {
            let loaded = veila_data::scan::read_points(f)
                .with_context(|| format!("reading {}", f.display()))?;
            if loaded.cloud.xyz.is_empty() {
                bail!("{}: the scan has no (finite) points", f.display());
            }
            let xyz = loaded.cloud.xyz;
            let mut hist = Vec::new();
            let mut occ = Vec::new();
            for &r in regions {
                if needs.hist {
                    hist.push(
                        bev_histogram_sparse(&xyz, &bev, r, "scan")
                            .with_context(|| f.display().to_string())?,
                    );
                }
                if needs.occ {
                    occ.push(
                        lidm::lidm_bev_occupancy(&xyz, &lcfg, r, "scan")
                            .with_context(|| f.display().to_string())?,
                    );
                }
            }
            pb.inc(1);
            Ok(ScanSummary {
                points: needs.points.then_some(xyz),
                hist,
                occ,
            })
        })
        .collect();
    pb.finish_and_clear();
    out
}

fn file_label(files: &[PathBuf], i: usize) -> String {
    files
        .get(i)
        .map(|f| f.display().to_string())
        .unwrap_or_else(|| format!("scan {i}"))
}

/// Turns the library's "generated scan 3" into the file name.
fn explain(
    err: veila_metrics::Error,
    gen_files: &[PathBuf],
    ref_files: &[PathBuf],
) -> anyhow::Error {
    if let veila_metrics::Error::NoPointsInWindow { what, window } = &err {
        for (prefix, files) in [
            ("generated scan ", gen_files),
            ("reference scan ", ref_files),
        ] {
            if let Some(i) = what
                .strip_prefix(prefix)
                .and_then(|s| s.parse::<usize>().ok())
            {
                return anyhow::anyhow!(
                    "{}: no point inside the {window} window (this metric normalises every scan on its own)",
                    file_label(files, i)
                );
            }
        }
    }
    anyhow::Error::new(err)
}

struct Sets<'a> {
    gen_files: &'a [PathBuf],
    ref_files: &'a [PathBuf],
    generated: Vec<ScanSummary>,
    reference: Vec<ScanSummary>,
}

/// Up to this many scans per set the R2DM MMD uses dense histograms (GEMM, faster); above, sparse ones
/// (the same value up to rounding, ~9x less memory).
const DENSE_MMD_MAX_SCANS: usize = 2000;

fn points_of(s: &ScanSummary) -> &[Vec3] {
    s.points.as_deref().unwrap_or(&[])
}

fn run_eval(a: EvalArgs) -> Result<()> {
    if let Some(path) = &a.report {
        crate::report::check_output_dir(path)?;
    }
    let gen_files = list_scans(&a.generated, "generated")?;
    let ref_files = list_scans(&a.reference, "reference")?;
    let mut metrics = a.metrics.clone();
    metrics.sort();
    metrics.dedup();
    if metrics.is_empty() {
        bail!("--metrics is empty");
    }
    if metrics.contains(&MetricName::Chamfer) {
        check_pairing(&gen_files, &ref_files, &a.generated, &a.reference)?;
    }
    let regions: Vec<Region> = a.regions.iter().map(|&r| Region::from(r)).collect();
    let needs = Needs {
        points: metrics
            .iter()
            .any(|m| matches!(m, MetricName::MmdCd | MetricName::Chamfer)),
        hist: metrics.iter().any(|m| {
            matches!(
                m,
                MetricName::Jsd | MetricName::Mmd | MetricName::MmdLidargen
            )
        }),
        occ: metrics.contains(&MetricName::MmdLidm),
    };
    let generated = load_scans(&gen_files, "generated", &regions, needs)?;
    let reference = load_scans(&ref_files, "reference", &regions, needs)?;
    let sets = Sets {
        gen_files: &gen_files,
        ref_files: &ref_files,
        generated,
        reference,
    };

    let mut report = MetricReport::default();
    let (ng, nr) = (gen_files.len(), ref_files.len());
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
    let pb = crate::progress::bar((metrics.len() * a.regions.len()) as u64, "metrics");
    for (ri, &region) in regions.iter().enumerate() {
        let sparse = |set: &[ScanSummary]| -> Vec<SparseBevHistogram> {
            set.iter().map(|s| s.hist[ri].clone()).collect()
        };
        let dense = |set: &[ScanSummary]| -> Vec<BevHistogram> {
            set.iter().map(|s| s.hist[ri].to_dense()).collect()
        };
        for &m in &metrics {
            pb.set_message(format!("{m:?} {region}"));
            let ex = |e| explain(e, sets.gen_files, sets.ref_files);
            let v = match m {
                // feature metrics: whole panorama, computed once below
                MetricName::Frd | MetricName::Fpd => {
                    pb.inc(1);
                    continue;
                }
                MetricName::Jsd => {
                    let (hg, hr) = (sparse(&sets.generated), sparse(&sets.reference));
                    value(
                        "jsd",
                        Protocol::R2dm,
                        region,
                        dist::jsd(&hg, &hr).map_err(ex)?,
                        None,
                    )
                }
                MetricName::Mmd => {
                    let mmd = if ng.max(nr) <= DENSE_MMD_MAX_SCANS {
                        dist::mmd_r2dm_dense(
                            &dense(&sets.generated),
                            &dense(&sets.reference),
                            dist::MMD_SIGMA,
                        )
                    } else {
                        dist::mmd_r2dm_sparse(
                            &sparse(&sets.generated),
                            &sparse(&sets.reference),
                            dist::MMD_SIGMA,
                        )
                    };
                    value(
                        "mmd",
                        Protocol::R2dm,
                        region,
                        mmd.map_err(ex)?,
                        Some(dist::MMD_PAPER_SCALE),
                    )
                }
                MetricName::MmdLidargen => value(
                    "mmd",
                    Protocol::Lidargen,
                    region,
                    dist::mmd_lidargen(
                        &dense(&sets.generated),
                        &dense(&sets.reference),
                        dist::MMD_SIGMA,
                    )
                    .map_err(ex)?,
                    None,
                ),
                MetricName::MmdLidm => {
                    let og: Vec<_> = sets.generated.iter().map(|s| s.occ[ri].clone()).collect();
                    let or: Vec<_> = sets.reference.iter().map(|s| s.occ[ri].clone()).collect();
                    value(
                        "mmd",
                        Protocol::Lidm,
                        region,
                        lidm::mmd_lidm(&og, &or).map_err(ex)?,
                        Some(lidm::LIDM_PAPER_SCALE),
                    )
                }
                MetricName::MmdCd => {
                    let ig = indexes(&sets.generated, sets.gen_files, region)?;
                    let ir = indexes(&sets.reference, sets.ref_files, region)?;
                    value(
                        "mmd-cd",
                        Protocol::Pytorch3d,
                        region,
                        chamfer::minimum_matching_distance(&ig, &ir)?,
                        None,
                    )
                }
                MetricName::Chamfer => {
                    let mut sum = 0.0;
                    for (i, (g, r)) in sets.generated.iter().zip(&sets.reference).enumerate() {
                        let g = veila_metrics::filter_region(points_of(g), region);
                        let r = veila_metrics::filter_region(points_of(r), region);
                        if g.is_empty() || r.is_empty() {
                            bail!(
                                "{} / {}: no points in region {region}; the Chamfer distance needs points on both sides",
                                file_label(sets.gen_files, i),
                                file_label(sets.ref_files, i)
                            );
                        }
                        sum += chamfer::chamfer_distance(&g, &r)?.value();
                    }
                    value(
                        "chamfer",
                        Protocol::Pytorch3d,
                        region,
                        sum / sets.generated.len() as f64,
                        None,
                    )
                }
            };
            report.metrics.push(v);
            pb.inc(1);
        }
    }
    pb.finish_and_clear();
    feature_metrics(&a, &metrics, &gen_files, &ref_files, &mut report)?;
    // the file first, then the table: a reader that goes away early (`| head`) cannot cost the JSON
    if let Some(path) = &a.json {
        write_json(path, &report)?;
    }
    if let Some(path) = &a.report {
        let html = crate::report::eval_report(&crate::report::EvalReportInputs {
            generated_dir: &a.generated,
            reference_dir: &a.reference,
            generated: &gen_files,
            reference: &ref_files,
            metrics: &report,
            date: veila_data::stamp::report_time(),
            command: crate::report::command_line(),
        })?;
        html.write(path)?;
    }
    print_table(&report);
    Ok(())
}

/// FRD and FPD (when requested), appended to `report` with the network protocol in the name.
fn feature_metrics(
    a: &EvalArgs,
    metrics: &[MetricName],
    gen_files: &[PathBuf],
    ref_files: &[PathBuf],
    report: &mut MetricReport,
) -> Result<()> {
    let want = eval_features::Want {
        frd: metrics.contains(&MetricName::Frd),
        fpd: metrics.contains(&MetricName::Fpd),
    };
    if !want.frd && !want.fpd {
        return Ok(());
    }
    for (files, dir) in [(gen_files, &a.generated), (ref_files, &a.reference)] {
        if files.len() < 2 {
            bail!(
                "frd / fpd need at least 2 scans per folder (a covariance), {} has {}",
                dir.display(),
                files.len()
            );
        }
    }
    let nets = eval_features::load_nets(a.feature_nets.as_deref())?;
    let g = eval_features::set_features(&nets, gen_files, "generated", want)?;
    let r = eval_features::set_features(&nets, ref_files, "reference", want)?;
    let dirs = (a.generated.as_path(), a.reference.as_path());
    let mut push = |name: String, v: f64| {
        report.metrics.push(MetricValue {
            name,
            protocol: Protocol::Frechet,
            region: Region::All,
            value: v,
            generated: gen_files.len(),
            reference: ref_files.len(),
            paper_scale: None,
        })
    };
    if let (Some(gs), Some(rs)) = (&g.range, &r.range) {
        let v = eval_features::frechet(gs, rs, "frd", dirs)?;
        push(format!("frd ({})", nets.frd_protocol()), v);
    }
    if let (Some(gs), Some(rs)) = (&g.point, &r.point) {
        let v = eval_features::frechet(gs, rs, "fpd", dirs)?;
        push(format!("fpd ({})", nets.fpd_protocol()), v);
    }
    Ok(())
}

fn indexes(scans: &[ScanSummary], files: &[PathBuf], region: Region) -> Result<Vec<PointIndex>> {
    scans
        .par_iter()
        .enumerate()
        .map(|(i, s)| {
            let pts = veila_metrics::filter_region(points_of(s), region);
            if pts.is_empty() {
                bail!("{}: no points in region {region}", file_label(files, i));
            }
            PointIndex::build(&pts, "scan").with_context(|| file_label(files, i))
        })
        .collect()
}

fn check_pairing(
    gen_files: &[PathBuf],
    ref_files: &[PathBuf],
    gdir: &Path,
    rdir: &Path,
) -> Result<()> {
    let names = |files: &[PathBuf]| -> BTreeMap<String, ()> {
        files
            .iter()
            .map(|f| {
                (
                    f.file_name()
                        .map(|n| n.to_string_lossy().into_owned())
                        .unwrap_or_default(),
                    (),
                )
            })
            .collect()
    };
    let (g, r) = (names(gen_files), names(ref_files));
    if let Some(missing) = g.keys().find(|k| !r.contains_key(*k)) {
        bail!(
            "chamfer pairs scans by file name: {} has {missing} but {} does not ({} vs {} scans)",
            gdir.display(),
            rdir.display(),
            gen_files.len(),
            ref_files.len()
        );
    }
    if let Some(missing) = r.keys().find(|k| !g.contains_key(*k)) {
        bail!(
            "chamfer pairs scans by file name: {} has {missing} but {} does not ({} vs {} scans)",
            rdir.display(),
            gdir.display(),
            ref_files.len(),
            gen_files.len()
        );
    }
    Ok(())
}

fn print_table(report: &MetricReport) {
    println!(
        "{:<10} {:<10} {:<6} {:>16} {:>14} {:>6} {:>6}",
        "metric", "protocol", "region", "value", "paper scale", "gen", "ref"
    );
    for m in &report.metrics {
        let scaled = m
            .paper_scale
            .map(|s| format!("{:.4} (x{s:.0e})", m.value * s))
            .unwrap_or_default();
        println!(
            "{:<10} {:<10} {:<6} {:>16.8e} {:>14} {:>6} {:>6}",
            m.name,
            m.protocol.name(),
            m.region.name(),
            m.value,
            scaled,
            m.generated,
            m.reference
        );
    }
}

fn write_json(path: &Path, report: &MetricReport) -> Result<()> {
    let mut text = serde_json::to_string_pretty(report)?;
    text.push('\n');
    veila_data::atomic::write_atomic(path, text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// A 2-D `.npy` feature matrix as `f64`, row-major.
fn read_npy_matrix(path: &Path) -> Result<(Vec<f64>, usize, usize)> {
    let file =
        std::fs::File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
    let npy = npyz::NpyFile::new(std::io::BufReader::new(file))
        .with_context(|| format!("{}: not a valid .npy file", path.display()))?;
    let shape = npy.shape().to_vec();
    if shape.len() != 2 {
        bail!(
            "{}: expected a 2-D array (samples x features), got shape {shape:?}",
            path.display()
        );
    }
    let (rows, cols) = (shape[0] as usize, shape[1] as usize);
    if rows == 0 || cols == 0 {
        bail!(
            "{}: the feature matrix is empty (shape {shape:?})",
            path.display()
        );
    }
    let order = npy.order();
    let dtype = npy.dtype();
    let data: Vec<f64> = match &dtype {
        npyz::DType::Plain(ts)
            if ts.type_char() == npyz::TypeChar::Float && ts.size_field() == 4 =>
        {
            npy.into_vec::<f32>()
                .with_context(|| format!("{}: reading f32 data", path.display()))?
                .into_iter()
                .map(f64::from)
                .collect()
        }
        npyz::DType::Plain(ts)
            if ts.type_char() == npyz::TypeChar::Float && ts.size_field() == 8 =>
        {
            npy.into_vec::<f64>()
                .with_context(|| format!("{}: reading f64 data", path.display()))?
        }
        other => bail!(
            "{}: unsupported dtype {}; expected float32 or float64",
            path.display(),
            other.descr()
        ),
    };
    if data.len() != rows * cols {
        bail!(
            "{}: expected {} values for shape {shape:?}, found {}",
            path.display(),
            rows * cols,
            data.len()
        );
    }
    let data = match order {
        npyz::Order::C => data,
        npyz::Order::Fortran => {
            let mut c = vec![0.0; rows * cols];
            for j in 0..cols {
                for i in 0..rows {
                    c[i * cols + j] = data[j * rows + i];
                }
            }
            c
        }
    };
    if let Some(k) = data.iter().position(|v| !v.is_finite()) {
        bail!(
            "{}: non-finite value at row {}, column {}",
            path.display(),
            k / cols,
            k % cols
        );
    }
    Ok((data, rows, cols))
}

fn run_fd(a: FdArgs) -> Result<()> {
    let (fa, ra, ca) = read_npy_matrix(&a.a)?;
    let (fb, rb, cb) = read_npy_matrix(&a.b)?;
    if ca != cb {
        bail!(
            "{} has {ca} feature columns but {} has {cb}",
            a.a.display(),
            a.b.display()
        );
    }
    for (rows, p) in [(ra, &a.a), (rb, &a.b)] {
        if rows < 2 {
            bail!(
                "{}: a covariance needs at least 2 rows (samples), got {rows}",
                p.display()
            );
        }
    }
    let (sa, sb) = rayon::join(
        || FeatureStats::from_rows(&fa, ca, "a"),
        || FeatureStats::from_rows(&fb, cb, "b"),
    );
    let (sa, sb) = (
        sa.with_context(|| a.a.display().to_string())?,
        sb.with_context(|| a.b.display().to_string())?,
    );
    let method = match a.newton_schulz {
        Some(iterations) => SqrtMethod::NewtonSchulz { iterations },
        None => SqrtMethod::Eigen,
    };
    let v = fd::frechet_distance_with(&sa, &sb, method)?;
    let report = MetricReport {
        metrics: vec![MetricValue {
            name: "fd".into(),
            protocol: Protocol::Frechet,
            region: Region::All,
            value: v,
            generated: rb,
            reference: ra,
            paper_scale: None,
        }],
    };
    // the file first, then the table: a reader that goes away early (`| head`) cannot cost the JSON
    if let Some(path) = &a.json {
        write_json(path, &report)?;
    }
    print_table(&report);
    Ok(())
}
