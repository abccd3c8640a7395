//! `veila edit`: the kept pixels of the scan come back exactly (up to the range encoding's
//! round-off), the regenerated ones change, and bad requests fail without output.

use std::path::{Path, PathBuf};
use std::process::Output;

use veila_data::range_exr::read_range_exr;
use veila_data::scan::{PointFormat, read_points};
use veila_diffusion::app::bundle::BundleConfig;
use veila_geom::{LidarSensor, ProjectionOptions, Projector, RangeImage, RayTable};

use crate::common::*;

/// (image, calib, scan)
fn simulate(dir: &Path) -> (PathBuf, PathBuf, PathBuf) {
    let sim = crate::common::simulate(dir, &tiny_scene(32, 512, 1), 5);
    (
        sim.join("image_2/000000.png"),
        sim.join("calib/000000.txt"),
        sim.join("velodyne/000000.bin"),
    )
}

fn model_sensor() -> LidarSensor {
    let cfg: BundleConfig =
        serde_json::from_slice(&std::fs::read(model_dir().join("bundle.json")).unwrap()).unwrap();
    cfg.denoiser.sensor
}

fn edit(image: &Path, calib: &Path, scan: &Path, out: &Path, extra: &[&str]) -> Output {
    veila()
        .args(["edit", "--quiet", "--image"])
        .arg(image)
        .arg("--calib")
        .arg(calib)
        .arg("--scan")
        .arg(scan)
        .arg("--model")
        .arg(model_dir())
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

/// The scan on the model grid, projected here independently of the command (returns nearer than
/// the encoding's minimum range are left out: the model cannot represent them; nuScenes'
/// intensities, 0..255, on the model's 0..1).
fn before(scan: &Path) -> RangeImage {
    let loaded = read_points(scan).unwrap();
    let pts = loaded.cloud;
    let cfg: BundleConfig =
        serde_json::from_slice(&std::fs::read(model_dir().join("bundle.json")).unwrap()).unwrap();
    let scale = if loaded.format == PointFormat::NuScenesPcdBin && cfg.encoding.intensity_max <= 1.0
    {
        255.0
    } else {
        1.0
    };
    let keep: Vec<usize> = (0..pts.xyz.len())
        .filter(|&i| pts.xyz[i].length() >= cfg.encoding.min_range_m)
        .collect();
    let xyz: Vec<_> = keep.iter().map(|&i| pts.xyz[i]).collect();
    let intensity: Vec<f32> = keep.iter().map(|&i| pts.intensity[i] / scale).collect();
    let projector = Projector::new(&model_sensor(), ProjectionOptions::default()).unwrap();
    projector.project(&xyz, Some(&intensity), None).unwrap().0
}

/// Checks an edit of `--remove-box b` (`[x0, y0, z0, x1, y1, z1]`, LiDAR frame): the expected
/// region, brute force, is the returns whose point lies in the box; it must hold enough returns,
/// the rest must be kept and most of it regenerated ([`check_edit`]). Returns the region.
fn check_box_edit(before: &RangeImage, out: &Path, b: [f32; 6]) -> Vec<bool> {
    let rays = RayTable::new(&model_sensor()).unwrap();
    let regen: Vec<bool> = (0..before.range_m.len())
        .map(|k| {
            let (r, c) = (k as u32 / before.cols, k as u32 % before.cols);
            let p = rays.dir(r, c) * before.range_m[k];
            before.mask[k]
                && (b[0]..=b[3]).contains(&p.x)
                && (b[1]..=b[4]).contains(&p.y)
                && (b[2]..=b[5]).contains(&p.z)
        })
        .collect();
    assert!(
        regen.iter().filter(|r| **r).count() > 50,
        "box holds too few returns"
    );
    let frac = check_edit(before, out, &regen);
    assert!(
        frac > 0.5,
        "only {frac:.2} of the regenerated pixels changed"
    );
    regen
}

/// Checks kept pixels are kept and regenerated pixels changed; returns the changed fraction.
fn check_edit(before: &RangeImage, out: &Path, regen: &[bool]) -> f64 {
    let mask_png = veila_data::image::open(out.join("mask.png"))
        .unwrap()
        .into_luma8();
    let written: Vec<bool> = mask_png.pixels().map(|p| p.0[0] > 127).collect();
    assert_eq!(written, regen, "mask.png differs from the expected region");
    let after = read_range_exr(&out.join("scan_000.exr")).unwrap().image;
    assert_eq!((after.rows, after.cols), (before.rows, before.cols));
    let mut kept = 0;
    let (mut changed, mut total) = (0usize, 0usize);
    for k in 0..regen.len() {
        if regen[k] {
            total += 1;
            if after.mask[k] != before.mask[k]
                || (after.range_m[k] - before.range_m[k]).abs() > 1e-3
            {
                changed += 1;
            }
            continue;
        }
        assert_eq!(
            after.mask[k], before.mask[k],
            "kept pixel {k}: return flag changed"
        );
        if before.mask[k] {
            // the model encodes ranges up to 80 m (log scale, f32): round-off only
            let want = before.range_m[k].min(80.0);
            let got = after.range_m[k];
            assert!(
                (got - want).abs() <= 1e-5 * want + 1e-5,
                "kept pixel {k}: range {want} became {got}"
            );
            let (wi, gi) = (before.intensity[k].clamp(0.0, 1.0), after.intensity[k]);
            assert!(
                (gi - wi).abs() <= 1e-5,
                "kept pixel {k}: intensity {wi} became {gi}"
            );
            kept += 1;
        }
    }
    assert!(kept > 100, "too few kept returns to test ({kept})");
    assert!(total > 0);
    changed as f64 / total as f64
}

#[test]
fn remove_box_keeps_the_rest_exactly_and_regenerates_the_box() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib, scan) = simulate(tmp.path());
    let out = tmp.path().join("edit");
    let b = [2.0f32, -6.0, -3.0, 25.0, 6.0, 3.0];
    let spec = "2,-6,-3,25,6,3";
    ok(&edit(
        &image,
        &calib,
        &scan,
        &out,
        &["--remove-box", spec, "--steps", "2", "--seed", "1"],
    ));
    let regen = check_box_edit(&before(&scan), &out, b);
    for f in [
        "scan_000.bin",
        "scan_000_range.png",
        "scan_000_bev.png",
        "scan_000_overlay.png",
        "scan_000_before_after.png",
        "before_range.png",
        "edit.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("edit.json")).unwrap()).unwrap();
    assert_eq!(
        json["regenerated_pixels"],
        regen.iter().filter(|r| **r).count()
    );
    // edit keeps the bundle's default sampler where RePaint can follow it (ddpm, ddim) and
    // switches a multistep DPM-Solver++ default to deterministic DDIM
    let bundle: serde_json::Value =
        serde_json::from_slice(&std::fs::read(model_dir().join("bundle.json")).unwrap()).unwrap();
    let expected = match bundle["sampler"]["kind"]["kind"].as_str().unwrap() {
        "dpm_solver_pp2_m" => "ddim",
        other => other,
    };
    assert_eq!(json["sampler"]["kind"]["kind"], expected);
    assert_eq!(json["sampler"]["steps"], 2, "--steps 2 was asked");
}

#[test]
fn mask_image_of_any_size_is_resized_nearest() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib, scan) = simulate(tmp.path());
    let sensor = model_sensor();
    let (rows, cols) = (sensor.rows, sensor.cols);
    // a mask at 2x the grid: white block over columns [cols/4, cols/2) and rows [rows/2, rows)
    let mask = veila_data::image::GrayImage::from_fn(cols * 2, rows * 2, |x, y| {
        let (c, r) = (x / 2, y / 2);
        veila_data::image::Luma([if c >= cols / 4 && c < cols / 2 && r >= rows / 2 {
            255
        } else {
            0
        }])
    });
    let mask_path = tmp.path().join("mask_2x.png");
    mask.save(&mask_path).unwrap();
    let out = tmp.path().join("edit");
    ok(&edit(
        &image,
        &calib,
        &scan,
        &out,
        &[
            "--mask",
            mask_path.to_str().unwrap(),
            "--steps",
            "2",
            "--sampler",
            "ddpm",
        ],
    ));
    let regen: Vec<bool> = (0..rows * cols)
        .map(|k| {
            let (r, c) = (k / cols, k % cols);
            c >= cols / 4 && c < cols / 2 && r >= rows / 2
        })
        .collect();
    let frac = check_edit(&before(&scan), &out, &regen);
    assert!(
        frac > 0.5,
        "only {frac:.2} of the regenerated pixels changed"
    );
}

#[test]
fn bad_edits_fail_without_output() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib, scan) = simulate(tmp.path());
    let out = tmp.path().join("edit");
    let cases: [(&[&str], &[&str]); 5] = [
        (
            &["--remove-box", "2,-6,-3,25,6,3", "--sampler", "dpm"],
            &["dpm", "ddim"],
        ),
        (
            &["--remove-box", "500,500,500,600,600,600"],
            &["no return", "000000.bin"],
        ),
        (&["--remove-box", "1,2,3"], &["6 numbers"]),
        (&["--remove-box", "5,0,0,1,1,1"], &["minimum"]),
        (&[], &["--mask", "--remove-box"]),
    ];
    for (args, needles) in cases {
        let o = edit(&image, &calib, &scan, &out, args);
        assert!(!o.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&o.stderr);
        for n in needles {
            assert!(err.contains(n), "{args:?}: stderr lacks `{n}`:\n{err}");
        }
        assert!(!out.exists(), "{args:?}: output left behind");
    }
    // an all-black mask selects nothing
    let black = tmp.path().join("black.png");
    veila_data::image::GrayImage::new(16, 4)
        .save(&black)
        .unwrap();
    let o = edit(
        &image,
        &calib,
        &scan,
        &out,
        &["--mask", black.to_str().unwrap()],
    );
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("black.png"));
    assert!(!out.exists());
}

/// Real nuScenes data: its LiDAR frame has y forward, so the scan and the box are turned into the
/// model's frame for inpainting and the result back. The kept pixels coming back exactly, in the
/// calibration's frame, shows the scan and the keep mask turned together and back.
#[test]
fn real_nuscenes_edit_runs_in_the_model_frame_and_keeps_the_rest() {
    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/nuscenes");
    if !real.is_dir() {
        eprintln!("skipping: {} not found", real.display());
        return;
    }
    let first = |dir: &str| {
        std::fs::read_dir(real.join(dir))
            .unwrap()
            .next()
            .unwrap()
            .unwrap()
            .path()
    };
    let (image, calib, scan) = (
        first("samples/CAM_FRONT"),
        first("calib"),
        first("samples/LIDAR_TOP"),
    );
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("edit");
    // ahead of the car in nuScenes' frame (y forward, x right)
    let b = [-6.0f32, 3.0, -3.0, 6.0, 30.0, 3.0];
    ok(&edit(
        &image,
        &calib,
        &scan,
        &out,
        &[
            "--camera",
            "CAM_FRONT",
            "--remove-box",
            "-6,3,-3,6,30,3",
            "--steps",
            "2",
            "--seed",
            "1",
        ],
    ));
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("edit.json")).unwrap()).unwrap();
    assert_eq!(json["model_frame_quarter_turns"], 1);
    // the scan on the model grid in nuScenes' own frame
    check_box_edit(&before(&scan), &out, b);
}
