//! Dataset -> shards on a small synthetic KITTI tree: content, resumption, corruption, worker split,
//! bad output folders, and lazy iteration with bad frames.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use veila_data::convert::{ConvertOptions, Progress, convert, open_dataset};
use veila_data::dataset::DatasetName;
use veila_data::dataset::frames;
use veila_data::image::{Rgb, RgbImage};
use veila_data::kitti::KittiObjectDataset;
use veila_data::shard::{Manifest, read_shard};
use veila_geom::{LidarSensor, NO_POINT, ProjectionOptions, Projector};

/// A calibration for the 20 x 10 (to 24 x 10) images of [`make_kitti`]: its principal point lies
/// in the image, as a real one does.
const CALIB: &str = "P0: 10 0 10 0 0 10 5 0 0 0 1 0\nP1: 10 0 10 0 0 10 5 0 0 0 1 0\nP2: 10 0 10 0 0 10 5 0 0 0 1 0\nP3: 10 0 10 0 0 10 5 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\nTr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n";

fn make_kitti(root: &Path, frames: usize) {
    let t = root.join("training");
    for d in ["velodyne", "image_2", "calib"] {
        std::fs::create_dir_all(t.join(d)).unwrap();
    }
    for f in 0..frames {
        let id = format!("{f:06}");
        let bytes: Vec<u8> = (0..300)
            .flat_map(|i| {
                let a = i as f32 * 0.21 + f as f32;
                let r = 4.0 + (i % 7) as f32;
                [r * a.cos(), r * a.sin(), -1.0, (i % 10) as f32 / 10.0]
            })
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(t.join(format!("velodyne/{id}.bin")), bytes).unwrap();
        RgbImage::from_pixel(20 + f as u32, 10, Rgb([f as u8, 0, 0]))
            .save(t.join(format!("image_2/{id}.png")))
            .unwrap();
        std::fs::write(t.join(format!("calib/{id}.txt")), CALIB).unwrap();
    }
}

fn small_sensor() -> LidarSensor {
    LidarSensor {
        rows: 16,
        cols: 64,
        ..LidarSensor::hdl64e()
    }
}

fn opts(out: &Path) -> ConvertOptions {
    let mut o = ConvertOptions::new(out, small_sensor());
    o.frames_per_shard = 2;
    o
}

#[test]
fn shards_hold_exactly_the_projected_frames() {
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 5);
    let (ds, map) = open_dataset(DatasetName::Kitti, dir.path(), true).unwrap();
    assert_eq!(ds.len(), 5);
    let out = dir.path().join("out");
    let seen = AtomicUsize::new(0);
    let total = AtomicUsize::new(0);
    let progress = |p: Progress| match p {
        Progress::Start { frames } => total.store(frames, Ordering::SeqCst),
        Progress::Frames(k) => {
            seen.fetch_add(k, Ordering::SeqCst);
        }
    };
    let s = convert(ds.as_ref(), map.as_ref(), &opts(&out), &progress).unwrap();
    assert_eq!((s.total_shards, s.written_shards, s.frames), (3, 3, 5));
    assert_eq!(
        (seen.load(Ordering::SeqCst), total.load(Ordering::SeqCst)),
        (5, 5)
    );
    assert!(s.manifest_written);
    let m = Manifest::read(&out.join("manifest.json")).unwrap();
    assert_eq!(m.count, 5);
    assert_eq!(
        m.shards.iter().map(|e| e.count).collect::<Vec<_>>(),
        vec![2, 2, 1]
    );
    m.verify(&out).unwrap();

    // every sample equals an independent projection of its frame
    let projector = Projector::new(&small_sensor(), ProjectionOptions::default()).unwrap();
    let mut k = 0;
    for e in &m.shards {
        let shard = read_shard(&out.join(&e.file)).unwrap();
        assert_eq!(shard.sensor, small_sensor());
        for sample in &shard.samples {
            let f = ds.load(k).unwrap();
            assert_eq!(sample.id, f.id);
            let (img, _) = projector
                .project(&f.points.xyz, Some(&f.points.intensity), None)
                .unwrap();
            assert_eq!(sample.scan.range_m, img.range_m);
            assert_eq!(sample.scan.mask, img.mask);
            assert_eq!(sample.image.as_ref().unwrap(), f.image.as_ref().unwrap());
            let cam = sample
                .camera
                .unwrap()
                .to_camera(f.image.as_ref().unwrap().width(), 10)
                .unwrap();
            assert_eq!(cam.cam_from_lidar, f.camera.unwrap().cam_from_lidar);
            assert!(img.point_index.iter().any(|p| *p != NO_POINT));
            k += 1;
        }
    }
    assert_eq!(k, 5);
}

#[test]
fn resume_skips_complete_shards_and_rebuilds_damaged_ones() {
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 5);
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    let out = dir.path().join("out");
    convert(&ds, None, &opts(&out), &|_| {}).unwrap();
    let m1 = std::fs::read(out.join("manifest.json")).unwrap();

    let s = convert(&ds, None, &opts(&out), &|_| {}).unwrap();
    assert_eq!((s.written_shards, s.skipped_shards, s.frames), (0, 3, 0));

    // flip a byte in shard 1 (as a crash or bit rot would): only that shard is rebuilt
    let m = Manifest::read(&out.join("manifest.json")).unwrap();
    let p = out.join(&m.shards[1].file);
    let mut b = std::fs::read(&p).unwrap();
    let mid = b.len() / 2;
    b[mid] ^= 0xff;
    std::fs::write(&p, &b).unwrap();
    // and delete the sidecar of shard 2 (killed between the shard and its sidecar)
    std::fs::remove_file(out.join(format!("{}.json", m.shards[2].file))).unwrap();
    let s = convert(&ds, None, &opts(&out), &|_| {}).unwrap();
    assert_eq!((s.written_shards, s.skipped_shards, s.frames), (2, 1, 3));
    assert_eq!(
        std::fs::read(out.join("manifest.json")).unwrap(),
        m1,
        "deterministic output"
    );

    // other settings never reuse old shards
    let mut o = opts(&out);
    o.include_images = false;
    let s = convert(&ds, None, &o, &|_| {}).unwrap();
    assert_eq!(s.written_shards, 3);
    let m2 = Manifest::read(&out.join("manifest.json")).unwrap();
    assert!(
        read_shard(&out.join(&m2.shards[0].file)).unwrap().samples[0]
            .image
            .is_none()
    );
    // the earlier conversion's shards are gone once the new one is published
    assert_eq!(folder_files(&out), published_files(&out));
}

/// The files of `out` a reader or a user sees (not the conversion's hidden lock files).
fn folder_files(out: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with(".veila-"))
        .collect();
    v.sort();
    v
}

/// `manifest.json`, the shards it lists and their sidecars.
fn published_files(out: &Path) -> Vec<String> {
    let m = Manifest::read(&out.join("manifest.json")).unwrap();
    let mut v = vec!["manifest.json".to_string()];
    for e in &m.shards {
        v.push(e.file.clone());
        v.push(format!("{}.json", e.file));
    }
    v.sort();
    v
}

/// The bytes of `manifest.json` and of every file it lists.
fn published_bytes(out: &Path) -> Vec<(String, Vec<u8>)> {
    published_files(out)
        .into_iter()
        .filter(|n| !n.ends_with(".safetensors.json"))
        .map(|n| {
            let b = std::fs::read(out.join(&n)).unwrap();
            (n, b)
        })
        .collect()
}

/// Shard files of `out` for shard `k`.
fn shard_files(out: &Path, k: usize) -> Vec<String> {
    folder_files(out)
        .into_iter()
        .filter(|n| n.starts_with(&format!("shard-{k:05}-")) && n.ends_with(".safetensors"))
        .collect()
}

#[test]
fn a_failed_reconversion_leaves_the_published_dataset_whole() {
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 5);
    let out = dir.path().join("out");
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    convert(&ds, None, &opts(&out), &|_| {}).unwrap();
    let before = published_bytes(&out);

    // other settings, and frame 4 (the last shard's) unreadable: shards 0 and 1 are written
    // beside the published ones, then the run fails, as a killed one would stop
    let calib4 = dir.path().join("training/calib/000004.txt");
    std::fs::write(&calib4, CALIB.replace("P2: 10 ", "P2: x10 ")).unwrap();
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    let mut o = opts(&out);
    o.include_images = false;
    let e = convert(&ds, None, &o, &|_| {}).unwrap_err().to_string();
    assert!(e.contains("000004.txt"), "{e}");
    assert_eq!(
        published_bytes(&out),
        before,
        "the published dataset is wholly old"
    );
    Manifest::read(&out.join("manifest.json"))
        .unwrap()
        .verify(&out)
        .unwrap();
    assert_eq!(shard_files(&out, 0).len(), 2, "new shard 0 beside the old");

    // repaired, the next run publishes the new dataset and removes every shard it does not list
    std::fs::write(&calib4, CALIB).unwrap();
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    let s = convert(&ds, None, &o, &|_| {}).unwrap();
    assert_eq!((s.written_shards, s.skipped_shards), (1, 2));
    assert_ne!(published_bytes(&out), before);
    assert_eq!(folder_files(&out), published_files(&out));
}

#[test]
fn workers_pick_the_shard_of_the_current_sources() {
    // shard 1 converted, its frame 2 changed under the same id, shard 1 converted again: two
    // complete shard-1 files with the same settings; the worker writing the manifest must list
    // the one made from the current files
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 5);
    let out = dir.path().join("out");
    let mut o = opts(&out);
    o.worker_count = 2;
    o.worker_index = 1;
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    convert(&ds, None, &o, &|_| {}).unwrap();
    let first = shard_files(&out, 1);
    RgbImage::from_pixel(22, 10, Rgb([9, 9, 9]))
        .save(dir.path().join("training/image_2/000002.png"))
        .unwrap();
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    convert(&ds, None, &o, &|_| {}).unwrap();
    let both = shard_files(&out, 1);
    assert_eq!(both.len(), 2, "{both:?}");
    o.worker_index = 0;
    let s = convert(&ds, None, &o, &|_| {}).unwrap();
    assert!(s.manifest_written);
    let m = Manifest::read(&out.join("manifest.json")).unwrap();
    assert!(
        !first.contains(&m.shards[1].file),
        "the old shard 1 was listed"
    );
    let img = read_shard(&out.join(&m.shards[1].file)).unwrap().samples[0]
        .image
        .clone()
        .unwrap();
    assert_eq!(img.get_pixel(0, 0), &Rgb([9, 9, 9]));
    assert_eq!(folder_files(&out), published_files(&out));
}

#[test]
fn a_folder_of_other_files_or_another_dataset_is_refused_untouched() {
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 3);
    let ds = KittiObjectDataset::open(dir.path()).unwrap();

    // a folder with the user's own files
    let mine = dir.path().join("mine");
    std::fs::create_dir(&mine).unwrap();
    std::fs::write(mine.join("notes.txt"), b"keep me").unwrap();
    let e = convert(&ds, None, &opts(&mine), &|_| {})
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("notes.txt") && e.contains("nothing was changed"),
        "{e}"
    );
    assert_eq!(folder_files(&mine), vec!["notes.txt".to_string()]);
    assert_eq!(std::fs::read_dir(&mine).unwrap().count(), 1);

    // a folder holding another dataset's conversion
    let other = dir.path().join("other");
    convert(&ds, None, &opts(&other), &|_| {}).unwrap();
    let text = std::fs::read_to_string(other.join("manifest.json")).unwrap();
    std::fs::write(
        other.join("manifest.json"),
        text.replace("\"kitti\"", "\"nuscenes\""),
    )
    .unwrap();
    let before = published_bytes(&other);
    let e = convert(&ds, None, &opts(&other), &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("nuscenes") && e.contains("manifest.json"), "{e}");
    assert_eq!(published_bytes(&other), before);
}

#[test]
fn workers_split_shards_and_the_last_one_writes_the_manifest() {
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 5);
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    let out = dir.path().join("out");
    let mut o = opts(&out);
    o.worker_count = 2;
    o.worker_index = 1;
    let s = convert(&ds, None, &o, &|_| {}).unwrap();
    assert_eq!(
        (s.assigned_shards, s.written_shards, s.manifest_written),
        (1, 1, false)
    );
    assert!(shard_files(&out, 1).len() == 1 && shard_files(&out, 0).is_empty());
    assert!(!out.join("manifest.json").exists());
    o.worker_index = 0;
    let s = convert(&ds, None, &o, &|_| {}).unwrap();
    assert_eq!(
        (s.assigned_shards, s.written_shards, s.manifest_written),
        (2, 2, true)
    );
    Manifest::read(&out.join("manifest.json"))
        .unwrap()
        .verify(&out)
        .unwrap();
    o.worker_index = 2;
    assert!(convert(&ds, None, &o, &|_| {}).is_err());
}

#[test]
fn unwritable_output_fails_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 2);
    let ds = KittiObjectDataset::open(dir.path()).unwrap();
    std::fs::write(dir.path().join("file"), b"x").unwrap();
    let out = dir.path().join("file/out");
    let called = AtomicUsize::new(0);
    let e = convert(&ds, None, &opts(&out), &|_| {
        called.fetch_add(1, Ordering::SeqCst);
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("file/out") || e.contains("file"), "{e}");
    assert_eq!(called.load(Ordering::SeqCst), 0);
}

#[test]
fn a_bad_frame_fails_the_run_with_its_file_and_writes_no_shard() {
    let dir = tempfile::tempdir().unwrap();
    make_kitti(dir.path(), 3);
    let t = dir.path().join("training");
    std::fs::write(
        t.join("calib/000001.txt"),
        CALIB.replace("P2: 10 ", "P2: x10 "),
    )
    .unwrap();
    let ds = KittiObjectDataset::open(dir.path())
        .unwrap()
        .with_images(false);
    // lazy iteration: frame 0 fine, frame 1 fails with its file named, frame 2 fine again
    let results: Vec<_> = frames(&ds).collect();
    assert!(results[0].is_ok() && results[2].is_ok());
    let e = results[1].as_ref().unwrap_err().to_string();
    assert!(e.contains("000001.txt") && e.contains("x10"), "{e}");
    let out = dir.path().join("out");
    let mut o = opts(&out);
    o.frames_per_shard = 3;
    assert!(convert(&ds, None, &o, &|_| {}).is_err());
    let left: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(left.is_empty(), "{left:?}");
}
