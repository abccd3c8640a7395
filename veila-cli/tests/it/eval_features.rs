//! `veila eval --metrics frd,fpd` end to end: zero against itself, growing with the strength of a
//! perturbation, the same with the shipped bundle given as a folder, and clean failures.

use std::path::{Path, PathBuf};
use std::process::Command;

use glam::Vec3;

fn veila() -> Command {
    Command::new(env!("CARGO_BIN_EXE_veila"))
}

fn shipped_nets() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/feature-nets")
}

fn write_bin(path: &Path, pts: &[Vec3]) {
    let mut bytes = Vec::with_capacity(pts.len() * 16);
    for p in pts {
        for v in [p.x, p.y, p.z, 0.3 + 0.01 * (p.z + 2.0)] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// xorshift in [0, 1).
struct Rng(u32);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 17;
        self.0 ^= self.0 << 5;
        (self.0 >> 8) as f32 / (1u32 << 24) as f32
    }
    fn normal(&mut self) -> f32 {
        let (u, v) = (self.next().max(1e-7), self.next());
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    }
}

/// A street-like scan of a 64 x 1024 spinning LiDAR 1.73 m above flat ground, inside a wall whose
/// distance varies with azimuth (seeded), cut off at 80 m.
fn street_scan(seed: u32) -> Vec<Vec3> {
    let mut rng = Rng(seed.wrapping_mul(2_654_435_761) | 1);
    let r0 = 8.0 + 20.0 * rng.next();
    let amp = 2.0 + 5.0 * rng.next();
    let lobes = 2.0 + (4.0 * rng.next()).floor();
    let phase = std::f32::consts::TAU * rng.next();
    let wall_h = 3.0 + 10.0 * rng.next();
    let mut pts = Vec::with_capacity(64 * 1024);
    for row in 0..64 {
        let el = (3.0 - 28.0 * (row as f32 + 0.5) / 64.0).to_radians();
        for col in 0..1024 {
            let az = std::f32::consts::TAU * (col as f32 + 0.5) / 1024.0 - std::f32::consts::PI;
            let dir = Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            let mut t = f32::INFINITY;
            if el < 0.0 {
                t = 1.73 / -el.sin();
            }
            let rw = r0 + amp * (lobes * az + phase).sin();
            let tw = rw / el.cos();
            if (dir * tw).z < wall_h - 1.73 {
                t = t.min(tw);
            }
            if t < 80.0 {
                pts.push(dir * t);
            }
        }
    }
    pts
}

/// Drops a fraction `s` of the points and jitters the rest by `s` metres (Gaussian sigma), seeded.
fn perturb(pts: &[Vec3], s: f32, seed: u32) -> Vec<Vec3> {
    let mut rng = Rng(seed.wrapping_mul(747_796_405) | 1);
    pts.iter()
        .filter_map(|p| {
            if rng.next() < s {
                return None;
            }
            Some(*p + Vec3::new(rng.normal(), rng.normal(), rng.normal()) * s)
        })
        .collect()
}

const SCANS: u32 = 6;

fn make_set(dir: &Path, strength: f32) {
    std::fs::create_dir_all(dir).unwrap();
    for i in 0..SCANS {
        let pts = street_scan(i);
        let pts = if strength > 0.0 {
            perturb(&pts, strength, 100 + i)
        } else {
            pts
        };
        write_bin(&dir.join(format!("{i:06}.bin")), &pts);
    }
}

/// (frd, fpd) of `generated` against `reference`, from the JSON output.
fn frd_fpd(generated: &Path, reference: &Path, extra: &[&str]) -> (f64, f64) {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("m.json");
    let out = veila()
        .args(["eval", "--metrics", "frd,fpd", "--generated"])
        .arg(generated)
        .arg("--reference")
        .arg(reference)
        .arg("--json")
        .arg(&json)
        .args(extra)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "veila eval failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("frd (veila-sim rangenet-small, gap features)"),
        "{stdout}"
    );
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let metrics = v["metrics"].as_array().unwrap();
    assert_eq!(metrics.len(), 2, "{v}");
    let get = |prefix: &str| {
        let m = metrics
            .iter()
            .find(|m| m["name"].as_str().unwrap().starts_with(prefix))
            .unwrap();
        assert_eq!(m["protocol"], "frechet");
        assert_eq!(m["region"], "all");
        assert_eq!(m["generated"], SCANS);
        m["value"].as_f64().unwrap()
    };
    (get("frd ("), get("fpd ("))
}

#[test]
fn frd_and_fpd_are_zero_against_itself_and_grow_with_the_perturbation() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let strengths = [0.0f32, 0.1, 0.3, 0.6];
    let dirs: Vec<PathBuf> = strengths
        .iter()
        .map(|s| {
            let d = root.join(format!("s{s}"));
            make_set(&d, *s);
            d
        })
        .collect();
    let (frd0, fpd0) = frd_fpd(&dirs[0], &dirs[0], &[]);
    assert!(
        frd0.abs() < 1e-6 && fpd0.abs() < 1e-6,
        "self: {frd0} {fpd0}"
    );
    let mut prev = (frd0, fpd0);
    for (d, s) in dirs.iter().zip(strengths).skip(1) {
        let (frd, fpd) = frd_fpd(d, &dirs[0], &[]);
        assert!(
            frd > prev.0 && fpd > prev.1,
            "strength {s}: frd {frd} (previous {}), fpd {fpd} (previous {})",
            prev.0,
            prev.1
        );
        prev = (frd, fpd);
    }
    assert!(prev.0 > 1e-3 && prev.1 > 1e-3, "strongest: {prev:?}");

    // the shipped bundle passed as a folder gives the same numbers as the built-in one
    let nets = shipped_nets();
    let built_in = frd_fpd(&dirs[2], &dirs[0], &[]);
    let from_dir = frd_fpd(
        &dirs[2],
        &dirs[0],
        &["--feature-nets", nets.to_str().unwrap()],
    );
    assert_eq!(built_in, from_dir);
}

#[test]
fn feature_metrics_fail_cleanly() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (one, many) = (root.join("one"), root.join("many"));
    std::fs::create_dir_all(&one).unwrap();
    write_bin(&one.join("a.bin"), &street_scan(1));
    make_set(&many, 0.0);
    // fewer than two scans on a side
    let out = veila()
        .args(["eval", "--metrics", "frd", "--generated"])
        .arg(&one)
        .arg("--reference")
        .arg(&many)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("at least 2 scans") && err.contains("one"),
        "{err}"
    );

    // a bundle folder with a corrupted weights file: the error names the file
    let nets = root.join("nets");
    std::fs::create_dir_all(&nets).unwrap();
    for e in std::fs::read_dir(shipped_nets()).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), nets.join(e.file_name())).unwrap();
    }
    let w = nets.join("rangenet.safetensors");
    let mut bytes = std::fs::read(&w).unwrap();
    bytes[100] ^= 0xff;
    std::fs::write(&w, bytes).unwrap();
    let json = root.join("out.json");
    let out = veila()
        .args(["eval", "--metrics", "fpd", "--generated"])
        .arg(&many)
        .arg("--reference")
        .arg(&many)
        .arg("--feature-nets")
        .arg(&nets)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("rangenet.safetensors") && err.contains("sha256"),
        "{err}"
    );
    assert!(!json.exists(), "no partial output");
}
