//! Library crates a downstream project can pick lean:
//! - veila-data without features: a project that reads KITTI compiles no ray tracer, random-number
//!   stack or plotting library. Those come with the `sim`, `weather`, `augment` and `vis` features.
//! - veila-diffusion without its default `app` feature: the schedules, objectives, samplers and
//!   trainer on candle and `veila-geom` alone, without the network, data or metrics crates.

/// Crates (name prefixes) that `veila-data` without features must not pull in, with the feature
/// that brings each.
const HEAVY: &[(&str, &str)] = &[
    ("obvhs", "sim"),
    ("rand", "sim / weather / augment"),
    ("plotters", "vis"),
    ("colorous", "vis"),
    ("ab_glyph", "vis"),
];

/// Crates `veila-diffusion` without default features must not pull in.
const DIFFUSION_APP: &[(&str, &str)] = &[
    ("veila-nn", "app"),
    ("veila-data", "app"),
    ("veila-metrics", "app"),
];

/// The offending lines of `cargo tree --prefix none --format {p}` output (`name vX.Y.Z ...`):
/// the crates of `heavy` (name prefixes, each with its feature).
fn heavy_crates(tree: &str, heavy: &[(&str, &str)]) -> Vec<String> {
    let mut hits: Vec<String> = tree
        .lines()
        .filter_map(|line| {
            let name = line.split_whitespace().next()?;
            heavy
                .iter()
                .find(|(h, _)| {
                    name == *h
                        || name.starts_with(&format!("{h}_"))
                        || name.starts_with(&format!("{h}-"))
                })
                .map(|(_, feature)| format!("{name} (belongs behind the `{feature}` feature)"))
        })
        .collect();
    hits.sort();
    hits.dedup();
    hits
}

/// `cargo tree` of `package` without default features: normal dependencies, one per line.
fn tree_without_defaults(package: &str) -> String {
    let tree = super::cargo_offline(&[
        "tree",
        "-p",
        package,
        "--no-default-features",
        "-e",
        "normal",
        "--prefix",
        "none",
        "--format",
        "{p}",
    ]);
    assert!(
        tree.contains("veila-geom"),
        "unexpected cargo tree output:\n{tree}"
    );
    tree
}

#[test]
fn veila_data_without_features_is_lean() {
    let hits = heavy_crates(&tree_without_defaults("veila-data"), HEAVY);
    assert!(
        hits.is_empty(),
        "veila-data --no-default-features pulls in:\n{}",
        hits.join("\n")
    );
}

#[test]
fn veila_diffusion_without_its_application_is_candle_and_geom_alone() {
    let tree = tree_without_defaults("veila-diffusion");
    assert!(
        tree.contains("candle-core"),
        "unexpected cargo tree output:\n{tree}"
    );
    let hits = heavy_crates(&tree, DIFFUSION_APP);
    assert!(
        hits.is_empty(),
        "veila-diffusion --no-default-features pulls in:\n{}",
        hits.join("\n")
    );
}

#[test]
fn lean_check_catches_heavy_crates() {
    let tree = "veila-data v0.1.0 (/w/veila-data)\nexr v1.74.0\nobvhs v0.4.0\nrand_chacha v0.9.0\n\
                randomize v1.0.0\nplotters-backend v0.3.7\nglam v0.34.0\nrand_chacha v0.9.0\n";
    assert_eq!(
        heavy_crates(tree, HEAVY),
        vec![
            "obvhs (belongs behind the `sim` feature)".to_string(),
            "plotters-backend (belongs behind the `vis` feature)".to_string(),
            "rand_chacha (belongs behind the `sim / weather / augment` feature)".to_string(),
        ]
    );
    let tree = "veila-diffusion v0.1.0 (/w/veila-diffusion)\nveila-geom v0.1.0 (/w/veila-geom)\n\
                veila-nn v0.1.0 (/w/veila-nn)\ncandle-core v0.11.1\n";
    assert_eq!(
        heavy_crates(tree, DIFFUSION_APP),
        vec!["veila-nn (belongs behind the `app` feature)".to_string()]
    );
}
