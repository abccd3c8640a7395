//! Structure-aware editors: each parses a valid seed of its format, changes one thing in a way
//! a hostile publisher would (a leaf, a count, a shape, a length field, a member, an attribute)
//! and writes it back, so the input gets past the parser into the reader's own checks.

use std::io::{Cursor, Read, Write};

use rand::Rng;
use rand::seq::IndexedRandom;
use serde_json::Value;

use crate::engine::FuzzRng;

/// Nesting depth of the deeply nested values (`[[[[...]]]]`): far past any parser's limit.
const DEEP: usize = 100_000;

/// A string of `1 << 20` characters (a "huge string" leaf).
fn huge_string() -> String {
    "A".repeat(1 << 20)
}

/// Strings a hostile file puts where a name or path goes.
const HOSTILE_STRINGS: [&str; 9] = [
    "",
    "../../../../../../etc/passwd",
    "/etc/passwd",
    "..",
    "a/../../b",
    "./../outside",
    "\u{1b}[2J\u{1b}[HFAKE: all checks passed",
    "\u{0}",
    "C:\\Windows\\win.ini",
];

// ------------------------------------------------------------------------------------ JSON

/// A placeholder string and the JSON text it stands for.
type Placeholder = (&'static str, fn() -> String);

/// Placeholders for what a `serde_json::Value` cannot hold, replaced in the written text.
const PLACEHOLDERS: [Placeholder; 5] = [
    ("\"__NAN__\"", || "NaN".into()),
    ("\"__INF__\"", || "Infinity".into()),
    ("\"__NEGINF__\"", || "-Infinity".into()),
    ("\"__BIGNUM__\"", || format!("1{}", "0".repeat(400))),
    ("\"__DEEP__\"", || {
        format!("{}{}", "[".repeat(DEEP), "]".repeat(DEEP))
    }),
];

fn hostile_json(rng: &mut FuzzRng) -> Value {
    use serde_json::json;
    match rng.random_range(0..32) {
        0 => json!(0),
        1 => json!(-1),
        2 => json!(1),
        3 => json!(1u64 << 31),
        4 => json!(1u64 << 32),
        5 => json!((1u64 << 53) + 1),
        6 => json!(1u64 << 63),
        7 => json!(u64::MAX),
        8 => json!(i64::MIN),
        9 => json!(1e300),
        10 => json!(-1e300),
        11 => json!(1e-300),
        12 => json!(0.5),
        13 => json!(-0.0),
        14 => json!("__NAN__"),
        15 => json!("__INF__"),
        16 => json!("__NEGINF__"),
        17 => json!("__BIGNUM__"),
        18 => json!("__DEEP__"),
        19 => json!(huge_string()),
        20 => Value::Null,
        21 => json!(true),
        22 => json!([]),
        23 => json!({}),
        24 => Value::Array(vec![json!(0); 100_000]),
        25 => json!(1_000_000),
        26 => json!(1e9),
        27 => json!(65),
        _ => json!(*HOSTILE_STRINGS.choose(rng).expect("a string")),
    }
}

/// JSON pointer of every node of `v` (at most a few thousand, not below depth 32).
fn pointers(v: &Value, at: String, out: &mut Vec<String>, depth: usize) {
    if out.len() > 4000 || depth > 32 {
        return;
    }
    out.push(at.clone());
    match v {
        Value::Object(m) => {
            for (k, c) in m {
                let key = k.replace('~', "~0").replace('/', "~1");
                pointers(c, format!("{at}/{key}"), out, depth + 1);
            }
        }
        Value::Array(a) => {
            // long arrays (ids, data): a few of their elements
            for (i, c) in a.iter().enumerate().take(16) {
                pointers(c, format!("{at}/{i}"), out, depth + 1);
            }
        }
        _ => {}
    }
}

/// One hostile edit of the JSON value `v`.
pub fn edit_json_value(v: &mut Value, rng: &mut FuzzRng, nested: usize) {
    let mut ptrs = Vec::new();
    pointers(v, String::new(), &mut ptrs, 0);
    // half of the time a number (counts, sizes, shapes, offsets)
    let numbers: Vec<&String> = ptrs
        .iter()
        .filter(|p| v.pointer(p).is_some_and(Value::is_number))
        .collect();
    let ptr = if !numbers.is_empty() && rng.random_bool(0.5) {
        (*numbers.choose(rng).expect("a number")).clone()
    } else {
        ptrs.choose(rng).cloned().unwrap_or_default()
    };
    let other = ptrs
        .choose(rng)
        .and_then(|p| v.pointer(p))
        .cloned()
        .unwrap_or(Value::Null);
    let Some(node) = v.pointer_mut(&ptr) else {
        return;
    };
    match rng.random_range(0..12) {
        0..=3 => *node = hostile_json(rng),
        // a plausible neighbour of a number (one more, one less, twice, half), so that some
        // inputs pass the bounds and reach what comes after them
        4 | 5 => match node.as_f64() {
            Some(x) => {
                let y = match rng.random_range(0..5) {
                    0 => x + 1.0,
                    1 => x - 1.0,
                    2 => x * 2.0,
                    3 => (x / 2.0).floor(),
                    _ => x * 10.0,
                };
                *node = if node.is_f64() {
                    serde_json::json!(y)
                } else if y >= 0.0 {
                    serde_json::json!(y as u64)
                } else {
                    serde_json::json!(y as i64)
                };
            }
            None => *node = other,
        },
        6 => {
            // JSON inside a string (a shard's or a safetensors file's metadata): edited inside
            let inner = node
                .as_str()
                .and_then(|s| serde_json::from_str::<Value>(s).ok())
                .filter(|i| i.is_object() || i.is_array());
            match inner {
                Some(mut i) if nested < 2 => {
                    edit_json_value(&mut i, rng, nested + 1);
                    *node = Value::String(expand(serde_json::to_string(&i).unwrap_or_default()));
                }
                _ => *node = hostile_json(rng),
            }
        }
        7 => match node {
            Value::Object(m) if !m.is_empty() && rng.random_bool(0.5) => {
                let keys: Vec<String> = m.keys().cloned().collect();
                let k = keys.choose(rng).expect("a key");
                m.remove(k);
            }
            Value::Object(m) => {
                m.insert("fuzz_extra".into(), hostile_json(rng));
            }
            _ => *node = hostile_json(rng),
        },
        8 => match node {
            Value::Array(a) if !a.is_empty() => {
                let e = a.choose(rng).expect("an element").clone();
                let k = *[1usize, 2, 100, 10_000].choose(rng).expect("a count");
                a.extend(std::iter::repeat_n(e, k));
            }
            _ => *node = hostile_json(rng),
        },
        9 => match node {
            Value::Array(a) if !a.is_empty() => {
                if rng.random_bool(0.5) {
                    a.pop();
                } else {
                    a.clear();
                }
            }
            _ => *node = hostile_json(rng),
        },
        _ => *node = other,
    }
}

/// `text` with the placeholders of [`PLACEHOLDERS`] written as what they stand for.
fn expand(mut text: String) -> String {
    for (p, with) in PLACEHOLDERS {
        if text.contains(p) {
            text = text.replace(p, &with());
        }
    }
    text
}

/// One hostile edit of a JSON document, written compact or pretty.
pub fn json(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    let mut v: Value = serde_json::from_slice(bytes).ok()?;
    edit_json_value(&mut v, rng, 0);
    let text = if rng.random_bool(0.5) {
        serde_json::to_string(&v).ok()?
    } else {
        serde_json::to_string_pretty(&v).ok()?
    };
    Some(expand(text).into_bytes())
}

// ------------------------------------------------------------------------------------ TOML

#[derive(Debug, Clone)]
enum Step {
    Key(String),
    Index(usize),
}

/// The path of every node of `v`, with whether it is a leaf (not a table).
fn toml_paths(v: &toml::Value, at: Vec<Step>, out: &mut Vec<(Vec<Step>, bool)>) {
    if out.len() > 4000 || at.len() > 32 {
        return;
    }
    out.push((at.clone(), !v.is_table()));
    match v {
        toml::Value::Table(t) => {
            for (k, c) in t {
                let mut p = at.clone();
                p.push(Step::Key(k.clone()));
                toml_paths(c, p, out);
            }
        }
        toml::Value::Array(a) => {
            for (i, c) in a.iter().enumerate().take(16) {
                let mut p = at.clone();
                p.push(Step::Index(i));
                toml_paths(c, p, out);
            }
        }
        _ => {}
    }
}

fn toml_at<'a>(v: &'a mut toml::Value, path: &[Step]) -> Option<&'a mut toml::Value> {
    let mut node = v;
    for s in path {
        node = match (s, node) {
            (Step::Key(k), toml::Value::Table(t)) => t.get_mut(k)?,
            (Step::Index(i), toml::Value::Array(a)) => a.get_mut(*i)?,
            _ => return None,
        };
    }
    Some(node)
}

fn hostile_toml(rng: &mut FuzzRng) -> toml::Value {
    use toml::Value as V;
    match rng.random_range(0..26) {
        0 => V::Integer(0),
        1 => V::Integer(-1),
        2 => V::Integer(1 << 31),
        3 => V::Integer(1 << 32),
        4 => V::Integer(i64::MAX),
        5 => V::Integer(i64::MIN),
        6 => V::Float(1e300),
        7 => V::Float(-1e300),
        8 => V::Float(f64::NAN),
        9 => V::Float(f64::INFINITY),
        10 => V::Float(f64::NEG_INFINITY),
        11 => V::Float(1e-300),
        12 => V::Float(-0.0),
        13 => V::String("__DEEP__".into()),
        14 => V::String("__BIGINT__".into()),
        15 => V::String(huge_string()),
        16 => V::Boolean(true),
        17 => V::Array(Vec::new()),
        18 => V::Array(vec![V::Integer(0); 100_000]),
        19 => V::Table(toml::Table::new()),
        20 => V::Integer(1_000_000_000),
        21 => V::Integer(65),
        _ => V::String((*HOSTILE_STRINGS.choose(rng).expect("a string")).into()),
    }
}

/// One hostile edit of a TOML document (a leaf, a key, an array's length).
pub fn toml_doc(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    let text = std::str::from_utf8(bytes).ok()?;
    let table: toml::Table = text.parse().ok()?;
    let mut root = toml::Value::Table(table);
    let mut paths = Vec::new();
    toml_paths(&root, Vec::new(), &mut paths);
    let leaves: Vec<&Vec<Step>> = paths.iter().filter(|p| p.1).map(|p| &p.0).collect();
    let path = if !leaves.is_empty() && rng.random_bool(0.7) {
        (*leaves.choose(rng).expect("a leaf")).clone()
    } else {
        paths.choose(rng).map(|p| p.0.clone()).unwrap_or_default()
    };
    let node = toml_at(&mut root, &path)?;
    match rng.random_range(0..9) {
        0..=2 => {
            if path.is_empty() {
                return None;
            }
            *node = hostile_toml(rng);
        }
        // a plausible neighbour of a number (see `edit_json_value`)
        3 | 4 => match node {
            toml::Value::Integer(i) => {
                *i = match rng.random_range(0..4) {
                    0 => i.saturating_add(1),
                    1 => i.saturating_sub(1),
                    2 => i.saturating_mul(2),
                    _ => *i / 2,
                }
            }
            toml::Value::Float(f) => {
                *f = match rng.random_range(0..4) {
                    0 => *f + 1.0,
                    1 => -*f,
                    2 => *f * 2.0,
                    _ => *f / 2.0,
                }
            }
            toml::Value::Boolean(b) => *b = !*b,
            _ => *node = hostile_toml(rng),
        },
        5 => match node {
            toml::Value::Table(t) if !t.is_empty() && rng.random_bool(0.5) => {
                let keys: Vec<String> = t.keys().cloned().collect();
                let k = keys.choose(rng).expect("a key");
                t.remove(k);
            }
            toml::Value::Table(t) => {
                t.insert("fuzz_extra".into(), hostile_toml(rng));
            }
            _ => *node = hostile_toml(rng),
        },
        6 => match node {
            toml::Value::Array(a) if !a.is_empty() => {
                let e = a.choose(rng).expect("an element").clone();
                let k = *[1usize, 100, 10_000].choose(rng).expect("a count");
                a.extend(std::iter::repeat_n(e, k));
            }
            _ => *node = hostile_toml(rng),
        },
        _ => match node {
            toml::Value::Array(a) if !a.is_empty() => a.clear(),
            _ => *node = hostile_toml(rng),
        },
    }
    let toml::Value::Table(t) = root else {
        return None;
    };
    let mut out = toml::to_string(&t).ok()?;
    if out.contains("\"__DEEP__\"") {
        let deep = format!("{}{}", "[".repeat(DEEP), "]".repeat(DEEP));
        out = out.replace("\"__DEEP__\"", &deep);
    }
    if out.contains("\"__BIGINT__\"") {
        out = out.replace("\"__BIGINT__\"", "9223372036854775808");
    }
    Some(out.into_bytes())
}

// ------------------------------------------------------------------------------- text tokens

/// Tokens put in place of a word of a text format (numbers of every kind that break parsers).
const HOSTILE_TOKENS: [&str; 32] = [
    "-1",
    "0",
    "-0",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e39",
    "1e300",
    "-1e300",
    "1e-45",
    "2147483648",
    "4294967296",
    "9223372036854775808",
    "99999999999999999999999999",
    "0x10",
    "1,5",
    "",
    "../",
    "/etc/passwd",
    "\u{1b}[2J",
    "é",
    ":",
    "[",
    "{",
    "*a",
    "&a",
    "!!binary",
    "~",
    ".nan",
    "'",
    "\"",
];

/// One edit of a line-oriented text (a calibration, a YAML map, a PLY header): a word replaced
/// by a hostile token or deleted, a line duplicated (up to a thousand times), deleted, swapped or
/// added.
pub fn text_tokens(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    let text = std::str::from_utf8(bytes).ok()?;
    let mut lines: Vec<String> = text.split('\n').map(str::to_string).collect();
    if lines.is_empty() {
        return None;
    }
    let li = rng.random_range(0..lines.len());
    match rng.random_range(0..9) {
        0..=3 => {
            let words: Vec<&str> = lines[li].split(' ').collect();
            let wi = rng.random_range(0..words.len());
            let tok = *HOSTILE_TOKENS.choose(rng).expect("a token");
            let mut w: Vec<String> = words.iter().map(|s| s.to_string()).collect();
            w[wi] = tok.to_string();
            lines[li] = w.join(" ");
        }
        4 => {
            let mut w: Vec<&str> = lines[li].split(' ').collect();
            let wi = rng.random_range(0..w.len());
            w.remove(wi);
            lines[li] = w.join(" ");
        }
        5 => {
            let k = *[1usize, 2, 1000].choose(rng).expect("a count");
            let l = lines[li].clone();
            for _ in 0..k {
                lines.insert(li, l.clone());
            }
        }
        6 => {
            lines.remove(li);
        }
        7 => {
            let lj = rng.random_range(0..lines.len());
            lines.swap(li, lj);
        }
        _ => {
            let l = match rng.random_range(0..3) {
                0 => "1 ".repeat(100_000),
                1 => lines[li]
                    .split(' ')
                    .map(|_| "nan")
                    .collect::<Vec<_>>()
                    .join(" "),
                _ => (*HOSTILE_TOKENS.choose(rng).expect("a token")).to_string(),
            };
            lines.insert(li, l);
        }
    }
    Some(lines.join("\n").into_bytes())
}

/// YAML's own tricks: an alias bomb (ten levels of ten aliases), a deeply nested flow or block
/// value, an alias in place of a map, a tag.
pub fn yaml(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    let text = std::str::from_utf8(bytes).ok()?;
    let lines: Vec<&str> = text.lines().collect();
    let li = rng.random_range(0..lines.len().max(1));
    let out = match rng.random_range(0..5) {
        0 => {
            let mut bomb = String::from("a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n");
            for i in 1..10 {
                let refs = vec![format!("*a{}", i - 1); 10].join(", ");
                bomb.push_str(&format!("a{i}: &a{i} [{refs}]\n"));
            }
            format!("{bomb}{text}\nlearning_map: *a9\n")
        }
        1 => {
            let deep = format!("{}{}", "[".repeat(DEEP), "]".repeat(DEEP));
            let mut l: Vec<String> = lines.iter().map(|s| s.to_string()).collect();
            if let Some(line) = l.get_mut(li)
                && let Some((k, _)) = line.split_once(':')
            {
                *line = format!("{k}: {deep}");
            }
            l.join("\n")
        }
        2 => {
            let mut nested = String::from("labels:\n");
            for d in 1..2000 {
                nested.push_str(&" ".repeat(d));
                nested.push_str("a:\n");
            }
            format!("{text}\n{nested}")
        }
        3 => format!("m: &m {{0: 0, 1: 1}}\n{text}\nlearning_map: *m\nlearning_map_inv: *m\n"),
        _ => {
            let mut l: Vec<String> = lines.iter().map(|s| s.to_string()).collect();
            if let Some(line) = l.get_mut(li)
                && let Some((k, v)) = line.split_once(':')
            {
                *line = format!("{k}: !!binary {v}");
            }
            l.join("\n")
        }
    };
    Some(out.into_bytes())
}

// ------------------------------------------------------------------------------ safetensors

/// One edit of a safetensors file: its JSON header (dtypes, shapes, offsets, metadata) edited
/// and its length prefix rewritten, the length prefix itself lying, or values poisoned (NaN,
/// infinity, 3e38).
pub fn safetensors(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    if bytes.len() < 8 {
        return None;
    }
    let n = u64::from_le_bytes(bytes[..8].try_into().ok()?) as usize;
    let header = bytes.get(8..8 + n)?;
    let data = &bytes[8 + n..];
    match rng.random_range(0..6) {
        0..=2 => {
            let h = json(header, rng)?;
            let mut out = (h.len() as u64).to_le_bytes().to_vec();
            out.extend_from_slice(&h);
            out.extend_from_slice(data);
            Some(out)
        }
        3 => {
            let lie = *[
                0u64,
                1,
                n as u64 - 1,
                n as u64 + 1,
                u64::MAX,
                1 << 31,
                100_000_001,
                bytes.len() as u64,
            ]
            .choose(rng)
            .expect("a length");
            let mut out = bytes.to_vec();
            out[..8].copy_from_slice(&lie.to_le_bytes());
            Some(out)
        }
        _ => {
            let mut out = bytes.to_vec();
            let words = data.len() / 4;
            if words == 0 {
                return None;
            }
            for _ in 0..rng.random_range(1..=4) {
                let at = 8 + n + 4 * rng.random_range(0..words);
                let v = *[f32::NAN, f32::INFINITY, -f32::INFINITY, 3e38, 1e9, -1e9]
                    .choose(rng)
                    .expect("a value");
                out[at..at + 4].copy_from_slice(&v.to_le_bytes());
            }
            Some(out)
        }
    }
}

// ------------------------------------------------------------------------------------ .npy

const SHAPES: [&str; 12] = [
    "()",
    "(0,)",
    "(0, 4)",
    "(-1, 4)",
    "(2147483648, 2147483648)",
    "(18446744073709551615,)",
    "(4294967296, 4294967296)",
    "(99999999999999999999999,)",
    "(1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1)",
    "(3, 4, 5)",
    "(1000000, 1000000)",
    "(5,",
];

const DESCRS: [&str; 11] = [
    "'<f4'",
    "'<f8'",
    "'>f4'",
    "'|O'",
    "'<i8'",
    "'<U10'",
    "'|b1'",
    "'<c8'",
    "'<f2'",
    "[('a', '<f4')]",
    "'<f4",
];

/// One edit of a `.npy` file's header (shape, dtype, order, or its words), the header re-padded
/// and its length rewritten (version 2 where it no longer fits version 1); sometimes the data is
/// cut or doubled as well.
pub fn npy(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return None;
    }
    let (hlen, start) = if bytes[6] == 1 {
        (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10)
    } else {
        (
            u32::from_le_bytes(bytes.get(8..12)?.try_into().ok()?) as usize,
            12,
        )
    };
    let header = std::str::from_utf8(bytes.get(start..start + hlen)?).ok()?;
    let mut data = bytes[start + hlen..].to_vec();
    let replace_between = |h: &str, key: &str, end: char, with: &str| -> Option<String> {
        let i = h.find(key)? + key.len();
        let j = i + h[i..].find(end)? + end.len_utf8();
        Some(format!("{}{with}{}", &h[..i], &h[j..]))
    };
    let mut h = match rng.random_range(0..5) {
        0 | 1 => replace_between(
            header,
            "'shape': ",
            ')',
            SHAPES.choose(rng).expect("a shape"),
        )?,
        2 => {
            let i = header.find("'descr': ")? + "'descr': ".len();
            let j = i + 1 + header[i + 1..].find('\'')? + 1;
            format!(
                "{}{}{}",
                &header[..i],
                DESCRS.choose(rng).expect("a dtype"),
                &header[j..]
            )
        }
        3 => header.replace("False", "True"),
        _ => String::from_utf8(text_tokens(header.as_bytes(), rng)?).ok()?,
    };
    if rng.random_bool(0.2) {
        if rng.random_bool(0.5) {
            let keep = rng.random_range(0..=data.len());
            data.truncate(keep);
        } else {
            data.extend(data.clone());
        }
    }
    h = h.trim_end().to_string();
    let v1 = start + h.len() < 65535;
    let pre = if v1 { 10 } else { 12 };
    while (pre + h.len() + 1) % 64 != 0 {
        h.push(' ');
    }
    h.push('\n');
    let mut out = b"\x93NUMPY".to_vec();
    if v1 {
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(h.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&[2, 0]);
        out.extend_from_slice(&(h.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(h.as_bytes());
    out.extend_from_slice(&data);
    Some(out)
}

// ------------------------------------------------------------------------------------- .npz

/// A zip of `members`, each stored or deflated.
pub fn zip_of(members: &[(String, Vec<u8>)], deflate: bool) -> Option<Vec<u8>> {
    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let method = if deflate {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    let opts = zip::write::SimpleFileOptions::default().compression_method(method);
    for (name, bytes) in members {
        w.start_file(name.as_str(), opts).ok()?;
        w.write_all(bytes).ok()?;
    }
    Some(w.finish().ok()?.into_inner())
}

/// One edit of a `.npz` archive: a member's `.npy` edited (or its bytes), renamed (a pickle, a
/// path, no suffix), another member added, then zipped again stored or deflated; or a size
/// field of the zip's headers forged.
pub fn npz(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    if rng.random_bool(0.25) {
        // the sizes in the local header (offsets 18, 22) or the central directory (20, 24)
        let mut out = bytes.to_vec();
        let (sig, offs): (&[u8], [usize; 2]) = if rng.random_bool(0.5) {
            (b"PK\x03\x04", [18, 22])
        } else {
            (b"PK\x01\x02", [20, 24])
        };
        let at = out.windows(4).position(|w| w == sig)?;
        let off = at + *offs.choose(rng).expect("a field");
        let v = *[0u32, 1, u32::MAX, 0x7fff_ffff, 1 << 30]
            .choose(rng)
            .expect("a size");
        out.get_mut(off..off + 4)?.copy_from_slice(&v.to_le_bytes());
        return Some(out);
    }
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes)).ok()?;
    let mut members = Vec::new();
    for i in 0..zip.len() {
        let mut f = zip.by_index(i).ok()?;
        let mut b = Vec::new();
        f.read_to_end(&mut b).ok()?;
        members.push((f.name().ok()?.into_owned(), b));
    }
    if members.is_empty() {
        return None;
    }
    let i = rng.random_range(0..members.len());
    match rng.random_range(0..5) {
        0 | 1 => members[i].1 = npy(&members[i].1, rng)?,
        2 => {
            members[i].0 = (*[
                "data.pkl",
                "arr_0",
                "../../arr_0.npy",
                "/abs/arr_0.npy",
                "",
                "a/b/arr_0.npy",
            ]
            .choose(rng)
            .expect("a name"))
            .to_string();
        }
        3 => {
            let extra = members[i].1.clone();
            members.push(("arr_1.npy".into(), extra));
        }
        _ => {
            let b = &mut members[i].1;
            let at = rng.random_range(0..b.len().max(1));
            b.truncate(at);
        }
    }
    zip_of(&members, rng.random_bool(0.5))
}

// -------------------------------------------------------------------------------------- EXR

/// Interesting `i32` values of EXR fields (windows, sizes, pixel types).
const I32S: [i32; 11] = [
    0,
    -1,
    1,
    i32::MAX,
    i32::MIN,
    1 << 20,
    1 << 30,
    -(1 << 30),
    65535,
    1 << 24,
    1023,
];

/// One edit of an OpenEXR file's header: a window (`box2i`) corner set to a boundary value, the
/// sensor description (a JSON string attribute) edited inside, a word of another attribute or
/// an attribute's size field changed, or a chunk offset forged. The chunk offsets are moved
/// with a header that grows or shrinks, so the edit is what the reader sees.
pub fn exr(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    if bytes.len() < 8 || bytes[..4] != [0x76, 0x2f, 0x31, 0x01] {
        return None;
    }
    struct Attr {
        kind: String,
        size_at: usize,
        value_at: usize,
        size: usize,
    }
    let cstr = |at: usize| -> Option<(String, usize)> {
        let end = at + bytes.get(at..)?.iter().position(|b| *b == 0)?;
        Some((
            String::from_utf8_lossy(&bytes[at..end]).into_owned(),
            end + 1,
        ))
    };
    let mut attrs = Vec::new();
    let mut at = 8;
    loop {
        let (name, next) = cstr(at)?;
        if name.is_empty() {
            at = next;
            break;
        }
        let (kind, next) = cstr(next)?;
        let size = i32::from_le_bytes(bytes.get(next..next + 4)?.try_into().ok()?) as usize;
        attrs.push(Attr {
            kind,
            size_at: next,
            value_at: next + 4,
            size,
        });
        at = next + 4 + size;
    }
    let table = at;
    let first = u64::from_le_bytes(bytes.get(table..table + 8)?.try_into().ok()?) as usize;
    let chunks = first.checked_sub(table)? / 8;
    let mut out = bytes.to_vec();
    let set_i32 = |out: &mut Vec<u8>, off: usize, v: i32| {
        if let Some(s) = out.get_mut(off..off + 4) {
            s.copy_from_slice(&v.to_le_bytes());
        }
    };
    match rng.random_range(0..6) {
        0 | 1 => {
            let boxes: Vec<&Attr> = attrs.iter().filter(|a| a.kind == "box2i").collect();
            let a = boxes.choose(rng)?;
            let off = a.value_at + 4 * rng.random_range(0..4);
            set_i32(&mut out, off, *I32S.choose(rng).expect("a value"));
        }
        2 => {
            let texts: Vec<&Attr> = attrs.iter().filter(|a| a.kind == "string").collect();
            let a = texts.choose(rng)?;
            let inner = json(bytes.get(a.value_at..a.value_at + a.size)?, rng)?;
            let delta = inner.len() as i64 - a.size as i64;
            let mut o = bytes[..a.size_at].to_vec();
            o.extend_from_slice(&(inner.len() as i32).to_le_bytes());
            o.extend_from_slice(&inner);
            o.extend_from_slice(&bytes[a.value_at + a.size..]);
            // the offsets table moved by `delta`, and so did every chunk it points at
            let t = (table as i64 + delta) as usize;
            for c in 0..chunks {
                let p = t + 8 * c;
                let v = u64::from_le_bytes(o.get(p..p + 8)?.try_into().ok()?);
                o[p..p + 8].copy_from_slice(&((v as i64 + delta) as u64).to_le_bytes());
            }
            out = o;
        }
        3 => {
            let a = attrs.choose(rng)?;
            if a.size >= 4 {
                let off = a.value_at + 4 * rng.random_range(0..a.size / 4);
                set_i32(&mut out, off, *I32S.choose(rng).expect("a value"));
            } else if a.size > 0 {
                out[a.value_at] = rng.random();
            }
        }
        4 => {
            let a = attrs.choose(rng)?;
            set_i32(&mut out, a.size_at, *I32S.choose(rng).expect("a value"));
        }
        _ => {
            if chunks == 0 {
                return None;
            }
            let p = table + 8 * rng.random_range(0..chunks);
            let v = *[
                0u64,
                u64::MAX,
                bytes.len() as u64,
                bytes.len() as u64 + 1000,
                1 << 62,
            ]
            .choose(rng)
            .expect("an offset");
            out[p..p + 8].copy_from_slice(&v.to_le_bytes());
        }
    }
    Some(out)
}

// -------------------------------------------------------------------------------------- PLY

/// One edit of a PLY header (the body kept): a count, a property's type, the format, an extra
/// element, a property removed, or a word of it.
pub fn ply(bytes: &[u8], rng: &mut FuzzRng) -> Option<Vec<u8>> {
    const END: &[u8] = b"end_header\n";
    let end = bytes.windows(END.len()).position(|w| w == END)? + END.len();
    let header = std::str::from_utf8(&bytes[..end]).ok()?;
    let body = &bytes[end..];
    let mut lines: Vec<String> = header.lines().map(str::to_string).collect();
    let props: Vec<usize> = (0..lines.len())
        .filter(|i| lines[*i].starts_with("property "))
        .collect();
    match rng.random_range(0..6) {
        0 | 1 => {
            let i = lines.iter().position(|l| l.starts_with("element "))?;
            let count = *[
                "0",
                "-1",
                "4294967295",
                "4294967296",
                "18446744073709551615",
                "99999999999999999999",
                "nan",
                "201",
                "400",
            ]
            .choose(rng)
            .expect("a count");
            let name = lines[i].split(' ').nth(1).unwrap_or("vertex").to_string();
            lines[i] = format!("element {name} {count}");
        }
        2 => {
            let i = *props.choose(rng)?;
            let ty = *[
                "char",
                "uchar",
                "short",
                "ushort",
                "int",
                "uint",
                "double",
                "int8",
                "uint16",
                "float64",
                "list uchar int",
                "list uint float",
                "bogus",
            ]
            .choose(rng)
            .expect("a type");
            let name = lines[i].rsplit(' ').next().unwrap_or("x").to_string();
            lines[i] = format!("property {ty} {name}");
        }
        3 => {
            let i = lines.iter().position(|l| l.starts_with("format "))?;
            lines[i] = (*[
                "format ascii 1.0",
                "format binary_big_endian 1.0",
                "format binary_little_endian 2.0",
                "format",
            ]
            .choose(rng)
            .expect("a format"))
            .to_string();
        }
        4 => {
            let at = lines.len() - 1;
            lines.insert(at, "property list uchar int vertex_indices".into());
            lines.insert(at, "element face 4294967295".into());
        }
        _ => {
            let i = *props.choose(rng)?;
            lines.remove(i);
        }
    }
    let mut out = lines.join("\n").into_bytes();
    out.push(b'\n');
    out.extend_from_slice(body);
    Some(out)
}
