//! The frames a dataset generation reads: a KITTI-layout folder (`image_2/NAME.png` with
//! `calib/NAME.txt`, read by [`load_view`] and so by the one calibration reader) or converted
//! shards (`manifest.json` and the shards it lists; every frame carries its images and cameras).
//!
//! Each frame has a name, the stem of its output files (`velodyne/NAME.bin`): a KITTI frame's
//! image stem, a shard frame's id with every character outside `A-Z a-z 0-9 . _ -` written `_`
//! (SemanticKITTI's `08/000123` is `08_000123`). Two frames of one name are an error.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use veila_data::ShardReader;
use veila_data::image::RgbImage;
use veila_data::kitti::{CameraFrame, list_camera_frames};
use veila_data::shard::{MANIFEST_FILE, Manifest, ShardSample};
use veila_geom::PinholeCamera;

use crate::app::rig::load_view;
use crate::error::{Error, Result};

/// The most frames one generated dataset holds (about a million; SemanticKITTI has 43 552 scans,
/// nuScenes 390 000 sweeps): its manifest lists them all, so it stays bounded.
pub const MAX_FRAMES: usize = 1 << 20;

/// The longest frame name, in bytes.
pub const MAX_NAME_BYTES: usize = 128;

/// Where frames come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceKind {
    /// A KITTI-layout folder: `image_2/NAME.png` and `calib/NAME.txt`.
    KittiLayout,
    /// Converted shards (`veila convert`): `manifest.json` and its shards.
    Shards,
}

impl SourceKind {
    /// How manifests name it: `kitti-layout` or `shards`.
    pub fn as_str(self) -> &'static str {
        match self {
            SourceKind::KittiLayout => "kitti-layout",
            SourceKind::Shards => "shards",
        }
    }
}

/// One frame read: the file it came from (for errors) and its cameras, each an image at the
/// resolution its camera describes.
#[derive(Debug, Clone)]
pub struct LoadedFrame {
    /// The image (KITTI layout) or shard file the frame was read from.
    pub origin: PathBuf,
    /// The rig's cameras, the first camera first.
    pub views: Vec<(RgbImage, PinholeCamera)>,
}

#[derive(Debug)]
enum Frames {
    Kitti(Vec<CameraFrame>),
    Shards(Box<ShardFrames>),
}

/// The frames of converted shards.
#[derive(Debug)]
struct ShardFrames {
    dir: PathBuf,
    manifest: Manifest,
    /// `(shard, sample)` of every frame, in order.
    at: Vec<(usize, usize)>,
    /// The shard read last (frames are read in order: one header read per shard).
    open: Mutex<Option<(usize, ShardReader)>>,
    /// The most cameras a frame of these shards has.
    views: usize,
}

/// The frames of a KITTI-layout folder or of converted shards, in order, with their names; a frame
/// is read only when asked for ([`FrameSource::load`]).
#[derive(Debug)]
pub struct FrameSource {
    dir: PathBuf,
    kind: SourceKind,
    names: Vec<String>,
    frames: Frames,
}

/// The file stem of frame `id`: every character outside `A-Z a-z 0-9 . _ -` becomes `_`, and a
/// leading `.` too (no hidden or `..` names).
pub fn frame_name(id: &str) -> String {
    id.chars()
        .enumerate()
        .map(|(i, c)| {
            let keep = c.is_ascii_alphanumeric() || c == '_' || c == '-' || (c == '.' && i > 0);
            if keep { c } else { '_' }
        })
        .collect()
}

impl FrameSource {
    /// Opens `dir`: converted shards when it holds `manifest.json` (every shard's header is
    /// checked against it), else a KITTI-layout folder (`image_2/` and `calib/`, or under
    /// `training/`). Only listings and headers are read. Errors name the folder or file.
    pub fn open(dir: &Path) -> Result<Self> {
        if !dir.is_dir() {
            return Err(Error::Input {
                path: dir.to_path_buf(),
                reason: "not a folder (--frames takes a KITTI-layout folder with image_2/ and \
                         calib/, or a folder of converted shards with manifest.json)"
                    .into(),
            });
        }
        let manifest_path = dir.join(MANIFEST_FILE);
        let (kind, ids, frames) = if manifest_path.exists() {
            let manifest = Manifest::read(&manifest_path)?;
            let mut ids = Vec::with_capacity(manifest.count.min(MAX_FRAMES));
            let mut at = Vec::with_capacity(manifest.count.min(MAX_FRAMES));
            let mut views = 0;
            for (s, entry) in manifest.shards.iter().enumerate() {
                if ids.len() + entry.ids.len() > MAX_FRAMES {
                    return Err(too_many(&manifest_path, manifest.count));
                }
                ids.extend(entry.ids.iter().cloned());
                at.extend((0..entry.ids.len()).map(|k| (s, k)));
                views = views.max(shard_views(dir, &manifest, s)?);
            }
            let frames = Frames::Shards(Box::new(ShardFrames {
                dir: dir.to_path_buf(),
                manifest,
                at,
                open: Mutex::new(None),
                views,
            }));
            (SourceKind::Shards, ids, frames)
        } else {
            let list = list_camera_frames(dir)?;
            if list.len() > MAX_FRAMES {
                return Err(too_many(dir, list.len()));
            }
            let ids = list.iter().map(|f| f.name.clone()).collect();
            (SourceKind::KittiLayout, ids, Frames::Kitti(list))
        };
        if ids.is_empty() {
            return Err(Error::Input {
                path: dir.to_path_buf(),
                reason: "holds no frames".into(),
            });
        }
        let names = unique_names(dir, &ids)?;
        Ok(FrameSource {
            dir: dir.to_path_buf(),
            kind,
            names,
            frames,
        })
    }

    /// The folder it reads.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// KITTI layout or shards.
    pub fn kind(&self) -> SourceKind {
        self.kind
    }

    /// The frames' names, in order.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// Whether there are no frames (never, for an opened source).
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// Refuses a model that takes more cameras than these frames have (a KITTI-layout folder
    /// gives `image_2` alone).
    pub fn check_views(&self, model_views: usize) -> Result<()> {
        let have = match &self.frames {
            Frames::Kitti(_) => 1,
            Frames::Shards(s) => s.views,
        };
        if have == 0 {
            return Err(Error::Input {
                path: self.dir.clone(),
                reason: "the shards hold no camera images: convert the dataset with images \
                         (`veila convert` without --no-images)"
                    .into(),
            });
        }
        if model_views > have {
            let how = match self.kind {
                SourceKind::KittiLayout => {
                    "a KITTI-layout folder gives image_2 alone; convert the dataset with its \
                     cameras (`veila convert --camera ...`) and generate from the shards"
                }
                SourceKind::Shards => {
                    "convert the dataset with more cameras (`veila convert --camera \
                     CAM_FRONT,CAM_FRONT_LEFT,CAM_FRONT_RIGHT`)"
                }
            };
            return Err(Error::Input {
                path: self.dir.clone(),
                reason: format!(
                    "the model takes {model_views} camera views, these frames have {have}: {how}"
                ),
            });
        }
        Ok(())
    }

    /// Reads frame `k` with its first `views` cameras. Errors name the image, calibration or
    /// shard and the frame.
    pub fn load(&self, k: usize, views: usize) -> Result<LoadedFrame> {
        match &self.frames {
            Frames::Kitti(list) => {
                let f = &list[k];
                let v = load_view(&f.image, &f.calib, None)?;
                Ok(LoadedFrame {
                    origin: v.image_path,
                    views: vec![(v.image, v.camera)],
                })
            }
            Frames::Shards(shards) => {
                let (s, j) = shards.at[k];
                let path = shards.manifest.shard_path(&shards.dir, s)?;
                let mut open = shards.open.lock().unwrap_or_else(|e| e.into_inner());
                if open.as_ref().is_none_or(|(o, _)| *o != s) {
                    *open = Some((s, ShardReader::open(&path)?));
                }
                let (_, reader) = open.as_ref().expect("opened above");
                let sample = reader.sample(j)?;
                drop(open);
                shard_views_of(&sample, views)
                    .map_err(|reason| Error::Input {
                        path: path.clone(),
                        reason: format!("frame `{}`: {reason}", sample.id),
                    })
                    .map(|views| LoadedFrame {
                        origin: path,
                        views,
                    })
            }
        }
    }
}

fn too_many(path: &Path, n: usize) -> Error {
    Error::Input {
        path: path.to_path_buf(),
        reason: format!("{n} frames: more than the {MAX_FRAMES} one generated dataset holds"),
    }
}

/// The output names of `ids`, checked: not empty, not too long, no two alike.
fn unique_names(dir: &Path, ids: &[String]) -> Result<Vec<String>> {
    let mut seen: HashMap<String, &str> = HashMap::with_capacity(ids.len());
    let mut names = Vec::with_capacity(ids.len());
    for id in ids {
        let name = frame_name(id);
        let bad = |reason: String| Error::Input {
            path: dir.to_path_buf(),
            reason,
        };
        if name.is_empty() || name.len() > MAX_NAME_BYTES {
            return Err(bad(format!(
                "frame id `{}`: a frame name is 1 to {MAX_NAME_BYTES} bytes",
                id.escape_debug()
            )));
        }
        if let Some(other) = seen.insert(name.clone(), id) {
            return Err(bad(format!(
                "frames `{}` and `{}` would both be written as `{name}`",
                other.escape_debug(),
                id.escape_debug()
            )));
        }
        names.push(name);
    }
    Ok(names)
}

/// How many cameras the frames of shard `s` carry (from its header: the tensors of sample 0).
fn shard_views(dir: &Path, manifest: &Manifest, s: usize) -> Result<usize> {
    if manifest.shards[s].ids.is_empty() {
        return Ok(0);
    }
    let reader = ShardReader::open(&manifest.shard_path(dir, s)?)?;
    Ok(reader.cameras(0))
}

/// The cameras of a shard sample, the first `views` of them.
fn shard_views_of(
    s: &ShardSample,
    views: usize,
) -> std::result::Result<Vec<(RgbImage, PinholeCamera)>, String> {
    let (Some(image), Some(matrices)) = (&s.image, &s.camera) else {
        return Err(
            "has no camera image or camera matrices (convert the dataset with images: \
                    `veila convert` without --no-images)"
                .into(),
        );
    };
    let mut out = Vec::with_capacity(views);
    let (w, h) = image.dimensions();
    let camera = matrices
        .to_camera(w, h)
        .map_err(|e| format!("invalid camera: {e}"))?;
    out.push((image.clone(), camera));
    for (j, v) in s
        .extra_views
        .iter()
        .take(views.saturating_sub(1))
        .enumerate()
    {
        let (w, h) = v.image.dimensions();
        let camera = v
            .camera
            .to_camera(w, h)
            .map_err(|e| format!("invalid camera of view {}: {e}", j + 1))?;
        out.push((v.image.clone(), camera));
    }
    if out.len() < views {
        return Err(format!(
            "has {} camera(s), the model takes {views}",
            out.len()
        ));
    }
    Ok(out)
}
