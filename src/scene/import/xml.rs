//! The XML tree of a scene file (Mitsuba's formats), with the line of every element, and the
//! properties of an object element as its importers read them.

use crate::scene::SceneError;
use quick_xml::XmlVersion;
use quick_xml::events::{BytesStart, Event};
use std::cell::Cell;
use std::path::Path;

type R<T> = Result<T, SceneError>;

/// An element: tag, attributes in order, children, and the line its tag starts on.
#[derive(Clone, Debug)]
pub(crate) struct Node {
    pub(crate) tag: String,
    pub(crate) attrs: Vec<(String, String)>,
    pub(crate) children: Vec<Node>,
    pub(crate) line: u32,
}

impl Node {
    /// The value of attribute `k`.
    pub(crate) fn attr(&self, k: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(a, _)| a == k)
            .map(|(_, v)| v.as_str())
    }

    /// `<tag type="x">` for messages.
    pub(crate) fn label(&self) -> String {
        match (self.attr("type"), self.attr("name")) {
            (Some(t), _) => format!("<{} type=\"{t}\">", self.tag),
            (None, Some(n)) => format!("<{} name=\"{n}\">", self.tag),
            _ => format!("<{}>", self.tag),
        }
    }
}

/// The error at element `n` of `file`: its line, and `message`.
pub(crate) fn error_at(file: &Path, n: &Node, message: impl Into<String>) -> SceneError {
    SceneError::new(file, format!("line {}", n.line), message)
}

/// The `value` attribute of element `n` of `file`.
pub(crate) fn value_of<'a>(file: &Path, n: &'a Node) -> R<&'a str> {
    n.attr("value")
        .ok_or_else(|| error_at(file, n, format!("{} has no value", n.label())))
}

/// The `<integer>` property `name` of `p` (an element of `file`), or `default` without one.
pub(crate) fn int_prop(file: &Path, p: &Props, name: &str, default: i64) -> R<i64> {
    match p.get(name) {
        Some(n) if n.tag == "integer" => {
            let v = value_of(file, n)?;
            v.trim()
                .parse::<i64>()
                .map_err(|_| error_at(file, n, format!("{}: malformed integer '{v}'", n.label())))
        }
        Some(n) => Err(error_at(
            file,
            n,
            format!("{} should be an <integer>", n.label()),
        )),
        None => Ok(default),
    }
}

/// The `<string>` property `name` of `p` (an element of `file`), if it has one.
pub(crate) fn string_prop(file: &Path, p: &Props, name: &str) -> R<Option<String>> {
    match p.get(name) {
        Some(n) if n.tag == "string" => Ok(Some(value_of(file, n)?.to_string())),
        Some(n) => Err(error_at(
            file,
            n,
            format!("{} should be a <string>", n.label()),
        )),
        None => Ok(None),
    }
}

/// Line starts of a text, to turn byte positions into line numbers.
struct Lines(Vec<usize>);

impl Lines {
    fn new(text: &str) -> Self {
        Lines(
            text.bytes()
                .enumerate()
                .filter(|(_, b)| *b == b'\n')
                .map(|(i, _)| i)
                .collect(),
        )
    }

    fn line(&self, pos: usize) -> u32 {
        1 + self.0.partition_point(|&n| n < pos) as u32
    }
}

/// Deepest nesting of elements a scene file may have. Real scenes nest a dozen levels at most
/// (scene, shape, bsdf, nested bsdfs, texture, property); the tree is built without recursion,
/// but walking and dropping it recurse, so the depth is bounded where it is read.
pub(crate) const MAX_XML_DEPTH: usize = 128;

/// Parses XML text into its tree of elements; errors name the line.
pub(crate) fn parse_xml(text: &str, file: &Path) -> R<Node> {
    let lines = Lines::new(text);
    let mut reader = quick_xml::Reader::from_str(text);
    reader.config_mut().trim_text(true);
    let err = |pos: usize, m: String| SceneError::new(file, format!("line {}", lines.line(pos)), m);
    let mut stack: Vec<Node> = Vec::new();
    let mut root: Option<Node> = None;
    let element = |e: &BytesStart, end: usize| -> R<Node> {
        // The tag starts at the last '<' before the end of the tag ('<' cannot occur inside
        // attribute values of well-formed XML).
        let start = text[..end].rfind('<').unwrap_or(0);
        let tag = e.name().as_ref().to_string();
        let mut attrs = Vec::new();
        for a in e.attributes() {
            let a = a.map_err(|x| err(start, format!("malformed attribute: {x}")))?;
            let k = a.key.as_ref().to_string();
            let v = a
                .normalized_value(XmlVersion::Implicit1_0)
                .map_err(|x| err(start, format!("malformed attribute value: {x}")))?
                .into_owned();
            attrs.push((k, v));
        }
        Ok(Node {
            tag,
            attrs,
            children: Vec::new(),
            line: lines.line(start),
        })
    };
    loop {
        let ev = reader.read_event();
        let pos = reader.buffer_position() as usize;
        match ev {
            Err(e) => {
                return Err(err(
                    reader.error_position() as usize,
                    format!("malformed XML: {e}"),
                ));
            }
            Ok(Event::Eof) => break,
            Ok(Event::Start(e)) => {
                let n = element(&e, pos)?;
                if stack.len() >= MAX_XML_DEPTH {
                    return Err(SceneError::new(
                        file,
                        format!("line {}", n.line),
                        format!(
                            "<{}> is nested more than {MAX_XML_DEPTH} elements deep",
                            n.tag
                        ),
                    ));
                }
                stack.push(n);
            }
            Ok(Event::Empty(e)) => {
                let n = element(&e, pos)?;
                match stack.last_mut() {
                    Some(p) => p.children.push(n),
                    None if root.is_none() => root = Some(n),
                    None => return Err(err(pos, "more than one root element".into())),
                }
            }
            Ok(Event::End(_)) => {
                let Some(n) = stack.pop() else {
                    return Err(err(pos, "unexpected closing tag".into()));
                };
                match stack.last_mut() {
                    Some(p) => p.children.push(n),
                    None if root.is_none() => root = Some(n),
                    None => return Err(err(pos, "more than one root element".into())),
                }
            }
            Ok(Event::Text(t)) => {
                if !t.as_ref().chars().all(char::is_whitespace) {
                    return Err(err(pos, "unexpected text between elements".into()));
                }
            }
            Ok(Event::CData(_) | Event::GeneralRef(_)) => {
                return Err(err(pos, "unexpected text between elements".into()));
            }
            Ok(Event::Comment(_) | Event::Decl(_) | Event::PI(_) | Event::DocType(_)) => {}
        }
    }
    if let Some(open) = stack.last() {
        return Err(SceneError::new(
            file,
            format!("line {}", open.line),
            format!("<{}> is never closed", open.tag),
        ));
    }
    root.ok_or_else(|| SceneError::new(file, "line 1", "no XML element in the file"))
}

/// The children of an object element, with a flag per child telling whether anything read it.
pub(crate) struct Props<'n> {
    pub(crate) node: &'n Node,
    used: Vec<Cell<bool>>,
}

impl<'n> Props<'n> {
    /// The properties of `node`, none read yet.
    pub(crate) fn new(node: &'n Node) -> Self {
        Props {
            node,
            used: node.children.iter().map(|_| Cell::new(false)).collect(),
        }
    }

    /// The last child named `name` (any tag).
    pub(crate) fn get(&self, name: &str) -> Option<&'n Node> {
        let (i, n) = self
            .node
            .children
            .iter()
            .enumerate()
            .rev()
            .find(|(_, c)| c.attr("name") == Some(name))?;
        self.used[i].set(true);
        Some(n)
    }

    /// Whether a child is named `name`.
    pub(crate) fn has(&self, name: &str) -> bool {
        self.node
            .children
            .iter()
            .any(|c| c.attr("name") == Some(name))
    }

    /// Children with tag `tag` and no `name` attribute (nested objects).
    pub(crate) fn objects(&self, tag: &str) -> Vec<&'n Node> {
        let mut out = Vec::new();
        for (i, c) in self.node.children.iter().enumerate() {
            if c.tag == tag && c.attr("name").is_none() {
                self.used[i].set(true);
                out.push(c);
            }
        }
        out
    }

    /// Children with tag `tag`, named or not.
    pub(crate) fn any_with_tag(&self, tag: &str) -> Vec<&'n Node> {
        let mut out = Vec::new();
        for (i, c) in self.node.children.iter().enumerate() {
            if c.tag == tag {
                self.used[i].set(true);
                out.push(c);
            }
        }
        out
    }

    /// Marks property `name` read (its value does not change the image).
    pub(crate) fn consume(&self, name: &str) {
        let _ = self.get(name);
    }

    /// The children nothing read.
    pub(crate) fn unused(&self) -> Vec<&'n Node> {
        self.node
            .children
            .iter()
            .zip(&self.used)
            .filter(|(_, u)| !u.get())
            .map(|(c, _)| c)
            .collect()
    }
}

/// Numbers separated by commas or white space.
pub(crate) fn split_numbers(s: &str) -> Result<Vec<f32>, String> {
    s.split(|c: char| c == ',' || c.is_whitespace())
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<f32>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("malformed number '{t}'"))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xml_tree_keeps_lines() {
        let t = "<?xml version=\"1.0\"?>\n<scene version=\"0.5.0\">\n  <shape type=\"cube\"\n     id=\"a\">\n    <float name=\"x\" value=\"1\"/>\n  </shape>\n</scene>\n";
        let root = parse_xml(t, Path::new("s.xml")).unwrap();
        assert_eq!(root.tag, "scene");
        assert_eq!(root.line, 2);
        assert_eq!(root.children[0].line, 3);
        assert_eq!(root.children[0].children[0].line, 5);
        let e = parse_xml("<scene>\n<shape>\n</scene>", Path::new("s.xml")).unwrap_err();
        assert!(e.location.starts_with("line "), "{e}");
    }
}
