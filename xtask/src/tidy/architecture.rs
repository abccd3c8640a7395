//! ARCHITECTURE.md stays true: every repository path and every Rust item it names in inline code
//! exists where it says, and the file stays under [`MAX_BYTES`]. The convention is the file's last
//! section, "Keeping this file true".

use std::path::{Path, PathBuf};

use super::sizes::rust_files;

/// The size ARCHITECTURE.md must stay under: a map, not a catalogue.
const MAX_BYTES: usize = 25 * 1024;

/// Keywords whose next word is a declared name.
const DECLARES: &str = "fn struct enum trait type const static mod union macro_rules";

/// Every `.rs` file of the workspace's `*/src` folders, with its text.
type Sources = [(PathBuf, String)];

/// The inline code spans of a Markdown text, fenced blocks left out (a span may wrap a line).
fn code_spans(text: &str) -> Vec<String> {
    let mut fenced = false;
    let mut prose = String::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
        } else if !fenced {
            prose.push_str(line);
            prose.push('\n');
        }
    }
    prose
        .split('`')
        .skip(1)
        .step_by(2)
        .map(|s| s.replace('\n', " "))
        .collect()
}

fn is_ident(s: &str) -> bool {
    s.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_')
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

fn is_camel(s: &str) -> bool {
    is_ident(s)
        && s.starts_with(|c: char| c.is_ascii_uppercase())
        && s.chars().any(|c| c.is_ascii_lowercase())
}

/// A path from the repository root: a `/`, no spaces, not outside the tree, no placeholder.
fn is_path(span: &str) -> bool {
    span.contains('/')
        && !span.contains(char::is_whitespace)
        && !span.starts_with(['~', '/'])
        && !span.starts_with("../")
        && !span.contains(['*', '<', '{', '|'])
}

fn words(s: &str) -> Vec<&str> {
    s.split(|c: char| !(c.is_alphanumeric() || c == '_'))
        .filter(|w| !w.is_empty())
        .collect()
}

/// Whether `text` declares `name`: after a [`DECLARES`] keyword, in a `pub use`, or as an enum
/// variant (a CamelCase name opening a line).
fn declares(text: &str, name: &str) -> bool {
    text.lines().any(|line| {
        let variant = is_camel(name)
            && line.trim_start().strip_prefix(name).is_some_and(|rest| {
                rest.is_empty() || rest.starts_with([',', '(', '{']) || rest.starts_with(" {")
            });
        variant
            || words(line)
                .windows(2)
                .any(|w| w[1] == name && DECLARES.split(' ').any(|k| k == w[0]))
    }) || text
        .split("pub use ")
        .skip(1)
        .any(|u| words(u.split(';').next().unwrap_or("")).contains(&name))
}

fn declared(sources: &Sources, name: &str, scope: impl Fn(&Path) -> bool) -> bool {
    sources
        .iter()
        .any(|(file, text)| scope(file) && declares(text, name))
}

/// What is wrong with the crate path `segs` (`veila_data`, `atomic`, `write_atomic`): its module
/// segments resolve to files of the crate, and each later name is declared in them.
fn item_problem(root: &Path, sources: &Sources, segs: &[&str]) -> Option<String> {
    let mut dir = root.join(segs[0].replace('_', "-")).join("src");
    let mut file: Option<PathBuf> = None;
    let mut in_modules = true;
    for seg in &segs[1..] {
        let (module_file, sub) = (dir.join(format!("{seg}.rs")), dir.join(seg));
        if in_modules && (module_file.is_file() || sub.join("mod.rs").is_file()) {
            file = Some(module_file);
            dir = sub;
            continue;
        }
        in_modules = false;
        let in_scope = |f: &Path| file.as_deref() == Some(f) || f.starts_with(&dir);
        if !declared(sources, seg, in_scope) {
            let at = dir.strip_prefix(root).unwrap_or(&dir);
            return Some(format!("no `{seg}` declared in {}", at.display()));
        }
    }
    None
}

/// Every name of `text` (Markdown) that does not exist in the workspace at `root`.
fn problems(root: &Path, text: &str) -> Vec<String> {
    let sources: Vec<(PathBuf, String)> = std::fs::read_dir(root)
        .expect("readable workspace root")
        .flatten()
        .map(|e| e.path().join("src"))
        .filter(|src| src.is_dir())
        .flat_map(|src| rust_files(&src))
        .map(|f| {
            let text = std::fs::read_to_string(&f).unwrap_or_default();
            (f, text)
        })
        .collect();
    let mut out = Vec::new();
    for span in code_spans(text) {
        let segs: Vec<&str> = span.trim_end_matches("()").split("::").collect();
        let problem = if is_path(&span) {
            (!root.join(&span).exists()).then(|| "no such path in the repository".to_string())
        } else if !segs.iter().all(|s| is_ident(s)) {
            None // prose in code: a command, a flag, an expression
        } else if segs.len() > 1 && root.join(segs[0].replace('_', "-")).join("src").is_dir() {
            item_problem(root, &sources, &segs)
        } else if is_camel(segs[0]) {
            let missing = segs.iter().find(|s| !declared(&sources, s, |_| true));
            missing.map(|seg| format!("`{seg}` is declared nowhere in the workspace"))
        } else {
            None
        };
        out.extend(problem.map(|p| format!("`{span}`: {p}")));
    }
    out
}

#[test]
fn architecture_md_names_only_what_exists() {
    let root = super::workspace_root();
    let text = std::fs::read_to_string(root.join("ARCHITECTURE.md")).expect("ARCHITECTURE.md");
    assert!(
        text.len() < MAX_BYTES,
        "ARCHITECTURE.md has {} bytes; keep it under {MAX_BYTES} (a map, not a catalogue)",
        text.len()
    );
    let found = problems(&root, &text);
    assert!(
        found.is_empty(),
        "ARCHITECTURE.md names what is not there (fix the name, or see its last section):\n{}",
        found.join("\n")
    );
}

#[test]
fn architecture_check_catches_missing_names() {
    let sample = "Here: `veila-data/src/shard.rs`, `veila-nn/src/fused/`, `.ci/run`,\n\
        `veila_data::contained::contained`, `veila_diffusion::app::ScanPipeline`, `RigView`,\n\
        `veila_geom::LidarSensor::hdl64e()`, `veila_diffusion::app::Examples::Memory`.\n\
        Not checked: `../shared/data/real`, `candle_nn::AdamW`, `cargo xtask tidy`, `<crate>/src`.\n\
        ```\n`veila-data/src/fenced.rs`\n```\n\
        Missing: `veila-data/src/no_such.rs`, `veila_data::shard::no_such_fn`,\n\
        `veila_data::no_such_module::Manifest`, `NoSuchType::new`.\n";
    let found = problems(&super::workspace_root(), sample);
    assert_eq!(found.len(), 4, "{found:#?}");
    assert!(found[0].starts_with("`veila-data/src/no_such.rs`: no such path"));
    assert!(found[1].contains("no `no_such_fn` declared in veila-data/src/shard"));
    assert!(found[2].contains("no `no_such_module` declared in veila-data/src"));
    assert!(found[3].contains("`NoSuchType` is declared nowhere"));
}
