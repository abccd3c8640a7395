//! `veila eval` (distribution and point metrics between two folders of scans) and `veila fd` (Fréchet
//! distance between two feature matrices stored as `.npy`). Both print a table and optionally write JSON
//! `{"metrics": [...]}` atomically.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::eval_features;
use crate::staging::{self, Inputs, check_ext};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use glam::Vec3;
use rayon::prelude::*;

use veila_metrics::crossmodal::{
    DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency, cm_semantic_consistency,
};
use veila_metrics::{
    MetricReport, MetricValue, Protocol, Region,
    bev::{BevConfig, BevHistogram, SparseBevHistogram, bev_histogram_sparse},
    chamfer, dist,
    fd::{self, FeatureStats, SqrtMethod},
    lidm::{self, LidmBevConfig},
    nn::PointIndex,
    protocol::{PeerProtocol, PeerSummary},
};
use veila_nn::encoders::dinov2::{DepthAnythingV2, DepthKind};
use veila_nn::encoders::kind::EncoderKind;
use veila_nn::encoders::mit::SegFormer;
use veila_nn::encoders::preprocess::ImageProcessor;

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

/// Metrics `veila eval` can compute.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, ValueEnum)]
pub(crate) enum MetricName {
    /// The --protocol's JSD after its whole pipeline (R2DM / Text2LiDAR / LiDARGen: summed 100 x 100
    /// BEV histograms; LiDM: summed 0.05 m occupancy).
    Jsd,
    /// The --protocol's MMD after its whole pipeline (R2DM / Text2LiDAR: Gaussian kernel, Frobenius,
    /// printed x 1e4; LiDARGen: spectral norm; LiDM: minimum matching 2-D Chamfer, printed x 1e4).
    Mmd,
    /// R2DM's BEV JSD on the raw points (no projection, no range caps).
    JsdRaw,
    /// R2DM's BEV MMD on the raw points (no projection, no range caps).
    MmdRaw,
    /// LiDARGen's spectral-norm BEV MMD on the raw points (O(N^2) SVDs).
    MmdLidargenRaw,
    /// LiDM's minimum matching distance on the raw points, 64-beam grid (+-50 m).
    MmdLidmRaw,
    /// LiDM's minimum matching distance on the raw points, 32-beam nuScenes grid (+-30 m).
    MmdLidmNuscenesRaw,
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
    /// Cross-modal depth consistency (the paper's CM-DC): each generated scan's points projected into
    /// its camera (--calib) against a depth map (--depth-maps), AbsRel after --depth-alignment,
    /// averaged over the scans; the camera's field of view only.
    CmDc,
    /// Cross-modal semantic consistency (the paper's CM-SC): the percentage of generated points whose
    /// class from the built-in range segmentation net (SemanticKITTI train ids) equals the class map's
    /// (--semantic-maps) where they project; averaged over the scans.
    CmSc,
}

/// How CM-DC aligns a depth map to the scan's depths.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum AlignmentArg {
    /// Scale by median(scan depth) / median(map): relative monocular depth (the paper's protocol).
    Median,
    /// Scale and shift by least squares (MiDaS-style).
    LeastSquares,
    /// None: metric depth maps.
    None,
    /// Scale and shift of the map to inverse depth by least squares: relative disparity maps
    /// (Depth-Anything-V2's relative checkpoints, MiDaS).
    Disparity,
}

impl From<AlignmentArg> for DepthAlignment {
    fn from(a: AlignmentArg) -> Self {
        match a {
            AlignmentArg::Median => DepthAlignment::Median,
            AlignmentArg::LeastSquares => DepthAlignment::LeastSquares,
            AlignmentArg::None => DepthAlignment::None,
            AlignmentArg::Disparity => DepthAlignment::Disparity,
        }
    }
}

/// The id space of --semantic-maps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum SemanticIdsArg {
    /// SemanticKITTI train ids (0 = ignored, 1..=19).
    Train,
    /// SemanticKITTI raw ids (10 car, 40 road, ...), mapped to train ids by its learning map (what
    /// `veila simulate` writes to `semantic_2/`).
    Raw,
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
    /// Folder of generated scans (.bin, .pcd.bin, .ply or range .exr; format detected per file), or of
    /// the peer's own sample sets (.npy / .npz range images in the --protocol's layout).
    #[arg(long)]
    generated: PathBuf,
    /// Folder of reference scans (same formats).
    #[arg(long)]
    reference: PathBuf,
    /// Comma-separated metrics.
    #[arg(long, value_delimiter = ',', default_value = "jsd,mmd")]
    metrics: Vec<MetricName>,
    /// The peer pipeline of `jsd` and `mmd` (projection to its range-image grid, range caps, metric).
    #[arg(long, value_enum, default_value = "r2dm")]
    protocol: ProtocolArg,
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
    /// Replace existing --json / --report files (never an input).
    #[arg(long)]
    force: bool,
    /// cm-dc / cm-sc: the generated scans' KITTI calibration (camera image_2): one file for every
    /// scan, or a folder with `<scan stem>.txt` per scan (e.g. `veila simulate`'s `calib/`).
    #[arg(long)]
    calib: Option<PathBuf>,
    /// cm-dc: a folder with a depth map per generated scan, `<scan stem>.png` (16-bit, metres x 256,
    /// 0 = none: the KITTI convention, `veila simulate`'s `depth_2/`) or `<scan stem>.npy` (float
    /// H x W, e.g. a monocular network's depth; not disparity).
    #[arg(long)]
    depth_maps: Option<PathBuf>,
    /// cm-dc: how each depth map is aligned to the scan's depths before AbsRel.
    #[arg(long, value_enum, default_value = "median")]
    depth_alignment: AlignmentArg,
    /// cm-sc: a folder with a class map per generated scan, `<scan stem>.png` (8- or 16-bit
    /// greyscale class ids; e.g. a SegFormer's classes mapped to SemanticKITTI ids).
    #[arg(long)]
    semantic_maps: Option<PathBuf>,
    /// cm-sc: the id space of --semantic-maps.
    #[arg(long, value_enum, default_value = "train")]
    semantic_ids: SemanticIdsArg,
    /// cm-dc / cm-sc with networks instead of map files: a folder with the camera image of each
    /// generated scan, `<scan stem>.png` (e.g. `veila simulate`'s `image_2/`).
    #[arg(long)]
    images: Option<PathBuf>,
    /// cm-dc: predict each image's depth with Depth-Anything-V2 as the paper does, `KIND=PATH`
    /// (`depth-anything-v2-small|base|large`, PATH its Hugging Face `model.safetensors`; the
    /// reference processor and post-processing). A relative checkpoint's inverse depth is aligned to
    /// the points' in disparity space; for a metric one pass --depth-model-max-m.
    #[arg(long, value_name = "KIND=PATH")]
    depth_model: Option<String>,
    /// cm-dc: --depth-model is a metric checkpoint (`Metric-*-hf`) with this max depth in metres
    /// (80 for the outdoor ones); its depth is compared as --depth-alignment says.
    #[arg(long, value_name = "M")]
    depth_model_max_m: Option<f32>,
    /// cm-sc: segment each image with SegFormer, `KIND=PATH` (`segformer-b0` .. `-b5`, PATH a
    /// Cityscapes checkpoint's `model.safetensors`, 1024 x 1024 processor); its 19 classes are
    /// mapped to SemanticKITTI's (sky ignored).
    #[arg(long, value_name = "KIND=PATH")]
    semantic_model: Option<String>,
    /// cm-dc / cm-sc: the camera image's size, WIDTHxHEIGHT, when the maps have another resolution
    /// (default: each map's own size).
    #[arg(long, value_parser = parse_size)]
    image_size: Option<(u32, u32)>,
}

fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected WIDTHxHEIGHT, e.g. 1242x375"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|&n| (1..=65_536).contains(&n))
            .ok_or_else(|| format!("`{s}`: sizes are whole numbers from 1 to 65536"))
    };
    Ok((parse(w)?, parse(h)?))
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

fn is_scan_file(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    name.ends_with(".bin") || name.ends_with(".ply") || name.ends_with(".exr")
}

/// Scan and sample files of a folder, sorted by name. A pickle in the folder is an error naming it.
fn list_scans(dir: &Path, what: &str) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir)
        .with_context(|| format!("{what} folder {}: cannot read", dir.display()))?;
    let mut files = Vec::new();
    for e in entries {
        let e = e.with_context(|| format!("{what} folder {}: cannot list", dir.display()))?;
        let p = e.path();
        if !p.is_file() {
            continue;
        }
        veila_data::peer_samples::refuse_pickle(&p)?;
        if is_scan_file(&p) || veila_data::peer_samples::is_sample_file(&p) {
            files.push(p);
        }
    }
    files.sort();
    if files.is_empty() {
        bail!(
            "{what} folder {} has no scans (.bin, .pcd.bin, .ply, .exr) or sample sets (.npy, .npz)",
            dir.display()
        );
    }
    Ok(files)
}

/// What `veila eval` keeps of each scan: per-region summaries are computed while loading, and the points
/// themselves only when a point metric (mmd-cd, chamfer) needs them, so memory stays small for large sets.
struct ScanSummary {
    /// `file` or `file[i]` for the i-th sample of a sample set.
    label: String,
    points: Option<Vec<Vec3>>,
    /// Sparse R2DM BEV histogram of the raw points per requested region.
    hist: Vec<SparseBevHistogram>,
    /// LiDM occupancy of the raw points per requested region (64-beam grid).
    occ: Vec<lidm::BevOccupancy>,
    /// LiDM occupancy of the raw points per requested region (32-beam grid).
    occ_nus: Vec<lidm::BevOccupancy>,
    /// The --protocol's summary after its pipeline, per requested region.
    peer: Vec<PeerSummary>,
}

#[derive(Debug, Clone, Copy)]
struct Needs {
    points: bool,
    hist: bool,
    occ: bool,
    occ_nus: bool,
    peer: bool,
}

impl Needs {
    /// Whether anything but the protocol pipeline is asked for (sample sets have no raw points).
    fn raw(&self) -> bool {
        self.points || self.hist || self.occ || self.occ_nus
    }
}

fn summarise_raw(
    xyz: Vec<Vec3>,
    label: String,
    regions: &[Region],
    needs: Needs,
    protocol: PeerProtocol,
) -> Result<ScanSummary> {
    let (bev, lcfg, lnus) = (
        BevConfig::r2dm(),
        LidmBevConfig::kitti(),
        LidmBevConfig::nuscenes(),
    );
    let prepared = if needs.peer {
        Some(
            protocol
                .prepare_scan(&xyz, "scan")
                .with_context(|| label.clone())?,
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
    };
    for &r in regions {
        if needs.hist {
            s.hist.push(
                bev_histogram_sparse(&xyz, &bev, r, "scan").with_context(|| s.label.clone())?,
            );
        }
        if needs.occ {
            s.occ.push(
                lidm::lidm_bev_occupancy(&xyz, &lcfg, r, "scan")
                    .with_context(|| s.label.clone())?,
            );
        }
        if needs.occ_nus {
            s.occ_nus.push(
                lidm::lidm_bev_occupancy(&xyz, &lnus, r, "scan")
                    .with_context(|| s.label.clone())?,
            );
        }
        if let Some(p) = &prepared {
            s.peer.push(
                protocol
                    .summarise(p, r, "scan")
                    .with_context(|| s.label.clone())?,
            );
        }
    }
    s.points = needs.points.then_some(xyz);
    Ok(s)
}

/// The samples of one peer sample set (.npy / .npz), each reduced by the protocol's pipeline.
fn summarise_samples(
    f: &Path,
    regions: &[Region],
    protocol: PeerProtocol,
) -> Result<Vec<ScanSummary>> {
    let arrays = veila_data::peer_samples::read_sample_arrays(f)?;
    let many = arrays.len() > 1;
    let mut out = Vec::new();
    for a in arrays {
        let (n, c, h, w) = protocol
            .split_samples(&a.shape)
            .with_context(|| format!("{}: array {}", f.display(), a.name))?;
        let per = c * h * w;
        for i in 0..n {
            let label = if many {
                format!("{}[{}][{i}]", f.display(), a.name)
            } else {
                format!("{}[{i}]", f.display())
            };
            let pts = protocol
                .points_from_image(&a.data[i * per..(i + 1) * per], c, h, w, "sample")
                .with_context(|| label.clone())?;
            let peer = regions
                .iter()
                .map(|&r| protocol.summarise(&pts, r, "sample"))
                .collect::<std::result::Result<Vec<_>, _>>()
                .with_context(|| label.clone())?;
            out.push(ScanSummary {
                label,
                points: None,
                hist: Vec::new(),
                occ: Vec::new(),
                occ_nus: Vec::new(),
                peer,
            });
        }
    }
    if out.is_empty() {
        bail!("{}: the sample set holds no sample", f.display());
    }
    Ok(out)
}

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
                summarise_samples(f, regions, protocol)?
            } else {
                let loaded = veila_data::scan::read_points_with(f, veila_data::scan::Keep::FiniteXyz)
                    .with_context(|| format!("reading {}", f.display()))?;
                if loaded.cloud.xyz.is_empty() {
                    bail!("{}: the scan has no (finite) points", f.display());
                }
                vec![summarise_raw(loaded.cloud.xyz, label, regions, needs, protocol)?]
            };
            pb.inc(1);
            Ok(s)
        })
        .collect();
    pb.finish_and_clear();
    Ok(out?.into_iter().flatten().collect())
}

fn label_of(set: &[ScanSummary], i: usize) -> String {
    set.get(i)
        .map(|s| s.label.clone())
        .unwrap_or_else(|| format!("scan {i}"))
}

/// Turns the library's "generated scan 3" into the file name.
fn explain(
    err: veila_metrics::Error,
    generated: &[ScanSummary],
    reference: &[ScanSummary],
) -> anyhow::Error {
    if let veila_metrics::Error::NoPointsInWindow { what, window } = &err {
        for (prefix, set) in [
            ("generated scan ", generated),
            ("reference scan ", reference),
        ] {
            if let Some(i) = what
                .strip_prefix(prefix)
                .and_then(|s| s.parse::<usize>().ok())
            {
                return anyhow::anyhow!(
                    "{}: no point inside the {window} window (this metric normalises every scan on its own)",
                    label_of(set, i)
                );
            }
        }
    }
    anyhow::Error::new(err)
}

/// Up to this many scans per set the R2DM MMD uses dense histograms (GEMM, faster); above, sparse ones
/// (the same value up to rounding, ~9x less memory).
const DENSE_MMD_MAX_SCANS: usize = 2000;

fn points_of(s: &ScanSummary) -> &[Vec3] {
    s.points.as_deref().unwrap_or(&[])
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
    check_crossmodal_args(&a, &metrics, &gen_files)?;
    let regions: Vec<Region> = a.regions.iter().map(|&r| Region::from(r)).collect();
    let needs = Needs {
        points: metrics
            .iter()
            .any(|m| matches!(m, MetricName::MmdCd | MetricName::Chamfer)),
        hist: metrics.iter().any(|m| {
            matches!(
                m,
                MetricName::JsdRaw | MetricName::MmdRaw | MetricName::MmdLidargenRaw
            )
        }),
        occ: metrics.contains(&MetricName::MmdLidmRaw),
        occ_nus: metrics.contains(&MetricName::MmdLidmNuscenesRaw),
        peer: metrics
            .iter()
            .any(|m| matches!(m, MetricName::Jsd | MetricName::Mmd)),
    };
    let generated = load_scans(&gen_files, "generated", &regions, needs, protocol)?;
    let reference = load_scans(&ref_files, "reference", &regions, needs, protocol)?;

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
    let pb = crate::progress::bar((metrics.len() * a.regions.len()) as u64, "metrics");
    for (ri, &region) in regions.iter().enumerate() {
        let sparse = |set: &[ScanSummary]| -> Vec<SparseBevHistogram> {
            set.iter().map(|s| s.hist[ri].clone()).collect()
        };
        let dense = |set: &[ScanSummary]| -> Vec<BevHistogram> {
            set.iter().map(|s| s.hist[ri].to_dense()).collect()
        };
        // the protocol's two metrics are computed together
        let peer_scores = if needs.peer {
            let pg: Vec<PeerSummary> = generated.iter().map(|s| s.peer[ri].clone()).collect();
            let pr: Vec<PeerSummary> = reference.iter().map(|s| s.peer[ri].clone()).collect();
            Some(
                protocol
                    .score(&pg, &pr)
                    .map_err(|e| explain(e, &generated, &reference))
                    .with_context(|| format!("protocol {protocol}, region {region}"))?,
            )
        } else {
            None
        };
        for &m in &metrics {
            pb.set_message(format!("{m:?} {region}"));
            let ex = |e| explain(e, &generated, &reference);
            let v = match m {
                // feature and cross-modal metrics: computed once below
                MetricName::Frd | MetricName::Fpd | MetricName::CmDc | MetricName::CmSc => {
                    pb.inc(1);
                    continue;
                }
                MetricName::Jsd | MetricName::Mmd => {
                    let want = if m == MetricName::Jsd { "jsd" } else { "mmd" };
                    let pm = peer_scores
                        .iter()
                        .flatten()
                        .find(|p| p.name == want)
                        .expect("the protocol computes jsd and mmd");
                    value(
                        want,
                        protocol.metric_protocol(),
                        region,
                        pm.value,
                        pm.paper_scale,
                    )
                }
                MetricName::JsdRaw => value(
                    "jsd-raw",
                    Protocol::R2dm,
                    region,
                    dist::jsd(&sparse(&generated), &sparse(&reference)).map_err(ex)?,
                    None,
                ),
                MetricName::MmdRaw => {
                    let mmd = if ng.max(nr) <= DENSE_MMD_MAX_SCANS {
                        dist::mmd_r2dm_dense(
                            &dense(&generated),
                            &dense(&reference),
                            dist::MMD_SIGMA,
                        )
                    } else {
                        dist::mmd_r2dm_sparse(
                            &sparse(&generated),
                            &sparse(&reference),
                            dist::MMD_SIGMA,
                        )
                    };
                    value(
                        "mmd-raw",
                        Protocol::R2dm,
                        region,
                        mmd.map_err(ex)?,
                        Some(dist::MMD_PAPER_SCALE),
                    )
                }
                MetricName::MmdLidargenRaw => value(
                    "mmd-lidargen-raw",
                    Protocol::Lidargen,
                    region,
                    dist::mmd_lidargen(&dense(&generated), &dense(&reference), dist::MMD_SIGMA)
                        .map_err(ex)?,
                    None,
                ),
                MetricName::MmdLidmRaw | MetricName::MmdLidmNuscenesRaw => {
                    let nus = m == MetricName::MmdLidmNuscenesRaw;
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
                        if nus {
                            "mmd-lidm-nuscenes-raw"
                        } else {
                            "mmd-lidm-raw"
                        },
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
                MetricName::MmdCd => {
                    let ig = indexes(&generated, region)?;
                    let ir = indexes(&reference, region)?;
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
                    for (g, r) in generated.iter().zip(&reference) {
                        let gp = veila_metrics::filter_region(points_of(g), region);
                        let rp = veila_metrics::filter_region(points_of(r), region);
                        if gp.is_empty() || rp.is_empty() {
                            bail!(
                                "{} / {}: no points in region {region}; the Chamfer distance needs points on both sides",
                                g.label,
                                r.label
                            );
                        }
                        sum += chamfer::chamfer_distance(&gp, &rp)?.value();
                    }
                    value(
                        "chamfer",
                        Protocol::Pytorch3d,
                        region,
                        sum / generated.len() as f64,
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
    crossmodal_metrics(&a, &metrics, &gen_files, &mut report)?;
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

fn indexes(scans: &[ScanSummary], region: Region) -> Result<Vec<PointIndex>> {
    scans
        .par_iter()
        .map(|s| {
            let pts = veila_metrics::filter_region(points_of(s), region);
            if pts.is_empty() {
                bail!("{}: no points in region {region}", s.label);
            }
            PointIndex::build(&pts, "scan").with_context(|| s.label.clone())
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
    let mut inputs = Inputs::new();
    inputs.add(&a.a).add(&a.b);
    check_report_outputs(a.json.as_deref(), None, &inputs, a.force)?;
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

/// What the cross-modal metrics need, checked before any work: a calibration and the maps, and
/// scans (not peer sample sets) to project.
fn check_crossmodal_args(
    a: &EvalArgs,
    metrics: &[MetricName],
    gen_files: &[PathBuf],
) -> Result<()> {
    let (dc, sc) = (
        metrics.contains(&MetricName::CmDc),
        metrics.contains(&MetricName::CmSc),
    );
    if !dc && !sc {
        return Ok(());
    }
    if a.calib.is_none() {
        bail!("cm-dc / cm-sc project the generated points into the camera: pass --calib FILE|DIR");
    }
    match (dc, a.depth_maps.is_some(), a.depth_model.is_some()) {
        (true, false, false) => bail!(
            "cm-dc compares with depth maps: pass --depth-maps DIR (<scan stem>.png or .npy), or \
             --depth-model depth-anything-v2-small=PATH with --images DIR"
        ),
        (_, true, true) => bail!("pass either --depth-maps or --depth-model, not both"),
        _ => {}
    }
    match (sc, a.semantic_maps.is_some(), a.semantic_model.is_some()) {
        (true, false, false) => bail!(
            "cm-sc compares with class maps: pass --semantic-maps DIR (<scan stem>.png), or \
             --semantic-model segformer-b0=PATH with --images DIR"
        ),
        (_, true, true) => bail!("pass either --semantic-maps or --semantic-model, not both"),
        _ => {}
    }
    if (a.depth_model.is_some() || a.semantic_model.is_some()) && a.images.is_none() {
        bail!(
            "--depth-model / --semantic-model run on the camera images: pass --images DIR (<scan stem>.png)"
        );
    }
    if let Some(m) = a.depth_model_max_m
        && !(m.is_finite() && m > 0.0)
    {
        bail!("--depth-model-max-m must be a positive number of metres, got {m}");
    }
    if let Some(f) = gen_files
        .iter()
        .find(|f| veila_data::peer_samples::is_sample_file(f))
    {
        bail!(
            "{}: cm-dc / cm-sc project scans into the camera; peer sample sets have no camera",
            f.display()
        );
    }
    Ok(())
}

/// A scan file's name without its point-format extension (`000001.bin`, `x.pcd.bin` -> `000001`, `x`).
fn scan_stem(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let lower = name.to_lowercase();
    for ext in [".pcd.bin", ".bin", ".ply", ".exr"] {
        if lower.ends_with(ext) {
            return name[..name.len() - ext.len()].to_string();
        }
    }
    name
}

/// `dir/<stem>.<ext>` for the first extension that exists, or an error naming what was looked for.
fn companion(dir: &Path, stem: &str, exts: &[&str], what: &str, scan: &Path) -> Result<PathBuf> {
    for ext in exts {
        let p = dir.join(format!("{stem}.{ext}"));
        if p.is_file() {
            return Ok(p);
        }
    }
    bail!(
        "{}: no {what} for it: expected {} in {}",
        scan.display(),
        exts.iter()
            .map(|e| format!("{stem}.{e}"))
            .collect::<Vec<_>>()
            .join(" or "),
        dir.display()
    )
}

/// `KIND=PATH` of --depth-model / --semantic-model.
fn split_model_arg<'s>(flag: &str, spec: &'s str) -> Result<(EncoderKind, &'s Path)> {
    let (kind, path) = spec
        .split_once('=')
        .with_context(|| format!("{flag} `{spec}`: expected KIND=PATH"))?;
    let kind: EncoderKind = kind
        .parse()
        .map_err(|e: String| anyhow::anyhow!("{flag}: {e}"))?;
    Ok((kind, Path::new(path)))
}

/// Depth-Anything-V2 with its head (relative, or metric with `max_m`); the flag says metric.
fn load_depth_model(
    spec: &str,
    max_m: Option<f32>,
    device: &candle_core::Device,
) -> Result<(DepthAnythingV2, bool)> {
    let (kind, path) = split_model_arg("--depth-model", spec)?;
    let mut cfg = kind.depth_anything_config().with_context(|| {
        format!("--depth-model: `{kind}` is not a Depth-Anything-V2 kind (depth-anything-v2-small|base|large)")
    })?;
    if let Some(m) = max_m {
        cfg.depth_estimation_type = DepthKind::Metric;
        cfg.max_depth = m;
    }
    let model =
        DepthAnythingV2::load(&cfg, path, candle_core::DType::F32, device).with_context(|| {
            format!(
                "--depth-model {kind}: {} (the `model.safetensors` of {})",
                path.display(),
                kind.hub_repo().unwrap_or("-")
            )
        })?;
    Ok((model, max_m.is_some()))
}

/// SegFormer with its Cityscapes head.
fn load_semantic_model(spec: &str, device: &candle_core::Device) -> Result<SegFormer> {
    let (kind, path) = split_model_arg("--semantic-model", spec)?;
    let cfg = kind.segformer_cityscapes_config().with_context(|| {
        format!("--semantic-model: `{kind}` is not a SegFormer kind (segformer-b0 .. segformer-b5)")
    })?;
    SegFormer::load(&cfg, path, candle_core::DType::F32, device).with_context(|| {
        format!(
            "--semantic-model {kind}: {} (the `model.safetensors` of {})",
            path.display(),
            kind.hub_repo().unwrap_or("-")
        )
    })
}

/// CM-DC and CM-SC (when requested) over the generated scans, appended to `report` (region front:
/// the camera's field of view; the value is the mean over the scans that have points in it).
fn crossmodal_metrics(
    a: &EvalArgs,
    metrics: &[MetricName],
    gen_files: &[PathBuf],
    report: &mut MetricReport,
) -> Result<()> {
    let (want_dc, want_sc) = (
        metrics.contains(&MetricName::CmDc),
        metrics.contains(&MetricName::CmSc),
    );
    if !want_dc && !want_sc {
        return Ok(());
    }
    let calib = a
        .calib
        .as_deref()
        .expect("checked by check_crossmodal_args");
    let nets = if want_sc {
        Some(eval_features::load_nets(a.feature_nets.as_deref())?)
    } else {
        None
    };
    // chosen once: on a CUDA build it opens the GPU
    let device = crate::model::device()?;
    let depth_model = match (&a.depth_model, want_dc) {
        (Some(spec), true) => Some(load_depth_model(spec, a.depth_model_max_m, &device)?),
        _ => None,
    };
    let semantic_model = match (&a.semantic_model, want_sc) {
        (Some(spec), true) => Some(load_semantic_model(spec, &device)?),
        _ => None,
    };
    let image_for = |stem: &str, f: &Path| -> Result<(PathBuf, veila_data::image::RgbImage)> {
        let dir = a.images.as_deref().expect("checked");
        let p = companion(dir, stem, &["png", "jpg"], "camera image", f)?;
        let img = veila_data::image_io::read_rgb_image(&p)?;
        Ok((p, img))
    };
    let (mut dc, mut sc) = (Vec::new(), Vec::new());
    let pb = crate::progress::bar(gen_files.len() as u64, "cross-modal");
    for f in gen_files {
        let stem = scan_stem(f);
        let calib_file = if calib.is_dir() {
            companion(calib, &stem, &["txt"], "calibration", f)?
        } else {
            calib.to_path_buf()
        };
        let loaded = veila_data::scan::read_points(f)?;
        let cloud = &loaded.cloud;
        let camera_for = |w: u32, h: u32| -> Result<veila_geom::PinholeCamera> {
            let (w, h) = a.image_size.unwrap_or((w, h));
            Ok(veila_data::weather::files::read_camera(&calib_file, w, h)?)
        };
        if want_dc {
            let (mp, map, alignment) = match &depth_model {
                Some((model, metric)) => {
                    let (p, img) = image_for(&stem, f)?;
                    let (w, h) = img.dimensions();
                    let data = model
                        .predict_depth_map_rgb8(
                            &ImageProcessor::depth_anything_v2(),
                            img.as_raw(),
                            h as usize,
                            w as usize,
                            &device,
                        )
                        .with_context(|| format!("{}: depth prediction", p.display()))?;
                    let alignment = if *metric {
                        a.depth_alignment.into()
                    } else {
                        DepthAlignment::Disparity
                    };
                    (
                        p,
                        veila_data::image_io::ImageMap {
                            width: w,
                            height: h,
                            data,
                        },
                        alignment,
                    )
                }
                None => {
                    let dir = a.depth_maps.as_deref().expect("checked");
                    let mp = companion(dir, &stem, &["png", "npy"], "depth map", f)?;
                    let map = veila_data::image_io::read_depth_map(&mp)?;
                    (mp, map, a.depth_alignment.into())
                }
            };
            let cam = camera_for(map.width, map.height)?;
            let m = Map2d::new(map.width, map.height, &map.data)
                .with_context(|| mp.display().to_string())?;
            match cm_depth_consistency(
                &cloud.xyz,
                &cam,
                &m,
                alignment,
                &ProjectionFilter::default(),
            ) {
                Ok(c) if c.abs_rel.is_finite() => dc.push(c.abs_rel),
                Ok(_) => tracing::warn!("{}: no point projects onto a depth value", f.display()),
                Err(e) => tracing::warn!("{}: cm-dc skipped: {e}", f.display()),
            }
        }
        if let Some(nets) = &nets {
            let (mp, map) = match &semantic_model {
                Some(model) => {
                    let (p, img) = image_for(&stem, f)?;
                    let (w, h) = img.dimensions();
                    let labels = model
                        .predict_label_map_rgb8(
                            &ImageProcessor::segformer(1024, 1024),
                            img.as_raw(),
                            h as usize,
                            w as usize,
                            &device,
                        )
                        .with_context(|| format!("{}: segmentation", p.display()))?;
                    let data = labels
                        .into_iter()
                        .map(veila_metrics::crossmodal::cityscapes_to_semantickitti)
                        .collect();
                    (
                        p,
                        veila_data::image_io::ImageMap {
                            width: w,
                            height: h,
                            data,
                        },
                    )
                }
                None => {
                    let dir = a.semantic_maps.as_deref().expect("checked");
                    let mp = companion(dir, &stem, &["png"], "class map", f)?;
                    let mut map = veila_data::image_io::read_label_map(&mp)?;
                    if a.semantic_ids == SemanticIdsArg::Train {
                        veila_metrics::crossmodal::check_train_ids(
                            &map.data,
                            &mp.display().to_string(),
                        )
                        .context("--semantic-ids train (pass --semantic-ids raw for raw ids)")?;
                    }
                    if a.semantic_ids == SemanticIdsArg::Raw {
                        for v in &mut map.data {
                            *v = u32::from(veila_data::sim::class::learning_id(
                                u16::try_from(*v).unwrap_or(0),
                            ));
                        }
                    }
                    (mp, map)
                }
            };
            let cam = camera_for(map.width, map.height)?;
            let (pts, labels) = nets.segment_points(&cloud.xyz, Some(&cloud.intensity))?;
            let m = Map2d::new(map.width, map.height, &map.data)
                .with_context(|| mp.display().to_string())?;
            let filter = ProjectionFilter {
                ignore_label: Some(0),
                ..ProjectionFilter::default()
            };
            match cm_semantic_consistency(&pts, &labels, &cam, &m, &filter) {
                Ok(c) if c.percent.is_finite() => sc.push(c.percent),
                Ok(_) => tracing::warn!("{}: no point projects onto a labelled pixel", f.display()),
                Err(e) => tracing::warn!("{}: cm-sc skipped: {e}", f.display()),
            }
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    for (want, name, vals) in [(want_dc, "cm-dc", &dc), (want_sc, "cm-sc (%)", &sc)] {
        if !want {
            continue;
        }
        if vals.is_empty() {
            bail!(
                "{name}: no generated scan has points in the camera's view with a map value there \
                 (check --calib and the maps)"
            );
        }
        report.metrics.push(MetricValue {
            name: name.into(),
            protocol: Protocol::Veila,
            region: Region::Front,
            value: mean(vals),
            generated: vals.len(),
            reference: 0,
            paper_scale: None,
        });
    }
    Ok(())
}
