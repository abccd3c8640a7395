//! Embeds the bundled default model (`models/default`, a few MiB) into the `veila` binary, so that
//! `cargo install --path veila-cli` gives a binary that generates from any directory. A checkout
//! without the folder builds a binary without it (it then asks for `--model` / `$VEILA_MODEL`).

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

fn main() {
    let manifest_dir = std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR");
    let dir = Path::new(&manifest_dir).join("../models/default");
    println!("cargo:rerun-if-changed={}", dir.display());
    let mut code = String::from(
        "/// The embedded default bundle's files.\npub(crate) const EMBEDDED_MODEL: &[(&str, &[u8])] = &[\n",
    );
    if dir.join("manifest.json").is_file() {
        for name in FILES {
            let path = dir.join(name);
            println!("cargo:rerun-if-changed={}", path.display());
            if path.is_file() {
                let abs = path
                    .canonicalize()
                    .expect("an existing file has a canonical path");
                let _ = writeln!(
                    code,
                    "    ({name:?}, include_bytes!({:?})),",
                    abs.display().to_string()
                );
            }
        }
    }
    code.push_str("];\n");
    let out =
        Path::new(&std::env::var("OUT_DIR").expect("cargo sets OUT_DIR")).join("embedded_model.rs");
    std::fs::write(&out, code).expect("OUT_DIR is writable");
}
