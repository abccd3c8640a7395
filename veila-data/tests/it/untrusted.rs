//! Untrusted artifacts: metadata files that are links to `/dev/zero`, FIFOs or sparse giants are
//! refused before they are read (or opened), with an error naming the file; `veila convert`
//! refuses a scan longer than its point cap before hashing it.

use std::fs::File;
use std::path::Path;
use std::time::{Duration, Instant};

use veila_data::convert::{ConvertOptions, convert, open_dataset};
use veila_data::dataset::DatasetName;
use veila_data::kitti::KittiCalib;
use veila_data::read_capped::{MAX_KITTI_SCAN_BYTES, MAX_LABEL_FILE_BYTES};
use veila_data::semantic_kitti::{LabelMap, read_labels};
use veila_data::shard::Manifest;
use veila_geom::LidarSensor;

const CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\nP2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n";

/// A sparse file of `len` bytes (no disk is used), or `None` where the file system refuses.
fn sparse(path: &Path, len: u64) -> Option<()> {
    match File::create(path).and_then(|f| f.set_len(len)) {
        Ok(()) => Some(()),
        Err(e) => {
            eprintln!("skipped: no sparse file of {len} bytes here ({e})");
            None
        }
    }
}

#[cfg(unix)]
fn link_to_dev_zero(path: &Path) {
    std::os::unix::fs::symlink("/dev/zero", path).unwrap();
}

#[cfg(unix)]
#[test]
fn a_shard_manifest_linked_to_dev_zero_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("manifest.json");
    link_to_dev_zero(&p);
    for e in [
        Manifest::read(&p).unwrap_err(),
        Manifest::read_listing(&p).unwrap_err(),
    ] {
        let e = e.to_string();
        assert!(
            e.contains("manifest.json") && e.contains("not a regular file (a character device)"),
            "{e}"
        );
    }
}

#[test]
fn a_sparse_shard_manifest_over_the_cap_is_refused_unread() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("manifest.json");
    let Some(()) = sparse(&p, 3 << 30) else {
        return;
    };
    let e = Manifest::read(&p).unwrap_err().to_string();
    assert!(
        e.contains("manifest.json")
            && e.contains(
                "3221225472 bytes, more than the cap of 67108864 bytes for a shard manifest"
            ),
        "{e}"
    );
}

#[cfg(unix)]
#[test]
fn a_label_map_that_is_a_fifo_is_refused_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("semantic-kitti.yaml");
    match std::process::Command::new("mkfifo").arg(&p).status() {
        Ok(s) if s.success() => {}
        other => {
            eprintln!("skipped: mkfifo is unavailable ({other:?})");
            return;
        }
    }
    let e = LabelMap::read(&p).unwrap_err().to_string();
    assert!(
        e.contains("semantic-kitti.yaml") && e.contains("(a FIFO)"),
        "{e}"
    );
}

#[cfg(unix)]
#[test]
fn a_calibration_linked_to_dev_zero_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("000000.txt");
    link_to_dev_zero(&p);
    let e = KittiCalib::read(&p).unwrap_err().to_string();
    assert!(
        e.contains("000000.txt") && e.contains("not a regular file"),
        "{e}"
    );
    let e = veila_data::spec::read_calib_camera(&p, None, 100, 50)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("000000.txt") && e.contains("not a regular file"),
        "{e}"
    );
}

#[test]
fn a_label_file_longer_than_the_point_cap_is_refused_unread() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("000000.label");
    let Some(()) = sparse(&p, MAX_LABEL_FILE_BYTES + 4) else {
        return;
    };
    let e = read_labels(&p, None).unwrap_err().to_string();
    assert!(
        e.contains("000000.label") && e.contains("more than the cap of 67108864 bytes"),
        "{e}"
    );
}

/// A one-frame KITTI tree whose scan is a sparse file of `scan_len` bytes.
fn kitti_with_scan(root: &Path, scan_len: u64) -> Option<()> {
    let t = root.join("training");
    for d in ["velodyne", "image_2", "calib"] {
        std::fs::create_dir_all(t.join(d)).unwrap();
    }
    std::fs::write(t.join("calib/000000.txt"), CALIB).unwrap();
    veila_data::image::RgbImage::new(20, 10)
        .save(t.join("image_2/000000.png"))
        .unwrap();
    sparse(&t.join("velodyne/000000.bin"), scan_len)
}

#[test]
fn convert_refuses_a_sparse_100_gb_scan_before_hashing_it() {
    let dir = tempfile::tempdir().unwrap();
    let Some(()) = kitti_with_scan(dir.path(), 100_000_000_000) else {
        return;
    };
    let (ds, map) = open_dataset(DatasetName::Kitti, dir.path(), false).unwrap();
    let sensor = LidarSensor {
        rows: 16,
        cols: 64,
        ..LidarSensor::hdl64e()
    };
    let opts = ConvertOptions::new(dir.path().join("out"), sensor);
    let start = Instant::now();
    let e = convert(ds.as_ref(), map.as_ref(), &opts, &|_| {})
        .unwrap_err()
        .to_string();
    // hashing 100 GB of holes would take minutes
    assert!(
        start.elapsed() < Duration::from_secs(30),
        "{:?}",
        start.elapsed()
    );
    assert!(
        e.contains("000000.bin")
            && e.contains(&format!(
                "100000000000 bytes, more than the cap of {MAX_KITTI_SCAN_BYTES} bytes for a KITTI scan"
            )),
        "{e}"
    );
}

// ------------------------------------------------------------------------------------------------
// issue 58, case 10: calibrations must describe a plausible camera for their image, and images
// must be complete

/// KITTI frame 000008's calibration (object benchmark), for its 1242 x 375 image.
const KITTI_P2: &str =
    "721.5377 0.0 609.5593 44.85728 0.0 721.5377 172.854 0.2163791 0.0 0.0 1.0 0.002745884";
const KITTI_TR: &str = "7.533745e-03 -9.999714e-01 -6.166020e-04 -4.069766e-03 1.480249e-02 7.280733e-04 -9.998902e-01 -7.631618e-02 9.998621e-01 7.523790e-03 1.480755e-02 -2.717806e-01";

fn kitti_calib(p2: &str, tr: &str) -> String {
    format!(
        "P0: {KITTI_P2}\nP1: {KITTI_P2}\nP2: {p2}\nP3: {KITTI_P2}\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: {tr}\n"
    )
}

/// The error of camera 2 of the KITTI calibration `text` for a 1242 x 375 image, through every
/// reader: the object and odometry parsers, and `read_calib_camera` (every door's) of both.
fn kitti_camera_errors(dir: &Path, text: &str) -> Vec<String> {
    let object = dir.join("calib_object.txt");
    std::fs::write(&object, text).unwrap();
    let odometry = dir.join("calib_odometry.txt");
    let odo_text = text
        .lines()
        .filter(|l| !l.starts_with("R0_rect"))
        .map(|l| l.replacen("Tr_velo_to_cam:", "Tr:", 1))
        .collect::<Vec<_>>()
        .join("\n");
    std::fs::write(&odometry, odo_text).unwrap();
    let err = |r: veila_data::Result<veila_geom::PinholeCamera>| match r {
        Ok(c) => panic!("accepted: {c:?}"),
        Err(e) => e.to_string(),
    };
    let read = |p: &Path| veila_data::spec::read_calib_camera(p, None, 1242, 375).map(|c| c.camera);
    vec![
        err(KittiCalib::read(&object).and_then(|c| c.camera(2, 1242, 375))),
        err(veila_data::semantic_kitti::OdometryCalib::read(&odometry)
            .and_then(|c| c.camera(2, 1242, 375))),
        err(read(&object)),
        err(read(&odometry)),
    ]
}

#[test]
fn the_real_kitti_calibration_is_accepted_by_every_reader() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("calib.txt");
    std::fs::write(&p, kitti_calib(KITTI_P2, KITTI_TR)).unwrap();
    let cam = KittiCalib::read(&p).unwrap().camera(2, 1242, 375).unwrap();
    assert_eq!(
        veila_data::spec::read_calib_camera(&p, None, 1242, 375)
            .unwrap()
            .camera,
        cam
    );
    cam.check_calibration().unwrap();
}

#[test]
fn kitti_calibrations_with_implausible_cameras_are_refused_saying_why() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(String, String, &[&str]); 5] = [
        // a negative focal length
        (
            KITTI_P2.replacen("721.5377", "-721.5377", 1),
            KITTI_TR.to_string(),
            &["focal lengths", "-721.5377", "must be positive"],
        ),
        // fy = 0
        (
            KITTI_P2.replacen("0.0 721.5377", "0.0 0.0", 1),
            KITTI_TR.to_string(),
            &["focal lengths", "fy 0", "must be positive"],
        ),
        // the principal point of 1e7 was "the 3x3 part of K is singular"
        (
            KITTI_P2.replacen("609.5593", "1e7", 1),
            KITTI_TR.to_string(),
            &[
                "principal point (10000000, 172.854)",
                "outside the 1242 x 375 image",
            ],
        ),
        // a LiDAR-to-camera translation of 1e30 m
        (
            KITTI_P2.to_string(),
            KITTI_TR.replacen("-4.069766e-03", "1e30", 1),
            &["LiDAR-to-camera translation", "limit of 100 m"],
        ),
        // a stereo offset of 1e4 m in P2's fourth column
        (
            KITTI_P2.replacen("44.85728", "7.2e6", 1),
            KITTI_TR.to_string(),
            &["fourth column of the projection matrix", "limit of 100 m"],
        ),
    ];
    for (p2, tr, words) in cases {
        for e in kitti_camera_errors(dir.path(), &kitti_calib(&p2, &tr)) {
            assert!(e.contains("calib_o"), "the file is not named: {e}");
            assert!(!e.contains("singular"), "{e}");
            for w in words {
                assert!(e.contains(w), "`{w}` not in: {e}");
            }
        }
    }
}

/// A per-sample nuScenes JSON whose CAM_FRONT has the 3x3 intrinsics `k` and translation `t`.
fn nuscenes_json(k: &str, t: [&str; 3]) -> String {
    format!(
        r#"{{"sample_token": "t0",
 "lidar": {{"file": "samples/LIDAR_TOP/x.pcd.bin", "timestamp_s": 1.0,
   "lidar2ego": {{"matrix_4x4_row_major": [[1,0,0,0],[0,1,0,0],[0,0,1,1.8],[0,0,0,1]]}}}},
 "ego2global_at_lidar_time": {{"matrix_4x4_row_major": [[1,0,0,5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}},
 "cameras": {{"CAM_FRONT": {{"file": "samples/CAM_FRONT/x.jpg", "timestamp_s": 1.0,
   "intrinsic_3x3": {k},
   "cam2ego": {{"matrix_4x4_row_major": [[0,0,1,1.7],[-1,0,0,0],[0,-1,0,1.5],[0,0,0,1]]}},
   "lidar2cam": {{"matrix_4x4_row_major": [[0,-1,0,{}],[0,0,-1,{}],[1,0,0,{}],[0,0,0,1]]}}}}}}}}"#,
        t[0], t[1], t[2]
    )
}

#[test]
fn nuscenes_calibrations_with_implausible_cameras_are_refused_saying_why() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("sample.json");
    let good_k = "[[1266,0,816],[0,1266,491],[0,0,1]]";
    let good_t = ["0", "0.3", "-0.7"];
    std::fs::write(&p, nuscenes_json(good_k, good_t)).unwrap();
    let read = |p: &Path| {
        veila_data::spec::read_calib_camera(p, Some("CAM_FRONT"), 1600, 900).map(|c| c.camera)
    };
    read(&p).unwrap();
    let cases: [(&str, [&str; 3], &[&str]); 4] = [
        (
            "[[-1266,0,816],[0,1266,491],[0,0,1]]",
            good_t,
            &["focal lengths", "-1266", "must be positive"],
        ),
        (
            "[[1266,0,816],[0,-1266,491],[0,0,1]]",
            good_t,
            &["focal lengths", "fy -1266"],
        ),
        (
            "[[1266,0,816],[0,1266,1e9],[0,0,1]]",
            good_t,
            &["principal point", "outside the 1600 x 900 image"],
        ),
        (
            good_k,
            ["1e30", "0.3", "-0.7"],
            &["translation", "limit of 100 m"],
        ),
    ];
    for (k, t, words) in cases {
        std::fs::write(&p, nuscenes_json(k, t)).unwrap();
        let sample = veila_data::nuscenes::NuScenesSample::read_json(&p).unwrap();
        let direct = sample
            .camera("CAM_FRONT", 1600, 900)
            .unwrap_err()
            .to_string();
        assert!(direct.contains("sample t0, camera CAM_FRONT"), "{direct}");
        let via_file = read(&p).unwrap_err().to_string();
        assert!(via_file.contains("sample.json"), "{via_file}");
        for e in [direct, via_file] {
            for w in words {
                assert!(e.contains(w), "`{w}` not in: {e}");
            }
        }
    }
}

/// A 64 x 48 test image, noisy enough that its JPEG has a long entropy-coded scan.
fn test_image() -> veila_data::image::RgbImage {
    veila_data::image::RgbImage::from_fn(64, 48, |x, y| {
        let v = (x * 37 + y * 91 + x * y) as u8;
        veila_data::image::Rgb([v, v.wrapping_mul(7), (x * 4) as u8])
    })
}

fn encoded(format: veila_data::image::ImageFormat) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    test_image().write_to(&mut buf, format).unwrap();
    buf.into_inner()
}

#[test]
fn truncated_jpeg_and_png_images_are_refused_naming_the_file() {
    use veila_data::image::ImageFormat;
    use veila_data::image_io::{check_complete, read_rgb_image};
    let dir = tempfile::tempdir().unwrap();
    for (format, name) in [
        (ImageFormat::Jpeg, "cut.jpg"),
        (ImageFormat::Png, "cut.png"),
    ] {
        let bytes = encoded(format);
        // the whole file reads, and so does one with a trailer after its end (some cameras append
        // one after a JPEG's end-of-image marker)
        let whole = dir.path().join(format!("whole_{name}"));
        std::fs::write(&whole, &bytes).unwrap();
        assert_eq!(read_rgb_image(&whole).unwrap().dimensions(), (64, 48));
        let mut trailer = bytes.clone();
        trailer.extend_from_slice(b"TRAILER\0\0\0");
        assert!(check_complete(&trailer, format).is_ok());
        // a third of it (the issue's case: the JPEG decoded without an error), and every cut from
        // the first byte after the header to the last byte
        let cut = dir.path().join(name);
        std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
        let e = read_rgb_image(&cut).unwrap_err().to_string();
        assert!(e.contains(name) && e.contains("truncated"), "{e}");
        for len in 12..bytes.len() {
            assert!(
                check_complete(&bytes[..len], format).is_err(),
                "{name} cut to {len} of {} bytes passed",
                bytes.len()
            );
        }
    }
}

/// A shard that is a FIFO inside the manifest's folder (a downloaded archive can hold one) was
/// opened, which blocks until a writer comes: refused unopened, by the manifest check, the shard
/// reader and the whole-file reader.
#[cfg(unix)]
#[test]
fn a_shard_that_is_a_fifo_is_refused_without_blocking() {
    use veila_data::shard::{Manifest, ShardReader, read_shard};
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("shard-00000.safetensors");
    match std::process::Command::new("mkfifo").arg(&p).status() {
        Ok(s) if s.success() => {}
        other => {
            eprintln!("skipped: mkfifo is unavailable ({other:?})");
            return;
        }
    }
    let (tx, rx) = std::sync::mpsc::channel();
    let (q, d) = (p.clone(), dir.path().to_path_buf());
    std::thread::spawn(move || {
        let manifest = serde_json::json!({
            "format": veila_data::shard::MANIFEST_FORMAT, "dataset": "x",
            "sensor": veila_geom::LidarSensor::hdl64e(), "frames_per_shard": 1, "count": 1,
            "shards": [{"file": "shard-00000.safetensors", "count": 1, "bytes": 0,
                        "sha256": "00", "ids": ["000000"]}],
        });
        let mp = d.join("manifest.json");
        std::fs::write(&mp, manifest.to_string()).unwrap();
        let _ = tx.send((
            ShardReader::open(&q).map(drop).map_err(|e| e.to_string()),
            read_shard(&q).map(drop).map_err(|e| e.to_string()),
            Manifest::read(&mp).map(drop).map_err(|e| e.to_string()),
        ));
    });
    let (a, b, c) = rx
        .recv_timeout(std::time::Duration::from_secs(10))
        .expect("blocked on the FIFO");
    for e in [a.unwrap_err(), b.unwrap_err(), c.unwrap_err()] {
        assert!(
            e.contains("shard-00000.safetensors") && e.contains("(a FIFO)"),
            "{e}"
        );
    }
}
