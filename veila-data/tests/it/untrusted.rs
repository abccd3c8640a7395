//! Untrusted artifacts: metadata files that are links to `/dev/zero`, FIFOs or sparse giants are
//! refused before they are read (or opened), with an error naming the file; `veila convert`
//! refuses a scan longer than its point cap before hashing it.

use std::fs::File;
use std::path::Path;
use std::time::{Duration, Instant};

use veila_data::convert::{ConvertOptions, convert, open_dataset};
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
    let e = veila_data::spec::camera_from_calib_file(&p, 100, 50, "CAM_FRONT")
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
    let (ds, map) = open_dataset("kitti", dir.path(), false).unwrap();
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
