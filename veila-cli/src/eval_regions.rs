//! Which regions `veila eval` scores. Scans cropped to a camera's view (KITTI's `velodyne_reduced`,
//! the `000008` sample of the help) have no point in the `rear` region, where the set metrics would
//! compare empty histograms: by default such a region is left out with a note; when `--regions`
//! names it, the error says which regions the scans cover.

use anyhow::{Result, bail};
use clap::ValueEnum;
use veila_metrics::Region;
use veila_metrics::suite::{ScanSummary, empty_regions};

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

/// The regions of `regions` to score: all of them when every one has points in both sets;
/// otherwise, when the user chose them (`given`), an error naming the regions to use, else the
/// covered ones (their summaries kept in `generated` and `reference`), with a note.
pub(crate) fn covered(
    given: bool,
    regions: Vec<Region>,
    generated: &mut [ScanSummary],
    reference: &mut [ScanSummary],
) -> Result<Vec<Region>> {
    let empty = empty_regions(&regions, generated, reference);
    if empty.is_empty() {
        return Ok(regions);
    }
    let keep: Vec<bool> = regions
        .iter()
        .map(|r| !empty.iter().any(|(e, _)| e == r))
        .collect();
    let kept: Vec<Region> = regions
        .iter()
        .zip(&keep)
        .filter(|(_, k)| **k)
        .map(|(r, _)| *r)
        .collect();
    let names = |rs: &[Region]| rs.iter().map(|r| r.name()).collect::<Vec<_>>().join(",");
    let (region, set) = empty[0];
    let why = format!(
        "region {region}: no {set} scan has a point there (scans cropped to a camera's view have \
         no rear)"
    );
    if given || kept.is_empty() {
        if kept.is_empty() {
            bail!("{why}; the scans cover none of the regions asked for");
        }
        bail!(
            "{why}; score the regions they cover: --regions {}",
            names(&kept)
        );
    }
    let left_out: Vec<Region> = empty.iter().map(|(r, _)| *r).collect();
    eprintln!(
        "note: {why}; scoring {} only (left out: {})",
        names(&kept),
        names(&left_out)
    );
    for s in generated.iter_mut().chain(reference.iter_mut()) {
        s.retain_regions(&keep);
    }
    Ok(kept)
}
