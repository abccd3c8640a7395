//! The YAML of the datasets' configuration files (`semantic-kitti.yaml`), read with `yaml-rust2`
//! (a maintained, pure-Rust YAML 1.2 parser; serde_yaml is archived and serde_yml deprecated).
//!
//! The parser's event stream is turned into a small tree of strings here, so that the readers decide
//! what a scalar means (`True`, `0`, `"car"`) and every error names the file. The tree is built
//! without recursion and bounded in depth; anchors, aliases and tags are rejected rather than
//! resolved, and a document must be a mapping.

use std::path::Path;

use yaml_rust2::parser::{Event, Parser};
use yaml_rust2::scanner::TScalarStyle;

use crate::{Error, Result};

/// Deepest nesting accepted (the label map needs 3).
const MAX_DEPTH: usize = 32;

/// A parsed YAML node.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Yaml {
    /// A mapping, in file order.
    Map(Vec<(String, Yaml)>),
    /// A sequence.
    Seq(Vec<Yaml>),
    /// A scalar, quotes removed.
    Scalar(String),
    /// An empty value (`key:` followed by nothing), `~` or `null`.
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

/// A collection being built: a mapping (with the key waiting for its value) or a sequence.
enum Open {
    Map(Vec<(String, Yaml)>, Option<String>),
    Seq(Vec<Yaml>),
}

/// Parse the first document of `text` (the content of `path`, used in error messages).
pub(crate) fn parse(text: &str, path: &Path) -> Result<Yaml> {
    let mut parser = Parser::new_from_str(text);
    let mut stack: Vec<Open> = Vec::new();
    let mut root = None;
    loop {
        let (event, mark) = parser
            .next_token()
            .map_err(|e| Error::format(path, format!("YAML: {e}")))?;
        let at = |what: &str| Error::format(path, format!("line {}: {what}", mark.line()));
        let node = match event {
            Event::StreamEnd | Event::DocumentEnd => break,
            Event::Nothing | Event::StreamStart | Event::DocumentStart => continue,
            Event::Alias(_) => return Err(at("aliases are not supported")),
            Event::Scalar(value, style, anchor, tag) => {
                if anchor != 0 || tag.is_some() {
                    return Err(at("anchors and tags are not supported"));
                }
                let empty = matches!(value.as_str(), "" | "~" | "null" | "Null" | "NULL");
                if style == TScalarStyle::Plain && empty {
                    Yaml::Null
                } else {
                    Yaml::Scalar(value)
                }
            }
            Event::SequenceStart(anchor, ref tag) | Event::MappingStart(anchor, ref tag) => {
                if anchor != 0 || tag.is_some() {
                    return Err(at("anchors and tags are not supported"));
                }
                if stack.len() >= MAX_DEPTH {
                    return Err(at(&format!("nested deeper than {MAX_DEPTH} levels")));
                }
                stack.push(if matches!(event, Event::MappingStart(..)) {
                    Open::Map(Vec::new(), None)
                } else {
                    Open::Seq(Vec::new())
                });
                continue;
            }
            Event::SequenceEnd | Event::MappingEnd => match stack.pop() {
                Some(Open::Seq(items)) => Yaml::Seq(items),
                Some(Open::Map(entries, None)) => Yaml::Map(entries),
                Some(Open::Map(_, Some(key))) => {
                    return Err(at(&format!("key `{key}` has no value")));
                }
                None => return Err(at("unbalanced collection")),
            },
        };
        match stack.last_mut() {
            None => {
                root = Some(node);
            }
            Some(Open::Seq(items)) => items.push(node),
            Some(Open::Map(entries, pending)) => match pending.take() {
                None => match node {
                    Yaml::Scalar(key) => {
                        if entries.iter().any(|(k, _)| *k == key) {
                            return Err(at(&format!("key `{key}` appears twice")));
                        }
                        *pending = Some(key);
                    }
                    _ => return Err(at("mapping keys must be scalars")),
                },
                Some(key) => entries.push((key, node)),
            },
        }
    }
    match root {
        Some(map @ Yaml::Map(_)) => Ok(map),
        Some(_) => Err(Error::format(path, "the document is not a mapping")),
        None => Err(Error::format(path, "no YAML document")),
    }
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
            "# head\na: # bgr\n  0 : [1, 2, 3]\n  10: \"car # not a comment\"\nsplit:\n  train:\n    - 0\n    - 1\n  valid:\n  - 8\n  test:\nflag: True\n",
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
        assert_eq!(y.get("split").unwrap().get("test").unwrap(), &Yaml::Null);
        assert_eq!(y.get("flag").unwrap(), &Yaml::Scalar("True".into()));
        // flow mappings are YAML too
        assert_eq!(
            p("a: {b: 1}\n").get("a").unwrap().get("b"),
            Some(&Yaml::Scalar("1".into()))
        );
    }

    #[test]
    fn rejects_what_it_does_not_understand() {
        let deep = format!("a: {}1{}\n", "[".repeat(40), "]".repeat(40));
        for bad in [
            "a:\n  b: 1\n c: 2\n",
            "a: [1, 2\n",
            "a: &x 1\nb: *x\n",
            "a: !!str 1\n",
            "a: 1\na: 2\n",
            "just text\n",
            "- 1\n- 2\n",
            "a: \"open\n",
            "a:\n\t- 1\n",
            "",
            deep.as_str(),
        ] {
            let e = parse(bad, Path::new("bad.yaml"));
            assert!(e.is_err(), "accepted {bad:?}");
            assert!(e.unwrap_err().to_string().contains("bad.yaml"));
        }
    }
}
