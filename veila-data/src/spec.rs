//! Sensors and cameras named on a command line: a preset name or a sensor file, and a calibration file
//! of any supported dataset (detected from its content).

use std::path::Path;

use veila_geom::{LidarSensor, PinholeCamera, SensorPreset};

use crate::kitti::KittiCalib;
use crate::nuscenes::NuScenesSample;
use crate::semantic_kitti::OdometryCalib;
use crate::{Error, Result};

/// A sensor from a preset name (one of [`SensorPreset::ALL`]) or a file: `*.toml` or `*.json`
/// holding a [`LidarSensor`] (as `veila sensors` prints it). The sensor is validated.
pub fn sensor_from_spec(spec: &str) -> Result<LidarSensor> {
    let sensor = match spec.parse::<SensorPreset>() {
        Ok(preset) => preset.sensor(),
        Err(_) => {
            let file = spec;
            let path = Path::new(file);
            let lower = file.to_lowercase();
            if !(lower.ends_with(".toml") || lower.ends_with(".json")) {
                return Err(Error::Invalid {
                    what: "sensor".into(),
                    message: format!(
                        "`{file}` is neither a preset ({}) nor a .toml / .json sensor file",
                        SensorPreset::names()
                    ),
                });
            }
            let text = crate::read_capped::read_metadata_string(
                path,
                crate::read_capped::MAX_CONFIG_BYTES,
                "a sensor file",
            )?;
            if lower.ends_with(".toml") {
                toml::from_str(&text)
                    .map_err(|e| Error::format(path, format!("not a sensor description: {e}")))?
            } else {
                serde_json::from_str(&text)
                    .map_err(|e| Error::format(path, format!("not a sensor description: {e}")))?
            }
        }
    };
    sensor.validate().map_err(|e| Error::Invalid {
        what: format!("sensor `{spec}`"),
        message: e.to_string(),
    })?;
    Ok(sensor)
}

/// A preset as a sensor file of its own (TOML, `*.toml` for [`sensor_from_spec`]), with a comment
/// naming it and the other presets.
pub fn sensor_preset_toml(preset: SensorPreset) -> Result<String> {
    let body = toml::to_string_pretty(&preset.sensor()).map_err(|e| Error::Invalid {
        what: format!("sensor preset `{preset}`"),
        message: e.to_string(),
    })?;
    let others: Vec<&str> = SensorPreset::ALL
        .into_iter()
        .filter(|p| *p != preset)
        .map(SensorPreset::as_str)
        .collect();
    Ok(format!(
        "# veila sensor preset `{preset}` (the others: {}; `veila sensors NAME` prints one)\n{body}",
        others.join(", ")
    ))
}

/// The kinds of calibration file [`read_calib_camera`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CalibKind {
    /// KITTI object benchmark `calib/NNNNNN.txt` (P0..P3, R0_rect, Tr_velo_to_cam).
    KittiObject,
    /// KITTI odometry / SemanticKITTI `calib.txt` (P0..P3, Tr).
    KittiOdometry,
    /// nuScenes per-sample JSON.
    NuScenesJson,
}

impl CalibKind {
    /// How reports name it: `kitti-object`, `kitti-odometry`, `nuscenes-json`.
    pub fn name(self) -> &'static str {
        match self {
            CalibKind::KittiObject => "kitti-object",
            CalibKind::KittiOdometry => "kitti-odometry",
            CalibKind::NuScenesJson => "nuscenes-json",
        }
    }

    /// The camera a file of this kind gives when none is named: KITTI `2` (`image_2`), nuScenes
    /// `CAM_FRONT`.
    pub fn default_camera(self) -> &'static str {
        match self {
            CalibKind::KittiObject | CalibKind::KittiOdometry => "2",
            CalibKind::NuScenesJson => "CAM_FRONT",
        }
    }
}

/// Detect the calibration kind from the content: JSON (first non-space character `{`) is nuScenes; a
/// text file with an `R0_rect`/`R_rect` key is KITTI object; one with a `Tr` key is KITTI odometry.
pub fn detect_calib_kind(path: &Path) -> Result<CalibKind> {
    let text = crate::read_capped::read_metadata_string(
        path,
        crate::read_capped::MAX_CALIBRATION_BYTES,
        "a calibration file",
    )?;
    calib_kind_of(&text, path)
}

fn calib_kind_of(text: &str, path: &Path) -> Result<CalibKind> {
    if text.trim_start().starts_with('{') {
        return Ok(CalibKind::NuScenesJson);
    }
    let has = |k: &str| {
        text.lines().any(|l| {
            let l = l.trim_start();
            l.strip_prefix(k)
                .is_some_and(|r| r.starts_with(':') || r.starts_with(' '))
        })
    };
    if has("R0_rect") || has("R_rect") {
        Ok(CalibKind::KittiObject)
    } else if has("Tr") {
        Ok(CalibKind::KittiOdometry)
    } else {
        Err(Error::format(
            path,
            "unknown calibration format: not nuScenes JSON, and no R0_rect (KITTI object) or Tr (KITTI odometry) line",
        ))
    }
}

/// A camera of a calibration file, as [`read_calib_camera`] reads it.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibCamera {
    /// The camera, for the image size it was read for.
    pub camera: PinholeCamera,
    /// The file's kind (from its content).
    pub kind: CalibKind,
    /// Which camera: a KITTI projection index (`0` to `3`) or a nuScenes channel, as named.
    pub name: String,
}

/// The one calibration reader, behind every door that takes a calibration file (`veila generate`,
/// `edit`, `render`, `weather`, `eval`'s CM-DC, the pipeline's `load_view`, the Python wheel):
/// camera `camera` of the file `path`, for an image of `width x height`. The kind is detected from
/// the content ([`detect_calib_kind`]): KITTI object `calib/NNNNNN.txt`, KITTI odometry /
/// SemanticKITTI `calib.txt`, or a nuScenes per-sample JSON. `camera` is a KITTI projection index
/// `0` to `3` (also written `P2` or `image_2`) or a nuScenes channel; `None` is the kind's
/// [`CalibKind::default_camera`]. Every error names the file.
pub fn read_calib_camera(
    path: &Path,
    camera: Option<&str>,
    width: u32,
    height: u32,
) -> Result<CalibCamera> {
    let text = crate::read_capped::read_metadata_string(
        path,
        crate::read_capped::MAX_CALIBRATION_BYTES,
        "a calibration file",
    )?;
    let kind = calib_kind_of(&text, path)?;
    let name = camera.unwrap_or(kind.default_camera()).to_string();
    let cam = match kind {
        CalibKind::KittiObject => {
            KittiCalib::parse(&text, path)?.camera(kitti_index(&name, path)?, width, height)
        }
        CalibKind::KittiOdometry => {
            OdometryCalib::parse(&text, path)?.camera(kitti_index(&name, path)?, width, height)
        }
        CalibKind::NuScenesJson => NuScenesSample::read_json(path)?.camera(&name, width, height),
    };
    let camera = cam.map_err(|e| match e {
        Error::Geom(g) => Error::format(path, format!("calibration gives an invalid camera: {g}")),
        // name the file in every error (the sample's own errors know only its token)
        Error::Invalid { message, .. } => Error::format(path, message),
        other => other,
    })?;
    Ok(CalibCamera { camera, kind, name })
}

/// The projection index a KITTI camera name gives: `2`, `P2` or `image_2`.
fn kitti_index(name: &str, path: &Path) -> Result<usize> {
    let digits = name
        .strip_prefix("image_")
        .or_else(|| name.strip_prefix('P'))
        .unwrap_or(name);
    match digits.parse::<usize>() {
        Ok(i) if i <= 3 => Ok(i),
        _ => Err(Error::format(
            path,
            format!(
                "camera {name}: a KITTI calibration has cameras 0 to 3 (P0..P3; 2 = image_2, \
                 3 = image_3)"
            ),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preset_prints_as_a_sensor_file_that_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        for preset in SensorPreset::ALL {
            let text = sensor_preset_toml(preset).unwrap();
            let p = dir.path().join(format!("{preset}.toml"));
            std::fs::write(&p, &text).unwrap();
            let back = sensor_from_spec(p.to_str().unwrap()).unwrap();
            assert_eq!(back, preset.sensor(), "{preset}");
            // and by name
            assert_eq!(sensor_from_spec(preset.as_str()).unwrap(), back, "{preset}");
        }
        // the per-beam table survives (it is what sets this preset apart)
        assert_ne!(
            SensorPreset::Hdl32ePerBeam.sensor(),
            SensorPreset::Hdl32e.sensor()
        );
        let e = sensor_from_spec("vlp16").unwrap_err().to_string();
        assert!(e.contains("vlp16") && e.contains("hdl32e-per-beam"), "{e}");
    }

    #[test]
    fn presets_files_and_errors() {
        assert_eq!(sensor_from_spec("hdl64e").unwrap(), LidarSensor::hdl64e());
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.toml");
        let s = LidarSensor {
            rows: 16,
            ..LidarSensor::hdl32e()
        };
        std::fs::write(&p, toml::to_string(&s).unwrap()).unwrap();
        assert_eq!(sensor_from_spec(p.to_str().unwrap()).unwrap(), s);
        std::fs::write(&p, "rows = 0\ncols = 4\nfov_up_deg = 1.0\nfov_down_deg = -1.0\nmin_range_m = 1.0\nmax_range_m = 2.0\n").unwrap();
        assert!(sensor_from_spec(p.to_str().unwrap()).is_err());
        std::fs::write(&p, "rows = \"x\"").unwrap();
        let e = sensor_from_spec(p.to_str().unwrap())
            .unwrap_err()
            .to_string();
        assert!(e.contains("s.toml"), "{e}");
        assert!(sensor_from_spec("vlp16").is_err());
    }

    #[test]
    fn the_one_reader_takes_a_camera_by_kitti_index_or_its_default() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("000000.txt");
        let row = |tx: f64| format!("721.5 0 609.6 {tx} 0 721.5 172.9 0 0 0 1 0");
        let text = format!(
            "P0: {}\nP1: {}\nP2: {}\nP3: {}\nR0_rect: 1 0 0 0 1 0 0 0 1\n\
             Tr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n",
            row(0.0),
            row(-386.1),
            row(44.9),
            row(-339.5)
        );
        std::fs::write(&p, text).unwrap();
        let read = |c: Option<&str>| read_calib_camera(&p, c, 1242, 375);
        let default = read(None).unwrap();
        assert_eq!(default.kind, CalibKind::KittiObject);
        assert_eq!(default.name, "2");
        for name in ["2", "P2", "image_2"] {
            assert_eq!(read(Some(name)).unwrap().camera, default.camera, "{name}");
        }
        assert_ne!(read(Some("3")).unwrap().camera, default.camera);
        for bad in ["7", "CAM_FRONT"] {
            let e = read(Some(bad)).unwrap_err().to_string();
            assert!(e.contains("000000.txt") && e.contains(bad), "{e}");
        }
    }

    #[test]
    fn calib_kinds() {
        let p = Path::new("c");
        assert_eq!(
            calib_kind_of(" {\"a\": 1}", p).unwrap(),
            CalibKind::NuScenesJson
        );
        assert_eq!(
            calib_kind_of("P2: 1\nR0_rect: 1\n", p).unwrap(),
            CalibKind::KittiObject
        );
        assert_eq!(
            calib_kind_of("P2: 1\nTr: 1\n", p).unwrap(),
            CalibKind::KittiOdometry
        );
        assert!(calib_kind_of("P2: 1\nTrx: 1\n", p).is_err());
    }
}
