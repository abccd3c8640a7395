//! KITTI object benchmark: velodyne scans, `image_2`, per-frame calibration and `label_2` boxes.
//!
//! Layout (`ROOT` may be the benchmark folder holding `training/`, or `training/` itself):
//! `velodyne/NNNNNN.bin`, `image_2/NNNNNN.png`, `calib/NNNNNN.txt`, `label_2/NNNNNN.txt` (optional).
//! Projection into `image_2`: `x_img = P2 * R0_rect * Tr_velo_to_cam * [x y z 1]^T`.

use std::path::{Path, PathBuf};

use glam::{Mat3, Vec3};
use veila_geom::{LidarSensor, PinholeCamera};

use crate::calib::CalibEntries;
use crate::dataset::{Dataset, Frame};
use crate::scan::read_kitti_bin;
use crate::{Error, Result};

/// Calibration of one KITTI object frame (`calib/NNNNNN.txt`).
#[derive(Debug, Clone, PartialEq)]
pub struct KittiCalib {
    /// Projection matrices `P0..P3` (row-major 3x4) of the rectified cameras.
    pub p: [[[f32; 4]; 3]; 4],
    /// Rectifying rotation `R0_rect`.
    pub r0_rect: Mat3,
    /// `Tr_velo_to_cam` (row-major 3x4): velodyne to (unrectified) camera 0.
    pub tr_velo_to_cam: [[f32; 4]; 3],
    /// `Tr_imu_to_velo` (row-major 3x4), when present.
    pub tr_imu_to_velo: Option<[[f32; 4]; 3]>,
    /// The file it was read from, named in the errors of [`KittiCalib::camera`].
    pub source: PathBuf,
}

impl KittiCalib {
    /// Parse calibration text (`path` names the source in errors). Accepts the object benchmark's
    /// `KEY: values` lines and the tracking benchmark's spellings (`R_rect`, `Tr_velo_cam`).
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let e = CalibEntries::parse(text, path)?;
        let mut p = [[[0f32; 4]; 3]; 4];
        for (i, pi) in p.iter_mut().enumerate() {
            *pi = e.require_3x4(&[&format!("P{i}")], path)?;
        }
        let r = e.require(&["R0_rect", "R_rect"], 9, path)?;
        let r0_rect = Mat3::from_cols_array(&[
            r[0] as f32,
            r[3] as f32,
            r[6] as f32, //
            r[1] as f32,
            r[4] as f32,
            r[7] as f32, //
            r[2] as f32,
            r[5] as f32,
            r[8] as f32,
        ]);
        crate::calib::check_rotation(
            path,
            "R0_rect",
            [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]],
        )?;
        let tr_velo_to_cam = e.require_3x4(&["Tr_velo_to_cam", "Tr_velo_cam"], path)?;
        crate::calib::check_rotation(
            path,
            "Tr_velo_to_cam",
            crate::calib::rotation_of(&tr_velo_to_cam),
        )?;
        let tr_imu_to_velo = e.get_3x4(&["Tr_imu_to_velo", "Tr_imu_velo"], path)?;
        Ok(KittiCalib {
            p,
            r0_rect,
            tr_velo_to_cam,
            tr_imu_to_velo,
            source: path.to_path_buf(),
        })
    }

    /// Read `calib/NNNNNN.txt`.
    pub fn read(path: &Path) -> Result<Self> {
        let text = crate::read_capped::read_metadata_string(
            path,
            crate::read_capped::MAX_CALIBRATION_BYTES,
            "a calibration file",
        )?;
        Self::parse(&text, path)
    }

    /// The pinhole camera of rectified camera `index` (2 = `image_2`, the left colour camera):
    /// `K = P{index}`, `cam_from_lidar = R0_rect * Tr_velo_to_cam`.
    pub fn camera(&self, index: usize, width: u32, height: u32) -> Result<PinholeCamera> {
        let p = *self.p.get(index).ok_or_else(|| Error::Invalid {
            what: "KITTI camera index".into(),
            message: format!("{index} is not one of 0..=3"),
        })?;
        PinholeCamera::from_kitti(p, self.r0_rect, self.tr_velo_to_cam, width, height).map_err(
            |e| {
                Error::format(
                    &self.source,
                    format!("P{index} gives an invalid camera: {e}"),
                )
            },
        )
    }
}

/// One object of `label_2/NNNNNN.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct KittiObjectLabel {
    /// Class name (`Car`, `Pedestrian`, `Cyclist`, `DontCare`, ...).
    pub class: String,
    /// Truncation 0..1 (-1 for `DontCare`).
    pub truncated: f32,
    /// Occlusion state 0..3 (-1 for `DontCare`).
    pub occluded: i32,
    /// Observation angle, radians.
    pub alpha_rad: f32,
    /// 2D box in image_2 pixels: left, top, right, bottom.
    pub bbox_px: [f32; 4],
    /// Height, width, length in metres.
    pub dimensions_hwl_m: [f32; 3],
    /// Bottom-centre of the box in the rectified camera frame, metres.
    pub location_cam_m: Vec3,
    /// Rotation around the camera y axis, radians.
    pub rotation_y_rad: f32,
    /// Detection score (result files only).
    pub score: Option<f32>,
}

/// Parse a `label_2` file (`path` names the source in errors).
pub fn parse_kitti_labels(text: &str, path: &Path) -> Result<Vec<KittiObjectLabel>> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line_no = i + 1;
        let w: Vec<&str> = line.split_whitespace().collect();
        if w.is_empty() {
            continue;
        }
        if w.len() != 15 && w.len() != 16 {
            return Err(Error::format(
                path,
                format!(
                    "line {line_no}: expected 15 or 16 fields, found {}",
                    w.len()
                ),
            ));
        }
        let num = |k: usize| -> Result<f32> {
            w[k].parse::<f32>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    Error::format(
                        path,
                        format!(
                            "line {line_no}, field {}: malformed number `{}`",
                            k + 1,
                            w[k]
                        ),
                    )
                })
        };
        let occluded = w[2].parse::<i32>().map_err(|_| {
            Error::format(
                path,
                format!("line {line_no}, field 3: malformed integer `{}`", w[2]),
            )
        })?;
        out.push(KittiObjectLabel {
            class: w[0].to_string(),
            truncated: num(1)?,
            occluded,
            alpha_rad: num(3)?,
            bbox_px: [num(4)?, num(5)?, num(6)?, num(7)?],
            dimensions_hwl_m: [num(8)?, num(9)?, num(10)?],
            location_cam_m: Vec3::new(num(11)?, num(12)?, num(13)?),
            rotation_y_rad: num(14)?,
            score: if w.len() == 16 { Some(num(15)?) } else { None },
        });
    }
    Ok(out)
}

/// Read a `label_2` file.
pub fn read_kitti_labels(path: &Path) -> Result<Vec<KittiObjectLabel>> {
    let text = crate::read_capped::read_metadata_string(
        path,
        crate::read_capped::MAX_CALIBRATION_BYTES,
        "a KITTI label file",
    )?;
    parse_kitti_labels(&text, path)
}

/// The stems of the files `dir/*{ext}` (`ext` with its dot, e.g. `.bin`), sorted; hidden files
/// (a leading `.`) are skipped. Errors name `dir`.
pub fn list_stems(dir: &Path, ext: &str) -> Result<Vec<String>> {
    let rd = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut out = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if let Some(stem) = name.strip_suffix(ext)
            && !stem.is_empty()
            && !stem.starts_with('.')
        {
            out.push(stem.to_string());
        }
    }
    out.sort();
    Ok(out)
}

/// The split folder of `root` that holds `sub/`: `root` itself or `root/training`; else an error
/// naming `root` as not being `what`.
fn split_folder(root: &Path, sub: &str, what: &str) -> Result<PathBuf> {
    if root.join(sub).is_dir() {
        Ok(root.to_path_buf())
    } else if root.join("training").join(sub).is_dir() {
        Ok(root.join("training"))
    } else {
        Err(Error::format(
            root,
            format!("not {what}: neither {sub}/ nor training/{sub}/ exists"),
        ))
    }
}

/// One camera frame of a KITTI-layout folder: `image_2/NAME.png` and its `calib/NAME.txt`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraFrame {
    /// The frame's name (the image's file stem, `000008`).
    pub name: String,
    /// `image_2/NAME.png` (or `.jpg`).
    pub image: PathBuf,
    /// `calib/NAME.txt`, read with the one calibration reader
    /// ([`crate::spec::read_calib_camera`]).
    pub calib: PathBuf,
}

/// The camera frames of a KITTI-layout folder, sorted by name: every `image_2/NAME.png` (or
/// `NAME.jpg`) of `root` (or of `root/training`) with its `calib/NAME.txt`. No scan is needed (the
/// layout of a folder to generate scans for). An image without its calibration, two images of one
/// name, or an `image_2/` without images is an error naming the file or folder; nothing is read
/// but the listings.
pub fn list_camera_frames(root: &Path) -> Result<Vec<CameraFrame>> {
    let base = split_folder(root, "image_2", "a KITTI-layout folder")?;
    let images = base.join("image_2");
    let mut found: Vec<(String, &str)> = Vec::new();
    for ext in [".png", ".jpg"] {
        found.extend(list_stems(&images, ext)?.into_iter().map(|s| (s, ext)));
    }
    found.sort();
    if let Some(w) = found.windows(2).find(|w| w[0].0 == w[1].0) {
        let (name, a, b) = (&w[0].0, w[0].1, w[1].1);
        return Err(Error::format(
            &images,
            format!("two images of frame `{name}` ({name}{a} and {name}{b}): keep one"),
        ));
    }
    if found.is_empty() {
        return Err(Error::format(&images, "no .png or .jpg camera image"));
    }
    found
        .into_iter()
        .map(|(name, ext)| {
            let calib = base.join("calib").join(format!("{name}.txt"));
            let image = images.join(format!("{name}{ext}"));
            if !calib.is_file() {
                return Err(Error::format(
                    &image,
                    format!(
                        "no calibration for this image: {} is missing",
                        calib.display()
                    ),
                ));
            }
            Ok(CameraFrame { name, image, calib })
        })
        .collect()
}

/// The KITTI object benchmark (one split), read lazily.
#[derive(Debug, Clone)]
pub struct KittiObjectDataset {
    base: PathBuf,
    ids: Vec<String>,
    load_images: bool,
}

impl KittiObjectDataset {
    /// Open `root` (the folder holding `training/`, or a split folder holding `velodyne/`). Only the
    /// file list is read; frames are read by [`Dataset::load`].
    pub fn open(root: &Path) -> Result<Self> {
        let base = split_folder(root, "velodyne", "a KITTI object folder")?;
        let ids = list_stems(&base.join("velodyne"), ".bin")?;
        Ok(KittiObjectDataset {
            base,
            ids,
            load_images: true,
        })
    }

    /// Decode camera images when loading frames (default true); without, frames carry the image
    /// path and camera only.
    pub fn with_images(mut self, load: bool) -> Self {
        self.load_images = load;
        self
    }

    /// The split folder (holding `velodyne/`).
    pub fn base(&self) -> &Path {
        &self.base
    }

    /// Frame ids (`000000`, ...), sorted.
    pub fn ids(&self) -> &[String] {
        &self.ids
    }

    fn file(&self, dir: &str, id: &str, ext: &str) -> PathBuf {
        self.base.join(dir).join(format!("{id}{ext}"))
    }

    /// Calibration of frame `index`.
    pub fn calib(&self, index: usize) -> Result<KittiCalib> {
        KittiCalib::read(&self.file("calib", &self.ids[index], ".txt"))
    }

    /// `label_2` boxes of frame `index` (empty when the split has no labels, e.g. `testing`).
    pub fn labels(&self, index: usize) -> Result<Vec<KittiObjectLabel>> {
        let p = self.file("label_2", &self.ids[index], ".txt");
        if !p.exists() && !self.base.join("label_2").is_dir() {
            return Ok(Vec::new());
        }
        read_kitti_labels(&p)
    }
}

impl Dataset for KittiObjectDataset {
    fn name(&self) -> &'static str {
        crate::dataset::DatasetName::Kitti.as_str()
    }
    fn len(&self) -> usize {
        self.ids.len()
    }
    fn frame_id(&self, index: usize) -> String {
        self.ids[index].clone()
    }
    fn load(&self, index: usize) -> Result<Frame> {
        let id = &self.ids[index];
        let scan_path = self.file("velodyne", id, ".bin");
        let loaded = read_kitti_bin(&scan_path)?;
        let image_path = self.file("image_2", id, ".png");
        let calib = self.calib(index)?;
        let (image, (w, h)) = crate::image_io::read_rgb_image_if(&image_path, self.load_images)?;
        let camera = calib.camera(2, w, h)?;
        Ok(Frame {
            id: id.clone(),
            points: loaded.cloud,
            dropped_non_finite: loaded.dropped_non_finite,
            scan_path,
            image_path: Some(image_path),
            image,
            camera: Some(camera),
            extra_views: Vec::new(),
        })
    }
    fn default_sensor(&self) -> LidarSensor {
        LidarSensor::hdl64e()
    }
    fn intensity_max(&self) -> f32 {
        1.0
    }
    fn source_files(&self, index: usize) -> Result<Vec<PathBuf>> {
        let id = &self.ids[index];
        Ok(vec![
            self.file("velodyne", id, ".bin"),
            self.file("image_2", id, ".png"),
            self.file("calib", id, ".txt"),
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CALIB: &str = "P0: 1 0 0 0 0 1 0 0 0 0 1 0\nP1: 1 0 0 0 0 1 0 0 0 0 1 0\nP2: 700 0 600 45 0 700 180 0 0 0 1 0.005\nP3: 1 0 0 0 0 1 0 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n";

    #[test]
    fn calib_parses_and_projects_forward_point() {
        let c = KittiCalib::parse(CALIB, Path::new("c.txt")).unwrap();
        assert!(c.tr_imu_to_velo.is_none());
        let cam = c.camera(2, 1242, 375).unwrap();
        // x forward 10 m -> camera z = 10; u = (700*0 + 600*10 + 45) / (10 + 0.005)
        let ip = cam.try_project(Vec3::new(10.0, 0.0, 0.0)).unwrap();
        assert!((ip.u_px - 6045.0 / 10.005).abs() < 1e-3, "{ip:?}");
        assert!((ip.v_px - 1800.0 / 10.005).abs() < 1e-3, "{ip:?}");
    }

    #[test]
    fn calib_errors_name_file_key_and_problem() {
        let missing = CALIB.replace("R0_rect: 1 0 0 0 1 0 0 0 1\n", "");
        let e = KittiCalib::parse(&missing, Path::new("000007.txt"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("000007.txt") && e.contains("R0_rect") && e.contains("missing"),
            "{e}"
        );
        let bad = CALIB.replace("700 0 600", "700 0 6x0");
        let e = KittiCalib::parse(&bad, Path::new("c.txt"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("P2") && e.contains("malformed number `6x0`") && e.contains("line 3"),
            "{e}"
        );
        let short = CALIB.replace("R0_rect: 1 0 0 0 1 0 0 0 1", "R0_rect: 1 0 0 0 1 0 0 0");
        let e = KittiCalib::parse(&short, Path::new("c.txt"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("expected 9 numbers, found 8"), "{e}");
        let nan = CALIB.replace("P3: 1 ", "P3: nan ");
        assert!(KittiCalib::parse(&nan, Path::new("c.txt")).is_err());
        // a camera that cannot be built (singular K) is reported with the file it came from
        let singular = CALIB.replace("P2: 700 0 600 45 0 700 180", "P2: 0 0 600 45 0 700 180");
        let c = KittiCalib::parse(&singular, Path::new("dir/000009.txt")).unwrap();
        let e = c.camera(2, 1242, 375).unwrap_err().to_string();
        assert!(e.contains("000009.txt") && e.contains("P2"), "{e}");
    }

    #[test]
    fn labels_parse_and_reject_garbage() {
        let l = parse_kitti_labels(
            "Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n",
            Path::new("l.txt"),
        )
        .unwrap();
        assert_eq!(l[0].class, "Car");
        assert_eq!(l[0].location_cam_m, Vec3::new(-16.53, 2.39, 58.49));
        assert!(parse_kitti_labels("Car 0 0 1\n", Path::new("l.txt")).is_err());
    }
}
