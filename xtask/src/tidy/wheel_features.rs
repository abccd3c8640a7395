//! The wheel (`python/`, a workspace of its own) turns on the same features of every shared
//! dependency as the workspace's test build, so that CI's wheel build reuses the dependencies
//! `cargo test --workspace` compiled: one feature apart (syn's `full`, say) and cargo compiles that
//! crate and everything above it a second time, minutes on two cores. `python/Cargo.toml` lists the
//! dependencies it declares for their features alone. The same holds for the dev profile: one
//! opt-level apart and the crate is compiled again.

use std::collections::{BTreeMap, BTreeSet};

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

fn tree(args: &[&str]) -> String {
    let mut all = vec!["tree"];
    all.extend_from_slice(args);
    all.extend_from_slice(&["--prefix", "none", "--format", "{p}|{f}"]);
    super::cargo_offline(&all)
}

/// The wheel's `cargo tree`, after fetching its dependencies the way `.ci/run` does when the
/// local registry lacks them (a fresh machine's `cargo test --workspace` fetched only the
/// workspace's); `None`, with a message saying what to run, where they cannot be fetched.
fn wheel_tree() -> Option<String> {
    let manifest = "python/Cargo.toml";
    let args = ["--manifest-path", manifest, "-e", "normal,build"];
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let run = |args: &[&str]| {
        std::process::Command::new(&cargo)
            .args(args)
            .current_dir(super::workspace_root())
            .output()
            .expect("cargo runs")
    };
    let mut offline = vec!["tree", "--offline"];
    offline.extend_from_slice(&args);
    offline.extend_from_slice(&["--prefix", "none", "--format", "{p}|{f}"]);
    let first = run(&offline);
    if first.status.success() {
        return Some(String::from_utf8_lossy(&first.stdout).into_owned());
    }
    let fetched = run(&["fetch", "--locked", "--manifest-path", manifest]);
    if !fetched.status.success() {
        eprintln!(
            "skipped: the wheel's dependencies are not in the local registry and could not be \
             fetched ({}); run `cargo fetch --locked --manifest-path {manifest}` once online",
            String::from_utf8_lossy(&fetched.stderr).trim()
        );
        return None;
    }
    Some(tree(&args))
}

#[test]
fn the_wheel_reuses_the_workspace_dependencies() {
    let Some(wheel) = wheel_tree() else { return };
    let workspace = feature_sets(&tree(&["--workspace", "-e", "normal,build,dev"]));
    let wheel = feature_sets(&wheel);
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

/// The `[profile.dev]` and `[profile.dev.package]` tables of a manifest, as their setting lines
/// (comments and blank lines dropped), in order.
fn dev_profile(manifest: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut inside = false;
    for line in manifest.lines() {
        let line = line.split('#').next().unwrap_or_default().trim();
        if line.starts_with('[') {
            inside = line == "[profile.dev]" || line == "[profile.dev.package]";
            if inside {
                out.push(line.to_string());
            }
        } else if inside && !line.is_empty() {
            out.push(line.to_string());
        }
    }
    out
}

/// The package a `[profile.dev.package]` line sets (`syn = { ... }` -> `syn`, `"*" = ...` -> `*`);
/// `None` for other lines.
fn setting_package(line: &str) -> Option<&str> {
    let (key, value) = line.split_once('=')?;
    value
        .trim_start()
        .starts_with('{')
        .then(|| key.trim().trim_matches('"'))
}

#[test]
fn the_wheel_builds_with_the_workspace_dev_profile() {
    let read = |path: &str| {
        std::fs::read_to_string(super::workspace_root().join(path))
            .unwrap_or_else(|e| panic!("{path}: {e}"))
    };
    // the wheel's build uses fewer packages: a setting for one it does not use is left out
    let Some(wheel_packages) = wheel_tree() else {
        return;
    };
    let used: BTreeSet<String> = feature_sets(&wheel_packages)
        .into_keys()
        .filter_map(|p| p.split_whitespace().next().map(str::to_string))
        .collect();
    let workspace: Vec<String> = dev_profile(&read("Cargo.toml"))
        .into_iter()
        .filter(|line| setting_package(line).is_none_or(|p| p == "*" || used.contains(p)))
        .collect();
    let wheel = dev_profile(&read("python/Cargo.toml"));
    assert!(
        workspace.iter().any(|l| l.starts_with("\"*\"")),
        "Cargo.toml: no [profile.dev.package] \"*\" line"
    );
    assert_eq!(
        wheel, workspace,
        "python/Cargo.toml's [profile.dev] and [profile.dev.package] must equal the workspace's, \
         or CI's wheel build compiles every dependency whose settings differ a second time"
    );
}

#[test]
fn profile_check_reads_settings_and_skips_comments_and_other_tables() {
    let a = "[profile.dev]\nopt-level = 1 # ours\n\n[profile.dev.package]\n# deps\n\"*\" = { opt-level = 1 }\n\
             [profile.release]\nopt-level = 3\n";
    let b = "[profile.dev]\nopt-level = 1\n[profile.dev.package]\n\"*\" = { opt-level = 2 }\n";
    assert_eq!(
        dev_profile(a),
        [
            "[profile.dev]",
            "opt-level = 1",
            "[profile.dev.package]",
            "\"*\" = { opt-level = 1 }"
        ]
    );
    assert_ne!(dev_profile(a), dev_profile(b));
    assert_eq!(setting_package("\"*\" = { opt-level = 1 }"), Some("*"));
    assert_eq!(setting_package("syn = { opt-level = 0 }"), Some("syn"));
    assert_eq!(setting_package("opt-level = 1"), None);
}
