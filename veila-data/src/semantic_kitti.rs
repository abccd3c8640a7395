//! KITTI odometry and SemanticKITTI: `sequences/NN/{velodyne,labels,image_2}`, the per-sequence
//! `calib.txt` (`P0..P3`, `Tr`; no `R0_rect`, `Tr` already maps to the rectified camera 0 frame),
//! `.label` files (u32 per point: semantic class in the low 16 bits, instance id in the high 16 bits)
//! and the label map of `semantic-kitti.yaml` (raw ids -> train ids 0..19, colours in BGR order,
//! the official split).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use veila_geom::{LidarSensor, PinholeCamera};

use crate::atomic::write_atomic_with;
use crate::calib::CalibEntries;
use crate::dataset::{Dataset, Frame};
use crate::kitti::list_stems;
use crate::scan::read_kitti_records;
use crate::yaml::{self, Yaml};
use crate::{Error, Result};

/// SemanticKITTI raw class ids (the `labels:` table of `semantic-kitti.yaml`), the built-in
/// learning map and the class names: what the simulator labels its surfaces with, and what the
/// cross-modal metrics and segmentation read, with no label-map file at hand.
pub mod class {
    /// Unlabelled (sky and no-return pixels in the semantic maps).
    pub const UNLABELED: u16 = 0;
    /// Car (also vans with a continuous body, following the SemanticKITTI definition).
    pub const CAR: u16 = 10;
    /// Bicycle without a rider.
    pub const BICYCLE: u16 = 11;
    /// Bus.
    pub const BUS: u16 = 13;
    /// Truck (cabin separate from the cargo body).
    pub const TRUCK: u16 = 18;
    /// Other vehicle (trailers, caravans).
    pub const OTHER_VEHICLE: u16 = 20;
    /// Person.
    pub const PERSON: u16 = 30;
    /// Bicyclist (the rider together with the bicycle).
    pub const BICYCLIST: u16 = 31;
    /// Road.
    pub const ROAD: u16 = 40;
    /// Parking area.
    pub const PARKING: u16 = 44;
    /// Sidewalk (kerb included).
    pub const SIDEWALK: u16 = 48;
    /// Building.
    pub const BUILDING: u16 = 50;
    /// Fence (also guardrails and other low barriers).
    pub const FENCE: u16 = 51;
    /// Lane marking.
    pub const LANE_MARKING: u16 = 60;
    /// Vegetation (tree crowns, bushes, hedges).
    pub const VEGETATION: u16 = 70;
    /// Tree trunk.
    pub const TRUNK: u16 = 71;
    /// Terrain (grass, soil).
    pub const TERRAIN: u16 = 72;
    /// Pole.
    pub const POLE: u16 = 80;
    /// Traffic sign (the plate; its post is a pole).
    pub const TRAFFIC_SIGN: u16 = 81;
    /// Moving car.
    pub const MOVING_CAR: u16 = 252;
    /// Moving bicyclist.
    pub const MOVING_BICYCLIST: u16 = 253;
    /// Moving person.
    pub const MOVING_PERSON: u16 = 254;
    /// Moving bus.
    pub const MOVING_BUS: u16 = 257;
    /// Moving truck.
    pub const MOVING_TRUCK: u16 = 258;
    /// Moving other vehicle.
    pub const MOVING_OTHER_VEHICLE: u16 = 259;

    /// The `moving-*` id of a movable class, or the class itself when SemanticKITTI has none.
    pub fn moving(class: u16) -> u16 {
        match class {
            CAR => MOVING_CAR,
            BICYCLIST => MOVING_BICYCLIST,
            PERSON => MOVING_PERSON,
            BUS => MOVING_BUS,
            TRUCK => MOVING_TRUCK,
            OTHER_VEHICLE => MOVING_OTHER_VEHICLE,
            c => c,
        }
    }

    /// Number of classes of SemanticKITTI's learning map (0 = unlabelled / ignored, 1..=19 the
    /// evaluated classes).
    pub const NUM_LEARNING_CLASSES: usize = 20;

    /// SemanticKITTI's `learning_map` (raw id -> train id in `0..20`, `semantic-kitti.yaml`): moving
    /// classes fold into their static class, lane marking into road, bus into other-vehicle, ids
    /// without a train class (outliers, other-structure, other-object, unknown ids) into 0.
    pub fn learning_id(raw: u16) -> u8 {
        match raw {
            10 | 252 => 1,
            11 => 2,
            15 => 3,
            18 | 258 => 4,
            13 | 16 | 20 | 256 | 257 | 259 => 5,
            30 | 254 => 6,
            31 | 253 => 7,
            32 | 255 => 8,
            40 | 60 => 9,
            44 => 10,
            48 => 11,
            49 => 12,
            50 => 13,
            51 => 14,
            70 => 15,
            71 => 16,
            72 => 17,
            80 => 18,
            81 => 19,
            _ => 0,
        }
    }

    /// SemanticKITTI's `learning_map_inv` (`semantic-kitti.yaml`): the raw id each train id is
    /// written back as.
    pub const LEARNING_MAP_INV: [u16; NUM_LEARNING_CLASSES] = [
        0, 10, 11, 15, 18, 20, 30, 31, 32, 40, 44, 48, 49, 50, 51, 70, 71, 72, 80, 81,
    ];

    /// The name of each train id: that of its [`LEARNING_MAP_INV`] raw id in `semantic-kitti.yaml`.
    pub const LEARNING_NAMES: [&str; NUM_LEARNING_CLASSES] = [
        "unlabeled",
        "car",
        "bicycle",
        "motorcycle",
        "truck",
        "other-vehicle",
        "person",
        "bicyclist",
        "motorcyclist",
        "road",
        "parking",
        "sidewalk",
        "other-ground",
        "building",
        "fence",
        "vegetation",
        "trunk",
        "terrain",
        "pole",
        "traffic-sign",
    ];

    /// Whether `semantic-kitti.yaml`'s `learning_map` lists the raw id: those with a train class,
    /// and the four it maps to 0 (unlabeled, outlier, other-structure, other-object). A raw id it
    /// does not list is not a SemanticKITTI class (a label written under another label map).
    pub fn in_learning_map(raw: u16) -> bool {
        learning_id(raw) != 0 || matches!(raw, 0 | 1 | 52 | 99)
    }

    /// The class name used in `semantic-kitti.yaml`, or `None` for ids the simulator never emits.
    pub fn name(class: u16) -> Option<&'static str> {
        Some(match class {
            UNLABELED => "unlabeled",
            CAR => "car",
            BICYCLE => "bicycle",
            BUS => "bus",
            TRUCK => "truck",
            OTHER_VEHICLE => "other-vehicle",
            PERSON => "person",
            BICYCLIST => "bicyclist",
            ROAD => "road",
            PARKING => "parking",
            SIDEWALK => "sidewalk",
            BUILDING => "building",
            FENCE => "fence",
            LANE_MARKING => "lane-marking",
            VEGETATION => "vegetation",
            TRUNK => "trunk",
            TERRAIN => "terrain",
            POLE => "pole",
            TRAFFIC_SIGN => "traffic-sign",
            MOVING_CAR => "moving-car",
            MOVING_BICYCLIST => "moving-bicyclist",
            MOVING_PERSON => "moving-person",
            MOVING_BUS => "moving-bus",
            MOVING_TRUCK => "moving-truck",
            MOVING_OTHER_VEHICLE => "moving-other-vehicle",
            _ => return None,
        })
    }
}

/// Calibration of a KITTI odometry sequence (`sequences/NN/calib.txt`).
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryCalib {
    /// Projection matrices `P0..P3` (row-major 3x4).
    pub p: [[[f32; 4]; 3]; 4],
    /// `Tr`: velodyne to rectified camera 0 (row-major 3x4).
    pub tr: [[f32; 4]; 3],
    /// The file it was read from, named in the errors of [`OdometryCalib::camera`].
    pub source: PathBuf,
}

impl OdometryCalib {
    /// Parse `calib.txt` text (`path` names the source in errors).
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let e = CalibEntries::parse(text, path)?;
        let mut p = [[[0f32; 4]; 3]; 4];
        for (i, pi) in p.iter_mut().enumerate() {
            *pi = e.require_3x4(&[&format!("P{i}")], path)?;
        }
        let tr = e.require_3x4(&["Tr", "Tr_velo_to_cam"], path)?;
        crate::calib::check_rotation(path, "Tr", crate::calib::rotation_of(&tr))?;
        Ok(OdometryCalib {
            p,
            tr,
            source: path.to_path_buf(),
        })
    }

    /// Read `calib.txt`.
    pub fn read(path: &Path) -> Result<Self> {
        let text = crate::read_capped::read_metadata_string(
            path,
            crate::read_capped::MAX_CALIBRATION_BYTES,
            "a calibration file",
        )?;
        Self::parse(&text, path)
    }

    /// The pinhole camera of camera `index` (2 = `image_2`): `K = P{index}`, `cam_from_lidar = Tr`.
    pub fn camera(&self, index: usize, width: u32, height: u32) -> Result<PinholeCamera> {
        let p = *self.p.get(index).ok_or_else(|| Error::Invalid {
            what: "KITTI camera index".into(),
            message: format!("{index} is not one of 0..=3"),
        })?;
        PinholeCamera::from_kitti_odometry(p, self.tr, width, height).map_err(|e| {
            Error::format(
                &self.source,
                format!("P{index} gives an invalid camera: {e}"),
            )
        })
    }
}

/// The semantic class of a raw label (low 16 bits).
#[inline]
pub fn semantic_id(raw: u32) -> u16 {
    (raw & 0xFFFF) as u16
}

/// The instance id of a raw label (high 16 bits).
#[inline]
pub fn instance_id(raw: u32) -> u16 {
    (raw >> 16) as u16
}

/// Decode `.label` bytes. With `expected_points`, a different count is an error naming both numbers.
pub fn parse_labels(bytes: &[u8], expected_points: Option<usize>, path: &Path) -> Result<Vec<u32>> {
    if !bytes.len().is_multiple_of(4) {
        return Err(Error::format(
            path,
            format!(
                "length {} bytes is not a multiple of 4 (u32 per point); truncated?",
                bytes.len()
            ),
        ));
    }
    let labels: Vec<u32> = bytes
        .chunks_exact(4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    if let Some(n) = expected_points
        && labels.len() != n
    {
        return Err(Error::Mismatch {
            context: path.display().to_string(),
            message: format!(
                "{} labels but the scan has {n} points ({} labels)",
                labels.len(),
                if labels.len() > n { "more" } else { "fewer" }
            ),
        });
    }
    Ok(labels)
}

/// Read a `.label` file; see [`parse_labels`].
pub fn read_labels(path: &Path, expected_points: Option<usize>) -> Result<Vec<u32>> {
    let bytes = crate::read_capped::read_metadata(
        path,
        crate::read_capped::MAX_LABEL_FILE_BYTES,
        "a `.label` file",
    )?;
    parse_labels(&bytes, expected_points, path)
}

/// Raw labels as the bytes of a `.label` file (one little-endian `u32` per point).
pub fn encode_labels(labels: &[u32]) -> Vec<u8> {
    labels.iter().flat_map(|l| l.to_le_bytes()).collect()
}

/// Write raw labels as a `.label` file, atomically.
pub fn write_labels(path: &Path, labels: &[u32]) -> Result<()> {
    let bytes = encode_labels(labels);
    write_atomic_with(path, |w| std::io::Write::write_all(w, &bytes))
}

/// The official SemanticKITTI split (sequence numbers).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Split {
    /// Training sequences.
    pub train: Vec<u32>,
    /// Validation sequences.
    pub valid: Vec<u32>,
    /// Test sequences (no labels).
    pub test: Vec<u32>,
}

/// Which part of the split.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SplitPart {
    /// Training sequences.
    Train,
    /// Validation sequences.
    Valid,
    /// Test sequences.
    Test,
}

impl Split {
    /// The sequences of one part.
    pub fn sequences(&self, part: SplitPart) -> &[u32] {
        match part {
            SplitPart::Train => &self.train,
            SplitPart::Valid => &self.valid,
            SplitPart::Test => &self.test,
        }
    }
}

/// The label definitions of `semantic-kitti.yaml`.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelMap {
    /// Raw class id -> name.
    pub names: BTreeMap<u16, String>,
    /// Raw class id -> colour as the file stores it, **BGR** order.
    pub color_bgr: BTreeMap<u16, [u8; 3]>,
    /// Raw class id -> train id (0 = ignored / unlabeled).
    pub learning_map: BTreeMap<u16, u8>,
    /// Train id -> representative raw class id.
    pub learning_map_inv: BTreeMap<u8, u16>,
    /// Train id -> ignored in training / evaluation.
    pub learning_ignore: BTreeMap<u8, bool>,
    /// The official split.
    pub split: Split,
    lut: Vec<u8>,
}

fn yaml_int_map(root: &Yaml, key: &str, path: &Path) -> Result<Vec<(u64, Yaml)>> {
    let Some(Yaml::Map(entries)) = root.get(key) else {
        return Err(Error::format(
            path,
            format!("label map has no `{key}` mapping"),
        ));
    };
    entries
        .iter()
        .map(|(k, v)| {
            k.parse::<u64>()
                .map(|k| (k, v.clone()))
                .map_err(|_| Error::format(path, format!("`{key}`: key `{k}` is not an integer")))
        })
        .collect()
}

fn scalar_int(v: &Yaml, what: &str, max: u64, path: &Path) -> Result<u64> {
    match v {
        Yaml::Scalar(s) => s.parse::<u64>().ok().filter(|x| *x <= max).ok_or_else(|| {
            Error::format(
                path,
                format!("{what}: `{s}` is not an integer in 0..={max}"),
            )
        }),
        other => Err(Error::format(
            path,
            format!("{what}: expected an integer, found {other:?}"),
        )),
    }
}

impl LabelMap {
    /// Parse the text of `semantic-kitti.yaml` (`path` names the source in errors).
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let root = yaml::parse(text, path)?;
        let key16 = |k: u64, what: &str| -> Result<u16> {
            u16::try_from(k)
                .map_err(|_| Error::format(path, format!("{what}: id {k} exceeds 65535")))
        };
        let mut names = BTreeMap::new();
        for (k, v) in yaml_int_map(&root, "labels", path)? {
            let Yaml::Scalar(name) = v else {
                return Err(Error::format(
                    path,
                    format!("labels: entry {k} is not a name"),
                ));
            };
            names.insert(key16(k, "labels")?, name);
        }
        let mut color_bgr = BTreeMap::new();
        for (k, v) in yaml_int_map(&root, "color_map", path)? {
            let what = format!("color_map entry {k}");
            let Yaml::Seq(items) = &v else {
                return Err(Error::format(path, format!("{what}: expected [b, g, r]")));
            };
            if items.len() != 3 {
                return Err(Error::format(
                    path,
                    format!("{what}: expected 3 values, found {}", items.len()),
                ));
            }
            let mut c = [0u8; 3];
            for (ci, item) in c.iter_mut().zip(items) {
                *ci = scalar_int(item, &what, 255, path)? as u8;
            }
            color_bgr.insert(key16(k, "color_map")?, c);
        }
        let mut learning_map = BTreeMap::new();
        for (k, v) in yaml_int_map(&root, "learning_map", path)? {
            let t = scalar_int(&v, &format!("learning_map entry {k}"), 255, path)? as u8;
            learning_map.insert(key16(k, "learning_map")?, t);
        }
        let mut learning_map_inv = BTreeMap::new();
        for (k, v) in yaml_int_map(&root, "learning_map_inv", path)? {
            let k = u8::try_from(k).map_err(|_| {
                Error::format(path, format!("learning_map_inv: train id {k} exceeds 255"))
            })?;
            let raw = scalar_int(&v, &format!("learning_map_inv entry {k}"), 65535, path)? as u16;
            learning_map_inv.insert(k, raw);
        }
        let mut learning_ignore = BTreeMap::new();
        if root.get("learning_ignore").is_some() {
            for (k, v) in yaml_int_map(&root, "learning_ignore", path)? {
                let b = match &v {
                    Yaml::Scalar(s) if s.eq_ignore_ascii_case("true") => true,
                    Yaml::Scalar(s) if s.eq_ignore_ascii_case("false") => false,
                    other => {
                        return Err(Error::format(
                            path,
                            format!(
                                "learning_ignore entry {k}: expected True/False, found {other:?}"
                            ),
                        ));
                    }
                };
                let k = u8::try_from(k).map_err(|_| {
                    Error::format(path, format!("learning_ignore: id {k} exceeds 255"))
                })?;
                learning_ignore.insert(k, b);
            }
        }
        let mut split = Split::default();
        if let Some(s) = root.get("split") {
            for (part, out) in [
                ("train", &mut split.train),
                ("valid", &mut split.valid),
                ("test", &mut split.test),
            ] {
                match s.get(part) {
                    Some(Yaml::Seq(items)) => {
                        for it in items {
                            out.push(scalar_int(it, &format!("split.{part}"), 9999, path)? as u32);
                        }
                    }
                    Some(Yaml::Null) | None => {}
                    Some(other) => {
                        return Err(Error::format(
                            path,
                            format!("split.{part}: expected a list, found {other:?}"),
                        ));
                    }
                }
            }
        }
        // consistency: every learning_map target must be a known train id
        for (raw, t) in &learning_map {
            if *t != 0 && !learning_map_inv.contains_key(t) {
                return Err(Error::format(
                    path,
                    format!(
                        "learning_map maps {raw} to train id {t}, which learning_map_inv lacks"
                    ),
                ));
            }
        }
        let mut lut = vec![0u8; 1 << 16];
        for (raw, t) in &learning_map {
            lut[*raw as usize] = *t;
        }
        Ok(LabelMap {
            names,
            color_bgr,
            learning_map,
            learning_map_inv,
            learning_ignore,
            split,
            lut,
        })
    }

    /// Read `semantic-kitti.yaml`.
    pub fn read(path: &Path) -> Result<Self> {
        let text = crate::read_capped::read_metadata_string(
            path,
            crate::read_capped::MAX_CONFIG_BYTES,
            "a label map",
        )?;
        Self::parse(&text, path)
    }

    /// Number of train classes including 0 (`max(learning_map_inv) + 1`, 20 for SemanticKITTI).
    pub fn num_classes(&self) -> usize {
        self.learning_map_inv
            .keys()
            .next_back()
            .map_or(1, |k| *k as usize + 1)
    }

    /// Train id of a raw label (the instance bits are ignored); unknown classes map to 0.
    #[inline]
    pub fn train_id(&self, raw: u32) -> u8 {
        self.lut[(raw & 0xFFFF) as usize]
    }

    /// Train ids of many raw labels.
    pub fn train_ids(&self, raw: &[u32]) -> Vec<u8> {
        raw.iter().map(|r| self.train_id(*r)).collect()
    }

    /// Histogram of train ids (length [`LabelMap::num_classes`]).
    pub fn train_histogram(&self, raw: &[u32]) -> Vec<u64> {
        let mut h = vec![0u64; self.num_classes().max(256)];
        for r in raw {
            h[self.train_id(*r) as usize] += 1;
        }
        h.truncate(self.num_classes());
        h
    }

    /// Display colour (**RGB**) of a raw label; black for unknown classes.
    pub fn color_rgb(&self, raw: u32) -> [u8; 3] {
        self.color_bgr
            .get(&semantic_id(raw))
            .map_or([0, 0, 0], |[b, g, r]| [*r, *g, *b])
    }

    /// Display colour (**RGB**) of a train id, through its representative raw class.
    pub fn train_color_rgb(&self, train_id: u8) -> [u8; 3] {
        self.learning_map_inv
            .get(&train_id)
            .map_or([0, 0, 0], |raw| self.color_rgb(u32::from(*raw)))
    }

    /// Name of a train id (the name of its representative raw class).
    pub fn train_name(&self, train_id: u8) -> Option<&str> {
        self.learning_map_inv
            .get(&train_id)
            .and_then(|raw| self.names.get(raw))
            .map(String::as_str)
    }
}

/// Which sequences a [`SemanticKittiDataset`] holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Sequences {
    /// Every `sequences/NN` folder present.
    All,
    /// One part of the official split (needs the label map); sequences of the part that are not on
    /// disk are skipped (a partial download), but at least one must be present.
    Split(SplitPart),
    /// An explicit list; every listed sequence must be present.
    List(Vec<u32>),
}

#[derive(Debug, Clone)]
struct SeqInfo {
    dir: PathBuf,
    calib: Option<OdometryCalib>,
}

/// KITTI odometry / SemanticKITTI, read lazily. Frame ids are `NN/NNNNNN`.
#[derive(Debug, Clone)]
pub struct SemanticKittiDataset {
    seqs: Vec<SeqInfo>,
    frames: Vec<(usize, String)>,
    label_map: Option<LabelMap>,
    load_images: bool,
    require_labels: bool,
}

impl SemanticKittiDataset {
    /// Open the dataset root (the folder holding `sequences/`). The label map is looked up as
    /// `ROOT/semantic-kitti.yaml`, then `ROOT/../semantic-kitti.yaml` (absent is allowed: labels then
    /// stay raw). Calibration of every selected sequence is read now; scans, labels and images lazily.
    pub fn open(root: &Path, sequences: Sequences) -> Result<Self> {
        let map_path = [
            root.join("semantic-kitti.yaml"),
            root.join("../semantic-kitti.yaml"),
        ]
        .into_iter()
        .find(|p| p.is_file());
        let label_map = map_path.map(|p| LabelMap::read(&p)).transpose()?;
        Self::open_with_label_map(root, sequences, label_map)
    }

    /// As [`SemanticKittiDataset::open`] with an explicit label map.
    pub fn open_with_label_map(
        root: &Path,
        sequences: Sequences,
        label_map: Option<LabelMap>,
    ) -> Result<Self> {
        let seq_root = root.join("sequences");
        if !seq_root.is_dir() {
            return Err(Error::format(
                root,
                "not a KITTI odometry folder: sequences/ does not exist",
            ));
        }
        let wanted: Option<Vec<u32>> = match &sequences {
            Sequences::All => None,
            Sequences::List(l) => Some(l.clone()),
            Sequences::Split(part) => {
                let map = label_map.as_ref().ok_or_else(|| Error::Invalid {
                    what: "sequence selection".into(),
                    message: "selecting by split needs semantic-kitti.yaml".into(),
                })?;
                Some(map.split.sequences(*part).to_vec())
            }
        };
        let mut present: Vec<(u32, PathBuf)> = Vec::new();
        for entry in std::fs::read_dir(&seq_root).map_err(|e| Error::io(&seq_root, e))? {
            let entry = entry.map_err(|e| Error::io(&seq_root, e))?;
            let name = entry.file_name().to_string_lossy().to_string();
            if let Ok(n) = name.parse::<u32>()
                && entry.path().join("velodyne").is_dir()
            {
                present.push((n, entry.path()));
            }
        }
        present.sort();
        if let (Some(w), Sequences::List(_)) = (&wanted, &sequences) {
            for s in w {
                if !present.iter().any(|(n, _)| n == s) {
                    return Err(Error::format(
                        &seq_root,
                        format!(
                            "sequence {s:02} was requested but sequences/{s:02}/velodyne does not exist"
                        ),
                    ));
                }
            }
        }
        let mut seqs = Vec::new();
        let mut frames = Vec::new();
        for (n, dir) in present {
            if wanted.as_ref().is_some_and(|w| !w.contains(&n)) {
                continue;
            }
            // a velodyne-only download has no calib.txt: frames then carry no camera
            let calib_path = dir.join("calib.txt");
            let calib = if calib_path.exists() {
                Some(OdometryCalib::read(&calib_path)?)
            } else {
                None
            };
            let si = seqs.len();
            for stem in list_stems(&dir.join("velodyne"), ".bin")? {
                frames.push((si, stem));
            }
            seqs.push(SeqInfo { dir, calib });
        }
        if seqs.is_empty()
            && let Some(w) = &wanted
        {
            let list: Vec<String> = w.iter().map(|n| format!("{n:02}")).collect();
            return Err(Error::format(
                &seq_root,
                format!(
                    "none of the selected sequences ({}) is present",
                    list.join(", ")
                ),
            ));
        }
        Ok(SemanticKittiDataset {
            seqs,
            frames,
            label_map,
            load_images: true,
            require_labels: false,
        })
    }

    /// Decode camera images when loading frames (default true).
    pub fn with_images(mut self, load: bool) -> Self {
        self.load_images = load;
        self
    }

    /// Fail when a frame has no `.label` file (default false: such frames carry no labels).
    pub fn with_required_labels(mut self, require: bool) -> Self {
        self.require_labels = require;
        self
    }

    /// The label map, when `semantic-kitti.yaml` was found or given.
    pub fn label_map(&self) -> Option<&LabelMap> {
        self.label_map.as_ref()
    }

    fn seq_name(&self, index: usize) -> String {
        let (si, _) = &self.frames[index];
        self.seqs[*si]
            .dir
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default()
    }

    /// The scan, label and image paths of frame `index`.
    pub fn paths(&self, index: usize) -> (PathBuf, PathBuf, PathBuf) {
        let (si, stem) = &self.frames[index];
        let dir = &self.seqs[*si].dir;
        (
            dir.join("velodyne").join(format!("{stem}.bin")),
            dir.join("labels").join(format!("{stem}.label")),
            dir.join("image_2").join(format!("{stem}.png")),
        )
    }

    /// Calibration of the sequence of frame `index` (`None` when the sequence has no `calib.txt`).
    pub fn calib(&self, index: usize) -> Option<&OdometryCalib> {
        self.seqs[self.frames[index].0].calib.as_ref()
    }
}

impl Dataset for SemanticKittiDataset {
    fn name(&self) -> &'static str {
        crate::dataset::DatasetName::SemanticKitti.as_str()
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn frame_id(&self, index: usize) -> String {
        format!("{}/{}", self.seq_name(index), self.frames[index].1)
    }
    fn load(&self, index: usize) -> Result<Frame> {
        let (scan_path, label_path, image_path) = self.paths(index);
        // labels are aligned with the raw records, so attach them before non-finite points are dropped
        let mut cloud = read_kitti_records(&scan_path)?;
        if label_path.is_file() {
            cloud.label = Some(read_labels(&label_path, Some(cloud.len()))?);
        } else if self.require_labels {
            return Err(Error::io(
                &label_path,
                std::io::Error::new(std::io::ErrorKind::NotFound, "label file is missing"),
            ));
        }
        let dropped_non_finite = cloud.retain_finite();
        let camera_and_image =
            if let (true, Some(calib)) = (image_path.is_file(), self.calib(index)) {
                let (image, (w, h)) =
                    crate::image_io::read_rgb_image_if(&image_path, self.load_images)?;
                Some((image, calib.camera(2, w, h)?))
            } else {
                None
            };
        let (image, camera) = match camera_and_image {
            Some((i, c)) => (i, Some(c)),
            None => (None, None),
        };
        Ok(Frame {
            id: self.frame_id(index),
            points: cloud,
            dropped_non_finite,
            scan_path,
            image_path: camera.map(|_| image_path),
            image,
            camera,
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
        let (scan, label, image) = self.paths(index);
        let calib = self.seqs[self.frames[index].0].dir.join("calib.txt");
        Ok(vec![scan, label, image, calib])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const YAML: &str = "labels:\n  0 : \"unlabeled\"\n  10: \"car\"\n  252: \"moving-car\"\ncolor_map: # bgr\n  0 : [0, 0, 0]\n  10: [245, 150, 100]\n  252: [245, 150, 100]\nlearning_map:\n  0 : 0\n  10: 1     # car\n  252: 1\nlearning_map_inv:\n  0: 0\n  1: 10\nlearning_ignore:\n  0: True\n  1: False\nsplit:\n  train:\n    - 0\n  valid:\n    - 8\n  test:\n    - 11\n";

    #[test]
    fn label_map_maps_ignores_instance_bits_and_swaps_bgr() {
        let m = LabelMap::parse(YAML, Path::new("s.yaml")).unwrap();
        assert_eq!(m.num_classes(), 2);
        assert_eq!(m.train_id(252 | (17 << 16)), 1);
        assert_eq!(m.train_id(10), 1);
        assert_eq!(m.train_id(999), 0);
        assert_eq!(m.color_rgb(10), [100, 150, 245]);
        assert_eq!(m.train_color_rgb(1), [100, 150, 245]);
        assert_eq!(m.split.valid, vec![8]);
        assert_eq!(
            m.train_histogram(&[0, 10, 252, 7, 10 | (3 << 16)]),
            vec![2, 3]
        );
        assert_eq!(m.train_name(1), Some("car"));
    }

    #[test]
    fn label_map_rejects_inconsistent_maps() {
        let bad = YAML.replace("  252: 1\nlearning_map_inv", "  252: 7\nlearning_map_inv");
        let e = LabelMap::parse(&bad, Path::new("s.yaml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("train id 7"), "{e}");
        let bad = YAML.replace("10: [245, 150, 100]", "10: [245, 150]");
        assert!(LabelMap::parse(&bad, Path::new("s.yaml")).is_err());
        let bad = YAML.replace("10: [245, 150, 100]", "10: [245, 150, 300]");
        assert!(LabelMap::parse(&bad, Path::new("s.yaml")).is_err());
    }

    #[test]
    fn label_counts_must_match() {
        let bytes: Vec<u8> = [1u32, 2, 3].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(
            parse_labels(&bytes, Some(3), Path::new("a.label")).unwrap(),
            vec![1, 2, 3]
        );
        let e = parse_labels(&bytes, Some(4), Path::new("a.label"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("a.label")
                && e.contains("3 labels")
                && e.contains("4 points")
                && e.contains("fewer"),
            "{e}"
        );
        let e = parse_labels(&bytes, Some(2), Path::new("a.label"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("more"), "{e}");
        assert!(parse_labels(&bytes[..5], None, Path::new("a.label")).is_err());
    }

    #[test]
    fn odometry_calib_needs_tr() {
        let txt = "P0: 1 0 0 0 0 1 0 0 0 0 1 0\nP1: 1 0 0 0 0 1 0 0 0 0 1 0\nP2: 1 0 0 0 0 1 0 0 0 0 1 0\nP3: 1 0 0 0 0 1 0 0 0 0 1 0\n";
        let e = OdometryCalib::parse(txt, Path::new("calib.txt"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("calib.txt") && e.contains("Tr"), "{e}");
        let ok = format!("{txt}Tr: 0 -1 0 0 0 0 -1 0 1 0 0 0\n");
        let c = OdometryCalib::parse(&ok, Path::new("calib.txt")).unwrap();
        assert_eq!(c.tr[2][0], 1.0);
    }
}
