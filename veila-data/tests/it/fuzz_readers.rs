//! Byte-mutation fuzzing of every reader: a valid file of each format, mutated (bit flips, byte
//! overwrites with boundary values, truncation, insertion, duplicated and deleted runs, length fields
//! pushed to extremes), must give `Ok` or an error naming the file; never a panic, a hang or an
//! allocation the input cannot justify (the process would abort).
//!
//! CI runs a short pass (`VEILA_FUZZ_CASES` unset: 24 cases per reader). Before each release run
//! at least 10,000 cases per reader:
//!
//! ```sh
//! VEILA_FUZZ_CASES=10000 cargo test --release -p veila-data --test it fuzz_readers::
//! ```
//!
//! A failure prints the minimal mutation list (proptest shrinks it) and the seed file's name.

use std::path::{Path, PathBuf};

use glam::Vec3;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};
use veila_data::PointCloud;
use veila_data::image::{Rgb, RgbImage};
use veila_data::shard::{CameraMatrices, ShardSample};
use veila_geom::{LidarSensor, PinholeCamera, ProjectionOptions, Projector};

/// Cases per reader: `VEILA_FUZZ_CASES`, else a short CI pass.
fn cases() -> u32 {
    std::env::var("VEILA_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(24)
}

#[derive(Debug, Clone)]
enum Mutation {
    /// Flip bit `bit` of byte `at` (positions are taken modulo the length).
    Flip { at: usize, bit: u8 },
    /// Overwrite 1, 2, 4 or 8 bytes at `at` with an interesting value.
    Set { at: usize, width: u8, value: u64 },
    /// Keep the first `keep` bytes (modulo length + 1).
    Truncate { keep: usize },
    /// Insert bytes at `at`.
    Insert { at: usize, bytes: Vec<u8> },
    /// Delete `len` bytes at `at`.
    Delete { at: usize, len: usize },
    /// Repeat the run `[at, at + len)` once more right after itself.
    Duplicate { at: usize, len: usize },
}

fn interesting() -> impl Strategy<Value = u64> {
    prop_oneof![
        Just(0u64),
        Just(1),
        Just(0x7f),
        Just(0xff),
        Just(0xffff),
        Just(0x7fff_ffff),
        Just(0xffff_ffff),
        Just(u64::MAX),
        Just(f32::NAN.to_bits() as u64),
        Just(f32::INFINITY.to_bits() as u64),
        Just(1e30f32.to_bits() as u64),
        any::<u64>(),
    ]
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        4 => (any::<usize>(), 0u8..8).prop_map(|(at, bit)| Mutation::Flip { at, bit }),
        3 => (any::<usize>(), prop_oneof![Just(1u8), Just(2), Just(4), Just(8)], interesting())
            .prop_map(|(at, width, value)| Mutation::Set { at, width, value }),
        1 => any::<usize>().prop_map(|keep| Mutation::Truncate { keep }),
        1 => (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
        1 => (any::<usize>(), 1usize..64).prop_map(|(at, len)| Mutation::Delete { at, len }),
        1 => (any::<usize>(), 1usize..64).prop_map(|(at, len)| Mutation::Duplicate { at, len }),
    ]
}

fn apply(seed: &[u8], muts: &[Mutation]) -> Vec<u8> {
    let mut b = seed.to_vec();
    for m in muts {
        let n = b.len();
        match m {
            Mutation::Flip { at, bit } if n > 0 => b[at % n] ^= 1 << bit,
            Mutation::Set { at, width, value } if n > 0 => {
                let bytes = value.to_le_bytes();
                let at = at % n;
                let len = (*width as usize).min(n - at);
                b[at..at + len].copy_from_slice(&bytes[..len]);
            }
            Mutation::Truncate { keep } => b.truncate(keep % (n + 1)),
            Mutation::Insert { at, bytes } => {
                let at = at % (n + 1);
                b.splice(at..at, bytes.iter().copied());
            }
            Mutation::Delete { at, len } if n > 0 => {
                let at = at % n;
                b.drain(at..(at + len).min(n));
            }
            Mutation::Duplicate { at, len } if n > 0 => {
                let at = at % n;
                let run: Vec<u8> = b[at..(at + len).min(n)].to_vec();
                let end = at + run.len();
                b.splice(end..end, run);
            }
            _ => {}
        }
    }
    b
}

/// Fuzz one reader: `seed` bytes saved as `name` in a temporary folder and mutated, then `read`.
/// Errors must name the file.
fn fuzz<T>(name: &str, seed: Vec<u8>, read: impl Fn(&Path) -> Result<T, veila_data::Error>) {
    let dir = tempfile::tempdir().unwrap();
    let path: PathBuf = dir.path().join(name);
    // the unmutated seed must be valid, or the suite tests nothing
    std::fs::write(&path, &seed).unwrap();
    if let Err(e) = read(&path) {
        panic!("the seed file {name} is not valid: {e}");
    }
    // a fixed seed: the CI pass is the same every time (a failure is a bug, not bad luck)
    let config = Config {
        cases: cases(),
        failure_persistence: None,
        ..Config::default()
    };
    let rng = proptest::test_runner::TestRng::deterministic_rng(config.rng_algorithm);
    let mut runner = TestRunner::new_with_rng(config, rng);
    let result = runner.run(&prop::collection::vec(mutation(), 1..6), |muts| {
        let bytes = apply(&seed, &muts);
        std::fs::write(&path, &bytes).unwrap();
        if let Err(e) = read(&path) {
            let msg = e.to_string();
            prop_assert!(
                msg.contains(name) || msg.contains(&dir.path().display().to_string()),
                "error does not name the file: {msg}"
            );
        }
        Ok(())
    });
    if let Err(e) = result {
        panic!("{name}: {e}");
    }
}

fn cloud() -> PointCloud {
    let n = 200;
    PointCloud {
        xyz: (0..n)
            .map(|i| {
                let a = i as f32 * 0.37;
                Vec3::new(8.0 * a.cos(), 8.0 * a.sin(), -1.0 + 0.01 * i as f32)
            })
            .collect(),
        intensity: (0..n).map(|i| (i % 10) as f32 / 10.0).collect(),
        ring: Some((0..n).map(|i| (i % 32) as u16).collect()),
        label: Some((0..n).map(|i| (i % 5) as u32).collect()),
    }
}

fn small_sensor() -> LidarSensor {
    LidarSensor {
        rows: 8,
        cols: 32,
        ..LidarSensor::hdl64e()
    }
}

fn image() -> RgbImage {
    RgbImage::from_fn(24, 12, |x, y| Rgb([(x * 10) as u8, (y * 20) as u8, 7]))
}

const KITTI_CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\nP2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\nTr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n";
const ODOMETRY_CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\nP2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 0 1 0 0 0\n";
const NUSCENES_JSON: &str = r#"{"sample_token": "t0",
 "lidar": {"file": "samples/LIDAR_TOP/x.pcd.bin", "timestamp_s": 1.0,
   "lidar2ego": {"matrix_4x4_row_major": [[1,0,0,0],[0,1,0,0],[0,0,1,1.8],[0,0,0,1]]}},
 "ego2global_at_lidar_time": {"matrix_4x4_row_major": [[1,0,0,5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
 "cameras": {"CAM_FRONT": {"file": "samples/CAM_FRONT/x.jpg", "timestamp_s": 1.0,
   "intrinsic_3x3": [[1266,0,816],[0,1266,491],[0,0,1]],
   "cam2ego": {"matrix_4x4_row_major": [[0,0,1,1.7],[-1,0,0,0],[0,-1,0,1.5],[0,0,0,1]]},
   "lidar2cam": {"matrix_4x4_row_major": [[0,-1,0,0],[0,0,-1,0.3],[1,0,0,-0.7],[0,0,0,1]]}}},
 "instances_lidar_frame": [{"label": "car", "bbox_3d": [10,2,-1,4,1.8,1.5,0.3], "num_lidar_pts": 40}]}"#;
const LABEL_YAML: &str = "labels:\n  0: unlabeled\n  10: car\n  40: road\ncolor_map:\n  0: [0, 0, 0]\n  10: [245, 150, 100]\n  40: [255, 0, 255]\nlearning_map:\n  0: 0\n  10: 1\n  40: 2\nlearning_map_inv:\n  0: 0\n  1: 10\n  2: 40\nlearning_ignore:\n  0: true\n  1: false\n  2: false\n";

#[test]
fn kitti_bin() {
    let bytes = veila_data::scan::encode_kitti_bin(&cloud());
    fuzz("scan.bin", bytes, veila_data::scan::read_points);
}

#[test]
fn nuscenes_pcd_bin() {
    let c = cloud();
    let mut bytes = Vec::new();
    for k in 0..c.len() {
        let p = c.xyz[k];
        let ring = c.ring.as_ref().unwrap()[k] as f32;
        for v in [p.x, p.y, p.z, 100.0 * c.intensity[k], ring] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    fuzz("scan.pcd.bin", bytes, veila_data::scan::read_points);
}

#[test]
fn ply() {
    let mut bytes = Vec::new();
    veila_data::ply::encode_ply(&cloud(), &mut bytes).unwrap();
    fuzz("scan.ply", bytes, veila_data::scan::read_points);
}

#[test]
fn range_exr() {
    let s = small_sensor();
    let c = cloud();
    let (img, _) = Projector::new(&s, ProjectionOptions::default())
        .unwrap()
        .project(&c.xyz, Some(&c.intensity), None)
        .unwrap();
    let bytes = veila_data::range_exr::encode_range_exr(&s, &img).unwrap();
    fuzz("scan.exr", bytes, veila_data::range_exr::read_range_exr);
}

#[test]
fn png_image() {
    let bytes = veila_data::image_io::encode_png(&image()).unwrap();
    fuzz("img.png", bytes, veila_data::image_io::read_rgb_image);
}

#[test]
fn jpeg_image() {
    let mut buf = std::io::Cursor::new(Vec::new());
    image()
        .write_to(&mut buf, veila_data::image::ImageFormat::Jpeg)
        .unwrap();
    fuzz(
        "img.jpg",
        buf.into_inner(),
        veila_data::image_io::read_rgb_image,
    );
}

#[test]
fn kitti_object_calib() {
    fuzz("calib.txt", KITTI_CALIB.as_bytes().to_vec(), |p| {
        veila_data::kitti::KittiCalib::read(p)?.camera(2, 100, 40)
    });
}

#[test]
fn kitti_odometry_calib() {
    fuzz("calib.txt", ODOMETRY_CALIB.as_bytes().to_vec(), |p| {
        veila_data::semantic_kitti::OdometryCalib::read(p)?.camera(2, 100, 40)
    });
}

#[test]
fn calib_of_any_kind() {
    fuzz("calib.json", NUSCENES_JSON.as_bytes().to_vec(), |p| {
        veila_data::spec::camera_from_calib_file(p, 1600, 900, "CAM_FRONT")
    });
}

#[test]
fn semantic_kitti_labels() {
    let bytes: Vec<u8> = (0..200u32)
        .flat_map(|i| ((i % 5) | (i << 16)).to_le_bytes())
        .collect();
    fuzz("000000.label", bytes, |p| {
        veila_data::semantic_kitti::read_labels(p, Some(200))
    });
}

#[test]
fn semantic_kitti_label_map() {
    fuzz(
        "semantic-kitti.yaml",
        LABEL_YAML.as_bytes().to_vec(),
        veila_data::semantic_kitti::LabelMap::read,
    );
}

#[test]
fn sensor_file() {
    let text = toml::to_string_pretty(&LidarSensor::hdl32e_per_beam()).unwrap();
    fuzz("sensor.toml", text.into_bytes(), |p| {
        veila_data::spec::sensor_from_spec(p.to_str().unwrap())
    });
}

#[test]
fn shard() {
    let s = small_sensor();
    let n = (s.rows * s.cols) as usize;
    let cam = PinholeCamera::new(
        [
            [100.0, 0.0, 12.0, 0.0],
            [0.0, 100.0, 6.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        glam::Mat4::IDENTITY,
        24,
        12,
    )
    .unwrap();
    let sample = ShardSample {
        id: "000000".into(),
        scan: veila_geom::RangeImage {
            range_m: (0..n).map(|i| 1.0 + i as f32 * 0.1).collect(),
            intensity: vec![0.5; n],
            mask: (0..n).map(|i| i % 3 != 0).collect(),
            label: Some(vec![10; n]),
            ..veila_geom::RangeImage::new_empty(s.rows, s.cols)
        },
        train_ids: Some(vec![1; n]),
        image: Some(image()),
        camera: Some(CameraMatrices::from_camera(&cam)),
        // a second camera, so view decoding is fuzzed too
        extra_views: vec![veila_data::shard::ShardView {
            image: image(),
            camera: CameraMatrices::from_camera(&cam),
        }],
    };
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("shard.safetensors");
    veila_data::shard::write_shard(&p, &s, "fuzz", &[sample]).unwrap();
    fuzz(
        "shard-00000.safetensors",
        std::fs::read(&p).unwrap(),
        veila_data::shard::read_shard,
    );
}

#[cfg(feature = "sim")]
#[test]
fn scene_file() {
    let text = "name = \"tiny\"\nlayout = \"straight\"\n[lidar.sensor]\nrows = 8\ncols = 64\nfov_up_deg = 3.0\nfov_down_deg = -25.0\nmin_range_m = 0.5\nmax_range_m = 120.0\n[camera]\nwidth = 40\nheight = 12\nfx = 30.0\nfy = 30.0\ncx = 20.0\ncy = 6.0\n[frames]\ncount = 1\n";
    fuzz(
        "scene.toml",
        text.as_bytes().to_vec(),
        veila_data::sim::SceneConfig::from_file,
    );
}
