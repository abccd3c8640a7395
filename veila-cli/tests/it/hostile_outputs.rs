//! Issue 47, part A: one output discipline. A folder output is wholly old or wholly new, `--force`
//! replaces only the command's own earlier files (recorded in `.veila-outputs.json`), one writer
//! per output folder, leftovers judged by locks (never by a process id) and removed by the next
//! run, and interrupts that say what was kept.

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::common::*;

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn simulate_into(scene: &Path, out: &Path, frames: u32, force: bool) -> Output {
    let mut c = veila();
    c.args(["simulate", "--quiet", "--frames", &frames.to_string()])
        .arg("--scene")
        .arg(scene)
        .arg("--out")
        .arg(out);
    if force {
        c.arg("--force");
    }
    c.output().unwrap()
}

#[test]
fn force_replaces_the_commands_own_files_and_nothing_else() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), &tiny_scene(16, 128, 1), 0);
    let out = tmp.path().join("gen");
    ok(&generate_cmd(&sim, &out, &["--samples", "2"])
        .output()
        .unwrap());
    // a user's file named like an output (the issue's `scan_2024_notes.txt`) and another
    std::fs::write(out.join("scan_2024_notes.txt"), "mine").unwrap();
    std::fs::write(out.join("scan_001_notes.txt"), "mine too").unwrap();
    ok(&generate_cmd(&sim, &out, &["--force"]).output().unwrap());
    let n = names(&out);
    assert!(n.contains(&"scan_2024_notes.txt".to_string()), "{n:?}");
    assert!(n.contains(&"scan_001_notes.txt".to_string()), "{n:?}");
    // the stale second scan of the earlier run went
    assert!(!n.iter().any(|f| f.starts_with("scan_001.")), "{n:?}");
    assert!(n.contains(&"scan_000.bin".to_string()), "{n:?}");
    // `edit --force` into generate's folder deletes none of generate's files: it refuses to write
    // over them, and the folder stays as it was
    let before: Vec<(String, Vec<u8>)> = n
        .iter()
        .map(|f| (f.clone(), std::fs::read(out.join(f)).unwrap()))
        .collect();
    std::fs::copy(out.join("scan_000.bin"), tmp.path().join("scan.bin")).unwrap();
    let o = veila()
        .args(["edit", "--quiet", "--steps", "1", "--force", "--image"])
        .arg(sim.join("image_2/000000.png"))
        .arg("--calib")
        .arg(sim.join("calib/000000.txt"))
        .arg("--scan")
        .arg(tmp.path().join("scan.bin"))
        .args(["--remove-box", "5,-2,-2,15,2,1", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    fails_with(&o, &["was not written there by `veila edit`"]);
    for (f, bytes) in &before {
        assert!(std::fs::read(out.join(f)).unwrap() == *bytes, "{f} changed");
    }
    assert_eq!(names(&out).len(), before.len());
    assert!(
        leftovers(tmp.path()).is_empty(),
        "{:?}",
        leftovers(tmp.path())
    );
}

#[test]
fn simulate_force_over_a_longer_run_leaves_no_stale_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("tiny.toml");
    std::fs::write(&scene, tiny_scene(8, 64, 3)).unwrap();
    let out = tmp.path().join("sim");
    ok(&simulate_into(&scene, &out, 3, false));
    assert_eq!(names(&out.join("velodyne")).len(), 3);
    std::fs::write(out.join("velodyne/README"), "mine").unwrap();
    ok(&simulate_into(&scene, &out, 1, true));
    assert_eq!(names(&out.join("velodyne")), ["000000.bin", "README"]);
    for dir in ["image_2", "calib", "labels", "depth_2", "semantic_2"] {
        if out.join(dir).is_dir() {
            assert_eq!(names(&out.join(dir)).len(), 1, "{dir}");
        }
    }
    let poses = std::fs::read_to_string(out.join("poses.txt")).unwrap_or_default();
    assert!(poses.lines().count() <= 1, "{poses}");
    assert_eq!(leftovers(tmp.path()), Vec::<String>::new());
}

#[test]
fn frames_beyond_the_scene_limit_are_refused_before_work() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("tiny.toml");
    std::fs::write(&scene, tiny_scene(8, 64, 1)).unwrap();
    let out = tmp.path().join("sim");
    let o = simulate_into(&scene, &out, u32::MAX, false);
    fails_with(&o, &["'4294967295' for '--frames", "between 1 and 100000"]);
    assert!(!out.exists());
    assert!(names(tmp.path()) == ["tiny.toml"]);
}

#[cfg(unix)]
#[test]
fn a_second_writer_is_refused_and_a_killed_one_is_cleaned_up_by_the_next() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), &tiny_scene(16, 128, 1), 0);
    let out = tmp.path().join("gen");
    ok(&generate_cmd(&sim, &out, &[]).output().unwrap());
    let old = std::fs::read(out.join("generate.json")).unwrap();
    let mut first = long_generate(&sim, &out, &["--force"]);
    // the second writer of the same folder (another spelling of it) gets a clear error at once
    let other = tmp.path().join(".").join("gen");
    let o = generate_cmd(&sim, &other, &["--force", "--seed", "7"])
        .output()
        .unwrap();
    fails_with(&o, &["another veila process is writing"]);
    // SIGKILL: the old output stays whole; the staging folder and lock file wait for the next run
    signal(&first, "-KILL");
    first.wait().unwrap();
    assert_eq!(std::fs::read(out.join("generate.json")).unwrap(), old);
    assert!(!leftovers(tmp.path()).is_empty());
    // a leftover whose process id is alive is still removed: liveness is the lock, not the pid
    let fake = tmp
        .path()
        .join(format!(".veila-staging-{}-abc", std::process::id()));
    std::fs::create_dir(&fake).unwrap();
    ok(&generate_cmd(&sim, &out, &["--force", "--seed", "7"])
        .output()
        .unwrap());
    assert_ne!(std::fs::read(out.join("generate.json")).unwrap(), old);
    assert_eq!(leftovers(tmp.path()), Vec::<String>::new());
}

#[cfg(unix)]
#[test]
fn an_interrupt_says_what_was_kept_and_leaves_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), &tiny_scene(16, 128, 1), 0);
    let out = tmp.path().join("gen");
    ok(&generate_cmd(&sim, &out, &[]).output().unwrap());
    let old = std::fs::read(out.join("scan_000.bin")).unwrap();
    for sig in ["-INT", "-TERM"] {
        let child = long_generate(&sim, &out, &["--force"]);
        signal(&child, sig);
        let o = child.wait_with_output().unwrap();
        assert!(!o.status.success());
        let e = stderr(&o);
        assert!(
            e.contains("interrupted: nothing was written to") && e.contains("left as it was"),
            "{sig}: {e}"
        );
        assert_eq!(std::fs::read(out.join("scan_000.bin")).unwrap(), old);
        assert_eq!(leftovers(tmp.path()), Vec::<String>::new(), "{sig}");
    }
}

/// What a killed swap leaves, restored by whichever veila writes beside it next.
#[test]
fn a_half_done_swap_is_finished_by_the_next_writer_beside_it() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("tiny.toml");
    std::fs::write(&scene, tiny_scene(8, 64, 1)).unwrap();
    // killed after moving the old output aside, before the new one arrived
    let backup = tmp.path().join(".veila-backup.old");
    std::fs::create_dir(&backup).unwrap();
    std::fs::write(backup.join("keep.txt"), "old output").unwrap();
    std::fs::create_dir(tmp.path().join(".veila-staging.old.Ab12Cd")).unwrap();
    std::fs::write(tmp.path().join(".veila-lock.old"), "").unwrap();
    // and killed after the swap, before the backup was removed
    std::fs::create_dir(tmp.path().join("new")).unwrap();
    std::fs::create_dir(tmp.path().join(".veila-backup.new")).unwrap();
    ok(&simulate_into(&scene, &tmp.path().join("sim"), 1, false));
    assert_eq!(
        std::fs::read_to_string(tmp.path().join("old/keep.txt")).unwrap(),
        "old output"
    );
    assert_eq!(names(tmp.path()), ["new", "old", "sim", "tiny.toml"]);
}

#[test]
fn the_manifest_is_the_same_for_identical_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("tiny.toml");
    std::fs::write(&scene, tiny_scene(8, 64, 2)).unwrap();
    let runs: Vec<PathBuf> = ["a", "b"].iter().map(|n| tmp.path().join(n)).collect();
    for r in &runs {
        ok(&simulate_into(&scene, r, 2, false));
    }
    let m: Vec<Vec<u8>> = runs
        .iter()
        .map(|r| std::fs::read(r.join(".veila-outputs.json")).unwrap())
        .collect();
    assert_eq!(m[0], m[1]);
    let v: serde_json::Value = serde_json::from_slice(&m[0]).unwrap();
    let files = v["commands"]["simulate"].as_array().unwrap();
    assert!(files.iter().any(|f| f == "velodyne/000001.bin"), "{v}");
}

/// Printing to a full disk (`/dev/full` as standard output) is an error with a clear message and a
/// non-zero exit, never a panic; `generate` keeps what it published before the report failed.
#[cfg(target_os = "linux")]
#[test]
fn printing_to_a_full_disk_is_an_error_not_a_panic() {
    let full = || {
        std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap()
    };
    let check = |what: &str, o: &Output| {
        let e = stderr(o);
        assert_eq!(o.status.code(), Some(1), "{what}: {e}");
        assert!(
            e.contains("cannot write to standard output") && e.contains("No space left"),
            "{what}: {e}"
        );
        assert!(!e.contains("panicked"), "{what}: {e}");
    };
    for args in [
        &["sensors"][..],
        &["sensors", "hdl32e"],
        &["completions", "bash"],
    ] {
        let o = veila().args(args).stdout(full()).output().unwrap();
        check(&args.join(" "), &o);
    }
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), &tiny_scene(16, 128, 1), 0);
    let out = tmp.path().join("gen");
    let o = generate_cmd(&sim, &out, &[])
        .stdout(full())
        .output()
        .unwrap();
    check("generate", &o);
    assert!(out.join("scan_000.bin").is_file() && out.join("generate.json").is_file());
}
