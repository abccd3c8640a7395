//! Helpers shared by the CLI tests that run the model commands (`generate`, `edit`, `train`).
#![allow(dead_code)] // each test binary uses its own subset

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// A small simulated scene: a `rows x cols` LiDAR, a 124 x 38 KITTI-like camera, `frames` frames.
pub fn tiny_scene(rows: u32, cols: u32, frames: u32) -> String {
    format!(
        r#"
name = "tiny"
layout = "straight"
[lidar.sensor]
rows = {rows}
cols = {cols}
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
count = {frames}
"#
    )
}

/// The `veila` binary, with the model taken from its default location, not the environment.
pub fn veila() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_veila"));
    c.env_remove("VEILA_MODEL");
    c
}

/// The bundled model folder.
pub fn model_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../models/default")
        .canonicalize()
        .unwrap()
}

/// Whether the bundle config `bundle_json` (a `bundle.json`) is residual diffusion: a mean network
/// and a residual denoiser.
pub fn is_residual_bundle(bundle_json: &Path) -> bool {
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(bundle_json).unwrap()).unwrap();
    v.get("residual").is_some_and(|r| !r.is_null())
}

/// `veila generate --quiet` of one image with the bundled model into `out`, plus `extra` flags.
pub fn generate(image: &Path, calib: &Path, out: &Path, extra: &[&str]) -> Output {
    veila()
        .args(["generate", "--quiet", "--image"])
        .arg(image)
        .arg("--calib")
        .arg(calib)
        .arg("--checkpoint")
        .arg(model_dir())
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

/// Asserts that a command succeeded, printing its output otherwise.
pub fn ok(o: &Output) {
    assert!(
        o.status.success(),
        "stdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Simulates frame 0 of `scene_toml` into `dir/sim` (KITTI layout) with `veila simulate` and
/// returns that folder.
pub fn simulate(dir: &Path, scene_toml: &str, seed: u64) -> PathBuf {
    let scene = dir.join("tiny.toml");
    std::fs::write(&scene, scene_toml).unwrap();
    let out = dir.join("sim");
    ok(&veila()
        .args(["simulate", "--quiet", "--frames", "1", "--seed"])
        .arg(seed.to_string())
        .arg("--scene")
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap());
    out
}
