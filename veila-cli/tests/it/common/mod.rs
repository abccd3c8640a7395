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
        .arg("--model")
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
    simulate_frames(dir, scene_toml, seed, 1)
}

/// Simulates `frames` frames of `scene_toml` into `dir/sim` (KITTI layout) with `veila simulate`
/// and returns that folder.
pub fn simulate_frames(dir: &Path, scene_toml: &str, seed: u64, frames: u32) -> PathBuf {
    let scene = dir.join("tiny.toml");
    std::fs::write(&scene, scene_toml).unwrap();
    let out = dir.join("sim");
    ok(&veila()
        .args([
            "simulate",
            "--quiet",
            "--frames",
            &frames.to_string(),
            "--seed",
        ])
        .arg(seed.to_string())
        .arg("--scene")
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap());
    out
}

/// Asserts that a command failed, without a panic, with a message containing every one of
/// `needles`.
pub fn fails_with(o: &Output, needles: &[&str]) {
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success(),
        "expected a failure, got success; stdout:\n{}",
        String::from_utf8_lossy(&o.stdout)
    );
    for n in needles {
        assert!(e.contains(n), "stderr lacks `{n}`:\n{e}");
    }
    assert!(!e.contains("panicked"), "panic:\n{e}");
}

/// Every name in `dir`, sorted.
pub fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Every file of `dir` and of its sub-folders, one level down (`velodyne/000000.bin`), with its
/// bytes.
pub fn files_in(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    for top in names(dir) {
        let p = dir.join(&top);
        if p.is_dir() {
            for n in names(&p) {
                out.insert(format!("{top}/{n}"), std::fs::read(p.join(&n)).unwrap());
            }
        } else {
            out.insert(top, std::fs::read(&p).unwrap());
        }
    }
    out
}

/// Names in `dir` that a veila process leaves while it works (staging folders, backups, lock and
/// temporary files).
pub fn leftovers(dir: &Path) -> Vec<String> {
    names(dir)
        .into_iter()
        .filter(|n| n.starts_with(".veila-"))
        .collect()
}

/// `veila generate --quiet` of frame 0 of the simulated folder `sim` into `out`, with `extra`
/// arguments (`--steps 1` unless they give `--steps`).
pub fn generate_cmd(sim: &Path, out: &Path, extra: &[&str]) -> Command {
    let mut c = veila();
    c.args(["generate", "--quiet"]);
    if !extra.contains(&"--steps") {
        c.args(["--steps", "1"]);
    }
    c.args(extra)
        .arg("--image")
        .arg(sim.join("image_2/000000.png"))
        .arg("--calib")
        .arg(sim.join("calib/000000.txt"))
        .arg("--out")
        .arg(out);
    c
}

/// Starts a long `veila generate` (1000 steps, `extra` arguments) into `out` and returns once
/// its staging folder exists beside `out`.
pub fn long_generate(sim: &Path, out: &Path, extra: &[&str]) -> std::process::Child {
    let mut args = vec!["--steps", "1000"];
    args.extend_from_slice(extra);
    let child = generate_cmd(sim, out, &args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let parent = out.parent().unwrap();
    let t = std::time::Instant::now();
    while !leftovers(parent)
        .iter()
        .any(|n| n.starts_with(".veila-staging."))
    {
        assert!(
            t.elapsed() < std::time::Duration::from_secs(120),
            "no staging folder appeared"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child
}

/// Sends `signal` (`-INT`, `-TERM`, `-KILL`) to `child`.
pub fn signal(child: &std::process::Child, signal: &str) {
    let st = Command::new("kill")
        .args([signal, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(st.success());
}

/// Writes a `.npy` (format 1.0) of float32 `values` with the Python tuple `shape`.
pub fn npy_f32(path: &Path, shape: &str, values: &[f32]) {
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, out).unwrap();
}
