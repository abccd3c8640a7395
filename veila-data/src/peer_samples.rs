//! The generated sample sets of peer projects, as float arrays: `.npy` (R2DM and LiDARGen range images
//! saved with `numpy.save`) and `.npz` (LiDM's `scripts/sample.py` writes `np.savez(path, batch)`).
//!
//! Only plain little-endian `float32` / `float64` arrays in C order are read (`float64` values are
//! rounded to `float32`, the peers' own precision). **Pickles are refused**, never unpickled: loading
//! one can run arbitrary code. [`refuse_pickle`] recognises them by name (`.pth`, `.pt`, `.pkl`,
//! `.pickle`, `.joblib`, `.ckpt`) and by content (the pickle protocol header `0x80 0x02..=0x05`, or a
//! zip holding a `data.pkl`, PyTorch's format), and `.npy` arrays of Python objects (`dtype=object`)
//! are refused with the same message. The error names the file and says how to convert it.
//!
//! What the values mean (metres, normalised log range, channel order) is the protocol's business; see
//! `veila_metrics::protocol`.

use std::io::Read;
use std::path::Path;

use crate::{Error, Result};

/// One array: its name (`"arr_0"` for a `.npz` member, the file stem for a `.npy`), shape and values
/// (row-major).
#[derive(Debug, Clone, PartialEq)]
pub struct SampleArray {
    /// Member name without `.npy`, or the file name.
    pub name: String,
    /// Shape, outermost first.
    pub shape: Vec<usize>,
    /// The values in C order.
    pub data: Vec<f32>,
}

/// Whether `path` names a `.npy` or `.npz` file.
pub fn is_sample_file(path: &Path) -> bool {
    let name = lower_name(path);
    name.ends_with(".npy") || name.ends_with(".npz")
}

fn lower_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default()
}

/// The most values one file may hold, all its arrays together (2 GiB as `float32`): a sample set
/// beyond it is refused from its headers, before anything is allocated. A 10 MB `.npz` of zeros
/// would otherwise unpack to 10 GB.
pub const MAX_SAMPLE_VALUES: u64 = 1 << 29;

/// Deflate's largest compression ratio (a run of one byte), rounded up.
const MAX_DEFLATE_RATIO: u64 = 1032;

const PICKLE_EXTENSIONS: &[&str] = &[".pth", ".pt", ".pkl", ".pickle", ".joblib", ".ckpt"];

fn pickle_error(path: &Path, what: &str) -> Error {
    Error::format(
        path,
        format!(
            "{what}: Veila never loads pickles (unpickling can run arbitrary code). Save the samples as a \
             plain float array instead, e.g. `numpy.save(\"samples.npy\", tensor.cpu().numpy())` for a \
             PyTorch tensor or `numpy.savez(\"samples.npz\", array)`"
        ),
    )
}

/// `Err` naming the file when `path` is a pickle by name or content (see the module docs); `Ok` for
/// anything else, including unreadable files (their readers report those). Raw `.bin` point files
/// are judged by name only: their first bytes are a float, which may look like a pickle header.
pub fn refuse_pickle(path: &Path) -> Result<()> {
    let name = lower_name(path);
    if let Some(ext) = PICKLE_EXTENSIONS.iter().find(|e| name.ends_with(**e)) {
        return Err(pickle_error(
            path,
            &format!("a `{ext}` file is a Python pickle"),
        ));
    }
    if name.ends_with(".bin") {
        return Ok(());
    }
    let mut head = [0u8; 4];
    let n = std::fs::File::open(path)
        .and_then(|mut f| f.read(&mut head))
        .unwrap_or(0);
    if n >= 2 && head[0] == 0x80 && (2..=5).contains(&head[1]) {
        return Err(pickle_error(path, "the file is a Python pickle"));
    }
    if n >= 4 && head == *b"PK\x03\x04" && !name.ends_with(".npz") {
        // a zip that is not an npz: PyTorch's format when it holds a data.pkl
        if let Ok(f) = std::fs::File::open(path)
            && let Ok(z) = zip::ZipArchive::new(std::io::BufReader::new(f))
            && z.file_names().flatten().any(|n| n.ends_with("data.pkl"))
        {
            return Err(pickle_error(
                path,
                "the file is a PyTorch checkpoint (a zipped pickle)",
            ));
        }
    }
    Ok(())
}

/// Reads the arrays of a `.npy` (one) or `.npz` (each `.npy` member, in name order) file. Errors name
/// the file: pickles, object arrays, other dtypes, Fortran order, or a header whose shape does not fit
/// the bytes present (memory is bounded by the file's size).
pub fn read_sample_arrays(path: &Path) -> Result<Vec<SampleArray>> {
    read_sample_arrays_within(path, MAX_SAMPLE_VALUES)
}

/// [`read_sample_arrays`] with at most `max_values` values in all.
fn read_sample_arrays_within(path: &Path, max_values: u64) -> Result<Vec<SampleArray>> {
    refuse_pickle(path)?;
    let name = lower_name(path);
    if name.ends_with(".npz") {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut zip = zip::ZipArchive::new(std::io::BufReader::new(file))
            .map_err(|e| Error::format(path, format!("not a valid .npz (zip) archive: {e}")))?;
        let mut names = Vec::new();
        for n in zip.file_names() {
            let n =
                n.map_err(|e| Error::format(path, format!("not a valid .npz (zip) archive: {e}")))?;
            names.push(n.into_owned());
        }
        names.sort();
        let mut out = Vec::new();
        let mut budget = max_values;
        for member in names {
            if member.ends_with(".pkl") {
                return Err(pickle_error(path, &format!("member {member} is a pickle")));
            }
            let Some(stem) = member.strip_suffix(".npy") else {
                continue;
            };
            let entry = zip
                .by_name(&member)
                .map_err(|e| Error::format(path, format!("member {member}: {e}")))?;
            let size = entry.size();
            // a compressed member cannot inflate more than deflate's ~1032:1: a forged size in the
            // archive's directory is refused before anything is allocated
            if size > entry.compressed_size().saturating_mul(MAX_DEFLATE_RATIO) + 4096 {
                return Err(Error::format(
                    path,
                    format!(
                        "member {member}: claims {size} bytes from {} compressed (corrupt archive)",
                        entry.compressed_size()
                    ),
                ));
            }
            let what = format!("member {member}");
            let array = read_npy(entry, size, path, stem.to_string(), &what, budget)?;
            budget -= array.data.len() as u64;
            out.push(array);
        }
        if out.is_empty() {
            return Err(Error::format(path, "the .npz archive holds no .npy array"));
        }
        Ok(out)
    } else {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let size = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        Ok(vec![read_npy(
            std::io::BufReader::new(file),
            size,
            path,
            stem,
            "array",
            max_values,
        )?])
    }
}

fn read_npy<R: Read>(
    reader: R,
    bytes: u64,
    path: &Path,
    name: String,
    what: &str,
    budget: u64,
) -> Result<SampleArray> {
    let reader = crate::npy::checked_npy_reader(reader, path, what)?;
    let npy = npyz::NpyFile::new(reader)
        .map_err(|e| Error::format(path, format!("{what}: not a valid .npy array: {e}")))?;
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let dtype = npy.dtype();
    let descr = dtype.descr();
    if descr.contains('O') {
        return Err(pickle_error(
            path,
            &format!("{what} holds Python objects (dtype=object, pickled)"),
        ));
    }
    if npy.order() != npyz::Order::C {
        return Err(Error::format(
            path,
            format!("{what}: Fortran-ordered array; save it with numpy.ascontiguousarray first"),
        ));
    }
    let (is_f32, item) = match &dtype {
        npyz::DType::Plain(ts)
            if ts.type_char() == npyz::TypeChar::Float && ts.size_field() == 4 =>
        {
            (true, 4u64)
        }
        npyz::DType::Plain(ts)
            if ts.type_char() == npyz::TypeChar::Float && ts.size_field() == 8 =>
        {
            (false, 8u64)
        }
        _ => {
            return Err(Error::format(
                path,
                format!("{what}: dtype {descr}; expected float32 or float64"),
            ));
        }
    };
    let count = shape
        .iter()
        .try_fold(1u64, |acc, &d| acc.checked_mul(d as u64))
        .unwrap_or(u64::MAX);
    if count.saturating_mul(item) > bytes {
        return Err(Error::format(
            path,
            format!(
                "{what}: shape {shape:?} needs {} bytes but the data has at most {bytes}",
                count.saturating_mul(item)
            ),
        ));
    }
    if count > budget {
        return Err(Error::format(
            path,
            format!(
                "{what}: shape {shape:?} holds {count} values, more than the {budget} left of the \
                 {MAX_SAMPLE_VALUES} values a sample file may hold in all (split the set into several files)"
            ),
        ));
    }
    let mut data: Vec<f32> = Vec::new();
    data.try_reserve_exact(count as usize).map_err(|_| {
        Error::format(
            path,
            format!("{what}: not enough memory for shape {shape:?} ({count} values)"),
        )
    })?;
    if is_f32 {
        let values = npy
            .data::<f32>()
            .map_err(|e| Error::format(path, format!("{what}: reading float32 data: {e}")))?;
        for v in values {
            data.push(
                v.map_err(|e| Error::format(path, format!("{what}: reading float32 data: {e}")))?,
            );
        }
    } else {
        let values = npy
            .data::<f64>()
            .map_err(|e| Error::format(path, format!("{what}: reading float64 data: {e}")))?;
        for v in values {
            data.push(
                v.map_err(|e| Error::format(path, format!("{what}: reading float64 data: {e}")))?
                    as f32,
            );
        }
    }
    if data.len() as u64 != count {
        return Err(Error::format(
            path,
            format!(
                "{what}: expected {count} values for shape {shape:?}, found {}",
                data.len()
            ),
        ));
    }
    Ok(SampleArray { name, shape, data })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A `.npy` (format 1.0) with dtype `descr`, shape `shape` (Python tuple syntax) and the raw
    /// `payload`, laid out by hand as numpy writes it.
    pub(crate) fn npy_bytes(descr: &str, shape: &str, payload: &[u8]) -> Vec<u8> {
        let mut header =
            format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + header.len() + 1) % 64 != 0 {
            header.push(' ');
        }
        header.push('\n');
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(payload);
        out
    }

    #[test]
    fn reads_f32_and_f64_and_refuses_pickles_and_lies() {
        let dir = tempfile::tempdir().unwrap();
        let f32s: Vec<u8> = [1.0f32, 2.0, 3.0, 4.5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let p = dir.path().join("a.npy");
        std::fs::write(&p, npy_bytes("<f4", "(2, 2)", &f32s)).unwrap();
        let a = read_sample_arrays(&p).unwrap();
        assert_eq!(a[0].shape, vec![2, 2]);
        assert_eq!(a[0].data, vec![1.0, 2.0, 3.0, 4.5]);

        let f64s: Vec<u8> = [0.25f64, -1.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let p = dir.path().join("b.npy");
        std::fs::write(&p, npy_bytes("<f8", "(2,)", &f64s)).unwrap();
        assert_eq!(read_sample_arrays(&p).unwrap()[0].data, vec![0.25, -1.0]);

        // a header that claims more than the file holds is refused before any allocation
        let p = dir.path().join("c.npy");
        std::fs::write(&p, npy_bytes("<f4", "(100000, 100000)", &f32s)).unwrap();
        let e = read_sample_arrays(&p).unwrap_err().to_string();
        assert!(e.contains("c.npy") && e.contains("needs"), "{e}");

        // integer arrays are not samples
        let p = dir.path().join("d.npy");
        std::fs::write(&p, npy_bytes("<i4", "(4,)", &f32s)).unwrap();
        assert!(
            read_sample_arrays(&p)
                .unwrap_err()
                .to_string()
                .contains("expected float32")
        );

        // pickles: by name, by content, as object arrays
        for (name, bytes) in [
            ("s.pth", b"PK\x03\x04rest".to_vec()),
            ("samples.pcd", b"\x80\x04\x95stuff".to_vec()),
            ("o.npy", npy_bytes("|O", "(1,)", b"\x80\x02")),
        ] {
            let p = dir.path().join(name);
            std::fs::write(&p, bytes).unwrap();
            let e = read_sample_arrays(&p).unwrap_err().to_string();
            assert!(
                e.contains(name) && e.contains("never loads pickles"),
                "{name}: {e}"
            );
        }
    }

    #[test]
    fn the_values_of_all_members_together_are_bounded_before_allocation() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("two.npz");
        let zeros = vec![0u8; 4 * 1000];
        {
            let mut z = zip::ZipWriter::new(std::fs::File::create(&p).unwrap());
            let opts = zip::write::SimpleFileOptions::default()
                .compression_method(zip::CompressionMethod::Deflated);
            for m in ["a.npy", "b.npy"] {
                z.start_file(m, opts).unwrap();
                z.write_all(&npy_bytes("<f4", "(1000,)", &zeros)).unwrap();
            }
            z.finish().unwrap();
        }
        // each member fits, both together do not
        assert_eq!(read_sample_arrays_within(&p, 2000).unwrap().len(), 2);
        let e = read_sample_arrays_within(&p, 1500).unwrap_err().to_string();
        assert!(
            e.contains("two.npz") && e.contains("b.npy") && e.contains("500 left"),
            "{e}"
        );
    }

    #[test]
    fn reads_the_lidm_npz_fixture_and_judges_bin_files_by_name() {
        let fixture = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../veila-metrics/tests/data/peer_samples/lidm.npz");
        let a = read_sample_arrays(&fixture).unwrap();
        assert_eq!(a.len(), 1);
        assert_eq!(a[0].name, "arr_0");
        assert_eq!(a[0].shape, vec![2, 16, 128]);
        assert_eq!(a[0].data.len(), 2 * 16 * 128);
        assert!(a[0].data.iter().all(|v| (0.0..=1.0).contains(v)));

        // a KITTI scan whose first float starts with the bytes 0x80 0x03 is a scan, not a pickle
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("000000.bin");
        std::fs::write(&p, [0x80, 0x03, 0x20, 0x41, 0, 0, 0, 0]).unwrap();
        refuse_pickle(&p).unwrap();
        // the same bytes under another name are refused
        let q = dir.path().join("samples.dat");
        std::fs::write(&q, [0x80, 0x03, 0x20, 0x41]).unwrap();
        assert!(refuse_pickle(&q).is_err());
    }
}
