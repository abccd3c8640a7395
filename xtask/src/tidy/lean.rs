//! veila-data stays lean by default: a project that reads KITTI compiles no ray tracer, random-number
//! stack or plotting library. Those come with the `sim`, `weather`, `augment` and `vis` features.

/// Crates (name prefixes) that `veila-data` without features must not pull in, with the feature
/// that brings each.
const HEAVY: &[(&str, &str)] = &[
    ("obvhs", "sim"),
    ("rand", "sim / weather / augment"),
    ("plotters", "vis"),
    ("colorous", "vis"),
    ("ab_glyph", "vis"),
];

/// The offending lines of `cargo tree --prefix none --format {p}` output (`name vX.Y.Z ...`).
fn heavy_crates(tree: &str) -> Vec<String> {
    let mut hits: Vec<String> = tree
        .lines()
        .filter_map(|line| {
            let name = line.split_whitespace().next()?;
            HEAVY
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

#[test]
fn veila_data_without_features_is_lean() {
    let tree = super::cargo_offline(&[
        "tree",
        "-p",
        "veila-data",
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
    let hits = heavy_crates(&tree);
    assert!(
        hits.is_empty(),
        "veila-data --no-default-features pulls in:\n{}",
        hits.join("\n")
    );
}

#[test]
fn lean_check_catches_heavy_crates() {
    let tree = "veila-data v0.1.0 (/w/veila-data)\nexr v1.74.0\nobvhs v0.4.0\nrand_chacha v0.9.0\n\
                randomize v1.0.0\nplotters-backend v0.3.7\nglam v0.34.0\nrand_chacha v0.9.0\n";
    assert_eq!(
        heavy_crates(tree),
        vec![
            "obvhs (belongs behind the `sim` feature)".to_string(),
            "plotters-backend (belongs behind the `vis` feature)".to_string(),
            "rand_chacha (belongs behind the `sim / weather / augment` feature)".to_string(),
        ]
    );
}
