//! `veila convert` killed (SIGKILL) at random points and resumed gives byte-identical shards,
//! sidecars and manifest to an uninterrupted run, leaves no temporary shard behind, and notices a
//! frame whose contents changed under the same id.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_data::image::{Rgb, RgbImage};

const CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\nP2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\nTr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n";

fn scan(f: usize, shift: f32) -> Vec<u8> {
    (0..2000)
        .flat_map(|i| {
            let a = i as f32 * 0.031 + f as f32;
            let r = 4.0 + (i % 13) as f32 + shift;
            [
                r * a.cos(),
                r * a.sin(),
                -1.5 + 0.001 * i as f32,
                (i % 10) as f32 / 10.0,
            ]
        })
        .flat_map(|v| v.to_le_bytes())
        .collect()
}

/// A KITTI object tree of `frames` frames (2000 points, a 60 x 30 image each).
fn make_kitti(root: &Path, frames: usize) {
    let t = root.join("training");
    for d in ["velodyne", "image_2", "calib"] {
        std::fs::create_dir_all(t.join(d)).unwrap();
    }
    for f in 0..frames {
        let id = format!("{f:06}");
        std::fs::write(t.join(format!("velodyne/{id}.bin")), scan(f, 0.0)).unwrap();
        RgbImage::from_fn(60, 30, |x, y| Rgb([(x + f as u32) as u8, y as u8, 3]))
            .save(t.join(format!("image_2/{id}.png")))
            .unwrap();
        std::fs::write(t.join(format!("calib/{id}.txt")), CALIB).unwrap();
    }
}

fn convert(root: &Path, out: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_veila"));
    c.args([
        "convert",
        "--quiet",
        "--dataset",
        "kitti",
        "--frames-per-shard",
        "2",
    ])
    .args(["--sensor", "hdl64e", "--root"])
    .arg(root)
    .arg("--out")
    .arg(out)
    .stdout(Stdio::piped())
    .stderr(Stdio::piped());
    c
}

fn run_ok(root: &Path, out: &Path) -> serde_json::Value {
    let o = convert(root, out).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// Every file of `dir`, sorted.
fn listing(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| PathBuf::from(e.unwrap().file_name()))
        .collect();
    v.sort();
    v
}

fn assert_same(a: &Path, b: &Path) {
    let la = listing(a);
    assert_eq!(la, listing(b));
    for f in la {
        assert!(
            std::fs::read(a.join(&f)).unwrap() == std::fs::read(b.join(&f)).unwrap(),
            "{} differs",
            f.display()
        );
    }
}

#[cfg(unix)]
#[test]
#[ignore = "kill-and-resume (about a minute): cargo test -p veila-cli --test it convert:: -- --ignored"]
fn killed_conversions_resume_to_the_uninterrupted_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("kitti");
    make_kitti(&root, 12);
    let reference = tmp.path().join("ref");
    let t = Instant::now();
    let summary = run_ok(&root, &reference);
    let full = t.elapsed();
    assert_eq!(summary["written_shards"], 6);
    assert!(reference.join("manifest.json").is_file());

    // SIGKILL at random points of the run (seeded), resume each time
    let out = tmp.path().join("out");
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let mut kills = 0;
    for _ in 0..6 {
        let mut child = convert(&root, &out).spawn().unwrap();
        let at = Duration::from_secs_f64(full.as_secs_f64() * rng.random_range(0.05..1.0));
        std::thread::sleep(at);
        let killed = Command::new("kill")
            .args(["-KILL", &child.id().to_string()])
            .status()
            .unwrap()
            .success();
        let st = child.wait().unwrap();
        if killed && !st.success() {
            kills += 1;
        }
    }
    let summary = run_ok(&root, &out);
    assert!(summary["manifest_written"].as_bool().unwrap());
    assert_same(&reference, &out);
    assert!(
        listing(&out)
            .iter()
            .map(|f| f.to_string_lossy().into_owned())
            .all(|f| !f.starts_with(".veila-") || f.starts_with(".veila-convert.")),
        "temporary files left: {:?}",
        listing(&out)
    );
    eprintln!("{kills} of 6 runs were killed before they finished");

    // a rerun over complete shards rewrites nothing
    let summary = run_ok(&root, &out);
    assert_eq!(summary["written_shards"], 0);
    assert_eq!(summary["skipped_shards"], 6);

    // frame 5 changes under the same id (same size): its shard (2) is rebuilt, nothing else
    std::fs::write(root.join("training/velodyne/000005.bin"), scan(5, 0.5)).unwrap();
    let summary = run_ok(&root, &out);
    assert_eq!(summary["written_shards"], 1, "{summary}");
    let fresh = tmp.path().join("fresh");
    run_ok(&root, &fresh);
    assert_same(&fresh, &out);
    let shard2 = |d: &Path| {
        let m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.join("manifest.json")).unwrap()).unwrap();
        m["shards"][2]["sha256"].as_str().unwrap().to_string()
    };
    assert_ne!(shard2(&reference), shard2(&out));
}

#[test]
fn converts_a_small_kitti_tree_and_names_a_missing_root() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("kitti");
    make_kitti(&root, 3);
    let out = tmp.path().join("shards");
    let summary = run_ok(&root, &out);
    assert_eq!(summary["written_shards"], 2, "{summary}");
    assert!(summary["manifest_written"].as_bool().unwrap());
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(
        manifest["shards"].as_array().map(Vec::len),
        Some(2),
        "{manifest}"
    );
    assert_eq!(manifest["count"], 3, "{manifest}");

    let missing = tmp.path().join("no-such-dataset");
    let o = convert(&missing, &tmp.path().join("out2"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("no-such-dataset"), "{err}");
    assert!(!tmp.path().join("out2").join("manifest.json").exists());
}
