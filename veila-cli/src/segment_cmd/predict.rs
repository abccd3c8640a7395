//! `veila segment predict --scans DIR --out DIR [--model DIR]`.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use veila_data::kitti::list_stems;
use veila_data::scan::read_kitti_bin_records;
use veila_data::semantic_kitti::write_labels;
use veila_diffusion::app::segment::{LabelSpace, check_classes};

use crate::staging::{self, Inputs};
use crate::{model, progress};

/// Arguments of `veila segment predict`.
#[derive(Debug, Args)]
pub(crate) struct PredictArgs {
    /// The scans: every `NAME.bin` (KITTI records: x, y, z, reflectance as f32).
    #[arg(long, value_name = "DIR")]
    scans: PathBuf,
    /// Where `NAME.label` goes for every scan (a new or empty folder, or --force).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// The segmenter folder (segmenter.json, segmenter.safetensors, manifest.json); default: the
    /// bundled one (models/segmenter).
    #[arg(long, value_name = "DIR")]
    model: Option<PathBuf>,
    /// Check that the model writes the raw ids of this label map (`semantic-kitti.yaml`).
    #[arg(long, value_name = "FILE.yaml")]
    label_map: Option<PathBuf>,
    /// Write into a non-empty --out, replacing the label files an earlier predict wrote there.
    #[arg(long)]
    force: bool,
}

pub(crate) fn run(a: PredictArgs) -> Result<()> {
    let names = list_stems(&a.scans, ".bin")
        .with_context(|| format!("listing the scans of {}", a.scans.display()))?;
    if names.is_empty() {
        bail!("{}: no `.bin` scan to label", a.scans.display());
    }
    let device = model::device()?;
    let seg = model::load_segmenter(a.model.as_deref(), &device)?;
    let model_file = seg.origin().join("segmenter.json");
    if let Some(map) = &a.label_map {
        check_classes(&seg.config.classes, &LabelSpace::read(map)?, &model_file)?;
    }
    let mut inputs = Inputs::new();
    inputs.add(&a.scans);
    for n in &names {
        inputs.add(&a.scans.join(format!("{n}.bin")));
    }
    if let Some(m) = &a.model {
        inputs.add(m);
    }
    let staged = staging::stage_checked(&a.out, a.force, &inputs)?;
    let pb = progress::bar(names.len() as u64, "predict");
    let (mut points, mut outside) = (0usize, 0usize);
    for n in &names {
        let scan_path = a.scans.join(format!("{n}.bin"));
        let cloud = read_kitti_bin_records(&scan_path)?;
        let grid = seg
            .grid_scan(&cloud.xyz, &cloud.intensity)
            .with_context(|| format!("projecting {}", scan_path.display()))?;
        outside += grid.pixels.iter().filter(|p| p.is_none()).count();
        let train_ids = seg
            .predict(std::slice::from_ref(&grid))
            .with_context(|| format!("segmenting {}", scan_path.display()))?
            .pop()
            .unwrap_or_default();
        points += train_ids.len();
        write_labels(
            &staged.path().join(format!("{n}.label")),
            &seg.raw_ids(&train_ids),
        )?;
        pb.inc(1);
    }
    pb.finish_and_clear();
    staged.commit()?;
    println!(
        "wrote {} label files to {} ({points} points; {outside} outside the {} x {} grid's field of view or range, labelled 0) with {} ({})",
        names.len(),
        a.out.display(),
        seg.config.network.rows,
        seg.config.network.cols,
        seg.origin().display(),
        seg.config.network.name,
    );
    Ok(())
}
