//! The augmentation benchmark (`cargo xtask bench-augment`, feature `sim`): do scans the bundle
//! generates from camera images, pseudo-labelled by a teacher, make a LiDAR segmenter better when
//! labels are scarce? The paper's last table, on the simulator.
//!
//! * **The split.** The frames of the bundle's training list that follow the ones it trained on
//!   (`pool_frames`): the bundle never saw them, as a generator trained on one dataset never saw
//!   another's frames. Each labelled fraction's frames are a fixed prefix of one seeded
//!   permutation ([`labelled_frames`]), shared by every row and seed; the rest are unlabelled and
//!   only their camera images are used, except by the true-scan control.
//! * **The rows**, at each fraction and training seed: the segmenter trained on the labelled
//!   frames alone (also the teacher); the labelled frames plus one scan for each unlabelled frame
//!   from each [`ScanSource`] (generated, the true scans, the mean network's, retrieved),
//!   pseudo-labelled by that teacher; the generated scans pseudo-labelled by a teacher trained on
//!   the whole split (the paper's variant, which uses more labels); and, once per seed, that
//!   whole-split teacher itself.
//! * **Everything on the bundle's grid.** Every scan is the bundle's 32 x 256 range image as
//!   points (one per pixel, at its ray's centre), the true scans too, so generated and true scans
//!   reach the segmenter the same way; the test frames are scored over those points with their
//!   true labels.
//! * **Resumable.** `work/` holds each source's scans once sampled and each run's checkpoints and
//!   result; a rerun of the same job continues where it stopped, and a different job is refused.

mod data;
mod options;
mod report;

use std::path::Path;
use std::time::Instant;

use candle_core::Device;

pub use data::{GridPoints, LABELLED_LIST_SEED, ScanSource, labelled_frames};
pub use options::{AugmentOptions, pct};
pub use report::{AugmentReport, FractionTable, MIN_EFFECT, RowStats, RunResult, Verdict, verdict};

use self::data::{Grid, read_work_json, run_dir, scan_set, split_name};
use super::bundle::Bundle;
use super::progress::Progress;
use super::segment::{
    HeldOutScan, LabelSpace, SegEvent, SegFrame, SegTrainSettings, SegmenterModel,
    SegmenterModelConfig, class_counts, class_weights, fit_segmenter, train::SegTrainInput,
};
use super::sim_examples::{render_split_after, test_list_for, train_split_of};
use crate::error::{Error, Result, invalid};

/// A run's name: its folder under `work/runs/`.
fn run_name(seed: u64, fraction: Option<f64>, what: &str) -> String {
    match fraction {
        Some(f) => format!("seed-{seed}/labelled-{}/{what}", pct(f)),
        None => format!("seed-{seed}/{what}"),
    }
}

/// The folder names of the runs that are not one source's student (those are the source's
/// [`ScanSource::name`]).
const WHOLE_SPLIT_RUN: &str = "whole-split";
const SUPERVISED_RUN: &str = "supervised";
const WHOLE_TEACHER_RUN: &str = "generated-whole-split-teacher";

/// The scan sources of `bundle`'s rows: every [`ScanSource`], less the mean network's where the
/// bundle has none.
fn sources_of(bundle: &Bundle) -> Vec<ScanSource> {
    ScanSource::ALL
        .into_iter()
        .filter(|s| *s != ScanSource::MeanNetwork || bundle.config.residual.is_some())
        .collect()
}

/// Runs the whole table takes: per seed, the whole-split teacher and, at each fraction, the
/// supervised run, one student per source and the whole-split teacher's student.
fn planned_runs(opts: &AugmentOptions, sources: usize) -> usize {
    opts.seeds.len() * (1 + opts.fractions.len() * (2 + sources))
}

/// What one segmenter run trains on and is called.
struct RunSpec<'a> {
    name: String,
    row: String,
    fraction: Option<f64>,
    seed: u64,
    labelled: &'a [SegFrame],
    /// The teacher, the scans it labels and which of them (made only when the run trains).
    pseudo: Option<(&'a SegmenterModel, &'a [GridPoints], &'a [usize])>,
    /// Whether its weights label the scans of other runs.
    teaches: bool,
}

/// The shared part of every run.
struct Bench<'a> {
    opts: &'a AugmentOptions,
    grid: &'a Grid,
    model: SegmenterModelConfig,
    test: Vec<HeldOutScan>,
    ignored: Vec<usize>,
    job: serde_json::Value,
    progress: &'a dyn Progress,
    device: Device,
}

impl Bench<'_> {
    /// Trains (or resumes, or reads back) the run `spec`; its weights are kept in its folder for
    /// when it teaches.
    fn run(&self, spec: RunSpec<'_>) -> Result<(RunResult, Option<SegmenterModel>)> {
        let dir = self.opts.root.join(run_dir(&self.opts.work, &spec.name));
        let result_path = dir.join("result.json");
        let model_dir = dir.join("segmenter");
        // a finished run is read back; a teacher's weights are needed too (a teacher whose
        // weights are gone, as from a work folder rebuilt from its results alone, trains again
        // to the same weights: every run is seeded)
        let have_model = model_dir.is_dir();
        let done = match have_model || !spec.teaches {
            true => read_work_json::<RunResult>(&result_path)?,
            false => None,
        };
        if let Some(r) = done {
            let model = match have_model {
                true => Some(SegmenterModel::from_dir(&model_dir, &self.device)?),
                false => None,
            };
            self.progress
                .line(&format!("  {}: done before, mIoU {:.3}", spec.name, r.miou));
            return Ok((r, model));
        }
        let pseudo: Vec<SegFrame> = match spec.pseudo {
            Some((teacher, points, which)) => which
                .iter()
                .map(|&i| self.grid.pseudo_labelled(teacher, &points[i]))
                .collect::<Result<_>>()?,
            None => Vec::new(),
        };
        let pseudo_frames = pseudo.len();
        let frames: Vec<SegFrame> = spec.labelled.iter().cloned().chain(pseudo).collect();
        let n = self.model.network.num_classes;
        let counts = class_counts(&frames, n);
        let weights = class_weights(&counts, self.opts.class_weighting, &self.ignored);
        let settings = SegTrainSettings {
            seed: spec.seed,
            ..self.opts.train.clone()
        };
        let bar = self.progress.bar(&spec.name, settings.steps);
        let t = Instant::now();
        let outcome = fit_segmenter(
            &SegTrainInput {
                model: &self.model,
                frames: &frames,
                class_weights: &weights,
                ignored: &self.ignored,
                held_out: &self.test,
                ck_dir: &dir.join("checkpoints"),
                data: serde_json::json!({ "job": self.job, "run": spec.name }),
            },
            &settings,
            &self.device,
            |e| {
                if let SegEvent::Step { step, loss, .. } = e {
                    bar.set(step, &format!("loss {loss:.3}"));
                }
                std::ops::ControlFlow::Continue(())
            },
        )?;
        drop(bar);
        let scores = outcome
            .held_out
            .ok_or_else(|| Error::Data(format!("{}: no held-out scores", spec.name)))?;
        let result = RunResult {
            name: spec.name.clone(),
            row: spec.row,
            fraction: spec.fraction,
            seed: spec.seed,
            labelled_frames: spec.labelled.len(),
            pseudo_frames,
            miou: scores.miou,
            miou_present: scores.miou_present,
            accuracy: scores.accuracy,
            iou: scores.iou.clone(),
            present: scores.present.clone(),
            train_seconds: outcome.train_seconds,
            wall_seconds: t.elapsed().as_secs_f64(),
        };
        let mut config = self.model.clone();
        config.provenance = serde_json::json!({
            "trained_by": "cargo xtask bench-augment",
            "run": spec.name,
            "steps": settings.steps,
        });
        SegmenterModel::save(&model_dir, &config, &outcome.weights)?;
        let json = serde_json::to_vec_pretty(&result).map_err(|source| Error::Json {
            path: result_path.clone(),
            source,
        })?;
        veila_data::atomic::write_atomic(&result_path, &json)?;
        // the checkpoints are not needed once the result and the weights are kept
        let _ = std::fs::remove_dir_all(dir.join("checkpoints"));
        self.progress.line(&format!(
            "  {}: mIoU {:.3} ({} labelled + {} pseudo-labelled frames, {:.0} s)",
            spec.name,
            result.miou,
            result.labelled_frames,
            result.pseudo_frames,
            result.train_seconds
        ));
        let model = SegmenterModel::from_dir(&model_dir, &self.device)?;
        Ok((result, Some(model)))
    }
}

/// A teacher's weights, which [`Bench::run`] always returns for a teacher.
fn teacher_of(model: Option<SegmenterModel>, r: &RunResult) -> Result<SegmenterModel> {
    model.ok_or_else(|| Error::Data(format!("{}: the teacher's weights are missing", r.name)))
}

/// Claims `work` for `job`: records it, or checks that the folder's is the same.
fn claim_work(work: &Path, job: &serde_json::Value) -> Result<()> {
    std::fs::create_dir_all(work).map_err(|source| Error::Io {
        action: "creating the work folder",
        path: work.to_path_buf(),
        source,
    })?;
    let path = work.join("job.json");
    match read_work_json::<serde_json::Value>(&path)? {
        Some(found) => {
            if &found != job {
                return Err(Error::Output {
                    path,
                    reason: "holds another job's runs (another bundle, sampler, split or \
                             training); give another --work or remove it"
                        .into(),
                });
            }
            Ok(())
        }
        None => {
            let bytes = serde_json::to_vec_pretty(job).map_err(|source| Error::Json {
                path: path.clone(),
                source,
            })?;
            Ok(veila_data::atomic::write_atomic(&path, &bytes)?)
        }
    }
}

/// Runs the benchmark of `opts` (module docs), writes its report (`report.md`, `report.json`)
/// into `out`, and returns it; `progress` shows the run.
pub fn run(opts: &AugmentOptions, progress: &dyn Progress) -> Result<AugmentReport> {
    opts.check()?;
    let t0 = Instant::now();
    let device = Device::Cpu;
    let bundle = Bundle::from_dir(&opts.root.join(&opts.model), &device)?;
    if !bundle.is_conditional() {
        return Err(invalid(
            "model",
            format!("{}: the bundle must be conditional", opts.model.display()),
        ));
    }
    let sampler = opts
        .sampler
        .clone()
        .unwrap_or_else(|| bundle.config.sampler.clone());
    let job = opts.job(&bundle, &sampler);
    let work = opts.root.join(&opts.work);
    claim_work(&work, &job)?;

    let labels = LabelSpace::semantic_kitti();
    let mut network = super::segment::SegPreset::Bundled.network();
    network.num_classes = labels.num_classes();
    let sensor = &bundle.config.denoiser.sensor;
    let model = SegmenterModelConfig::new(network.clone(), sensor, labels.classes());
    let grid = Grid::new(sensor, network)?;

    let train_list = train_split_of(&bundle.config);
    let test_list = test_list_for(&opts.root, &train_list);
    let cfg = &bundle.config;
    let split = render_split_after(
        &opts.root,
        &train_list,
        opts.pool_frames,
        opts.split_frames,
        cfg,
        "simulating the split",
        progress,
    )?;
    let tests = render_split_after(
        &opts.root,
        &test_list,
        0,
        opts.test_frames,
        cfg,
        "simulating test frames",
        progress,
    )?;
    let test: Vec<HeldOutScan> = tests
        .iter()
        .map(|e| grid.held_out(&grid.points(&e.range)?))
        .collect::<Result<_>>()?;
    drop(tests);
    let split_label = split_name(&train_list, opts.pool_frames, opts.split_frames);
    let mut pool = || {
        render_split_after(
            &opts.root,
            &train_list,
            0,
            opts.pool_frames,
            cfg,
            "simulating the retrieval database",
            progress,
        )
    };
    // each source's scans of the split as points
    let mut sources: Vec<(ScanSource, Vec<GridPoints>, Option<f64>)> = Vec::new();
    // a bundle without a mean network has no mean-network row
    for source in sources_of(&bundle) {
        let (scans, secs) = scan_set(
            source,
            &bundle,
            &sampler,
            &split,
            &split_label,
            opts.pool_frames,
            &mut pool,
            opts.pool_frames,
            &work,
            progress,
        )?;
        let points = scans
            .iter()
            .map(|s| grid.points(s))
            .collect::<Result<Vec<_>>>()?;
        sources.push((source, points, secs));
    }
    let of = |which: ScanSource| {
        &sources
            .iter()
            .find(|(s, ..)| *s == which)
            .expect("every bundle has generated and true scans")
            .1
    };
    let truth = of(ScanSource::True);
    let true_frames: Vec<SegFrame> = truth
        .iter()
        .map(|p| grid.frame(p, &grid.train_ids(p)))
        .collect::<Result<_>>()?;
    drop(split);

    let bench = Bench {
        opts,
        grid: &grid,
        model,
        test,
        ignored: labels.ignored(),
        job,
        progress,
        device,
    };
    let generated = of(ScanSource::Generated);
    let per_scan: Vec<(ScanSource, Option<f64>)> =
        sources.iter().map(|(s, _, secs)| (*s, *secs)).collect();
    let planned = planned_runs(opts, sources.len());
    let test_name = test_list.display().to_string();
    // the report so far after every run (a long run shows its first seed's table early)
    let write = |results: &[RunResult]| -> Result<AugmentReport> {
        let report = AugmentReport::new(
            opts,
            &bundle,
            &sampler,
            &split_label,
            &test_name,
            per_scan.clone(),
            results.to_vec(),
            planned,
            t0.elapsed().as_secs_f64(),
        );
        report.write(&opts.root.join(&opts.out))?;
        Ok(report)
    };
    let mut results = Vec::new();
    for &seed in &opts.seeds {
        // the paper's teacher: the whole split labelled
        let (whole, whole_teacher) = bench.run(RunSpec {
            name: run_name(seed, None, WHOLE_SPLIT_RUN),
            row: report::WHOLE_SPLIT.into(),
            fraction: None,
            seed,
            labelled: &true_frames,
            pseudo: None,
            teaches: true,
        })?;
        let whole_teacher = teacher_of(whole_teacher, &whole)?;
        results.push(whole);
        write(&results)?;
        for &fraction in &opts.fractions {
            let lab = labelled_frames(true_frames.len(), fraction);
            let unlabelled: Vec<usize> = (0..true_frames.len())
                .filter(|i| lab.binary_search(i).is_err())
                .collect();
            let labelled: Vec<SegFrame> = lab.iter().map(|&i| true_frames[i].clone()).collect();
            let (sup, teacher) = bench.run(RunSpec {
                name: run_name(seed, Some(fraction), SUPERVISED_RUN),
                row: report::SUPERVISED.into(),
                fraction: Some(fraction),
                seed,
                labelled: &labelled,
                pseudo: None,
                teaches: true,
            })?;
            let teacher = teacher_of(teacher, &sup)?;
            results.push(sup);
            write(&results)?;
            // the students: each source's scans by the fraction's teacher, then the generated
            // scans by the whole-split teacher
            let mut students: Vec<(&str, String, &SegmenterModel, &[GridPoints])> = sources
                .iter()
                .map(|(s, p, _)| (s.name(), report::source_row(*s), &teacher, p.as_slice()))
                .collect();
            students.push((
                WHOLE_TEACHER_RUN,
                report::WHOLE_TEACHER.into(),
                &whole_teacher,
                generated.as_slice(),
            ));
            for (what, row, by, points) in students {
                let (r, _) = bench.run(RunSpec {
                    name: run_name(seed, Some(fraction), what),
                    row,
                    fraction: Some(fraction),
                    seed,
                    labelled: &labelled,
                    pseudo: Some((by, points, &unlabelled)),
                    teaches: false,
                })?;
                results.push(r);
                write(&results)?;
            }
        }
    }
    write(&results)
}

/// Writes the report of `opts` from the results already in its work folder, rendering and
/// training nothing, and returns it: the merge of workers that ran the seeds apart (`--seeds 0`
/// and `--seeds 1` at once on the same work folder, each writing a report of its own seed), or
/// a look at a run in progress. Runs not done are left out and the report says it is partial.
pub fn report_from_work(opts: &AugmentOptions) -> Result<AugmentReport> {
    opts.check()?;
    let t0 = Instant::now();
    let bundle = Bundle::from_dir(&opts.root.join(&opts.model), &Device::Cpu)?;
    let sampler = opts
        .sampler
        .clone()
        .unwrap_or_else(|| bundle.config.sampler.clone());
    let work = opts.root.join(&opts.work);
    if !work.join("job.json").is_file() {
        return Err(Error::Input {
            path: work.join("job.json"),
            reason: "no benchmark ran in this work folder".into(),
        });
    }
    claim_work(&work, &opts.job(&bundle, &sampler))?;
    let train_list = train_split_of(&bundle.config);
    let test_list = test_list_for(&opts.root, &train_list);
    let kinds = sources_of(&bundle);
    let per_scan = kinds
        .iter()
        .map(|&s| Ok((s, data::cached_seconds(&work, s)?)))
        .collect::<Result<Vec<_>>>()?;
    let mut results = Vec::new();
    for seed in &opts.seeds {
        let fractions = std::iter::once(None).chain(opts.fractions.iter().map(|&f| Some(f)));
        for fraction in fractions {
            let names: Vec<&str> = match fraction {
                None => vec![WHOLE_SPLIT_RUN],
                Some(_) => std::iter::once(SUPERVISED_RUN)
                    .chain(kinds.iter().map(|s| s.name()))
                    .chain(std::iter::once(WHOLE_TEACHER_RUN))
                    .collect(),
            };
            for what in names {
                let path = run_dir(&work, &run_name(*seed, fraction, what)).join("result.json");
                results.extend(read_work_json::<RunResult>(&path)?);
            }
        }
    }
    let planned = planned_runs(opts, kinds.len());
    let report = AugmentReport::new(
        opts,
        &bundle,
        &sampler,
        &split_name(&train_list, opts.pool_frames, opts.split_frames),
        &test_list.display().to_string(),
        per_scan,
        results,
        planned,
        t0.elapsed().as_secs_f64(),
    );
    report.write(&opts.root.join(&opts.out))?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::app::segment::ClassWeighting;

    fn options(root: &Path, tmp: &Path, steps: u64) -> AugmentOptions {
        AugmentOptions {
            root: root.to_path_buf(),
            model: root.join("models/default"),
            pool_frames: 4,
            split_frames: 8,
            test_frames: 3,
            fractions: vec![0.25],
            seeds: vec![3],
            train: SegTrainSettings {
                steps,
                batch: 2,
                lr: 1e-3,
                min_lr: 1e-4,
                warmup_steps: 1,
                weight_decay: 0.0,
                seed: 0,
                augment: true,
                checkpoint_every: 1,
                keep_checkpoints: Some(1),
                eval_every: None,
            },
            class_weighting: ClassWeighting::InverseSqrtFrequency,
            sampler: None,
            work: tmp.join("work"),
            out: tmp.join("out"),
            command: "test".into(),
        }
    }

    /// A whole run at toy size: every row at the fraction, the fixed lists' sizes, the report;
    /// a rerun reads every result back instead of training, and another job's folder is refused.
    #[test]
    fn a_toy_run_has_every_row_resumes_from_its_results_and_refuses_another_job() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        if !root.join("models/default").is_dir() {
            eprintln!("skipped: no models/default");
            return;
        }
        let tmp = tempfile::tempdir().unwrap();
        let mut opts = options(&root, tmp.path(), 2);
        let mut bundle_sampler = Bundle::from_dir(&opts.model, &Device::Cpu)
            .unwrap()
            .config
            .sampler;
        bundle_sampler.steps = 1;
        opts.sampler = Some(bundle_sampler);
        let report = run(&opts, &()).unwrap();
        let table = &report.fractions[0];
        let rows: Vec<&str> = table.rows.iter().map(|r| r.row.as_str()).collect();
        assert_eq!(
            rows,
            [
                report::SUPERVISED.to_string(),
                report::source_row(ScanSource::Generated),
                report::source_row(ScanSource::True),
                report::source_row(ScanSource::MeanNetwork),
                report::source_row(ScanSource::Retrieved),
                report::WHOLE_TEACHER.to_string(),
            ]
        );
        // 25 % of 8 frames labelled, the other 6 pseudo-labelled in every augmented row
        for r in &table.rows {
            assert_eq!(r.labelled_frames, 2, "{}", r.row);
            let pseudo = if r.row == report::SUPERVISED { 0 } else { 6 };
            assert_eq!(r.pseudo_frames, pseudo, "{}", r.row);
            assert!((0.0..=1.0).contains(&r.miou), "{}: {}", r.row, r.miou);
        }
        let whole = report.whole_split.as_ref().unwrap();
        assert_eq!((whole.labelled_frames, whole.pseudo_frames), (8, 0));
        assert_eq!((report.runs.len(), report.planned_runs), (7, 7));
        assert!(table.generated_vs_supervised.is_some() && table.generated_vs_true.is_some());
        let md = std::fs::read_to_string(tmp.path().join("out/report.md")).unwrap();
        assert!(md.contains("## 25% labelled") && md.contains("generated scans against"));
        assert!(!md.contains("Partial"), "{md}");
        let work = tmp.path().join("work");
        assert!(work.join("scans/generated.safetensors").is_file());
        // a rerun reads every result (and the scans) back: the same numbers, no training
        let again = run(&opts, &()).unwrap();
        assert_eq!(again.runs, report.runs);
        // the sampling time is the one recorded when the scans were made, not the cache's read
        assert_eq!(again.seconds_per_scan, report.seconds_per_scan);
        assert!(report.seconds_per_scan.iter().all(|(_, s)| s.is_some()));
        assert!(
            !work
                .join("runs/seed-3/labelled-25/generated/checkpoints")
                .exists()
        );
        // the report from the work folder alone: the same runs and tables, no training; one
        // result gone, it is partial and that run's row has no seed
        let merged = report_from_work(&opts).unwrap();
        assert_eq!(merged.runs, report.runs);
        assert_eq!(merged.fractions, report.fractions);
        assert_eq!(merged.seconds_per_scan, report.seconds_per_scan);
        let kept = work.join("runs/seed-3/labelled-25/retrieved/result.json");
        let text = std::fs::read(&kept).unwrap();
        std::fs::remove_file(&kept).unwrap();
        let partial = report_from_work(&opts).unwrap();
        assert_eq!((partial.runs.len(), partial.planned_runs), (6, 7));
        let md = std::fs::read_to_string(tmp.path().join("out/report.md")).unwrap();
        assert!(md.contains("Partial: 6 of 7 runs"), "{md}");
        std::fs::write(&kept, text).unwrap();
        // a work folder holding results alone (restored from committed results): a student is
        // read back, a teacher trains again, to the same weights (every run is seeded)
        let runs = work.join("runs/seed-3/labelled-25");
        let (student, teacher) = (
            runs.join("generated/segmenter"),
            runs.join("supervised/segmenter"),
        );
        let weights = std::fs::read(teacher.join("segmenter.safetensors")).unwrap();
        std::fs::remove_dir_all(&student).unwrap();
        std::fs::remove_dir_all(&teacher).unwrap();
        let third = run(&opts, &()).unwrap();
        let scores = |r: &AugmentReport| -> Vec<(String, f64, Vec<f64>)> {
            r.runs
                .iter()
                .map(|x| (x.name.clone(), x.miou, x.iou.clone()))
                .collect()
        };
        assert_eq!(scores(&third), scores(&report));
        assert!(!student.exists());
        assert_eq!(
            std::fs::read(teacher.join("segmenter.safetensors")).unwrap(),
            weights
        );
        // another job in the same folder is refused, the folder untouched
        let before = std::fs::read(work.join("job.json")).unwrap();
        let other = AugmentOptions {
            train: SegTrainSettings {
                steps: 3,
                ..opts.train.clone()
            },
            ..opts.clone()
        };
        let e = run(&other, &()).unwrap_err().to_string();
        assert!(e.contains("another job"), "{e}");
        assert_eq!(std::fs::read(work.join("job.json")).unwrap(), before);
    }

    #[test]
    fn bad_options_are_refused_before_anything_runs() {
        let tmp = tempfile::tempdir().unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        for (edit, what) in [
            (
                Box::new(|o: &mut AugmentOptions| o.fractions = vec![0.0])
                    as Box<dyn Fn(&mut AugmentOptions)>,
                "strictly between 0 and 1",
            ),
            (Box::new(|o| o.fractions = vec![1.0]), "strictly between"),
            (Box::new(|o| o.seeds.clear()), "no seed"),
            (Box::new(|o| o.split_frames = 1), "2 frames or more"),
        ] {
            let mut o = options(&root, tmp.path(), 2);
            edit(&mut o);
            let e = run(&o, &()).unwrap_err().to_string();
            assert!(e.contains(what), "{e}");
        }
        assert!(!tmp.path().join("work").exists());
    }
}
