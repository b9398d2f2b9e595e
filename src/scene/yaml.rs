//! A YAML document as a tree of nodes that remember their line, so that every error
//! about a scene can point at the line and the key at fault.
//!
//! Parsing is serde-saphyr's; this module only keeps its spans on every node.

use crate::expr::excerpt;
use serde::de::{self, Deserialize, Deserializer, MapAccess, SeqAccess, Visitor};
use serde_saphyr::budget::BudgetBreach;
use serde_saphyr::Spanned;
use std::fmt;

/// A YAML value with its 1-based source line (0 when unknown).
#[derive(Debug, Clone)]
pub struct Node {
    pub value: Value,
    pub line: u64,
}

#[derive(Debug, Clone)]
pub enum Value {
    Null,
    Bool(bool),
    Number(f64),
    String(String),
    Seq(Vec<Node>),
    /// Key–value pairs in file order.
    Map(Vec<(Node, Node)>),
}

impl Node {
    pub fn kind(&self) -> &'static str {
        match self.value {
            Value::Null => "null",
            Value::Bool(_) => "a boolean",
            Value::Number(_) => "a number",
            Value::String(_) => "a string",
            Value::Seq(_) => "a list",
            Value::Map(_) => "a mapping",
        }
    }

    /// The node as text (a string, or a number written back as text).
    pub fn as_text(&self) -> Option<String> {
        match &self.value {
            Value::String(s) => Some(s.clone()),
            Value::Number(v) => Some(format!("{v}")),
            _ => None,
        }
    }
}

/// A syntax error reported by the YAML parser: message, line, and the key whose value
/// is at fault where the line shows it (empty otherwise).
#[derive(Debug, Clone)]
pub struct SyntaxError {
    pub message: String,
    pub line: Option<u64>,
    pub key: String,
}

/// Parses a whole YAML document into a located tree.
pub fn parse(text: &str) -> Result<Node, SyntaxError> {
    if text
        .lines()
        .all(|l| l.trim().is_empty() || l.trim_start().starts_with('#') || l.trim() == "---")
    {
        return Err(SyntaxError {
            message: "the file is empty: a scene is a YAML mapping (name, points, bodies, …)"
                .to_string(),
            line: None,
            key: String::new(),
        });
    }
    let options = serde_saphyr::options! {
        duplicate_keys: serde_saphyr::options::DuplicateKeyPolicy::Error,
        // YAML 1.2 booleans only: `y` and `n` are coordinates here, not yes and no.
        strict_booleans: true,
    };
    match serde_saphyr::from_str_with_options::<Spanned<Raw>>(text, options) {
        Ok(root) => Ok(located(root)),
        Err(e) => {
            let inner = e.without_snippet();
            let line = e.location().map(|l| l.line()).filter(|&l| l > 0);
            let column = e.location().map_or(0, |l| l.column() as usize);
            let key = match line {
                Some(l) if !matches!(inner, serde_saphyr::Error::Budget { .. }) => {
                    key_before(text, l as usize, column)
                }
                _ => String::new(),
            };
            // A flow mapping or list left open is found by the parser lines later,
            // where something cannot continue it: name the line that opened it.
            if let Some((open_line, bracket)) = line.and_then(|l| unclosed_flow(text, l as usize)) {
                return Err(SyntaxError {
                    message: format!(
                        "`{bracket}` opened on this line is not closed (a {} must end with `{}`)",
                        if bracket == '{' {
                            "flow mapping {…}"
                        } else {
                            "flow list […]"
                        },
                        if bracket == '{' { '}' } else { ']' }
                    ),
                    line: Some(open_line as u64),
                    key: String::new(),
                });
            }
            let message = match inner {
                serde_saphyr::Error::Budget { breach, .. } => budget_words(breach),
                // The user-facing wording: the default one gives advice on the
                // parser's own API ("set DuplicateKeyPolicy in Options").
                _ => {
                    let text = inner.render_with_formatter(&serde_saphyr::UserMessageFormatter);
                    let first = text.lines().next().unwrap_or("invalid YAML");
                    // A breach wrapped in another error still renders in Debug form.
                    match first.find("limits breached") {
                        Some(_) => "YAML document too large or too complex".to_string(),
                        // The line is the error's own; the column is in the key.
                        None => excerpt(first.split(" at line ").next().unwrap_or(first), 200),
                    }
                }
            };
            Err(SyntaxError { message, line, key })
        }
    }
}

/// The key written before `column` (1-based) of line `line` (1-based): `k` in
/// `  k: .nan` or in `{x: 1, k: .nan}`; empty when there is none.
fn key_before(text: &str, line: usize, column: usize) -> String {
    let Some(source) = text.lines().nth(line.saturating_sub(1)) else {
        return String::new();
    };
    let before: String = source.chars().take(column.saturating_sub(1)).collect();
    let Some(head) = before.trim_end().strip_suffix(':') else {
        return String::new();
    };
    let key: String = head
        .chars()
        .rev()
        .take_while(|c| !matches!(c, '{' | ',' | ' ' | '-' | '[' | '\t'))
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    excerpt(key.trim_matches(['"', '\'']), 40)
}

/// The line (1-based) and bracket of the outermost flow mapping or list still open at
/// the start of line `error_line`, outside quotes and comments; None when all are
/// closed there.
fn unclosed_flow(text: &str, error_line: usize) -> Option<(usize, char)> {
    let mut open: Vec<(usize, char)> = Vec::new();
    for (n, source) in text.lines().enumerate().take(error_line.saturating_sub(1)) {
        let mut quote: Option<char> = None;
        let mut previous = ' ';
        for c in source.chars() {
            match quote {
                Some(q) if c == q => quote = None,
                Some(_) => {}
                None => match c {
                    '#' if previous.is_whitespace() => break,
                    '"' | '\'' => quote = Some(c),
                    '{' | '[' => open.push((n + 1, c)),
                    '}' | ']' => {
                        open.pop();
                    }
                    _ => {}
                },
            }
            previous = c;
        }
    }
    open.first().copied()
}

/// A budget breach in plain words (the parser's own message is Rust Debug text).
fn budget_words(breach: &BudgetBreach) -> String {
    let what = match breach {
        BudgetBreach::Events { events } => {
            format!("more than {} parser events", events.saturating_sub(1))
        }
        BudgetBreach::Aliases { aliases } => {
            format!("more than {} aliases", aliases.saturating_sub(1))
        }
        BudgetBreach::Anchors { anchors } => {
            format!("more than {} anchors", anchors.saturating_sub(1))
        }
        BudgetBreach::Depth { depth } => {
            format!("nested {depth} levels deep (lists and mappings)")
        }
        BudgetBreach::Documents { documents } => format!("{documents} documents"),
        BudgetBreach::Nodes { nodes } => format!("more than {} values", nodes.saturating_sub(1)),
        BudgetBreach::ScalarBytes { total_scalar_bytes } => {
            format!("{total_scalar_bytes} bytes of text in values")
        }
        BudgetBreach::MergeKeys { merge_keys } => format!("{merge_keys} merge keys"),
        BudgetBreach::AliasAnchorRatio { aliases, anchors } => {
            format!("{aliases} aliases for {anchors} anchors")
        }
        BudgetBreach::SequenceUnbalanced => "unbalanced lists or mappings".to_string(),
        BudgetBreach::InputBytes { input_bytes } => format!("{input_bytes} bytes"),
        BudgetBreach::RecordedAnchorEvents {
            recorded_anchor_events,
        } => format!("{recorded_anchor_events} values copied through aliases"),
        BudgetBreach::RecordedAnchorBytes {
            recorded_anchor_bytes,
        } => format!("{recorded_anchor_bytes} bytes copied through aliases"),
        _ => "a size limit exceeded".to_string(),
    };
    format!("YAML document too large or too complex: {what}")
}

/// The node as parsed, before its span is attached.
struct Raw(Value);

fn located(s: Spanned<Raw>) -> Node {
    Node {
        value: s.value.0,
        line: s.referenced.line(),
    }
}

impl<'de> Deserialize<'de> for Raw {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(RawVisitor)
    }
}

struct RawVisitor;

impl<'de> Visitor<'de> for RawVisitor {
    type Value = Raw;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("any YAML value")
    }
    fn visit_unit<E: de::Error>(self) -> Result<Raw, E> {
        Ok(Raw(Value::Null))
    }
    fn visit_none<E: de::Error>(self) -> Result<Raw, E> {
        Ok(Raw(Value::Null))
    }
    fn visit_some<D: Deserializer<'de>>(self, d: D) -> Result<Raw, D::Error> {
        Raw::deserialize(d)
    }
    fn visit_bool<E: de::Error>(self, v: bool) -> Result<Raw, E> {
        Ok(Raw(Value::Bool(v)))
    }
    fn visit_i64<E: de::Error>(self, v: i64) -> Result<Raw, E> {
        Ok(Raw(Value::Number(v as f64)))
    }
    fn visit_u64<E: de::Error>(self, v: u64) -> Result<Raw, E> {
        Ok(Raw(Value::Number(v as f64)))
    }
    fn visit_f64<E: de::Error>(self, v: f64) -> Result<Raw, E> {
        Ok(Raw(Value::Number(v)))
    }
    fn visit_str<E: de::Error>(self, v: &str) -> Result<Raw, E> {
        Ok(Raw(Value::String(v.to_string())))
    }
    fn visit_string<E: de::Error>(self, v: String) -> Result<Raw, E> {
        Ok(Raw(Value::String(v)))
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Raw, A::Error> {
        let mut items = Vec::new();
        while let Some(item) = seq.next_element::<Spanned<Raw>>()? {
            items.push(located(item));
        }
        Ok(Raw(Value::Seq(items)))
    }
    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Raw, A::Error> {
        let mut pairs = Vec::new();
        while let Some(key) = map.next_key::<Spanned<Raw>>()? {
            let value = map.next_value::<Spanned<Raw>>()?;
            pairs.push((located(key), located(value)));
        }
        Ok(Raw(Value::Map(pairs)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nodes_keep_their_lines() {
        let doc = parse("a: 1\nb:\n  - x\n  - {y: 2.5}\nc: (1/3)*m\n").unwrap();
        let Value::Map(pairs) = &doc.value else {
            panic!("not a map")
        };
        assert_eq!(pairs.len(), 3);
        assert_eq!(pairs[0].0.line, 1);
        let Value::Seq(items) = &pairs[1].1.value else {
            panic!("not a seq")
        };
        assert_eq!(items[1].line, 4);
        assert_eq!(pairs[2].1.as_text().unwrap(), "(1/3)*m");
        assert_eq!(pairs[2].1.line, 5);
    }

    #[test]
    fn an_unclosed_flow_mapping_is_named_where_it_opened() {
        let e = parse("a: 1\nb:\n  - {x: 1, y: 2\n  - {x: 3, y: 4}\nc:\n  - {z: 1}\n").unwrap_err();
        assert_eq!(e.line, Some(3), "{e:?}");
        assert!(
            e.message.contains("`{` opened on this line is not closed"),
            "{e:?}"
        );
        // Flow mappings may span lines; closed ones are not blamed.
        assert!(parse("a: {x: 1,\n  y: 2}\nb: [1, # c\n 2]\n").is_ok());
    }

    #[test]
    fn a_value_that_is_not_finite_names_its_key() {
        let e = parse("a: 1\nk: .nan\n").unwrap_err();
        assert_eq!((e.line, e.key.as_str()), (Some(2), "k"), "{e:?}");
        let e = parse("p:\n  - {x: 1, mass: .inf}\n").unwrap_err();
        assert_eq!((e.line, e.key.as_str()), (Some(2), "mass"), "{e:?}");
    }

    #[test]
    fn an_empty_file_is_called_empty() {
        for text in ["", "\n  \n", "# only a comment\n"] {
            assert!(parse(text)
                .unwrap_err()
                .message
                .contains("the file is empty"));
        }
    }

    #[test]
    fn syntax_errors_have_a_line() {
        let e = parse("a: 1\nb: [1, 2\nc: 3\n").unwrap_err();
        assert!(e.line.is_some(), "{e:?}");
        let d = parse("a: 1\na: 2\n").unwrap_err();
        assert!(d.message.to_lowercase().contains("duplicate"), "{d:?}");
    }
}
