//! Tests on the real sensor samples in `../shared/data/real` (skipped when the folder is absent).
//! Reference numbers come from `tests/data/golden_real.json`, made by `tests/data/make_golden_real.py`
//! with numpy/PyYAML independently of this crate; some checks also recompute a brute-force reference
//! here.

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec4, Vec3};
use serde_json::Value;
use veila_data::dataset::{Dataset, frames};
use veila_data::kitti::{KittiCalib, KittiObjectDataset};
use veila_data::nuscenes::{NuScenesDataset, NuScenesSample, NuScenesTables, Pose, cam_from_lidar};
use veila_data::scan::{PointFormat, read_points};
use veila_data::semantic_kitti::{LabelMap, SemanticKittiDataset, Sequences, read_labels};
use veila_geom::{LidarSensor, NO_POINT, ProjectionOptions, Projector};

fn real() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("skipping: {} not found", p.display());
        None
    }
}

fn golden() -> Value {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/golden_real.json");
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

fn g(v: &Value, path: &[&str]) -> u64 {
    let mut x = v;
    for k in path {
        x = &x[*k];
    }
    x.as_u64()
        .unwrap_or_else(|| panic!("golden {path:?} missing"))
}

#[test]
fn kitti_point_counts_and_points_in_image_2() {
    let Some(root) = real() else { return };
    let gold = golden();
    let ds = KittiObjectDataset::open(&root.join("kitti"))
        .unwrap()
        .with_images(false);
    assert_eq!(ds.ids(), ["000000", "000001"]);
    let expected_counts = [115_384usize, 120_268];
    for (i, frame) in frames(&ds).enumerate() {
        let frame = frame.unwrap();
        let key = format!("kitti_{}", frame.id);
        assert_eq!(frame.points.len(), expected_counts[i]);
        assert_eq!(frame.points.len() as u64, g(&gold, &[&key, "points"]));
        assert_eq!(frame.dropped_non_finite, 0);
        let cam = frame.camera.unwrap();
        assert_eq!(
            (cam.width as u64, cam.height as u64),
            (g(&gold, &[&key, "width"]), g(&gold, &[&key, "height"]))
        );
        let n_in = frame
            .points
            .xyz
            .iter()
            .filter(|p| cam.try_project_in_image(**p).is_some())
            .count();

        // brute force in f64 from the calibration numbers
        let calib = KittiCalib::read(&ds.base().join(format!("calib/{}.txt", frame.id))).unwrap();
        let m34 = |m: [[f32; 4]; 3]| {
            DMat4::from_cols_array_2d(&[
                [m[0][0] as f64, m[1][0] as f64, m[2][0] as f64, 0.0],
                [m[0][1] as f64, m[1][1] as f64, m[2][1] as f64, 0.0],
                [m[0][2] as f64, m[1][2] as f64, m[2][2] as f64, 0.0],
                [m[0][3] as f64, m[1][3] as f64, m[2][3] as f64, 1.0],
            ])
        };
        let full = m34(calib.p[2])
            * DMat4::from_mat3(calib.r0_rect.as_dmat3())
            * m34(calib.tr_velo_to_cam);
        let brute = frame
            .points
            .xyz
            .iter()
            .filter(|p| {
                let q = full * DVec4::new(p.x as f64, p.y as f64, p.z as f64, 1.0);
                if q.z <= 0.1 {
                    return false;
                }
                let (u, v) = (q.x / q.z, q.y / q.z);
                u >= -0.5 && u < cam.width as f64 - 0.5 && v >= -0.5 && v < cam.height as f64 - 0.5
            })
            .count();
        let gold_in = g(&gold, &[&key, "in_image_2"]) as usize;
        assert!(
            n_in.abs_diff(brute) <= 3,
            "{key}: {n_in} vs brute force {brute}"
        );
        assert!(
            n_in.abs_diff(gold_in) <= 3,
            "{key}: {n_in} vs numpy {gold_in}"
        );
        assert!(
            (18_000..=21_000).contains(&n_in),
            "{key}: {n_in} points in image_2"
        );
    }
    // boxes of label_2
    let labels = ds.labels(0).unwrap();
    assert_eq!(labels.len(), 1);
    assert_eq!(labels[0].class, "Pedestrian");
}

#[test]
fn read_points_detects_every_real_format() {
    let Some(root) = real() else { return };
    let k = read_points(&root.join("kitti/training/velodyne/000001.bin")).unwrap();
    assert_eq!((k.format, k.cloud.len()), (PointFormat::KittiBin, 120_268));
    let nus_dir = root.join("nuscenes/samples/LIDAR_TOP");
    let nus_file = std::fs::read_dir(&nus_dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let n = read_points(&nus_file).unwrap();
    let gold = golden();
    assert_eq!(n.format, PointFormat::NuScenesPcdBin);
    assert_eq!(
        n.cloud.len() as u64,
        g(&gold, &["nuscenes_cam_front", "points"])
    );
    let rings = n.cloud.ring.as_ref().unwrap();
    let mut per_ring = [0usize; 32];
    for r in rings {
        per_ring[*r as usize] += 1;
    }
    assert!(per_ring.iter().all(|c| *c == 1084), "{per_ring:?}");
    let near = n.cloud.xyz.iter().filter(|p| p.length() < 1.0).count();
    assert_eq!(near as u64, g(&gold, &["nuscenes_cam_front", "within_1m"]));
    assert!(n.cloud.intensity.iter().all(|i| (0.0..=255.0).contains(i)));
}

#[test]
fn semantickitti_counts_and_label_histogram_through_learning_map() {
    let Some(root) = real() else { return };
    let gold = golden();
    let sk = root.join("semantickitti");
    let ds = SemanticKittiDataset::open(
        &sk,
        Sequences::Split(veila_data::semantic_kitti::SplitPart::Train),
    )
    .unwrap()
    .with_required_labels(true);
    assert_eq!(ds.len(), 2);
    assert_eq!(ds.frame_id(0), "00/000000");
    let map = ds.label_map().unwrap().clone();
    // the split and map as the README states them
    assert_eq!(map.split.train, vec![0, 1, 2, 3, 4, 5, 6, 7, 9, 10]);
    assert_eq!(map.split.valid, vec![8]);
    assert_eq!(map.split.test, (11..=21).collect::<Vec<_>>());
    assert_eq!(map.names.len(), 34);
    assert_eq!(map.num_classes(), 20);
    for (t, raw) in &map.learning_map_inv {
        if *t != 0 {
            assert_eq!(
                map.learning_map[raw], *t,
                "learning_map_inv[{t}] = {raw} does not map back"
            );
        }
    }
    // colours: car is [245, 150, 100] in BGR
    assert_eq!(map.color_rgb(10), [100, 150, 245]);

    for (i, key) in ["semantickitti_000000", "semantickitti_000001"]
        .iter()
        .enumerate()
    {
        let f = ds.load(i).unwrap();
        assert_eq!(f.points.len() as u64, g(&gold, &[key, "points"]));
        let labels = f.points.label.as_ref().unwrap();
        assert_eq!(labels.len(), f.points.len());
        let hist = map.train_histogram(labels);
        // brute force: linear search in the parsed map, not the lookup table
        let mut brute = vec![0u64; 20];
        for l in labels {
            let t = map
                .learning_map
                .iter()
                .find(|(k, _)| **k == (l & 0xFFFF) as u16)
                .map_or(0, |(_, v)| *v);
            brute[t as usize] += 1;
        }
        assert_eq!(hist, brute);
        let numpy: Vec<u64> = gold[key]["train_histogram"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        assert_eq!(hist, numpy, "{key}");
    }
    assert_eq!(frames(&ds).next().unwrap().unwrap().points.len(), 124_668);
}

#[test]
fn semantickitti_label_count_mismatch_is_an_error() {
    let Some(root) = real() else { return };
    let p = root.join("semantickitti/sequences/00/labels/000001.label");
    let e = read_labels(&p, Some(124_668)).unwrap_err().to_string();
    assert!(
        e.contains("000001.label") && e.contains("124605 labels") && e.contains("124668 points"),
        "{e}"
    );
}

fn nuscenes_json(root: &Path) -> PathBuf {
    root.join("nuscenes/calib/ca9a282c9e77460f8360f564131a8af5.json")
}

#[test]
fn nuscenes_cam_front_points_in_image() {
    let Some(root) = real() else { return };
    let gold = golden();
    let ds = NuScenesDataset::open(&root.join("nuscenes"), "CAM_FRONT")
        .unwrap()
        .with_images(false);
    assert_eq!(ds.len(), 1);
    let f = ds.load(0).unwrap();
    let cam = f.camera.unwrap();
    assert_eq!((cam.width, cam.height), (1600, 900));
    let devkit = f
        .points
        .xyz
        .iter()
        .filter_map(|p| cam.try_project(*p))
        .filter(|ip| {
            ip.depth_m > 1.0
                && ip.u_px > 1.0
                && ip.u_px < 1599.0
                && ip.v_px > 1.0
                && ip.v_px < 899.0
        })
        .count();
    let plain = f
        .points
        .xyz
        .iter()
        .filter_map(|p| cam.try_project_in_image(*p))
        .filter(|ip| ip.depth_m > 1.0)
        .count();
    let gd = g(&gold, &["nuscenes_cam_front", "in_image_devkit_rule"]) as usize;
    let gp = g(&gold, &["nuscenes_cam_front", "in_image_depth_gt_1m"]) as usize;
    assert!(devkit.abs_diff(gd) <= 2, "{devkit} vs numpy {gd}");
    assert!(plain.abs_diff(gp) <= 2, "{plain} vs numpy {gp}");
    // the front camera sees points ahead (x > 0 in the LiDAR frame? nuScenes LIDAR_TOP has y forward)
    let s = NuScenesSample::read_json(&nuscenes_json(&root)).unwrap();
    assert_eq!(s.cameras.len(), 6);
    assert_eq!(s.boxes.len(), 69);
}

#[test]
fn nuscenes_paper_cameras_come_as_extra_views() {
    let Some(root) = real() else { return };
    let dir = root.join("nuscenes");
    let ds = NuScenesDataset::open_cameras(&dir, &veila_data::nuscenes::PAPER_CAMERAS).unwrap();
    let f = ds.load(0).unwrap();
    let s = NuScenesSample::read_json(&nuscenes_json(&root)).unwrap();
    assert_eq!(f.camera.unwrap(), s.camera("CAM_FRONT", 1600, 900).unwrap());
    let names: Vec<&str> = f.extra_views.iter().map(|v| v.channel.as_str()).collect();
    assert_eq!(names, ["CAM_FRONT_LEFT", "CAM_FRONT_RIGHT"]);
    let mut seen = Vec::new();
    for v in &f.extra_views {
        let img = v.image.as_ref().unwrap();
        assert_eq!(img.dimensions(), (1600, 900));
        assert_eq!(v.camera, s.camera(&v.channel, 1600, 900).unwrap());
        assert!(v.image_path.to_string_lossy().contains(&v.channel));
        // each side camera sees its own part of the sweep
        let visible: Vec<usize> = f
            .points
            .xyz
            .iter()
            .enumerate()
            .filter(|(_, p)| {
                v.camera
                    .try_project_in_image(**p)
                    .is_some_and(|ip| ip.depth_m > 1.0)
            })
            .map(|(i, _)| i)
            .collect();
        assert!(
            visible.len() > 1000,
            "{}: {} points",
            v.channel,
            visible.len()
        );
        seen.push(visible);
    }
    let shared = seen[0].iter().filter(|i| seen[1].contains(i)).count();
    assert!(
        shared < seen[0].len() / 10,
        "left and right see the same points"
    );
    // one camera by name, a camera twice, an unknown one
    assert!(
        NuScenesDataset::open_cameras(&dir, &["CAM_FRONT"])
            .unwrap()
            .load(0)
            .unwrap()
            .extra_views
            .is_empty()
    );
    assert!(NuScenesDataset::open_cameras(&dir, &["CAM_FRONT", "CAM_FRONT"]).is_err());
    assert!(NuScenesDataset::open_cameras(&dir, &["CAM_TOP"]).is_err());
    assert!(NuScenesDataset::open_cameras(&dir, &[]).is_err());
}

/// Build nuScenes release tables from the raw records quoted in the sample JSON, read them with
/// [`NuScenesTables`] and check the devkit chain against the precomputed `lidar2cam`.
#[test]
fn nuscenes_tables_chain_matches_lidar2cam() {
    let Some(root) = real() else { return };
    let text = std::fs::read_to_string(nuscenes_json(&root))
        .unwrap()
        .replace("NaN", "null");
    let j: Value = serde_json::from_str(&text).unwrap();
    let cc = &j["cross_check_raw_records"];
    let arr = |v: &Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let lidar_cs = Pose {
        rotation_wxyz: arr(&j["lidar"]["lidar2ego"]["rotation_quaternion_wxyz"])
            .try_into()
            .unwrap(),
        translation: arr(&j["lidar"]["lidar2ego"]["translation"])
            .try_into()
            .unwrap(),
    };
    let ego_l = Pose {
        rotation_wxyz: arr(&j["ego2global_at_lidar_time"]["rotation_quaternion_wxyz"])
            .try_into()
            .unwrap(),
        translation: arr(&j["ego2global_at_lidar_time"]["translation"])
            .try_into()
            .unwrap(),
    };
    let ego_c = Pose {
        rotation_wxyz: arr(&cc["CAM_FRONT_ego_pose"]["rotation_wxyz"])
            .try_into()
            .unwrap(),
        translation: arr(&cc["CAM_FRONT_ego_pose"]["translation"])
            .try_into()
            .unwrap(),
    };
    let cam_cs = Pose {
        rotation_wxyz: arr(&cc["CAM_FRONT_calibrated_sensor"]["rotation_wxyz"])
            .try_into()
            .unwrap(),
        translation: arr(&cc["CAM_FRONT_calibrated_sensor"]["translation"])
            .try_into()
            .unwrap(),
    };
    let expected = {
        let rows = j["cameras"]["CAM_FRONT"]["lidar2cam"]["matrix_4x4_row_major"]
            .as_array()
            .unwrap();
        let m: Vec<Vec<f64>> = rows.iter().map(arr).collect();
        DMat4::from_cols_array_2d(&[
            [m[0][0], m[1][0], m[2][0], m[3][0]],
            [m[0][1], m[1][1], m[2][1], m[3][1]],
            [m[0][2], m[1][2], m[2][2], m[3][2]],
            [m[0][3], m[1][3], m[2][3], m[3][3]],
        ])
    };
    let chained = cam_from_lidar(&lidar_cs, &ego_l, &ego_c, &cam_cs);
    let diff = (chained - expected)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |a, b| a.max(b.abs()));
    assert!(diff < 1e-4, "max |chain - lidar2cam| = {diff}");
    // and the naive inv(cam2ego) * lidar2ego (no ego motion) is measurably worse for CAM_FRONT
    let naive = cam_cs.to_matrix().inverse() * lidar_cs.to_matrix();
    let naive_diff = (naive - expected)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |a, b| a.max(b.abs()));
    assert!(naive_diff > 0.1, "{naive_diff}");

    // the same through release tables on disk
    let dir = tempfile::tempdir().unwrap();
    let t = dir.path().join("v1.0-mini");
    std::fs::create_dir(&t).unwrap();
    let lidar_file = j["lidar"]["file"].as_str().unwrap();
    let cam_file = j["cameras"]["CAM_FRONT"]["file"].as_str().unwrap();
    let k = &cc["CAM_FRONT_calibrated_sensor"]["camera_intrinsic"];
    let write = |name: &str, v: Value| std::fs::write(t.join(name), v.to_string()).unwrap();
    write(
        "sensor.json",
        serde_json::json!([
        {"token": "s_lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
        {"token": "s_cam", "channel": "CAM_FRONT", "modality": "camera"}]),
    );
    write(
        "calibrated_sensor.json",
        serde_json::json!([
        {"token": "cs_lidar", "sensor_token": "s_lidar", "translation": lidar_cs.translation, "rotation": lidar_cs.rotation_wxyz, "camera_intrinsic": []},
        {"token": "cs_cam", "sensor_token": "s_cam", "translation": cam_cs.translation, "rotation": cam_cs.rotation_wxyz, "camera_intrinsic": k}]),
    );
    write(
        "ego_pose.json",
        serde_json::json!([
        {"token": "ep_lidar", "timestamp": 1, "translation": ego_l.translation, "rotation": ego_l.rotation_wxyz},
        {"token": "ep_cam", "timestamp": 0, "translation": ego_c.translation, "rotation": ego_c.rotation_wxyz},
        {"token": "ep_unused", "timestamp": 5, "translation": [0, 0, 0], "rotation": [1, 0, 0, 0]}]),
    );
    write(
        "sample.json",
        serde_json::json!([{"token": "smp", "timestamp": 1, "scene_token": "x", "prev": "", "next": ""}]),
    );
    write(
        "sample_data.json",
        serde_json::json!([
        {"token": "sd_l", "sample_token": "smp", "ego_pose_token": "ep_lidar", "calibrated_sensor_token": "cs_lidar", "timestamp": 1532402927647951i64, "fileformat": "pcd", "is_key_frame": true, "height": 0, "width": 0, "filename": lidar_file, "prev": "", "next": ""},
        {"token": "sd_c", "sample_token": "smp", "ego_pose_token": "ep_cam", "calibrated_sensor_token": "cs_cam", "timestamp": 1532402927612460i64, "fileformat": "jpg", "is_key_frame": true, "height": 900, "width": 1600, "filename": cam_file, "prev": "", "next": ""},
        {"token": "sd_sweep", "sample_token": "smp", "ego_pose_token": "ep_unused", "calibrated_sensor_token": "cs_lidar", "timestamp": 2, "fileformat": "pcd", "is_key_frame": false, "height": 0, "width": 0, "filename": "sweeps/x.pcd.bin", "prev": "", "next": ""}]),
    );
    let tables = NuScenesTables::read(&t).unwrap();
    let s = tables.sample("smp", &["CAM_FRONT"]).unwrap();
    let d = (s.cameras["CAM_FRONT"].cam_from_lidar - expected)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |a, b| a.max(b.abs()));
    assert!(d < 1e-4, "{d}");
    // the sample files must lie inside the data root, links included: a `samples` linked in from
    // elsewhere is refused unread, a copy is read
    symlink_dir(&root.join("nuscenes/samples"), &dir.path().join("samples"));
    let e = NuScenesDataset::open(dir.path(), "CAM_FRONT")
        .unwrap()
        .load(0)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("sample_data.json") && e.contains("leads through the link `samples`"),
        "{e}"
    );
    std::fs::remove_file(dir.path().join("samples")).unwrap();
    copy_dir(&root.join("nuscenes/samples"), &dir.path().join("samples"));
    // frames through the tables land the same points in CAM_FRONT as the per-sample JSON
    let via_tables = NuScenesDataset::open(dir.path(), "CAM_FRONT")
        .unwrap()
        .with_images(false);
    let via_json = NuScenesDataset::open(&root.join("nuscenes"), "CAM_FRONT")
        .unwrap()
        .with_images(false);
    let count = |ds: &NuScenesDataset| {
        let f = ds.load(0).unwrap();
        let cam = f.camera.unwrap();
        f.points
            .xyz
            .iter()
            .filter(|p| {
                cam.try_project_in_image(**p)
                    .is_some_and(|ip| ip.depth_m > 1.0)
            })
            .count()
    };
    let (a, b) = (count(&via_tables), count(&via_json));
    assert!(a.abs_diff(b) <= 3, "{a} vs {b}");
}

#[cfg(unix)]
fn symlink_dir(src: &Path, dst: &Path) {
    std::os::unix::fs::symlink(src, dst).unwrap();
}

fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), to).unwrap();
        }
    }
}

#[test]
fn exr_and_ply_round_trips_on_real_scans() {
    let Some(root) = real() else { return };
    let ds =
        SemanticKittiDataset::open(&root.join("semantickitti"), Sequences::List(vec![0])).unwrap();
    let f = ds.load(0).unwrap();
    let sensor = LidarSensor::hdl64e();
    let proj = Projector::new(&sensor, ProjectionOptions::default()).unwrap();
    let (mut img, stats) = proj
        .project(&f.points.xyz, Some(&f.points.intensity), None)
        .unwrap();
    img.gather_labels(f.points.label.as_ref().unwrap()).unwrap();
    assert!(stats.written > 40_000, "{stats:?}");
    let dir = tempfile::tempdir().unwrap();
    let exr = dir.path().join("scan.exr");
    veila_data::range_exr::write_range_exr(&exr, &sensor, &img).unwrap();
    let back = veila_data::range_exr::read_range_exr(&exr).unwrap();
    assert_eq!(back.sensor, sensor);
    assert_eq!(back.image.mask, img.mask);
    assert_eq!(back.image.label, img.label);
    assert_eq!(back.image.point_index, img.point_index);
    assert!(
        back.image
            .range_m
            .iter()
            .zip(&img.range_m)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );
    assert!(
        back.image
            .intensity
            .iter()
            .zip(&img.intensity)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );
    // unprojection through read_points: one point per valid pixel, each within the pixel's angular
    // footprint of the source point it came from
    let pts = read_points(&exr).unwrap();
    assert_eq!(pts.format, PointFormat::RangeExr);
    assert_eq!(pts.cloud.len(), img.num_valid());
    let mut k = 0;
    for (pix, &pi) in img.point_index.iter().enumerate() {
        if pi == NO_POINT {
            continue;
        }
        let src: Vec3 = f.points.xyz[pi as usize];
        let got = pts.cloud.xyz[k];
        assert!((got.length() - src.length()).abs() < 1e-3);
        assert!(
            got.normalize().angle_between(src.normalize()) < 0.45f32.to_radians(),
            "pixel {pix}"
        );
        assert_eq!(
            pts.cloud.label.as_ref().unwrap()[k],
            f.points.label.as_ref().unwrap()[pi as usize]
        );
        k += 1;
    }

    let ply = dir.path().join("scan.ply");
    veila_data::scan::write_points(&ply, &f.points).unwrap();
    let back = read_points(&ply).unwrap();
    assert_eq!(back.format, PointFormat::Ply);
    assert_eq!(back.cloud, f.points);
    let bin = dir.path().join("scan.bin");
    veila_data::scan::write_points(&bin, &f.points).unwrap();
    assert_eq!(
        std::fs::read(&bin).unwrap(),
        std::fs::read(&f.scan_path).unwrap()
    );
}

#[test]
fn label_map_parses_real_yaml_like_pyyaml() {
    let Some(root) = real() else { return };
    let map = LabelMap::read(&root.join("semantickitti/semantic-kitti.yaml")).unwrap();
    assert_eq!(map.learning_map.len(), 34);
    assert_eq!(map.color_bgr.len(), 34);
    assert_eq!(map.learning_map[&252], 1);
    assert_eq!(map.learning_map[&60], 9);
    assert_eq!(map.train_name(19), Some("traffic-sign"));
    assert!(map.learning_ignore[&0] && !map.learning_ignore[&1]);
}
