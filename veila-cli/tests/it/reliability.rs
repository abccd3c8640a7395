//! Issue 17, "nothing the user had is ever lost": every case of the report as a test. Inputs are
//! never outputs (whatever the spelling), outputs appear whole or not at all, nothing is replaced
//! without `--force`, resources are bounded by the input's sense rather than its claims, interrupts
//! leave nothing behind, and identical runs write identical bytes.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use veila_data::PointCloud;
use veila_data::image::{Rgb, RgbImage};

use crate::common::*;

// ------------------------------------------------------------------------------------ helpers

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A small KITTI scan: a ring of points around the sensor.
fn scan_bytes() -> Vec<u8> {
    let n = 400;
    let cloud = PointCloud {
        xyz: (0..n)
            .map(|i| {
                let a = i as f32 * 0.05;
                glam::Vec3::new(10.0 * a.cos(), 10.0 * a.sin(), -1.0 + 0.002 * i as f32)
            })
            .collect(),
        intensity: (0..n).map(|i| (i % 10) as f32 / 10.0).collect(),
        ring: None,
        label: None,
    };
    veila_data::scan::encode_kitti_bin(&cloud)
}

fn png_bytes() -> Vec<u8> {
    veila_data::image_io::encode_png(&RgbImage::from_fn(40, 12, |x, y| {
        Rgb([(x * 6) as u8, (y * 20) as u8, 90])
    }))
    .unwrap()
}

const KITTI_CALIB: &str = "P0: 30 0 20 0 0 30 6 0 0 0 1 0\nP1: 30 0 20 0 0 30 6 0 0 0 1 0\nP2: 30 0 20 0 0 30 6 0 0 0 1 0\nP3: 30 0 20 0 0 30 6 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\nTr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n";

/// A folder with `scan.bin`, `img.png` and `calib.txt`.
fn inputs() -> tempfile::TempDir {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(d.path().join("scan.bin"), scan_bytes()).unwrap();
    std::fs::write(d.path().join("img.png"), png_bytes()).unwrap();
    std::fs::write(d.path().join("calib.txt"), KITTI_CALIB).unwrap();
    d
}

fn read(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// Every file under `dir` (relative paths, sorted) except `skip`.
fn files(dir: &Path, skip: &[&str]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![PathBuf::new()];
    while let Some(rel) = stack.pop() {
        for e in std::fs::read_dir(dir.join(&rel)).unwrap() {
            let e = e.unwrap();
            let r = rel.join(e.file_name());
            if e.path().is_dir() {
                stack.push(r);
            } else if !skip.contains(&r.to_string_lossy().as_ref()) {
                out.push(r);
            }
        }
    }
    out.sort();
    out
}

fn assert_same_tree(a: &Path, b: &Path, skip: &[&str]) {
    let fa = files(a, skip);
    assert_eq!(fa, files(b, skip));
    assert!(!fa.is_empty());
    for f in &fa {
        assert!(
            read(&a.join(f)) == read(&b.join(f)),
            "{} differs",
            f.display()
        );
    }
}

fn weather(dir: &Path) -> Command {
    let mut c = veila();
    c.current_dir(dir).arg("weather");
    c
}

// --------------------------------------------------------- 1. weather overwrote its own inputs

#[test]
fn weather_refuses_every_spelling_of_an_input_as_output() {
    let d = inputs();
    let p = d.path();
    let before = read(&p.join("scan.bin"));
    let abs = p.display().to_string();
    for out in [".", "./", abs.as_str(), "sub/.."] {
        if out == "sub/.." {
            std::fs::create_dir_all(p.join("sub")).unwrap();
        }
        let o = weather(p)
            .args(["scan.bin", "--fog-visibility", "50", "--out", out])
            .output()
            .unwrap();
        fails_with(&o, &["scan.bin", "input"]);
        assert_eq!(read(&p.join("scan.bin")), before, "--out {out}");
        // --force does not make an input an output either
        let o = weather(p)
            .args([
                "scan.bin",
                "--fog-visibility",
                "50",
                "--force",
                "--out",
                out,
            ])
            .output()
            .unwrap();
        fails_with(&o, &["input"]);
        assert_eq!(read(&p.join("scan.bin")), before, "--out {out} --force");
    }
    // the image, through the night preset
    let img = read(&p.join("img.png"));
    std::fs::create_dir(p.join("o")).unwrap();
    std::fs::copy(p.join("scan.bin"), p.join("o/other.bin")).unwrap();
    let o = weather(p)
        .args(["o/other.bin", "--image", "img.png", "--calib", "calib.txt"])
        .args(["--preset", "kitti-night", "--out", "."])
        .output()
        .unwrap();
    fails_with(&o, &["img.png", "input"]);
    assert_eq!(read(&p.join("img.png")), img);
    assert!(leftovers(p).is_empty(), "{:?}", leftovers(p));
}

#[cfg(unix)]
#[test]
fn links_to_an_input_are_the_input() {
    let d = inputs();
    let p = d.path();
    std::fs::create_dir(p.join("o")).unwrap();
    std::fs::hard_link(p.join("scan.bin"), p.join("o/scan.bin")).unwrap();
    let o = weather(p)
        .args([
            "scan.bin",
            "--fog-visibility",
            "50",
            "--force",
            "--out",
            "o",
        ])
        .output()
        .unwrap();
    fails_with(&o, &["input"]);
    std::os::unix::fs::symlink(p.join("scan.bin"), p.join("link.exr")).unwrap();
    let o = veila()
        .current_dir(p)
        .args(["project", "scan.bin", "--force", "--out", "link.exr"])
        .output()
        .unwrap();
    fails_with(&o, &["input"]);
    assert_eq!(read(&p.join("scan.bin")), scan_bytes());
}

// ---------------------------------- 2. project replaced its scan, any extension, no --force

#[test]
fn project_checks_names_inputs_and_existing_files() {
    let d = inputs();
    let p = d.path();
    let project = |args: &[&str]| {
        veila()
            .current_dir(p)
            .arg("project")
            .args(args)
            .output()
            .unwrap()
    };
    fails_with(&project(&["scan.bin", "--out", "scan.bin"]), &["scan.bin"]);
    assert_eq!(read(&p.join("scan.bin")), scan_bytes());
    fails_with(
        &project(&["scan.bin", "--out", "o.txt"]),
        &["o.txt", ".exr"],
    );
    assert!(!p.join("o.txt").exists());
    fails_with(
        &project(&["scan.bin", "--out", "o.exr", "--png", "o.jpg"]),
        &["o.jpg", ".png"],
    );
    ok(&project(&["scan.bin", "--out", "o.exr"]));
    let first = read(&p.join("o.exr"));
    std::fs::write(p.join("o.exr"), b"keep me").unwrap();
    fails_with(
        &project(&["scan.bin", "--out", "o.exr"]),
        &["o.exr", "--force"],
    );
    assert_eq!(read(&p.join("o.exr")), b"keep me");
    ok(&project(&["scan.bin", "--out", "o.exr", "--force"]));
    assert_eq!(read(&p.join("o.exr")), first);
    // the same file twice among the outputs
    fails_with(
        &project(&[
            "scan.bin",
            "--out",
            "b.exr",
            "--png",
            "x.png",
            "--intensity-png",
            "./x.png",
        ]),
        &["same file"],
    );
    // unproject and render follow the same rules
    let o = veila()
        .current_dir(p)
        .args(["unproject", "o.exr", "--out", "scan.bin"])
        .output()
        .unwrap();
    fails_with(&o, &["scan.bin"]);
    assert_eq!(read(&p.join("scan.bin")), scan_bytes());
    let o = veila()
        .current_dir(p)
        .args(["render", "scan.bin", "--bev", "img.png"])
        .output()
        .unwrap();
    fails_with(&o, &["img.png"]);
    assert_eq!(read(&p.join("img.png")), png_bytes());
    assert!(!p.join("b.exr").exists());
    assert!(leftovers(p).is_empty(), "{:?}", leftovers(p));
}

// ------------------------------------------------------------- 3. --samples in bounded batches

#[test]
fn samples_stream_in_batches_and_identical_runs_write_identical_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), &tiny_scene(16, 128, 1), 0);
    let gen_ = |out: &str, samples: &str| {
        let o = veila()
            .args([
                "generate",
                "--quiet",
                "--steps",
                "1",
                "--samples",
                samples,
                "--image",
            ])
            .arg(sim.join("image_2/000000.png"))
            .arg("--calib")
            .arg(sim.join("calib/000000.txt"))
            .arg("--out")
            .arg(tmp.path().join(out))
            .output()
            .unwrap();
        ok(&o);
        tmp.path().join(out)
    };
    let a = gen_("a", "9");
    let b = gen_("b", "9");
    let c = gen_("c", "8");
    // 3. nine samples are two batches: the record says so, and the second batch has its own noise
    let rec: serde_json::Value = serde_json::from_slice(&read(&a.join("generate.json"))).unwrap();
    assert_eq!(rec["sample_batch"], 8);
    assert_eq!(rec["scans"].as_array().unwrap().len(), 9);
    assert!(a.join("scan_008.bin").is_file());
    assert_ne!(read(&a.join("scan_008.bin")), read(&a.join("scan_000.bin")));
    // the first batch is the same whatever follows it
    for i in 0..8 {
        let f = format!("scan_{i:03}.exr");
        assert!(read(&a.join(&f)) == read(&c.join(&f)), "{f}");
    }
    // 8. timings live apart: every other output of identical runs is byte-identical
    assert!(rec.get("seconds").is_none());
    let t: serde_json::Value = serde_json::from_slice(&read(&a.join("timings.json"))).unwrap();
    assert!(t["sampling"].is_number());
    assert_same_tree(&a, &b, &["timings.json"]);

    // 8. --force drops the stale scans of a bigger earlier run, and only the command's own files
    std::fs::write(a.join("notes.txt"), b"mine").unwrap();
    let o = veila()
        .args(["generate", "--quiet", "--steps", "1", "--force", "--image"])
        .arg(sim.join("image_2/000000.png"))
        .arg("--calib")
        .arg(sim.join("calib/000000.txt"))
        .arg("--out")
        .arg(&a)
        .output()
        .unwrap();
    ok(&o);
    let names: Vec<String> = files(&a, &[])
        .iter()
        .map(|p| p.display().to_string())
        .collect();
    assert!(
        names
            .iter()
            .filter(|n| n.starts_with("scan_"))
            .all(|n| n.starts_with("scan_000")),
        "{names:?}"
    );
    assert!(names.contains(&"scan_000.bin".to_string()), "{names:?}");
    assert!(a.join("notes.txt").is_file(), "a user's file was removed");
    let rec: serde_json::Value = serde_json::from_slice(&read(&a.join("generate.json"))).unwrap();
    assert_eq!(rec["scans"].as_array().unwrap().len(), 1);
    // and generate refuses to write its outputs over one of its inputs (the overlay has the size
    // of the camera image, so it is a usable input)
    let overlay = read(&a.join("scan_000_overlay.png"));
    let o = veila()
        .args(["generate", "--quiet", "--steps", "1", "--force", "--image"])
        .arg(a.join("scan_000_overlay.png"))
        .arg("--calib")
        .arg(sim.join("calib/000000.txt"))
        .arg("--out")
        .arg(&a)
        .output()
        .unwrap();
    fails_with(&o, &["scan_000_overlay.png", "input"]);
    assert_eq!(read(&a.join("scan_000_overlay.png")), overlay);
    assert!(
        leftovers(tmp.path()).is_empty(),
        "{:?}",
        leftovers(tmp.path())
    );
}

#[test]
fn demo_reruns_are_byte_identical_apart_from_timings() {
    let tmp = tempfile::tempdir().unwrap();
    let run = |out: &str| {
        ok(&veila()
            .args([
                "demo",
                "--quiet",
                "--steps",
                "1",
                "--baseline-frames",
                "2",
                "--out",
            ])
            .arg(tmp.path().join(out))
            .output()
            .unwrap());
        tmp.path().join(out)
    };
    let a = run("a");
    let b = run("b");
    let m: serde_json::Value = serde_json::from_slice(&read(&a.join("metrics.json"))).unwrap();
    assert!(m.get("seconds_generation").is_none());
    assert!(a.join("timings.json").is_file());
    assert_same_tree(&a, &b, &["timings.json"]);
}

// ----------------------------------------------------------- 4. sensor size in total pixels

#[test]
fn a_huge_sensor_file_is_refused_by_its_pixel_count() {
    let d = inputs();
    let p = d.path();
    let mut s = veila_geom::LidarSensor::hdl64e();
    s.rows = 4096;
    s.cols = 262_144;
    std::fs::write(p.join("big.toml"), toml::to_string(&s).unwrap()).unwrap();
    let o = veila()
        .current_dir(p)
        .args([
            "project", "scan.bin", "--sensor", "big.toml", "--out", "o.exr",
        ])
        .output()
        .unwrap();
    fails_with(&o, &["big.toml", "pixels", "limit"]);
    assert!(!p.join("o.exr").exists());
}

// ----------------------------------------------- 5, 6. weather: staged, and inputs checked first

#[test]
fn weather_checks_inputs_before_creating_anything_and_publishes_all_or_nothing() {
    let d = inputs();
    let p = d.path();
    // a missing input: --out is not created
    let o = weather(p)
        .args(["missing.bin", "--fog-visibility", "50", "--out", "new"])
        .output()
        .unwrap();
    fails_with(&o, &["missing.bin"]);
    assert!(!p.join("new").exists());
    // one output cannot be written (a folder is in the way): no other output appears
    std::fs::create_dir_all(p.join("o/effects.json")).unwrap();
    let o = weather(p)
        .args([
            "scan.bin",
            "--image",
            "img.png",
            "--fog-visibility",
            "50",
            "--out",
            "o",
        ])
        .output()
        .unwrap();
    fails_with(&o, &["effects.json"]);
    assert!(!p.join("o/scan.bin").exists() && !p.join("o/img.png").exists());
    // an existing output is not replaced without --force
    std::fs::remove_dir(p.join("o/effects.json")).unwrap();
    std::fs::write(p.join("o/scan.bin"), b"old").unwrap();
    let o = weather(p)
        .args(["scan.bin", "--fog-visibility", "50", "--out", "o"])
        .output()
        .unwrap();
    fails_with(&o, &["scan.bin", "--force"]);
    assert_eq!(read(&p.join("o/scan.bin")), b"old");
    assert!(!p.join("o/effects.json").exists());
    let o = weather(p)
        .args([
            "scan.bin",
            "--fog-visibility",
            "50",
            "--force",
            "--out",
            "o",
        ])
        .output()
        .unwrap();
    ok(&o);
    assert!(p.join("o/effects.json").is_file());
    assert!(leftovers(&p.join("o")).is_empty());
}

/// A PNG whose header claims `w x h` pixels (the CRC fixed so only the size is implausible).
fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    let mut b = png_bytes();
    b[16..20].copy_from_slice(&w.to_be_bytes());
    b[20..24].copy_from_slice(&h.to_be_bytes());
    let crc = crc32(&b[12..29]);
    b[29..33].copy_from_slice(&crc.to_be_bytes());
    b
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &byte in data {
        c ^= u32::from(byte);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

#[test]
fn weather_without_effects_still_checks_its_inputs() {
    let d = inputs();
    let p = d.path();
    let mut truncated = scan_bytes();
    truncated.truncate(truncated.len() - 5);
    std::fs::write(p.join("cut.bin"), truncated).unwrap();
    std::fs::write(
        p.join("noise.bin"),
        (0..4003u32)
            .map(|i| (i * 7919 % 251) as u8)
            .collect::<Vec<u8>>(),
    )
    .unwrap();
    std::fs::write(p.join("bomb.png"), png_claiming(100_000, 100_000)).unwrap();
    for (scan, image) in [
        ("cut.bin", None),
        ("noise.bin", None),
        ("scan.bin", Some("bomb.png")),
    ] {
        let mut c = weather(p);
        c.arg(scan);
        if let Some(i) = image {
            c.args(["--image", i]);
        }
        let o = c.args(["--out", "o"]).output().unwrap();
        fails_with(&o, &[image.unwrap_or(scan)]);
        assert!(!p.join("o").exists(), "{scan}");
    }
    // and a good frame still passes through byte for byte
    let o = weather(p)
        .args(["scan.bin", "--image", "img.png", "--out", "o"])
        .output()
        .unwrap();
    ok(&o);
    assert_eq!(read(&p.join("o/scan.bin")), scan_bytes());
    assert_eq!(read(&p.join("o/img.png")), png_bytes());
}

// ------------------------------------------------------------------------- 7. interrupts

/// Starts a long `veila generate` into `tmp/out` and waits until its staging folder exists.
fn long_generate(tmp: &Path, sim: &Path) -> std::process::Child {
    crate::common::long_generate(sim, &tmp.join("out"), &[])
}

#[cfg(unix)]
#[test]
fn interrupts_leave_nothing_behind_and_killed_runs_are_swept() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate(tmp.path(), &tiny_scene(16, 128, 1), 0);
    for signal in ["-INT", "-TERM"] {
        let mut child = long_generate(tmp.path(), &sim);
        crate::common::signal(&child, signal);
        let st = child.wait().unwrap();
        assert!(!st.success(), "{signal}");
        assert!(
            leftovers(tmp.path()).is_empty(),
            "{signal}: {:?}",
            leftovers(tmp.path())
        );
        assert!(!tmp.path().join("out").exists());
    }
    // SIGKILL cannot be caught: the staging folder and the lock file stay until the next veila
    // writes beside them
    let mut child = long_generate(tmp.path(), &sim);
    crate::common::signal(&child, "-KILL");
    child.wait().unwrap();
    let mut left = leftovers(tmp.path());
    left.sort();
    assert_eq!(left.len(), 2, "{left:?}");
    assert_eq!(left[0], ".veila-lock.out");
    assert!(left[1].starts_with(".veila-staging.out."), "{left:?}");
    // a temporary file of another dead process, too
    std::fs::write(tmp.path().join(".veila-4194999-abc.tmp"), b"x").unwrap();
    let d = inputs();
    std::fs::copy(d.path().join("scan.bin"), tmp.path().join("scan.bin")).unwrap();
    ok(&veila()
        .current_dir(tmp.path())
        .args(["project", "scan.bin", "--out", "scan.exr"])
        .output()
        .unwrap());
    assert!(
        leftovers(tmp.path()).is_empty(),
        "{:?}",
        leftovers(tmp.path())
    );
}

// ---------------------------------------------------------------------- 8. smaller problems

#[test]
fn sampler_settings_outside_their_sense_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let gen_ = |args: &[&str]| {
        veila()
            .args(["generate", "--image", "i.png", "--calib", "c.txt", "--out"])
            .arg(tmp.path().join("o"))
            .args(args)
            .output()
            .unwrap()
    };
    // the parser takes a negative number as a value (no `-- -5` hint), and the range check refuses it
    let o = gen_(&["--guidance", "-5"]);
    fails_with(&o, &["'-5' for '--guidance", "between 0 and 20"]);
    assert!(!stderr(&o).contains("-- -5"));
    fails_with(&gen_(&["--guidance", "1e300"]), &["between 0 and 20"]);
    fails_with(&gen_(&["--guidance", "NaN"]), &["between 0 and 20"]);
    // the help says 1 to 1000 steps: 0 is refused by the parser (the mean network alone of a
    // residual bundle is --residual-weight 0)
    fails_with(
        &gen_(&["--steps", "0"]),
        &["'0' for '--steps", "between 1 and 1000"],
    );
    for w in ["2", "-0.5", "NaN"] {
        fails_with(
            &gen_(&["--residual-weight", w]),
            &[&format!("'{w}' for '--residual-weight"), "between 0 and 1"],
        );
    }
    fails_with(&gen_(&["--steps", "1000000"]), &["between 1 and 1000"]);
    fails_with(&gen_(&["--samples", "0"]), &["--samples"]);
    let o = veila()
        .args([
            "edit", "--image", "i.png", "--calib", "c.txt", "--scan", "s.bin",
        ])
        .args(["--remove-box", "0,0,0,1,1,1", "--guidance", "-5", "--out"])
        .arg(tmp.path().join("o"))
        .output()
        .unwrap();
    fails_with(&o, &["between 0 and 20"]);
    assert!(!tmp.path().join("o").exists());
}

#[test]
fn all_nan_and_oversized_scans_are_refused_before_work() {
    let d = inputs();
    let p = d.path();
    let nan: Vec<u8> = (0..64).flat_map(|_| f32::NAN.to_le_bytes()).collect();
    std::fs::write(p.join("nan.bin"), nan).unwrap();
    let o = veila()
        .current_dir(p)
        .args(["project", "nan.bin", "--out", "o.exr"])
        .output()
        .unwrap();
    fails_with(&o, &["nan.bin", "non-finite"]);
    // 2 GiB of zeros (sparse: no disk used) is rejected from its length, not read
    let f = std::fs::File::create(p.join("huge.bin")).unwrap();
    f.set_len(2 << 30).unwrap();
    let o = veila()
        .current_dir(p)
        .args(["project", "huge.bin", "--out", "o.exr"])
        .output()
        .unwrap();
    fails_with(&o, &["huge.bin", "points, more than"]);
    assert!(!p.join("o.exr").exists());
}

#[test]
fn calibration_and_sensor_errors_name_their_file() {
    let d = inputs();
    let p = d.path();
    // a nuScenes sample without cameras
    let json = r#"{"sample_token": "t0",
      "lidar": {"file": "x.pcd.bin", "lidar2ego": {"matrix_4x4_row_major": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}},
      "ego2global_at_lidar_time": {"matrix_4x4_row_major": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
      "cameras": {}}"#;
    std::fs::write(p.join("sample.json"), json).unwrap();
    let render = |calib: &str| {
        veila()
            .current_dir(p)
            .args(["render", "scan.bin", "--image", "img.png", "--calib", calib])
            .args(["--overlay", "ov.png"])
            .output()
            .unwrap()
    };
    let o = render("sample.json");
    fails_with(&o, &["sample.json", "CAM_FRONT"]);
    assert!(!stderr(&o).contains("(has )"), "{}", stderr(&o));
    // a transform that is not rigid (scaled by 2)
    let scaled = KITTI_CALIB.replace(
        "Tr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0",
        "Tr_velo_to_cam: 0 -2 0 0 0 0 -2 0 2 0 0 0",
    );
    std::fs::write(p.join("scaled.txt"), scaled).unwrap();
    fails_with(&render("scaled.txt"), &["scaled.txt", "rigid"]);
    // a mirror is not a rotation either
    let mirrored = KITTI_CALIB.replace("R0_rect: 1 0 0 0 1 0 0 0 1", "R0_rect: -1 0 0 0 1 0 0 0 1");
    std::fs::write(p.join("mirror.txt"), mirrored).unwrap();
    fails_with(&render("mirror.txt"), &["mirror.txt", "rigid"]);
    assert!(!p.join("ov.png").exists());
    // the ring-sensor error names the scan
    let o = veila()
        .current_dir(p)
        .args([
            "project",
            "scan.bin",
            "--sensor",
            "hdl32e-per-beam",
            "--out",
            "o.exr",
        ])
        .output()
        .unwrap();
    fails_with(&o, &["scan.bin", "ring"]);
}
