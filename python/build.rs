//! Embeds `../models/default` (every file its manifest lists) in the extension, so `veila.generate`
//! works from the wheel alone. The file list comes from the manifest, so a retrained bundle with
//! other files (e.g. residual diffusion's `mean.safetensors`) needs no change here.

use std::fmt::Write as _;
use std::path::PathBuf;

fn main() {
    let dir = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("set by cargo"))
        .join("../models/default");
    let manifest_path = dir.join("manifest.json");
    println!("cargo::rerun-if-changed={}", manifest_path.display());
    let manifest = std::fs::read_to_string(&manifest_path)
        .unwrap_or_else(|e| panic!("{}: {e}", manifest_path.display()));
    let manifest: serde_json::Value = serde_json::from_str(&manifest)
        .unwrap_or_else(|e| panic!("{}: {e}", manifest_path.display()));
    let mut names: Vec<&str> = manifest["files"]
        .as_object()
        .unwrap_or_else(|| panic!("{}: no \"files\" object", manifest_path.display()))
        .keys()
        .map(String::as_str)
        .collect();
    names.push("manifest.json");
    names.sort_unstable();
    names.dedup();
    let mut code = String::from("static DEFAULT_MODEL: &[(&str, &[u8])] = &[\n");
    for name in names {
        assert!(
            !name.contains(['/', '\\', '"']),
            "{}: odd file name {name:?}",
            manifest_path.display()
        );
        let path = dir.join(name);
        println!("cargo::rerun-if-changed={}", path.display());
        let path = path
            .canonicalize()
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        writeln!(code, "    ({name:?}, include_bytes!({path:?})),").expect("string");
    }
    code.push_str("];\n");
    let out =
        PathBuf::from(std::env::var("OUT_DIR").expect("set by cargo")).join("default_model.rs");
    std::fs::write(&out, code).unwrap_or_else(|e| panic!("{}: {e}", out.display()));
}
