//! `veila generate --frames`: a dataset killed (SIGKILL) mid-run and resumed, and one split over
//! two workers (flags and a Slurm array), give the bytes of one uninterrupted run; converted
//! shards give the scans of their KITTI folder; a frame's scan is `generate --image`'s with the
//! frame's seed; bad input fails clearly, naming the file, and never writes among the inputs.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use veila_diffusion::app::dataset_gen::frame_seed;

use crate::common::*;

/// `frames` simulated frames in the KITTI layout, in `dir/sim`.
fn simulate(dir: &Path, frames: u32) -> PathBuf {
    simulate_frames(dir, &tiny_scene(16, 128, frames), 3, frames)
}

/// `veila generate --quiet --frames FRAMES --out OUT --seed 9` with the bundled model, and
/// `--steps 1` unless `extra` gives `--steps`.
fn frames_cmd(frames: &Path, out: &Path, extra: &[&str]) -> Command {
    let mut c = veila();
    c.args(["generate", "--quiet", "--seed", "9"]);
    if !extra.contains(&"--steps") {
        c.args(["--steps", "1"]);
    }
    c.arg("--frames")
        .arg(frames)
        .arg("--model")
        .arg(model_dir())
        .arg("--out")
        .arg(out)
        .args(extra);
    c
}

fn run(frames: &Path, out: &Path, extra: &[&str]) -> Output {
    frames_cmd(frames, out, extra).output().unwrap()
}

#[test]
fn killed_resumed_and_split_datasets_are_one_runs_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), 6);
    let whole = tmp.path().join("whole");
    let o = run(&sim, &whole, &[]);
    ok(&o);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("6 of 6 frames; the dataset is complete"),
        "{stdout}"
    );
    let want = files_in(&whole);
    assert_eq!(want.len(), 7, "{:?}", want.keys());
    assert!(want.contains_key("dataset.json"));

    // killed once a frame is written, then resumed: the same files, nothing else
    let killed = tmp.path().join("killed");
    let mut child = frames_cmd(&sim, &killed, &[])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t = Instant::now();
    let velodyne = killed.join("velodyne");
    while !velodyne.is_dir() || !names(&velodyne).iter().any(|n| n.ends_with(".bin")) {
        assert!(t.elapsed() < Duration::from_secs(120), "no scan appeared");
        std::thread::sleep(Duration::from_millis(10));
    }
    signal(&child, "-KILL");
    child.wait().unwrap();
    // what a kill leaves visible is complete: every scan is the uninterrupted run's
    for n in names(&velodyne).iter().filter(|n| !n.starts_with('.')) {
        let got = std::fs::read(velodyne.join(n)).unwrap();
        assert_eq!(&got, &want[&format!("velodyne/{n}")], "{n} after the kill");
    }
    let o = run(&sim, &killed, &[]);
    ok(&o);
    assert_eq!(files_in(&killed), want, "killed and resumed");

    // two workers: one by its flags, one as task 1 of a Slurm array
    let split = tmp.path().join("split");
    ok(&run(
        &sim,
        &split,
        &["--shard-index", "0", "--shard-count", "2"],
    ));
    let o = frames_cmd(&sim, &split, &[])
        .env("SLURM_ARRAY_TASK_ID", "1")
        .env("SLURM_ARRAY_TASK_COUNT", "2")
        .output()
        .unwrap();
    ok(&o);
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("worker 1 of 2: generated 3 scan(s)"),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    assert_eq!(files_in(&split), want, "two workers");

    // a frame's scan is the one `generate --image` draws with the frame's seed
    let one = tmp.path().join("one");
    let seed = frame_seed(9, "000003").to_string();
    ok(&veila()
        .args([
            "generate", "--quiet", "--steps", "1", "--seed", &seed, "--image",
        ])
        .arg(sim.join("image_2/000003.png"))
        .arg("--calib")
        .arg(sim.join("calib/000003.txt"))
        .arg("--model")
        .arg(model_dir())
        .arg("--out")
        .arg(&one)
        .output()
        .unwrap());
    assert_eq!(
        std::fs::read(one.join("scan_000.bin")).unwrap(),
        want["velodyne/000003.bin"]
    );

    // converted shards: the same scans
    let shards = tmp.path().join("shards");
    ok(&veila()
        .args(["convert", "--quiet", "--dataset", "kitti", "--root"])
        .arg(&sim)
        .arg("--out")
        .arg(&shards)
        .output()
        .unwrap());
    let from_shards = tmp.path().join("from-shards");
    ok(&run(&shards, &from_shards, &[]));
    let got = files_in(&from_shards);
    for (name, bytes) in want.iter().filter(|(n, _)| n.ends_with(".bin")) {
        assert_eq!(&got[name], bytes, "{name} from shards");
    }
}

#[test]
fn bad_frames_and_outputs_fail_clearly_and_leave_the_inputs_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), 2);
    let inputs = files_in(&sim);
    // the output among the inputs
    for out in [sim.clone(), sim.join("generated")] {
        fails_with(
            &run(&sim, &out, &[]),
            &["frames' folder", "choose another --out"],
        );
    }
    assert_eq!(files_in(&sim), inputs);
    // no such folder; a folder of neither layout
    let missing = tmp.path().join("missing");
    fails_with(
        &run(&missing, &tmp.path().join("o1"), &[]),
        &["missing", "not a folder"],
    );
    fails_with(
        &run(&sim.join("velodyne"), &tmp.path().join("o1"), &[]),
        &["velodyne", "not a KITTI-layout folder"],
    );
    assert!(!tmp.path().join("o1").exists());
    // an output folder holding other files
    let other = tmp.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("keep.txt"), b"mine").unwrap();
    fails_with(
        &run(&sim, &other, &[]),
        &["keep.txt", "not part of a generated dataset"],
    );
    assert_eq!(names(&other), ["keep.txt"]);
    // another job's folder: refused with what differs, unchanged
    let done = tmp.path().join("done");
    ok(&run(&sim, &done, &[]));
    let before = files_in(&done);
    fails_with(
        &run(&sim, &done, &["--steps", "2"]),
        &[
            "dataset.json",
            "another job",
            "sampler.steps: this run 2, the folder's 1",
        ],
    );
    assert_eq!(files_in(&done), before);
    // the worker flags belong to --frames; --samples does not
    fails_with(
        &generate(
            &sim.join("image_2/000000.png"),
            &sim.join("calib/000000.txt"),
            &tmp.path().join("o2"),
            &["--shard-count", "2"],
        ),
        &["--frames"],
    );
    fails_with(
        &run(&sim, &tmp.path().join("o3"), &["--samples", "2"]),
        &["--samples"],
    );
    fails_with(
        &run(
            &sim,
            &tmp.path().join("o3"),
            &["--shard-index", "2", "--shard-count", "2"],
        ),
        &["shard index 2 is not in 0..2"],
    );
    // a frame whose image is not a PNG, another without its calibration: errors name the file
    let bad = tmp.path().join("bad");
    std::fs::create_dir_all(bad.join("image_2")).unwrap();
    std::fs::create_dir_all(bad.join("calib")).unwrap();
    std::fs::write(bad.join("image_2/000000.png"), b"not a png").unwrap();
    std::fs::copy(sim.join("calib/000000.txt"), bad.join("calib/000000.txt")).unwrap();
    fails_with(&run(&bad, &tmp.path().join("o4"), &[]), &["000000.png"]);
    assert!(names(&tmp.path().join("o4/velodyne")).is_empty());
    std::fs::copy(
        sim.join("image_2/000001.png"),
        bad.join("image_2/000001.png"),
    )
    .unwrap();
    fails_with(
        &run(&bad, &tmp.path().join("o5"), &[]),
        &["000001.png", "calib/000001.txt"],
    );
    assert!(!tmp.path().join("o5").exists());
}

#[test]
fn segmenter_pseudo_labels_every_point_and_is_part_of_the_job() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), 2);
    let out = tmp.path().join("labelled");
    ok(&run(&sim, &out, &["--segmenter"]));
    let f = files_in(&out);
    for id in ["000000", "000001"] {
        let bin = &f[&format!("velodyne/{id}.bin")];
        let labels = &f[&format!("labels/{id}.label")];
        // one u32 per 16-byte KITTI record
        assert_eq!(labels.len() * 4, bin.len(), "frame {id}");
    }
    let manifest = String::from_utf8_lossy(&f["dataset.json"]).into_owned();
    assert!(manifest.contains("segmenter manifest sha256"), "{manifest}");
    // the same folder without the segmenter is another job, refused and unchanged
    fails_with(&run(&sim, &out, &[]), &["dataset.json", "another job"]);
    assert_eq!(files_in(&out), f);
    // a segmenter folder that is not one: named, nothing written
    let missing = tmp.path().join("no-segmenter");
    fails_with(
        &run(
            &sim,
            &tmp.path().join("o6"),
            &["--segmenter", missing.to_str().unwrap()],
        ),
        &["no segmenter at", "no-segmenter"],
    );
    assert!(!tmp.path().join("o6").exists());
    // --segmenter belongs to --frames
    fails_with(
        &generate(
            &sim.join("image_2/000000.png"),
            &sim.join("calib/000000.txt"),
            &tmp.path().join("o7"),
            &["--segmenter"],
        ),
        &["--frames"],
    );
}
