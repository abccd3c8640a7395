//! `veila weather` end to end with the built binary on the real KITTI files.

use std::path::{Path, PathBuf};
use std::process::Command;

fn kitti() -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti/training");
    if root.join("velodyne/000001.bin").is_file() {
        Some(root)
    } else {
        eprintln!("skipping: {} not found", root.display());
        None
    }
}

fn veila() -> Command {
    Command::new(env!("CARGO_BIN_EXE_veila"))
}

fn effects(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("effects.json")).unwrap()).unwrap()
}

fn names(v: &serde_json::Value, sensor: &str) -> Vec<String> {
    v[sensor]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["effect"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn no_effect_gives_byte_identical_copies() {
    let Some(k) = kitti() else { return };
    let out = tempfile::tempdir().unwrap();
    let st = veila()
        .arg("weather")
        .arg(k.join("velodyne/000001.bin"))
        .arg("--image")
        .arg(k.join("image_2/000001.png"))
        .arg("--calib")
        .arg(k.join("calib/000001.txt"))
        .args(["--seed", "9", "--time-of-day", "day", "--out"])
        .arg(out.path())
        .status()
        .unwrap();
    assert!(st.success());
    assert_eq!(
        std::fs::read(out.path().join("000001.bin")).unwrap(),
        std::fs::read(k.join("velodyne/000001.bin")).unwrap()
    );
    assert_eq!(
        std::fs::read(out.path().join("000001.png")).unwrap(),
        std::fs::read(k.join("image_2/000001.png")).unwrap()
    );
    let e = effects(out.path());
    assert!(names(&e, "lidar").is_empty() && names(&e, "camera").is_empty());
}

#[test]
fn fog_changes_both_sensors_and_night_only_the_camera() {
    let Some(k) = kitti() else { return };
    let out = tempfile::tempdir().unwrap();
    let run = |extra: &[&str], dir: &Path| {
        let o = veila()
            .arg("weather")
            .arg(k.join("velodyne/000000.bin"))
            .arg("--image")
            .arg(k.join("image_2/000000.png"))
            .arg("--calib")
            .arg(k.join("calib/000000.txt"))
            .args(extra)
            .arg("--out")
            .arg(dir)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let fog = out.path().join("fog");
    run(&["--fog-visibility", "50", "--seed", "1"], &fog);
    let e = effects(&fog);
    assert_eq!(names(&e, "lidar"), ["fog"]);
    assert_eq!(names(&e, "camera"), ["veil"]);
    let bin = std::fs::read(fog.join("000000.bin")).unwrap();
    let orig = std::fs::read(k.join("velodyne/000000.bin")).unwrap();
    assert_eq!(bin.len(), orig.len(), "fog never deletes points");
    assert_ne!(bin, orig);
    assert!(
        e["lidar"][0]["counts"]["replaced_by_fog_return"]
            .as_u64()
            .unwrap()
            > 0
    );
    let img = veila_data::image_io::read_rgb_image(&fog.join("000000.png")).unwrap();
    assert_eq!((img.width(), img.height()), (1224, 370));

    let night = out.path().join("night");
    run(&["--time-of-day", "night"], &night);
    let e = effects(&night);
    assert!(names(&e, "lidar").is_empty());
    assert_eq!(names(&e, "camera"), ["darken", "sensor_noise"]);
    assert_eq!(
        std::fs::read(night.join("000000.bin")).unwrap(),
        orig,
        "night leaves the LiDAR untouched"
    );
}

#[test]
fn bad_input_fails_without_partial_output() {
    let Some(k) = kitti() else { return };
    let tmp = tempfile::tempdir().unwrap();
    // a truncated scan
    let bad = tmp.path().join("bad.bin");
    std::fs::write(&bad, [0u8; 18]).unwrap();
    let out = tmp.path().join("out");
    let o = veila()
        .arg("weather")
        .arg(&bad)
        .args(["--rain-rate", "5", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad.bin"), "{err}");
    assert!(!out.join("bad.bin").exists() && !out.join("effects.json").exists());
    // camera fog without calibration
    let o = veila()
        .arg("weather")
        .arg(k.join("velodyne/000001.bin"))
        .arg("--image")
        .arg(k.join("image_2/000001.png"))
        .args(["--fog-visibility", "100", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("calibration"));
    assert!(!out.join("000001.bin").exists(), "no partial output");
    // invalid weather
    let o = veila()
        .arg("weather")
        .arg(k.join("velodyne/000001.bin"))
        .args(["--fog-visibility", "3", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!o.status.success());
    // refused by the parser, which states the range
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--fog-visibility") && err.contains("between 10 and"),
        "{err}"
    );
}
