//! `veila simulate`: byte-identical output for the same seed, clear errors and no partial output.

use std::path::Path;
use std::process::Command;

const TINY_SCENE: &str = r#"
name = "tiny"
layout = "junction"
[lidar.sensor]
rows = 16
cols = 128
fov_up_deg = 3.0
fov_down_deg = -25.0
min_range_m = 0.5
max_range_m = 120.0
[camera]
width = 124
height = 38
fx = 72.15
fy = 72.15
cx = 61.0
cy = 17.3
[frames]
count = 2
"#;

fn veila() -> Command {
    Command::new(env!("CARGO_BIN_EXE_veila"))
}

fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for sub in [
        "",
        "velodyne",
        "labels",
        "image_2",
        "calib",
        "depth_2",
        "semantic_2",
    ] {
        let d = dir.join(sub);
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_file() {
                out.push((
                    format!("{sub}/{}", p.file_name().unwrap().to_string_lossy()),
                    std::fs::read(&p).unwrap(),
                ));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn same_seed_gives_identical_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("tiny.toml");
    std::fs::write(&scene, TINY_SCENE).unwrap();
    for (out, seed) in [("a", "4"), ("b", "4"), ("c", "5")] {
        let st = veila()
            .args(["simulate", "--quiet", "--scene"])
            .arg(&scene)
            .arg("--out")
            .arg(tmp.path().join(out))
            .args(["--seed", seed])
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{}",
            String::from_utf8_lossy(&st.stderr)
        );
    }
    let (a, b, c) = (
        files(&tmp.path().join("a")),
        files(&tmp.path().join("b")),
        files(&tmp.path().join("c")),
    );
    assert_eq!(a.iter().filter(|f| f.0.starts_with("velodyne/")).count(), 2);
    // six files per frame, five per run, and the record of simulate's files (.veila-outputs.json)
    assert_eq!(a.len(), 2 * 6 + 5 + 1);
    assert!(a == b, "same seed, different bytes");
    assert!(a != c, "another seed, same bytes");
    // --frames overrides the scene file
    let st = veila()
        .args(["simulate", "--quiet", "--frames", "1", "--scene"])
        .arg(&scene)
        .arg("--out")
        .arg(tmp.path().join("d"))
        .output()
        .unwrap();
    assert!(st.status.success());
    assert_eq!(
        std::fs::read_dir(tmp.path().join("d/velodyne"))
            .unwrap()
            .count(),
        1
    );
}

#[test]
fn bad_scene_fails_clearly_without_output() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("bad.toml");
    std::fs::write(
        &scene,
        "layout = \"straight\"\n[road]\nlane_width_m = -3.0\n",
    )
    .unwrap();
    let out = tmp.path().join("out");
    let st = veila()
        .args(["simulate", "--quiet", "--scene"])
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(
        err.contains("bad.toml") && err.contains("lane_width_m"),
        "{err}"
    );
    assert!(!out.exists(), "partial output left behind");
    // nothing else (no staging directory) is left either
    let left: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
    // an existing non-empty output directory is refused
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("keep.txt"), "x").unwrap();
    std::fs::write(&scene, TINY_SCENE).unwrap();
    let st = veila()
        .args(["simulate", "--quiet", "--scene"])
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("not empty"));
    let st = veila()
        .args(["simulate", "--quiet", "--force", "--frames", "1", "--scene"])
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(st.status.success());
    assert!(out.join("keep.txt").exists() && out.join("velodyne/000000.bin").exists());
}
