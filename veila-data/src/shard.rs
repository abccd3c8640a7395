//! Training shards: safetensors files of range images, camera images and camera matrices, with the
//! sensor in the metadata, listed in a JSON manifest with per-shard SHA-256 checksums.
//!
//! # Layout of one shard
//!
//! Sample `k` of a shard (`k` = 0, 1, ... as a 5-digit number) holds the tensors
//!
//! | name                  | dtype | shape       | content                                           |
//! |-----------------------|-------|-------------|---------------------------------------------------|
//! | `NNNNN/range_m`       | F32   | `[h, w]`    | range in metres, 0 where empty                    |
//! | `NNNNN/intensity`     | F32   | `[h, w]`    | intensity scaled to `[0, 1]`, 0 where empty       |
//! | `NNNNN/mask`          | U8    | `[h, w]`    | 1 where the pixel holds a return                  |
//! | `NNNNN/label`         | U8    | `[h, w]`    | train id 0..19 (when a label map is known)        |
//! | `NNNNN/label_raw`     | U32   | `[h, w]`    | raw dataset label (when the dataset has labels)   |
//! | `NNNNN/image`         | U8    | `[H, W, 3]` | the camera image, RGB                             |
//! | `NNNNN/intrinsics`    | F32   | `[3, 4]`    | `K`, row-major                                    |
//! | `NNNNN/cam_from_lidar`| F32   | `[4, 4]`    | `T`, row-major                                    |
//! | `NNNNN/viewJ/...`     |       |             | further cameras `J` = 1, 2, ...: `image`, `intrinsics`, `cam_from_lidar` as above |
//!
//! and the string metadata `format` ([`SHARD_FORMAT`]), `sensor` (JSON of [`LidarSensor`]), `count`,
//! `ids` (JSON list of frame ids) and `dataset`.

use std::io::Read;
use std::path::Path;

use glam::Mat4;
use image::RgbImage;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use veila_geom::{LidarSensor, PinholeCamera, RangeImage};

use crate::atomic::write_atomic_with;
use crate::{Error, Result};

/// The `format` metadata of every shard.
pub const SHARD_FORMAT: &str = "veila-shard/1";
/// The `format` field of every manifest.
pub const MANIFEST_FORMAT: &str = "veila-manifest/1";

/// One training sample.
#[derive(Debug, Clone, PartialEq)]
pub struct ShardSample {
    /// Frame id in its dataset.
    pub id: String,
    /// The range image on the shard's sensor grid: range in metres, intensity in `[0, 1]`, the
    /// return mask, and the raw dataset labels in `label` when the dataset has them (read back
    /// without source points: `point_index` is [`veila_geom::NO_POINT`]).
    pub scan: RangeImage,
    /// Train ids per pixel (0 = ignored), when a label map is known.
    pub train_ids: Option<Vec<u8>>,
    /// Camera image.
    pub image: Option<RgbImage>,
    /// `K` (3x4, row-major) and `cam_from_lidar` (4x4, row-major).
    pub camera: Option<CameraMatrices>,
    /// The rig's further cameras (nuScenes' side cameras, KITTI's `image_3`), in order.
    pub extra_views: Vec<ShardView>,
}

/// A further camera of a [`ShardSample`] (stored as `NNNNN/view{j}/image`,
/// `NNNNN/view{j}/intrinsics` and `NNNNN/view{j}/cam_from_lidar`, `j` = 1, 2, ...).
#[derive(Debug, Clone, PartialEq)]
pub struct ShardView {
    /// The image, RGB.
    pub image: RgbImage,
    /// Its camera matrices.
    pub camera: CameraMatrices,
}

/// Camera matrices as stored in a shard.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraMatrices {
    /// `K`, row-major 3x4.
    pub intrinsics: [[f32; 4]; 3],
    /// `T` (camera from LiDAR), row-major 4x4.
    pub cam_from_lidar: [[f32; 4]; 4],
}

impl CameraMatrices {
    /// From a pinhole camera.
    pub fn from_camera(c: &PinholeCamera) -> Self {
        let k = c.intrinsics.transpose().to_cols_array_2d();
        CameraMatrices {
            intrinsics: [k[0], k[1], k[2]],
            cam_from_lidar: c.cam_from_lidar.transpose().to_cols_array_2d(),
        }
    }

    /// Back to a pinhole camera for an image of `width x height`. The matrices come from a file (a
    /// shard), so they are checked as a calibration is
    /// ([`PinholeCamera::from_calibration`]: positive focal lengths, the principal point in the
    /// image, sane offsets).
    pub fn to_camera(&self, width: u32, height: u32) -> Result<PinholeCamera> {
        let t = Mat4::from_cols_array_2d(&self.cam_from_lidar).transpose();
        Ok(PinholeCamera::from_calibration(
            self.intrinsics,
            t,
            width,
            height,
        )?)
    }
}

/// A shard read back.
#[derive(Debug, Clone, PartialEq)]
pub struct Shard {
    /// The sensor of every range image.
    pub sensor: LidarSensor,
    /// The dataset name.
    pub dataset: String,
    /// The samples, in order.
    pub samples: Vec<ShardSample>,
}

struct OwnedTensor {
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

/// Tensors in file order, with their names.
type NamedTensors = Vec<(String, OwnedTensor)>;

fn dtype_name(d: Dtype) -> &'static str {
    match d {
        Dtype::U8 => "U8",
        Dtype::U32 => "U32",
        _ => "F32",
    }
}

fn bytes_f32(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}
fn bytes_u32(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// `intrinsics` and `cam_from_lidar` of a camera as (name, shape, f32 bytes).
fn camera_tensors(c: &CameraMatrices) -> [(&'static str, Vec<usize>, Vec<u8>); 2] {
    let k: Vec<f32> = c.intrinsics.iter().flatten().copied().collect();
    let t: Vec<f32> = c.cam_from_lidar.iter().flatten().copied().collect();
    [
        ("intrinsics", vec![3, 4], bytes_f32(&k)),
        ("cam_from_lidar", vec![4, 4], bytes_f32(&t)),
    ]
}

/// The tensors of a shard, in file order (4-byte types first so every tensor stays aligned, then by
/// name), and the header bytes (length prefix included). Everything is deterministic: the same samples
/// always give the same bytes, which makes checksums meaningful.
fn prepare_shard(
    sensor: &LidarSensor,
    dataset: &str,
    samples: &[ShardSample],
) -> Result<(Vec<u8>, NamedTensors)> {
    sensor.validate()?;
    let (h, w) = (sensor.rows as usize, sensor.cols as usize);
    let n = h * w;
    let mut tensors: Vec<(String, OwnedTensor)> = Vec::new();
    for (k, s) in samples.iter().enumerate() {
        let bad = |what: &str, len: usize| Error::Mismatch {
            context: format!("shard sample {} ({})", k, s.id),
            message: format!("{what} has {len} values, the {h}x{w} sensor needs {n}"),
        };
        if (s.scan.rows, s.scan.cols) != (sensor.rows, sensor.cols) {
            return Err(Error::Mismatch {
                context: format!("shard sample {} ({})", k, s.id),
                message: format!(
                    "a {}x{} range image on a {h}x{w} sensor",
                    s.scan.rows, s.scan.cols
                ),
            });
        }
        let scan = &s.scan;
        for (what, len) in [
            ("range_m", scan.range_m.len()),
            ("intensity", scan.intensity.len()),
            ("mask", scan.mask.len()),
        ] {
            if len != n {
                return Err(bad(what, len));
            }
        }
        let p = format!("{k:05}");
        let mut put = |name: &str, dtype, shape: Vec<usize>, data| {
            tensors.push((format!("{p}/{name}"), OwnedTensor { dtype, shape, data }));
        };
        put("range_m", Dtype::F32, vec![h, w], bytes_f32(&scan.range_m));
        put(
            "intensity",
            Dtype::F32,
            vec![h, w],
            bytes_f32(&scan.intensity),
        );
        put(
            "mask",
            Dtype::U8,
            vec![h, w],
            scan.mask.iter().map(|&m| u8::from(m)).collect(),
        );
        if let Some(l) = &s.train_ids {
            if l.len() != n {
                return Err(bad("label", l.len()));
            }
            put("label", Dtype::U8, vec![h, w], l.clone());
        }
        if let Some(l) = &scan.label {
            if l.len() != n {
                return Err(bad("label_raw", l.len()));
            }
            put("label_raw", Dtype::U32, vec![h, w], bytes_u32(l));
        }
        if let Some(img) = &s.image {
            let (iw, ih) = img.dimensions();
            put(
                "image",
                Dtype::U8,
                vec![ih as usize, iw as usize, 3],
                img.as_raw().clone(),
            );
        }
        if let Some(c) = &s.camera {
            for (name, shape, data) in camera_tensors(c) {
                put(name, Dtype::F32, shape, data);
            }
        }
        for (j, v) in s.extra_views.iter().enumerate() {
            let prefix = format!("view{}/", j + 1);
            for (name, shape, data) in camera_tensors(&v.camera) {
                put(&format!("{prefix}{name}"), Dtype::F32, shape, data);
            }
            let (iw, ih) = v.image.dimensions();
            put(
                &format!("{prefix}image"),
                Dtype::U8,
                vec![ih as usize, iw as usize, 3],
                v.image.as_raw().clone(),
            );
        }
    }
    tensors.sort_by(|(a, ta), (b, tb)| {
        let wide = |t: &OwnedTensor| t.dtype != Dtype::U8;
        wide(tb).cmp(&wide(ta)).then_with(|| a.cmp(b))
    });
    let ids: Vec<&str> = samples.iter().map(|s| s.id.as_str()).collect();
    let mut header = serde_json::Map::new();
    let mut meta = serde_json::Map::new();
    meta.insert("format".into(), SHARD_FORMAT.into());
    meta.insert("sensor".into(), json(sensor)?.into());
    meta.insert("count".into(), samples.len().to_string().into());
    meta.insert("ids".into(), json(&ids)?.into());
    meta.insert("dataset".into(), dataset.into());
    header.insert("__metadata__".into(), serde_json::Value::Object(meta));
    let mut offset = 0usize;
    for (name, t) in &tensors {
        let end = offset + t.data.len();
        header.insert(
            name.clone(),
            serde_json::json!({ "dtype": dtype_name(t.dtype), "shape": t.shape, "data_offsets": [offset, end] }),
        );
        offset = end;
    }
    let mut text = serde_json::Value::Object(header).to_string().into_bytes();
    text.resize(text.len().next_multiple_of(8), b' ');
    let mut bytes = (text.len() as u64).to_le_bytes().to_vec();
    bytes.extend_from_slice(&text);
    Ok((bytes, tensors))
}

/// Encode samples as safetensors bytes (deterministic). Every sample must match the sensor's size.
pub fn encode_shard(
    sensor: &LidarSensor,
    dataset: &str,
    samples: &[ShardSample],
) -> Result<Vec<u8>> {
    let (mut out, tensors) = prepare_shard(sensor, dataset, samples)?;
    for (_, t) in &tensors {
        out.extend_from_slice(&t.data);
    }
    Ok(out)
}

fn json<T: Serialize + ?Sized>(v: &T) -> Result<String> {
    serde_json::to_string(v).map_err(|e| Error::Invalid {
        what: "JSON".into(),
        message: e.to_string(),
    })
}

/// Hex SHA-256 of bytes.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

fn hex(d: &[u8]) -> String {
    d.iter().map(|b| format!("{b:02x}")).collect()
}

/// Hex SHA-256 and size of a file, streamed.
pub fn sha256_file(path: &Path) -> Result<(String, u64)> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    sha256_read(f, path)
}

/// Hex SHA-256 and size of what `f` yields, streamed; `path` names it in errors.
pub(crate) fn sha256_read(mut f: impl Read, path: &Path) -> Result<(String, u64)> {
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut total = 0u64;
    loop {
        let k = f.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if k == 0 {
            break;
        }
        total += k as u64;
        h.update(&buf[..k]);
    }
    Ok((hex(&h.finalize()), total))
}

/// Write a shard atomically, streaming the tensors to disk while hashing them (no second copy of
/// the shard in memory), and return its manifest entry (file name, count, size, checksum).
pub fn write_shard(
    path: &Path,
    sensor: &LidarSensor,
    dataset: &str,
    samples: &[ShardSample],
) -> Result<ShardEntry> {
    let (header, tensors) = prepare_shard(sensor, dataset, samples)?;
    let mut hasher = Sha256::new();
    let mut total = 0u64;
    write_atomic_with(path, |w| {
        for chunk in std::iter::once(&header[..]).chain(tensors.iter().map(|(_, t)| &t.data[..])) {
            hasher.update(chunk);
            total += chunk.len() as u64;
            std::io::Write::write_all(w, chunk)?;
        }
        Ok(())
    })?;
    Ok(ShardEntry {
        file: path
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default(),
        count: samples.len(),
        bytes: total,
        sha256: hex(&hasher.finalize()),
        ids: samples.iter().map(|s| s.id.clone()).collect(),
    })
}

fn tensor<'a>(st: &SafeTensors<'a>, name: &str, path: &Path) -> Result<Option<TensorView<'a>>> {
    match st.tensor(name) {
        Ok(t) => Ok(Some(t)),
        Err(safetensors::SafeTensorError::TensorNotFound(_)) => Ok(None),
        Err(e) => Err(Error::format(path, format!("tensor {name}: {e}"))),
    }
}

fn expect(
    t: &TensorView<'_>,
    dtype: Dtype,
    shape: &[usize],
    name: &str,
    path: &Path,
) -> Result<()> {
    if t.dtype() != dtype || t.shape() != shape {
        return Err(Error::format(
            path,
            format!(
                "tensor {name}: expected {dtype:?} {shape:?}, found {:?} {:?}",
                t.dtype(),
                t.shape()
            ),
        ));
    }
    Ok(())
}

fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// A shard's string metadata checked: its sensor and frame ids.
fn shard_metadata(
    meta: &std::collections::HashMap<String, String>,
    path: &Path,
) -> Result<(LidarSensor, Vec<String>)> {
    let fmt = |m: String| Error::format(path, m);
    let get = |k: &str| {
        meta.get(k)
            .ok_or_else(|| fmt(format!("shard metadata has no `{k}`")))
    };
    if get("format")? != SHARD_FORMAT {
        return Err(fmt(format!(
            "unsupported shard format `{}`",
            get("format")?
        )));
    }
    let sensor: LidarSensor = serde_json::from_str(get("sensor")?)
        .map_err(|e| fmt(format!("bad sensor metadata: {e}")))?;
    sensor
        .validate()
        .map_err(|e| fmt(format!("bad sensor metadata: {e}")))?;
    let ids: Vec<String> =
        serde_json::from_str(get("ids")?).map_err(|e| fmt(format!("bad ids metadata: {e}")))?;
    let count: usize = get("count")?
        .parse()
        .map_err(|_| fmt("bad count metadata".into()))?;
    if ids.len() != count {
        return Err(fmt(format!("metadata count {count} but {} ids", ids.len())));
    }
    Ok((sensor, ids))
}

/// Decode shard bytes (`path` names the source in errors).
pub fn decode_shard(bytes: &[u8], path: &Path) -> Result<Shard> {
    let fmt = |m: String| Error::format(path, m);
    let st =
        SafeTensors::deserialize(bytes).map_err(|e| fmt(format!("not a safetensors file: {e}")))?;
    let (_, meta) =
        SafeTensors::read_metadata(bytes).map_err(|e| fmt(format!("bad header: {e}")))?;
    let meta = meta.metadata().clone().unwrap_or_default();
    let (sensor, ids) = shard_metadata(&meta, path)?;
    let mut samples = Vec::with_capacity(ids.len());
    for (k, id) in ids.into_iter().enumerate() {
        let get = |name: &str| tensor(&st, name, path);
        samples.push(decode_sample(get, k, id, &sensor, path)?);
    }
    Ok(Shard {
        sensor,
        dataset: meta.get("dataset").cloned().unwrap_or_default(),
        samples,
    })
}

/// The image and camera stored under `prefix` (`NNNNN/` or `NNNNN/viewJ/`).
fn decode_view<'a>(
    get: &impl Fn(&str) -> Result<Option<TensorView<'a>>>,
    prefix: &str,
    path: &Path,
) -> Result<(Option<RgbImage>, Option<CameraMatrices>)> {
    let fmt = |m: String| Error::format(path, m);
    let image = match get(&format!("{prefix}image"))? {
        Some(t) => {
            let s = t.shape().to_vec();
            if t.dtype() != Dtype::U8 || s.len() != 3 || s[2] != 3 {
                return Err(fmt(format!(
                    "tensor {prefix}image: expected U8 [H, W, 3], found {:?} {s:?}",
                    t.dtype()
                )));
            }
            Some(
                RgbImage::from_raw(s[1] as u32, s[0] as u32, t.data().to_vec())
                    .ok_or_else(|| fmt(format!("tensor {prefix}image: size mismatch")))?,
            )
        }
        None => None,
    };
    let camera = match (
        get(&format!("{prefix}intrinsics"))?,
        get(&format!("{prefix}cam_from_lidar"))?,
    ) {
        (Some(k), Some(t)) => {
            expect(&k, Dtype::F32, &[3, 4], "intrinsics", path)?;
            expect(&t, Dtype::F32, &[4, 4], "cam_from_lidar", path)?;
            let (kv, tv) = (f32s(k.data()), f32s(t.data()));
            let mut intrinsics = [[0f32; 4]; 3];
            let mut cam_from_lidar = [[0f32; 4]; 4];
            for r in 0..3 {
                intrinsics[r].copy_from_slice(&kv[r * 4..r * 4 + 4]);
            }
            for r in 0..4 {
                cam_from_lidar[r].copy_from_slice(&tv[r * 4..r * 4 + 4]);
            }
            Some(CameraMatrices {
                intrinsics,
                cam_from_lidar,
            })
        }
        (None, None) => None,
        _ => {
            return Err(fmt(format!(
                "{prefix}: intrinsics and cam_from_lidar must come together"
            )));
        }
    };
    Ok((image, camera))
}

/// Sample `k` (frame `id`) of a shard whose tensors `get` looks up by name (`None`: absent).
fn decode_sample<'a>(
    get: impl Fn(&str) -> Result<Option<TensorView<'a>>>,
    k: usize,
    id: String,
    sensor: &LidarSensor,
    path: &Path,
) -> Result<ShardSample> {
    let fmt = |m: String| Error::format(path, m);
    let (h, w) = (sensor.rows as usize, sensor.cols as usize);
    let p = format!("{k:05}");
    let req = |name: &str| -> Result<TensorView<'a>> {
        get(&format!("{p}/{name}"))?.ok_or_else(|| fmt(format!("missing tensor {p}/{name}")))
    };
    let range = req("range_m")?;
    expect(&range, Dtype::F32, &[h, w], "range_m", path)?;
    let inten = req("intensity")?;
    expect(&inten, Dtype::F32, &[h, w], "intensity", path)?;
    let mask = req("mask")?;
    expect(&mask, Dtype::U8, &[h, w], "mask", path)?;
    let label = match get(&format!("{p}/label"))? {
        Some(t) => {
            expect(&t, Dtype::U8, &[h, w], "label", path)?;
            Some(t.data().to_vec())
        }
        None => None,
    };
    let label_raw = match get(&format!("{p}/label_raw"))? {
        Some(t) => {
            expect(&t, Dtype::U32, &[h, w], "label_raw", path)?;
            Some(
                t.data()
                    .chunks_exact(4)
                    .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect(),
            )
        }
        None => None,
    };
    let (image, camera) = decode_view(&get, &format!("{p}/"), path)?;
    let mut extra_views = Vec::new();
    for j in 1.. {
        let prefix = format!("{p}/view{j}/");
        match decode_view(&get, &prefix, path)? {
            (Some(image), Some(camera)) => extra_views.push(ShardView { image, camera }),
            (None, None) => break,
            _ => {
                return Err(fmt(format!(
                    "sample {p}: view {j} needs both its image and its camera"
                )));
            }
        }
    }
    let n = h * w;
    Ok(ShardSample {
        id,
        scan: RangeImage {
            rows: sensor.rows,
            cols: sensor.cols,
            range_m: f32s(range.data()),
            intensity: f32s(inten.data()),
            point_index: vec![veila_geom::NO_POINT; n],
            mask: mask.data().iter().map(|&m| m != 0).collect(),
            label: label_raw,
        },
        train_ids: label,
        image,
        camera,
        extra_views,
    })
}

/// Read a shard file (a regular file, links followed: a FIFO or device is refused unopened).
pub fn read_shard(path: &Path) -> Result<Shard> {
    crate::read_capped::check_regular_file(path)?;
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_shard(&bytes, path)
}

/// Random access to the samples of one shard file: [`Self::open`] reads the header alone (the
/// tensors' offsets, the sensor, the ids), [`Self::sample`] then reads just that sample's tensors,
/// so memory does not grow with the shard. Used by streaming training.
#[derive(Debug)]
pub struct ShardReader {
    path: std::path::PathBuf,
    file: std::sync::Mutex<std::fs::File>,
    sensor: LidarSensor,
    dataset: String,
    ids: Vec<String>,
    /// Byte offset of the tensor data in the file.
    data_start: u64,
    data_len: u64,
    tensors: std::collections::HashMap<String, safetensors::tensor::TensorInfo>,
}

impl ShardReader {
    /// Opens a shard and reads its header (at most 100 MB, as safetensors allows). The shard must
    /// be a regular file, links followed: a FIFO (which a downloaded archive can hold) would
    /// block the open, a device never end; both are refused before opening.
    pub fn open(path: &Path) -> Result<Self> {
        use std::io::Seek;
        let fmt = |m: String| Error::format(path, m);
        crate::read_capped::check_regular_file(path)?;
        let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let mut n = [0u8; 8];
        file.read_exact(&mut n)
            .map_err(|_| fmt("not a safetensors file: shorter than its header".into()))?;
        let n = u64::from_le_bytes(n);
        if n > 100_000_000 || 8 + n > file_len {
            return Err(fmt(format!(
                "not a safetensors file: header of {n} bytes in a file of {file_len}"
            )));
        }
        let mut header = vec![0u8; n as usize];
        file.read_exact(&mut header)
            .map_err(|e| Error::io(path, e))?;
        let meta: safetensors::tensor::Metadata =
            serde_json::from_slice(&header).map_err(|e| fmt(format!("bad header: {e}")))?;
        let info = meta.metadata().clone().unwrap_or_default();
        let (sensor, ids) = shard_metadata(&info, path)?;
        let tensors = meta
            .tensors()
            .into_iter()
            .map(|(k, v)| (k, v.clone()))
            .collect();
        let data_start = file.stream_position().map_err(|e| Error::io(path, e))?;
        Ok(Self {
            path: path.to_path_buf(),
            file: std::sync::Mutex::new(file),
            sensor,
            dataset: info.get("dataset").cloned().unwrap_or_default(),
            ids,
            data_start,
            data_len: file_len - data_start,
            tensors,
        })
    }

    /// The sensor of every range image.
    pub fn sensor(&self) -> &LidarSensor {
        &self.sensor
    }

    /// The dataset name.
    pub fn dataset(&self) -> &str {
        &self.dataset
    }

    /// Frame ids, in order.
    pub fn ids(&self) -> &[String] {
        &self.ids
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether the shard holds no samples.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// How many cameras with an image sample `k` holds (`NNNNN/image` and each
    /// `NNNNN/viewJ/image`), from the header alone.
    pub fn cameras(&self, k: usize) -> usize {
        let first = format!("{k:05}/image");
        let view = format!("{k:05}/view");
        self.tensors
            .keys()
            .filter(|n| {
                *n == &first
                    || n.strip_prefix(&view)
                        .is_some_and(|r| r.ends_with("/image") && r.split('/').count() == 2)
            })
            .count()
    }

    /// Sample `k`, read from the file (what [`read_shard`] gives as `samples[k]`).
    pub fn sample(&self, k: usize) -> Result<ShardSample> {
        use std::io::{Seek, SeekFrom};
        let fmt = |m: String| Error::format(&self.path, m);
        let id = self
            .ids
            .get(k)
            .ok_or_else(|| fmt(format!("no sample {k}: the shard holds {}", self.ids.len())))?
            .clone();
        let prefix = format!("{k:05}/");
        let mut owned: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = Vec::new();
        {
            let mut file = self
                .file
                .lock()
                .map_err(|_| fmt("the shard's file lock is poisoned".into()))?;
            for (name, t) in self.tensors.iter().filter(|(n, _)| n.starts_with(&prefix)) {
                let (start, end) = t.data_offsets;
                let elems: usize = t.shape.iter().product();
                if end < start
                    || end as u64 > self.data_len
                    || end - start != elems * t.dtype.bitsize() / 8
                {
                    return Err(fmt(format!(
                        "tensor {name}: bad offsets {start}..{end} for {:?} {:?}",
                        t.dtype, t.shape
                    )));
                }
                let mut buf = vec![0u8; end - start];
                file.seek(SeekFrom::Start(self.data_start + start as u64))
                    .and_then(|_| file.read_exact(&mut buf))
                    .map_err(|e| Error::io(&self.path, e))?;
                owned.push((name.clone(), t.dtype, t.shape.clone(), buf));
            }
        }
        let views: std::collections::HashMap<&str, TensorView<'_>> = owned
            .iter()
            .map(|(n, d, s, b)| {
                TensorView::new(*d, s.clone(), b)
                    .map(|v| (n.as_str(), v))
                    .map_err(|e| fmt(format!("tensor {n}: {e}")))
            })
            .collect::<Result<_>>()?;
        let get = |name: &str| Ok(views.get(name).cloned());
        decode_sample(get, k, id, &self.sensor, &self.path)
    }
}

/// One shard in a manifest.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// File name, relative to the manifest's folder.
    pub file: String,
    /// Number of samples.
    pub count: usize,
    /// File size in bytes.
    pub bytes: u64,
    /// Hex SHA-256 of the file.
    pub sha256: String,
    /// Frame ids, in order.
    pub ids: Vec<String>,
}

impl ShardEntry {
    /// This entry's file in `dir`, the folder of the manifest `manifest` that lists it as shard
    /// `index`: relative and inside `dir`, links included ([`crate::contained::contained`]), or an
    /// error naming `shards[index].file` and the manifest; nothing is opened.
    fn path_in(&self, dir: &Path, index: usize, manifest: &Path) -> Result<std::path::PathBuf> {
        crate::contained::contained(
            dir,
            Path::new(&self.file),
            &format!("shards[{index}].file"),
            manifest,
        )
    }

    /// The shard file (in `dir`, listed by `manifest` as shard `index`) holds this entry's
    /// samples: its header's count and ids are the entry's. Only the header is read.
    fn check_against_file(&self, dir: &Path, index: usize, manifest: &Path) -> Result<()> {
        let bad = |m: String| Error::format(manifest, format!("shard {}: {m}", self.file));
        let file = self.path_in(dir, index, manifest)?;
        let reader = ShardReader::open(&file).map_err(|e| bad(format!("{e}")))?;
        if reader.len() != self.count {
            return Err(bad(format!(
                "the manifest lists {} samples, the shard file holds {}",
                self.count,
                reader.len()
            )));
        }
        if reader.ids() != self.ids.as_slice() {
            return Err(bad(
                "the manifest's frame ids differ from the shard file's".into()
            ));
        }
        Ok(())
    }
}

/// The manifest of a converted dataset (`manifest.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`MANIFEST_FORMAT`].
    pub format: String,
    /// Dataset name.
    pub dataset: String,
    /// The sensor of every range image.
    pub sensor: LidarSensor,
    /// Frames per shard (the last shard may hold fewer).
    pub frames_per_shard: usize,
    /// Total number of samples.
    pub count: usize,
    /// The shards, in order.
    pub shards: Vec<ShardEntry>,
}

/// The name of a converted dataset's manifest in its folder.
pub const MANIFEST_FILE: &str = "manifest.json";

/// The folder of the file `path` (`.` for a bare name).
fn dir_of(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// The most samples a manifest may list, in all (2^24, about 16.8 million: SemanticKITTI has 43 552
/// scans, nuScenes 390 000 sweeps): a manifest claiming more is refused before anything sized by
/// its counts is allocated.
pub const MAX_MANIFEST_SAMPLES: usize = 1 << 24;

impl Manifest {
    /// Read `manifest.json` and check it against its shards: [`Self::read_listing`]'s checks,
    /// then every shard's header (the file in the manifest's folder; its header alone is read)
    /// must hold the samples the manifest lists for it. Errors name the manifest and the shard.
    pub fn read(path: &Path) -> Result<Self> {
        let m = Self::read_listing(path)?;
        let dir = dir_of(path);
        for (i, entry) in m.shards.iter().enumerate() {
            entry.check_against_file(dir, i, path)?;
        }
        Ok(m)
    }

    /// The file of shard `index` in `dir`, the folder holding this manifest (`manifest.json`):
    /// relative and inside `dir`, links included, else an error naming `shards[index].file` and
    /// the manifest, before the file is opened ([`crate::contained::contained`]).
    pub fn shard_path(&self, dir: &Path, index: usize) -> Result<std::path::PathBuf> {
        let entry = self.shards.get(index).ok_or_else(|| Error::Invalid {
            what: "shard index".into(),
            message: format!("no shard {index}: the manifest lists {}", self.shards.len()),
        })?;
        entry.path_in(dir, index, &dir.join(MANIFEST_FILE))
    }

    /// Read `manifest.json` alone, without opening the shards: its format, each shard's count
    /// against its listed ids, the counts' total (summed without overflow, at most
    /// [`MAX_MANIFEST_SAMPLES`]) against `count`, and each shard's `file` a relative path inside
    /// the manifest's folder (links included; see [`Self::shard_path`]).
    pub fn read_listing(path: &Path) -> Result<Self> {
        let text = crate::read_capped::read_metadata_string(
            path,
            crate::read_capped::MAX_JSON_METADATA_BYTES,
            "a shard manifest",
        )?;
        let m: Manifest = serde_json::from_str(&text)
            .map_err(|e| Error::format(path, format!("not a shard manifest: {e}")))?;
        if m.format != MANIFEST_FORMAT {
            return Err(Error::format(
                path,
                format!("unsupported manifest format `{}`", m.format),
            ));
        }
        m.check_counts(path)?;
        let dir = dir_of(path);
        for (i, entry) in m.shards.iter().enumerate() {
            entry.path_in(dir, i, path)?;
        }
        Ok(m)
    }

    /// Each shard's `count` equals its number of ids, the counts sum (checked) to `count`, and
    /// that is at most [`MAX_MANIFEST_SAMPLES`].
    fn check_counts(&self, path: &Path) -> Result<()> {
        let bad = |m: String| Err(Error::format(path, m));
        if self.count > MAX_MANIFEST_SAMPLES {
            return bad(format!(
                "count {} is more than the limit of {MAX_MANIFEST_SAMPLES} samples",
                self.count
            ));
        }
        let mut sum = 0usize;
        for s in &self.shards {
            if s.count != s.ids.len() {
                return bad(format!(
                    "shard {}: count {} but {} ids",
                    s.file,
                    s.count,
                    s.ids.len()
                ));
            }
            match sum.checked_add(s.count) {
                Some(t) if t <= MAX_MANIFEST_SAMPLES => sum = t,
                _ => {
                    return bad(format!(
                        "the shards' counts add up to more than the limit of {MAX_MANIFEST_SAMPLES} samples (at shard {})",
                        s.file
                    ));
                }
            }
        }
        if sum != self.count {
            return bad(format!("count {} but the shards hold {sum}", self.count));
        }
        Ok(())
    }

    /// Write atomically.
    pub fn write(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self).map_err(|e| Error::Invalid {
            what: "manifest".into(),
            message: e.to_string(),
        })?;
        crate::atomic::write_atomic(path, text.as_bytes())
    }

    /// Check every shard file in `dir` against its size and checksum (each file inside `dir`
    /// first, see [`Self::shard_path`]: nothing outside is hashed).
    pub fn verify(&self, dir: &Path) -> Result<()> {
        for (i, s) in self.shards.iter().enumerate() {
            let p = self.shard_path(dir, i)?;
            let (sha, bytes) = sha256_file(&p)?;
            if bytes != s.bytes || sha != s.sha256 {
                return Err(Error::format(
                    &p,
                    format!(
                        "checksum mismatch: manifest says {} bytes sha256 {}, file has {bytes} bytes sha256 {sha}",
                        s.bytes, s.sha256
                    ),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(id: &str, sensor: &LidarSensor, seed: u32) -> ShardSample {
        let n = sensor.num_pixels();
        ShardSample {
            id: id.into(),
            scan: RangeImage {
                range_m: (0..n).map(|i| (i as u32 ^ seed) as f32 * 0.25).collect(),
                intensity: (0..n).map(|i| (i % 7) as f32 / 7.0).collect(),
                mask: (0..n).map(|i| i % 3 != 0).collect(),
                label: Some((0..n).map(|i| (i as u32) << 16 | 40).collect()),
                ..RangeImage::new_empty(sensor.rows, sensor.cols)
            },
            train_ids: Some((0..n).map(|i| (i % 20) as u8).collect()),
            image: Some(RgbImage::from_fn(5, 3, |x, y| {
                image::Rgb([x as u8, y as u8, seed as u8])
            })),
            camera: Some(CameraMatrices {
                intrinsics: [
                    [700.0, 0.0, 600.0, 45.0],
                    [0.0, 700.0, 180.0, 0.0],
                    [0.0, 0.0, 1.0, 0.005],
                ],
                cam_from_lidar: [
                    [0.0, -1.0, 0.0, 0.1],
                    [0.0, 0.0, -1.0, 0.2],
                    [1.0, 0.0, 0.0, 0.3],
                    [0.0, 0.0, 0.0, 1.0],
                ],
            }),
            // seed % 3 further cameras (0, 1 or 2), each its own size and matrices
            extra_views: (0..seed % 3)
                .map(|v| ShardView {
                    image: RgbImage::from_fn(4 + v, 2 + v, |x, y| {
                        image::Rgb([x as u8, y as u8, (seed + v) as u8])
                    }),
                    camera: CameraMatrices {
                        intrinsics: [
                            [600.0 + v as f32, 0.0, 300.0, 0.0],
                            [0.0, 600.0, 180.0, 0.0],
                            [0.0, 0.0, 1.0, 0.0],
                        ],
                        cam_from_lidar: [
                            [1.0, 0.0, 0.0, v as f32],
                            [0.0, 1.0, 0.0, 0.0],
                            [0.0, 0.0, 1.0, 0.0],
                            [0.0, 0.0, 0.0, 1.0],
                        ],
                    },
                })
                .collect(),
        }
    }

    #[test]
    fn shard_round_trip_and_checksums() {
        let sensor = LidarSensor {
            rows: 4,
            cols: 8,
            ..LidarSensor::hdl64e()
        };
        let samples = vec![sample("a", &sensor, 1), {
            let mut b = sample("b", &sensor, 2);
            b.scan.label = None;
            b.train_ids = None;
            b.image = None;
            b.camera = None;
            b
        }];
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("shard-00000.safetensors");
        let entry = write_shard(&p, &sensor, "test", &samples).unwrap();
        assert_eq!(entry.count, 2);
        assert_eq!(
            sha256_file(&p).unwrap(),
            (entry.sha256.clone(), entry.bytes)
        );
        let back = read_shard(&p).unwrap();
        assert_eq!(back.sensor, sensor);
        assert_eq!(back.samples, samples);
        let m = Manifest {
            format: MANIFEST_FORMAT.into(),
            dataset: "test".into(),
            sensor,
            frames_per_shard: 2,
            count: 2,
            shards: vec![entry],
        };
        m.verify(dir.path()).unwrap();
        // corrupt one byte: verify names the file
        let mut bytes = std::fs::read(&p).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 1;
        std::fs::write(&p, &bytes).unwrap();
        let e = m.verify(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("shard-00000.safetensors") && e.contains("checksum"),
            "{e}"
        );
    }

    #[test]
    fn the_reader_gives_each_sample_alone_as_read_shard_does() {
        let sensor = LidarSensor {
            rows: 4,
            cols: 8,
            ..LidarSensor::hdl64e()
        };
        let mut samples: Vec<ShardSample> = (0..5)
            .map(|k| sample(&format!("f{k}"), &sensor, k as u32 + 1))
            .collect();
        samples[3].image = None;
        samples[3].camera = None;
        samples[3].train_ids = None;
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("shard-00000.safetensors");
        write_shard(&p, &sensor, "test", &samples).unwrap();
        let r = ShardReader::open(&p).unwrap();
        assert_eq!((r.len(), r.sensor(), r.dataset()), (5, &sensor, "test"));
        assert_eq!(r.ids(), &["f0", "f1", "f2", "f3", "f4"]);
        // the cameras with an image, from the header: sample 3 has lost its first one
        let cameras: Vec<usize> = (0..5).map(|k| r.cameras(k)).collect();
        assert_eq!(cameras, [2, 3, 1, 1, 3]);
        // any order, any number of times
        for k in [4, 0, 3, 3, 1, 2] {
            assert_eq!(r.sample(k).unwrap(), samples[k], "sample {k}");
        }
        let e = r.sample(5).unwrap_err().to_string();
        assert!(
            e.contains("no sample 5") && e.contains("shard-00000"),
            "{e}"
        );
        // a truncated file: the header still reads, the lost samples fail naming the file
        let bytes = std::fs::read(&p).unwrap();
        let cut = dir.path().join("cut.safetensors");
        std::fs::write(&cut, &bytes[..bytes.len() - 200]).unwrap();
        let r = ShardReader::open(&cut).unwrap();
        let e = (0..5).find_map(|k| r.sample(k).err()).unwrap().to_string();
        assert!(e.contains("cut.safetensors"), "{e}");
        // not a shard at all
        let junk = dir.path().join("junk.safetensors");
        std::fs::write(&junk, b"\xff\xff\xff\xff\xff\xff\xff\x7fjunk").unwrap();
        let e = ShardReader::open(&junk).unwrap_err().to_string();
        assert!(e.contains("junk.safetensors"), "{e}");
        std::fs::write(&junk, b"\x04\x00\x00\x00\x00\x00\x00\x00{}  ").unwrap();
        assert!(ShardReader::open(&junk).is_err());
    }

    #[test]
    fn encoding_is_deterministic_and_readable_by_the_safetensors_crate() {
        let sensor = LidarSensor {
            rows: 2,
            cols: 4,
            ..LidarSensor::hdl64e()
        };
        let samples = vec![sample("x", &sensor, 3), sample("y", &sensor, 4)];
        let a = encode_shard(&sensor, "d", &samples).unwrap();
        for _ in 0..5 {
            assert_eq!(encode_shard(&sensor, "d", &samples).unwrap(), a);
        }
        let st = SafeTensors::deserialize(&a).unwrap();
        // 8 tensors per sample, and 3 for y's second camera
        assert_eq!(st.len(), 19);
        assert_eq!(st.tensor("00001/view1/image").unwrap().shape(), &[2, 4, 3]);
        let t = st.tensor("00001/range_m").unwrap();
        assert_eq!(t.shape(), &[2, 4]);
        assert_eq!(f32s(t.data()), samples[1].scan.range_m);
        let dir = tempfile::tempdir().unwrap();
        let e = write_shard(&dir.path().join("s.safetensors"), &sensor, "d", &samples).unwrap();
        assert_eq!(e.sha256, sha256_hex(&a));
        assert_eq!(std::fs::read(dir.path().join("s.safetensors")).unwrap(), a);
    }

    /// A folder with one 2-sample shard and the text of its valid manifest.
    fn two_sample_dataset() -> (tempfile::TempDir, serde_json::Value) {
        let sensor = LidarSensor {
            rows: 2,
            cols: 4,
            ..LidarSensor::hdl64e()
        };
        let dir = tempfile::tempdir().unwrap();
        let samples = vec![sample("a", &sensor, 1), sample("b", &sensor, 2)];
        let p = dir.path().join("shard-00000.safetensors");
        let entry = write_shard(&p, &sensor, "test", &samples).unwrap();
        let m = Manifest {
            format: MANIFEST_FORMAT.into(),
            dataset: "test".into(),
            sensor,
            frames_per_shard: 2,
            count: 2,
            shards: vec![entry],
        };
        (dir, serde_json::to_value(&m).unwrap())
    }

    /// Writes `manifest` to `dir/manifest.json` and reads it back.
    fn read_back(dir: &Path, manifest: &serde_json::Value) -> Result<Manifest> {
        let p = dir.join("manifest.json");
        std::fs::write(&p, manifest.to_string()).unwrap();
        Manifest::read(&p)
    }

    #[test]
    fn a_manifest_must_match_the_headers_of_its_shards() {
        let (dir, good) = two_sample_dataset();
        assert_eq!(read_back(dir.path(), &good).unwrap().count, 2);
        // 5 samples (with 5 ids) claimed for the 2-sample shard
        let mut m = good.clone();
        m["count"] = 5.into();
        m["shards"][0]["count"] = 5.into();
        m["shards"][0]["ids"] = serde_json::json!(["a", "b", "c", "d", "e"]);
        let e = read_back(dir.path(), &m).unwrap_err().to_string();
        assert!(
            e.contains("manifest.json")
                && e.contains("shard-00000.safetensors")
                && e.contains("lists 5 samples, the shard file holds 2"),
            "{e}"
        );
        // other ids, a count without its ids, a missing shard
        let mut m = good.clone();
        m["shards"][0]["ids"] = serde_json::json!(["a", "z"]);
        let e = read_back(dir.path(), &m).unwrap_err().to_string();
        assert!(e.contains("frame ids differ"), "{e}");
        let mut m = good.clone();
        m["count"] = 3.into();
        m["shards"][0]["count"] = 3.into();
        let e = read_back(dir.path(), &m).unwrap_err().to_string();
        assert!(e.contains("count 3 but 2 ids"), "{e}");
        std::fs::remove_file(dir.path().join("shard-00000.safetensors")).unwrap();
        let e = read_back(dir.path(), &good).unwrap_err().to_string();
        assert!(
            e.contains("manifest.json") && e.contains("shard-00000.safetensors"),
            "{e}"
        );
        // the listing alone does not open the shards
        assert!(Manifest::read_listing(&dir.path().join("manifest.json")).is_ok());
    }

    #[test]
    fn huge_or_wrapping_manifest_counts_are_refused() {
        let (dir, good) = two_sample_dataset();
        let entry = good["shards"][0].clone();
        let shard_with = |count: u64| {
            let mut e = entry.clone();
            e["count"] = count.into();
            e
        };
        // 10^15 samples (an allocation of ~10^17 bytes downstream), and counts of 2^63 and
        // 2^63 + 2 that a wrapping sum adds up to 2
        let mut m = good.clone();
        m["count"] = 1_000_000_000_000_000u64.into();
        m["shards"][0]["count"] = 1_000_000_000_000_000u64.into();
        let e = read_back(dir.path(), &m).unwrap_err().to_string();
        assert!(e.contains("manifest.json") && e.contains("limit"), "{e}");
        let mut m = good.clone();
        m["shards"] = serde_json::json!([shard_with(1 << 63), shard_with((1 << 63) + 2)]);
        let e = read_back(dir.path(), &m).unwrap_err().to_string();
        assert!(e.contains("manifest.json") && e.contains("count"), "{e}");
        assert!(Manifest::read_listing(&dir.path().join("manifest.json")).is_err());
    }

    #[test]
    fn camera_matrices_round_trip_through_pinhole() {
        let s = sample("a", &LidarSensor::hdl64e(), 0);
        let c = s.camera.unwrap();
        let cam = c.to_camera(1242, 375).unwrap();
        assert_eq!(CameraMatrices::from_camera(&cam), c);
    }

    #[test]
    fn shard_cameras_are_checked_as_calibrations() {
        let c = sample("a", &LidarSensor::hdl64e(), 0).camera.unwrap();
        // a negative focal length (a camera `PinholeCamera::new` takes) and a principal point
        // outside the image are refused, saying what is wrong
        let mut neg = c;
        neg.intrinsics[1][1] = -neg.intrinsics[1][1];
        let e = neg.to_camera(1242, 375).unwrap_err().to_string();
        assert!(e.contains("focal lengths"), "{e}");
        let e = c.to_camera(100, 100).unwrap_err().to_string();
        assert!(e.contains("principal point"), "{e}");
        let mut far = c;
        far.cam_from_lidar[0][3] = 1e30;
        let e = far.to_camera(1242, 375).unwrap_err().to_string();
        assert!(e.contains("translation"), "{e}");
    }
}
