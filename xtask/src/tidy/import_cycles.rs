//! No import circles between the files of one crate: if `a.rs` uses `b.rs`, nothing `b.rs` uses
//! (directly or through other files) may use `a.rs`. A circle means two files share one idea and
//! neither is the bottom; the fix is a small module both use.
//!
//! The check reads the sources, not the compiler: module files come from `mod x;` declarations
//! (from `lib.rs` / `main.rs` down), and a file depends on another when it names one of its items
//! through a path that starts with `crate`, `super`, `self` or a child module (in `use` trees and in
//! code). A parent's `pub use child::Item` re-exports are a façade, not a dependency, and a name
//! reached through such a re-export counts as a use of the child. Comments, strings and
//! `#[cfg(test)]` modules are left out.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A lexical token of the small subset of Rust the check needs.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Tok {
    Ident(String),
    /// `::`
    Path,
    Punct(char),
}

/// Tokens of `src` without comments, string / char literals and lifetimes.
fn lex(src: &str) -> Vec<Tok> {
    let b = src.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if c == b'/' && b.get(i + 1) == Some(&b'/') {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if c == b'/' && b.get(i + 1) == Some(&b'*') {
            let mut depth = 1;
            i += 2;
            while i < b.len() && depth > 0 {
                if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == b'*' && b.get(i + 1) == Some(&b'/') {
                    depth -= 1;
                    i += 2;
                } else {
                    i += 1;
                }
            }
        } else if c == b'r' && matches!(b.get(i + 1), Some(b'"') | Some(b'#')) && {
            // raw string r"..." / r#"..."#
            let mut j = i + 1;
            while b.get(j) == Some(&b'#') {
                j += 1;
            }
            b.get(j) == Some(&b'"')
        } {
            let mut j = i + 1;
            let mut hashes = 0;
            while b[j] == b'#' {
                hashes += 1;
                j += 1;
            }
            j += 1;
            loop {
                if j >= b.len() {
                    break;
                }
                if b[j] == b'"' && (0..hashes).all(|h| b.get(j + 1 + h) == Some(&b'#')) {
                    j += 1 + hashes;
                    break;
                }
                j += 1;
            }
            i = j;
        } else if c == b'"' {
            i += 1;
            while i < b.len() && b[i] != b'"' {
                if b[i] == b'\\' {
                    i += 1;
                }
                i += 1;
            }
            i += 1;
        } else if c == b'\'' {
            // char literal ('x', '\n', '\u{..}') or lifetime ('a)
            if b.get(i + 1) == Some(&b'\\') {
                i += 3;
                while i < b.len() && b[i] != b'\'' {
                    i += 1;
                }
                i += 1;
            } else if b.get(i + 2) == Some(&b'\'') {
                i += 3;
            } else {
                // a lifetime or a multi-byte char: skip the quote and the identifier / char
                i += 1;
                let s = &src[i..];
                let ch = s.chars().next().map_or(1, char::len_utf8);
                if src[i + ch..].starts_with('\'') {
                    i += ch + 1;
                } else {
                    while i < b.len() && (b[i].is_ascii_alphanumeric() || b[i] == b'_') {
                        i += 1;
                    }
                }
            }
        } else if c.is_ascii_alphabetic() || c == b'_' {
            let start = i;
            while i < b.len() && (b[i].is_ascii_alphanumeric() || b[i] == b'_') {
                i += 1;
            }
            let word = &src[start..i];
            // byte strings and raw identifiers
            if (word == "b" || word == "br") && matches!(b.get(i), Some(b'"') | Some(b'\'')) {
                continue;
            }
            out.push(Tok::Ident(word.to_string()));
        } else if c == b':' && b.get(i + 1) == Some(&b':') {
            out.push(Tok::Path);
            i += 2;
        } else if c.is_ascii_whitespace() || c.is_ascii_digit() {
            i += 1;
        } else {
            let ch = src[i..].chars().next().expect("in bounds");
            out.push(Tok::Punct(ch));
            i += ch.len_utf8();
        }
    }
    out
}

/// A module path inside the crate (`[]` is the crate root).
type ModPath = Vec<String>;

/// What one file says: child modules it declares (`mod x;`), paths it names, and its re-exports.
#[derive(Debug, Default)]
struct FileFacts {
    /// `mod x;` declarations, as (module path of the child, declaring module path).
    children: Vec<ModPath>,
    /// Paths named, each with the module it is written in (inline modules included) and whether it
    /// comes from a `pub use` (a re-export).
    paths: Vec<(ModPath, Vec<String>, bool)>,
}

fn ident(t: Option<&Tok>) -> Option<&str> {
    match t {
        Some(Tok::Ident(s)) => Some(s),
        _ => None,
    }
}

/// Index of the token after the bracket group that starts at `i` (`open` at `toks[i]`).
fn skip_group(toks: &[Tok], mut i: usize, open: char, close: char) -> usize {
    let mut depth = 0;
    while i < toks.len() {
        match toks[i] {
            Tok::Punct(c) if c == open => depth += 1,
            Tok::Punct(c) if c == close => {
                depth -= 1;
                if depth == 0 {
                    return i + 1;
                }
            }
            _ => {}
        }
        i += 1;
    }
    i
}

/// Expand a `use` tree starting at `i` into full paths; returns the index after it.
fn use_tree(toks: &[Tok], mut i: usize, prefix: &[String], out: &mut Vec<Vec<String>>) -> usize {
    let mut path = prefix.to_vec();
    loop {
        match toks.get(i) {
            Some(Tok::Ident(s)) if s == "as" => {
                i += 2; // `as name`
                out.push(path);
                return i;
            }
            Some(Tok::Ident(s)) => {
                path.push(s.clone());
                i += 1;
            }
            Some(Tok::Punct('*')) => {
                path.push("*".into());
                out.push(path);
                return i + 1;
            }
            Some(Tok::Path) => i += 1,
            Some(Tok::Punct('{')) => {
                i += 1;
                loop {
                    match toks.get(i) {
                        Some(Tok::Punct('}')) => return i + 1,
                        Some(Tok::Punct(',')) => i += 1,
                        None => return i,
                        _ => i = use_tree(toks, i, &path, out),
                    }
                }
            }
            _ => {
                out.push(path);
                return i;
            }
        }
    }
}

/// Read the facts of one file whose module path is `module`.
fn file_facts(src: &str, module: &ModPath) -> FileFacts {
    let toks = lex(src);
    let mut facts = FileFacts::default();
    // inline modules: (path, brace depth at which it closes)
    let mut stack: Vec<(ModPath, usize)> = vec![(module.clone(), 0)];
    let mut depth = 0usize;
    let mut i = 0;
    while i < toks.len() {
        let here = stack.last().expect("root").0.clone();
        match &toks[i] {
            Tok::Punct('{') => {
                depth += 1;
                i += 1;
            }
            Tok::Punct('}') => {
                depth = depth.saturating_sub(1);
                if stack.len() > 1 && stack.last().expect("inline").1 == depth {
                    stack.pop();
                }
                i += 1;
            }
            Tok::Punct('#') => {
                // `#[cfg(test)] mod x { .. }` / `mod x;`: left out
                let attr_end = skip_group(&toks, i + 1, '[', ']');
                let is_test = toks[i + 1..attr_end]
                    == [
                        Tok::Punct('['),
                        Tok::Ident("cfg".into()),
                        Tok::Punct('('),
                        Tok::Ident("test".into()),
                        Tok::Punct(')'),
                        Tok::Punct(']'),
                    ];
                let mut j = attr_end;
                if ident(toks.get(j)) == Some("pub") {
                    j += 1;
                }
                if is_test && ident(toks.get(j)) == Some("mod") {
                    j += 2;
                    i = match toks.get(j) {
                        Some(Tok::Punct('{')) => skip_group(&toks, j, '{', '}'),
                        _ => j + 1,
                    };
                } else {
                    i = attr_end;
                }
            }
            Tok::Ident(w) if w == "mod" => {
                if let Some(name) = ident(toks.get(i + 1)) {
                    let mut child = here.clone();
                    child.push(name.to_string());
                    match toks.get(i + 2) {
                        Some(Tok::Punct(';')) => facts.children.push(child),
                        Some(Tok::Punct('{')) => {
                            stack.push((child, depth));
                            depth += 1;
                        }
                        _ => {}
                    }
                    i += 3;
                } else {
                    i += 1;
                }
            }
            Tok::Ident(w) if w == "use" => {
                let public = i > 0
                    && (ident(toks.get(i - 1)) == Some("pub")
                        || matches!(toks.get(i - 1), Some(Tok::Punct(')'))));
                let mut paths = Vec::new();
                i = use_tree(&toks, i + 1, &[], &mut paths);
                for p in paths {
                    facts.paths.push((here.clone(), p, public));
                }
            }
            Tok::Ident(w)
                if toks.get(i + 1) == Some(&Tok::Path) && (i == 0 || toks[i - 1] != Tok::Path) =>
            {
                let mut p = vec![w.clone()];
                let mut j = i + 1;
                while toks.get(j) == Some(&Tok::Path) {
                    match toks.get(j + 1) {
                        Some(Tok::Ident(s)) => {
                            p.push(s.clone());
                            j += 2;
                        }
                        _ => break,
                    }
                }
                facts.paths.push((here.clone(), p, false));
                i = j;
            }
            _ => i += 1,
        }
    }
    facts
}

/// The file of a `mod name;` declared in `parent_file` (which is the file of module `parent`).
fn child_file(parent_file: &Path, name: &str) -> Option<PathBuf> {
    let stem = parent_file.file_stem()?.to_str()?;
    let dir = parent_file.parent()?;
    let base = if matches!(stem, "lib" | "main" | "mod") {
        dir.to_path_buf()
    } else {
        dir.join(stem)
    };
    [
        base.join(format!("{name}.rs")),
        base.join(name).join("mod.rs"),
    ]
    .into_iter()
    .find(|p| p.is_file())
}

/// The import graph between the files of the crate whose root file is `root`: file -> files it uses.
fn file_graph(root: &Path) -> BTreeMap<PathBuf, BTreeSet<PathBuf>> {
    // module tree
    let mut file_of: BTreeMap<ModPath, PathBuf> = BTreeMap::new();
    let mut facts: BTreeMap<PathBuf, FileFacts> = BTreeMap::new();
    let mut todo = vec![(Vec::new(), root.to_path_buf())];
    while let Some((module, file)) = todo.pop() {
        let src = std::fs::read_to_string(&file).expect("readable source file");
        let f = file_facts(&src, &module);
        for child in &f.children {
            let name = child.last().expect("named");
            // inline parents (`mod a { mod b; }`) are rare; resolve from the file's own folder
            if let Some(cf) = child_file(&file, name) {
                todo.push((child.clone(), cf));
            }
        }
        file_of.insert(module, file.clone());
        facts.insert(file, f);
    }
    // inline modules live in their file
    let mut inline = Vec::new();
    for (file, f) in &facts {
        for (m, _, _) in &f.paths {
            if !file_of.contains_key(m) {
                inline.push((m.clone(), file.clone()));
            }
        }
    }
    for (m, file) in inline {
        file_of.entry(m).or_insert(file);
    }
    let is_module = |m: &ModPath| file_of.contains_key(m);
    // re-exports per module: item name -> the module it comes from
    let mut reexports: BTreeMap<ModPath, BTreeMap<String, ModPath>> = BTreeMap::new();
    let resolve_prefix = |here: &ModPath, p: &[String]| -> Option<(ModPath, usize)> {
        let mut base: ModPath = match p.first().map(String::as_str)? {
            "crate" => Vec::new(),
            "self" => here.clone(),
            "super" => {
                let mut b = here.clone();
                b.pop()?;
                b
            }
            first => {
                let mut b = here.clone();
                b.push(first.to_string());
                if !is_module(&b) {
                    return None;
                }
                here.clone()
            }
        };
        let mut k = usize::from(matches!(p[0].as_str(), "crate" | "self" | "super"));
        while p.get(k).map(String::as_str) == Some("super") {
            base.pop()?;
            k += 1;
        }
        while let Some(seg) = p.get(k) {
            let mut next = base.clone();
            next.push(seg.clone());
            if !is_module(&next) {
                break;
            }
            base = next;
            k += 1;
        }
        Some((base, k))
    };
    for f in facts.values() {
        for (here, p, public) in &f.paths {
            if !public {
                continue;
            }
            if let Some((target, k)) = resolve_prefix(here, p)
                && target.starts_with(here)
                && target != *here
                && let Some(item) = p.get(k)
            {
                reexports
                    .entry(here.clone())
                    .or_default()
                    .insert(item.clone(), target);
            }
        }
    }
    let mut graph: BTreeMap<PathBuf, BTreeSet<PathBuf>> = BTreeMap::new();
    for (file, f) in &facts {
        let edges = graph.entry(file.clone()).or_default();
        for (here, p, public) in &f.paths {
            let Some((mut target, k)) = resolve_prefix(here, p) else {
                continue;
            };
            if *public && target.starts_with(here) {
                continue; // a façade re-export of a descendant
            }
            // follow re-exports (possibly several levels of façades)
            // a name reached through re-exports counts as a use of the module that defines it
            // (re-exports always point down the tree, so this ends)
            if let Some(name) = p.get(k) {
                while let Some(src) = reexports.get(&target).and_then(|r| r.get(name)) {
                    target = src.clone();
                }
            }
            let target_file = &file_of[&target];
            if target_file != file {
                edges.insert(target_file.clone());
            }
        }
    }
    graph
}

/// Strongly connected components with more than one file (Tarjan), each sorted.
fn cycles(graph: &BTreeMap<PathBuf, BTreeSet<PathBuf>>) -> Vec<Vec<PathBuf>> {
    struct State<'a> {
        graph: &'a BTreeMap<PathBuf, BTreeSet<PathBuf>>,
        index: BTreeMap<&'a PathBuf, usize>,
        low: BTreeMap<&'a PathBuf, usize>,
        stack: Vec<&'a PathBuf>,
        on_stack: BTreeSet<&'a PathBuf>,
        out: Vec<Vec<PathBuf>>,
    }
    fn visit<'a>(s: &mut State<'a>, v: &'a PathBuf) {
        let n = s.index.len();
        s.index.insert(v, n);
        s.low.insert(v, n);
        s.stack.push(v);
        s.on_stack.insert(v);
        let graph = s.graph;
        for w in graph.get(v).into_iter().flatten() {
            let Some((w, _)) = graph.get_key_value(w) else {
                continue;
            };
            if !s.index.contains_key(w) {
                visit(s, w);
                let lw = s.low[w];
                let lv = s.low.get_mut(v).expect("visited");
                *lv = (*lv).min(lw);
            } else if s.on_stack.contains(w) {
                let iw = s.index[w];
                let lv = s.low.get_mut(v).expect("visited");
                *lv = (*lv).min(iw);
            }
        }
        if s.low[v] == s.index[v] {
            let mut comp = Vec::new();
            loop {
                let w = s.stack.pop().expect("on stack");
                s.on_stack.remove(w);
                comp.push(w.clone());
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                s.out.push(comp);
            }
        }
    }
    let mut s = State {
        graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in graph.keys() {
        if !s.index.contains_key(v) {
            visit(&mut s, v);
        }
    }
    s.out.sort();
    s.out
}

/// The import circles of the crate in `crate_dir` (its `src/lib.rs` or `src/main.rs`), as lists of
/// files relative to `crate_dir`.
pub(super) fn import_cycles(crate_dir: &Path) -> Vec<Vec<String>> {
    let src = crate_dir.join("src");
    let root = ["lib.rs", "main.rs"]
        .into_iter()
        .map(|f| src.join(f))
        .find(|p| p.is_file())
        .expect("a crate root");
    cycles(&file_graph(&root))
        .into_iter()
        .map(|c| {
            c.iter()
                .map(|p| p.strip_prefix(crate_dir).unwrap_or(p).display().to_string())
                .collect()
        })
        .collect()
}

/// Circles known and not yet broken, each with the way out. The test fails when one of them is
/// gone (so the list only shrinks) as well as when a new one appears.
const KNOWN_CIRCLES: &[(&str, &str)] = &[];

#[test]
fn no_import_cycles_between_files() {
    let root = super::workspace_root();
    let mut problems = Vec::new();
    let mut found = Vec::new();
    for krate in super::INTERNAL_ALLOWED.iter().map(|(k, _)| k) {
        for c in import_cycles(&root.join(krate)) {
            let circle = c.join(" <-> ");
            if KNOWN_CIRCLES.contains(&(krate, circle.as_str())) {
                found.push((*krate, circle));
            } else {
                problems.push(format!("{krate}: {circle}"));
            }
        }
    }
    assert!(
        problems.is_empty(),
        "import circles between files (move what they share into a module both use):\n{}",
        problems.join("\n")
    );
    for (krate, circle) in KNOWN_CIRCLES {
        assert!(
            found.iter().any(|(k, c)| k == krate && c == circle),
            "{krate}: {circle} is no longer a circle: remove it from KNOWN_CIRCLES"
        );
    }
}

#[test]
fn import_cycle_check_finds_planted_cycles_and_only_those() {
    let dir = tempfile::tempdir().expect("temp dir");
    let src = dir.path().join("src");
    std::fs::create_dir_all(src.join("weather")).expect("mkdir");
    let write = |p: &str, text: &str| std::fs::write(src.join(p), text).expect("write");
    // lib re-exports (a façade, no edge); `a` and `b` use each other through a re-export and a
    // `use` tree; `c` uses `a` only; `weather::lidar` and `weather::rain` use each other through
    // `super::` and a path in code; `weather::mod` defines an item `plan` uses (no circle);
    // comments, strings and test modules mention `a` from `c`'s point of view without an edge.
    write(
        "lib.rs",
        "pub mod a;\nmod b;\nmod c;\npub mod weather;\npub use a::A;\n",
    );
    write(
        "a.rs",
        "use crate::{Thing, b::{self as bee}};\npub struct A;\n",
    );
    write(
        "b.rs",
        "//! uses crate::c::C in docs only\nuse crate::A;\npub struct B;\n",
    );
    write(
        "c.rs",
        "use super::a::A;\nconst S: &str = \"crate::b::B\";\nfn f<'a>(x: &'a str) -> char { 'c' }\n\
         #[cfg(test)]\nmod tests { use crate::b::B; }\n",
    );
    write(
        "weather/mod.rs",
        "mod lidar;\nmod plan;\nmod rain;\npub use plan::Plan;\npub struct Shared;\n\
         fn run() { lidar::drive(); }\n",
    );
    write(
        "weather/lidar.rs",
        "pub fn drive() { super::rain::fall(); }\npub struct State;\n",
    );
    write(
        "weather/rain.rs",
        "use super::lidar::State;\npub fn fall() {}\n",
    );
    write("weather/plan.rs", "use super::Shared;\npub struct Plan;\n");
    let found = import_cycles(dir.path());
    assert_eq!(
        found,
        vec![
            vec!["src/a.rs".to_string(), "src/b.rs".to_string()],
            vec![
                "src/weather/lidar.rs".to_string(),
                "src/weather/rain.rs".to_string()
            ],
        ],
        "{found:#?}"
    );
    // remove one direction of each circle: no circles left
    write("b.rs", "pub struct B;\n");
    write("weather/rain.rs", "pub fn fall() {}\n");
    assert!(import_cycles(dir.path()).is_empty());
}
