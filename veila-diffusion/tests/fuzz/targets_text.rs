//! Text artifacts: KITTI and nuScenes calibrations, the training and scene TOML, sensor files,
//! SemanticKITTI label maps (YAML).

use std::path::Path;

use rand::Rng;
use rand::seq::IndexedRandom;
use veila_data::dataset::Dataset;
use veila_data::nuscenes::{NuScenesDataset, NuScenesSample};
use veila_data::read_capped::{MAX_CONFIG_BYTES, read_metadata_string};
use veila_diffusion::app::train_config::TrainFile;

use crate::engine::{FuzzRng, Verdict, fuzz, put, tempdir};
use crate::{mutate, seeds};

/// The first violation or error of several verdicts, else `Ok`.
fn all(verdicts: Vec<Verdict>) -> Verdict {
    let mut first_err = None;
    for v in verdicts {
        match v {
            Verdict::Violation(_) => return v,
            Verdict::Err(e) if first_err.is_none() => first_err = Some(e),
            _ => {}
        }
    }
    first_err.map_or(Verdict::Ok, Verdict::Err)
}

#[test]
fn kitti_calibration() {
    let tmp = tempdir();
    let path = tmp.path().join("calib.txt");
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        let (w, h) = (100, 40);
        // each reader on every input (an object file given to the odometry reader, too), and
        // the one that detects the kind, whose result is the verdict
        let object = veila_data::kitti::KittiCalib::read(&path).and_then(|c| c.camera(2, w, h));
        let odometry =
            veila_data::semantic_kitti::OdometryCalib::read(&path).and_then(|c| c.camera(2, w, h));
        let any = veila_data::spec::read_calib_camera(&path, None, w, h);
        let quiet = |r: veila_data::Result<_>| match Verdict::of(r, &[&name]) {
            v @ Verdict::Violation(_) => v,
            _ => Verdict::Ok,
        };
        all(vec![
            quiet(object),
            quiet(odometry),
            Verdict::of(any, &[&name]),
        ])
    };
    fuzz(
        "KITTI calibration (object, odometry)",
        &[
            seeds::KITTI_CALIB.as_bytes().to_vec(),
            seeds::ODOMETRY_CALIB.as_bytes().to_vec(),
        ],
        &[&mutate::text_tokens, &mutate::text_tokens],
        &run,
    );
}

#[test]
fn nuscenes_calibration() {
    let tmp = tempdir();
    let root = tmp.path().join("nuscenes");
    let json = root.join("calib/t0.json");
    std::fs::create_dir_all(root.join("calib")).expect("a folder");
    let c = seeds::cloud();
    seeds::write(
        &root.join("samples/LIDAR_TOP/x.pcd.bin"),
        &seeds::pcd_bin(&c),
    );
    seeds::write(
        &root.join("samples/CAM_FRONT/x.jpg"),
        &seeds::jpeg(&seeds::image(64, 36)),
    );
    // decoys outside the data root (another point count, another image size), and links to them
    let decoy_points = 7;
    let few = veila_data::PointCloud {
        xyz: c.xyz[..decoy_points].to_vec(),
        intensity: c.intensity[..decoy_points].to_vec(),
        ring: None,
        label: None,
    };
    let outside = tmp.path().join("outside");
    seeds::write(&outside.join("x.pcd.bin"), &seeds::pcd_bin(&few));
    seeds::write(&outside.join("x.jpg"), &seeds::jpeg(&seeds::image(10, 10)));
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(outside.join("x.pcd.bin"), root.join("samples/out.pcd.bin"))
            .expect("a link");
        std::os::unix::fs::symlink(outside.join("x.jpg"), root.join("samples/out.jpg"))
            .expect("a link");
    }
    let abs_points = outside.join("x.pcd.bin").display().to_string();
    let abs_image = outside.join("x.jpg").display().to_string();
    let paths = move |b: &[u8], rng: &mut FuzzRng| -> Option<Vec<u8>> {
        let mut v: serde_json::Value = serde_json::from_slice(b).ok()?;
        let (field, choices): (&str, [&str; 5]) = if rng.random_bool(0.5) {
            (
                "/lidar/file",
                [
                    "../outside/x.pcd.bin",
                    abs_points.as_str(),
                    "samples/out.pcd.bin",
                    "samples/../../outside/x.pcd.bin",
                    "",
                ],
            )
        } else {
            (
                "/cameras/CAM_FRONT/file",
                [
                    "../outside/x.jpg",
                    abs_image.as_str(),
                    "samples/out.jpg",
                    "samples/../../outside/x.jpg",
                    "samples",
                ],
            )
        };
        *v.pointer_mut(field)? = (*choices.choose(rng).expect("a path")).into();
        serde_json::to_vec_pretty(&v).ok()
    };
    let name = root.display().to_string();
    let run = |bytes: &[u8]| {
        put(&json, bytes);
        let (w, h) = (64, 36);
        let sample = NuScenesSample::read_json(&json).and_then(|s| s.camera("CAM_FRONT", w, h));
        let any = veila_data::spec::read_calib_camera(&json, None, w, h);
        let frame = NuScenesDataset::open(&root, "CAM_FRONT").and_then(|d| d.load(0));
        let outside_read = match &frame {
            Ok(f) if f.points.len() == decoy_points => {
                Verdict::Violation("read the points outside the data root".into())
            }
            Ok(f) if f.image.as_ref().is_some_and(|i| i.width() == 10) => {
                Verdict::Violation("read the image outside the data root".into())
            }
            _ => Verdict::Ok,
        };
        all(vec![
            outside_read,
            Verdict::of(sample, &[&name]),
            Verdict::of(any, &[&name]),
            Verdict::of(frame, &[&name]),
        ])
    };
    fuzz(
        "nuScenes calibration (sample JSON)",
        &[seeds::NUSCENES_JSON.as_bytes().to_vec()],
        &[&mutate::json, &mutate::json, &paths, &mutate::text_tokens],
        &run,
    );
}

/// What `veila train` does with its config before training: read it (capped), parse it, resolve
/// and check it, build the bundle config and the recipe settings.
fn read_train_config(path: &Path) -> Result<(), String> {
    let text = read_metadata_string(path, MAX_CONFIG_BYTES, "a training config")
        .map_err(|e| e.to_string())?;
    let mut file: TrainFile = toml::from_str(&text)
        .map_err(|e| format!("{}: not a valid training config: {e}", path.display()))?;
    file.resolve_and_check(path).map_err(|e| e.to_string())?;
    let cfg = file.bundle_config(path).map_err(|e| e.to_string())?;
    let _ = file.train.recipe_settings();
    let _ = cfg.weight_files();
    Ok(())
}

#[test]
fn train_toml() {
    let tmp = tempdir();
    let path = tmp.path().join("train.toml");
    let bundle = tmp.path().join("bundle");
    seeds::save_bundle(&bundle);
    seeds::write(
        &tmp.path().join("b/bundle.json"),
        &std::fs::read(bundle.join("bundle.json")).expect("bundle.json"),
    );
    let name = tmp.path().display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        match read_train_config(&path) {
            Ok(()) => Verdict::Ok,
            Err(e) => Verdict::named(e, &[&name]),
        }
    };
    fuzz(
        "training config (TOML)",
        &[
            seeds::TRAIN_TOML.as_bytes().to_vec(),
            seeds::TRAIN_TOML_BUNDLE.as_bytes().to_vec(),
        ],
        &[&mutate::toml_doc, &mutate::toml_doc, &mutate::text_tokens],
        &run,
    );
}

#[test]
fn scene_toml() {
    let tmp = tempdir();
    let path = tmp.path().join("scene.toml");
    let mut seeds = vec![seeds::SCENE_TOML.as_bytes().to_vec()];
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    let mut names: Vec<_> = std::fs::read_dir(&scenes)
        .map(|rd| {
            rd.flatten()
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|x| x == "toml"))
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    for p in names.iter().take(3) {
        seeds.push(std::fs::read(p).expect("a scene file"));
    }
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        Verdict::of(veila_data::sim::SceneConfig::from_file(&path), &[&name])
    };
    fuzz(
        "scene file (TOML)",
        &seeds,
        &[&mutate::toml_doc, &mutate::toml_doc, &mutate::text_tokens],
        &run,
    );
}

#[test]
fn sensor_file() {
    let tmp = tempdir();
    let toml_path = tmp.path().join("sensor.toml");
    let json_path = tmp.path().join("sensor.json");
    let toml_seed =
        toml::to_string_pretty(&veila_geom::LidarSensor::hdl32e_per_beam()).expect("a sensor file");
    let json_seed =
        serde_json::to_vec_pretty(&veila_geom::LidarSensor::hdl64e()).expect("a sensor file");
    let name = tmp.path().display().to_string();
    let run = |bytes: &[u8]| {
        // the format follows the content: JSON starts with `{`
        let path = if bytes.first() == Some(&b'{') {
            &json_path
        } else {
            &toml_path
        };
        put(path, bytes);
        let spec = path.to_str().expect("a UTF-8 path");
        // a sensor that passes is one the tools then build ray tables for
        let r = veila_data::spec::sensor_from_spec(spec)
            .and_then(|s| Ok(veila_geom::RayTable::new(&s)?));
        Verdict::of(r, &[&name])
    };
    fuzz(
        "sensor file (TOML, JSON)",
        &[toml_seed.into_bytes(), json_seed],
        &[&mutate::toml_doc, &mutate::json, &mutate::text_tokens],
        &run,
    );
}

#[test]
fn label_map() {
    let tmp = tempdir();
    let path = tmp.path().join("semantic-kitti.yaml");
    let name = path.display().to_string();
    let raw: Vec<u32> = (0..64).map(|i| (i * 5) | (i << 16)).collect();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        let r = veila_data::semantic_kitti::LabelMap::read(&path).map(|m| {
            let ids = m.train_ids(&raw);
            let hist = m.train_histogram(&raw);
            (m.num_classes(), ids.len(), hist.len())
        });
        Verdict::of(r, &[&name])
    };
    fuzz(
        "label map (YAML)",
        &[seeds::LABEL_YAML.as_bytes().to_vec()],
        &[&mutate::yaml, &mutate::text_tokens, &mutate::text_tokens],
        &run,
    );
}

#[test]
fn generated_dataset_manifest() {
    use veila_diffusion::app::dataset_gen::{
        BundleId, DATASET_FORMAT, DATASET_MANIFEST, DatasetManifest, SEED_RULE,
    };
    let tmp = tempdir();
    let path = tmp.path().join(DATASET_MANIFEST);
    let seed = DatasetManifest {
        format: DATASET_FORMAT.into(),
        bundle: BundleId {
            name: "default".into(),
            manifest_sha256: "ab".repeat(32),
        },
        sampler: veila_diffusion::SamplerName::Ddpm.config(16),
        residual_weight: 1.0,
        seed: 7,
        seed_rule: SEED_RULE.into(),
        source: "kitti-layout".into(),
        labeller: Some("segmenter".into()),
        frames: vec!["000000".into(), "08_000123".into()],
    }
    .to_bytes()
    .expect("a manifest");
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        Verdict::of(DatasetManifest::read(&path), &[&name])
    };
    fuzz(
        "generated dataset manifest (dataset.json)",
        &[seed],
        &[&mutate::json, &mutate::text_tokens],
        &run,
    );
}
