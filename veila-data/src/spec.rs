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

/// The kinds of calibration file [`camera_from_calib_file`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CalibKind {
    /// KITTI object benchmark `calib/NNNNNN.txt` (P0..P3, R0_rect, Tr_velo_to_cam).
    KittiObject,
    /// KITTI odometry / SemanticKITTI `calib.txt` (P0..P3, Tr).
    KittiOdometry,
    /// nuScenes per-sample JSON.
    NuScenesJson,
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

/// The camera described by a calibration file, for an image of `width x height`. KITTI files give
/// camera 2 (`image_2`); nuScenes JSON gives `nuscenes_channel` (e.g. `CAM_FRONT`).
pub fn camera_from_calib_file(
    path: &Path,
    width: u32,
    height: u32,
    nuscenes_channel: &str,
) -> Result<PinholeCamera> {
    let text = crate::read_capped::read_metadata_string(
        path,
        crate::read_capped::MAX_CALIBRATION_BYTES,
        "a calibration file",
    )?;
    let cam = match calib_kind_of(&text, path)? {
        CalibKind::KittiObject => KittiCalib::parse(&text, path)?.camera(2, width, height),
        CalibKind::KittiOdometry => OdometryCalib::parse(&text, path)?.camera(2, width, height),
        CalibKind::NuScenesJson => {
            NuScenesSample::read_json(path)?.camera(nuscenes_channel, width, height)
        }
    };
    cam.map_err(|e| match e {
        Error::Geom(g) => Error::format(path, format!("calibration gives an invalid camera: {g}")),
        // name the file in every error (the sample's own errors know only its token)
        Error::Invalid { message, .. } => Error::format(path, message),
        other => other,
    })
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
