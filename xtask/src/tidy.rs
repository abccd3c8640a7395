//! Tidy checks run by `cargo test` (there are no extra checks in CI): the workspace's layering rules,
//! read from `cargo metadata`, and the "no file IO below veila-data" invariant, read from the sources.
//! ARCHITECTURE.md states the same rules in words; keep the two in step.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

mod architecture;
mod import_cycles;
mod lean;
mod sizes;
mod wheel_features;

/// Workspace crates each crate may depend on (any dependency kind). Anything above is a layering break.
const INTERNAL_ALLOWED: &[(&str, &[&str])] = &[
    ("veila-geom", &[]),
    ("veila-data", &["veila-geom"]),
    ("veila-nn", &["veila-geom"]),
    (
        "veila-diffusion",
        &["veila-geom", "veila-data", "veila-nn", "veila-metrics"],
    ),
    ("veila-metrics", &["veila-geom"]),
    (
        "veila-cli",
        &[
            "veila-geom",
            "veila-data",
            "veila-nn",
            "veila-diffusion",
            "veila-metrics",
        ],
    ),
    (
        "xtask",
        &[
            "veila-geom",
            "veila-data",
            "veila-nn",
            "veila-diffusion",
            "veila-metrics",
        ],
    ),
];

/// The only normal (non-dev) external dependencies veila-geom may have.
const GEOM_EXTERNAL: &[&str] = &["glam", "serde", "thiserror"];

/// External crates a library must not depend on (normal dependencies), with the reason.
const FORBIDDEN: &[(&str, &str, &str)] = &[
    (
        "veila-metrics",
        "candle-core",
        "metrics take points and feature vectors, not networks",
    ),
    (
        "veila-metrics",
        "candle-nn",
        "metrics take points and feature vectors, not networks",
    ),
    (
        "veila-data",
        "candle-core",
        "data IO must not pull in the model stack",
    ),
    (
        "veila-data",
        "candle-nn",
        "data IO must not pull in the model stack",
    ),
    (
        "veila-nn",
        "exr",
        "dataset and image formats live in veila-data",
    ),
    (
        "veila-nn",
        "image",
        "dataset and image formats live in veila-data",
    ),
    (
        "veila-diffusion",
        "exr",
        "dataset and image formats live in veila-data",
    ),
    (
        "veila-diffusion",
        "image",
        "dataset and image formats live in veila-data",
    ),
    (
        "veila-metrics",
        "exr",
        "dataset and image formats live in veila-data",
    ),
    (
        "veila-metrics",
        "image",
        "dataset and image formats live in veila-data",
    ),
];

const LIBRARIES: &[&str] = &[
    "veila-geom",
    "veila-data",
    "veila-nn",
    "veila-diffusion",
    "veila-metrics",
];

struct Dep {
    name: String,
    kind: String,
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("xtask sits in the workspace")
        .to_path_buf()
}

/// Stdout of `cargo ARGS --offline` in the workspace root (the checks read cargo's own view).
fn cargo_offline(args: &[&str]) -> String {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(args)
        .arg("--offline")
        .current_dir(workspace_root())
        .output()
        .expect("cargo runs");
    assert!(
        out.status.success(),
        "cargo {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn metadata() -> BTreeMap<String, Vec<Dep>> {
    let out = cargo_offline(&["metadata", "--format-version", "1", "--no-deps"]);
    let v: serde_json::Value = serde_json::from_str(&out).expect("cargo metadata prints JSON");
    let mut map = BTreeMap::new();
    for pkg in v["packages"].as_array().expect("packages array") {
        let name = pkg["name"].as_str().expect("package name").to_string();
        let deps = pkg["dependencies"]
            .as_array()
            .expect("dependencies array")
            .iter()
            .map(|d| Dep {
                name: d["name"].as_str().expect("dependency name").to_string(),
                kind: d["kind"].as_str().unwrap_or("normal").to_string(),
            })
            .collect();
        map.insert(name, deps);
    }
    map
}

/// The pure check, separated from `cargo metadata` so that it can be tested on made-up graphs.
fn layering_violations(graph: &BTreeMap<String, Vec<Dep>>) -> Vec<String> {
    let allowed: BTreeMap<&str, BTreeSet<&str>> = INTERNAL_ALLOWED
        .iter()
        .map(|(k, v)| (*k, v.iter().copied().collect()))
        .collect();
    let mut problems = Vec::new();
    for (krate, deps) in graph {
        let Some(ok) = allowed.get(krate.as_str()) else {
            problems.push(format!("{krate}: a workspace member with no layering rule (add it to tidy.rs and ARCHITECTURE.md)"));
            continue;
        };
        for d in deps {
            if allowed.contains_key(d.name.as_str()) && !ok.contains(d.name.as_str()) {
                problems.push(format!(
                    "{krate} depends on {} ({}): breaks the layering",
                    d.name, d.kind
                ));
            }
            if d.kind == "normal" {
                if krate == "veila-geom" && !GEOM_EXTERNAL.contains(&d.name.as_str()) {
                    problems.push(format!(
                        "veila-geom depends on {}: only {GEOM_EXTERNAL:?} are allowed",
                        d.name
                    ));
                }
                if LIBRARIES.contains(&krate.as_str()) && d.name == "anyhow" {
                    problems.push(format!(
                        "{krate} depends on anyhow: libraries use their own thiserror enum"
                    ));
                }
                for (k, forbidden, why) in FORBIDDEN {
                    if krate == k && d.name == *forbidden {
                        problems.push(format!("{krate} depends on {forbidden}: {why}"));
                    }
                }
            }
        }
    }
    problems
}

#[test]
fn workspace_layering_holds() {
    let graph = metadata();
    for krate in INTERNAL_ALLOWED.iter().map(|(k, _)| k) {
        assert!(
            graph.contains_key(*krate),
            "workspace member {krate} is missing"
        );
    }
    let problems = layering_violations(&graph);
    assert!(
        problems.is_empty(),
        "layering violations:\n{}",
        problems.join("\n")
    );
}

#[test]
fn layering_check_catches_an_upward_dependency() {
    let mut graph = BTreeMap::new();
    graph.insert(
        "veila-geom".to_string(),
        vec![Dep {
            name: "veila-data".into(),
            kind: "dev".into(),
        }],
    );
    graph.insert(
        "veila-metrics".to_string(),
        vec![
            Dep {
                name: "candle-core".into(),
                kind: "normal".into(),
            },
            Dep {
                name: "veila-geom".into(),
                kind: "normal".into(),
            },
        ],
    );
    graph.insert(
        "veila-data".to_string(),
        vec![Dep {
            name: "anyhow".into(),
            kind: "normal".into(),
        }],
    );
    let problems = layering_violations(&graph);
    assert_eq!(problems.len(), 3, "{problems:#?}");
    assert!(problems[0].contains("veila-data depends on anyhow"));
    assert!(problems[1].contains("veila-geom depends on veila-data"));
    assert!(problems[2].contains("veila-metrics depends on candle-core"));
}

/// Source files under `dir` (recursively) containing any of `needles`, as `path: needle`.
fn grep(dir: &Path, needles: &[&str]) -> Vec<String> {
    let mut hits = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).expect("readable source directory") {
            let path = entry.expect("directory entry").path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = std::fs::read_to_string(&path).expect("readable source file");
                for n in needles {
                    if text.contains(n) {
                        hits.push(format!("{}: {n}", path.display()));
                    }
                }
            }
        }
    }
    hits
}

#[test]
fn no_file_io_in_pure_crates() {
    let root = workspace_root();
    let needles = [
        "std::fs",
        "File::open",
        "File::create",
        "fs::read",
        "fs::write",
    ];
    for krate in ["veila-geom", "veila-metrics"] {
        let hits = grep(&root.join(krate).join("src"), &needles);
        assert!(
            hits.is_empty(),
            "{krate} must not do file IO (that is veila-data's job):\n{}",
            hits.join("\n")
        );
    }
}

#[test]
fn every_library_has_crate_docs_with_an_example() {
    let root = workspace_root();
    for krate in LIBRARIES {
        let lib =
            std::fs::read_to_string(root.join(krate).join("src/lib.rs")).expect("lib.rs exists");
        assert!(
            lib.trim_start().starts_with("//!"),
            "{krate}/src/lib.rs must open with crate docs"
        );
        assert!(
            lib.contains("//! ```"),
            "{krate}/src/lib.rs crate docs need a runnable example"
        );
    }
}

/// The crates only the application module (`src/app/`, the `app` feature) of `veila-diffusion`
/// may name.
const APP_ONLY_CRATES: [&str; 3] = ["veila_nn", "veila_data", "veila_metrics"];

/// Files of `veila-diffusion/src` outside the application module (`src/app/`) that name one of
/// [`APP_ONLY_CRATES`]. The crate's one error enum (`error.rs`) is the single exception: it wraps
/// their errors, each variant behind the `app` feature.
fn diffusion_core_naming_app_crates() -> Vec<String> {
    let src = workspace_root().join("veila-diffusion/src");
    grep(&src, &APP_ONLY_CRATES)
        .into_iter()
        .filter(|hit| {
            let path = Path::new(hit.split(": ").next().unwrap_or(""));
            !(path.starts_with(src.join("app")) || path == src.join("error.rs"))
        })
        .collect()
}

#[test]
fn diffusion_core_names_no_application_crate() {
    let hits = diffusion_core_naming_app_crates();
    assert!(
        hits.is_empty(),
        "the generic diffusion core must not name veila-nn, veila-data or veila-metrics (they belong in src/app/, behind the `app` feature):\n{}",
        hits.join("\n")
    );
    // the check looks where those crates are named: the application module names each
    for krate in APP_ONLY_CRATES {
        let app = grep(&workspace_root().join("veila-diffusion/src/app"), &[krate]);
        assert!(!app.is_empty(), "the grep finds no {krate} in src/app/");
    }
}

/// `(importer, imported)` for every command module of `dir` (`*_cmd.rs`) that names another
/// command module (`crate::other_cmd` or `other_cmd` inside a `use crate::{..}` list).
fn command_imports(dir: &Path) -> Vec<(String, String)> {
    let mut commands: Vec<(String, String)> = std::fs::read_dir(dir)
        .expect("readable source directory")
        .filter_map(|e| {
            let path = e.expect("directory entry").path();
            let stem = path.file_stem()?.to_str()?.to_string();
            stem.ends_with("_cmd").then(|| {
                // a command is a file or a folder of files (`bench_cmd/`): all of its text
                let text = if path.is_dir() {
                    let mut files: Vec<_> = std::fs::read_dir(&path)
                        .expect("readable command folder")
                        .map(|e| e.expect("directory entry").path())
                        .filter(|p| p.extension().is_some_and(|x| x == "rs"))
                        .collect();
                    files.sort();
                    files
                        .iter()
                        .map(|f| std::fs::read_to_string(f).expect("readable source file"))
                        .collect::<Vec<_>>()
                        .join("\n")
                } else {
                    std::fs::read_to_string(&path).expect("readable source file")
                };
                (stem, text)
            })
        })
        .collect();
    commands.sort();
    let mut found = Vec::new();
    for (name, text) in &commands {
        let flat: String = text.split_whitespace().collect();
        let uses: Vec<&str> = flat
            .split("usecrate::")
            .skip(1)
            .map(|rest| rest.split(';').next().unwrap_or(""))
            .collect();
        for (other, _) in &commands {
            if other == name {
                continue;
            }
            let named_in_use = uses.iter().any(|u| {
                u.split(|c: char| !(c.is_alphanumeric() || c == '_'))
                    .any(|seg| seg == other)
            });
            if named_in_use || flat.contains(&format!("crate::{other}")) {
                found.push((name.clone(), other.clone()));
            }
        }
    }
    found
}

#[test]
fn no_command_imports_another_command() {
    let dir = workspace_root().join("veila-cli/src");
    let found = command_imports(&dir);
    assert!(
        found.is_empty(),
        "commands import other commands (move the shared part into veila_diffusion::app or a shared CLI module): {found:?}"
    );
}

#[test]
fn command_import_check_catches_an_import() {
    let dir = tempfile::tempdir().expect("temporary folder");
    std::fs::write(
        dir.path().join("a_cmd.rs"),
        "use crate::{\n    b_cmd::{X, Y},\n    model,\n};\n",
    )
    .unwrap();
    std::fs::write(
        dir.path().join("b_cmd.rs"),
        "use crate::model;\nfn f() { crate::c_cmd::g(); }\n",
    )
    .unwrap();
    std::fs::write(dir.path().join("c_cmd.rs"), "use crate::progress;\n").unwrap();
    assert_eq!(
        command_imports(dir.path()),
        [
            ("a_cmd".to_string(), "b_cmd".to_string()),
            ("b_cmd".to_string(), "c_cmd".to_string())
        ]
    );
}
