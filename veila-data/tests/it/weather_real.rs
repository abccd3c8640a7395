//! Weather on the real sensor samples in /work/shared/data/real (skipped when absent).

use std::path::{Path, PathBuf};

use veila_data::spec::read_calib_camera;
use veila_data::weather::files::{FrameFiles, FrameOutputs, depth_from_scan, process_frame};
use veila_data::weather::{
    BeamTable, LidarInput, PointOrigin, Preset, Weather, WeatherConfig, WeatherSim,
};

fn real() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    if p.join("kitti/training/velodyne/000000.bin").is_file() {
        Some(p)
    } else {
        eprintln!("skipping: {} not found", p.display());
        None
    }
}

#[test]
fn kitti_weather_variants_on_a_real_scan() {
    let Some(root) = real() else { return };
    let k = root.join("kitti/training");
    let cloud = veila_data::scan::read_points(&k.join("velodyne/000000.bin"))
        .unwrap()
        .cloud;
    assert_eq!(cloud.len(), 115_384);
    let beams = BeamTable::hdl64e();
    let input = LidarInput {
        cloud: &cloud,
        ground_mask: None,
        beams: Some(&beams),
    };
    let cfg = WeatherConfig::default();

    let fog = WeatherSim::new(&Preset::KittiFog.weather(), &cfg)
        .unwrap()
        .apply_lidar(input)
        .unwrap();
    assert_eq!(fog.cloud.len(), cloud.len(), "fog never deletes points");
    let n_fog = fog
        .origin
        .iter()
        .filter(|o| **o == PointOrigin::Fog)
        .count();
    assert!(
        n_fog > 100 && n_fog < cloud.len() / 2,
        "{n_fog} fog returns"
    );
    for (p, o) in fog.cloud.xyz.iter().zip(&fog.origin) {
        assert!(p.is_finite());
        if *o == PointOrigin::Fog {
            let r = p.length();
            assert!((1.0..=20.0).contains(&r), "fog return at {r} m");
        }
    }

    let snow = WeatherSim::new(&Preset::KittiSnow.weather(), &cfg)
        .unwrap()
        .apply_lidar(input)
        .unwrap();
    let n_snow = snow
        .origin
        .iter()
        .filter(|o| **o == PointOrigin::Snow)
        .count();
    assert!(n_snow > 100, "{n_snow} flake returns");
    assert!(
        snow.cloud
            .intensity
            .iter()
            .all(|i| i.is_finite() && (0.0..=1.0).contains(i))
    );

    let night = WeatherSim::new(&Preset::KittiNight.weather(), &cfg)
        .unwrap()
        .apply_lidar(input)
        .unwrap();
    assert_eq!(night.cloud, cloud);

    // the camera depth map from the scan covers the road and leaves no NaN
    let img = veila_data::image_io::read_rgb_image(&k.join("image_2/000000.png")).unwrap();
    let cam = read_calib_camera(&k.join("calib/000000.txt"), None, img.width(), img.height())
        .unwrap()
        .camera;
    let depth = depth_from_scan(&cloud, &cam);
    depth.validate(img.width(), img.height()).unwrap();
    let w = img.width() as usize;
    let lower = &depth.z_m[depth.z_m.len() / 2..];
    let finite = lower.iter().filter(|z| z.is_finite()).count() as f64 / lower.len() as f64;
    assert!(finite > 0.95, "{finite}");
    // bottom centre of the image is road a few metres ahead
    let z = depth.z_m[(img.height() as usize - 1) * w + w / 2];
    assert!((3.0..15.0).contains(&z), "{z}");
}

#[test]
fn nuscenes_scan_keeps_its_format_and_rings() {
    let Some(root) = real() else { return };
    let dir = root.join("nuscenes/samples/LIDAR_TOP");
    let Some(scan) = std::fs::read_dir(&dir)
        .ok()
        .and_then(|mut d| d.find_map(|e| e.ok().map(|e| e.path())))
    else {
        eprintln!("skipping: no nuScenes scan");
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = FrameOutputs {
        scan: tmp.path().join("out.pcd.bin"),
        image: None,
    };
    let files = FrameFiles {
        scan: scan.clone(),
        ..Default::default()
    };
    let w = Weather {
        rain_rate_mm_h: 20.0,
        snowfall_rate_mm_h: 0.5,
        seed: 3,
        ..Weather::clear()
    };
    let sim = WeatherSim::new(&w, &WeatherConfig::default()).unwrap();
    let report = process_frame(&sim, &files, &out).unwrap();
    assert_eq!(
        report
            .lidar
            .iter()
            .map(|r| r.effect.as_str())
            .collect::<Vec<_>>(),
        ["extinction", "rain", "snow"]
    );
    let snow = report.lidar.iter().find(|r| r.effect == "snow").unwrap();
    assert!(
        snow.notes.is_empty(),
        "rings come from the file: {:?}",
        snow.notes
    );
    assert_eq!(snow.counts["rings"], 32);
    let bytes = std::fs::read(&out.scan).unwrap();
    assert_eq!(bytes.len() % 20, 0);
    let back = veila_data::scan::read_points(&out.scan).unwrap().cloud;
    let orig = veila_data::scan::read_points(&scan).unwrap().cloud;
    assert!(back.len() <= orig.len() && back.len() > orig.len() * 9 / 10);
    assert!(back.intensity.iter().all(|i| (0.0..=255.0).contains(i)));
    assert!(
        back.intensity.iter().any(|i| *i > 1.0),
        "intensity stays on the 0..255 scale"
    );
}

#[test]
fn semantickitti_labels_give_the_wet_road() {
    let Some(root) = real() else { return };
    let seq = root.join("semantickitti/sequences/00");
    let tmp = tempfile::tempdir().unwrap();
    let files = FrameFiles {
        scan: seq.join("velodyne/000000.bin"),
        labels: Some(seq.join("labels/000000.label")),
        ..Default::default()
    };
    let out = FrameOutputs {
        scan: tmp.path().join("000000.bin"),
        image: None,
    };
    let sim = WeatherSim::new(
        &Weather {
            water_depth_mm: 1.2,
            ..Weather::clear()
        },
        &WeatherConfig::default(),
    )
    .unwrap();
    let report = process_frame(&sim, &files, &out).unwrap();
    let wet = &report.lidar[0];
    assert_eq!(wet.effect, "wet_ground");
    assert!(
        wet.notes.iter().any(|n| n.contains("labels")),
        "{:?}",
        wet.notes
    );
    assert!(wet.counts["ground_points"] > 20_000, "{:?}", wet.counts);
    assert!(wet.counts["intensity_reduced"] + wet.counts["dropped"] > 10_000);
}

/// Snowflake returns on KITTI 000000 against the public reference implementation (Hahner et al. 2022,
/// SysCV/LiDAR_snow_sim), whose counts `data/snow_reference/compare_snow_reference.py` measured by
/// running the reference's own `process_single_channel` with its own flake layers and seeds. Compared
/// where the two models are meant to agree: the reference without the HDL-64 S3 per-channel intensity
/// correction (calibrated for another sensor), against veila (a) as shipped, with the reference's
/// never-reset power constant repaired in the reference, and (b) with that quirk reproduced in veila.
#[test]
fn snow_flake_returns_match_the_reference_implementation() {
    let Some(root) = real() else { return };
    let reference: serde_json::Value =
        serde_json::from_str(include_str!("../data/snow_reference/snow_reference.json")).unwrap();
    assert_eq!(
        reference["scan"],
        "../shared/data/real/kitti/training/velodyne/000000.bin"
    );
    let cloud = veila_data::scan::read_points(&root.join("kitti/training/velodyne/000000.bin"))
        .unwrap()
        .cloud;
    let beams = BeamTable::hdl64e();
    let input = LidarInput {
        cloud: &cloud,
        ground_mask: None,
        beams: Some(&beams),
    };
    for (rate, key) in [(1.0, "1.0"), (2.5, "2.5")] {
        for (quirk, variant) in [(false, "no_focal_reset_power"), (true, "no_focal")] {
            let want = reference["summary"][format!("{key}/{variant}")]["mean"]
                .as_f64()
                .unwrap();
            let mut cfg = WeatherConfig::default();
            cfg.lidar.snow.reference_power_quirk = quirk;
            let weather = Weather {
                snowfall_rate_mm_h: rate,
                snow_terminal_velocity_m_s: 1.6,
                seed: 11,
                ..Weather::clear()
            };
            let out = WeatherSim::new(&weather, &cfg)
                .unwrap()
                .apply_lidar(input)
                .unwrap();
            let got = out
                .origin
                .iter()
                .filter(|o| **o == PointOrigin::Snow)
                .count() as f64;
            eprintln!("{rate} mm/h, quirk {quirk}: veila {got}, reference {want:.0}");
            assert!(
                (got - want).abs() <= 0.10 * want,
                "{rate} mm/h, quirk {quirk}: veila {got} flake returns, reference {want}"
            );
        }
    }
}
