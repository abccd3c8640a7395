//! The wheel (`python/`, a workspace of its own) turns on the same features of every shared
//! dependency as the workspace's test build, so that CI's wheel build reuses the dependencies
//! `cargo test --workspace` compiled: one feature apart (syn's `full`, say) and cargo compiles that
//! crate and everything above it a second time, minutes on two cores. `python/Cargo.toml` lists the
//! dependencies it declares for their features alone.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;

/// Registry crates whose features may differ, with the reason.
const ALLOWED: &[(&str, &str)] = &[(
    "num-integer",
    "numpy's ndarray turns on its default feature; only npyz's small number crates are rebuilt",
)];

/// Feature sets by package (`name vX.Y.Z`) in `cargo tree --format {p}|{f}` output; a package built
/// for the host and the target with other features has two sets.
fn feature_sets(tree: &str) -> BTreeMap<String, BTreeSet<String>> {
    let mut out: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for line in tree.lines() {
        let line = line.trim().trim_end_matches(" (*)");
        let Some((package, features)) = line.split_once('|') else {
            continue;
        };
        let package = package.trim_end_matches(" (*)").trim();
        if package.is_empty() || package.contains(" (/") {
            continue; // a path crate: ours, compiled per build anyway
        }
        out.entry(package.to_string())
            .or_default()
            .insert(features.trim_end_matches(" (*)").to_string());
    }
    out
}

/// The packages both builds use whose feature sets differ and that [`ALLOWED`] does not name.
fn mismatches(
    workspace: &BTreeMap<String, BTreeSet<String>>,
    wheel: &BTreeMap<String, BTreeSet<String>>,
) -> Vec<String> {
    wheel
        .iter()
        .filter_map(|(package, sets)| {
            let theirs = workspace.get(package)?;
            let name = package.split_whitespace().next().unwrap_or_default();
            (sets != theirs && !ALLOWED.iter().any(|(a, _)| *a == name)).then(|| {
                format!(
                    "{package}: the wheel builds it with {sets:?}, the workspace with {theirs:?}"
                )
            })
        })
        .collect()
}

fn tree(root: &Path, args: &[&str]) -> String {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .arg("tree")
        .args(args)
        .args(["--prefix", "none", "--format", "{p}|{f}", "--offline"])
        .current_dir(root)
        .output()
        .expect("cargo tree runs");
    assert!(
        out.status.success(),
        "cargo tree {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn the_wheel_reuses_the_workspace_dependencies() {
    let root = super::workspace_root();
    let workspace = feature_sets(&tree(&root, &["--workspace", "-e", "normal,build,dev"]));
    let wheel = feature_sets(&tree(
        &root,
        &["--manifest-path", "python/Cargo.toml", "-e", "normal,build"],
    ));
    assert!(
        wheel.keys().any(|p| p.starts_with("candle-core ")),
        "unexpected cargo tree output"
    );
    let bad = mismatches(&workspace, &wheel);
    assert!(
        bad.is_empty(),
        "python/Cargo.toml: turn on the workspace's features of these dependencies (its unused \
         dependencies are there for that), or CI compiles them twice:\n{}",
        bad.join("\n")
    );
}

#[test]
fn feature_check_finds_a_differing_feature_and_only_that() {
    let ws = feature_sets(
        "syn v3.0.9|derive,full\nserde v1.0.0|std\nnum-integer v0.1.0|std\nveila-nn v0.1.0 (/x)|\n",
    );
    let py = feature_sets(
        "syn v3.0.9|derive (*)\nserde v1.0.0|std\nnum-integer v0.1.0|default,std\n\
         veila-nn v0.1.0 (/x)|cuda\npyo3 v0.27.0|\n",
    );
    let bad = mismatches(&ws, &py);
    assert_eq!(bad.len(), 1, "{bad:?}");
    assert!(bad[0].starts_with("syn v3.0.9"), "{bad:?}");
}
