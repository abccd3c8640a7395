//! `veila generate` with the bundled model on a simulated frame: the files parse and agree with each
//! other, the same seed gives identical bytes, another seed other bytes, and bad input fails clearly
//! without output.

use std::path::{Path, PathBuf};
use std::process::Output;

use veila_data::range_exr::read_range_exr;
use veila_data::scan::read_kitti_bin;

use crate::common::*;

/// Simulates one frame into `dir/sim` (KITTI layout) and returns (image, calib).
fn simulate(dir: &Path) -> (PathBuf, PathBuf) {
    let sim = crate::common::simulate(dir, &tiny_scene(16, 128, 1), 3);
    (sim.join("image_2/000000.png"), sim.join("calib/000000.txt"))
}

fn read(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn generated_scans_parse_agree_and_are_seeded() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib) = simulate(tmp.path());
    let a = tmp.path().join("a");
    let b = tmp.path().join("b");
    let c = tmp.path().join("c");
    let small = ["--steps", "2", "--samples", "2"];
    ok(&generate(
        &image,
        &calib,
        &a,
        &[&small[..], &["--seed", "7"]].concat(),
    ));
    ok(&generate(
        &image,
        &calib,
        &b,
        &[&small[..], &["--seed", "7"]].concat(),
    ));
    ok(&generate(
        &image,
        &calib,
        &c,
        &[&small[..], &["--seed", "8"]].concat(),
    ));

    for i in 0..2 {
        let stem = format!("scan_{i:03}");
        for suffix in [
            ".bin",
            ".ply",
            ".exr",
            "_range.png",
            "_bev.png",
            "_overlay.png",
        ] {
            assert!(
                a.join(format!("{stem}{suffix}")).is_file(),
                "{stem}{suffix} missing"
            );
        }
        let bin = read_kitti_bin(&a.join(format!("{stem}.bin"))).unwrap();
        let exr = read_range_exr(&a.join(format!("{stem}.exr"))).unwrap();
        let valid = exr.image.mask.iter().filter(|m| **m).count();
        assert!(!bin.cloud.is_empty(), "{stem}: no points");
        assert_eq!(bin.cloud.len(), valid, "{stem}: points vs EXR returns");
        assert_eq!(bin.dropped_non_finite, 0);
        // the PLY holds the same points with intensity and a colour per point
        let ply_bytes = read(&a.join(format!("{stem}.ply")));
        let header_end = ply_bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap();
        let header = String::from_utf8_lossy(&ply_bytes[..header_end]);
        assert!(
            header.contains("format binary_little_endian 1.0"),
            "{header}"
        );
        assert!(
            header.contains("property float intensity\nproperty uchar red\nproperty uchar green\nproperty uchar blue"),
            "{header}"
        );
        assert_eq!(ply_bytes.len(), header_end + 11 + bin.cloud.len() * 19);
        let ply = veila_data::ply::read_ply(&a.join(format!("{stem}.ply"))).unwrap();
        assert_eq!(ply.xyz, bin.cloud.xyz);
        assert_eq!(ply.intensity, bin.cloud.intensity);
        // the model's grid is stored in the EXR and every point lies on a ray of that grid at the
        // EXR's range (brute-force comparison of the .bin with the EXR unprojection)
        let from_exr = exr.to_points().unwrap();
        assert_eq!(from_exr.xyz.len(), bin.cloud.len());
        for (p, q) in from_exr.xyz.iter().zip(&bin.cloud.xyz) {
            assert!((*p - *q).length() < 1e-4, "{p} vs {q}");
        }
        let max_r = exr
            .image
            .range_m
            .iter()
            .zip(&exr.image.mask)
            .filter(|(_, m)| **m)
            .map(|(r, _)| *r)
            .fold(0.0f32, f32::max);
        assert!(max_r > 0.0 && max_r <= 80.0 + 1e-3, "max range {max_r}");
        // same seed: identical bytes; another seed: different
        for suffix in [".bin", ".exr"] {
            let f = format!("{stem}{suffix}");
            assert_eq!(
                read(&a.join(&f)),
                read(&b.join(&f)),
                "{f}: same seed, other bytes"
            );
            assert_ne!(
                read(&a.join(&f)),
                read(&c.join(&f)),
                "{f}: other seed, same bytes"
            );
        }
    }
    // the two samples of one run differ
    assert_ne!(read(&a.join("scan_000.exr")), read(&a.join("scan_001.exr")));
    // the report names the inputs, the model checksum and the sampler
    let json: serde_json::Value = serde_json::from_slice(&read(&a.join("generate.json"))).unwrap();
    assert_eq!(json["steps"], 2);
    assert_eq!(json["seed"], 7);
    assert_eq!(json["samples"], 2);
    assert_eq!(json["inputs"][0]["calib_kind"], "kitti-object");
    let manifest: serde_json::Value =
        serde_json::from_slice(&read(&model_dir().join("manifest.json"))).unwrap();
    assert_eq!(
        json["model"]["denoiser_sha256"],
        manifest["files"]["denoiser.safetensors"]
    );
    let bin0 = read_kitti_bin(&a.join("scan_000.bin")).unwrap();
    assert_eq!(json["scans"][0]["points"], bin0.cloud.len());

    // $VEILA_MODEL names the model; stderr is a pipe here, not a terminal, so instead of a bar
    // the run prints plain progress lines (the first at once)
    let d = tmp.path().join("d");
    let o = crate::common::veila()
        .env("VEILA_MODEL", model_dir())
        .args(["generate", "--steps", "2", "--image"])
        .arg(&image)
        .arg("--calib")
        .arg(&calib)
        .arg("--out")
        .arg(&d)
        .output()
        .unwrap();
    ok(&o);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr
            .lines()
            .any(|l| l.trim_start().starts_with("generate ") && l.contains("/2 (")),
        "no progress line on a non-terminal stderr:\n{stderr}"
    );
    assert!(
        !stderr.contains('\r') && !stderr.contains("\x1b["),
        "{stderr:?}"
    );
    assert!(d.join("scan_000.bin").is_file());
    // -q: no progress lines
    let e = tmp.path().join("e");
    let o = crate::common::veila()
        .env("VEILA_MODEL", model_dir())
        .args(["generate", "-q", "--steps", "2", "--image"])
        .arg(&image)
        .arg("--calib")
        .arg(&calib)
        .arg("--out")
        .arg(&e)
        .output()
        .unwrap();
    ok(&o);
    assert_eq!(String::from_utf8_lossy(&o.stderr), "");
}

#[test]
fn odometry_calib_two_cameras_and_sampler_flags() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, _) = simulate(tmp.path());
    // the sequence-level calib.txt (P0..P3, Tr) is KITTI odometry format; P3 is the right camera
    let calib = tmp.path().join("sim/calib.txt");
    let out = tmp.path().join("rig");
    let o = veila()
        .args(["generate", "--quiet", "--steps", "1", "--sampler", "ddim"])
        .arg("--image")
        .arg(&image)
        .arg("--image")
        .arg(&image)
        .args(["--camera", "2", "--camera", "3", "--calib"])
        .arg(&calib)
        .arg("--model")
        .arg(model_dir())
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    ok(&o);
    let json: serde_json::Value =
        serde_json::from_slice(&read(&out.join("generate.json"))).unwrap();
    assert_eq!(json["inputs"].as_array().unwrap().len(), 2);
    assert_eq!(json["inputs"][1]["camera"], "3");
    assert_eq!(json["inputs"][0]["calib_kind"], "kitti-odometry");
    assert_eq!(json["sampler"]["kind"]["kind"], "ddim");
    assert_eq!(json["steps"], 1);
}

fn assert_fails_cleanly(o: &Output, out: &Path, needles: &[&str]) {
    assert!(!o.status.success(), "should have failed");
    let err = String::from_utf8_lossy(&o.stderr);
    for n in needles {
        assert!(err.contains(n), "stderr lacks `{n}`:\n{err}");
    }
    assert!(!out.exists(), "output folder left behind");
    let parent = out.parent().unwrap();
    let staging: Vec<_> = std::fs::read_dir(parent)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with(".veila-staging")
        })
        .collect();
    assert!(staging.is_empty(), "staging folder left behind");
}

#[test]
fn bad_input_fails_with_the_file_named_and_no_output() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib) = simulate(tmp.path());
    let out = tmp.path().join("out");

    // a calibration without R0_rect / Tr
    let bad = tmp.path().join("broken_calib.txt");
    std::fs::write(&bad, "P2: 1 0 0 0 0 1 0 0 0 0 1 0\n").unwrap();
    let o = generate(&image, &bad, &out, &["--steps", "1"]);
    assert_fails_cleanly(&o, &out, &["broken_calib.txt"]);

    // a truncated KITTI calibration (P2 with 5 numbers)
    let text = std::fs::read_to_string(&calib).unwrap();
    let cut: String = text
        .lines()
        .map(|l| {
            if l.starts_with("P2:") {
                "P2: 1 2 3 4 5".to_string()
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let trunc = tmp.path().join("truncated_calib.txt");
    std::fs::write(&trunc, cut).unwrap();
    let o = generate(&image, &trunc, &out, &["--steps", "1"]);
    assert_fails_cleanly(&o, &out, &["truncated_calib.txt", "P2"]);

    // a camera the calibration does not have
    let o = generate(&image, &calib, &out, &["--steps", "1", "--camera", "7"]);
    assert_fails_cleanly(&o, &out, &["000000.txt", "7"]);

    // an unreadable image
    let junk = tmp.path().join("junk.png");
    std::fs::write(&junk, b"not an image").unwrap();
    let o = generate(&junk, &calib, &out, &["--steps", "1"]);
    assert_fails_cleanly(&o, &out, &["junk.png"]);

    // an image of another size than the calibration's (principal point outside)
    let big = tmp.path().join("downscaled.png");
    let img = veila_data::image_io::read_rgb_image(&image).unwrap();
    let small = veila_data::image::imageops::resize(
        &img,
        30,
        10,
        veila_data::image::imageops::FilterType::Triangle,
    );
    veila_data::image_io::write_png(&big, &small).unwrap();
    let o = generate(&big, &calib, &out, &["--steps", "1"]);
    assert_fails_cleanly(&o, &out, &["downscaled.png", "principal point"]);

    // zero samples, zero steps
    let o = generate(&image, &calib, &out, &["--samples", "0"]);
    assert_fails_cleanly(&o, &out, &["--samples"]);
    // 0 steps is the mean network alone: only a residual bundle has one
    let steps = if is_residual_bundle(&model_dir().join("bundle.json")) {
        "1001"
    } else {
        "0"
    };
    let o = generate(&image, &calib, &out, &["--steps", steps]);
    assert_fails_cleanly(&o, &out, &["--steps"]);

    // a corrupted model: the manifest check names the file
    let model = tmp.path().join("model");
    std::fs::create_dir(&model).unwrap();
    for e in std::fs::read_dir(model_dir()).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, model.join(p.file_name().unwrap())).unwrap();
    }
    let mut bytes = std::fs::read(model.join("denoiser.safetensors")).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0x55;
    std::fs::write(model.join("denoiser.safetensors"), bytes).unwrap();
    let o = veila()
        .args(["generate", "--quiet", "--steps", "1", "--image"])
        .arg(&image)
        .arg("--calib")
        .arg(&calib)
        .arg("--model")
        .arg(&model)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert_fails_cleanly(&o, &out, &["denoiser.safetensors", "sha256"]);
}

/// Real data: a six-camera nuScenes rig (per-sample JSON calibration) and a KITTI object frame.
#[test]
fn real_nuscenes_rig_and_kitti_frame() {
    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    if !real.is_dir() {
        eprintln!("skipping: {} not found", real.display());
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let calib = std::fs::read_dir(real.join("nuscenes/calib"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let channels = [
        "CAM_FRONT",
        "CAM_FRONT_LEFT",
        "CAM_FRONT_RIGHT",
        "CAM_BACK",
        "CAM_BACK_LEFT",
        "CAM_BACK_RIGHT",
    ];
    let mut cmd = veila();
    cmd.args(["generate", "--quiet", "--steps", "1", "--calib"])
        .arg(&calib)
        .arg("--model")
        .arg(model_dir())
        .arg("--out")
        .arg(tmp.path().join("nus"));
    for ch in channels {
        let img = std::fs::read_dir(real.join("nuscenes/samples").join(ch))
            .unwrap()
            .next()
            .unwrap()
            .unwrap()
            .path();
        cmd.arg("--image").arg(img).args(["--camera", ch]);
    }
    let o = cmd.output().unwrap();
    ok(&o);
    let json: serde_json::Value =
        serde_json::from_slice(&read(&tmp.path().join("nus/generate.json"))).unwrap();
    assert_eq!(json["inputs"].as_array().unwrap().len(), 6);
    assert_eq!(json["inputs"][0]["image_size"][0], 1600);
    assert_eq!(json["inputs"][0]["calib_kind"], "nuscenes-json");
    // nuScenes' LiDAR has y forward: sampled in the model's frame, written in the LiDAR's
    assert_eq!(json["model_frame_quarter_turns"], 1);
    let bin = read_kitti_bin(&tmp.path().join("nus/scan_000.bin")).unwrap();
    assert!(!bin.cloud.is_empty());

    // KITTI 000000 is 1224 x 370 with its own P2
    let k = real.join("kitti/training");
    let out = tmp.path().join("kitti");
    ok(&generate(
        &k.join("image_2/000000.png"),
        &k.join("calib/000000.txt"),
        &out,
        &["--steps", "1"],
    ));
    let json: serde_json::Value =
        serde_json::from_slice(&read(&out.join("generate.json"))).unwrap();
    assert_eq!(
        json["inputs"][0]["image_size"],
        serde_json::json!([1224, 370])
    );
    assert_eq!(json["model_frame_quarter_turns"], 0);
    // an image at half the size does not fit the calibration
    let img = veila_data::image_io::read_rgb_image(&k.join("image_2/000000.png")).unwrap();
    let half = veila_data::image::imageops::resize(
        &img,
        612,
        185,
        veila_data::image::imageops::FilterType::Triangle,
    );
    let half_path = tmp.path().join("half.png");
    veila_data::image_io::write_png(&half_path, &half).unwrap();
    let bad = tmp.path().join("bad");
    let o = generate(
        &half_path,
        &k.join("calib/000000.txt"),
        &bad,
        &["--steps", "1"],
    );
    assert_fails_cleanly(&o, &bad, &["half.png", "principal point"]);
}

/// `--device`: `cpu` runs, `cuda` in a CPU-only build says how to get a CUDA build, and an
/// unknown device is refused by the argument parser; none of them leaves output behind.
#[test]
fn device_flag_selects_or_refuses_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib) = simulate(tmp.path());
    ok(&generate(
        &image,
        &calib,
        &tmp.path().join("cpu"),
        &["--device", "cpu", "--steps", "1"],
    ));
    if cfg!(feature = "cuda") {
        return;
    }
    let o = generate(
        &image,
        &calib,
        &tmp.path().join("gpu"),
        &["--device", "cuda:1", "--steps", "1"],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("built without CUDA") && err.contains("xtask build-cuda"),
        "{err}"
    );
    assert!(!tmp.path().join("gpu").exists());
    let o = generate(
        &image,
        &calib,
        &tmp.path().join("tpu"),
        &["--device", "tpu"],
    );
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("expected cpu, cuda or cuda:N"));
}

/// Each scan has its own noise stream of the seed: `--samples 1` and `--samples 3` give the same
/// `scan_000` (it once drew different noise whenever the count changed). Batched network
/// evaluations round differently from a single one, so the points agree to a fraction of a
/// millimetre rather than bit for bit.
#[test]
fn a_scan_does_not_depend_on_how_many_are_drawn_with_it() {
    let tmp = tempfile::tempdir().unwrap();
    let sim = crate::common::simulate(tmp.path(), &tiny_scene(16, 128, 1), 0);
    let read = |dir: &str| -> Vec<[f32; 4]> {
        std::fs::read(tmp.path().join(dir).join("scan_000.bin"))
            .unwrap()
            .chunks_exact(16)
            .map(|c| {
                std::array::from_fn(|k| f32::from_le_bytes(c[4 * k..4 * k + 4].try_into().unwrap()))
            })
            .collect()
    };
    for (dir, n) in [("one", "1"), ("three", "3")] {
        ok(&generate_cmd(
            &sim,
            &tmp.path().join(dir),
            &["--steps", "4", "--seed", "5", "--samples", n],
        )
        .output()
        .unwrap());
    }
    let (one, three) = (read("one"), read("three"));
    assert_eq!(one.len(), three.len());
    let worst = one
        .iter()
        .zip(&three)
        .flat_map(|(a, b)| (0..3).map(move |k| (a[k] - b[k]).abs()))
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-3, "scan_000 moved by {worst} m");
    // and the seed matters: another seed gives another scan
    ok(&generate_cmd(
        &sim,
        &tmp.path().join("other"),
        &["--steps", "4", "--seed", "6"],
    )
    .output()
    .unwrap());
    assert_ne!(read("other"), one);
}
