//! Feature matrices as `.npy` files (`veila fd`: the features of two sample sets, computed by any
//! network, rows = samples).

use std::io::Read;
use std::path::Path;

use crate::{Error, Result};

/// The longest `.npy` header read (the dictionary text): numpy writes under 1 KiB for any real
/// array.
const MAX_NPY_HEADER_BYTES: usize = 1 << 20;

/// `reader`, a `.npy` stream, with its header read ahead and checked before the `npyz` crate
/// parses it: the element count of its shape, and every partial product of its dimensions (the
/// strides of either order; zero dimensions aside), must fit in 64 bits (`npyz` multiplies them
/// unchecked: a shape of `(4294967296, 4294967296)` overflowed, a panic in a build with overflow
/// checks and a wrong count without). What is not a `.npy` header, or a shape it cannot read, is
/// left to `npyz` to refuse. The returned reader yields the whole stream, header included.
/// `what` names the array in errors ("array", "member arr_0.npy").
pub(crate) fn checked_npy_reader<R: Read>(
    mut reader: R,
    path: &Path,
    what: &str,
) -> Result<std::io::Chain<std::io::Cursor<Vec<u8>>, R>> {
    let mut head = vec![0u8; 10];
    let got = read_up_to(&mut reader, &mut head, path)?;
    head.truncate(got);
    let len_bytes = match head.get(6) {
        Some(1) if head.starts_with(b"\x93NUMPY") => 2,
        Some(2 | 3) if head.starts_with(b"\x93NUMPY") => 4,
        _ => return Ok(std::io::Cursor::new(head).chain(reader)),
    };
    if len_bytes == 4 {
        let mut more = [0u8; 2];
        let n = read_up_to(&mut reader, &mut more, path)?;
        head.extend_from_slice(&more[..n]);
    }
    if head.len() < 8 + len_bytes {
        return Ok(std::io::Cursor::new(head).chain(reader));
    }
    let mut n = [0u8; 4];
    n[..len_bytes].copy_from_slice(&head[8..8 + len_bytes]);
    let header_len = u32::from_le_bytes(n) as usize;
    if header_len > MAX_NPY_HEADER_BYTES {
        return Err(Error::format(
            path,
            format!(
                "{what}: a .npy header of {header_len} bytes, more than the {MAX_NPY_HEADER_BYTES} \
                 a header may have"
            ),
        ));
    }
    let start = head.len();
    head.resize(start + header_len, 0);
    let got = read_up_to(&mut reader, &mut head[start..], path)?;
    head.truncate(start + got);
    let text = String::from_utf8_lossy(&head[start..]);
    if let Some(dims) = shape_of(&text) {
        let product = dims
            .iter()
            .filter(|d| **d != 0)
            .try_fold(1u64, |acc, d| acc.checked_mul(*d));
        if product.is_none() {
            return Err(Error::format(
                path,
                format!(
                    "{what}: shape {dims:?} has more elements than 64 bits count (a corrupt or \
                     forged .npy header)"
                ),
            ));
        }
    }
    Ok(std::io::Cursor::new(head).chain(reader))
}

/// Reads into `buf` until it is full or the stream ends; the bytes read.
fn read_up_to(reader: &mut impl Read, buf: &mut [u8], path: &Path) -> Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match reader.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(k) => got += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(Error::io(path, e)),
        }
    }
    Ok(got)
}

/// The dimensions of the `shape` tuple of a `.npy` header dictionary, where every one is a
/// decimal integer that fits in 64 bits (else `None`: `npyz` judges it).
fn shape_of(header: &str) -> Option<Vec<u64>> {
    let at = header
        .find("'shape'")
        .or_else(|| header.find("\"shape\""))?;
    let rest = &header[at + "'shape'".len()..];
    let rest = rest.trim_start().strip_prefix(':')?.trim_start();
    let inner = rest.strip_prefix('(')?;
    let inner = &inner[..inner.find(')')?];
    inner
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<u64>().ok())
        .collect()
}

/// A 2-D `.npy` matrix of float32 or float64 (C or Fortran order) as `f64`, row-major, with its
/// `(rows, cols)`. Errors name the file: not an `.npy`, not 2-D, empty, another dtype, or a
/// non-finite value (with its row and column).
pub fn read_matrix_f64(path: &Path) -> Result<(Vec<f64>, usize, usize)> {
    let bad = |message: String| Error::Format {
        path: path.to_path_buf(),
        message,
    };
    crate::read_capped::check_regular_file(path)?;
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let reader = checked_npy_reader(std::io::BufReader::new(file), path, "array")?;
    let npy = npyz::NpyFile::new(reader).map_err(|e| bad(format!("not a valid .npy file: {e}")))?;
    let shape = npy.shape().to_vec();
    if shape.len() != 2 {
        return Err(bad(format!(
            "expected a 2-D array (samples x features), got shape {shape:?}"
        )));
    }
    if shape[0] == 0 || shape[1] == 0 {
        return Err(bad(format!(
            "the feature matrix is empty (shape {shape:?})"
        )));
    }
    // the values the shape claims must be in the file (at 4 bytes each at least), before any
    // buffer is sized by them
    let claimed = shape[0].saturating_mul(shape[1]).saturating_mul(4);
    if claimed > file_len {
        return Err(bad(format!(
            "shape {shape:?} needs at least {claimed} bytes of values, the file has {file_len}"
        )));
    }
    let (rows, cols) = (shape[0] as usize, shape[1] as usize);
    let order = npy.order();
    let dtype = npy.dtype();
    let data: Vec<f64> = match &dtype {
        npyz::DType::Plain(ts)
            if ts.type_char() == npyz::TypeChar::Float && ts.size_field() == 4 =>
        {
            npy.into_vec::<f32>()
                .map_err(|e| bad(format!("reading f32 data: {e}")))?
                .into_iter()
                .map(f64::from)
                .collect()
        }
        npyz::DType::Plain(ts)
            if ts.type_char() == npyz::TypeChar::Float && ts.size_field() == 8 =>
        {
            npy.into_vec::<f64>()
                .map_err(|e| bad(format!("reading f64 data: {e}")))?
        }
        other => {
            return Err(bad(format!(
                "unsupported dtype {}; expected float32 or float64",
                other.descr()
            )));
        }
    };
    if data.len() != rows * cols {
        return Err(bad(format!(
            "expected {} values for shape {shape:?}, found {}",
            rows * cols,
            data.len()
        )));
    }
    let data = match order {
        npyz::Order::C => data,
        npyz::Order::Fortran => {
            let mut c = vec![0.0; rows * cols];
            for j in 0..cols {
                for i in 0..rows {
                    c[i * cols + j] = data[j * rows + i];
                }
            }
            c
        }
    };
    if let Some(k) = data.iter().position(|v| !v.is_finite()) {
        return Err(bad(format!(
            "non-finite value at row {}, column {}",
            k / cols,
            k % cols
        )));
    }
    Ok((data, rows, cols))
}
