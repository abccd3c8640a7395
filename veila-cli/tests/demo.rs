//! `veila demo`, the README's main job: end to end through the built binary.

use std::path::Path;
use std::process::Command;

fn veila(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_veila"))
        .args(args)
        .arg("--quiet")
        .output()
        .expect("the veila binary runs")
}

fn metrics(dir: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join("metrics.json")).expect("metrics.json written");
    serde_json::from_str(&text).expect("metrics.json is JSON")
}

fn metric(m: &serde_json::Value, name: &str, region: &str) -> f64 {
    m["metrics"]
        .as_array()
        .expect("metrics array")
        .iter()
        .find(|v| v["name"] == name && v["region"] == region)
        .unwrap_or_else(|| panic!("metric {name}/{region} missing"))["value"]
        .as_f64()
        .expect("numeric value")
}

#[test]
fn clear_weather_demo_is_an_exact_identity_end_to_end() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let o = veila(&["demo", "--weather", "clear", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in [
        "points.bin",
        "points.ply",
        "range.exr",
        "camera.png",
        "range.png",
        "bev.png",
        "overlay.png",
    ] {
        let a = std::fs::read(out.join("clear").join(f)).unwrap();
        let b = std::fs::read(out.join("weather").join(f)).unwrap();
        assert_eq!(
            a, b,
            "{f}: clear weather must leave both sensors bit-identical"
        );
    }
    let m = metrics(&out);
    assert_eq!(m["lidar_effects"].as_array().unwrap().len(), 0);
    assert_eq!(m["camera_effects"].as_array().unwrap().len(), 0);
    for region in ["all", "front", "rear"] {
        assert_eq!(metric(&m, "jsd", region), 0.0);
        assert_eq!(metric(&m, "mmd", region), 0.0);
        assert_eq!(metric(&m, "chamfer", region), 0.0);
    }
    // the simulated scan agrees with the simulated camera's own ground truth
    assert!(metric(&m, "cm-sc (clear scan vs true semantics)", "front") > 90.0);
    assert!(metric(&m, "cm-dc (clear scan vs true depth)", "front") < 0.05);
}

#[test]
fn fog_demo_changes_both_sensors_and_the_metrics_see_it() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let o = veila(&["demo", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("jsd") && stdout.contains("chamfer"),
        "printed table: {stdout}"
    );
    let m = metrics(&out);
    assert_eq!(m["weather"], "kitti-fog");
    assert!(
        m["lidar_effects"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e == "fog")
    );
    assert!(
        m["camera_effects"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e == "veil")
    );
    assert!(
        metric(&m, "jsd", "all") > 0.01,
        "dense fog must move points"
    );
    assert!(metric(&m, "chamfer", "all") > 0.1);
    let clear = std::fs::read(out.join("clear/camera.png")).unwrap();
    let fog = std::fs::read(out.join("weather/camera.png")).unwrap();
    assert_ne!(clear, fog);
    for f in [
        "range_clear_vs_weather.png",
        "bev_clear_vs_weather.png",
        "camera_clear_vs_weather.png",
        "weather/effects.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
}

#[test]
fn bad_arguments_fail_cleanly_without_output() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let o = veila(&[
        "demo",
        "--weather",
        "monsoon",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("monsoon"));
    assert!(!out.exists(), "no partial output");
    let o = veila(&[
        "demo",
        "--scene",
        "/nonexistent/scene.toml",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent/scene.toml"));
    assert!(!out.exists(), "no partial output");
    // nothing left behind beside the output either (no staging folders)
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 0);
}

#[test]
fn rerunning_the_demo_refreshes_its_own_output_but_protects_other_folders() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let args = ["demo", "--weather", "clear", "--out", out.to_str().unwrap()];
    assert!(veila(&args).status.success());
    let o = veila(&args);
    assert!(
        o.status.success(),
        "second run: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    // a folder with a file of the user's is not touched without --force
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let o = veila(&args);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("not empty"));
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );
}

/// `veila ... | head` must end quietly when the reader goes away, not panic on the closed pipe.
#[cfg(unix)]
#[test]
fn a_closed_stdout_pipe_ends_the_process_quietly() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let mut child = Command::new(env!("CARGO_BIN_EXE_veila"))
        .args(["demo", "--quiet", "--out", out.to_str().unwrap()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take()); // the reader goes away before anything is printed
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(
        o.status.signal(),
        Some(libc_sigpipe()),
        "status {:?}",
        o.status
    );
    // the output folder was committed before anything was printed, and no staging folder is left
    assert!(out.join("metrics.json").is_file());
    let names: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, ["demo"]);
}

#[cfg(unix)]
fn libc_sigpipe() -> i32 {
    13 // SIGPIPE on Linux and the BSDs
}
