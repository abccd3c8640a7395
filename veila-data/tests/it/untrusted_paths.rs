//! Paths inside artifacts stay inside (issue 58, cases 3 and 4): a nuScenes calibration's
//! `lidar.file` / `cameras.<CH>.file` and a shard manifest's `shards[].file` that are absolute,
//! climb out with `..` or lead out through a link are refused with an error naming the field and
//! the file, before the target is opened or hashed; a nested relative path inside is accepted.

use std::path::{Path, PathBuf};

use veila_data::convert::{ConvertOptions, convert, open_dataset};
use veila_data::dataset::Dataset;
use veila_data::dataset::DatasetName;
use veila_data::nuscenes::NuScenesDataset;
use veila_data::shard::{MANIFEST_FORMAT, Manifest, ShardSample, write_shard};
use veila_geom::LidarSensor;

/// A per-sample nuScenes JSON naming `lidar` and `camera` (relative to the data root).
fn sample_json(lidar: &str, camera: &str) -> String {
    serde_json::json!({
        "sample_token": "t0",
        "lidar": {"file": lidar, "timestamp_s": 1.0,
            "lidar2ego": {"matrix_4x4_row_major": [[1,0,0,0],[0,1,0,0],[0,0,1,1.8],[0,0,0,1]]}},
        "ego2global_at_lidar_time":
            {"matrix_4x4_row_major": [[1,0,0,5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
        "cameras": {"CAM_FRONT": {"file": camera, "timestamp_s": 1.0,
            "intrinsic_3x3": [[100,0,50],[0,100,20],[0,0,1]],
            "cam2ego": {"matrix_4x4_row_major": [[0,0,1,1.7],[-1,0,0,0],[0,-1,0,1.5],[0,0,0,1]]},
            "lidar2cam": {"matrix_4x4_row_major": [[0,-1,0,0],[0,0,-1,0.3],[1,0,0,-0.7],[0,0,0,1]]}}}
    })
    .to_string()
}

/// A sweep of three points ahead (x, y, z, intensity, ring as `f32`).
fn sweep_bytes() -> Vec<u8> {
    [
        [5.0f32, 0.5, 0.2, 10.0, 3.0],
        [8.0, -1.0, 0.0, 20.0, 5.0],
        [12.0, 2.0, 1.0, 30.0, 7.0],
    ]
    .iter()
    .flatten()
    .flat_map(|v| v.to_le_bytes())
    .collect()
}

fn png_bytes(shade: u8) -> Vec<u8> {
    let img = veila_data::image::RgbImage::from_pixel(100, 40, veila_data::image::Rgb([shade; 3]));
    veila_data::image_io::encode_png(&img).unwrap()
}

/// `tmp/root` (a nuScenes data root whose sample JSON names `lidar` and `camera`, with a real
/// sweep and image at `samples/...`) and `tmp/outside` (a private image and sweep beside it).
fn nuscenes_root(tmp: &Path, lidar: &str, camera: &str) -> PathBuf {
    let root = tmp.join("root");
    for d in ["calib", "samples/LIDAR_TOP", "samples/CAM_FRONT"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    std::fs::write(root.join("samples/LIDAR_TOP/x.pcd.bin"), sweep_bytes()).unwrap();
    std::fs::write(root.join("samples/CAM_FRONT/x.png"), png_bytes(90)).unwrap();
    let outside = tmp.join("outside");
    std::fs::create_dir_all(&outside).unwrap();
    std::fs::write(outside.join("private.png"), png_bytes(200)).unwrap();
    std::fs::write(outside.join("sweep.pcd.bin"), sweep_bytes()).unwrap();
    std::fs::write(root.join("calib/t0.json"), sample_json(lidar, camera)).unwrap();
    root
}

/// Every way of reading sample 0's files: loading the frame, listing its sources, and `convert`
/// (which hashes the sources and copies the image into a shard). Each must fail naming `want`.
fn nuscenes_refused(root: &Path, want: &[&str]) {
    let ds = NuScenesDataset::open(root, "CAM_FRONT").unwrap();
    let errors = [
        ds.load(0).map(|_| ()).unwrap_err().to_string(),
        ds.source_files(0).map(|_| ()).unwrap_err().to_string(),
    ];
    for e in &errors {
        for w in want {
            assert!(e.contains(w), "`{w}` missing from: {e}");
        }
        assert!(
            e.contains("calib/t0.json") && e.contains("nothing read"),
            "{e}"
        );
    }
    let (ds, map) = open_dataset(DatasetName::NuScenes, root, true).unwrap();
    let sensor = LidarSensor {
        rows: 8,
        cols: 32,
        ..LidarSensor::hdl32e()
    };
    let out = root.parent().unwrap().join("shards");
    let e = convert(
        ds.as_ref(),
        map.as_ref(),
        &ConvertOptions::new(&out, sensor),
        &|_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(want.iter().all(|w| e.contains(w)), "{e}");
    // no shard holds the outside file's bytes
    let shards = std::fs::read_dir(&out).map_or(0, |rd| {
        rd.flatten()
            .filter(|e| e.file_name().to_string_lossy().ends_with(".safetensors"))
            .count()
    });
    assert_eq!(shards, 0);
}

#[test]
fn nuscenes_sample_files_inside_the_root_are_read() {
    let tmp = tempfile::tempdir().unwrap();
    let root = nuscenes_root(
        tmp.path(),
        "samples/LIDAR_TOP/x.pcd.bin",
        "./samples/CAM_FRONT/x.png",
    );
    let ds = NuScenesDataset::open(&root, "CAM_FRONT").unwrap();
    let f = ds.load(0).unwrap();
    assert_eq!(f.points.len(), 3);
    assert_eq!(f.image.unwrap().get_pixel(0, 0).0, [90; 3]);
    assert_eq!(
        ds.source_files(0).unwrap(),
        [
            root.join("samples/LIDAR_TOP/x.pcd.bin"),
            root.join("./samples/CAM_FRONT/x.png"),
            root.join("calib/t0.json"),
        ]
    );
}

#[test]
fn an_absolute_nuscenes_camera_file_is_refused_naming_the_field() {
    let tmp = tempfile::tempdir().unwrap();
    let private = tmp.path().join("outside/private.png");
    let root = nuscenes_root(
        tmp.path(),
        "samples/LIDAR_TOP/x.pcd.bin",
        private.to_str().unwrap(),
    );
    assert!(private.is_file());
    nuscenes_refused(&root, &["cameras.CAM_FRONT.file", "an absolute path"]);
}

#[test]
fn a_nuscenes_lidar_file_climbing_out_is_refused_naming_the_field() {
    let tmp = tempfile::tempdir().unwrap();
    let root = nuscenes_root(
        tmp.path(),
        "../outside/sweep.pcd.bin",
        "samples/CAM_FRONT/x.png",
    );
    assert!(root.join("../outside/sweep.pcd.bin").is_file());
    nuscenes_refused(
        &root,
        &["lidar.file", "`../outside/sweep.pcd.bin`", "climbs out"],
    );
}

#[cfg(unix)]
#[test]
fn a_nuscenes_camera_file_linked_out_of_the_root_is_refused_naming_the_field() {
    let tmp = tempfile::tempdir().unwrap();
    let root = nuscenes_root(
        tmp.path(),
        "samples/LIDAR_TOP/x.pcd.bin",
        "samples/CAM_FRONT/link.png",
    );
    std::os::unix::fs::symlink(
        tmp.path().join("outside/private.png"),
        root.join("samples/CAM_FRONT/link.png"),
    )
    .unwrap();
    nuscenes_refused(
        &root,
        &[
            "cameras.CAM_FRONT.file",
            "leads through the link `samples/CAM_FRONT/link.png`",
        ],
    );
}

// ---------------------------------------------------------------------------- shard manifests

/// `tmp/shards` with one real shard listed as `file` in its manifest (with the real shard's size
/// and hash), and the same shard outside at `tmp/outside/shard-00000.safetensors`.
fn shards_listing(tmp: &Path, file: &str) -> PathBuf {
    let sensor = LidarSensor {
        rows: 4,
        cols: 16,
        ..LidarSensor::hdl64e()
    };
    let sample = ShardSample {
        id: "000000".into(),
        scan: veila_geom::RangeImage::new_empty(sensor.rows, sensor.cols),
        train_ids: None,
        image: None,
        camera: None,
        extra_views: Vec::new(),
    };
    let dir = tmp.join("shards");
    let outside = tmp.join("outside");
    std::fs::create_dir_all(dir.join("nested")).unwrap();
    std::fs::create_dir_all(&outside).unwrap();
    let mut entry = write_shard(
        &dir.join("nested/shard-00000.safetensors"),
        &sensor,
        "sim",
        std::slice::from_ref(&sample),
    )
    .unwrap();
    std::fs::copy(
        dir.join("nested/shard-00000.safetensors"),
        outside.join("shard-00000.safetensors"),
    )
    .unwrap();
    entry.file = file.into();
    Manifest {
        format: MANIFEST_FORMAT.into(),
        dataset: "sim".into(),
        sensor,
        frames_per_shard: 1,
        count: 1,
        shards: vec![entry],
    }
    .write(&dir.join("manifest.json"))
    .unwrap();
    dir
}

/// Reading the manifest (with or without the shards' headers), and verifying its listing as
/// given, all fail naming `shards[0].file`, `want` and the manifest, and none says the outside
/// file's size or hash.
fn manifest_refused(dir: &Path, want: &str) {
    let p = dir.join("manifest.json");
    let listed: Manifest = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    let errors = [
        Manifest::read(&p).unwrap_err().to_string(),
        Manifest::read_listing(&p).unwrap_err().to_string(),
        listed.verify(dir).unwrap_err().to_string(),
        listed.shard_path(dir, 0).unwrap_err().to_string(),
    ];
    // the outside copy is the listed shard byte for byte: its size and hash are the entry's
    let outside_bytes = format!("{} bytes", listed.shards[0].bytes);
    for e in &errors {
        assert!(
            e.contains("manifest.json") && e.contains("shards[0].file") && e.contains(want),
            "{e}"
        );
        assert!(
            !e.contains("sha256")
                && !e.contains(&listed.shards[0].sha256)
                && !e.contains(&outside_bytes),
            "says something of the outside file: {e}"
        );
    }
}

#[test]
fn a_nested_shard_inside_the_folder_is_read() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = shards_listing(tmp.path(), "nested/shard-00000.safetensors");
    let m = Manifest::read(&dir.join("manifest.json")).unwrap();
    m.verify(&dir).unwrap();
    assert_eq!(
        m.shard_path(&dir, 0).unwrap(),
        dir.join("nested/shard-00000.safetensors")
    );
    assert!(m.shard_path(&dir, 1).is_err());
}

#[test]
fn an_absolute_shard_path_is_refused_without_hashing_it() {
    let tmp = tempfile::tempdir().unwrap();
    let outside = tmp.path().join("outside/shard-00000.safetensors");
    let dir = shards_listing(tmp.path(), outside.to_str().unwrap());
    manifest_refused(&dir, "an absolute path");
}

#[test]
fn a_shard_path_climbing_out_is_refused_without_hashing_it() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = shards_listing(tmp.path(), "../outside/shard-00000.safetensors");
    manifest_refused(&dir, "climbs out");
}

#[cfg(unix)]
#[test]
fn a_shard_linked_out_of_the_folder_is_refused_without_hashing_it() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = shards_listing(tmp.path(), "out/shard-00000.safetensors");
    std::os::unix::fs::symlink(tmp.path().join("outside"), dir.join("out")).unwrap();
    manifest_refused(&dir, "leads through the link `out`");
}
