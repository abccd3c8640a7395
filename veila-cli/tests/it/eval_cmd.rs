//! `veila eval` and `veila fd` end to end: values against the library, JSON shape, and clean failures.

use std::path::Path;
use std::process::Command;

use glam::Vec3;
use veila_metrics::{
    Region,
    bev::{BevConfig, bev_histogram},
    chamfer, dist, fd,
    protocol::PeerProtocol,
};

fn veila() -> Command {
    Command::new(env!("CARGO_BIN_EXE_veila"))
}

fn write_bin(path: &Path, pts: &[Vec3]) {
    let mut bytes = Vec::new();
    for p in pts {
        for v in [p.x, p.y, p.z, 0.5] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).unwrap();
}

fn scan(seed: u32, n: usize) -> Vec<Vec3> {
    let mut s = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        s as f32 / u32::MAX as f32
    };
    (0..n)
        .map(|_| {
            let r = 4.0 + 60.0 * next();
            let t = std::f32::consts::TAU * next();
            Vec3::new(r * t.cos(), r * t.sin(), -1.5 + next())
        })
        .collect()
}

/// A minimal little-endian .npy (v1.0) of a C-order 2-D f64 array.
fn write_npy_f64(path: &Path, rows: usize, cols: usize, data: &[f64]) {
    let mut header =
        format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows}, {cols}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn eval_matches_the_library_and_writes_json() {
    let dir = tempfile::tempdir().unwrap();
    let (g, r) = (dir.path().join("gen"), dir.path().join("ref"));
    std::fs::create_dir_all(&g).unwrap();
    std::fs::create_dir_all(&r).unwrap();
    let gs: Vec<Vec<Vec3>> = (0..3).map(|i| scan(i, 400)).collect();
    let rs: Vec<Vec<Vec3>> = (0..3).map(|i| scan(100 + i, 500)).collect();
    for (i, (a, b)) in gs.iter().zip(&rs).enumerate() {
        write_bin(&g.join(format!("{i:06}.bin")), a);
        write_bin(&r.join(format!("{i:06}.bin")), b);
    }
    let json = dir.path().join("out.json");
    let out = veila()
        .args([
            "--quiet",
            "eval",
            "--metrics",
            "jsd-raw,mmd-raw,jsd,chamfer",
            "--regions",
            "all,front",
            "--json",
        ])
        .arg(&json)
        .arg("--generated")
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let metrics = v["metrics"].as_array().unwrap();
    assert_eq!(metrics.len(), 8);
    let get = |name: &str, region: &str| {
        metrics
            .iter()
            .find(|m| m["name"] == name && m["region"] == region)
            .unwrap_or_else(|| panic!("{name} {region} missing"))
    };
    let cfg = BevConfig::r2dm();
    let hg: Vec<_> = gs
        .iter()
        .map(|s| bev_histogram(s, &cfg, Region::All, "g").unwrap())
        .collect();
    let hr: Vec<_> = rs
        .iter()
        .map(|s| bev_histogram(s, &cfg, Region::All, "r").unwrap())
        .collect();
    let jsd = get("jsd-raw", "all");
    assert_eq!(jsd["protocol"], "r2dm");
    assert_eq!(
        (jsd["generated"].as_u64(), jsd["reference"].as_u64()),
        (Some(3), Some(3))
    );
    assert_eq!(jsd["value"].as_f64().unwrap(), dist::jsd(&hg, &hr).unwrap());
    let mmd = get("mmd-raw", "all");
    assert_eq!(
        mmd["value"].as_f64().unwrap(),
        dist::mmd_r2dm_dense(&hg, &hr, 0.5).unwrap()
    );
    assert_eq!(mmd["paper_scale"].as_f64(), Some(1e4));
    // `jsd` runs R2DM's whole pipeline (64 x 1024 projection, range caps) before the metric
    let peer = PeerProtocol::R2dm;
    let summ = |set: &[Vec<Vec3>]| -> Vec<_> {
        set.iter()
            .map(|s| {
                let p = peer.prepare_scan(s, "s").unwrap();
                peer.summarise(&p, Region::All, "s").unwrap()
            })
            .collect()
    };
    let want = peer.score(&summ(&gs), &summ(&rs)).unwrap()[0].value;
    let pj = get("jsd", "all");
    assert_eq!(pj["protocol"], "r2dm");
    assert_eq!(pj["value"].as_f64().unwrap(), want);
    assert_ne!(want, dist::jsd(&hg, &hr).unwrap());
    let cd: f64 = gs
        .iter()
        .zip(&rs)
        .map(|(a, b)| chamfer::chamfer_distance(a, b).unwrap().value())
        .sum::<f64>()
        / 3.0;
    assert!((get("chamfer", "all")["value"].as_f64().unwrap() - cd).abs() <= 1e-12 * cd);
    assert_eq!(get("chamfer", "front")["protocol"], "pytorch3d");
}

#[test]
fn a_nan_intensity_does_not_drop_the_point_from_the_geometry_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let (g, r) = (dir.path().join("gen"), dir.path().join("ref"));
    std::fs::create_dir_all(&g).unwrap();
    std::fs::create_dir_all(&r).unwrap();
    let gs = scan(7, 300);
    let rs = scan(8, 300);
    // the generated scan's first 50 points have a NaN intensity but valid coordinates
    let mut bytes = Vec::new();
    for (i, p) in gs.iter().enumerate() {
        let inten = if i < 50 { f32::NAN } else { 0.5 };
        for v in [p.x, p.y, p.z, inten] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(g.join("000000.bin"), bytes).unwrap();
    write_bin(&r.join("000000.bin"), &rs);
    let json = dir.path().join("out.json");
    let out = veila()
        .args([
            "--quiet",
            "eval",
            "--metrics",
            "jsd-raw",
            "--regions",
            "all",
            "--json",
        ])
        .arg(&json)
        .arg("--generated")
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let got = v["metrics"][0]["value"].as_f64().unwrap();
    let cfg = BevConfig::r2dm();
    let hr = [bev_histogram(&rs, &cfg, Region::All, "r").unwrap()];
    let all = dist::jsd(&[bev_histogram(&gs, &cfg, Region::All, "g").unwrap()], &hr).unwrap();
    let dropped = dist::jsd(
        &[bev_histogram(&gs[50..], &cfg, Region::All, "g").unwrap()],
        &hr,
    )
    .unwrap();
    assert_ne!(all, dropped);
    assert_eq!(got, all, "the NaN-intensity points must be kept");
}

#[test]
fn fd_newton_schulz_divergence_fails_instead_of_printing_zero() {
    let dir = tempfile::tempdir().unwrap();
    // 5 samples in 16 dimensions: rank-deficient covariances
    let mut s = 12345u64;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let a: Vec<f64> = (0..5 * 16).map(|_| next()).collect();
    let b: Vec<f64> = (0..5 * 16).map(|_| next()).collect();
    write_npy_f64(&dir.path().join("a.npy"), 5, 16, &a);
    write_npy_f64(&dir.path().join("b.npy"), 5, 16, &b);
    let json = dir.path().join("fd.json");
    let out = veila()
        .args(["--quiet", "fd"])
        .arg(dir.path().join("a.npy"))
        .arg(dir.path().join("b.npy"))
        .args(["--newton-schulz", "100", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("Newton–Schulz diverged"), "{err}");
    assert!(!json.exists());
    // the exact method works on the same input
    let ok = veila()
        .args(["--quiet", "fd"])
        .arg(dir.path().join("a.npy"))
        .arg(dir.path().join("b.npy"))
        .output()
        .unwrap();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
}

#[test]
fn eval_fails_cleanly_on_bad_folders() {
    let dir = tempfile::tempdir().unwrap();
    let (g, r, e) = (
        dir.path().join("gen"),
        dir.path().join("ref"),
        dir.path().join("empty"),
    );
    for d in [&g, &r, &e] {
        std::fs::create_dir_all(d).unwrap();
    }
    write_bin(&g.join("a.bin"), &scan(1, 100));
    write_bin(&r.join("b.bin"), &scan(2, 100));
    let json = dir.path().join("out.json");
    // empty folder
    let out = veila()
        .args(["--quiet", "eval", "--generated"])
        .arg(&e)
        .arg("--reference")
        .arg(&r)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no scans"));
    // chamfer pairs by name
    let out = veila()
        .args(["--quiet", "eval", "--metrics", "chamfer", "--json"])
        .arg(&json)
        .arg("--generated")
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("a.bin"));
    assert!(!json.exists(), "no partial output");
    // a scan with no point in the BEV window: MMD names the file
    write_bin(&g.join("c.bin"), &[Vec3::new(1.0, 0.0, 0.0)]);
    let out = veila()
        .args(["--quiet", "eval", "--metrics", "mmd", "--generated"])
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("c.bin"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn fd_reads_npy_and_matches_the_library() {
    let dir = tempfile::tempdir().unwrap();
    let (rows_a, rows_b, cols) = (40, 30, 5);
    let a: Vec<f64> = (0..rows_a * cols)
        .map(|k| ((k * 37 % 101) as f64 / 101.0).sin())
        .collect();
    let b: Vec<f64> = (0..rows_b * cols)
        .map(|k| ((k * 53 % 97) as f64 / 97.0).cos() + 0.1)
        .collect();
    let (pa, pb) = (dir.path().join("a.npy"), dir.path().join("b.npy"));
    write_npy_f64(&pa, rows_a, cols, &a);
    write_npy_f64(&pb, rows_b, cols, &b);
    let json = dir.path().join("fd.json");
    let out = veila()
        .args(["fd"])
        .arg(&pa)
        .arg(&pb)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let want = fd::frechet_distance_rows(&a, &b, cols, fd::SqrtMethod::Eigen).unwrap();
    assert_eq!(v["metrics"][0]["name"], "fd");
    // same algorithm; the matrix products may split work differently across threads (last-ulp differences)
    assert!((v["metrics"][0]["value"].as_f64().unwrap() - want).abs() <= 1e-12 * want);
    // mismatched columns
    let pc = dir.path().join("c.npy");
    write_npy_f64(&pc, 10, 4, &[0.5; 40]);
    let out = veila().args(["fd"]).arg(&pa).arg(&pc).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("columns"));
    // not an npy file
    std::fs::write(dir.path().join("bad.npy"), b"hello").unwrap();
    let out = veila()
        .args(["fd"])
        .arg(&pa)
        .arg(dir.path().join("bad.npy"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("bad.npy"));
}

/// `eval` and `fd` follow the output discipline of every command: an output is named for its
/// format, never an input, never an existing file without `--force`, and `--json` with
/// `--report` appear together or not at all.
#[test]
fn eval_outputs_never_replace_inputs_or_existing_files() {
    let dir = tempfile::tempdir().unwrap();
    let (g, r) = (dir.path().join("gen"), dir.path().join("ref"));
    std::fs::create_dir_all(&g).unwrap();
    std::fs::create_dir_all(&r).unwrap();
    for i in 0..2u32 {
        write_bin(&g.join(format!("{i:06}.bin")), &scan(i, 300));
        write_bin(&r.join(format!("{i:06}.bin")), &scan(50 + i, 300));
    }
    let eval = |extra: &[&std::ffi::OsStr]| {
        let mut c = veila();
        c.args(["--quiet", "eval", "--metrics", "jsd", "--regions", "all"])
            .arg("--generated")
            .arg(&g)
            .arg("--reference")
            .arg(&r)
            .args(extra);
        c.output().unwrap()
    };
    let fails_naming = |o: &std::process::Output, what: &str| {
        assert!(!o.status.success());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(what), "{err}");
    };
    let input = g.join("000000.bin");
    let before = std::fs::read(&input).unwrap();
    // an input as --json (even with --force) is refused and left alone
    let o = eval(&["--json".as_ref(), input.as_os_str(), "--force".as_ref()]);
    fails_naming(&o, "000000.bin");
    assert_eq!(std::fs::read(&input).unwrap(), before);
    // a name that does not say JSON / HTML
    let txt = dir.path().join("out.txt");
    fails_naming(&eval(&["--json".as_ref(), txt.as_os_str()]), ".json");
    fails_naming(&eval(&["--report".as_ref(), txt.as_os_str()]), ".html");
    assert!(!txt.exists());
    // an existing file needs --force; with a report beside it, neither is written
    let json = dir.path().join("m.json");
    let html = dir.path().join("r.html");
    std::fs::write(&json, b"keep").unwrap();
    let o = eval(&[
        "--json".as_ref(),
        json.as_os_str(),
        "--report".as_ref(),
        html.as_os_str(),
    ]);
    fails_naming(&o, "--force");
    assert_eq!(std::fs::read(&json).unwrap(), b"keep");
    assert!(!html.exists(), "all or nothing");
    let o = eval(&[
        "--json".as_ref(),
        json.as_os_str(),
        "--report".as_ref(),
        html.as_os_str(),
        "--force".as_ref(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(std::fs::read_to_string(&json).unwrap().contains("\"jsd\""));
    assert!(std::fs::read_to_string(&html).unwrap().contains("<html"));
    // fd: its inputs are protected the same way
    let a = dir.path().join("a.npy");
    write_npy_f64(&a, 3, 2, &[1.0, 2.0, 3.0, 5.0, 4.0, 1.0]);
    let o = veila()
        .args(["--quiet", "fd"])
        .arg(&a)
        .arg(&a)
        .arg("--json")
        .arg(&a)
        .arg("--force")
        .output()
        .unwrap();
    fails_naming(&o, "a.npy");
    assert!(std::fs::read(&a).unwrap().starts_with(b"\x93NUMPY"));
}

/// References cropped to the camera's view (KITTI's `velodyne_reduced`, the `000008` sample of the
/// help) have no rear: by default that region is left out with a note (the run once failed with
/// "every reference scan has no point inside the BEV window" and no hint); asked for, the error
/// names the regions to use.
#[test]
fn camera_cropped_references_score_the_regions_they_cover() {
    let tmp = tempfile::tempdir().unwrap();
    let (g, r) = (tmp.path().join("gen"), tmp.path().join("ref"));
    std::fs::create_dir_all(&g).unwrap();
    std::fs::create_dir_all(&r).unwrap();
    for i in 0..2u32 {
        write_bin(&g.join(format!("{i:06}.bin")), &scan(i, 3000));
        let front: Vec<Vec3> = scan(10 + i, 3000)
            .into_iter()
            .filter(|p| p.x > 0.0)
            .collect();
        write_bin(&r.join(format!("{i:06}.bin")), &front);
    }
    let eval = |extra: &[&str]| {
        veila()
            .arg("eval")
            .arg("--generated")
            .arg(&g)
            .arg("--reference")
            .arg(&r)
            .args(extra)
            .output()
            .unwrap()
    };
    let json = tmp.path().join("eval.json");
    let o = eval(&["--json", json.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("region rear") && err.contains("left out"),
        "{err}"
    );
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let regions: std::collections::BTreeSet<&str> = v["metrics"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["region"].as_str().unwrap())
        .collect();
    assert_eq!(regions, ["all", "front"].into_iter().collect());
    let o = eval(&["--regions", "front,rear"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("region rear") && err.contains("--regions front"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

/// The help example of `eval` on the KITTI `000008` sample it names (a scan cropped to the camera)
/// runs with the default regions.
#[test]
fn the_eval_example_runs_on_the_kitti_sample_it_names() {
    let real =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti_mmdet3d_demo");
    if !real.is_dir() {
        eprintln!("skipped: {} is absent", real.display());
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (g, r) = (tmp.path().join("gen"), tmp.path().join("velodyne"));
    std::fs::create_dir_all(&g).unwrap();
    std::fs::create_dir_all(&r).unwrap();
    std::fs::copy(
        real.join("velodyne_reduced/000008.bin"),
        r.join("000008.bin"),
    )
    .unwrap();
    write_bin(&g.join("000008.bin"), &scan(3, 20_000));
    let o = veila()
        .args(["eval", "--metrics", "jsd,mmd", "--generated"])
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}
