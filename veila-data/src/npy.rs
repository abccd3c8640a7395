//! Feature matrices as `.npy` files (`veila fd`: the features of two sample sets, computed by any
//! network, rows = samples).

use std::path::Path;

use crate::{Error, Result};

/// A 2-D `.npy` matrix of float32 or float64 (C or Fortran order) as `f64`, row-major, with its
/// `(rows, cols)`. Errors name the file: not an `.npy`, not 2-D, empty, another dtype, or a
/// non-finite value (with its row and column).
pub fn read_matrix_f64(path: &Path) -> Result<(Vec<f64>, usize, usize)> {
    let bad = |message: String| Error::Format {
        path: path.to_path_buf(),
        message,
    };
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let npy = npyz::NpyFile::new(std::io::BufReader::new(file))
        .map_err(|e| bad(format!("not a valid .npy file: {e}")))?;
    let shape = npy.shape().to_vec();
    if shape.len() != 2 {
        return Err(bad(format!(
            "expected a 2-D array (samples x features), got shape {shape:?}"
        )));
    }
    let (rows, cols) = (shape[0] as usize, shape[1] as usize);
    if rows == 0 || cols == 0 {
        return Err(bad(format!(
            "the feature matrix is empty (shape {shape:?})"
        )));
    }
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
