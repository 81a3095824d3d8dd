//! Mitsuba 3 (and Mitsuba 2) scene files: the XML format of the Mitsuba 3 renderer (Jakob,
//! Speierer, Roussel, Nimier-David, Vicini, Zeltner, Nicolet, Crespo, Leroy and Zhang, 2022;
//! its documentation's "Scene file format" and plugin reference, version 3.9), mapped onto our
//! scene model.
//!
//! A file is read the way Mitsuba reads it:
//! - `<default name value>` and `$name` in any attribute, the values given from outside
//!   (`SceneParams`: `--define`, a job's `defines`) winning over the file's defaults; a `$name`
//!   used before it is defined, or a value given from outside that the file never uses, is an
//!   error;
//! - `<include filename>` (nested at most `MAX_INCLUDE_DEPTH` deep), `<ref id>` to any object
//!   with an id, also forward, and `<alias>`;
//! - the property names of versions 2 and 3 (`to_world`, `max_depth`): a file of version 2 or
//!   3 is read as written, without Mitsuba 0.5's camelCase names.
//!
//! Whatever our renderer cannot represent exactly is a warning naming the file and line; a
//! construct without which the image would no longer mean what the file says (an emitter or a
//! material it lacks, participating media) is an error, every such construct of the file named
//! at once. Mitsuba's `max_depth` counts the emitter vertex: its depth d is our max depth d - 1
//! (scenes/README.md).

mod bsdfs;
mod emitters;
mod sensor;
mod shapes;
mod values;

use super::common::{Bitmaps, Warnings};
use super::resolve::Resolver;
use super::xml::{self, MAX_XML_DEPTH, Node, parse_xml};
use crate::scene::import::mesh::MeshError;
use crate::scene::{MeshData, SceneBuilder, SceneError, SceneParams};
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

type R<T> = Result<T, SceneError>;

/// Nesting limit of `<include>` (Mitsuba's own).
const MAX_INCLUDE_DEPTH: usize = 15;

/// Our max depth for Mitsuba's `max_depth -1` (unlimited): paths are ended by Russian roulette
/// long before it.
pub(crate) const UNLIMITED_DEPTH: u32 = 64;

/// The major version of a Mitsuba file (`version="3.0.0"`), or None when malformed.
pub(crate) fn major_version(v: &str) -> Option<u32> {
    v.trim().split('.').next()?.parse().ok()
}

/// Parses a Mitsuba 2 or 3 file whose tree is `root`, with the parameter values `params`.
pub(crate) fn parse(root: Node, resolver: Resolver, params: &SceneParams) -> R<SceneBuilder> {
    let file = resolver.scene_file().to_path_buf();
    let mut cx = Ctx {
        file: file.clone(),
        b: SceneBuilder::new(resolver),
        warn: Warnings::default(),
        refused: Vec::new(),
        table: params
            .values()
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect(),
        given: params.values().keys().cloned().collect(),
        used: HashSet::new(),
        ids: HashMap::new(),
        materials: HashMap::new(),
        bitmaps: Bitmaps::default(),
        meshes: HashMap::new(),
        default_bsdf: None,
        black_bsdf: None,
        environment_seen: false,
    };
    let root = cx.expand(root, &file, 0)?;
    if root.tag != "scene" {
        return Err(cx.err(
            &root,
            format!("the root element is <{}>, expected <scene>", root.tag),
        ));
    }
    let unused: Vec<&String> = cx.given.iter().filter(|k| !cx.used.contains(*k)).collect();
    if !unused.is_empty() {
        return Err(SceneError::new(
            &file,
            "parameters",
            format!(
                "the file uses no parameter {} (given with --define or the job's defines)",
                unused
                    .iter()
                    .map(|k| format!("${k}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    }
    cx.index_ids(&root)?;
    cx.preload_meshes(&root);
    let mut sensor_seen = false;
    for c in &root.children {
        match c.tag.as_str() {
            "integrator" => cx.integrator(c)?,
            "sensor" => {
                if sensor_seen {
                    cx.warn(c, "more than one <sensor>: the first is rendered");
                    continue;
                }
                sensor_seen = true;
                cx.sensor(c)?;
            }
            "shape" => cx.shape(c, &crate::geometry::Mat4::IDENTITY)?,
            "emitter" => cx.emitter(c)?,
            // Instantiated where they are referenced (a top-level one unreferenced is unused).
            "bsdf" | "texture" | "spectrum" | "default" | "alias" | "rfilter" | "film"
            | "sampler" => {}
            "path" => cx.warn(
                c,
                "<path> search paths are not supported; files are looked up beside the scene file",
            ),
            "medium" | "phase" | "volume" => cx.refuse(
                c,
                format!("<{}>: participating media are not supported", c.tag),
            ),
            other => return Err(cx.err(c, format!("unknown element <{other}> in <scene>"))),
        }
    }
    if !sensor_seen {
        return Err(cx.err(&root, "the scene has no <sensor>"));
    }
    if !cx.refused.is_empty() {
        let n = cx.refused.len();
        let list = cx
            .refused
            .iter()
            .map(|(line, m)| format!("line {line}: {m}"))
            .collect::<Vec<_>>()
            .join("; ");
        return Err(SceneError::new(
            &file,
            format!("line {}", cx.refused[0].0),
            format!(
                "the scene cannot be rendered as the file means it ({n} reason{}): {list}",
                if n == 1 { "" } else { "s" }
            ),
        ));
    }
    let Ctx { mut b, warn, .. } = cx;
    warn.flush(&mut b);
    Ok(b)
}

/// The importer's state.
struct Ctx {
    file: PathBuf,
    b: SceneBuilder,
    warn: Warnings,
    /// What the scene needs and we cannot render: (line, reason), reported together.
    refused: Vec<(u32, String)>,
    /// Parameter values: given from outside, then the file's `<default>`s.
    table: HashMap<String, String>,
    /// The parameters given from outside, each of which the file must use.
    given: Vec<String>,
    used: HashSet<String>,
    /// Objects by id (nodes of the expanded tree, cloned), aliases included.
    ids: HashMap<String, Node>,
    /// Builder materials of bsdfs with an id, made once.
    materials: HashMap<String, u32>,
    bitmaps: Bitmaps,
    meshes: HashMap<PathBuf, Result<MeshData, MeshError>>,
    default_bsdf: Option<u32>,
    black_bsdf: Option<u32>,
    /// An environment emitter was read (a scene has at most one).
    environment_seen: bool,
}

impl Ctx {
    fn err(&self, n: &Node, m: impl Into<String>) -> SceneError {
        xml::error_at(&self.file, n, m)
    }

    fn warn(&mut self, n: &Node, m: impl Into<String>) {
        let place = format!("{}:{}", self.file.display(), n.line);
        self.warn.add(place, m);
    }

    /// Records a construct the scene needs and we cannot render (the load fails at the end,
    /// naming all of them).
    fn refuse(&mut self, n: &Node, m: impl Into<String>) {
        self.refused.push((n.line, m.into()));
    }

    /// The tree with includes spliced in, `<default>`s applied in document order and `$name`
    /// substituted in every attribute; an element nested deeper than the XML limit, counting
    /// includes, is refused.
    fn expand(&mut self, node: Node, file: &Path, depth: usize) -> R<Node> {
        self.expand_at(node, file, depth, 0)
    }

    /// `expand` of an element `level` elements below the root, counting includes.
    fn expand_at(&mut self, mut node: Node, file: &Path, depth: usize, level: usize) -> R<Node> {
        if level >= MAX_XML_DEPTH {
            return Err(SceneError::new(
                file,
                format!("line {}", node.line),
                format!(
                    "<{}> is nested more than {MAX_XML_DEPTH} elements deep (counting includes)",
                    node.tag
                ),
            ));
        }
        for (_, v) in &mut node.attrs {
            *v = self.substitute(v, node.line, file)?;
        }
        if node.tag == "default" {
            let (Some(n), Some(v)) = (node.attr("name"), node.attr("value")) else {
                return Err(SceneError::new(
                    file,
                    format!("line {}", node.line),
                    "<default> needs name and value",
                ));
            };
            if !self.table.contains_key(n) {
                self.table.insert(n.to_string(), v.to_string());
            }
            return Ok(node);
        }
        let children = std::mem::take(&mut node.children);
        for c in children {
            if c.tag != "include" {
                node.children
                    .push(self.expand_at(c, file, depth, level + 1)?);
                continue;
            }
            let line = c.line;
            let at = |m: String| SceneError::new(file, format!("line {line}"), m);
            if depth + 1 > MAX_INCLUDE_DEPTH {
                return Err(at(format!(
                    "<include> nested deeper than {MAX_INCLUDE_DEPTH} (a cycle?)"
                )));
            }
            let c = self.expand_at(c, file, depth, level + 1)?;
            let rel = c
                .attr("filename")
                .ok_or_else(|| at("<include> has no filename".into()))?;
            let inc = self
                .b
                .resolver()
                .resolve(rel, "include")
                .map_err(|e| at(format!("<include filename=\"{rel}\">: {}", e.message)))?;
            let text = inc
                .read_to_string()
                .map_err(|e| at(format!("<include filename=\"{rel}\">: cannot read: {e}")))?;
            let inc_path = inc.path().to_path_buf();
            let inc_root = parse_xml(&text, &inc_path)?;
            match inc_root.attr("version").map(major_version) {
                Some(Some(v)) if v >= 2 => {}
                Some(_) => {
                    return Err(at(format!(
                        "<include filename=\"{rel}\">: its version is not 2.x or 3.x"
                    )));
                }
                None => {
                    return Err(at(format!(
                        "<include filename=\"{rel}\">: its root element has no version"
                    )));
                }
            }
            // A scene's children take its place; another object is a child of the includer.
            let inc_level = if inc_root.tag == "scene" {
                level
            } else {
                level + 1
            };
            let inc_root = self.expand_at(inc_root, &inc_path, depth + 1, inc_level)?;
            if inc_root.tag == "scene" {
                node.children.extend(inc_root.children);
            } else {
                node.children.push(inc_root);
            }
        }
        Ok(node)
    }

    /// `text` with every `$name` replaced by its value (the longest name that matches first),
    /// `\$` kept as a literal `$`.
    fn substitute(&mut self, text: &str, line: u32, file: &Path) -> R<String> {
        if !text.contains('$') {
            return Ok(text.to_string());
        }
        let mut keys: Vec<String> = self.table.keys().cloned().collect();
        keys.sort_by_key(|k| std::cmp::Reverse(k.len()));
        let mut out = String::with_capacity(text.len());
        let mut rest = text;
        while let Some(i) = rest.find(['$', '\\']) {
            out.push_str(&rest[..i]);
            let after = &rest[i + 1..];
            if rest[i..].starts_with('\\') {
                if let Some(a) = after.strip_prefix('$') {
                    out.push('$');
                    rest = a;
                } else {
                    out.push('\\');
                    rest = after;
                }
                continue;
            }
            let Some(k) = keys.iter().find(|k| after.starts_with(k.as_str())) else {
                let name: String = after
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                return Err(SceneError::new(
                    file,
                    format!("line {line}"),
                    format!(
                        "undefined parameter ${name} (give it a <default> before its first use, \
                         or a value with --define)"
                    ),
                ));
            };
            out.push_str(&self.table[k.as_str()]);
            self.used.insert(k.clone());
            rest = &after[k.len()..];
        }
        out.push_str(rest);
        Ok(out)
    }

    /// Registers every object with an id, and every `<alias>`, anywhere in the tree.
    fn index_ids(&mut self, root: &Node) -> R<()> {
        let mut stack: Vec<&Node> = root.children.iter().collect();
        let mut aliases = Vec::new();
        while let Some(n) = stack.pop() {
            if n.tag == "alias" {
                aliases.push(n);
                continue;
            }
            if let Some(id) = n.attr("id")
                && n.tag != "ref"
                && self.ids.insert(id.to_string(), n.clone()).is_some()
            {
                return Err(self.err(n, format!("duplicate id \"{id}\"")));
            }
            stack.extend(n.children.iter());
        }
        aliases.sort_by_key(|n| n.line);
        for a in aliases {
            let (Some(id), Some(as_)) = (a.attr("id"), a.attr("as")) else {
                return Err(self.err(a, "<alias> needs id and as"));
            };
            let target = self
                .ids
                .get(id)
                .cloned()
                .ok_or_else(|| self.err(a, format!("<alias>: unknown id \"{id}\"")))?;
            if self.ids.insert(as_.to_string(), target).is_some() {
                return Err(self.err(a, format!("<alias>: id \"{as_}\" already exists")));
            }
        }
        Ok(())
    }

    /// The object `n` stands for: itself, or the object its `<ref id>` names.
    fn deref<'a>(&'a self, n: &'a Node) -> R<&'a Node> {
        if n.tag != "ref" {
            return Ok(n);
        }
        let id = n
            .attr("id")
            .ok_or_else(|| self.err(n, "<ref> without id"))?;
        self.ids
            .get(id)
            .ok_or_else(|| self.err(n, format!("<ref>: unknown id \"{id}\"")))
    }
}
