//! A benchmark's report folder (feature `sim`): created if need be, with `report.json` and
//! `report.md` written atomically; the plots beside them are each benchmark's own.

use std::path::Path;

use serde::Serialize;
use veila_data::atomic::write_atomic;

use crate::error::{Error, Result};

/// Writes `report` as `out/report.json` and `markdown` as `out/report.md`.
pub fn write_report_files(out: &Path, report: &impl Serialize, markdown: &str) -> Result<()> {
    std::fs::create_dir_all(out).map_err(|source| Error::Io {
        action: "creating the report folder",
        path: out.to_path_buf(),
        source,
    })?;
    let json_path = out.join("report.json");
    let json = serde_json::to_string_pretty(report).map_err(|source| Error::Json {
        path: json_path.clone(),
        source,
    })?;
    write_atomic(&json_path, json.as_bytes())?;
    write_atomic(&out.join("report.md"), markdown.as_bytes())?;
    Ok(())
}
