//! A deliberately small YAML reader for the block-structured configuration files of the datasets
//! (`semantic-kitti.yaml`): nested block mappings (`key: value` / `key:` + indented block), block
//! sequences (`- item`), flow sequences of scalars (`[1, 2, 3]`), quoted and plain scalars and `#`
//! comments. Anchors, multi-line strings, flow mappings and documents are rejected with a clear error
//! rather than misread.

use std::path::Path;

use crate::{Error, Result};

/// A parsed YAML node.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Yaml {
    /// A block mapping, in file order.
    Map(Vec<(String, Yaml)>),
    /// A block or flow sequence.
    Seq(Vec<Yaml>),
    /// A scalar, quotes removed.
    Scalar(String),
    /// A key with no value (`key:` followed by nothing indented).
    Null,
}

impl Yaml {
    /// The value of `key` when this is a mapping.
    pub(crate) fn get(&self, key: &str) -> Option<&Yaml> {
        match self {
            Yaml::Map(entries) => entries.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }
}

#[derive(Debug)]
struct Line<'a> {
    number: usize,
    indent: usize,
    text: &'a str,
}

/// Parse `text` (the content of `path`, used in error messages).
pub(crate) fn parse(text: &str, path: &Path) -> Result<Yaml> {
    let mut lines = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let number = i + 1;
        let lead = &raw[..raw.len() - raw.trim_start().len()];
        if lead.contains('\t') {
            return Err(Error::format(
                path,
                format!("line {number}: tab indentation is not YAML"),
            ));
        }
        let content = strip_comment(raw);
        let trimmed = content.trim_end();
        if trimmed.trim().is_empty() {
            continue;
        }
        if trimmed.trim() == "---" || trimmed.trim() == "..." {
            continue;
        }
        let indent = trimmed.len() - trimmed.trim_start().len();
        lines.push(Line {
            number,
            indent,
            text: trimmed.trim_start(),
        });
    }
    if lines.is_empty() {
        return Ok(Yaml::Null);
    }
    let mut pos = 0;
    let indent = lines[0].indent;
    let node = parse_block(&lines, &mut pos, indent, path)?;
    if pos != lines.len() {
        let l = &lines[pos];
        return Err(Error::format(
            path,
            format!(
                "line {}: unexpected indentation (expected column {})",
                l.number, indent
            ),
        ));
    }
    Ok(node)
}

/// Remove a `#` comment that is not inside quotes (a comment needs whitespace or line start before it).
fn strip_comment(line: &str) -> &str {
    let bytes = line.as_bytes();
    let mut quote: Option<u8> = None;
    for (i, &b) in bytes.iter().enumerate() {
        match quote {
            Some(q) if b == q => quote = None,
            Some(_) => {}
            None => {
                if b == b'"' || b == b'\'' {
                    quote = Some(b);
                } else if b == b'#' && (i == 0 || bytes[i - 1] == b' ' || bytes[i - 1] == b'\t') {
                    return &line[..i];
                }
            }
        }
    }
    line
}

fn parse_block(lines: &[Line<'_>], pos: &mut usize, indent: usize, path: &Path) -> Result<Yaml> {
    let first = &lines[*pos];
    if first.text.starts_with("- ") || first.text == "-" {
        let mut items = Vec::new();
        while *pos < lines.len() && lines[*pos].indent == indent {
            let l = &lines[*pos];
            let Some(rest) = l.text.strip_prefix('-') else {
                return Err(Error::format(
                    path,
                    format!("line {}: a mapping entry inside a sequence", l.number),
                ));
            };
            let rest = rest.trim();
            *pos += 1;
            if rest.is_empty() {
                items.push(parse_nested(lines, pos, indent, path)?);
            } else if split_key(rest).is_some() {
                return Err(Error::format(
                    path,
                    format!(
                        "line {}: mappings inside sequence items are not supported",
                        l.number
                    ),
                ));
            } else {
                items.push(parse_inline(rest, l.number, path)?);
            }
        }
        return Ok(Yaml::Seq(items));
    }
    let mut entries: Vec<(String, Yaml)> = Vec::new();
    while *pos < lines.len() && lines[*pos].indent == indent {
        let l = &lines[*pos];
        let Some((key, value)) = split_key(l.text) else {
            return Err(Error::format(
                path,
                format!(
                    "line {}: expected `key: value`, found `{}`",
                    l.number, l.text
                ),
            ));
        };
        let key = unquote(key.trim(), l.number, path)?;
        if entries.iter().any(|(k, _)| *k == key) {
            return Err(Error::format(
                path,
                format!("line {}: duplicate key `{key}`", l.number),
            ));
        }
        *pos += 1;
        let value = value.trim();
        let node = if value.is_empty() {
            parse_nested(lines, pos, indent, path)?
        } else {
            parse_inline(value, l.number, path)?
        };
        entries.push((key, node));
    }
    if *pos < lines.len() && lines[*pos].indent > indent {
        let l = &lines[*pos];
        return Err(Error::format(
            path,
            format!("line {}: unexpected indentation", l.number),
        ));
    }
    Ok(Yaml::Map(entries))
}

/// The block nested under a `key:` or `-` at `parent_indent`; a sequence may sit at the same indent as
/// its parent key (`key:\n- a`), as YAML allows.
fn parse_nested(
    lines: &[Line<'_>],
    pos: &mut usize,
    parent_indent: usize,
    path: &Path,
) -> Result<Yaml> {
    match lines.get(*pos) {
        Some(next) if next.indent > parent_indent => parse_block(lines, pos, next.indent, path),
        Some(next) if next.indent == parent_indent && next.text.starts_with("- ") => {
            parse_block(lines, pos, next.indent, path)
        }
        _ => Ok(Yaml::Null),
    }
}

/// Split `key: value` at the first `:` outside quotes that is followed by a space or the line end.
fn split_key(text: &str) -> Option<(&str, &str)> {
    let bytes = text.as_bytes();
    let mut quote: Option<u8> = None;
    for (i, &b) in bytes.iter().enumerate() {
        match quote {
            Some(q) if b == q => quote = None,
            Some(_) => {}
            None => {
                if (b == b'"' || b == b'\'') && i == 0 {
                    quote = Some(b);
                } else if b == b'[' || b == b'{' {
                    return None;
                } else if b == b':' && (i + 1 == bytes.len() || bytes[i + 1] == b' ') {
                    return Some((&text[..i], &text[i + 1..]));
                }
            }
        }
    }
    None
}

fn parse_inline(text: &str, line: usize, path: &Path) -> Result<Yaml> {
    let t = text.trim();
    if let Some(inner) = t.strip_prefix('[') {
        let Some(inner) = inner.strip_suffix(']') else {
            return Err(Error::format(
                path,
                format!("line {line}: unterminated flow sequence"),
            ));
        };
        if inner.trim().is_empty() {
            return Ok(Yaml::Seq(Vec::new()));
        }
        let mut items = Vec::new();
        for part in inner.split(',') {
            let part = part.trim();
            if part.starts_with('[') || part.starts_with('{') {
                return Err(Error::format(
                    path,
                    format!("line {line}: nested flow collections"),
                ));
            }
            items.push(Yaml::Scalar(unquote(part, line, path)?));
        }
        return Ok(Yaml::Seq(items));
    }
    if t.starts_with('{')
        || t.starts_with('&')
        || t.starts_with('*')
        || t.starts_with('|')
        || t.starts_with('>')
    {
        return Err(Error::format(
            path,
            format!(
                "line {line}: unsupported YAML construct `{t}` (flow map, anchor, alias or block string)"
            ),
        ));
    }
    Ok(Yaml::Scalar(unquote(t, line, path)?))
}

fn unquote(t: &str, line: usize, path: &Path) -> Result<String> {
    for q in ['"', '\''] {
        if let Some(rest) = t.strip_prefix(q) {
            return match rest.strip_suffix(q) {
                Some(inner) => Ok(inner.to_string()),
                None => Err(Error::format(
                    path,
                    format!("line {line}: unterminated quote in `{t}`"),
                )),
            };
        }
    }
    Ok(t.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(text: &str) -> Yaml {
        parse(text, Path::new("t.yaml")).unwrap()
    }

    #[test]
    fn nested_maps_sequences_and_comments() {
        let y = p(
            "# head\na: # bgr\n  0 : [1, 2, 3]\n  10: \"car # not a comment\"\nsplit:\n  train:\n    - 0\n    - 1\n  valid:\n  - 8\nflag: True\n",
        );
        assert_eq!(
            y.get("a").unwrap().get("0").unwrap(),
            &Yaml::Seq(vec![
                Yaml::Scalar("1".into()),
                Yaml::Scalar("2".into()),
                Yaml::Scalar("3".into())
            ])
        );
        assert_eq!(
            y.get("a").unwrap().get("10").unwrap(),
            &Yaml::Scalar("car # not a comment".into())
        );
        assert_eq!(
            y.get("split").unwrap().get("train").unwrap(),
            &Yaml::Seq(vec![Yaml::Scalar("0".into()), Yaml::Scalar("1".into())])
        );
        assert_eq!(
            y.get("split").unwrap().get("valid").unwrap(),
            &Yaml::Seq(vec![Yaml::Scalar("8".into())])
        );
        assert_eq!(y.get("flag").unwrap(), &Yaml::Scalar("True".into()));
    }

    #[test]
    fn rejects_what_it_does_not_understand() {
        for bad in [
            "a:\n  b: 1\n c: 2\n",
            "a: [1, 2\n",
            "a: {b: 1}\n",
            "a: &x 1\n",
            "a: 1\na: 2\n",
            "just text\n",
            "a: \"open\n",
        ] {
            let e = parse(bad, Path::new("bad.yaml"));
            assert!(e.is_err(), "accepted {bad:?}");
            assert!(e.unwrap_err().to_string().contains("bad.yaml"));
        }
    }
}
