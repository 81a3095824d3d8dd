//! Mitsuba 0.5 scene importer (XML, read with `quick-xml`): the subset of the format that maps
//! onto our scene model (see `scenes/README.md`, "Importers").
//!
//! Conventions of Mitsuba 0.5 that matter here (Mitsuba 0.5 documentation and sources):
//! - `<matrix value="...">` is row-major; the steps of a `<transform>` apply in document order
//!   (each left-multiplies the transform so far).
//! - Camera space: +z forward, +y up, and raster x runs toward -x (`lookat` builds the columns
//!   `left = up x dir`, `up`, `dir`). Our raster x runs along forward x up; a camera-to-world
//!   transform of the other handedness is mirrored with [`Camera::with_flip_x`].
//! - `fov` spans `fovAxis` (default `x`).
//! - `maxDepth` counts path vertices after the camera: 1 shows directly visible emitters only, 2
//!   is direct lighting; our `max_depth` = Mitsuba's `maxDepth` - 1; -1 (unlimited) becomes 64.
//! - BSDFs are one-sided (black from behind) unless wrapped in `twosided`; dielectrics see both
//!   sides. Area emitters emit on the side of the (shading) normal.
//! - OBJ texture coordinates are flipped vertically by default (`flipTexCoords`) and bitmaps are
//!   looked up with v = 0 at the image's top row: together that is the usual OBJ convention,
//!   which is ours (v = 0 at the bottom). Built-in shapes and PLY uvs are in Mitsuba's own
//!   convention and get v -> 1 - v.

use super::json::resolve_in_folder;
use super::mesh::{load_obj, load_ply};
use super::pbrt::{COPPER_ETA, COPPER_K, Warnings, uniform_scale};
use super::{MeshData, Scene, SceneBuilder, SceneError};
use crate::camera::Camera;
use crate::geometry::{Frame, Mat4, Rgb, Transform, Vec2, Vec3};
use crate::material::microfacet::MIN_ALPHA;
use crate::material::texture::srgb_to_linear;
use crate::material::{Bitmap, Material, MaterialKind, Texture};
use quick_xml::XmlVersion;
use quick_xml::events::{BytesStart, Event};
use rayon::prelude::*;
use std::cell::Cell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

type R<T> = Result<T, SceneError>;

/// Our depth limit for Mitsuba's `maxDepth = -1` (unlimited); Russian roulette ends most paths
/// long before.
pub const UNLIMITED_DEPTH: u32 = 64;

/// Triangles of the fan a `disk` is tessellated into.
const DISK_SEGMENTS: usize = 256;

// ------------------------------------------------------------------------------------------
// XML tree with line numbers.

#[derive(Debug)]
struct Node {
    tag: String,
    attrs: Vec<(String, String)>,
    children: Vec<Node>,
    line: u32,
}

impl Node {
    fn attr(&self, k: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(a, _)| a == k)
            .map(|(_, v)| v.as_str())
    }

    /// `<tag type="x">` for messages.
    fn label(&self) -> String {
        match (self.attr("type"), self.attr("name")) {
            (Some(t), _) => format!("<{} type=\"{t}\">", self.tag),
            (None, Some(n)) => format!("<{} name=\"{n}\">", self.tag),
            _ => format!("<{}>", self.tag),
        }
    }
}

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

fn parse_xml(text: &str, file: &Path) -> R<Node> {
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

/// Replaces `$name` in attribute values with `<default name= value=>` values.
fn substitute(node: &mut Node, defaults: &HashMap<String, String>, file: &Path) -> R<()> {
    for (_, v) in &mut node.attrs {
        if v.contains('$') {
            let mut out = String::new();
            let mut rest = v.as_str();
            while let Some(i) = rest.find('$') {
                out.push_str(&rest[..i]);
                let after = &rest[i + 1..];
                let n = after
                    .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                    .unwrap_or(after.len());
                let key = &after[..n];
                let val = defaults.get(key).ok_or_else(|| {
                    SceneError::new(
                        file,
                        format!("line {}", node.line),
                        format!("undefined parameter ${key}"),
                    )
                })?;
                out.push_str(val);
                rest = &after[n..];
            }
            out.push_str(rest);
            *v = out;
        }
    }
    for c in &mut node.children {
        substitute(c, defaults, file)?;
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------
// Properties of an object element.

/// The children of an object element, with a flag per child telling whether anything read it.
struct Props<'n> {
    node: &'n Node,
    used: Vec<Cell<bool>>,
}

impl<'n> Props<'n> {
    fn new(node: &'n Node) -> Self {
        Props {
            node,
            used: node.children.iter().map(|_| Cell::new(false)).collect(),
        }
    }

    /// The last child named `name` (any tag).
    fn get(&self, name: &str) -> Option<&'n Node> {
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

    fn has(&self, name: &str) -> bool {
        self.node
            .children
            .iter()
            .any(|c| c.attr("name") == Some(name))
    }

    /// Children with tag `tag` and no `name` attribute (nested objects).
    fn objects(&self, tag: &str) -> Vec<&'n Node> {
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
    fn any_with_tag(&self, tag: &str) -> Vec<&'n Node> {
        let mut out = Vec::new();
        for (i, c) in self.node.children.iter().enumerate() {
            if c.tag == tag {
                self.used[i].set(true);
                out.push(c);
            }
        }
        out
    }

    fn consume(&self, name: &str) {
        let _ = self.get(name);
    }

    fn unused(&self) -> Vec<&'n Node> {
        self.node
            .children
            .iter()
            .zip(&self.used)
            .filter(|(_, u)| !u.get())
            .map(|(c, _)| c)
            .collect()
    }
}

// ------------------------------------------------------------------------------------------
// The loader.

/// What an `id` names.
enum Obj {
    Bsdf { mat: Material, index: Option<u32> },
    Texture(Texture),
    Other(String),
}

struct Ctx {
    file: PathBuf,
    b: SceneBuilder,
    warn: Warnings,
    ids: HashMap<String, Obj>,
    bitmaps: HashMap<(PathBuf, bool), Arc<Bitmap>>,
    meshes: HashMap<PathBuf, Result<MeshData, String>>,
    default_bsdf: Option<u32>,
}

/// Loads a Mitsuba 0.5 XML file.
pub fn load(path: &Path) -> Result<Scene, SceneError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| SceneError::new(path, "file", format!("cannot read: {e}")))?;
    parse(&text, path)?.build()
}

/// Parses Mitsuba 0.5 XML text; `file` names it in errors and anchors relative paths.
pub fn parse(text: &str, file: &Path) -> Result<SceneBuilder, SceneError> {
    let mut root = parse_xml(text, file)?;
    if root.tag != "scene" {
        return Err(SceneError::new(
            file,
            format!("line {}", root.line),
            format!("the root element is <{}>, expected <scene>", root.tag),
        ));
    }
    let mut defaults = HashMap::new();
    for c in &root.children {
        if c.tag == "default"
            && let (Some(n), Some(v)) = (c.attr("name"), c.attr("value"))
        {
            defaults.insert(n.to_string(), v.to_string());
        }
    }
    substitute(&mut root, &defaults, file)?;
    let mut cx = Ctx {
        file: file.to_path_buf(),
        b: SceneBuilder::new(file),
        warn: Warnings::default(),
        ids: HashMap::new(),
        bitmaps: HashMap::new(),
        meshes: HashMap::new(),
        default_bsdf: None,
    };
    if let Some(v) = root.attr("version")
        && !v.starts_with("0.")
    {
        cx.warn(
            &root,
            format!("scene version {v}: this importer reads Mitsuba 0.5 files"),
        );
    }
    cx.preload_meshes(&root)?;
    let mut sensor_seen = false;
    for c in &root.children {
        match c.tag.as_str() {
            "integrator" => cx.integrator(c)?,
            "sensor" => {
                if sensor_seen {
                    cx.warn(c, "more than one <sensor>: the first is used");
                    continue;
                }
                sensor_seen = true;
                cx.sensor(c)?;
            }
            "bsdf" => {
                cx.bsdf(c)?;
                if c.attr("id").is_none() && !contains_id(c) {
                    cx.warn(c, "a top-level <bsdf> without id is never used");
                }
            }
            "texture" => {
                let t = cx.texture(c)?;
                match c.attr("id") {
                    Some(id) => cx.register(c, id, Obj::Texture(t))?,
                    None => cx.warn(c, "a top-level <texture> without id is never used"),
                }
            }
            "shape" => cx.shape(c)?,
            "emitter" => cx.emitter(c)?,
            "default" => {}
            "alias" => {
                let (Some(id), Some(as_)) = (c.attr("id"), c.attr("as")) else {
                    return Err(cx.err(c, "<alias> needs id and as"));
                };
                let o = match cx.ids.get(id) {
                    Some(Obj::Bsdf { mat, .. }) => Obj::Bsdf {
                        mat: mat.clone(),
                        index: None,
                    },
                    Some(Obj::Texture(t)) => Obj::Texture(t.clone()),
                    Some(Obj::Other(t)) => Obj::Other(t.clone()),
                    None => return Err(cx.err(c, format!("<alias>: unknown id \"{id}\""))),
                };
                cx.register(c, as_, o)?;
            }
            "medium" | "phase" | "subsurface" => {
                cx.warn(c, format!("<{}> (participating media, subsurface scattering) is not supported and was ignored", c.tag));
                if let Some(id) = c.attr("id") {
                    cx.register(c, id, Obj::Other(c.tag.clone()))?;
                }
            }
            "include" => return Err(cx.err(c, "<include> is not supported")),
            other => return Err(cx.err(c, format!("unknown element <{other}> in <scene>"))),
        }
    }
    if !sensor_seen {
        return Err(cx.err(&root, "the scene has no <sensor>"));
    }
    let Ctx { mut b, warn, .. } = cx;
    warn.flush(&mut b);
    Ok(b)
}

fn contains_id(n: &Node) -> bool {
    n.children
        .iter()
        .any(|c| c.attr("id").is_some() || contains_id(c))
}

/// Mitsuba's named indices of refraction (Mitsuba 0.5 documentation, table of IOR values).
fn named_ior(name: &str) -> Option<f32> {
    Some(match name.to_ascii_lowercase().as_str() {
        "vacuum" => 1.0,
        "helium" => 1.00004,
        "hydrogen" => 1.00013,
        "air" => 1.00028,
        "carbon dioxide" => 1.00045,
        "water" => 1.3330,
        "acetone" => 1.36,
        "ethanol" => 1.361,
        "carbon tetrachloride" => 1.461,
        "glycerol" => 1.4729,
        "benzene" => 1.501,
        "silicone oil" => 1.52045,
        "bromine" => 1.661,
        "water ice" => 1.31,
        "fused quartz" => 1.458,
        "pyrex" => 1.470,
        "acrylic glass" => 1.49,
        "polypropylene" => 1.49,
        "bk7" => 1.5046,
        "sodium chloride" => 1.544,
        "amber" => 1.55,
        "pet" => 1.5750,
        "diamond" => 2.419,
        _ => return None,
    })
}

/// RGB complex IORs of Mitsuba's named conductors, as Bitterli's scene exports give them
/// (veach-mis, staircase, veach-bidir); `none` is Mitsuba's ideal mirror.
fn named_conductor(name: &str) -> Option<(Rgb, Rgb)> {
    Some(match name {
        "Cu" => (Vec3::from_array(COPPER_ETA), Vec3::from_array(COPPER_K)),
        "Au" => (
            Vec3::new(0.143119, 0.374957, 1.44248),
            Vec3::new(3.98316, 2.38572, 1.60322),
        ),
        "Al" => (
            Vec3::new(1.65746, 0.880369, 0.521229),
            Vec3::new(9.22387, 6.26952, 4.837),
        ),
        "CuZn" => (
            Vec3::new(2.8656, 2.11918, 1.94008),
            Vec3::new(3.03233, 2.05611, 1.61629),
        ),
        "none" => (Vec3::ZERO, Vec3::ONE),
        _ => return None,
    })
}

fn split_numbers(s: &str) -> Result<Vec<f32>, String> {
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

impl Ctx {
    fn err(&self, n: &Node, m: impl Into<String>) -> SceneError {
        SceneError::new(&self.file, format!("line {}", n.line), m)
    }

    fn warn(&mut self, n: &Node, m: impl Into<String>) {
        let place = format!("{}:{}", self.file.display(), n.line);
        self.warn.add(place, m);
    }

    fn report_unused(&mut self, p: &Props, what: &str) {
        for c in p.unused() {
            let m = match c.attr("name") {
                Some(name) => format!(
                    "{what}: property \"{name}\" (<{}>) is not supported and was ignored",
                    c.tag
                ),
                None => format!(
                    "{what}: nested {} is not supported and was ignored",
                    c.label()
                ),
            };
            self.warn(c, m);
        }
    }

    fn register(&mut self, n: &Node, id: &str, o: Obj) -> R<()> {
        if self.ids.contains_key(id) {
            return Err(self.err(n, format!("duplicate id \"{id}\"")));
        }
        self.ids.insert(id.to_string(), o);
        Ok(())
    }

    // ---- typed values

    fn value_attr<'a>(&self, n: &'a Node) -> R<&'a str> {
        n.attr("value")
            .ok_or_else(|| self.err(n, format!("{} has no value", n.label())))
    }

    fn num_of(&self, n: &Node) -> R<f32> {
        match n.tag.as_str() {
            "float" | "integer" => {
                let v = self.value_attr(n)?;
                v.trim()
                    .parse::<f32>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.err(n, format!("{}: malformed number '{v}'", n.label())))
            }
            _ => Err(self.err(n, format!("{} should be a <float>", n.label()))),
        }
    }

    fn float(&self, p: &Props, name: &str, default: f32) -> R<f32> {
        match p.get(name) {
            Some(n) => self.num_of(n),
            None => Ok(default),
        }
    }

    fn int(&self, p: &Props, name: &str, default: i64) -> R<i64> {
        match p.get(name) {
            Some(n) if n.tag == "integer" => {
                let v = self.value_attr(n)?;
                v.trim()
                    .parse::<i64>()
                    .map_err(|_| self.err(n, format!("{}: malformed integer '{v}'", n.label())))
            }
            Some(n) => Err(self.err(n, format!("{} should be an <integer>", n.label()))),
            None => Ok(default),
        }
    }

    fn boolean(&self, p: &Props, name: &str, default: bool) -> R<bool> {
        match p.get(name) {
            Some(n) if n.tag == "boolean" => match self.value_attr(n)?.trim() {
                "true" => Ok(true),
                "false" => Ok(false),
                v => Err(self.err(
                    n,
                    format!("{}: expected true or false, got '{v}'", n.label()),
                )),
            },
            Some(n) => Err(self.err(n, format!("{} should be a <boolean>", n.label()))),
            None => Ok(default),
        }
    }

    fn string(&self, p: &Props, name: &str) -> R<Option<String>> {
        match p.get(name) {
            Some(n) if n.tag == "string" => Ok(Some(self.value_attr(n)?.to_string())),
            Some(n) => Err(self.err(n, format!("{} should be a <string>", n.label()))),
            None => Ok(None),
        }
    }

    /// A colour element: `rgb`, `srgb`, `spectrum` (uniform or flat), or a plain `float`.
    fn color_of(&self, n: &Node) -> R<Rgb> {
        let c = match n.tag.as_str() {
            "rgb" | "srgb" => {
                let v = self.value_attr(n)?;
                let c = if let Some(hex) = v.trim().strip_prefix('#') {
                    let byte = |i: usize| {
                        hex.get(i..i + 2)
                            .and_then(|h| u8::from_str_radix(h, 16).ok())
                            .map(|x| x as f32 / 255.0)
                    };
                    match (hex.len(), byte(0), byte(2), byte(4)) {
                        (6, Some(r), Some(g), Some(b)) => Vec3::new(r, g, b),
                        _ => {
                            return Err(
                                self.err(n, format!("{}: malformed colour '{v}'", n.label()))
                            );
                        }
                    }
                } else {
                    let v =
                        split_numbers(v).map_err(|m| self.err(n, format!("{}: {m}", n.label())))?;
                    match v.len() {
                        1 => Vec3::splat(v[0]),
                        3 => Vec3::new(v[0], v[1], v[2]),
                        k => {
                            return Err(self.err(
                                n,
                                format!("{}: expected 1 or 3 values, got {k}", n.label()),
                            ));
                        }
                    }
                };
                if n.tag == "srgb" {
                    Vec3::new(
                        srgb_to_linear(c.x),
                        srgb_to_linear(c.y),
                        srgb_to_linear(c.z),
                    )
                } else {
                    c
                }
            }
            "spectrum" => {
                if n.attr("filename").is_some() {
                    return Err(self.err(
                        n,
                        format!(
                            "{}: spectrum files are not supported; give an <rgb>",
                            n.label()
                        ),
                    ));
                }
                let v = self.value_attr(n)?;
                if v.contains(':') {
                    // wavelength:value pairs; only a flat spectrum has an exact RGB equivalent.
                    let mut vals = Vec::new();
                    for pair in v.split(',') {
                        let x = pair
                            .split(':')
                            .nth(1)
                            .and_then(|s| s.trim().parse::<f32>().ok())
                            .ok_or_else(|| {
                                self.err(n, format!("{}: malformed spectrum '{v}'", n.label()))
                            })?;
                        vals.push(x);
                    }
                    let first = vals[0];
                    if vals
                        .iter()
                        .any(|x| (x - first).abs() > 1e-6 * first.abs().max(1.0))
                    {
                        return Err(self.err(
                            n,
                            format!(
                                "{}: sampled spectra are not supported; give an <rgb>",
                                n.label()
                            ),
                        ));
                    }
                    Vec3::splat(first)
                } else {
                    let v =
                        split_numbers(v).map_err(|m| self.err(n, format!("{}: {m}", n.label())))?;
                    match v.len() {
                        1 => Vec3::splat(v[0]),
                        k => return Err(self.err(
                            n,
                            format!(
                                "{}: expected 1 value or wavelength:value pairs, got {k} values",
                                n.label()
                            ),
                        )),
                    }
                }
            }
            "float" | "integer" => Vec3::splat(self.num_of(n)?),
            "blackbody" => {
                return Err(self.err(
                    n,
                    format!(
                        "{}: blackbody spectra are not supported; give an <rgb>",
                        n.label()
                    ),
                ));
            }
            _ => {
                return Err(self.err(
                    n,
                    format!(
                        "{} should be a colour (<rgb>, <srgb>, <spectrum>)",
                        n.label()
                    ),
                ));
            }
        };
        if !c.is_finite() || c.min_element() < 0.0 {
            return Err(self.err(
                n,
                format!("{}: must be finite and >= 0, got {c:?}", n.label()),
            ));
        }
        Ok(c)
    }

    /// A colour property that may be a texture (nested, or `<ref name= id=>`).
    fn spectrum_tex(&mut self, p: &Props, name: &str, default: Rgb) -> R<Texture> {
        let Some(n) = p.get(name) else {
            return Ok(Texture::Constant(default));
        };
        match n.tag.as_str() {
            "texture" => self.texture(n),
            "ref" => {
                let id = n
                    .attr("id")
                    .ok_or_else(|| self.err(n, "<ref> without id"))?;
                match self.ids.get(id) {
                    Some(Obj::Texture(t)) => Ok(t.clone()),
                    Some(_) => Err(self.err(n, format!("\"{id}\" is not a texture"))),
                    None => Err(self.err(n, format!("unknown id \"{id}\""))),
                }
            }
            _ => Ok(Texture::Constant(self.color_of(n)?)),
        }
    }

    /// A colour property our models take as a constant; a texture becomes its average.
    fn spectrum_const(&mut self, p: &Props, name: &str, default: Rgb, what: &str) -> R<Rgb> {
        let n = p.get(name);
        let t = self.spectrum_tex(p, name, default)?;
        if let (Texture::Bitmap { .. }, Some(n)) = (&t, n) {
            self.warn(
                n,
                format!("{what}: a texture for \"{name}\" is not supported; its average is used"),
            );
        }
        Ok(t.average())
    }

    /// An IOR: a number or one of Mitsuba's named materials.
    fn ior(&self, p: &Props, name: &str, default: f32) -> R<f32> {
        match p.get(name) {
            None => Ok(default),
            Some(n) if n.tag == "string" => {
                let v = self.value_attr(n)?;
                named_ior(v).ok_or_else(|| self.err(n, format!("unknown IOR name \"{v}\"")))
            }
            Some(n) => {
                let v = self.num_of(n)?;
                if !(v > 0.0) {
                    return Err(self.err(n, format!("{}: must be > 0", n.label())));
                }
                Ok(v)
            }
        }
    }

    fn point_of(&self, n: &Node) -> R<Vec3> {
        if let Some(v) = n.attr("value") {
            let v = split_numbers(v).map_err(|m| self.err(n, format!("{}: {m}", n.label())))?;
            return match v.len() {
                3 => Ok(Vec3::new(v[0], v[1], v[2])),
                1 => Ok(Vec3::splat(v[0])),
                k => Err(self.err(n, format!("{}: expected 3 values, got {k}", n.label()))),
            };
        }
        let c = |k: &str, d: f32| -> R<f32> {
            match n.attr(k) {
                None => Ok(d),
                Some(s) => s
                    .trim()
                    .parse::<f32>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.err(n, format!("{}: malformed {k} '{s}'", n.label()))),
            }
        };
        Ok(Vec3::new(c("x", 0.0)?, c("y", 0.0)?, c("z", 0.0)?))
    }

    fn vec_attr(&self, n: &Node, k: &str) -> R<Option<Vec3>> {
        match n.attr(k) {
            None => Ok(None),
            Some(s) => {
                let v =
                    split_numbers(s).map_err(|m| self.err(n, format!("<{}> {k}: {m}", n.tag)))?;
                if v.len() != 3 {
                    return Err(self.err(n, format!("<{}> {k}: expected 3 values", n.tag)));
                }
                Ok(Some(Vec3::new(v[0], v[1], v[2])))
            }
        }
    }

    /// A `<transform>`: its steps in document order, each applied after the previous.
    fn transform_of(&self, n: &Node) -> R<Mat4> {
        if n.tag != "transform" {
            return Err(self.err(n, format!("{} should be a <transform>", n.label())));
        }
        let mut m = Mat4::IDENTITY;
        for s in &n.children {
            let step = match s.tag.as_str() {
                "translate" => Mat4::from_translation(self.point_of(s)?),
                "scale" => {
                    let v = match s.attr("value") {
                        Some(_) => self.point_of(s)?,
                        None => {
                            let c = |k: &str| -> R<f32> {
                                s.attr(k).map_or(Ok(1.0), |v| {
                                    v.trim().parse::<f32>().map_err(|_| {
                                        self.err(s, format!("<scale> {k}: malformed number '{v}'"))
                                    })
                                })
                            };
                            Vec3::new(c("x")?, c("y")?, c("z")?)
                        }
                    };
                    Mat4::from_scale(v)
                }
                "rotate" => {
                    let axis = self.point_of(s)?.normalize_or_zero();
                    let angle = s
                        .attr("angle")
                        .ok_or_else(|| self.err(s, "<rotate> has no angle"))?
                        .trim()
                        .parse::<f32>()
                        .map_err(|_| self.err(s, "<rotate>: malformed angle"))?;
                    if axis == Vec3::ZERO {
                        return Err(self.err(s, "<rotate>: the axis is zero"));
                    }
                    Mat4::from_axis_angle(axis, angle.to_radians())
                }
                "matrix" => {
                    let v = split_numbers(self.value_attr(s)?)
                        .map_err(|m| self.err(s, format!("<matrix>: {m}")))?;
                    if v.len() != 16 {
                        return Err(
                            self.err(s, format!("<matrix> needs 16 values, got {}", v.len()))
                        );
                    }
                    let mut a = [0f32; 16];
                    a.copy_from_slice(&v);
                    // Row-major in the file.
                    Mat4::from_cols_array(&a).transpose()
                }
                "lookat" => {
                    let origin = self
                        .vec_attr(s, "origin")?
                        .ok_or_else(|| self.err(s, "<lookat> has no origin"))?;
                    let target = self
                        .vec_attr(s, "target")?
                        .ok_or_else(|| self.err(s, "<lookat> has no target"))?;
                    let dir = (target - origin).normalize_or_zero();
                    if dir == Vec3::ZERO {
                        return Err(self.err(s, "<lookat>: origin equals target"));
                    }
                    // Mitsuba picks some perpendicular up when none is given.
                    let up = self
                        .vec_attr(s, "up")?
                        .unwrap_or_else(|| Frame::from_normal(dir).s);
                    let left = up.cross(dir).normalize_or_zero();
                    if left == Vec3::ZERO {
                        return Err(self.err(s, "<lookat>: up is parallel to the view direction"));
                    }
                    let new_up = dir.cross(left);
                    Mat4::from_cols(
                        left.extend(0.0),
                        new_up.extend(0.0),
                        dir.extend(0.0),
                        origin.extend(1.0),
                    )
                }
                other => return Err(self.err(s, format!("unknown transform step <{other}>"))),
            };
            m = step * m;
        }
        if !m.is_finite() {
            return Err(self.err(n, "the transform is not finite"));
        }
        Ok(m)
    }

    fn to_world(&self, p: &Props) -> R<Mat4> {
        match p.get("toWorld") {
            Some(n) => self.transform_of(n),
            None => Ok(Mat4::IDENTITY),
        }
    }

    // ---- integrator, sensor

    fn integrator(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        if matches!(ty, "adaptive" | "irrcache" | "multichannel") {
            self.warn(
                n,
                format!("integrator \"{ty}\" is not supported; its nested integrator is used"),
            );
            let inner = p.objects("integrator");
            return match inner.first() {
                Some(i) => self.integrator(i),
                None => Err(self.err(n, format!("integrator \"{ty}\" has no nested integrator"))),
            };
        }
        let depth = self.int(&p, "maxDepth", -1)?;
        let ours = match depth {
            -1 => {
                self.warn(
                    n,
                    format!("maxDepth -1 (unlimited) is rendered with max depth {UNLIMITED_DEPTH}"),
                );
                UNLIMITED_DEPTH
            }
            d if d >= 1 => {
                // Mitsuba counts the emitter hit as one more vertex: maxDepth 2 is direct light.
                if d == 1 {
                    self.warn(n, "maxDepth 1 shows only directly visible emitters in Mitsuba (our max depth 0)");
                }
                (d - 1).min(u32::MAX as i64) as u32
            }
            d => {
                return Err(self.err(
                    n,
                    format!("maxDepth {d}: Mitsuba renders nothing; use -1 or >= 1"),
                ));
            }
        };
        self.b.defaults.max_depth = Some(ours);
        match ty {
            "path" | "volpath" | "volpath_simple" | "bdpt" | "pssmlt" | "mlt" | "erpt" | "ptracer" | "sppm" | "ppm" => {
                if ty != "path" {
                    self.warn(n, format!("integrator \"{ty}\" rendered with our path tracer (the same expected image)"));
                }
            }
            other => self.warn(
                n,
                format!("integrator \"{other}\" is not supported; our path tracer renders full global illumination"),
            ),
        }
        // Russian roulette does not change the expected image. `strictNormals` stops paths
        // where geometric and shading normals disagree; our BSDFs already return nothing there.
        p.consume("rrDepth");
        p.consume("strictNormals");
        if self.boolean(&p, "hideEmitters", false)? {
            self.warn(
                n,
                "hideEmitters is not supported; directly visible emitters are shown",
            );
        }
        self.report_unused(&p, &format!("integrator \"{ty}\""));
        Ok(())
    }

    fn sensor(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        match ty {
            "perspective" => {}
            "thinlens" => {
                self.warn(
                    n,
                    "sensor \"thinlens\": depth of field is not supported; pinhole used",
                );
                p.consume("apertureRadius");
                p.consume("focusDistance");
            }
            other => {
                return Err(self.err(
                    n,
                    format!("sensor \"{other}\" is not supported (only \"perspective\")"),
                ));
            }
        }
        let c2w = self.to_world(&p)?;
        // Film.
        let (mut w, mut h) = (768u32, 576u32);
        if let Some(f) = p.objects("film").first() {
            let fp = Props::new(f);
            let fw = self.int(&fp, "width", 768)?;
            let fh = self.int(&fp, "height", 576)?;
            if !(1..=65536).contains(&fw) || !(1..=65536).contains(&fh) {
                return Err(self.err(f, format!("film size must be 1..65536, got {fw}x{fh}")));
            }
            (w, h) = (fw as u32, fh as u32);
            match fp.any_with_tag("rfilter").first() {
                Some(r) if r.attr("type") == Some("box") => {}
                Some(r) => {
                    let t = r.attr("type").unwrap_or("?");
                    self.warn(r, format!("rfilter \"{t}\" is not supported; box filter used"));
                }
                None => self.warn(f, "Mitsuba's default gaussian reconstruction filter is not supported; box filter used"),
            }
            for k in ["cropOffsetX", "cropOffsetY", "cropWidth", "cropHeight"] {
                if fp.has(k) {
                    fp.consume(k);
                    self.warn(
                        f,
                        "film crop window is not supported; the whole image is rendered",
                    );
                }
            }
            // Output format settings do not change the rendered radiance.
            for k in [
                "fileFormat",
                "pixelFormat",
                "componentFormat",
                "gamma",
                "banner",
                "attachLog",
                "highQualityEdges",
                "label",
                "tonemapMethod",
                "exposure",
                "key",
                "burn",
                "channelNames",
            ] {
                fp.consume(k);
            }
            self.report_unused(&fp, &format!("film \"{}\"", f.attr("type").unwrap_or("?")));
        }
        if let Some(s) = p.objects("sampler").first() {
            let sp = Props::new(s);
            let spp = self.int(&sp, "sampleCount", 4)?;
            if spp < 1 {
                return Err(self.err(s, format!("sampleCount must be >= 1, got {spp}")));
            }
            self.b.defaults.spp = Some(spp.min(u32::MAX as i64) as u32);
            // Sampler type, dimension and scramble settings do not change the expected image.
            sp.consume("dimension");
            sp.consume("scramble");
            self.report_unused(
                &sp,
                &format!("sampler \"{}\"", s.attr("type").unwrap_or("?")),
            );
        }
        // Field of view along fovAxis, or from a 35 mm-equivalent focal length (on the diagonal
        // of the 36 x 24 mm frame, as Mitsuba does).
        let axis = self.string(&p, "fovAxis")?.unwrap_or_else(|| "x".into());
        let (fov, axis) = match p.get("fov") {
            Some(f) => (self.num_of(f)?, axis),
            None => {
                let fl = self
                    .string(&p, "focalLength")?
                    .unwrap_or_else(|| "50mm".into());
                let mm = fl
                    .trim()
                    .trim_end_matches("mm")
                    .trim()
                    .parse::<f32>()
                    .ok()
                    .filter(|v| *v > 0.0)
                    .ok_or_else(|| self.err(n, format!("malformed focalLength '{fl}'")))?;
                let diag = (36.0f32 * 36.0 + 24.0 * 24.0).sqrt();
                (
                    (2.0 * (diag / (2.0 * mm)).atan()).to_degrees(),
                    "diagonal".into(),
                )
            }
        };
        if !(fov > 0.0 && fov < 180.0) {
            return Err(self.err(n, format!("fov must be in (0, 180) degrees, got {fov}")));
        }
        let (wf, hf) = (w as f32, h as f32);
        let t = (0.5 * fov.to_radians()).tan();
        // tan(vfov / 2) from tan(fov / 2) on the given axis.
        let tan_v = match axis.as_str() {
            "x" => t * hf / wf,
            "y" => t,
            "diagonal" => t * hf / (wf * wf + hf * hf).sqrt(),
            "smaller" => {
                if w < h {
                    t * hf / wf
                } else {
                    t
                }
            }
            "larger" => {
                if w > h {
                    t * hf / wf
                } else {
                    t
                }
            }
            other => return Err(self.err(n, format!("unknown fovAxis \"{other}\""))),
        };
        let vfov = 2.0 * tan_v.atan().to_degrees();
        for k in ["nearClip", "farClip", "shutterOpen", "shutterClose"] {
            p.consume(k);
        }
        self.report_unused(&p, &format!("sensor \"{ty}\""));
        let c2w =
            Transform::new(c2w).ok_or_else(|| self.err(n, "the sensor transform is singular"))?;
        let position = c2w.point(Vec3::ZERO);
        let forward = c2w.vector(Vec3::Z).normalize_or_zero();
        let up = c2w.vector(Vec3::Y);
        let cam = Camera::new(position, position + forward, up, vfov, w, h)
            .map_err(|m| self.err(n, format!("sensor: {m}")))?;
        // Mitsuba's raster x runs along camera -x.
        let image_right = -c2w.vector(Vec3::X);
        let flip = image_right.dot(cam.right()) < 0.0;
        self.b.set_camera(cam.with_flip_x(flip));
        Ok(())
    }

    // ---- textures

    fn bitmap(&mut self, n: &Node, rel: &str, srgb: bool) -> R<Arc<Bitmap>> {
        let path = resolve_in_folder(&self.file, rel, &format!("line {}", n.line))?;
        let key = (path.clone(), srgb);
        if let Some(b) = self.bitmaps.get(&key) {
            return Ok(b.clone());
        }
        let bm = Arc::new(Bitmap::load_with(&path, srgb).map_err(|e| self.err(n, e))?);
        self.bitmaps.insert(key, bm.clone());
        Ok(bm)
    }

    fn texture(&mut self, n: &Node) -> R<Texture> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let what = format!("texture \"{ty}\"");
        let t = match ty {
            "bitmap" => {
                let file = self
                    .string(&p, "filename")?
                    .ok_or_else(|| self.err(n, "bitmap texture has no filename"))?;
                // gamma: -1 (default) is the file's own curve: sRGB for 8-bit images; 1 is linear.
                let gamma = self.float(&p, "gamma", -1.0)?;
                let srgb = if gamma == -1.0 || (gamma - 2.2).abs() < 0.25 {
                    if gamma != -1.0 {
                        self.warn(n, format!("{what}: gamma {gamma} decoded as sRGB"));
                    }
                    true
                } else if gamma == 1.0 {
                    false
                } else {
                    return Err(self.err(
                        n,
                        format!("{what}: gamma {gamma} is not supported (only sRGB or 1)"),
                    ));
                };
                let image = self.bitmap(n, &file, srgb)?;
                let us = self.float(&p, "uscale", 1.0)?;
                let vs = self.float(&p, "vscale", 1.0)?;
                let uo = self.float(&p, "uoffset", 0.0)?;
                let vo = self.float(&p, "voffset", 0.0)?;
                if us != 1.0 || vs != 1.0 || uo != 0.0 || vo != 0.0 {
                    self.warn(
                        n,
                        format!("{what}: uv scale/offset is not supported; plain uv used"),
                    );
                }
                for k in ["wrapMode", "wrapModeU", "wrapModeV"] {
                    if let Some(w) = self.string(&p, k)?
                        && w != "repeat"
                    {
                        self.warn(
                            n,
                            format!("{what}: {k} \"{w}\" is not supported; repeat used"),
                        );
                    }
                }
                if let Some(c) = self.string(&p, "channel")? {
                    self.warn(
                        n,
                        format!("{what}: channel \"{c}\" is not supported; RGB used"),
                    );
                }
                // Filtering does not change the expected value at a point.
                for k in ["filterType", "maxAnisotropy", "cache"] {
                    p.consume(k);
                }
                Texture::Bitmap {
                    image,
                    scale: Rgb::ONE,
                }
            }
            "scale" => {
                let s = match p.get("scale") {
                    Some(c) => self.color_of(c)?,
                    None => Rgb::ONE,
                };
                let inner = p.objects("texture");
                let inner_t = match inner.first() {
                    Some(i) => self.texture(i)?,
                    None => self.spectrum_tex(&p, "texture", Rgb::ONE)?,
                };
                match inner_t {
                    Texture::Constant(c) => Texture::Constant(c * s),
                    Texture::Bitmap { image, scale } => Texture::Bitmap {
                        image,
                        scale: scale * s,
                    },
                }
            }
            other => {
                // checkerboard, gridtexture, vertexcolors, wireframe, curvature, ...
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                self.warn(
                    n,
                    format!("texture \"{other}\" is not supported: became constant 0.5"),
                );
                Texture::Constant(Rgb::splat(0.5))
            }
        };
        self.report_unused(&p, &what);
        Ok(t)
    }

    // ---- BSDFs

    /// Translates a `<bsdf>` element, registering its id and the ids nested in it.
    fn bsdf(&mut self, n: &Node) -> R<Material> {
        let m = self.bsdf_inner(n)?;
        if let Some(id) = n.attr("id") {
            self.register(
                n,
                id,
                Obj::Bsdf {
                    mat: m.clone(),
                    index: None,
                },
            )?;
        }
        Ok(m)
    }

    /// The material of a nested `<bsdf>` or `<ref>` child.
    fn child_bsdf(&mut self, n: &Node, p: &Props) -> R<Option<Material>> {
        for c in &n.children {
            let named = c.attr("name").is_some();
            if c.tag == "bsdf" && !named {
                p.objects("bsdf");
                return Ok(Some(self.bsdf(c)?));
            }
            if c.tag == "ref" && !named {
                p.objects("ref");
                let id = c
                    .attr("id")
                    .ok_or_else(|| self.err(c, "<ref> without id"))?;
                return match self.ids.get(id) {
                    Some(Obj::Bsdf { mat, .. }) => Ok(Some(mat.clone())),
                    Some(_) => Err(self.err(c, format!("\"{id}\" is not a bsdf"))),
                    None => Err(self.err(c, format!("unknown id \"{id}\""))),
                };
            }
        }
        Ok(None)
    }

    fn alpha(&mut self, n: &Node, p: &Props, what: &str) -> R<(f32, f32)> {
        let dist = self
            .string(p, "distribution")?
            .unwrap_or_else(|| "beckmann".into());
        match dist.as_str() {
            "ggx" => {}
            "beckmann" => self.warn(n, "beckmann approximated by ggx (same alpha)"),
            "phong" => self.warn(n, "phong microfacet distribution approximated by ggx (same alpha)"),
            "as" => self.warn(n, "Ashikhmin-Shirley microfacet distribution approximated by anisotropic ggx (same alphas)"),
            other => return Err(self.err(n, format!("{what}: unknown distribution \"{other}\""))),
        }
        let a = self.float(p, "alpha", 0.1)?;
        let au = self.float(p, "alphaU", a)?;
        let av = self.float(p, "alphaV", a)?;
        if !(au >= 0.0 && av >= 0.0) {
            return Err(self.err(n, format!("{what}: alpha must be >= 0")));
        }
        if au < MIN_ALPHA || av < MIN_ALPHA {
            self.warn(
                n,
                format!("{what}: alpha below {MIN_ALPHA} is traced as GGX alpha {MIN_ALPHA}"),
            );
        }
        p.consume("sampleVisible");
        Ok((au.max(MIN_ALPHA), av.max(MIN_ALPHA)))
    }

    /// Conductor eta and k, relative to the exterior IOR `extEta`.
    fn conductor_ior(&mut self, n: &Node, p: &Props, what: &str) -> R<(Rgb, Rgb)> {
        let (mut eta, mut k) = (Vec3::from_array(COPPER_ETA), Vec3::from_array(COPPER_K));
        if let Some(name) = self.string(p, "material")? {
            (eta, k) = named_conductor(&name).ok_or_else(|| {
                self.err(n, format!("{what}: conductor material \"{name}\" is not known here (Cu, Au, Al, CuZn, none); give eta and k"))
            })?;
        }
        if let Some(e) = p.get("eta") {
            eta = self.color_of(e)?;
        }
        if let Some(e) = p.get("k") {
            k = self.color_of(e)?;
        }
        let ext = self.ior(p, "extEta", 1.00028)?;
        Ok((eta / ext, k / ext))
    }

    fn bsdf_inner(&mut self, n: &Node) -> R<Material> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let name = n
            .attr("id")
            .map_or_else(|| format!("{ty} (line {})", n.line), str::to_string);
        let what = format!("bsdf \"{ty}\"");
        let one_sided = |kind| Material::new(name.clone(), kind, false);
        let m = match ty {
            "twosided" => {
                let inner: Vec<&Node> = n
                    .children
                    .iter()
                    .filter(|c| c.tag == "bsdf" || c.tag == "ref")
                    .collect();
                if inner.len() > 1 {
                    self.warn(n, "twosided with a different back-side bsdf is not supported; the front bsdf is used on both sides");
                }
                p.any_with_tag("bsdf");
                p.any_with_tag("ref");
                let Some(first) = inner.first() else {
                    return Err(self.err(n, "twosided has no nested bsdf"));
                };
                let mut m = if first.tag == "bsdf" {
                    self.bsdf(first)?
                } else {
                    let id = first
                        .attr("id")
                        .ok_or_else(|| self.err(first, "<ref> without id"))?;
                    match self.ids.get(id) {
                        Some(Obj::Bsdf { mat, .. }) => mat.clone(),
                        _ => return Err(self.err(first, format!("unknown bsdf id \"{id}\""))),
                    }
                };
                for extra in inner.iter().skip(1) {
                    if extra.tag == "bsdf" {
                        self.bsdf(extra)?;
                    }
                }
                m.name = name.clone();
                m.two_sided = true;
                m
            }
            "diffuse" | "roughdiffuse" => {
                if ty == "roughdiffuse" {
                    self.warn(
                        n,
                        "roughdiffuse (Oren-Nayar) approximated by a Lambertian diffuse bsdf",
                    );
                    p.consume("alpha");
                    p.consume("useFastApprox");
                }
                one_sided(MaterialKind::Lambert {
                    albedo: self.spectrum_tex(&p, "reflectance", Rgb::splat(0.5))?,
                })
            }
            "dielectric" | "roughdielectric" => {
                if ty == "roughdielectric" {
                    self.warn(n, "roughdielectric approximated by a smooth dielectric");
                    let _ = self.alpha(n, &p, &what)?;
                }
                let int = self.ior(&p, "intIOR", 1.5046)?;
                let ext = self.ior(&p, "extIOR", 1.00028)?;
                let reflectance =
                    self.spectrum_const(&p, "specularReflectance", Rgb::ONE, &what)?;
                let transmittance =
                    self.spectrum_const(&p, "specularTransmittance", Rgb::ONE, &what)?;
                Material::new(
                    name.clone(),
                    MaterialKind::Dielectric {
                        ior: int / ext,
                        reflectance,
                        transmittance,
                    },
                    true,
                )
            }
            "conductor" | "roughconductor" => {
                let (eta, k) = self.conductor_ior(n, &p, &what)?;
                let (alpha_u, alpha_v) = if ty == "conductor" {
                    self.warn(
                        n,
                        format!("smooth conductor traced as GGX alpha {MIN_ALPHA} (near-specular)"),
                    );
                    (MIN_ALPHA, MIN_ALPHA)
                } else {
                    self.alpha(n, &p, &what)?
                };
                // Mitsuba's specularReflectance multiplies the Fresnel reflectance: our `scale`.
                let scale = self.spectrum_const(&p, "specularReflectance", Rgb::ONE, &what)?;
                one_sided(MaterialKind::RoughConductor {
                    eta,
                    k,
                    alpha_u,
                    alpha_v,
                    scale,
                })
            }
            "plastic" | "roughplastic" => {
                let alpha = if ty == "plastic" {
                    // Smooth plastic: a delta coat. Our coat is GGX; the smallest alpha we trace
                    // keeps the highlights sharp and the (identical) diffuse coupling exact.
                    self.warn(n, format!("smooth plastic traced with a GGX coat of alpha {MIN_ALPHA} (near-specular)"));
                    MIN_ALPHA
                } else {
                    let (au, av) = self.alpha(n, &p, &what)?;
                    if au != av {
                        self.warn(n, "anisotropic roughplastic is not supported; alpha sqrt(alphaU alphaV) used");
                    }
                    (au * av).sqrt()
                };
                let int = self.ior(&p, "intIOR", 1.49)?;
                let ext = self.ior(&p, "extIOR", 1.00028)?;
                let specular = self.spectrum_const(&p, "specularReflectance", Rgb::ONE, &what)?;
                let diffuse = self.spectrum_tex(&p, "diffuseReflectance", Rgb::splat(0.5))?;
                let nonlinear = self.boolean(&p, "nonlinear", false)?;
                one_sided(MaterialKind::Plastic {
                    diffuse,
                    specular,
                    ior: int / ext,
                    alpha,
                    layered: true,
                    nonlinear,
                })
            }
            "phong" => {
                // Mitsuba's phong is the energy-normalised modified Phong model we implement.
                let mut kd =
                    self.spectrum_const(&p, "diffuseReflectance", Rgb::splat(0.5), &what)?;
                let mut ks =
                    self.spectrum_const(&p, "specularReflectance", Rgb::splat(0.2), &what)?;
                let exponent = self.float(&p, "exponent", 30.0)?;
                let sum = (kd + ks).max_element();
                if sum > 1.0 {
                    self.warn(
                        n,
                        format!(
                            "{what}: diffuse + specular reflectance {sum} > 1 scaled down to 1"
                        ),
                    );
                    kd /= sum;
                    ks /= sum;
                }
                one_sided(MaterialKind::Phong { kd, ks, exponent })
            }
            "bumpmap" | "normalmap" | "mask" | "coating" | "roughcoating" => {
                let m = self
                    .child_bsdf(n, &p)?
                    .ok_or_else(|| self.err(n, format!("{what} has no nested bsdf")))?;
                let msg = match ty {
                    "bumpmap" | "normalmap" => "bump mapping is not supported and was ignored",
                    "mask" => "opacity masks are not supported; the surface is opaque",
                    _ => "coating layers are not supported; the base bsdf is used",
                };
                self.warn(n, format!("{what}: {msg}"));
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                m
            }
            "blendbsdf" | "mixturebsdf" => {
                let m = self
                    .child_bsdf(n, &p)?
                    .ok_or_else(|| self.err(n, format!("{what} has no nested bsdf")))?;
                for c in &n.children {
                    if c.tag == "bsdf" && c.attr("name").is_none() && c.attr("id").is_some() {
                        // Register the other components' ids too.
                        if !self.ids.contains_key(c.attr("id").unwrap_or("")) {
                            self.bsdf(c)?;
                        }
                    }
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                p.any_with_tag("bsdf");
                p.any_with_tag("ref");
                self.warn(
                    n,
                    format!("{what} is not supported: became its first component"),
                );
                m
            }
            "null" => {
                self.warn(
                    n,
                    "null bsdf (pass-through) is not supported: became an opaque black surface",
                );
                Material::new(
                    name.clone(),
                    MaterialKind::Lambert {
                        albedo: Texture::Constant(Rgb::ZERO),
                    },
                    true,
                )
            }
            other => {
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                p.any_with_tag("bsdf");
                self.warn(
                    n,
                    format!(
                        "bsdf \"{other}\" is not supported: became diffuse with reflectance 0.5"
                    ),
                );
                one_sided(MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::splat(0.5)),
                })
            }
        };
        self.report_unused(&p, &what);
        Ok(m)
    }

    // ---- shapes

    /// Loads every OBJ / PLY file of the scene in parallel (the slow part of big scenes).
    fn preload_meshes(&mut self, root: &Node) -> R<()> {
        let mut paths = Vec::new();
        for c in &root.children {
            if c.tag == "shape"
                && matches!(c.attr("type"), Some("obj" | "ply"))
                && let Some(f) = c
                    .children
                    .iter()
                    .find(|k| k.attr("name") == Some("filename"))
                    .and_then(|k| k.attr("value"))
                && let Ok(p) = resolve_in_folder(&self.file, f, "")
            {
                paths.push(p);
            }
        }
        paths.sort();
        paths.dedup();
        let loaded: Vec<(PathBuf, Result<MeshData, String>)> = paths
            .into_par_iter()
            .map(|p| {
                let m = if p.extension().is_some_and(|e| e.eq_ignore_ascii_case("ply")) {
                    load_ply(&p)
                } else {
                    load_obj(&p)
                };
                (p, m)
            })
            .collect();
        self.meshes.extend(loaded);
        Ok(())
    }

    fn default_bsdf(&mut self) -> u32 {
        if let Some(m) = self.default_bsdf {
            return m;
        }
        // Mitsuba gives shapes without a bsdf a one-sided diffuse bsdf of reflectance 0.5.
        let m = self.b.add_material(Material::new(
            "Mitsuba default (diffuse 0.5)",
            MaterialKind::Lambert {
                albedo: Texture::Constant(Rgb::splat(0.5)),
            },
            false,
        ));
        self.default_bsdf = Some(m);
        m
    }

    /// The builder material of a shape: its nested bsdf, its `<ref>`, or the default.
    fn shape_material(&mut self, n: &Node, p: &Props) -> R<u32> {
        for c in &n.children {
            if c.attr("name").is_some() {
                continue;
            }
            if c.tag == "bsdf" {
                p.objects("bsdf");
                let m = self.bsdf(c)?;
                if let Some(id) = c.attr("id") {
                    return self.material_index(c, id);
                }
                return Ok(self.b.add_material(m));
            }
            if c.tag == "ref" {
                p.objects("ref");
                let id = c
                    .attr("id")
                    .ok_or_else(|| self.err(c, "<ref> without id"))?;
                return self.material_index(c, id);
            }
        }
        Ok(self.default_bsdf())
    }

    fn material_index(&mut self, n: &Node, id: &str) -> R<u32> {
        let mat = match self.ids.get(id) {
            Some(Obj::Bsdf { index: Some(i), .. }) => return Ok(*i),
            Some(Obj::Bsdf { mat, .. }) => mat.clone(),
            Some(Obj::Texture(_)) => {
                return Err(self.err(n, format!("\"{id}\" is a texture, not a bsdf")));
            }
            Some(Obj::Other(t)) => {
                return Err(self.err(n, format!("\"{id}\" is a <{t}>, not a bsdf")));
            }
            None => return Err(self.err(n, format!("unknown id \"{id}\""))),
        };
        let i = self.b.add_material(mat);
        if let Some(Obj::Bsdf { index, .. }) = self.ids.get_mut(id) {
            *index = Some(i);
        }
        Ok(i)
    }

    fn shape(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let what = format!("shape \"{ty}\"");
        let mut loc = format!("line {}", n.line);
        let material = self.shape_material(n, &p)?;
        let mut emission = None;
        for e in p.objects("emitter") {
            let ep = Props::new(e);
            match e.attr("type") {
                Some("area") => {
                    let r = match ep.get("radiance") {
                        Some(r) => self.color_of(r)?,
                        None => return Err(self.err(e, "area emitter has no radiance")),
                    };
                    ep.consume("samplingWeight");
                    self.report_unused(&ep, "emitter \"area\"");
                    emission = Some(r);
                }
                Some(other) => {
                    return Err(self.err(
                        e,
                        format!(
                            "emitter \"{other}\" inside a shape is not supported (only \"area\")"
                        ),
                    ));
                }
                None => return Err(self.err(e, "emitter without type")),
            }
        }
        for k in ["medium", "subsurface"] {
            if !p.any_with_tag(k).is_empty() {
                self.warn(n, format!("{what}: <{k}> is not supported and was ignored"));
            }
        }
        let to_world = self.to_world(&p)?;
        let t = Transform::new(to_world)
            .ok_or_else(|| self.err(n, format!("{what}: toWorld is singular")))?;
        let flip = self.boolean(&p, "flipNormals", false)?;
        let mut mesh = match ty {
            "obj" | "ply" => {
                let file = self
                    .string(&p, "filename")?
                    .ok_or_else(|| self.err(n, format!("{what} has no filename")))?;
                let path = resolve_in_folder(&self.file, &file, &loc)?;
                // Errors in the mesh's data name its file.
                loc = format!("{loc} ({})", path.display());
                // Preloaded meshes are taken (a file used twice is read again).
                let mut mesh = match self.meshes.remove(&path) {
                    Some(Ok(m)) => m,
                    Some(Err(e)) => return Err(self.err(n, format!("{}: {e}", path.display()))),
                    None => {
                        let m = if ty == "ply" {
                            load_ply(&path)
                        } else {
                            load_obj(&path)
                        };
                        m.map_err(|e| self.err(n, format!("{}: {e}", path.display())))?
                    }
                };
                let flip_tex = if ty == "obj" {
                    self.boolean(&p, "flipTexCoords", true)?
                } else {
                    false
                };
                // See the module comment: Mitsuba's OBJ default equals our convention.
                if !flip_tex {
                    for uv in &mut mesh.uvs {
                        uv.y = 1.0 - uv.y;
                    }
                }
                let face_normals = self.boolean(&p, "faceNormals", false)?;
                if face_normals {
                    mesh.normals.clear();
                } else if mesh.normals.is_empty() {
                    // Mitsuba generates smooth vertex normals for meshes without them.
                    smooth_normals(&mut mesh);
                }
                if p.has("maxSmoothAngle") {
                    p.consume("maxSmoothAngle");
                    self.warn(
                        n,
                        format!(
                            "{what}: maxSmoothAngle is not supported; the file's normals are used"
                        ),
                    );
                }
                if self.int(&p, "shapeIndex", -1)? >= 0 {
                    return Err(self.err(n, format!("{what}: shapeIndex is not supported")));
                }
                p.consume("collapse");
                p.consume("loadMaterials");
                mesh
            }
            "rectangle" => MeshData {
                positions: vec![
                    Vec3::new(-1.0, -1.0, 0.0),
                    Vec3::new(1.0, -1.0, 0.0),
                    Vec3::new(1.0, 1.0, 0.0),
                    Vec3::new(-1.0, 1.0, 0.0),
                ],
                normals: Vec::new(),
                // Mitsuba's (0,0) (1,0) (1,1) (0,1), with v flipped to our convention.
                uvs: vec![
                    Vec2::new(0.0, 1.0),
                    Vec2::new(1.0, 1.0),
                    Vec2::new(1.0, 0.0),
                    Vec2::new(0.0, 0.0),
                ],
                indices: vec![[0, 1, 2], [2, 3, 0]],
            },
            "cube" => cube(),
            "disk" => {
                self.warn(
                    n,
                    format!("disk tessellated into {DISK_SEGMENTS} triangles"),
                );
                disk()
            }
            "sphere" => {
                let center = match p.get("center") {
                    Some(c) => self.point_of(c)?,
                    None => Vec3::ZERO,
                };
                let radius = self.float(&p, "radius", 1.0)?;
                if !(radius > 0.0) {
                    return Err(self.err(n, format!("sphere radius must be > 0, got {radius}")));
                }
                let scale = uniform_scale(&to_world).ok_or_else(|| {
                    self.err(
                        n,
                        "a sphere under non-uniform scale or shear is not supported",
                    )
                })?;
                self.report_unused(&p, &what);
                return self.b.add_sphere(
                    t.point(center),
                    radius * scale,
                    flip,
                    material,
                    emission,
                    &loc,
                );
            }
            "serialized" => {
                return Err(self.err(
                    n,
                    "shape \"serialized\" is not supported (convert it to PLY or OBJ)",
                ));
            }
            other => {
                return Err(self.err(
                    n,
                    format!("shape \"{other}\" is not supported (obj, ply, rectangle, cube, disk, sphere)"),
                ));
            }
        };
        if flip {
            for tri in &mut mesh.indices {
                tri.swap(1, 2);
            }
            for nn in &mut mesh.normals {
                *nn = -*nn;
            }
        }
        self.report_unused(&p, &what);
        self.b.add_mesh(&mesh, &t, material, emission, &loc)
    }

    fn emitter(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        match n.attr("type").unwrap_or("") {
            "point" => {
                let to_world = self.to_world(&p)?;
                let local = match p.get("position") {
                    Some(c) => self.point_of(c)?,
                    None => Vec3::ZERO,
                };
                let pos = to_world.transform_point3(local);
                let intensity = match p.get("intensity") {
                    Some(c) => self.color_of(c)?,
                    None => Rgb::ONE,
                };
                p.consume("samplingWeight");
                self.report_unused(&p, "emitter \"point\"");
                self.b.add_point_light(pos, intensity, &format!("line {}", n.line))
            }
            "area" => Err(self.err(n, "an area emitter must be nested in a <shape>")),
            other => Err(self.err(
                n,
                format!("emitter \"{other}\" is not supported (only \"point\" and area emitters in shapes)"),
            )),
        }
    }
}

/// Area-weighted vertex normals from the faces around each vertex (Mitsuba sums the unit face
/// normals of the triangles sharing a vertex).
fn smooth_normals(mesh: &mut MeshData) {
    let mut n = vec![Vec3::ZERO; mesh.positions.len()];
    for t in &mesh.indices {
        let [a, b, c] = t.map(|k| mesh.positions[k as usize]);
        let f = (b - a).cross(c - a).normalize_or_zero();
        for &k in t {
            n[k as usize] += f;
        }
    }
    for v in &mut n {
        *v = v.normalize_or_zero();
    }
    mesh.normals = n;
}

/// Mitsuba's `cube`: [-1, 1]^3 with outward faces.
fn cube() -> MeshData {
    let mut m = MeshData::default();
    // (normal, u axis, v axis) with u x v = normal, so counter-clockwise seen from outside.
    let faces = [
        (Vec3::X, Vec3::NEG_Z, Vec3::Y),
        (Vec3::NEG_X, Vec3::Z, Vec3::Y),
        (Vec3::Y, Vec3::X, Vec3::NEG_Z),
        (Vec3::NEG_Y, Vec3::X, Vec3::Z),
        (Vec3::Z, Vec3::X, Vec3::Y),
        (Vec3::NEG_Z, Vec3::NEG_X, Vec3::Y),
    ];
    for (nrm, u, v) in faces {
        let base = m.positions.len() as u32;
        for (su, sv) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            m.positions.push(nrm + u * su + v * sv);
            m.uvs.push(Vec2::new(0.5 * (su + 1.0), 0.5 * (sv + 1.0)));
        }
        m.indices.push([base, base + 1, base + 2]);
        m.indices.push([base, base + 2, base + 3]);
    }
    m
}

/// Mitsuba's `disk`: the unit disk in the xy plane facing +z, as a triangle fan.
fn disk() -> MeshData {
    let mut m = MeshData::default();
    m.positions.push(Vec3::ZERO);
    m.uvs.push(Vec2::new(0.5, 0.5));
    for i in 0..DISK_SEGMENTS {
        let a = i as f32 / DISK_SEGMENTS as f32 * std::f32::consts::TAU;
        m.positions.push(Vec3::new(a.cos(), a.sin(), 0.0));
        m.uvs
            .push(Vec2::new(0.5 + 0.5 * a.cos(), 0.5 - 0.5 * a.sin()));
        let k = i as u32 + 1;
        let next = (i as u32 + 1) % DISK_SEGMENTS as u32 + 1;
        m.indices.push([0, k, next]);
    }
    m
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

    #[test]
    fn cube_faces_point_outward() {
        let m = cube();
        for t in &m.indices {
            let [a, b, c] = t.map(|k| m.positions[k as usize]);
            let n = (b - a).cross(c - a);
            let center = (a + b + c) / 3.0;
            assert!(n.dot(center) > 0.0);
        }
        let d = disk();
        for t in &d.indices {
            let [a, b, c] = t.map(|k| d.positions[k as usize]);
            assert!((b - a).cross(c - a).z > 0.0);
        }
    }
}
