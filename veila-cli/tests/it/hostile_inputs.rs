//! Issue 47, parts B to D: every size from an input or an argument is checked before anything is
//! allocated, and the error names the file or the argument; cm-sc refuses a class map outside the
//! id space it was told; `veila sensors` prints a valid sensor file for every preset.

use std::path::{Path, PathBuf};

use crate::common::*;

/// Seeded values in [0, 1) (a linear congruential generator).
fn values(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect()
}

#[test]
fn fd_refuses_a_feature_width_it_cannot_hold_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    // the two 1 MB arrays of shape (4, 65536): a 65536 x 65536 covariance is 34 GB
    let (a, b) = (tmp.path().join("a.npy"), tmp.path().join("b.npy"));
    npy_f32(&a, "(4, 65536)", &values(4 * 65536, 1));
    npy_f32(&b, "(4, 65536)", &values(4 * 65536, 2));
    let o = veila().arg("fd").arg(&a).arg(&b).output().unwrap();
    fails_with(&o, &["a.npy", "at most 4096 features", "65536"]);
}

#[test]
fn fd_newton_schulz_iterations_are_range_checked() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a.npy"), tmp.path().join("b.npy"));
    npy_f32(&a, "(40, 3)", &values(120, 1));
    npy_f32(&b, "(40, 3)", &values(120, 2));
    for n in ["0", "1001"] {
        let o = veila()
            .arg("fd")
            .arg(&a)
            .arg(&b)
            .args(["--newton-schulz", n])
            .output()
            .unwrap();
        fails_with(&o, &["--newton-schulz", "between 1 and 1000"]);
    }
    // a sane count agrees with the exact method (well-conditioned 3 x 3 covariances)
    let value = |extra: &[&str]| -> f64 {
        let json = tmp.path().join("fd.json");
        let o = veila()
            .arg("fd")
            .arg(&a)
            .arg(&b)
            .args(extra)
            .args(["--force", "--json"])
            .arg(&json)
            .output()
            .unwrap();
        ok(&o);
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
        v["metrics"][0]["value"].as_f64().unwrap()
    };
    let exact = value(&[]);
    let ns = value(&["--newton-schulz", "50"]);
    assert!(
        (exact - ns).abs() <= 1e-6 * exact.abs().max(1e-3),
        "{exact} vs {ns}"
    );
}

#[test]
fn sensors_prints_a_valid_file_for_every_preset() {
    let tmp = tempfile::tempdir().unwrap();
    for preset in veila_geom::SensorPreset::ALL {
        let (name, default) = (
            preset.as_str(),
            preset == veila_geom::SensorPreset::default(),
        );
        let mut c = veila();
        c.arg("sensors");
        if !default {
            c.arg(name);
        }
        let o = c.output().unwrap();
        ok(&o);
        // a valid TOML document (no duplicate keys) describing exactly the preset
        let text = String::from_utf8(o.stdout).unwrap();
        let parsed: veila_geom::LidarSensor =
            toml::from_str(&text).unwrap_or_else(|e| panic!("{name}: {e}\n{text}"));
        assert_eq!(parsed, preset.sensor(), "{name}");
        // and the file works where a sensor file is taken
        let p = tmp.path().join(format!("{name}.toml"));
        std::fs::write(&p, &text).unwrap();
        assert_eq!(
            veila_data::spec::sensor_from_spec(p.to_str().unwrap()).unwrap(),
            parsed
        );
    }
    fails_with(
        &veila().args(["sensors", "vlp16"]).output().unwrap(),
        &["vlp16", "hdl32e-per-beam"],
    );
}

/// `veila simulate` of the bundled straight road into `dir/sim`, two frames.
fn simulate_road(dir: &Path) -> PathBuf {
    let out = dir.join("sim");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/straight_road.toml");
    ok(&veila()
        .args([
            "simulate", "--quiet", "--frames", "1", "--seed", "7", "--scene",
        ])
        .arg(scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap());
    out
}

#[test]
fn cm_sc_refuses_raw_ids_read_as_train_ids() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = simulate_road(tmp.path());
    // simulate's class maps hold SemanticKITTI raw ids: read as train ids (the default) they
    // would compare 40 (road) with 9 (road) and report ~0 %; refused, naming the map
    let o = veila()
        .args(["eval", "--quiet", "--metrics", "cm-sc", "--generated"])
        .arg(sim.join("velodyne"))
        .arg("--reference")
        .arg(sim.join("velodyne"))
        .arg("--calib")
        .arg(sim.join("calib"))
        .arg("--semantic-maps")
        .arg(sim.join("semantic_2"))
        .output()
        .unwrap();
    fails_with(
        &o,
        &[
            "000000.png",
            "SemanticKITTI train",
            "raw id",
            "--semantic-ids raw",
        ],
    );
}

/// A KITTI frame of the real samples (`I`, `C` of the repros), or `None` with a message.
fn kitti_frame() -> Option<(PathBuf, PathBuf, PathBuf)> {
    let real =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti_mmdet3d_demo");
    if !real.is_dir() {
        eprintln!("skipped: {} is absent", real.display());
        return None;
    }
    Some((
        real.join("velodyne_reduced/000008.bin"),
        real.join("image_2/000008.png"),
        real.join("calib/000008.txt"),
    ))
}

#[test]
fn weather_names_the_calibration_with_a_negative_focal_length() {
    let Some((scan, image, calib)) = kitti_frame() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(&calib).unwrap();
    let bad = tmp.path().join("negative_focal.txt");
    std::fs::write(&bad, text.replacen("P2: ", "P2: -", 1)).unwrap();
    let o = veila()
        .arg("weather")
        .arg(&scan)
        .arg("--image")
        .arg(&image)
        .arg("--calib")
        .arg(&bad)
        .args(["--preset", "fog-moderate", "--out"])
        .arg(tmp.path().join("o"))
        .output()
        .unwrap();
    fails_with(&o, &["negative_focal.txt", "invalid camera"]);
    assert!(!tmp.path().join("o").exists());
}

#[test]
fn a_one_pixel_depth_map_is_read_and_its_mismatch_named() {
    let Some((scan, _, calib)) = kitti_frame() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let (gen_, maps, cal) = (
        tmp.path().join("g"),
        tmp.path().join("d"),
        tmp.path().join("c"),
    );
    for d in [&gen_, &maps, &cal] {
        std::fs::create_dir(d).unwrap();
    }
    std::fs::copy(&scan, gen_.join("000008.bin")).unwrap();
    std::fs::copy(&calib, cal.join("000008.txt")).unwrap();
    // a (1, 1) array is a 1 x 1 map (not "must have shape [H, W], this one has [1, 1]"), and a
    // map that small cannot be the camera image's: the calibration's principal point says so
    npy_f32(&maps.join("000008.npy"), "(1, 1)", &[5.0]);
    let o = veila()
        .args(["eval", "--quiet", "--metrics", "cm-dc", "--generated"])
        .arg(&gen_)
        .arg("--reference")
        .arg(&gen_)
        .arg("--calib")
        .arg(&cal)
        .arg("--depth-maps")
        .arg(&maps)
        .output()
        .unwrap();
    fails_with(&o, &["000008.txt", "principal point", "1 x 1 image"]);
}
