//! `veila eval --protocol P` on real scans and on the peers' own sample files, against the numpy
//! reproductions of the peers' scripts (`veila-metrics/tests/data/peer_protocols.py` and its JSON).
//! The real-scan checks skip with a message when `../shared/data/real` is absent.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

fn veila() -> Command {
    Command::new(env!("CARGO_BIN_EXE_veila"))
}

fn data_root() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("skipping: {} is absent", p.display());
        None
    }
}

fn metrics_data() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../veila-metrics/tests/data")
}

fn reference() -> Value {
    let p = metrics_data().join("peer_protocols.json");
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

/// Copies `files` (relative to `root`) into a fresh folder `dir/name` (keeping the file names).
fn folder(dir: &Path, name: &str, root: &Path, files: &[Value]) -> PathBuf {
    let out = dir.join(name);
    std::fs::create_dir_all(&out).unwrap();
    for (i, f) in files.iter().enumerate() {
        let src = root.join(f.as_str().unwrap());
        let file = src.file_name().unwrap().to_string_lossy().into_owned();
        // scans of different sequences share names: prefix the index
        std::fs::copy(&src, out.join(format!("{i}_{file}"))).unwrap();
    }
    out
}

/// Runs `veila eval --protocol P` and returns `(jsd, mmd)` of the whole panorama.
fn eval(protocol: &str, g: &Path, r: &Path, json: &Path) -> (f64, f64) {
    let out = veila()
        .args([
            "--quiet",
            "eval",
            "--protocol",
            protocol,
            "--regions",
            "all",
            "--force",
            "--json",
        ])
        .arg(json)
        .arg("--generated")
        .arg(g)
        .arg("--reference")
        .arg(r)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{protocol}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    let get = |n: &str| {
        v["metrics"]
            .as_array()
            .unwrap()
            .iter()
            .find(|m| m["name"] == n)
            .unwrap()["value"]
            .as_f64()
            .unwrap()
    };
    (get("jsd"), get("mmd"))
}

fn check(what: &str, got: f64, want: &Value) {
    let want = want.as_f64().unwrap();
    let rel = (got - want).abs() / want.abs();
    eprintln!("{what}: {got:.10e} (numpy {want:.10e}, rel {rel:.1e})");
    assert!(rel <= 1e-4, "{what}: {got} vs numpy {want} (rel {rel:.2e})");
}

#[test]
fn every_protocol_gives_the_peer_number_from_raw_scans() {
    let Some(root) = data_root() else { return };
    let r = reference();
    let dir = tempfile::tempdir().unwrap();
    for (set_name, set) in r["sets"].as_object().unwrap() {
        let g = folder(
            dir.path(),
            &format!("{set_name}-gen"),
            &root,
            set["generated"].as_array().unwrap(),
        );
        let rf = folder(
            dir.path(),
            &format!("{set_name}-ref"),
            &root,
            set["reference"].as_array().unwrap(),
        );
        for proto in ["r2dm", "text2lidar", "lidargen", "lidm", "lidm-nuscenes"] {
            let (jsd, mmd) = eval(proto, &g, &rf, &dir.path().join("m.json"));
            let want = &r["raw"][set_name][proto];
            check(&format!("{set_name} {proto} jsd"), jsd, &want["jsd"]);
            check(&format!("{set_name} {proto} mmd"), mmd, &want["mmd"]);
        }
    }
}

#[test]
fn the_peers_own_sample_files_are_scored() {
    let Some(root) = data_root() else { return };
    let r = reference();
    let dir = tempfile::tempdir().unwrap();
    let rf = folder(
        dir.path(),
        "ref",
        &root,
        r["samples_reference"].as_array().unwrap(),
    );
    for (key, want) in r["samples"].as_object().unwrap() {
        let file = key.split(' ').next().unwrap();
        let g = dir
            .path()
            .join(format!("gen-{}", key.replace([' ', '(', ')'], "_")));
        std::fs::create_dir_all(&g).unwrap();
        std::fs::copy(metrics_data().join("peer_samples").join(file), g.join(file)).unwrap();
        let proto = want["protocol"].as_str().unwrap();
        let (jsd, mmd) = eval(proto, &g, &rf, &dir.path().join("s.json"));
        check(&format!("{key} jsd"), jsd, &want["jsd"]);
        check(&format!("{key} mmd"), mmd, &want["mmd"]);
    }
}

#[test]
fn pickles_are_refused_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let (g, r) = (dir.path().join("gen"), dir.path().join("ref"));
    std::fs::create_dir_all(&g).unwrap();
    std::fs::create_dir_all(&r).unwrap();
    std::fs::copy(
        metrics_data().join("peer_samples/lidm.npz"),
        r.join("lidm.npz"),
    )
    .unwrap();
    for (name, src) in [
        (
            "pickled.npy",
            Some(metrics_data().join("peer_samples/pickled.npy")),
        ),
        ("samples_0000000001.pth", None),
    ] {
        match src {
            Some(s) => {
                std::fs::copy(s, g.join(name)).unwrap();
            }
            None => std::fs::write(g.join(name), b"PK\x03\x04not really").unwrap(),
        }
        let out = veila()
            .args(["--quiet", "eval", "--protocol", "lidm", "--generated"])
            .arg(&g)
            .arg("--reference")
            .arg(&r)
            .output()
            .unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains(name) && err.contains("never loads pickles"),
            "{err}"
        );
        std::fs::remove_file(g.join(name)).unwrap();
    }
}

#[test]
fn sample_sets_refuse_raw_point_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let g = dir.path().join("gen");
    std::fs::create_dir_all(&g).unwrap();
    std::fs::copy(
        metrics_data().join("peer_samples/lidm.npz"),
        g.join("lidm.npz"),
    )
    .unwrap();
    let out = veila()
        .args([
            "--quiet",
            "eval",
            "--protocol",
            "lidm",
            "--metrics",
            "jsd-raw",
            "--generated",
        ])
        .arg(&g)
        .arg("--reference")
        .arg(&g)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("lidm.npz") && err.contains("no raw points"),
        "{err}"
    );
}

/// A `.npy` file of `float32` values with the given shape (numpy's format, version 1.0).
fn npy_f32(shape: &str, values: &[f32]) -> Vec<u8> {
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
    out
}

#[test]
fn bad_sample_sets_fail_with_the_file_named_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path().join("ref");
    std::fs::create_dir_all(&r).unwrap();
    std::fs::copy(
        metrics_data().join("peer_samples/lidm.npz"),
        r.join("lidm.npz"),
    )
    .unwrap();
    let cases: [(&str, Vec<u8>, &str); 4] = [
        // one axis is not a range image
        ("flat.npy", npy_f32("(6,)", &[0.5; 6]), "(H, W)"),
        // LiDM images are one channel
        (
            "two_channels.npy",
            npy_f32("(1, 2, 4, 8)", &[0.5; 64]),
            "channels",
        ),
        // the header promises more values than the file holds
        ("short.npy", npy_f32("(4, 16, 128)", &[0.5; 10]), "needs"),
        // not finite
        (
            "nan.npy",
            npy_f32("(1, 4, 8)", &[f32::NAN; 32]),
            "non-finite",
        ),
    ];
    for (name, bytes, says) in cases {
        let g = dir.path().join(format!("gen-{name}"));
        std::fs::create_dir_all(&g).unwrap();
        std::fs::write(g.join(name), bytes).unwrap();
        let json = dir.path().join(format!("{name}.json"));
        let out = veila()
            .args(["--quiet", "eval", "--protocol", "lidm", "--json"])
            .arg(&json)
            .arg("--generated")
            .arg(&g)
            .arg("--reference")
            .arg(&r)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{name}: {err}");
        assert!(!err.contains("panicked"), "{name}: {err}");
        assert!(err.contains(name) && err.contains(says), "{name}: {err}");
        assert!(!json.exists(), "{name}: no output on failure");
    }
    // a missing folder is named
    let out = veila()
        .args(["--quiet", "eval", "--protocol", "lidm", "--generated"])
        .arg(dir.path().join("no-such-folder"))
        .arg("--reference")
        .arg(&r)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("no-such-folder"), "{err}");
}
