//! Shared parsing of KITTI-style calibration text: one `KEY: v1 v2 ...` (or `KEY v1 v2 ...`) per line.

use std::collections::BTreeMap;
use std::path::Path;

use crate::{Error, Result};

/// Largest deviation of `R^T R` from the identity accepted for the rotation of a rigid transform
/// (calibration files print 7 significant digits: real ones deviate by ~1e-6).
pub(crate) const ROTATION_TOLERANCE: f64 = 1e-3;

/// Refuse a 3x3 block (row-major `rows`) that is not a rotation: `R^T R = I` within
/// [`ROTATION_TOLERANCE`] and `det R = +1` (no scaling, shearing or mirroring).
pub(crate) fn check_rotation(path: &Path, key: &str, rows: [[f64; 3]; 3]) -> Result<()> {
    let mut worst = 0.0f64;
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|k| rows[k][i] * rows[k][j]).sum();
            let want = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((dot - want).abs());
        }
    }
    let r = rows;
    let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
    if worst.is_nan() || worst > ROTATION_TOLERANCE || det <= 0.0 {
        return Err(Error::format(
            path,
            format!(
                "{key} is not a rigid transform: its rotation part deviates from orthonormal by \
                 {worst:.2e} (tolerance {ROTATION_TOLERANCE:.0e}) with determinant {det:.4} \
                 (must be +1: no scaling, shearing or mirroring)"
            ),
        ));
    }
    Ok(())
}

/// The rotation block of a row-major 3x4 transform.
pub(crate) fn rotation_of(m: &[[f32; 4]; 3]) -> [[f64; 3]; 3] {
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = f64::from(m[i][j]);
        }
    }
    r
}

/// Key -> (line number, values).
#[derive(Debug, Clone)]
pub(crate) struct CalibEntries {
    entries: BTreeMap<String, (usize, Vec<f64>)>,
}

impl CalibEntries {
    pub(crate) fn parse(text: &str, path: &Path) -> Result<Self> {
        let mut entries = BTreeMap::new();
        for (i, line) in text.lines().enumerate() {
            let line_no = i + 1;
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let (key, rest) = match line.split_once(':') {
                Some((k, r)) if !k.trim().contains(char::is_whitespace) => (k.trim(), r),
                _ => match line.split_once(char::is_whitespace) {
                    Some((k, r)) => (k, r),
                    None => {
                        return Err(Error::format(
                            path,
                            format!("line {line_no}: `{line}` is not `KEY: numbers`"),
                        ));
                    }
                },
            };
            let mut values = Vec::new();
            for tok in rest.split_whitespace() {
                let v: f64 = tok.parse().map_err(|_| {
                    Error::format(
                        path,
                        format!("line {line_no}, key {key}: malformed number `{tok}`"),
                    )
                })?;
                if !v.is_finite() {
                    return Err(Error::format(
                        path,
                        format!("line {line_no}, key {key}: non-finite number `{tok}`"),
                    ));
                }
                values.push(v);
            }
            if entries.insert(key.to_string(), (line_no, values)).is_some() {
                return Err(Error::format(
                    path,
                    format!("line {line_no}: key {key} appears twice"),
                ));
            }
        }
        Ok(CalibEntries { entries })
    }

    /// Values of the first key in `names` that exists, checked to have `n` numbers.
    pub(crate) fn get(&self, names: &[&str], n: usize, path: &Path) -> Result<Option<Vec<f64>>> {
        for name in names {
            if let Some((line, v)) = self.entries.get(*name) {
                if v.len() != n {
                    return Err(Error::format(
                        path,
                        format!(
                            "line {line}, key {name}: expected {n} numbers, found {}",
                            v.len()
                        ),
                    ));
                }
                return Ok(Some(v.clone()));
            }
        }
        Ok(None)
    }

    pub(crate) fn require(&self, names: &[&str], n: usize, path: &Path) -> Result<Vec<f64>> {
        self.get(names, n, path)?.ok_or_else(|| {
            Error::format(
                path,
                format!("calibration key {} is missing", names.join(" / ")),
            )
        })
    }

    pub(crate) fn require_3x4(&self, names: &[&str], path: &Path) -> Result<[[f32; 4]; 3]> {
        Ok(to_3x4(&self.require(names, 12, path)?))
    }

    pub(crate) fn get_3x4(&self, names: &[&str], path: &Path) -> Result<Option<[[f32; 4]; 3]>> {
        Ok(self.get(names, 12, path)?.map(|v| to_3x4(&v)))
    }
}

pub(crate) fn to_3x4(v: &[f64]) -> [[f32; 4]; 3] {
    let mut m = [[0f32; 4]; 3];
    for r in 0..3 {
        for c in 0..4 {
            m[r][c] = v[r * 4 + c] as f32;
        }
    }
    m
}
