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

/// Reads a KITTI `.bin` as `[x, y, z, intensity]` rows.
fn read_bin(path: &Path) -> Vec<[f32; 4]> {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(bytes.len() % 16, 0, "{}: not whole points", path.display());
    bytes
        .chunks_exact(16)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes(c[4 * i..4 * i + 4].try_into().unwrap());
            [f(0), f(1), f(2), f(3)]
        })
        .collect()
}

#[test]
fn demo_generates_a_scan_from_the_camera_and_writes_every_view_and_metric() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let o = veila(&["demo", "--steps", "2", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("jsd") && stdout.contains("chamfer") && stdout.contains("cm-dc"),
        "printed table: {stdout}"
    );
    for f in [
        "camera.png",
        "range_generated_vs_true.png",
        "bev_generated_vs_true.png",
        "overlay_generated_vs_true.png",
        "generated.exr",
        "generated.ply",
        "generated.bin",
        "true.exr",
        "true.ply",
        "true.bin",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let m = metrics(&out);
    let generated = read_bin(&out.join("generated.bin"));
    assert_eq!(
        generated.len() as u64,
        m["points_generated"].as_u64().unwrap()
    );
    assert_eq!(
        generated.len() as u64,
        m["range_pixels_generated"].as_u64().unwrap(),
        "one point per generated return"
    );
    assert!(generated.iter().all(|p| p.iter().all(|v| v.is_finite())));
    assert_eq!(m["grid"], serde_json::json!([32, 256]));
    for region in ["all", "front", "rear"] {
        let jsd = metric(&m, "jsd", region);
        assert!((0.0..=1.0).contains(&jsd), "jsd {jsd}");
    }
    // the true scan agrees with the simulated camera's own depth: the floor of the metric
    assert!(metric(&m, "cm-dc (true scan vs true depth)", "front") < 0.05);
    assert!(metric(&m, "cm-dc (generated scan vs true depth)", "front").is_finite());
}

#[test]
fn demo_is_seeded_and_night_touches_only_the_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let run = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        // two baseline frames: the baselines run, at a twelfth of their default cost
        let mut args = vec![
            "demo",
            "--steps",
            "2",
            "--baseline-frames",
            "2",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let o = veila(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        out
    };
    let a = run("a", &[]);
    let b = run("b", &["--weather", "clear"]);
    let c = run("c", &["--sample-seed", "5"]);
    let night = run("night", &["--weather", "kitti-night"]);
    let read = |d: &Path, f: &str| std::fs::read(d.join(f)).unwrap();
    // clear weather is an exact identity on the input image, and the same seed gives the same scan
    assert_eq!(read(&a, "camera.png"), read(&b, "camera.png"));
    assert_eq!(read(&a, "generated.bin"), read(&b, "generated.bin"));
    // another sample seed gives another scan of the same scene
    assert_ne!(read(&a, "generated.bin"), read(&c, "generated.bin"));
    assert_eq!(read(&a, "true.bin"), read(&c, "true.bin"));
    // night degrades the camera image only: the true scan is untouched
    assert_ne!(read(&a, "camera.png"), read(&night, "camera.png"));
    assert_eq!(read(&a, "true.bin"), read(&night, "true.bin"));
    let m = metrics(&night);
    assert!(!m["camera_effects"].as_array().unwrap().is_empty());
    assert_eq!(metrics(&a)["camera_effects"].as_array().unwrap().len(), 0);
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
    let o = veila(&[
        "demo",
        "--model",
        "/nonexistent/model",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent/model"));
    assert!(!out.exists(), "no partial output");
    // nothing left behind beside the output either (no staging folders)
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 0);
}

#[test]
fn rerunning_the_demo_refreshes_its_own_output_but_protects_other_folders() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let args = [
        "demo",
        "--steps",
        "2",
        "--baseline-frames",
        "2",
        "--out",
        out.to_str().unwrap(),
    ];
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
        .args([
            "demo",
            "--quiet",
            "--steps",
            "2",
            "--baseline-frames",
            "2",
            "--out",
            out.to_str().unwrap(),
        ])
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

/// A residual-diffusion model's demo shows its own mean network next to the sample, and
/// `--residual-weight 0` generates exactly that mean; a model without a mean network refuses the
/// flag before writing anything.
#[test]
fn the_residual_weight_moves_between_the_sample_and_the_mean_network() {
    let tmp = tempfile::tempdir().unwrap();
    let out = |name: &str| tmp.path().join(name);
    if !crate::common::is_residual_bundle(&crate::common::model_dir().join("bundle.json")) {
        let o = veila(&[
            "demo",
            "--residual-weight",
            "0.5",
            "--out",
            out("x").to_str().unwrap(),
        ]);
        assert!(!o.status.success());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains("residual-diffusion"), "{err}");
        assert!(!out("x").exists(), "no partial output");
        return;
    }
    let run = |name: &str, extra: &[&str]| {
        let mut args = vec!["demo", "--steps", "2", "--baseline-frames", "2", "--out"];
        let dir = out(name);
        args.push(dir.to_str().unwrap());
        args.extend_from_slice(extra);
        let o = veila(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        metrics(&dir)
    };
    let full = run("full", &[]);
    let mean = run("mean", &["--residual-weight", "0"]);
    let column = full["baselines"]
        .as_array()
        .unwrap()
        .iter()
        .find(|b| b["name"] == "mean net")
        .expect("a mean-net column next to the sample");
    let name = "range mae (m, both valid)";
    for region in ["all", "front", "rear"] {
        let col = column["metrics"]
            .as_array()
            .unwrap()
            .iter()
            .find(|v| v["name"] == name && v["region"] == region)
            .unwrap()["value"]
            .as_f64()
            .unwrap();
        assert_eq!(col, metric(&mean, name, region), "{region}");
        assert_ne!(
            col,
            metric(&full, name, region),
            "{region}: the sample differs"
        );
    }
    assert!(
        mean["baselines"]
            .as_array()
            .unwrap()
            .iter()
            .all(|b| b["name"] != "mean net"),
        "at weight 0 the scan is the mean network's"
    );
}
