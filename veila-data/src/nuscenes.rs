//! nuScenes: LIDAR_TOP sweeps (`.pcd.bin`, 5 f32 per point with the ring index), camera JPEGs and
//! calibration, either from a release's JSON tables (`sample`, `sample_data`, `calibrated_sensor`,
//! `ego_pose`, `sensor`) or from a simple per-sample JSON (`calib/<sample_token>.json`).
//!
//! # The LiDAR -> camera chain
//!
//! Exactly as the devkit's `map_pointcloud_to_image`: LiDAR -> ego at the LiDAR timestamp (the LiDAR's
//! `calibrated_sensor`) -> global (the `ego_pose` of the LiDAR sample_data) -> ego at the camera
//! timestamp (inverse `ego_pose` of the camera sample_data) -> camera (inverse camera
//! `calibrated_sensor`). Quaternions are stored `w, x, y, z` and normalised before use, as pyquaternion
//! does. The chain is composed in f64 ([`cam_from_lidar`]) and only the result is rounded to f32.
//! The per-sample JSON's `lidar2cam` is that same chain, precomputed.
//!
//! Tables are streamed: only key-frame `sample_data` records and the `ego_pose` records they point to
//! are kept, so the index of a full release stays small.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fmt;
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3, Mat3, Mat4};
use serde::de::{DeserializeOwned, DeserializeSeed, SeqAccess, Visitor};
use serde::{Deserialize, Deserializer};
use veila_geom::{LidarSensor, PinholeCamera};

use crate::dataset::{Dataset, Frame, FrameView};
use crate::scan::read_nuscenes_pcd_bin;
use crate::{Error, Result};

/// The six camera channels of nuScenes.
pub const CAMERA_CHANNELS: [&str; 6] = [
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
];

/// A rigid transform as nuScenes stores it: rotation quaternion `w, x, y, z` and translation (metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation quaternion, `w, x, y, z` (normalised before use).
    pub rotation_wxyz: [f64; 4],
    /// Translation, metres.
    pub translation: [f64; 3],
}

impl Pose {
    /// The 4x4 matrix `[R t; 0 1]` (maps the child frame into the parent frame).
    pub fn to_matrix(&self) -> DMat4 {
        let [w, x, y, z] = self.rotation_wxyz;
        let q = DQuat::from_xyzw(x, y, z, w).normalize();
        DMat4::from_rotation_translation(q, DVec3::from_array(self.translation))
    }

    fn check(&self, what: &str, path: &Path) -> Result<()> {
        let [w, x, y, z] = self.rotation_wxyz;
        let n = (w * w + x * x + y * y + z * z).sqrt();
        if !n.is_finite() || n < 1e-6 || !self.translation.iter().all(|t| t.is_finite()) {
            return Err(Error::format(
                path,
                format!("{what}: non-finite or zero quaternion/translation"),
            ));
        }
        Ok(())
    }
}

/// Inverse of a rigid transform (rotation transposed), exact up to rounding.
fn rigid_inverse(m: &DMat4) -> DMat4 {
    let r = DMat3::from_mat4(*m).transpose();
    let t = -(r * m.w_axis.truncate());
    DMat4::from_cols(
        r.x_axis.extend(0.0),
        r.y_axis.extend(0.0),
        r.z_axis.extend(0.0),
        t.extend(1.0),
    )
}

/// `cam_from_lidar` by the devkit chain: LiDAR -> ego(t_lidar) -> global -> ego(t_cam) -> camera.
/// `lidar_sensor` / `camera_sensor` are `calibrated_sensor` records (sensor in ego), `ego_at_lidar` /
/// `ego_at_camera` are `ego_pose` records (ego in global).
pub fn cam_from_lidar(
    lidar_sensor: &Pose,
    ego_at_lidar: &Pose,
    ego_at_camera: &Pose,
    camera_sensor: &Pose,
) -> DMat4 {
    rigid_inverse(&camera_sensor.to_matrix())
        * rigid_inverse(&ego_at_camera.to_matrix())
        * ego_at_lidar.to_matrix()
        * lidar_sensor.to_matrix()
}

fn dmat4_to_mat4(m: &DMat4) -> Mat4 {
    m.as_mat4()
}

fn intrinsic_mat3(k: &[[f64; 3]; 3]) -> Mat3 {
    Mat3::from_cols_array_2d(&[
        [k[0][0] as f32, k[1][0] as f32, k[2][0] as f32],
        [k[0][1] as f32, k[1][1] as f32, k[2][1] as f32],
        [k[0][2] as f32, k[1][2] as f32, k[2][2] as f32],
    ])
}

// ---------------------------------------------------------------------------------------------
// per-sample JSON
// ---------------------------------------------------------------------------------------------

#[derive(Debug, Clone, Deserialize)]
struct JsonTransform {
    matrix_4x4_row_major: [[f64; 4]; 4],
}

impl JsonTransform {
    fn to_dmat4(&self, what: &str, path: &Path) -> Result<DMat4> {
        let m = &self.matrix_4x4_row_major;
        if !m.iter().flatten().all(|v| v.is_finite()) {
            return Err(Error::format(
                path,
                format!("{what}: non-finite matrix entry"),
            ));
        }
        if m[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err(Error::format(
                path,
                format!("{what}: last row must be 0 0 0 1, found {:?}", m[3]),
            ));
        }
        let rot = [
            [m[0][0], m[0][1], m[0][2]],
            [m[1][0], m[1][1], m[1][2]],
            [m[2][0], m[2][1], m[2][2]],
        ];
        crate::calib::check_rotation(path, what, rot)?;
        Ok(DMat4::from_cols_array_2d(m).transpose())
    }
}

#[derive(Debug, Clone, Deserialize)]
struct JsonLidar {
    file: String,
    #[serde(default)]
    timestamp_s: f64,
    lidar2ego: JsonTransform,
}

#[derive(Debug, Clone, Deserialize)]
struct JsonCamera {
    file: String,
    #[serde(default)]
    timestamp_s: f64,
    intrinsic_3x3: [[f64; 3]; 3],
    cam2ego: JsonTransform,
    lidar2cam: JsonTransform,
}

#[derive(Debug, Clone, Deserialize)]
struct JsonBox {
    #[serde(default)]
    label: Option<String>,
    bbox_3d: [f64; 7],
    #[serde(default)]
    num_lidar_pts: i64,
}

#[derive(Debug, Clone, Deserialize)]
struct JsonSample {
    sample_token: String,
    lidar: JsonLidar,
    ego2global_at_lidar_time: JsonTransform,
    cameras: BTreeMap<String, JsonCamera>,
    #[serde(default)]
    instances_lidar_frame: Vec<JsonBox>,
}

/// A 3D box in the LiDAR frame (per-sample JSON; geometric centre).
#[derive(Debug, Clone, PartialEq)]
pub struct NuScenesBox {
    /// Category name (`None` for categories outside the detection classes).
    pub label: Option<String>,
    /// Geometric centre in the LiDAR frame, metres.
    pub center_m: glam::Vec3,
    /// Length, width, height, metres.
    pub size_lwh_m: glam::Vec3,
    /// Yaw around the LiDAR z axis, radians.
    pub yaw_rad: f32,
    /// LiDAR points inside the box according to the annotation.
    pub num_lidar_pts: i64,
}

/// One camera of a [`NuScenesSample`].
#[derive(Debug, Clone, PartialEq)]
pub struct NuScenesCameraCalib {
    /// Image file, relative to the data root.
    pub file: String,
    /// Timestamp, seconds.
    pub timestamp_s: f64,
    /// Intrinsic matrix (3x3).
    pub intrinsic: Mat3,
    /// Camera frame from LiDAR frame (the devkit chain, ego motion compensated).
    pub cam_from_lidar: DMat4,
    /// Ego frame (at the camera timestamp) from camera frame.
    pub ego_from_cam: DMat4,
}

/// Calibration of one nuScenes sample: LiDAR file and pose, and every camera.
#[derive(Debug, Clone, PartialEq)]
pub struct NuScenesSample {
    /// The sample token.
    pub token: String,
    /// LIDAR_TOP file, relative to the data root.
    pub lidar_file: String,
    /// LIDAR_TOP timestamp, seconds.
    pub lidar_timestamp_s: f64,
    /// Ego from LiDAR.
    pub ego_from_lidar: DMat4,
    /// Global from ego at the LiDAR timestamp.
    pub global_from_ego: DMat4,
    /// Cameras by channel (`CAM_FRONT`, ...).
    pub cameras: BTreeMap<String, NuScenesCameraCalib>,
    /// Annotated boxes (empty when the source has none).
    pub boxes: Vec<NuScenesBox>,
    /// Where the sample was read from (its JSON file, or the release's `calibrated_sensor.json`):
    /// what an error about its calibration names.
    pub source: PathBuf,
}

impl NuScenesSample {
    /// Read the simple per-sample JSON (`calib/<sample_token>.json`).
    pub fn read_json(path: &Path) -> Result<Self> {
        let text = crate::read_capped::read_metadata_string(
            path,
            crate::read_capped::MAX_CALIBRATION_BYTES,
            "a nuScenes sample JSON",
        )?;
        let j: JsonSample = serde_json::from_str(&python_json_to_strict(&text)).map_err(|e| {
            Error::format(path, format!("not a nuScenes sample calibration JSON: {e}"))
        })?;
        let mut cameras = BTreeMap::new();
        for (name, c) in &j.cameras {
            if !c.intrinsic_3x3.iter().flatten().all(|v| v.is_finite()) {
                return Err(Error::format(
                    path,
                    format!("{name}.intrinsic_3x3: non-finite entry"),
                ));
            }
            cameras.insert(
                name.clone(),
                NuScenesCameraCalib {
                    file: c.file.clone(),
                    timestamp_s: c.timestamp_s,
                    intrinsic: intrinsic_mat3(&c.intrinsic_3x3),
                    cam_from_lidar: c.lidar2cam.to_dmat4(&format!("{name}.lidar2cam"), path)?,
                    ego_from_cam: c.cam2ego.to_dmat4(&format!("{name}.cam2ego"), path)?,
                },
            );
        }
        let boxes = j
            .instances_lidar_frame
            .iter()
            .map(|b| NuScenesBox {
                label: b.label.clone(),
                center_m: glam::Vec3::new(
                    b.bbox_3d[0] as f32,
                    b.bbox_3d[1] as f32,
                    b.bbox_3d[2] as f32,
                ),
                size_lwh_m: glam::Vec3::new(
                    b.bbox_3d[3] as f32,
                    b.bbox_3d[4] as f32,
                    b.bbox_3d[5] as f32,
                ),
                yaw_rad: b.bbox_3d[6] as f32,
                num_lidar_pts: b.num_lidar_pts,
            })
            .collect();
        Ok(NuScenesSample {
            token: j.sample_token,
            lidar_file: j.lidar.file,
            lidar_timestamp_s: j.lidar.timestamp_s,
            ego_from_lidar: j.lidar.lidar2ego.to_dmat4("lidar.lidar2ego", path)?,
            global_from_ego: j
                .ego2global_at_lidar_time
                .to_dmat4("ego2global_at_lidar_time", path)?,
            cameras,
            boxes,
            source: path.to_path_buf(),
        })
    }

    /// The pinhole camera of `channel` for an image of `width x height`.
    pub fn camera(&self, channel: &str, width: u32, height: u32) -> Result<PinholeCamera> {
        // the sample's file is named: the channel list came from it
        let c = self.cameras.get(channel).ok_or_else(|| {
            Error::format(
                &self.source,
                if self.cameras.is_empty() {
                    format!(
                        "sample {} has no camera {channel}: it lists no camera at all",
                        self.token
                    )
                } else {
                    format!(
                        "sample {} has no camera {channel} (has {})",
                        self.token,
                        self.cameras.keys().cloned().collect::<Vec<_>>().join(", ")
                    )
                },
            )
        })?;
        // focal lengths, principal point and translation: `PinholeCamera::check_calibration`
        PinholeCamera::from_nuscenes(c.intrinsic, dmat4_to_mat4(&c.cam_from_lidar), width, height)
            .map_err(|e| {
                Error::format(
                    &self.source,
                    format!("sample {}, camera {channel}: {e}", self.token),
                )
            })
    }
}

/// Replace the bare `NaN`, `Infinity` and `-Infinity` tokens Python's `json` module writes (outside
/// strings) with `null`, so strict JSON parsers accept the file; fields that may hold them are
/// optional or ignored.
fn python_json_to_strict(text: &str) -> std::borrow::Cow<'_, str> {
    if !(text.contains("NaN") || text.contains("Infinity")) {
        return std::borrow::Cow::Borrowed(text);
    }
    let bytes = text.as_bytes();
    let mut out: Vec<u8> = Vec::with_capacity(bytes.len());
    let (mut in_str, mut escaped, mut i) = (false, false, 0);
    'outer: while i < bytes.len() {
        let b = bytes[i];
        if in_str {
            if escaped {
                escaped = false;
            } else if b == b'\\' {
                escaped = true;
            } else if b == b'"' {
                in_str = false;
            }
        } else if b == b'"' {
            in_str = true;
        } else {
            for tok in [&b"-Infinity"[..], b"Infinity", b"NaN"] {
                if bytes[i..].starts_with(tok) {
                    out.extend_from_slice(b"null");
                    i += tok.len();
                    continue 'outer;
                }
            }
        }
        out.push(b);
        i += 1;
    }
    // only ASCII tokens were replaced, so the bytes stay valid UTF-8
    std::borrow::Cow::Owned(String::from_utf8(out).unwrap_or_else(|_| text.to_string()))
}

// ---------------------------------------------------------------------------------------------
// release tables
// ---------------------------------------------------------------------------------------------

#[derive(Debug, Clone, Deserialize)]
struct SampleRec {
    token: String,
    timestamp: i64,
}

#[derive(Debug, Clone, Deserialize)]
struct SampleDataRec {
    token: String,
    sample_token: String,
    ego_pose_token: String,
    calibrated_sensor_token: String,
    timestamp: i64,
    filename: String,
    #[serde(default)]
    is_key_frame: bool,
    #[serde(default)]
    width: u32,
    #[serde(default)]
    height: u32,
}

#[derive(Debug, Clone, Deserialize)]
struct CalibratedSensorRec {
    token: String,
    sensor_token: String,
    rotation: [f64; 4],
    translation: [f64; 3],
    #[serde(default)]
    camera_intrinsic: Vec<Vec<f64>>,
}

#[derive(Debug, Clone, Deserialize)]
struct EgoPoseRec {
    token: String,
    rotation: [f64; 4],
    translation: [f64; 3],
}

#[derive(Debug, Clone, Deserialize)]
struct SensorRec {
    token: String,
    channel: String,
}

/// Deserialize a JSON array keeping only the elements `keep` accepts, one element in memory at a time.
struct FilteredSeq<T, F> {
    keep: F,
    _t: PhantomData<T>,
}

impl<'de, T: DeserializeOwned, F: FnMut(&T) -> bool> DeserializeSeed<'de> for FilteredSeq<T, F> {
    type Value = Vec<T>;
    fn deserialize<D: Deserializer<'de>>(self, d: D) -> std::result::Result<Vec<T>, D::Error> {
        struct V<T, F>(F, PhantomData<T>);
        impl<'de, T: DeserializeOwned, F: FnMut(&T) -> bool> Visitor<'de> for V<T, F> {
            type Value = Vec<T>;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a JSON array of records")
            }
            fn visit_seq<A: SeqAccess<'de>>(
                mut self,
                mut seq: A,
            ) -> std::result::Result<Vec<T>, A::Error> {
                let mut out = Vec::new();
                while let Some(item) = seq.next_element::<T>()? {
                    if (self.0)(&item) {
                        out.push(item);
                    }
                }
                Ok(out)
            }
        }
        d.deserialize_seq(V(self.keep, PhantomData))
    }
}

fn read_table<T: DeserializeOwned>(path: &Path, keep: impl FnMut(&T) -> bool) -> Result<Vec<T>> {
    // streamed, so not capped; but opening a FIFO would block
    crate::read_capped::check_regular_file(path)?;
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut de =
        serde_json::Deserializer::from_reader(std::io::BufReader::with_capacity(1 << 20, f));
    let v = FilteredSeq {
        keep,
        _t: PhantomData,
    }
    .deserialize(&mut de)
    .map_err(|e| Error::format(path, format!("malformed nuScenes table: {e}")))?;
    de.end()
        .map_err(|e| Error::format(path, format!("trailing data after the table: {e}")))?;
    Ok(v)
}

#[derive(Debug, Clone)]
struct KeyData {
    filename: String,
    timestamp_us: i64,
    calibrated_sensor: String,
    ego_pose: String,
    width: u32,
    height: u32,
}

/// The JSON tables of a nuScenes release (`v1.0-mini`, `v1.0-trainval`, ...), indexed by sample.
#[derive(Debug, Clone)]
pub struct NuScenesTables {
    table_dir: PathBuf,
    samples: Vec<(String, i64)>,
    key_data: HashMap<(String, String), KeyData>,
    calibrated: HashMap<String, (String, Pose, Vec<Vec<f64>>)>,
    ego_poses: HashMap<String, Pose>,
}

impl NuScenesTables {
    /// Read the tables in `table_dir` (the folder holding `sample.json`, ...). Samples are ordered by
    /// timestamp, then token.
    pub fn read(table_dir: &Path) -> Result<Self> {
        let sensors: Vec<SensorRec> = read_table(&table_dir.join("sensor.json"), |_| true)?;
        let channel_of: HashMap<String, String> =
            sensors.into_iter().map(|s| (s.token, s.channel)).collect();
        let cs_path = table_dir.join("calibrated_sensor.json");
        let cs: Vec<CalibratedSensorRec> = read_table(&cs_path, |_| true)?;
        let mut calibrated = HashMap::new();
        for c in cs {
            let pose = Pose {
                rotation_wxyz: c.rotation,
                translation: c.translation,
            };
            pose.check(&format!("calibrated_sensor {}", c.token), &cs_path)?;
            let channel = channel_of.get(&c.sensor_token).cloned().ok_or_else(|| {
                Error::format(
                    &cs_path,
                    format!(
                        "calibrated_sensor {} names unknown sensor {}",
                        c.token, c.sensor_token
                    ),
                )
            })?;
            calibrated.insert(c.token, (channel, pose, c.camera_intrinsic));
        }
        let mut samples: Vec<(String, i64)> =
            read_table::<SampleRec>(&table_dir.join("sample.json"), |_| true)?
                .into_iter()
                .map(|s| (s.token, s.timestamp))
                .collect();
        samples.sort_by(|a, b| a.1.cmp(&b.1).then_with(|| a.0.cmp(&b.0)));
        let sd_path = table_dir.join("sample_data.json");
        let key: Vec<SampleDataRec> = read_table(&sd_path, |r: &SampleDataRec| r.is_key_frame)?;
        let mut key_data = HashMap::new();
        let mut needed_poses = HashSet::new();
        for r in key {
            let channel = calibrated
                .get(&r.calibrated_sensor_token)
                .map(|c| c.0.clone())
                .ok_or_else(|| {
                    Error::format(
                        &sd_path,
                        format!(
                            "sample_data {} names unknown calibrated_sensor {}",
                            r.token, r.calibrated_sensor_token
                        ),
                    )
                })?;
            needed_poses.insert(r.ego_pose_token.clone());
            key_data.insert(
                (r.sample_token, channel),
                KeyData {
                    filename: r.filename,
                    timestamp_us: r.timestamp,
                    calibrated_sensor: r.calibrated_sensor_token,
                    ego_pose: r.ego_pose_token,
                    width: r.width,
                    height: r.height,
                },
            );
        }
        let ep_path = table_dir.join("ego_pose.json");
        let poses: Vec<EgoPoseRec> =
            read_table(&ep_path, |p: &EgoPoseRec| needed_poses.contains(&p.token))?;
        let mut ego_poses = HashMap::new();
        for p in poses {
            let pose = Pose {
                rotation_wxyz: p.rotation,
                translation: p.translation,
            };
            pose.check(&format!("ego_pose {}", p.token), &ep_path)?;
            ego_poses.insert(p.token, pose);
        }
        Ok(NuScenesTables {
            table_dir: table_dir.to_path_buf(),
            samples,
            key_data,
            calibrated,
            ego_poses,
        })
    }

    /// Sample tokens in timestamp order.
    pub fn sample_tokens(&self) -> impl Iterator<Item = &str> {
        self.samples.iter().map(|s| s.0.as_str())
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when there are no samples.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    fn key(&self, sample: &str, channel: &str) -> Result<&KeyData> {
        self.key_data
            .get(&(sample.to_string(), channel.to_string()))
            .ok_or_else(|| {
                Error::format(
                    self.table_dir.join("sample_data.json"),
                    format!("sample {sample} has no key-frame {channel} sample_data"),
                )
            })
    }

    fn pose(&self, token: &str) -> Result<&Pose> {
        self.ego_poses.get(token).ok_or_else(|| {
            Error::format(
                self.table_dir.join("ego_pose.json"),
                format!("ego_pose {token} is missing"),
            )
        })
    }

    /// Build the calibration of one sample for the given camera channels (devkit chain).
    pub fn sample(&self, token: &str, channels: &[&str]) -> Result<NuScenesSample> {
        let cs_path = self.table_dir.join("calibrated_sensor.json");
        let lidar = self.key(token, "LIDAR_TOP")?;
        let lidar_cs = &self.calibrated[&lidar.calibrated_sensor].1;
        let lidar_pose = self.pose(&lidar.ego_pose)?;
        let mut cameras = BTreeMap::new();
        for ch in channels {
            let cam = self.key(token, ch)?;
            let (_, cam_cs, k) = &self.calibrated[&cam.calibrated_sensor];
            if k.len() != 3
                || k.iter().any(|r| r.len() != 3)
                || !k.iter().flatten().all(|v| v.is_finite())
            {
                return Err(Error::format(
                    &cs_path,
                    format!(
                        "calibrated_sensor {}: camera_intrinsic is not a finite 3x3 matrix",
                        cam.calibrated_sensor
                    ),
                ));
            }
            let k3 = [
                [k[0][0], k[0][1], k[0][2]],
                [k[1][0], k[1][1], k[1][2]],
                [k[2][0], k[2][1], k[2][2]],
            ];
            let cam_pose = self.pose(&cam.ego_pose)?;
            cameras.insert(
                ch.to_string(),
                NuScenesCameraCalib {
                    file: cam.filename.clone(),
                    timestamp_s: cam.timestamp_us as f64 * 1e-6,
                    intrinsic: intrinsic_mat3(&k3),
                    cam_from_lidar: cam_from_lidar(lidar_cs, lidar_pose, cam_pose, cam_cs),
                    ego_from_cam: cam_cs.to_matrix(),
                },
            );
        }
        Ok(NuScenesSample {
            token: token.to_string(),
            lidar_file: lidar.filename.clone(),
            lidar_timestamp_s: lidar.timestamp_us as f64 * 1e-6,
            ego_from_lidar: lidar_cs.to_matrix(),
            global_from_ego: lidar_pose.to_matrix(),
            cameras,
            boxes: Vec::new(),
            source: cs_path.clone(),
        })
    }

    /// Image size recorded in `sample_data` (0 x 0 when the table lacks it).
    pub fn image_size(&self, token: &str, channel: &str) -> Result<(u32, u32)> {
        let k = self.key(token, channel)?;
        Ok((k.width, k.height))
    }
}

#[derive(Debug, Clone)]
enum Source {
    Tables(Box<NuScenesTables>),
    SampleJson(Vec<PathBuf>),
}

/// nuScenes key frames (LIDAR_TOP + one or more cameras), read lazily. Frame ids are sample
/// tokens.
#[derive(Debug, Clone)]
pub struct NuScenesDataset {
    dataroot: PathBuf,
    source: Source,
    ids: Vec<String>,
    /// The cameras: the first is the frame's camera, the others its `extra_views`.
    channels: Vec<String>,
    load_images: bool,
}

/// The paper's three cameras (front, front-left, front-right), in that order.
pub const PAPER_CAMERAS: [&str; 3] = ["CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT"];

impl NuScenesDataset {
    /// Open `dataroot`: the release tables when a `v1.0-*` folder (or `sample.json` in the root) is
    /// present, otherwise the per-sample JSON files in `dataroot/calib/`. `camera` is the paired
    /// channel (`CAM_FRONT` in the paper).
    pub fn open(dataroot: &Path, camera: &str) -> Result<Self> {
        Self::open_cameras(dataroot, &[camera])
    }

    /// [`Self::open`] with several cameras (e.g. [`PAPER_CAMERAS`]): the first is each frame's
    /// camera, the others its `extra_views`, in this order.
    pub fn open_cameras(dataroot: &Path, cameras: &[&str]) -> Result<Self> {
        if cameras.is_empty() {
            return Err(Error::Invalid {
                what: "nuScenes camera channels".into(),
                message: "name at least one camera".into(),
            });
        }
        for (i, camera) in cameras.iter().enumerate() {
            if !CAMERA_CHANNELS.contains(camera) {
                return Err(Error::Invalid {
                    what: "nuScenes camera channel".into(),
                    message: format!("`{camera}` is not one of {}", CAMERA_CHANNELS.join(", ")),
                });
            }
            if cameras[..i].contains(camera) {
                return Err(Error::Invalid {
                    what: "nuScenes camera channels".into(),
                    message: format!("`{camera}` is named twice"),
                });
            }
        }
        let mut ds = if let Some(dir) = find_table_dir(dataroot)? {
            Self::open_tables(dataroot, &dir, cameras[0])?
        } else if dataroot.join("calib").is_dir() {
            Self::open_sample_json(dataroot, cameras[0])?
        } else {
            return Err(Error::format(
                dataroot,
                "not a nuScenes data root: no v1.0-*/sample.json tables and no calib/*.json",
            ));
        };
        ds.channels = cameras.iter().map(|c| c.to_string()).collect();
        Ok(ds)
    }

    /// Open with the release tables in `table_dir` (file names relative to `dataroot`).
    pub fn open_tables(dataroot: &Path, table_dir: &Path, camera: &str) -> Result<Self> {
        let tables = NuScenesTables::read(table_dir)?;
        let ids = tables.sample_tokens().map(str::to_string).collect();
        Ok(NuScenesDataset {
            dataroot: dataroot.to_path_buf(),
            source: Source::Tables(Box::new(tables)),
            ids,
            channels: vec![camera.to_string()],
            load_images: true,
        })
    }

    /// Open with the per-sample JSON files `dataroot/calib/*.json` (sorted by name).
    pub fn open_sample_json(dataroot: &Path, camera: &str) -> Result<Self> {
        let dir = dataroot.join("calib");
        let stems = crate::kitti::list_stems(&dir, ".json")?;
        let files = stems
            .iter()
            .map(|s| dir.join(format!("{s}.json")))
            .collect();
        Ok(NuScenesDataset {
            dataroot: dataroot.to_path_buf(),
            source: Source::SampleJson(files),
            ids: stems,
            channels: vec![camera.to_string()],
            load_images: true,
        })
    }

    /// Decode camera images when loading frames (default true).
    pub fn with_images(mut self, load: bool) -> Self {
        self.load_images = load;
        self
    }

    /// The file `rel` that sample `index` names for `channel` (`None`: the LiDAR sweep), inside
    /// the data root ([`crate::contained::contained`]): else an error naming the field
    /// (`lidar.file`, `cameras.CAM_FRONT.file` of a sample JSON, a `sample_data.json` record's
    /// `filename`) and the file holding it, before anything at the path is opened.
    fn sample_file(&self, index: usize, channel: Option<&str>, rel: &str) -> Result<PathBuf> {
        let (file, field) = match (&self.source, channel) {
            (Source::SampleJson(jsons), None) => (jsons[index].clone(), "lidar.file".to_string()),
            (Source::SampleJson(jsons), Some(ch)) => {
                (jsons[index].clone(), format!("cameras.{ch}.file"))
            }
            (Source::Tables(t), ch) => (
                t.table_dir.join("sample_data.json"),
                format!(
                    "filename (the {} record of sample {})",
                    ch.unwrap_or("LIDAR_TOP"),
                    self.ids[index].escape_debug()
                ),
            ),
        };
        crate::contained::contained(&self.dataroot, Path::new(rel), &field, &file)
    }

    /// Calibration of sample `index` (the dataset's camera only, for tables; all cameras for JSON).
    pub fn sample(&self, index: usize) -> Result<NuScenesSample> {
        match &self.source {
            Source::Tables(t) => {
                let channels: Vec<&str> = self.channels.iter().map(String::as_str).collect();
                t.sample(&self.ids[index], &channels)
            }
            Source::SampleJson(files) => NuScenesSample::read_json(&files[index]),
        }
    }
}

fn find_table_dir(dataroot: &Path) -> Result<Option<PathBuf>> {
    if dataroot.join("sample.json").is_file() {
        return Ok(Some(dataroot.to_path_buf()));
    }
    let Ok(rd) = std::fs::read_dir(dataroot) else {
        return Err(Error::io(
            dataroot,
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "data root is not a readable directory",
            ),
        ));
    };
    let mut dirs: Vec<PathBuf> = rd
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("v1.0"))
                && p.join("sample.json").is_file()
        })
        .collect();
    dirs.sort();
    if dirs.len() > 1 {
        return Err(Error::format(
            dataroot,
            format!(
                "several table folders ({}); open one with NuScenesDataset::open_tables",
                dirs.len()
            ),
        ));
    }
    Ok(dirs.pop())
}

impl Dataset for NuScenesDataset {
    fn name(&self) -> &'static str {
        crate::dataset::DatasetName::NuScenes.as_str()
    }
    fn len(&self) -> usize {
        self.ids.len()
    }
    fn frame_id(&self, index: usize) -> String {
        self.ids[index].clone()
    }
    fn load(&self, index: usize) -> Result<Frame> {
        let sample = self.sample(index)?;
        let scan_path = self.sample_file(index, None, &sample.lidar_file)?;
        let loaded = read_nuscenes_pcd_bin(&scan_path)?;
        let mut views = Vec::with_capacity(self.channels.len());
        for channel in &self.channels {
            let cam = sample.cameras.get(channel).ok_or_else(|| {
                Error::format(
                    &sample.source,
                    format!("sample {} has no camera {channel}", sample.token),
                )
            })?;
            let image_path = self.sample_file(index, Some(channel.as_str()), &cam.file)?;
            let (image, (w, h)) =
                crate::image_io::read_rgb_image_if(&image_path, self.load_images)?;
            views.push(FrameView {
                channel: channel.clone(),
                camera: sample.camera(channel, w, h)?,
                image_path,
                image,
            });
        }
        let first = views.remove(0);
        Ok(Frame {
            id: sample.token.clone(),
            points: loaded.cloud,
            dropped_non_finite: loaded.dropped_non_finite,
            scan_path,
            image_path: Some(first.image_path),
            image: first.image,
            camera: Some(first.camera),
            extra_views: views,
        })
    }
    fn default_sensor(&self) -> LidarSensor {
        LidarSensor::hdl32e()
    }
    fn intensity_max(&self) -> f32 {
        255.0
    }
    fn source_files(&self, index: usize) -> Result<Vec<PathBuf>> {
        let sample = self.sample(index)?;
        let mut files = vec![self.sample_file(index, None, &sample.lidar_file)?];
        for channel in &self.channels {
            if let Some(cam) = sample.cameras.get(channel) {
                files.push(self.sample_file(index, Some(channel.as_str()), &cam.file)?);
            }
        }
        if let Source::SampleJson(jsons) = &self.source {
            files.push(jsons[index].clone());
        }
        Ok(files)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(w: f64, x: f64, y: f64, z: f64, t: [f64; 3]) -> Pose {
        Pose {
            rotation_wxyz: [w, x, y, z],
            translation: t,
        }
    }

    #[test]
    fn python_json_tokens_become_null_outside_strings() {
        let t = r#"{"a": [NaN, -Infinity, Infinity], "s": "NaN \" Infinity"}"#;
        let v: serde_json::Value = serde_json::from_str(&python_json_to_strict(t)).unwrap();
        assert_eq!(v["a"], serde_json::json!([null, null, null]));
        assert_eq!(v["s"], "NaN \" Infinity");
    }

    #[test]
    fn chain_matches_hand_composition() {
        // lidar yawed +90 deg on the ego, ego moved 1 m forward between lidar and camera time
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let lidar_cs = pose(s, 0.0, 0.0, s, [1.0, 0.0, 2.0]);
        let ego_l = pose(1.0, 0.0, 0.0, 0.0, [100.0, 50.0, 0.0]);
        let ego_c = pose(1.0, 0.0, 0.0, 0.0, [101.0, 50.0, 0.0]);
        // camera looking forward: z_cam = x_ego, x_cam = -y_ego, y_cam = -z_ego
        let cam_cs_m = DMat3::from_cols(
            DVec3::new(0.0, -1.0, 0.0),
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(1.0, 0.0, 0.0),
        );
        let q = DQuat::from_mat3(&cam_cs_m);
        let cam_cs = pose(q.w, q.x, q.y, q.z, [1.5, 0.0, 1.5]);
        let t = cam_from_lidar(&lidar_cs, &ego_l, &ego_c, &cam_cs);
        // a point 10 m along lidar +x = ego +y (left): ego(t_l) = (1, 10, 2) -> global (101, 60, 2)
        // -> ego(t_c) = (0, 10, 2) -> camera: d = (-1.5, 10, 0.5) -> (x=-10, y=-0.5, z=-1.5)
        let p = t.transform_point3(DVec3::new(10.0, 0.0, 0.0));
        assert!(
            (p - DVec3::new(-10.0, -0.5, -1.5)).length() < 1e-12,
            "{p:?}"
        );
        // unnormalised quaternions give the same result (pyquaternion normalises)
        let lidar_cs2 = pose(2.0 * s, 0.0, 0.0, 2.0 * s, [1.0, 0.0, 2.0]);
        let t2 = cam_from_lidar(&lidar_cs2, &ego_l, &ego_c, &cam_cs);
        assert!(t2.abs_diff_eq(t, 1e-12));
        assert!(
            rigid_inverse(&t)
                .mul_mat4(&t)
                .abs_diff_eq(DMat4::IDENTITY, 1e-12)
        );
    }
}
