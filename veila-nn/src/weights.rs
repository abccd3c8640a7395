//! Weights IO, the bottom of the crate: which tensors a model reads (found by running its builder on
//! a recording `VarBuilder`), reading safetensors bytes checked against that list, deterministic
//! safetensors serialisation and sha256 sums. Models, encoders, feature networks and checkpoints all
//! build on it; it builds on nothing of this crate but the error type.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::VarBuilder;

use crate::error::{Error, Result, TensorReport};

/// Name and shape of one tensor a model reads from its `VarBuilder`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorSpec {
    /// Full tensor name, e.g. `segformer.encoder.block.0.0.attention.self.query.weight`.
    pub name: String,
    /// Expected shape.
    pub shape: Vec<usize>,
}

/// The most weights (tensor elements, summed over every tensor) a model may ask for when its
/// tensors are recorded ([`record_tensor_specs`], which every checked load runs first): 2^30,
/// 4 GiB of `f32`. The shipped models have a few million, the largest pretrained encoder
/// (Depth-Anything-V2-Large) about 335 million; a config from a file that asks for more fails
/// with [`Error::Config`] before anything of that size is allocated.
pub const MAX_PARAMETERS: usize = 1 << 30;

/// The largest magnitude a weight may have when a file is loaded: far beyond any trained weight
/// (the bundled model's largest is 1.9, a batch-norm running variance of the feature networks'
/// 60), and small enough that no single weight overflows an activation by itself; a file with a
/// 3e38 (or infinite, or NaN) weight generated empty scans without a word.
pub const MAX_ABS_WEIGHT: f32 = 1e8;

/// The largest weights file (safetensors) read: [`MAX_PARAMETERS`] `f32` values and the largest
/// header the safetensors parser takes (100 MB), about 4.1 GiB. A file that is larger holds more
/// than any model may ask for (or lies in its header); it is refused from its length, before
/// anything is read ([`read_weights_file`]).
pub const MAX_WEIGHTS_FILE_BYTES: u64 = MAX_PARAMETERS as u64 * 4 + 100_000_000;

/// The dtypes a weight tensor may be stored in when the model takes it in a float type: the IEEE
/// float precisions (a published checkpoint may be in half precision; it is converted to the
/// model's dtype). Integers, booleans and the 8-bit and microscaling floats are refused.
const FLOAT_DTYPES: [safetensors::Dtype; 4] = [
    safetensors::Dtype::F32,
    safetensors::Dtype::F16,
    safetensors::Dtype::BF16,
    safetensors::Dtype::F64,
];

/// Which stored dtypes [`read_checked_scoped`] accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Stored {
    /// Exactly `f32`: the files this crate writes ([`safetensors_bytes`], checkpoints).
    F32,
    /// Any of [`FLOAT_DTYPES`] (pretrained checkpoints, encoder and feature-network files).
    Float,
}

/// Checks one tensor of a file about to be loaded: its dtype is one `stored` accepts, and every
/// value is finite and within [`MAX_ABS_WEIGHT`]. One pass over its bytes, nothing allocated.
fn check_weight(
    name: &str,
    view: &safetensors::tensor::TensorView<'_>,
    stored: Stored,
    path: &Path,
) -> Result<()> {
    use safetensors::Dtype;
    let bad = |reason: String| Error::BadWeights {
        path: path.to_path_buf(),
        tensor: name.to_string(),
        reason,
    };
    let dtype = view.dtype();
    let ok = match stored {
        Stored::F32 => dtype == Dtype::F32,
        Stored::Float => FLOAT_DTYPES.contains(&dtype),
    };
    if !ok {
        let want = match stored {
            Stored::F32 => "F32 (the model's weights are f32, as this crate writes them)".into(),
            Stored::Float => {
                format!("a float type, one of {FLOAT_DTYPES:?} (the model's weights are floats)")
            }
        };
        return Err(bad(format!("stored as {dtype:?}, must be {want}")));
    }
    let data = view.data();
    // the first value that is not finite or too large, as f64 (exact for every float type)
    let first_bad: Option<(usize, f64)> = match dtype {
        // the fast pass: the largest magnitude's bits (NaN's are above infinity's, which are
        // above every finite value's), a branch-free fold that vectorises; the values are
        // searched only when that is over the limit
        Dtype::F32 if f32_abs_bits_max(data) <= MAX_ABS_WEIGHT.to_bits() => None,
        Dtype::F32 => data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .enumerate()
            .find(|(_, v)| v.is_nan() || v.abs() > MAX_ABS_WEIGHT)
            .map(|(i, v)| (i, f64::from(v))),
        // half precision: at most 65504, so only the all-ones exponent (inf, NaN) is refused
        Dtype::F16 => data
            .chunks_exact(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
            .enumerate()
            .find(|(_, h)| h & 0x7c00 == 0x7c00)
            .map(|(i, h)| {
                (
                    i,
                    if h & 0x03ff == 0 {
                        f64::INFINITY
                    } else {
                        f64::NAN
                    },
                )
            }),
        // bfloat16 is the upper half of an f32
        Dtype::BF16 => data
            .chunks_exact(2)
            .map(|b| f32::from_bits(u32::from(u16::from_le_bytes([b[0], b[1]])) << 16))
            .enumerate()
            .find(|(_, v)| v.is_nan() || v.abs() > MAX_ABS_WEIGHT)
            .map(|(i, v)| (i, f64::from(v))),
        Dtype::F64 => data
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
            .enumerate()
            .find(|(_, v)| v.is_nan() || v.abs() > f64::from(MAX_ABS_WEIGHT)),
        _ => None,
    };
    let Some((i, v)) = first_bad else {
        return Ok(());
    };
    // shown in the file's own precision (an f32 of 3e38 as `3e38`)
    let shown = if dtype == Dtype::F64 {
        format!("{v:e}")
    } else {
        format!("{:e}", v as f32)
    };
    Err(bad(if v.is_finite() {
        format!("value {i} is {shown}, beyond the limit of {MAX_ABS_WEIGHT:e} in magnitude")
    } else {
        format!("value {i} is {shown}: weights must be finite")
    }))
}

/// The largest `bits & 0x7fff_ffff` of the little-endian `f32` values in `data`: for magnitudes,
/// the bit patterns order as the values do, with infinity above every finite value and NaN above
/// infinity.
fn f32_abs_bits_max(data: &[u8]) -> u32 {
    data.chunks_exact(4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) & 0x7fff_ffff)
        .fold(0, u32::max)
}

/// What the recorder has seen: the specs in request order, their total element count, and the
/// reason it refused a tensor (if it did).
#[derive(Debug, Default)]
struct Recording {
    specs: Vec<TensorSpec>,
    total: usize,
    refused: Option<String>,
}

impl Recording {
    /// Adds `name` of shape `dims` to the list, or refuses it (keeping the reason) when its
    /// element count overflows or the running total passes [`MAX_PARAMETERS`].
    fn add(&mut self, name: &str, dims: &[usize]) -> std::result::Result<(), String> {
        let elems = dims.iter().try_fold(1usize, |a, d| a.checked_mul(*d));
        let total = elems.and_then(|e| self.total.checked_add(e));
        match total {
            Some(t) if t <= MAX_PARAMETERS => {
                self.total = t;
                self.specs.push(TensorSpec {
                    name: name.to_string(),
                    shape: dims.to_vec(),
                });
                Ok(())
            }
            _ => {
                let size = elems.map_or_else(|| "more than usize::MAX".into(), |e| e.to_string());
                let why = format!(
                    "the model's weights pass the limit of {MAX_PARAMETERS} elements at tensor \
                     `{name}` of shape {dims:?} ({size} elements, after {} in the tensors before it)",
                    self.total
                );
                self.refused = Some(why.clone());
                Err(why)
            }
        }
    }
}

/// A `VarBuilder` backend that records every tensor asked for and hands out zeros: one scalar
/// zero broadcast to the shape, so recording allocates nothing of the model's size.
#[derive(Debug, Default)]
struct RecordingBackend {
    seen: Arc<Mutex<Recording>>,
}

impl candle_nn::var_builder::SimpleBackend for RecordingBackend {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let mut seen = self
            .seen
            .lock()
            .map_err(|_| candle_core::Error::Msg("record_tensor_specs: lock poisoned".into()))?;
        seen.add(name, s.dims()).map_err(candle_core::Error::Msg)?;
        drop(seen);
        Tensor::zeros((), dtype, dev)?.broadcast_as(s)
    }
    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("record_tensor_specs: tensor {name} requested without a shape")
    }
    fn contains_tensor(&self, _: &str) -> bool {
        true
    }
}

/// Lists every tensor (name and shape) that `build` reads, in request order, by running it on a
/// recording `VarBuilder` that hands out zeros (broadcast from one scalar: nothing of the model's
/// size is allocated). Use it to compare a checkpoint's keys against a model (missing,
/// unexpected and mis-shaped tensors) before loading, e.g.
/// `record_tensor_specs(|vb| MitEncoder::new(&cfg, vb))`.
///
/// # Errors
/// [`Error::Config`] when the tensors together have more than [`MAX_PARAMETERS`] elements (or a
/// shape's element count overflows), before anything of that size is allocated; any error of
/// `build`.
pub fn record_tensor_specs<T>(
    build: impl FnOnce(VarBuilder<'static>) -> crate::Result<T>,
) -> crate::Result<Vec<TensorSpec>> {
    let seen = Arc::new(Mutex::new(Recording::default()));
    let backend = RecordingBackend { seen: seen.clone() };
    let vb = VarBuilder::from_backend(Box::new(backend), DType::F32, Device::Cpu);
    let built = build(vb).map(drop);
    let mut rec = seen
        .lock()
        .map_err(|_| candle_core::Error::Msg("record_tensor_specs: lock poisoned".into()))?;
    if let Some(why) = rec.refused.take() {
        return Err(Error::Config(why));
    }
    built?;
    Ok(std::mem::take(&mut rec.specs))
}

/// Loads the weights of a model from a safetensors file, verifying them first.
///
/// `build` constructs the model from a `VarBuilder` (it is run once on a recording builder to learn
/// the expected names and shapes, then on the file's tensors). Tensors the model needs but the file
/// lacks, and tensors with the wrong shape, fail with [`crate::Error::CheckpointMismatch`] naming
/// them and the file; tensors of the file that the model does not read are reported as unexpected
/// only when `in_scope(name)` is true (pretrained files carry heads the encoder ignores, e.g.
/// `classifier.*` or `decode_head.*`). IO and parse errors name the file.
pub fn load_checked<T>(
    path: &std::path::Path,
    dtype: DType,
    device: &Device,
    in_scope: impl Fn(&str) -> bool,
    build: impl Fn(VarBuilder<'static>) -> crate::Result<T>,
) -> crate::Result<T> {
    let bytes = read_weights_file(path)?;
    load_checked_bytes(&bytes, path, dtype, device, in_scope, build)
}

/// The bytes of the weights file `path`, refused before anything is read unless it is, links
/// followed, a regular file (not a link to `/dev/zero`, a FIFO or a device) of at most
/// [`MAX_WEIGHTS_FILE_BYTES`]; at most that many bytes are read (a file that grows meanwhile is
/// refused too). Every weights file this crate and its users load is read through it; the
/// tensors are then checked by [`read_checked_bytes`] (or [`load_checked_bytes`]).
///
/// # Errors
/// [`Error::Refused`] for a file of another kind or size, [`Error::Io`] when it cannot be read;
/// both name the file.
pub fn read_weights_file(path: &Path) -> Result<Vec<u8>> {
    read_capped(path, MAX_WEIGHTS_FILE_BYTES, "a weights file")
}

/// The largest JSON file of a model this crate reads (a checkpoint's `config.json`, the feature
/// networks' manifest and configs): 64 MiB, as `veila-data`'s cap of JSON metadata.
pub(crate) const MAX_MODEL_JSON_BYTES: u64 = 64 << 20;

/// The bytes of `path`, a regular file (links followed; checked on the path before it is opened,
/// since opening a FIFO blocks, and again on the open file) of at most `cap` bytes; `what` names
/// the kind of file, with its article, in errors.
pub(crate) fn read_capped(path: &Path, cap: u64, what: &str) -> Result<Vec<u8>> {
    use std::io::Read;
    let io = |source| Error::Io {
        path: path.to_path_buf(),
        source,
    };
    let refused = |message: String| Error::Refused {
        path: path.to_path_buf(),
        message,
    };
    let check = |meta: &std::fs::Metadata| -> Result<()> {
        if !meta.is_file() {
            let kind = if meta.is_dir() {
                "a directory"
            } else {
                "a FIFO, device or socket"
            };
            return Err(refused(format!(
                "{what} must be a regular file, this is {kind}"
            )));
        }
        if meta.len() > cap {
            return Err(refused(format!(
                "{} bytes, more than the cap of {cap} bytes for {what}",
                meta.len()
            )));
        }
        Ok(())
    };
    check(&std::fs::metadata(path).map_err(io)?)?;
    let file = std::fs::File::open(path).map_err(io)?;
    let meta = file.metadata().map_err(io)?;
    check(&meta)?;
    let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0));
    file.take(cap.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > cap {
        return Err(refused(format!(
            "grew past the cap of {cap} bytes for {what} while it was read"
        )));
    }
    Ok(bytes)
}

/// [`load_checked`] on the bytes of a safetensors file already in memory (e.g. embedded in a
/// binary); `path` names the source in errors.
pub fn load_checked_bytes<T>(
    bytes: &[u8],
    path: &std::path::Path,
    dtype: DType,
    device: &Device,
    in_scope: impl Fn(&str) -> bool,
    build: impl Fn(VarBuilder<'static>) -> crate::Result<T>,
) -> crate::Result<T> {
    let expected = record_tensors(|vb| build(vb).map(|_| ()))?;
    let tensors = read_checked_scoped(
        bytes,
        path,
        &expected,
        in_scope,
        Stored::Float,
        dtype,
        device,
    )?;
    build(VarBuilder::from_tensors(tensors, dtype, device))
}

/// The tensors (name -> shape) a model builder asks its `VarBuilder` for, found by running it on a
/// recording builder that hands out zeros (see [`record_tensor_specs`]).
pub fn record_tensors(
    build: impl FnOnce(VarBuilder<'static>) -> Result<()>,
) -> Result<BTreeMap<String, Vec<usize>>> {
    Ok(record_tensor_specs(build)?
        .into_iter()
        .map(|s| (s.name, s.shape))
        .collect())
}

/// Parses safetensors bytes (`path` names them in errors), checks them against `expected` (every
/// tensor present with its shape, nothing else; stored as `f32`, as this crate writes them, with
/// finite values within [`MAX_ABS_WEIGHT`]) and loads them as `f32`.
pub fn read_checked_bytes(
    bytes: &[u8],
    path: &Path,
    expected: &BTreeMap<String, Vec<usize>>,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    read_checked_scoped(
        bytes,
        path,
        expected,
        |_| true,
        Stored::F32,
        DType::F32,
        device,
    )
}

/// [`read_checked_bytes`] for a file whose tensors may be stored in any IEEE float type (`f32`,
/// `f16`, `bf16`, `f64`: a training checkpoint keeps its variables' own dtype), with the same
/// checks (names and shapes against `expected`, finite values within [`MAX_ABS_WEIGHT`], before
/// any tensor is made), converted to `dtype`.
pub fn read_checked_float_bytes(
    bytes: &[u8],
    path: &Path,
    expected: &BTreeMap<String, Vec<usize>>,
    dtype: DType,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    read_checked_scoped(
        bytes,
        path,
        expected,
        |_| true,
        Stored::Float,
        dtype,
        device,
    )
}

/// [`read_checked_bytes`] where tensors of the file that `expected` lacks are reported only when
/// `in_scope(name)` is true (and otherwise dropped, unread), stored as `stored` allows and
/// converted to `dtype`. Names, shapes, dtypes and values are all checked before any tensor is
/// made: a refused file allocates nothing of its size.
pub(crate) fn read_checked_scoped(
    bytes: &[u8],
    path: &Path,
    expected: &BTreeMap<String, Vec<usize>>,
    in_scope: impl Fn(&str) -> bool,
    stored: Stored,
    dtype: DType,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    let st_err = |message: String| Error::SafeTensors {
        path: path.to_path_buf(),
        message,
    };
    let file = safetensors::SafeTensors::deserialize(bytes).map_err(|e| st_err(e.to_string()))?;
    let views = file.tensors();
    let found: BTreeMap<String, Vec<usize>> = views
        .iter()
        .map(|(k, v)| (k.clone(), v.shape().to_vec()))
        .collect();
    let mut report = compare_tensors(expected, &found);
    report.unexpected.retain(|n| in_scope(n));
    if !report.is_clean() {
        return Err(Error::CheckpointMismatch {
            path: path.to_path_buf(),
            report,
        });
    }
    let mut kept: Vec<(String, safetensors::tensor::TensorView<'_>)> = views
        .into_iter()
        .filter(|(k, _)| expected.contains_key(k))
        .collect();
    kept.sort_by(|a, b| a.0.cmp(&b.0));
    for (name, view) in &kept {
        check_weight(name, view, stored, path)?;
    }
    use candle_core::safetensors::Load;
    kept.into_iter()
        .map(|(name, view)| {
            let t = view
                .load(device)
                .map_err(|e| st_err(format!("tensor `{name}`: {e}")))?;
            Ok((name, t.to_dtype(dtype)?))
        })
        .collect()
}

/// Serialises tensors as safetensors bytes, sorted by name and as contiguous `f32` on the CPU, so
/// the same weights always give the same bytes (and the same sha256). `path` names the file in
/// errors. A few lines over `safetensors::serialize` rather than candle's `save` on purpose: the
/// bytes, and so the manifests' sums, must not depend on the device or dtype the weights live in.
pub fn safetensors_bytes(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<Vec<u8>> {
    let mut sorted: Vec<(String, Tensor)> = tensors
        .iter()
        .map(|(k, v)| {
            Ok((
                k.clone(),
                v.to_device(&Device::Cpu)?
                    .to_dtype(DType::F32)?
                    .contiguous()?,
            ))
        })
        .collect::<candle_core::Result<_>>()?;
    sorted.sort_by(|a, b| a.0.cmp(&b.0));
    safetensors::serialize(sorted, None).map_err(|e| Error::SafeTensors {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// Lower-case hex sha256 of `bytes` (the sums of the weight manifests).
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Compares what a model needs with what a file holds.
pub fn compare_tensors(
    expected: &BTreeMap<String, Vec<usize>>,
    found: &BTreeMap<String, Vec<usize>>,
) -> TensorReport {
    let mut r = TensorReport::default();
    for (name, shape) in expected {
        match found.get(name) {
            None => r.missing.push(name.clone()),
            Some(s) if s != shape => r.mis_shaped.push((name.clone(), shape.clone(), s.clone())),
            Some(_) => {}
        }
    }
    r.unexpected = found
        .keys()
        .filter(|k| !expected.contains_key(*k))
        .cloned()
        .collect();
    r
}

/// A temporary name beside `path` (same folder, so a rename publishes it atomically).
pub(crate) fn tmp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".tmp{}", std::process::id()));
    path.with_file_name(name)
}
