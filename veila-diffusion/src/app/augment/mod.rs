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
//! * **Shared.** Workers started on one work folder of one machine (one a core) split the table:
//!   each takes the next run of the plan that no other holds (a `flock` in the folder, which
//!   goes with a killed worker) and whose teacher is done, one makes each scan set while the
//!   others wait for it, and each writes the report of every result done.

mod data;
mod options;
mod report;

use std::path::Path;
use std::time::Instant;

use candle_core::Device;

pub use data::{GridPoints, LABELLED_LIST_SEED, ScanSource, labelled_frames};
pub use options::{AugmentOptions, pct};
pub use report::{AugmentReport, FractionTable, MIN_EFFECT, RowStats, RunResult, Verdict, verdict};

use self::data::{Grid, POLL, read_work_json, run_dir, scan_set, split_name};
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

/// One run of the table, as planned before anything trains.
#[derive(Debug, Clone)]
struct PlannedRun {
    name: String,
    row: String,
    fraction: Option<f64>,
    seed: u64,
    /// The run whose weights label its extra scans, and whose scans they are (`None`: the
    /// labelled frames alone).
    pseudo: Option<(String, ScanSource)>,
    /// Whether its weights label the scans of other runs.
    teaches: bool,
}

/// Every run of the table, in the order a worker takes them: per seed, the whole-split teacher
/// and, at each fraction, the supervised run (the fraction's teacher), one student per source and
/// the whole-split teacher's student. A student comes after its teacher.
fn plan(opts: &AugmentOptions, sources: &[ScanSource]) -> Vec<PlannedRun> {
    let mut runs = Vec::new();
    for &seed in &opts.seeds {
        let whole = run_name(seed, None, WHOLE_SPLIT_RUN);
        runs.push(PlannedRun {
            name: whole.clone(),
            row: report::WHOLE_SPLIT.into(),
            fraction: None,
            seed,
            pseudo: None,
            teaches: true,
        });
        for &fraction in &opts.fractions {
            let at = |what: &str| run_name(seed, Some(fraction), what);
            let teacher = at(SUPERVISED_RUN);
            let student = |name: String, row: String, by: &str, source: ScanSource| PlannedRun {
                name,
                row,
                fraction: Some(fraction),
                seed,
                pseudo: Some((by.to_string(), source)),
                teaches: false,
            };
            runs.push(PlannedRun {
                name: teacher.clone(),
                row: report::SUPERVISED.into(),
                fraction: Some(fraction),
                seed,
                pseudo: None,
                teaches: true,
            });
            for &source in sources {
                runs.push(student(
                    at(source.name()),
                    report::source_row(source),
                    &teacher,
                    source,
                ));
            }
            runs.push(student(
                at(WHOLE_TEACHER_RUN),
                report::WHOLE_TEACHER.into(),
                &whole,
                ScanSource::Generated,
            ));
        }
    }
    runs
}

/// The results of `plan`'s runs that are done in `work`, in the plan's order (whichever worker
/// ran them).
fn results_in(work: &Path, plan: &[PlannedRun]) -> Result<Vec<RunResult>> {
    let mut results = Vec::new();
    for p in plan {
        results.extend(read_work_json::<RunResult>(
            &run_dir(work, &p.name).join("result.json"),
        )?);
    }
    Ok(results)
}

/// What [`Bench::run`] did with a run.
enum Taken {
    /// Trained now, or read back: its result, and its weights where it teaches.
    Done(Box<(RunResult, Option<SegmenterModel>)>),
    /// Another worker holds it.
    Held,
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
    fn run(&self, spec: RunSpec<'_>) -> Result<Taken> {
        let dir = self.opts.root.join(run_dir(&self.opts.work, &spec.name));
        let result_path = dir.join("result.json");
        let model_dir = dir.join("segmenter");
        // a finished run is read back; a teacher's weights are needed too (a teacher whose
        // weights are gone, as from a work folder rebuilt from its results alone, trains again
        // to the same weights: every run is seeded)
        let read_back = || -> Result<Option<Taken>> {
            let have_model = model_dir.is_dir();
            let done = match have_model || !spec.teaches {
                true => read_work_json::<RunResult>(&result_path)?,
                false => None,
            };
            let Some(r) = done else { return Ok(None) };
            let model = match have_model {
                true => Some(SegmenterModel::from_dir(&model_dir, &self.device)?),
                false => None,
            };
            self.progress
                .line(&format!("  {}: done before, mIoU {:.3}", spec.name, r.miou));
            Ok(Some(Taken::Done(Box::new((r, model)))))
        };
        if let Some(done) = read_back()? {
            return Ok(done);
        }
        // workers sharing the work folder take a run each: the one that holds its lock trains
        // it (the lock goes with a killed worker); another may have finished it meanwhile
        if let Some(parent) = dir.parent() {
            std::fs::create_dir_all(parent).map_err(|source| Error::Io {
                action: "creating the run folder",
                path: parent.to_path_buf(),
                source,
            })?;
        }
        let Some(_lock) = veila_data::atomic::OutputLock::try_acquire(&dir)? else {
            return Ok(Taken::Held);
        };
        if let Some(done) = read_back()? {
            return Ok(done);
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
        Ok(Taken::Done(Box::new((result, Some(model)))))
    }
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
    let per_scan: Vec<(ScanSource, Option<f64>)> =
        sources.iter().map(|(s, _, secs)| (*s, *secs)).collect();
    let kinds: Vec<ScanSource> = sources.iter().map(|(s, ..)| *s).collect();
    let plan = plan(opts, &kinds);
    let test_name = test_list.display().to_string();
    // the report of every run done so far, by this worker or another, after each run (a long
    // run shows its first seed's table early)
    let write = || -> Result<AugmentReport> {
        let report = AugmentReport::new(
            opts,
            &bundle,
            &sampler,
            &split_label,
            &test_name,
            per_scan.clone(),
            results_in(&work, &plan)?,
            plan.len(),
            t0.elapsed().as_secs_f64(),
        );
        report.write(&opts.root.join(&opts.out))?;
        Ok(report)
    };
    // each fraction's labelled frames and the unlabelled frames whose scans are pseudo-labelled
    let fractions: Vec<(f64, Vec<SegFrame>, Vec<usize>)> = opts
        .fractions
        .iter()
        .map(|&fraction| {
            let lab = labelled_frames(true_frames.len(), fraction);
            let unlabelled = (0..true_frames.len())
                .filter(|i| lab.binary_search(i).is_err())
                .collect();
            let labelled = lab.iter().map(|&i| true_frames[i].clone()).collect();
            (fraction, labelled, unlabelled)
        })
        .collect();
    // the first run of the plan that is not done, not held by another worker and whose teacher
    // is known, again and again: workers sharing the folder split the table between them, and
    // a worker with nothing to take waits for the others
    let mut teachers: std::collections::HashMap<String, SegmenterModel> = Default::default();
    let mut done = vec![false; plan.len()];
    let mut waiting = false;
    while done.iter().any(|d| !d) {
        let mut took = None;
        for (k, p) in plan.iter().enumerate().filter(|(k, _)| !done[*k]) {
            let (labelled, unlabelled): (&[SegFrame], &[usize]) = match p.fraction {
                None => (&true_frames, &[]),
                Some(f) => fractions
                    .iter()
                    .find(|(x, ..)| *x == f)
                    .map(|(_, l, u)| (l.as_slice(), u.as_slice()))
                    .expect("every planned fraction has its lists"),
            };
            let pseudo = match &p.pseudo {
                None => None,
                Some((by, source)) => match teachers.get(by) {
                    // its teacher is still to train (here or by another worker)
                    None => continue,
                    Some(teacher) => Some((teacher, of(*source).as_slice(), unlabelled)),
                },
            };
            let taken = bench.run(RunSpec {
                name: p.name.clone(),
                row: p.row.clone(),
                fraction: p.fraction,
                seed: p.seed,
                labelled,
                pseudo,
                teaches: p.teaches,
            })?;
            if let Taken::Done(done) = taken {
                let (r, model) = *done;
                took = Some((k, r, model));
                break;
            }
        }
        match took {
            Some((k, r, model)) => {
                if plan[k].teaches {
                    let model = model.ok_or_else(|| {
                        Error::Data(format!("{}: the teacher's weights are missing", r.name))
                    })?;
                    teachers.insert(plan[k].name.clone(), model);
                }
                done[k] = true;
                waiting = false;
                write()?;
            }
            None => {
                if !waiting {
                    progress.line("  waiting for runs that other workers hold");
                    waiting = true;
                }
                std::thread::sleep(POLL);
            }
        }
    }
    write()
}

/// Writes the report of `opts` from the results already in its work folder, rendering and
/// training nothing, and returns it: a look at a run in progress, or a report rebuilt from
/// committed results. Runs not done are left out and the report says it is partial.
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
    let plan = plan(opts, &kinds);
    let report = AugmentReport::new(
        opts,
        &bundle,
        &sampler,
        &split_name(&train_list, opts.pool_frames, opts.split_frames),
        &test_list.display().to_string(),
        per_scan,
        results_in(&work, &plan)?,
        plan.len(),
        t0.elapsed().as_secs_f64(),
    );
    report.write(&opts.root.join(&opts.out))?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::app::segment::ClassWeighting;

    use crate::app::progress::Lines;

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
        // two workers share the work folder: every run is trained once, by one of them, and
        // each ends with the whole report
        let (lines, lines_b) = (Lines::default(), Lines::default());
        let (report, other) = std::thread::scope(|s| {
            let b = s.spawn(|| run(&opts, &lines_b).unwrap());
            (run(&opts, &lines).unwrap(), b.join().unwrap())
        });
        assert_eq!(other.runs, report.runs);
        let trained = |l: &Lines| {
            l.0.lock()
                .unwrap()
                .iter()
                .filter(|t| t.contains("pseudo-labelled frames"))
                .count()
        };
        assert_eq!(trained(&lines) + trained(&lines_b), 7);
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
