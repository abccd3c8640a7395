//! `ScanPipeline` with the bundled model gives scans in the LiDAR's own frame, whichever way that
//! frame faces (issue 46: the library's path sampled a nuScenes rig, whose LiDAR has `y` forward,
//! without turning it into the model's frame, and gave another scan than `veila generate`).
//!
//! The check needs no reference numbers: one rig described in two LiDAR frames a quarter turn
//! apart (nuScenes' `y` forward and KITTI's `x` forward) must give the same scan, turned by that
//! quarter turn, point for point. Run on a synthetic rig, and on the real nuScenes CAM_FRONT
//! sample of `../shared/data/real` when it is there.

use std::f32::consts::FRAC_PI_2;
use std::path::{Path, PathBuf};

use candle_core::Device;
use glam::{Mat3, Mat4, Vec3};
use veila_data::image::{Rgb, RgbImage};
use veila_diffusion::app::{Bundle, GenerateOptions, RigImage, Scan, ScanPipeline, load_view};
use veila_geom::PinholeCamera;

fn bundled() -> Bundle {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/default");
    Bundle::from_dir(&dir, &Device::Cpu).unwrap()
}

/// A 1242 x 375 KITTI-like camera whose LiDAR has `y` forward: the camera looks along LiDAR `+y`.
fn y_forward_camera() -> PinholeCamera {
    // KITTI's axes: camera z = LiDAR x, camera x = -LiDAR y, camera y = -LiDAR z
    let kitti = Mat4::from_cols_array_2d(&[
        [0.0, 0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, -0.08, -0.27, 1.0],
    ]);
    // p_kitti = R_z(-90°) p_nus takes the y-forward frame's +y to +x
    let cam_from_lidar = kitti * Mat4::from_rotation_z(-FRAC_PI_2);
    let k = [
        [721.5, 0.0, 609.6, 44.9],
        [0.0, 721.5, 172.9, 0.2],
        [0.0, 0.0, 1.0, 0.003],
    ];
    PinholeCamera::new(k, cam_from_lidar, 1242, 375).unwrap()
}

/// A street-like picture: sky above the horizon, a road below, a bright block on the left.
fn synthetic_image() -> RgbImage {
    RgbImage::from_fn(1242, 375, |x, y| {
        if (200..420).contains(&x) && (90..240).contains(&y) {
            Rgb([230, 210, 60])
        } else if y < 173 {
            Rgb([120, 160, 220 - (y / 2) as u8])
        } else {
            let g = 60 + ((x / 40 + y / 25) % 3) as u8 * 20;
            Rgb([g, g, g + 10])
        }
    })
}

/// The same camera, its LiDAR frame turned so that `x` is forward: `p_x = R_z(-90°) p_y`.
fn x_forward(camera: &PinholeCamera) -> PinholeCamera {
    PinholeCamera {
        cam_from_lidar: camera.cam_from_lidar * Mat4::from_rotation_z(FRAC_PI_2),
        ..*camera
    }
}

fn one_scan(bundle: &Bundle, image: &RgbImage, camera: &PinholeCamera, turns: i32) -> Scan {
    let pipeline = ScanPipeline::new(bundle, &[RigImage { image, camera }]).unwrap();
    assert_eq!(pipeline.quarter_turns(), turns);
    let options = GenerateOptions {
        seed: 11,
        ..GenerateOptions::new(bundle.config.sampler.clone())
    };
    pipeline.generate(&options, |_, _| {}).unwrap().remove(0)
}

/// The scans of one rig in a `y`-forward and an `x`-forward LiDAR frame are one scan, turned.
fn check_turned_frames_agree(what: &str, bundle: &Bundle, image: &RgbImage, y_cam: &PinholeCamera) {
    let y = one_scan(bundle, image, y_cam, 1);
    let x = one_scan(bundle, image, &x_forward(y_cam), 0);
    assert_eq!(y.points.len(), x.points.len(), "{what}");
    assert!(y.points.len() > 1000, "{what}: {} points", y.points.len());
    // the range images hold the same values, moved: a quarter of the columns
    let sorted = |s: &Scan| {
        let mut v: Vec<u32> = s.range.range_m.iter().map(|r| r.to_bits()).collect();
        v.sort_unstable();
        v
    };
    assert_eq!(sorted(&y), sorted(&x), "{what}");
    assert_ne!(y.range.range_m, x.range.range_m, "{what}: no turn at all");
    // and the points are the same points in the other frame, up to the rays' float rounding: each
    // turned point has an x-forward point within 1 mm (looked up in the 27 centimetre cells around
    // it, so a point on a cell's edge is found as well as one inside)
    let turn = Mat3::from_rotation_z(-FRAC_PI_2);
    let cell = |p: Vec3| {
        (
            (p.x * 100.0).floor() as i64,
            (p.y * 100.0).floor() as i64,
            (p.z * 100.0).floor() as i64,
        )
    };
    let mut cells: std::collections::HashMap<(i64, i64, i64), Vec<Vec3>> = Default::default();
    for p in &x.points.xyz {
        cells.entry(cell(*p)).or_default().push(*p);
    }
    let found = |p: Vec3| {
        let (cx, cy, cz) = cell(p);
        (-1..=1).any(|dx| {
            (-1..=1).any(|dy| {
                (-1..=1).any(|dz| {
                    cells
                        .get(&(cx + dx, cy + dy, cz + dz))
                        .is_some_and(|ps| ps.iter().any(|q| q.distance(p) < 1e-3))
                })
            })
        })
    };
    let differ = y.points.xyz.iter().filter(|p| !found(turn * **p)).count();
    assert_eq!(
        differ,
        0,
        "{what}: {differ} of {} points are not the x-forward scan's, turned",
        y.points.len()
    );
}

#[test]
fn a_y_forward_lidar_gets_the_x_forward_scan_turned() {
    let bundle = bundled();
    check_turned_frames_agree(
        "synthetic rig",
        &bundle,
        &synthetic_image(),
        &y_forward_camera(),
    );
}

#[test]
fn the_real_nuscenes_front_camera_gets_its_scan_in_the_lidar_frame() {
    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/nuscenes");
    if !real.is_dir() {
        eprintln!("skipping: {} not found", real.display());
        return;
    }
    let first = |dir: PathBuf| -> PathBuf {
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        files.sort();
        files.remove(0)
    };
    let view = load_view(
        &first(real.join("samples/CAM_FRONT")),
        &first(real.join("calib")),
        None,
    )
    .unwrap();
    check_turned_frames_agree("nuScenes CAM_FRONT", &bundled(), &view.image, &view.camera);
}
