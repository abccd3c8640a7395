//! `veila segment eval --predictions DIR --labels DIR`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use veila_diffusion::app::segment::{FolderScores, LabelSpace, evaluate_label_dirs};

use crate::progress;
use crate::staging::{self, Inputs, check_ext};

/// Arguments of `veila segment eval`.
#[derive(Debug, Args)]
pub(crate) struct EvalArgs {
    /// The predicted `NAME.label` files.
    #[arg(long, value_name = "DIR")]
    predictions: PathBuf,
    /// The ground-truth `NAME.label` files (every one needs its prediction).
    #[arg(long, value_name = "DIR")]
    labels: PathBuf,
    /// The label map both folders are written in (`semantic-kitti.yaml`); default:
    /// SemanticKITTI's, built in.
    #[arg(long, value_name = "FILE.yaml")]
    label_map: Option<PathBuf>,
    /// Also write the scores as JSON.
    #[arg(long, value_name = "FILE.json")]
    json: Option<PathBuf>,
    /// Replace an existing --json file (never an input).
    #[arg(long)]
    force: bool,
}

pub(crate) fn run(a: EvalArgs) -> Result<()> {
    let mut inputs = Inputs::new();
    inputs.add(&a.predictions).add(&a.labels);
    if let Some(m) = &a.label_map {
        inputs.add(m);
    }
    if let Some(j) = &a.json {
        check_ext(j, "--json", &["json"])?;
        staging::check_outputs(&[j.as_path()], &inputs, a.force, false)?;
    }
    let space = LabelSpace::read_or_built_in(a.label_map.as_deref())?;
    let count = veila_data::kitti::list_stems(&a.labels, ".label").map_or(0, |v| v.len());
    let pb = progress::bar(count as u64, "eval");
    let scores = evaluate_label_dirs(&a.predictions, &a.labels, &space, |_| pb.inc(1))
        .with_context(|| {
            format!(
                "scoring {} against {}",
                a.predictions.display(),
                a.labels.display()
            )
        })?;
    pb.finish_and_clear();
    if let Some(j) = &a.json {
        let mut text = serde_json::to_string_pretty(&scores)?;
        text.push('\n');
        staging::publish_files(&[(j.clone(), text.into_bytes())], &inputs, a.force, false)?;
    }
    print_scores(&scores);
    Ok(())
}

fn print_scores(f: &FolderScores) {
    let s = &f.scores;
    println!(
        "{} scans, {} points scored, label map: {}",
        f.scans, s.points, f.label_map
    );
    println!("{:<3} {:<16} {:>8}  present", "id", "class", "IoU");
    for &c in &s.included {
        let name = f.class_names.get(c).map_or("", String::as_str);
        let present = if s.present.contains(&c) { "yes" } else { "no" };
        println!("{c:<3} {name:<16} {:>8.4}  {present}", s.iou[c]);
    }
    println!(
        "mIoU {:.4} ({} classes); over the {} classes present {:.4}; accuracy {:.4}",
        s.miou,
        s.included.len(),
        s.present.len(),
        s.miou_present,
        s.accuracy
    );
}
