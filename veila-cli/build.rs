//! Embeds the bundled default model (`models/default`, a few MiB) and the bundled segmenter
//! (`models/segmenter`, under 2 MiB) into the `veila` binary, so that `cargo install --path
//! veila-cli` gives a binary that generates and segments from any directory. A checkout without a
//! folder builds a binary without it (it then asks for `--model` / `$VEILA_MODEL`).

use std::fmt::Write;
use std::path::Path;

/// Every file a bundle folder can hold (`veila_diffusion::app::bundle`'s names).
const FILES: &[&str] = &[
    "manifest.json",
    "bundle.json",
    "semantic_encoder.safetensors",
    "depth_encoder.safetensors",
    "denoiser.safetensors",
    "mean.safetensors",
];

/// The files of a segmenter folder (`veila_diffusion::app::segment::model`'s names).
const SEGMENTER_FILES: &[&str] = &["manifest.json", "segmenter.json", "segmenter.safetensors"];

/// `pub(crate) const NAME: &[(&str, &[u8])]` with the files of `dir` that `files` names (none
/// without its `manifest.json`).
fn embed(code: &mut String, name: &str, what: &str, dir: &Path, files: &[&str]) {
    println!("cargo:rerun-if-changed={}", dir.display());
    let _ = writeln!(
        code,
        "/// The embedded {what}'s files.\npub(crate) const {name}: &[(&str, &[u8])] = &["
    );
    if dir.join("manifest.json").is_file() {
        for file in files {
            let path = dir.join(file);
            println!("cargo:rerun-if-changed={}", path.display());
            if path.is_file() {
                let abs = path
                    .canonicalize()
                    .expect("an existing file has a canonical path");
                let _ = writeln!(
                    code,
                    "    ({file:?}, include_bytes!({:?})),",
                    abs.display().to_string()
                );
            }
        }
    }
    code.push_str("];\n");
}

fn main() {
    let manifest_dir = std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR");
    let models = Path::new(&manifest_dir).join("../models");
    let mut code = String::new();
    embed(
        &mut code,
        "EMBEDDED_MODEL",
        "default bundle",
        &models.join("default"),
        FILES,
    );
    embed(
        &mut code,
        "EMBEDDED_SEGMENTER",
        "bundled segmenter",
        &models.join("segmenter"),
        SEGMENTER_FILES,
    );
    let out =
        Path::new(&std::env::var("OUT_DIR").expect("cargo sets OUT_DIR")).join("embedded_model.rs");
    std::fs::write(&out, code).expect("OUT_DIR is writable");
}
