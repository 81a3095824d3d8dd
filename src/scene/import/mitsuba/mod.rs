//! Mitsuba 0.5 scene importer (XML, read with `quick-xml`, `xml`): the subset of the format
//! that maps onto our scene model (see `scenes/README.md`, "Importers"), with properties
//! (`props`), BSDFs, textures, shapes and the sensor in a module each.
//!
//! Conventions of Mitsuba 0.5 that matter here (Mitsuba 0.5 documentation and sources):
//! - `<matrix value="...">` is row-major; the steps of a `<transform>` apply in document order
//!   (each left-multiplies the transform so far).
//! - Camera space: +z forward, +y up, and raster x runs toward -x (`lookat` builds the columns
//!   `left = up x dir`, `up`, `dir`). Our raster x runs along forward x up; a camera-to-world
//!   transform of the other handedness is mirrored with [`crate::camera::Camera::with_flip_x`].
//! - `fov` spans `fovAxis` (default `x`).
//! - `maxDepth` counts path vertices after the camera: 1 shows directly visible emitters only, 2
//!   is direct lighting; our `max_depth` = Mitsuba's `maxDepth` - 1; -1 (unlimited) becomes 64.
//! - BSDFs are one-sided (black from behind) unless wrapped in `twosided`; dielectrics see both
//!   sides. Area emitters emit on the side of the (shading) normal.
//! - OBJ texture coordinates are flipped vertically by default (`flipTexCoords`) and bitmaps are
//!   looked up with v = 0 at the image's top row: together that is the usual OBJ convention,
//!   which is ours (v = 0 at the bottom). Built-in shapes and PLY uvs are in Mitsuba's own
//!   convention and get v -> 1 - v.

mod camera;
mod materials;
mod props;
mod shapes;
mod textures;

use super::common::{Bitmaps, Warnings};
use super::resolve::Resolver;
use crate::material::{Material, Texture};
use crate::scene::import::mesh::MeshError;
use crate::scene::import::xml::Props;
use crate::scene::import::xml::{self, Node, parse_xml};
use crate::scene::{MeshData, SceneBuilder, SceneError, SceneParams};
use std::collections::HashMap;
use std::path::Path;
use std::path::PathBuf;

type R<T> = Result<T, SceneError>;

/// Our depth limit for Mitsuba's `maxDepth = -1` (unlimited); the path tracer's Russian roulette
/// ends most paths long before (BDPT has none: give it a `--max-depth`).
pub(crate) const UNLIMITED_DEPTH: u32 = 64;

// ------------------------------------------------------------------------------------------
// The loader.

/// What an `id` names.
enum Obj {
    Bsdf { mat: Material, index: Option<u32> },
    Texture(Texture),
    Other(String),
}

/// The loader's state.
struct Ctx {
    file: PathBuf,
    b: SceneBuilder,
    warn: Warnings,
    ids: HashMap<String, Obj>,
    bitmaps: Bitmaps,
    meshes: HashMap<PathBuf, Result<MeshData, MeshError>>,
    default_bsdf: Option<u32>,
}

/// Parses Mitsuba XML text, reading the files it names through `resolver`: a Mitsuba 2 or 3
/// file (its root's version) goes to `mitsuba3` with `params`, a Mitsuba 0.5 file is read here.
pub(crate) fn parse_with(
    text: &str,
    resolver: Resolver,
    params: &SceneParams,
) -> Result<SceneBuilder, SceneError> {
    let file = &resolver.scene_file().to_path_buf();
    let mut root = parse_xml(text, file)?;
    if let Some(v) = root.attr("version") {
        match super::mitsuba3::major_version(v) {
            Some(m) if m >= 2 => return super::mitsuba3::parse(root, resolver, params),
            Some(_) => {}
            None => {
                return Err(SceneError::new(
                    file,
                    format!("line {}", root.line),
                    format!("malformed scene version \"{v}\""),
                ));
            }
        }
    }
    if !params.is_empty() {
        return Err(SceneError::new(
            file,
            "parameters",
            "parameters (--define, a job's defines) apply only to Mitsuba 2/3 files; this is a Mitsuba 0.5 file",
        ));
    }
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
        b: SceneBuilder::new(resolver),
        warn: Warnings::default(),
        ids: HashMap::new(),
        bitmaps: Bitmaps::default(),
        meshes: HashMap::new(),
        default_bsdf: None,
    };
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

impl Ctx {
    fn err(&self, n: &Node, m: impl Into<String>) -> SceneError {
        xml::error_at(&self.file, n, m)
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
