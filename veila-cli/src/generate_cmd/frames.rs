//! `veila generate --frames DIR --out DIR`: a scan for every frame of a dataset. The job (listing
//! the frames, their seeds, the output folder's manifest, skipping complete frames, the split
//! across workers, the atomic writes) is the library's, `veila_diffusion::app::dataset_gen`; this
//! file opens the frames, shows progress (frames done of those left, seconds per frame, ETA) and
//! says what was done.
//!
//! Its output is not staged as a whole, as `convert`'s is not: a dataset takes hours over many
//! workers, so each frame appears whole on its own (temporary files renamed into place) and a
//! rerun resumes.

use std::path::Path;

use anyhow::{Context, Result};
use veila_diffusion::app::dataset_gen::{DatasetEvent, DatasetJob, FrameSource, generate_dataset};
use veila_diffusion::app::segment::SegmenterModel;
use veila_diffusion::app::{Bundle, GenerateOptions};

use crate::{progress, staging};

/// What `generate` hands over for a dataset.
pub(super) struct FramesRun<'a> {
    /// `--frames`.
    pub(super) frames: &'a Path,
    /// `--out`.
    pub(super) out: &'a Path,
    /// The sampler, `--residual-weight` and `--seed` (checked against the bundle).
    pub(super) options: &'a GenerateOptions,
    /// `(index, count)` of this worker.
    pub(super) worker: (usize, usize),
    /// `--segmenter`: labels every scan's points.
    pub(super) segmenter: Option<&'a SegmenterModel>,
}

pub(super) fn run(bundle: &Bundle, r: FramesRun<'_>) -> Result<()> {
    let source = FrameSource::open(r.frames)
        .with_context(|| format!("reading the frames of {}", r.frames.display()))?;
    let (index, count) = r.worker;
    let job = DatasetJob {
        out_dir: r.out.to_path_buf(),
        sampler: r.options.sampler.clone(),
        residual_weight: r.options.residual_weight,
        seed: r.options.seed,
        worker_index: index,
        worker_count: count,
        labeller: r
            .segmenter
            .map(|s| s as &dyn veila_diffusion::app::dataset_gen::ScanLabeller),
    };
    let out = r.out.display().to_string();
    staging::set_interrupt_note(move || {
        format!(
            "every scan in {out}/velodyne is complete (each file appears whole); run the same \
             command again to resume"
        )
    });
    eprintln!(
        "generating scans for the {} frames of {} ({}) as worker {index} of {count} into {}{}",
        source.len(),
        r.frames.display(),
        source.kind().as_str(),
        r.out.display(),
        match r.segmenter {
            Some(s) => format!(", pseudo-labelled by {}", s.origin().display()),
            None => String::new(),
        }
    );
    let bar = progress::bar(0, "generate");
    let (mut done, mut seconds) = (0usize, 0.0f64);
    let mut on_event = |e: DatasetEvent<'_>| match e {
        DatasetEvent::Start {
            assigned,
            to_generate,
            ..
        } => {
            bar.set_length(to_generate as u64);
            if to_generate < assigned {
                eprintln!(
                    "{} of this worker's {assigned} frames are complete already: skipped",
                    assigned - to_generate
                );
            }
        }
        DatasetEvent::Frame { seconds: s, .. } => {
            done += 1;
            seconds += s;
            bar.set_message(format!("{:.2} s/frame", seconds / done as f64));
            bar.inc(1);
        }
    };
    let summary = generate_dataset(bundle, &source, &job, &mut on_event)
        .with_context(|| format!("generating the dataset into {}", r.out.display()))?;
    bar.finish_and_clear();
    let per_frame = if done > 0 {
        format!(", {:.2} s per frame", seconds / done as f64)
    } else {
        String::new()
    };
    println!(
        "worker {index} of {count}: generated {} scan(s){per_frame}, {} complete already, with \
         model `{}` ({}, seed {})",
        summary.generated,
        summary.skipped,
        crate::out::untrusted(&bundle.config.name),
        r.options.sampler,
        r.options.seed
    );
    let state = if summary.complete == summary.total {
        "the dataset is complete".to_string()
    } else {
        format!(
            "{} frame(s) still to generate (other workers', or a rerun's)",
            summary.total - summary.complete
        )
    };
    println!(
        "{}: {} of {} frames; {state}",
        r.out.display(),
        summary.complete,
        summary.total
    );
    Ok(())
}
