//! `veila eval` (metrics between two folders of scans: `veila_metrics::suite`) and `veila fd` (Fréchet
//! distance of two `.npy` feature matrices); both print a table and may write JSON atomically.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use rayon::prelude::*;
use veila_metrics::fd::{self, FeatureStats, SqrtMethod};
use veila_metrics::protocol::PeerProtocol;
use veila_metrics::suite::{Needs, ScanSummary, score_sets};
use veila_metrics::{MetricName, MetricReport, MetricValue, Protocol, Region};

use crate::eval_crossmodal::{self, CrossModalArgs};
use crate::eval_features;
use crate::eval_files::list_scans;
use crate::eval_regions::RegionArg;
use crate::staging::{self, Inputs, check_ext};

/// Evaluation commands.
#[derive(Debug, Subcommand)]
pub(crate) enum EvalCmd {
    /// Score generated scans against reference scans, each metric named by its protocol, for the whole
    /// panorama and its front (x > 0) and rear (x <= 0) halves. `jsd` and `mmd` run a peer's whole
    /// pipeline (`--protocol`: its range-image projection, range caps, then its metric), so raw scans
    /// give the number the peer's scripts report; the `*-raw` metrics score the raw points instead.
    /// Generated folders may also hold the peers' own sample sets (.npy / .npz range images, read as
    /// the protocol's layout; pickles are refused). FRD and FPD: whole panorama only; their built-in
    /// networks are simulator-trained, so the values are not comparable with published FRD / FPD
    /// numbers.
    Eval(Box<EvalArgs>),
    /// Fréchet distance between two feature matrices (.npy, f32 or f64, one row per sample).
    Fd(FdArgs),
}

/// Whether `metrics` ask for CM-DC and CM-SC.
fn cross_modal(metrics: &[MetricName]) -> (bool, bool) {
    (
        metrics.contains(&MetricName::CmDc),
        metrics.contains(&MetricName::CmSc),
    )
}

/// The peer pipelines `jsd` and `mmd` follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum ProtocolArg {
    /// R2DM: 64 x 1024 grid (+3..-25 deg), nearest point per pixel, 1.45 <= r <= 80 and 0.5 < r < 63 m.
    R2dm,
    /// Text2LiDAR (R2DM's code): 32 x 1024 grid with the same +3..-25 deg rows.
    Text2lidar,
    /// LiDARGen: 64 x 1024, log-range clipped at 63 m, unprojected, 3 < r < 70 m; spectral-norm MMD.
    Lidargen,
    /// LiDM, 64-beam: 1 < r < 56 m, 64 x 1024 round trip; occupancy JSD and MMD over +-50 m.
    Lidm,
    /// LiDM, 32-beam nuScenes: 1 < r < 45 m, 32 x 1024 (+10..-30 deg) round trip; grids over +-30 m.
    LidmNuscenes,
}

impl From<ProtocolArg> for PeerProtocol {
    fn from(p: ProtocolArg) -> Self {
        match p {
            ProtocolArg::R2dm => PeerProtocol::R2dm,
            ProtocolArg::Text2lidar => PeerProtocol::Text2lidar,
            ProtocolArg::Lidargen => PeerProtocol::Lidargen,
            ProtocolArg::Lidm => PeerProtocol::Lidm,
            ProtocolArg::LidmNuscenes => PeerProtocol::LidmNuscenes,
        }
    }
}

#[derive(Debug, Args)]
pub(crate) struct EvalArgs {
    /// Folder of generated scans (.bin, .pcd.bin, .ply or range .exr; format detected per file), or of
    /// the peer's own sample sets (.npy / .npz range images in the --protocol's layout).
    #[arg(long)]
    generated: PathBuf,
    /// Folder of reference scans (same formats).
    #[arg(long)]
    reference: PathBuf,
    /// Comma-separated metrics.
    #[arg(long, value_delimiter = ',', default_value = "jsd,mmd",
          value_parser = crate::choices::metric_parser())]
    metrics: Vec<MetricName>,
    /// The peer pipeline of `jsd` and `mmd` (projection to its range-image grid, range caps, metric).
    #[arg(long, value_enum, default_value = "r2dm")]
    protocol: ProtocolArg,
    /// Comma-separated regions (default: all,front,rear, less a region no scan of a set reaches,
    /// such as the rear of scans cropped to a camera's view, with a note).
    #[arg(long, value_delimiter = ',')]
    regions: Option<Vec<RegionArg>>,
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
    /// Replace existing --json / --report files (never an input).
    #[arg(long)]
    force: bool,
    /// The cross-modal metrics' inputs.
    #[command(flatten)]
    crossmodal: CrossModalArgs,
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
    /// Newton-Schulz iterations, 1 to 1000, instead of the exact eigendecomposition (approximate).
    #[arg(long, value_parser = crate::bounds::int::<usize>(1, 1000))]
    newton_schulz: Option<usize>,
    /// Replace an existing --json file (never an input).
    #[arg(long)]
    force: bool,
}

pub(crate) fn run(cmd: EvalCmd) -> Result<()> {
    match cmd {
        EvalCmd::Eval(a) => run_eval(*a),
        EvalCmd::Fd(a) => run_fd(a),
    }
}

/// The scans and sample sets of `files`, each reduced to what the metrics need (in parallel).
fn load_scans(
    files: &[PathBuf],
    what: &str,
    regions: &[Region],
    needs: Needs,
    protocol: PeerProtocol,
) -> Result<Vec<ScanSummary>> {
    let pb = crate::progress::bar(files.len() as u64, what);
    let out: Result<Vec<Vec<ScanSummary>>> = files
        .par_iter()
        .map(|f| {
            let label = f.display().to_string();
            let s = if veila_data::peer_samples::is_sample_file(f) {
                if needs.raw() {
                    bail!(
                        "{}: a peer sample set has no raw points; only `jsd` and `mmd` (the --protocol \
                         pipeline) read it",
                        f.display()
                    );
                }
                let arrays = veila_data::peer_samples::read_sample_arrays(f)?;
                let many = arrays.len() > 1;
                let mut out = Vec::new();
                for a in arrays {
                    let label = if many {
                        format!("{label}[{}]", a.name)
                    } else {
                        label.clone()
                    };
                    out.extend(ScanSummary::of_sample_array(
                        &label, &a.shape, &a.data, regions, protocol,
                    )?);
                }
                if out.is_empty() {
                    bail!("{}: the sample set holds no sample", f.display());
                }
                out
            } else {
                let loaded = veila_data::scan::read_points_with(f, veila_data::scan::Keep::FiniteXyz)
                    .with_context(|| format!("reading {}", f.display()))?;
                if loaded.cloud.xyz.is_empty() {
                    bail!("{}: the scan has no (finite) points", f.display());
                }
                vec![ScanSummary::of_points(
                    loaded.cloud.xyz,
                    label,
                    regions,
                    needs,
                    protocol,
                )?]
            };
            pb.inc(1);
            Ok(s)
        })
        .collect();
    pb.finish_and_clear();
    Ok(out?.into_iter().flatten().collect())
}

/// Checks the `--json` / `--report` destinations before any work: named for their format, not an
/// input, not existing unless `force`, in an existing folder.
fn check_report_outputs(
    json: Option<&Path>,
    report: Option<&Path>,
    inputs: &Inputs,
    force: bool,
) -> Result<()> {
    if let Some(p) = json {
        check_ext(p, "--json", &["json"])?;
    }
    if let Some(p) = report {
        check_ext(p, "--report", &["html", "htm"])?;
        crate::report::check_output_dir(p)?;
    }
    let dests: Vec<&Path> = json.into_iter().chain(report).collect();
    staging::check_outputs(&dests, inputs, force, false)
}

fn json_bytes(report: &MetricReport) -> Result<Vec<u8>> {
    let mut text = serde_json::to_string_pretty(report)?;
    text.push('\n');
    Ok(text.into_bytes())
}

fn run_eval(a: EvalArgs) -> Result<()> {
    let gen_files = list_scans(&a.generated, "generated")?;
    let ref_files = list_scans(&a.reference, "reference")?;
    let mut inputs = Inputs::new();
    inputs.extend(&gen_files).extend(&ref_files);
    check_report_outputs(a.json.as_deref(), a.report.as_deref(), &inputs, a.force)?;
    let mut metrics = a.metrics.clone();
    metrics.sort();
    metrics.dedup();
    if metrics.is_empty() {
        bail!("--metrics is empty");
    }
    let protocol = PeerProtocol::from(a.protocol);
    let has_samples = |files: &[PathBuf]| {
        files
            .iter()
            .find(|f| veila_data::peer_samples::is_sample_file(f))
            .cloned()
    };
    if let Some(f) = has_samples(&gen_files).or_else(|| has_samples(&ref_files)) {
        if a.report.is_some() {
            bail!(
                "{}: --report draws scans, not peer sample sets; leave it out for sample sets",
                f.display()
            );
        }
        if metrics
            .iter()
            .any(|m| matches!(m, MetricName::Frd | MetricName::Fpd))
        {
            bail!(
                "{}: frd / fpd read scans, not peer sample sets; only `jsd` and `mmd` (the --protocol \
                 pipeline) read sample sets",
                f.display()
            );
        }
    }
    if metrics.contains(&MetricName::Chamfer) {
        check_pairing(&gen_files, &ref_files, &a.generated, &a.reference)?;
    }
    eval_crossmodal::check_args(&a.crossmodal, cross_modal(&metrics), &gen_files)?;
    let given = a
        .regions
        .as_deref()
        .map(|r| r.iter().map(|&r| Region::from(r)).collect());
    let regions: Vec<Region> = given.clone().unwrap_or_else(|| Region::ALL.to_vec());
    let set_metrics: Vec<MetricName> = metrics
        .iter()
        .copied()
        .filter(|m| m.is_set_metric())
        .collect();
    let needs = Needs::of(&set_metrics);
    let mut generated = load_scans(&gen_files, "generated", &regions, needs, protocol)?;
    let mut reference = load_scans(&ref_files, "reference", &regions, needs, protocol)?;
    let regions =
        crate::eval_regions::covered(given.is_some(), regions, &mut generated, &mut reference)?;
    let pb = crate::progress::bar((metrics.len() * regions.len()) as u64, "metrics");
    let mut report = score_sets(
        &set_metrics,
        &regions,
        &generated,
        &reference,
        protocol,
        |m, region| {
            pb.set_message(format!("{m:?} {region}"));
            pb.inc(1);
        },
    )
    .with_context(|| format!("protocol {protocol}"))?;
    pb.finish_and_clear();
    feature_metrics(&a, &metrics, &gen_files, &ref_files, &mut report)?;
    eval_crossmodal::metrics(
        &a.crossmodal,
        cross_modal(&metrics),
        a.feature_nets.as_deref(),
        &gen_files,
        &mut report,
    )?;
    // the files first (all or none), then the table: a reader that goes away early (`| head`)
    // cannot cost them
    let mut files = Vec::new();
    if let Some(path) = &a.json {
        files.push((path.clone(), json_bytes(&report)?));
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
        let bytes = html.to_html().into_bytes();
        tracing::info!(
            "report {}: {} images, {} bytes",
            path.display(),
            html.image_count(),
            bytes.len()
        );
        files.push((path.clone(), bytes));
    }
    staging::publish_files(&files, &inputs, a.force, false)?;
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
        "{:<10} {:<13} {:<6} {:>16} {:>14} {:>6} {:>6}",
        "metric", "protocol", "region", "value", "paper scale", "gen", "ref"
    );
    for m in &report.metrics {
        let scaled = m
            .paper_scale
            .map(|s| format!("{:.4} (x{s:.0e})", m.value * s))
            .unwrap_or_default();
        println!(
            "{:<10} {:<13} {:<6} {:>16.8e} {:>14} {:>6} {:>6}",
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

fn run_fd(a: FdArgs) -> Result<()> {
    let mut inputs = Inputs::new();
    inputs.add(&a.a).add(&a.b);
    check_report_outputs(a.json.as_deref(), None, &inputs, a.force)?;
    let (fa, ra, ca) = veila_data::npy::read_matrix_f64(&a.a)?;
    let (fb, rb, cb) = veila_data::npy::read_matrix_f64(&a.b)?;
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
        staging::publish_files(
            &[(path.clone(), json_bytes(&report)?)],
            &inputs,
            a.force,
            false,
        )?;
    }
    print_table(&report);
    Ok(())
}
