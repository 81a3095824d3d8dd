//! pbrt-v3 scene importer: a tokenizer whose tokens carry file and line, and a parser for the
//! subset of the format that maps onto our scene model (see `scenes/README.md`, "Importers").
//!
//! Conventions of pbrt-v3 that matter here (Pharr, Jakob, Humphreys, *Physically Based
//! Rendering*, 3rd ed., and the pbrt-v3 sources):
//! - `Transform` and `ConcatTransform` give a 4x4 matrix column by column (pbrt transposes the
//!   16 numbers it reads); every other transform directive post-multiplies the current
//!   transformation matrix (CTM).
//! - At `Camera` the CTM is world-to-camera. Camera space is left-handed: x right, y up, z
//!   forward. Our camera is right-handed (right = forward x up), so when the camera-to-world
//!   transform maps x to `up x forward` (a proper rotation, e.g. from `LookAt`) we mirror raster x
//!   ([`Camera::with_flip_x`]); exporters that write a reflection (Tungsten/Bitterli files,
//!   `Scale -1 1 1`) need no mirroring.
//! - `fov` is the field of view of the shorter image axis.
//! - Materials are two-sided; `diffuse` area lights emit on the side of the surface normal (which
//!   for triangles with vertex normals follows the vertex normals, as our scene builder does).
//! - The path integrator's `maxdepth` counts bounces exactly as our `max_depth` does: 1 is
//!   direct lighting.
//!
//! Anything unsupported is reported once (by name, with the file and line of its first use);
//! where ignoring it would make the image meaningless (distant and infinite lights, unknown
//! shapes, partial spheres) it is an error instead.

use super::json::resolve_in_folder;
use super::mesh::load_ply;
use super::{MeshData, Scene, SceneBuilder, SceneError};
use crate::camera::Camera;
use crate::geometry::{Mat4, Rgb, Transform, Vec2, Vec3};
use crate::material::microfacet::MIN_ALPHA;
use crate::material::{Bitmap, Material, MaterialKind, Texture};
use std::cell::Cell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::sync::Arc;

/// Nesting limit for `Include` (guards against include cycles).
const MAX_INCLUDE_DEPTH: usize = 16;

/// pbrt-v3's default `metal` is copper; these are the RGB values of its complex index of
/// refraction used by Bitterli's scene exports (and by Mitsuba's `Cu`).
pub const COPPER_ETA: [f32; 3] = [0.200438, 0.924033, 1.102212];
pub const COPPER_K: [f32; 3] = [3.912949, 2.452848, 2.142188];

/// pbrt-v3's `TrowbridgeReitzDistribution::RoughnessToAlpha`: maps the perceptual `roughness`
/// of `remaproughness true` materials to the GGX alpha (a quartic fit in log roughness).
pub fn roughness_to_alpha(roughness: f32) -> f32 {
    let x = roughness.max(1e-3).ln();
    1.62142 + 0.819955 * x + 0.1734 * x * x + 0.0171201 * x * x * x + 0.000640711 * x * x * x * x
}

// ------------------------------------------------------------------------------------------
// Warnings, shared with the Mitsuba importer.

/// Collects warnings, each message once with the place of its first occurrence and a count.
#[derive(Default)]
pub(crate) struct Warnings {
    entries: Vec<(String, String, usize)>,
    index: HashMap<String, usize>,
}

impl Warnings {
    /// Records `message` seen at `place` ("file:line").
    pub(crate) fn add(&mut self, place: String, message: impl Into<String>) {
        let m = message.into();
        match self.index.get(&m) {
            Some(&i) => self.entries[i].2 += 1,
            None => {
                self.index.insert(m.clone(), self.entries.len());
                self.entries.push((m, place, 1));
            }
        }
    }

    /// Hands the warnings to the scene builder, one line each.
    pub(crate) fn flush(self, b: &mut SceneBuilder) {
        for (m, place, n) in self.entries {
            if n > 1 {
                b.warn(format!("{place}: {m} ({n} occurrences)"));
            } else {
                b.warn(format!("{place}: {m}"));
            }
        }
    }
}

// ------------------------------------------------------------------------------------------
// Tokens.

#[derive(Clone, Copy, Debug)]
struct Loc {
    file: u16,
    line: u32,
}

#[derive(Clone, Debug, PartialEq)]
enum Tok {
    /// A bare word: a directive name, or `true`/`false`.
    Word(String),
    Str(String),
    Num(f64),
    Open,
    Close,
}

#[derive(Clone, Debug)]
struct Token {
    tok: Tok,
    loc: Loc,
}

fn describe(t: &Tok) -> String {
    match t {
        Tok::Word(w) => format!("'{w}'"),
        Tok::Str(s) => format!("\"{s}\""),
        Tok::Num(n) => format!("the number {n}"),
        Tok::Open => "'['".into(),
        Tok::Close => "']'".into(),
    }
}

/// Splits pbrt text into tokens: quoted strings (with C escapes), `[`, `]`, numbers and bare
/// words; `#` starts a comment that runs to the end of the line.
fn tokenize(text: &str, file: u16, path: &Path) -> Result<Vec<Token>, SceneError> {
    let err = |line: u32, m: String| SceneError::new(path, format!("line {line}"), m);
    let mut out = Vec::new();
    let mut line = 1u32;
    let mut it = text.chars().peekable();
    while let Some(c) = it.next() {
        let loc = Loc { file, line };
        match c {
            '\n' => line += 1,
            c if c.is_whitespace() => {}
            '#' => {
                while it.peek().is_some_and(|&n| n != '\n') {
                    it.next();
                }
            }
            '[' => out.push(Token {
                tok: Tok::Open,
                loc,
            }),
            ']' => out.push(Token {
                tok: Tok::Close,
                loc,
            }),
            '"' => {
                let mut s = String::new();
                loop {
                    match it.next() {
                        None => return Err(err(loc.line, "unterminated string".into())),
                        Some('"') => break,
                        Some('\n') => {
                            return Err(err(loc.line, "string is not closed on its line".into()));
                        }
                        Some('\\') => {
                            let e = match it.next() {
                                Some('n') => '\n',
                                Some('t') => '\t',
                                Some('r') => '\r',
                                Some('b') => '\u{8}',
                                Some('f') => '\u{c}',
                                Some(ch @ ('\\' | '\'' | '"')) => ch,
                                other => {
                                    return Err(err(
                                        loc.line,
                                        format!(
                                            "unknown escape sequence '\\{}'",
                                            other.unwrap_or(' ')
                                        ),
                                    ));
                                }
                            };
                            s.push(e);
                        }
                        Some(ch) => s.push(ch),
                    }
                }
                out.push(Token {
                    tok: Tok::Str(s),
                    loc,
                });
            }
            _ => {
                let mut w = String::from(c);
                while let Some(&n) = it.peek() {
                    if n.is_whitespace() || matches!(n, '[' | ']' | '"' | '#') {
                        break;
                    }
                    w.push(n);
                    it.next();
                }
                let tok = if c.is_ascii_digit() || matches!(c, '-' | '+' | '.') {
                    match w.parse::<f64>() {
                        Ok(v) if v.is_finite() => Tok::Num(v),
                        _ => return Err(err(loc.line, format!("malformed number '{w}'"))),
                    }
                } else if c.is_ascii_alphabetic()
                    && w.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_')
                {
                    Tok::Word(w)
                } else {
                    return Err(err(loc.line, format!("unexpected text '{w}'")));
                };
                out.push(Token { tok, loc });
            }
        }
    }
    Ok(out)
}

// ------------------------------------------------------------------------------------------
// Parameter lists.

#[derive(Clone, Debug)]
enum Values {
    Nums(Vec<f64>),
    Strs(Vec<String>),
    Bools(Vec<bool>),
}

#[derive(Clone, Debug)]
struct Param {
    /// Declared type with pbrt-v3's synonyms folded (`point` = `point3`, `color` = `rgb`, ...).
    ty: String,
    /// The declaration as written, for messages.
    decl: String,
    name: String,
    values: Values,
    loc: Loc,
    used: Cell<bool>,
}

#[derive(Clone, Debug, Default)]
struct ParamSet {
    params: Vec<Param>,
}

impl ParamSet {
    fn find(&self, name: &str, types: &[&str]) -> Option<&Param> {
        let p = self
            .params
            .iter()
            .rev()
            .find(|p| p.name == name && types.contains(&p.ty.as_str()))?;
        p.used.set(true);
        Some(p)
    }

    fn has(&self, name: &str) -> bool {
        self.params.iter().any(|p| p.name == name)
    }

    /// Marks every parameter used (for directives whose parameters are all ignored at once).
    fn consume_all(&self) {
        for p in &self.params {
            p.used.set(true);
        }
    }
}

fn canonical_type(ty: &str) -> Option<&'static str> {
    Some(match ty {
        "integer" => "integer",
        "float" => "float",
        "point" | "point3" => "point3",
        "point2" => "point2",
        "vector" | "vector3" => "vector3",
        "vector2" => "vector2",
        "normal" | "normal3" => "normal3",
        "rgb" | "color" => "rgb",
        "xyz" => "xyz",
        "blackbody" => "blackbody",
        "spectrum" => "spectrum",
        "bool" => "bool",
        "string" => "string",
        "texture" => "texture",
        _ => return None,
    })
}

// ------------------------------------------------------------------------------------------
// Graphics state.

#[derive(Clone)]
enum SpecTex {
    Ok(Texture),
    Unsupported(String),
}

#[derive(Clone)]
enum FloatTex {
    Const(f32),
    Unsupported(String),
}

#[derive(Clone)]
struct GState {
    ctm: Mat4,
    /// Builder material index; `None` is pbrt's default (`matte`, Kd 0.5).
    material: Option<u32>,
    /// Radiance of the current `AreaLightSource`.
    area: Option<Rgb>,
    reverse: bool,
    named: Rc<HashMap<String, u32>>,
    float_tex: Rc<HashMap<String, FloatTex>>,
    spec_tex: Rc<HashMap<String, SpecTex>>,
}

enum Frame {
    Attribute(Box<GState>, Loc),
    Transform(Mat4, Loc),
}

/// A shape recorded inside `ObjectBegin`/`ObjectEnd`, instantiated by `ObjectInstance`.
#[derive(Clone)]
struct ShapeCall {
    ty: String,
    params: ParamSet,
    ctm: Mat4,
    material: u32,
    reverse: bool,
    loc: Loc,
}

struct CameraDef {
    ty: String,
    params: ParamSet,
    world_to_camera: Mat4,
    loc: Loc,
}

struct Source {
    tokens: Vec<Token>,
    pos: usize,
}

struct Parser {
    files: Vec<PathBuf>,
    sources: Vec<Source>,
    b: SceneBuilder,
    warn: Warnings,
    g: GState,
    stack: Vec<Frame>,
    in_world: bool,
    world_ended: bool,
    camera: Option<CameraDef>,
    resolution: (u32, u32),
    named_coords: HashMap<String, Mat4>,
    bitmaps: HashMap<(PathBuf, bool), Arc<Bitmap>>,
    default_material: Option<u32>,
    objects: HashMap<String, Vec<ShapeCall>>,
    defining: Option<(String, Vec<ShapeCall>)>,
    /// `ActiveTransform`: whether transform directives update the start / end transform.
    active: (bool, bool),
    last_loc: Loc,
}

type R<T> = Result<T, SceneError>;

/// Loads a pbrt-v3 file.
pub fn load(path: &Path) -> Result<Scene, SceneError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| SceneError::new(path, "file", format!("cannot read: {e}")))?;
    parse(&text, path)?.build()
}

/// Parses pbrt-v3 text; `file` names it in errors and anchors relative paths.
pub fn parse(text: &str, file: &Path) -> Result<SceneBuilder, SceneError> {
    let tokens = tokenize(text, 0, file)?;
    let mut p = Parser {
        files: vec![file.to_path_buf()],
        sources: vec![Source { tokens, pos: 0 }],
        b: SceneBuilder::new(file),
        warn: Warnings::default(),
        g: GState {
            ctm: Mat4::IDENTITY,
            material: None,
            area: None,
            reverse: false,
            named: Rc::default(),
            float_tex: Rc::default(),
            spec_tex: Rc::default(),
        },
        stack: Vec::new(),
        in_world: false,
        world_ended: false,
        camera: None,
        resolution: (640, 480),
        named_coords: HashMap::new(),
        bitmaps: HashMap::new(),
        default_material: None,
        objects: HashMap::new(),
        defining: None,
        active: (true, true),
        last_loc: Loc { file: 0, line: 1 },
    };
    // pbrt-v3's defaults when the file names no Integrator / Sampler: path, maxdepth 5; 16 spp.
    p.b.defaults.max_depth = Some(5);
    p.b.defaults.spp = Some(16);
    p.run()?;
    let Parser { mut b, warn, .. } = p;
    warn.flush(&mut b);
    Ok(b)
}

impl Parser {
    // ---- errors and warnings

    fn err(&self, loc: Loc, m: impl Into<String>) -> SceneError {
        SceneError::new(
            &self.files[loc.file as usize],
            format!("line {}", loc.line),
            m,
        )
    }

    fn warn(&mut self, loc: Loc, m: impl Into<String>) {
        let place = format!("{}:{}", self.files[loc.file as usize].display(), loc.line);
        self.warn.add(place, m);
    }

    /// Re-anchors an error from a helper (path resolution, mesh loading) at `loc`.
    fn at(&self, loc: Loc, e: SceneError) -> SceneError {
        self.err(loc, e.message)
    }

    // ---- token stream

    fn peek(&mut self) -> Option<&Token> {
        while let Some(s) = self.sources.last() {
            if s.pos < s.tokens.len() {
                break;
            }
            if self.sources.len() == 1 {
                return None;
            }
            self.sources.pop();
        }
        let s = self.sources.last()?;
        s.tokens.get(s.pos)
    }

    fn next(&mut self) -> Option<Token> {
        self.peek()?;
        let s = self.sources.last_mut()?;
        let t = s.tokens[s.pos].clone();
        s.pos += 1;
        self.last_loc = t.loc;
        Some(t)
    }

    fn eof_err(&self, what: &str) -> SceneError {
        self.err(self.last_loc, format!("unexpected end of file: {what}"))
    }

    /// The quoted string argument of a directive.
    fn arg_str(&mut self, directive: &str) -> R<String> {
        match self.next() {
            Some(Token {
                tok: Tok::Str(s), ..
            }) => Ok(s),
            Some(t) => Err(self.err(
                t.loc,
                format!(
                    "{directive} expects a quoted string, found {}",
                    describe(&t.tok)
                ),
            )),
            None => Err(self.eof_err(&format!("{directive} expects a quoted string"))),
        }
    }

    /// `n` numbers, optionally in brackets (`Translate 1 2 3`, `Transform [ ... ]`).
    fn arg_nums(&mut self, directive: &str, n: usize, loc: Loc) -> R<Vec<f32>> {
        let bracketed = matches!(self.peek(), Some(Token { tok: Tok::Open, .. }));
        let mut v = Vec::with_capacity(n);
        if bracketed {
            self.next();
            loop {
                match self.next() {
                    Some(Token {
                        tok: Tok::Close, ..
                    }) => break,
                    Some(Token {
                        tok: Tok::Num(x), ..
                    }) => v.push(x as f32),
                    Some(t) => {
                        return Err(self.err(
                            t.loc,
                            format!("{directive} expects numbers, found {}", describe(&t.tok)),
                        ));
                    }
                    None => return Err(self.eof_err("missing ']'")),
                }
            }
        } else {
            while v.len() < n {
                match self.peek() {
                    Some(Token {
                        tok: Tok::Num(x), ..
                    }) => {
                        let x = *x as f32;
                        self.next();
                        v.push(x);
                    }
                    _ => break,
                }
            }
        }
        if v.len() != n {
            return Err(self.err(
                loc,
                format!("{directive} expects {n} numbers, got {}", v.len()),
            ));
        }
        Ok(v)
    }

    /// The parameter list after a directive's arguments: `"type name" value` or
    /// `"type name" [ values ]`, until the next directive.
    fn params(&mut self) -> R<ParamSet> {
        let mut ps = ParamSet::default();
        while let Some(Token {
            tok: Tok::Str(_), ..
        }) = self.peek()
        {
            let Some(Token {
                tok: Tok::Str(decl),
                loc,
            }) = self.next()
            else {
                break; // cannot happen: a string was peeked
            };
            let parts: Vec<&str> = decl.split_whitespace().collect();
            if parts.len() != 2 {
                return Err(self.err(
                    loc,
                    format!("malformed parameter declaration \"{decl}\": expected \"type name\""),
                ));
            }
            let Some(ty) = canonical_type(parts[0]) else {
                return Err(self.err(
                    loc,
                    format!("unknown parameter type '{}' in \"{decl}\"", parts[0]),
                ));
            };
            // Raw items: one literal, or a bracketed list.
            let mut items: Vec<Token> = Vec::new();
            match self.peek() {
                Some(Token { tok: Tok::Open, .. }) => {
                    self.next();
                    loop {
                        match self.next() {
                            Some(Token {
                                tok: Tok::Close, ..
                            }) => break,
                            Some(t @ Token { tok: Tok::Open, .. }) => {
                                return Err(self.err(t.loc, "nested '[' in a parameter list"));
                            }
                            Some(t) => items.push(t),
                            None => {
                                return Err(self.err(loc, format!("\"{decl}\": missing ']'")));
                            }
                        }
                    }
                }
                Some(Token {
                    tok: Tok::Num(_) | Tok::Str(_),
                    ..
                }) => {
                    if let Some(t) = self.next() {
                        items.push(t);
                    }
                }
                Some(Token {
                    tok: Tok::Word(w), ..
                }) if ty == "bool" && (w == "true" || w == "false") => {
                    if let Some(t) = self.next() {
                        items.push(t);
                    }
                }
                _ => return Err(self.err(loc, format!("parameter \"{decl}\" has no value"))),
            }
            let values = self.param_values(ty, &decl, loc, items)?;
            ps.params.push(Param {
                ty: ty.to_string(),
                decl: decl.clone(),
                name: parts[1].to_string(),
                values,
                loc,
                used: Cell::new(false),
            });
        }
        Ok(ps)
    }

    fn param_values(&self, ty: &str, decl: &str, loc: Loc, items: Vec<Token>) -> R<Values> {
        let nums = |items: &[Token]| -> R<Vec<f64>> {
            items
                .iter()
                .map(|t| match &t.tok {
                    Tok::Num(x) => Ok(*x),
                    other => Err(self.err(
                        t.loc,
                        format!(
                            "parameter \"{decl}\" expects numbers, found {}",
                            describe(other)
                        ),
                    )),
                })
                .collect()
        };
        let strs = |items: &[Token]| -> R<Vec<String>> {
            items
                .iter()
                .map(|t| match &t.tok {
                    Tok::Str(s) => Ok(s.clone()),
                    other => Err(self.err(
                        t.loc,
                        format!(
                            "parameter \"{decl}\" expects quoted strings, found {}",
                            describe(other)
                        ),
                    )),
                })
                .collect()
        };
        Ok(match ty {
            "bool" => Values::Bools(
                items
                    .iter()
                    .map(|t| match &t.tok {
                        Tok::Str(s) | Tok::Word(s) if s == "true" => Ok(true),
                        Tok::Str(s) | Tok::Word(s) if s == "false" => Ok(false),
                        other => Err(self.err(
                            t.loc,
                            format!(
                                "parameter \"{decl}\" expects \"true\" or \"false\", found {}",
                                describe(other)
                            ),
                        )),
                    })
                    .collect::<R<Vec<bool>>>()?,
            ),
            "string" | "texture" => Values::Strs(strs(&items)?),
            "spectrum"
                if items.iter().all(|t| matches!(t.tok, Tok::Str(_))) && !items.is_empty() =>
            {
                Values::Strs(strs(&items)?)
            }
            _ => {
                let v = nums(&items)?;
                if ty == "integer" && v.iter().any(|x| x.fract() != 0.0) {
                    return Err(
                        self.err(loc, format!("parameter \"{decl}\" has a non-integer value"))
                    );
                }
                Values::Nums(v)
            }
        })
    }

    // ---- typed parameter lookup

    fn nums<'p>(&self, p: &'p Param) -> R<&'p [f64]> {
        match &p.values {
            Values::Nums(v) => Ok(v),
            _ => Err(self.err(p.loc, format!("parameter \"{}\" expects numbers", p.decl))),
        }
    }

    fn one_num(&self, p: &Param) -> R<f64> {
        let v = self.nums(p)?;
        if v.len() != 1 {
            return Err(self.err(
                p.loc,
                format!("parameter \"{}\" expects 1 value, got {}", p.decl, v.len()),
            ));
        }
        Ok(v[0])
    }

    fn float(&self, ps: &ParamSet, name: &str, default: f32) -> R<f32> {
        match ps.find(name, &["float"]) {
            Some(p) => Ok(self.one_num(p)? as f32),
            None => Ok(default),
        }
    }

    fn opt_float(&self, ps: &ParamSet, name: &str) -> R<Option<f32>> {
        match ps.find(name, &["float"]) {
            Some(p) => Ok(Some(self.one_num(p)? as f32)),
            None => Ok(None),
        }
    }

    fn int(&self, ps: &ParamSet, name: &str, default: i64) -> R<i64> {
        match ps.find(name, &["integer"]) {
            Some(p) => Ok(self.one_num(p)? as i64),
            None => Ok(default),
        }
    }

    fn ints(&self, ps: &ParamSet, name: &str) -> R<Option<Vec<i64>>> {
        match ps.find(name, &["integer"]) {
            Some(p) => Ok(Some(self.nums(p)?.iter().map(|&x| x as i64).collect())),
            None => Ok(None),
        }
    }

    fn boolean(&self, ps: &ParamSet, name: &str, default: bool) -> R<bool> {
        match ps.find(name, &["bool"]) {
            Some(p) => match &p.values {
                Values::Bools(v) if v.len() == 1 => Ok(v[0]),
                _ => Err(self.err(p.loc, format!("parameter \"{}\" expects 1 value", p.decl))),
            },
            None => Ok(default),
        }
    }

    fn string(&self, ps: &ParamSet, name: &str) -> R<Option<String>> {
        self.string_of(ps, name, &["string"])
    }

    fn string_of(&self, ps: &ParamSet, name: &str, types: &[&str]) -> R<Option<String>> {
        match ps.find(name, types) {
            Some(p) => match &p.values {
                Values::Strs(v) if v.len() == 1 => Ok(Some(v[0].clone())),
                _ => Err(self.err(p.loc, format!("parameter \"{}\" expects 1 string", p.decl))),
            },
            None => Ok(None),
        }
    }

    /// Triples of a point / vector / normal parameter.
    fn vec3s(&self, ps: &ParamSet, name: &str, types: &[&str]) -> R<Option<Vec<Vec3>>> {
        match ps.find(name, types) {
            Some(p) => {
                let v = self.nums(p)?;
                if v.len() % 3 != 0 {
                    return Err(self.err(
                        p.loc,
                        format!(
                            "parameter \"{}\" has {} values, not a multiple of 3",
                            p.decl,
                            v.len()
                        ),
                    ));
                }
                Ok(Some(
                    v.chunks_exact(3)
                        .map(|c| Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32))
                        .collect(),
                ))
            }
            None => Ok(None),
        }
    }

    /// A colour parameter (`rgb`/`color`, `xyz`, a flat `spectrum`); `None` when absent.
    fn rgb(&self, ps: &ParamSet, name: &str) -> R<Option<Rgb>> {
        let Some(p) = ps.find(name, &["rgb", "xyz", "spectrum", "blackbody", "float"]) else {
            return Ok(None);
        };
        let c = match p.ty.as_str() {
            "rgb" | "xyz" => {
                let v = self.nums(p)?;
                if v.len() != 3 {
                    return Err(self.err(
                        p.loc,
                        format!("parameter \"{}\" expects 3 values, got {}", p.decl, v.len()),
                    ));
                }
                let c = Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32);
                if p.ty == "xyz" {
                    // CIE XYZ to linear sRGB (pbrt-v3 XYZToRGB).
                    Vec3::new(
                        3.240479 * c.x - 1.53715 * c.y - 0.498535 * c.z,
                        -0.969256 * c.x + 1.875991 * c.y + 0.041556 * c.z,
                        0.055648 * c.x - 0.204043 * c.y + 1.057311 * c.z,
                    )
                } else {
                    c
                }
            }
            "spectrum" => match &p.values {
                // (wavelength, value) pairs: only a flat spectrum has an exact RGB equivalent.
                Values::Nums(v) if v.len() >= 2 && v.len() % 2 == 0 => {
                    let first = v[1];
                    if v.chunks_exact(2)
                        .any(|c| (c[1] - first).abs() > 1e-6 * first.abs().max(1.0))
                    {
                        return Err(self.err(
                            p.loc,
                            format!("parameter \"{}\": sampled spectra are not supported; give an \"rgb\" value", p.decl),
                        ));
                    }
                    Vec3::splat(first as f32)
                }
                _ => {
                    return Err(self.err(
                        p.loc,
                        format!("parameter \"{}\": spectrum files and malformed spectra are not supported; give an \"rgb\" value", p.decl),
                    ));
                }
            },
            "blackbody" => {
                return Err(self.err(
                    p.loc,
                    format!("parameter \"{}\": blackbody emitters are not supported; give an \"rgb\" value", p.decl),
                ));
            }
            _ => {
                // A float where a colour is expected: pbrt-v3 would not find it.
                p.used.set(false);
                return Ok(None);
            }
        };
        if !(c.is_finite()) {
            return Err(self.err(p.loc, format!("parameter \"{}\" is not finite", p.decl)));
        }
        Ok(Some(c))
    }

    fn color(&self, ps: &ParamSet, name: &str, default: Rgb) -> R<Rgb> {
        let c = self.rgb(ps, name)?.unwrap_or(default);
        if c.min_element() < 0.0 {
            let loc = ps
                .params
                .iter()
                .rev()
                .find(|p| p.name == name)
                .map_or(self.last_loc, |p| p.loc);
            return Err(self.err(loc, format!("'{name}' must be >= 0, got {c:?}")));
        }
        Ok(c)
    }

    /// Warns about every parameter of `ps` nothing looked at.
    fn report_unused(&mut self, ps: &ParamSet, what: &str) {
        let unused: Vec<(Loc, String)> = ps
            .params
            .iter()
            .filter(|p| !p.used.get())
            .map(|p| (p.loc, p.decl.clone()))
            .collect();
        for (loc, decl) in unused {
            self.warn(
                loc,
                format!("{what}: parameter \"{decl}\" is not supported and was ignored"),
            );
        }
    }

    // ---- textures

    fn bitmap(&mut self, rel: &str, srgb: bool, loc: Loc) -> R<Arc<Bitmap>> {
        let path =
            resolve_in_folder(&self.files[0], rel, "texture").map_err(|e| self.at(loc, e))?;
        let key = (path.clone(), srgb);
        if let Some(b) = self.bitmaps.get(&key) {
            return Ok(b.clone());
        }
        let bm = Arc::new(Bitmap::load_with(&path, srgb).map_err(|e| self.err(loc, e))?);
        self.bitmaps.insert(key, bm.clone());
        Ok(bm)
    }

    /// `Texture "name" "spectrum"|"float" "class" params`.
    fn texture_directive(&mut self, loc: Loc) -> R<()> {
        let name = self.arg_str("Texture")?;
        let ty = self.arg_str("Texture")?;
        let class = self.arg_str("Texture")?;
        let ps = self.params()?;
        let what = format!("Texture \"{name}\" (\"{class}\")");
        let is_float = match ty.as_str() {
            "float" => true,
            "spectrum" | "color" | "rgb" => false,
            other => {
                return Err(self.err(
                    loc,
                    format!("Texture type must be \"float\" or \"spectrum\", got \"{other}\""),
                ));
            }
        };
        let spec: SpecTex = match class.as_str() {
            "imagemap" => {
                let Some(file) = self.string(&ps, "filename")? else {
                    return Err(self.err(loc, format!("{what} has no \"string filename\"")));
                };
                let lower = file.to_ascii_lowercase();
                let eight_bit = [".png", ".tga", ".jpg", ".jpeg", ".bmp"]
                    .iter()
                    .any(|e| lower.ends_with(e));
                if !eight_bit {
                    return Err(self.err(
                        loc,
                        format!("{what}: '{file}' is not an 8-bit image (PNG, JPEG, TGA, BMP); other formats are not supported"),
                    ));
                }
                // pbrt-v3 decodes PNG and TGA as sRGB unless "gamma" is false.
                let gamma = self.boolean(&ps, "gamma", true)?;
                let image = self.bitmap(&file, gamma, loc)?;
                let scale = self.float(&ps, "scale", 1.0)?;
                if self.boolean(&ps, "invert", false)? {
                    self.warn(
                        loc,
                        format!("{what}: \"invert\" is not supported and was ignored"),
                    );
                }
                let (us, vs) = (
                    self.float(&ps, "uscale", 1.0)?,
                    self.float(&ps, "vscale", 1.0)?,
                );
                let (ud, vd) = (
                    self.float(&ps, "udelta", 0.0)?,
                    self.float(&ps, "vdelta", 0.0)?,
                );
                if us != 1.0 || vs != 1.0 || ud != 0.0 || vd != 0.0 {
                    self.warn(loc, format!("{what}: uv scale/offset is not supported; the texture is mapped with plain uv"));
                }
                if let Some(m) = self.string(&ps, "mapping")?
                    && m != "uv"
                {
                    self.warn(
                        loc,
                        format!("{what}: mapping \"{m}\" is not supported; uv mapping used"),
                    );
                }
                if let Some(w) = self.string(&ps, "wrap")?
                    && w != "repeat"
                {
                    self.warn(
                        loc,
                        format!("{what}: wrap \"{w}\" is not supported; repeat used"),
                    );
                }
                // Filtering does not change the expected value at a point.
                let _ = self.string(&ps, "filter")?;
                let _ = self.float(&ps, "maxanisotropy", 8.0)?;
                let _ = self.boolean(&ps, "trilinear", false)?;
                SpecTex::Ok(Texture::Bitmap {
                    image,
                    scale: Rgb::splat(scale),
                })
            }
            "constant" => {
                if is_float {
                    let v = self.float(&ps, "value", 1.0)?;
                    SpecTex::Ok(Texture::Constant(Rgb::splat(v)))
                } else {
                    SpecTex::Ok(Texture::Constant(self.color(&ps, "value", Rgb::ONE)?))
                }
            }
            "scale" => {
                let a = self.tex_operand(&ps, "tex1", is_float)?;
                let b = self.tex_operand(&ps, "tex2", is_float)?;
                match (a, b) {
                    (Some(Texture::Constant(x)), Some(Texture::Constant(y))) => {
                        SpecTex::Ok(Texture::Constant(x * y))
                    }
                    (Some(Texture::Bitmap { image, scale }), Some(Texture::Constant(y)))
                    | (Some(Texture::Constant(y)), Some(Texture::Bitmap { image, scale })) => {
                        SpecTex::Ok(Texture::Bitmap {
                            image,
                            scale: scale * y,
                        })
                    }
                    _ => SpecTex::Unsupported(class.clone()),
                }
            }
            _ => {
                ps.consume_all();
                SpecTex::Unsupported(class.clone())
            }
        };
        self.report_unused(&ps, &what);
        if is_float {
            let f = match spec {
                SpecTex::Ok(Texture::Constant(c)) => FloatTex::Const(c.x),
                SpecTex::Ok(_) => FloatTex::Unsupported(format!("{class} (float image)")),
                SpecTex::Unsupported(c) => FloatTex::Unsupported(c),
            };
            Rc::make_mut(&mut self.g.float_tex).insert(name, f);
        } else {
            Rc::make_mut(&mut self.g.spec_tex).insert(name, spec);
        }
        Ok(())
    }

    /// An operand of a `scale` texture: a value or a named texture.
    fn tex_operand(&self, ps: &ParamSet, name: &str, is_float: bool) -> R<Option<Texture>> {
        if let Some(t) = self.string_of(ps, name, &["texture"])? {
            return Ok(if is_float {
                match self.g.float_tex.get(&t) {
                    Some(FloatTex::Const(v)) => Some(Texture::Constant(Rgb::splat(*v))),
                    _ => None,
                }
            } else {
                match self.g.spec_tex.get(&t) {
                    Some(SpecTex::Ok(x)) => Some(x.clone()),
                    _ => None,
                }
            });
        }
        if is_float {
            Ok(Some(Texture::Constant(Rgb::splat(
                self.float(ps, name, 1.0)?,
            ))))
        } else {
            Ok(Some(Texture::Constant(self.color(ps, name, Rgb::ONE)?)))
        }
    }

    /// The texture name and place of a `"texture name"` parameter.
    fn texture_ref(&self, ps: &ParamSet, name: &str) -> R<Option<(String, Loc)>> {
        match ps.find(name, &["texture"]) {
            Some(p) => match &p.values {
                Values::Strs(v) if v.len() == 1 => Ok(Some((v[0].clone(), p.loc))),
                _ => Err(self.err(
                    p.loc,
                    format!("parameter \"{}\" expects 1 texture name", p.decl),
                )),
            },
            None => Ok(None),
        }
    }

    /// A spectrum parameter that may be textured (`"texture Kd" "name"`).
    fn spec_texture(&mut self, ps: &ParamSet, name: &str, default: Rgb, what: &str) -> R<Texture> {
        if let Some((tname, loc)) = self.texture_ref(ps, name)? {
            return Ok(match self.g.spec_tex.get(&tname).cloned() {
                Some(SpecTex::Ok(t)) => t,
                Some(SpecTex::Unsupported(class)) => {
                    self.warn(
                        loc,
                        format!("{what}: texture \"{tname}\" of class \"{class}\" is not supported; '{name}' uses its default {default:?}"),
                    );
                    Texture::Constant(default)
                }
                None => {
                    return Err(self.err(loc, format!("{what}: unknown texture \"{tname}\"")));
                }
            });
        }
        Ok(Texture::Constant(self.color(ps, name, default)?))
    }

    /// A spectrum parameter our model takes as a constant: textures become their average.
    fn spec_const(&mut self, ps: &ParamSet, name: &str, default: Rgb, what: &str) -> R<Rgb> {
        let textured = ps
            .params
            .iter()
            .any(|p| p.name == name && p.ty == "texture");
        let loc = ps
            .params
            .iter()
            .rev()
            .find(|p| p.name == name)
            .map_or(self.last_loc, |p| p.loc);
        let t = self.spec_texture(ps, name, default, what)?;
        if textured && let Texture::Bitmap { .. } = t {
            self.warn(
                loc,
                format!("{what}: a texture for '{name}' is not supported; its average is used"),
            );
        }
        Ok(t.average())
    }

    /// A float parameter that may name a float texture (only constant ones are supported).
    fn float_or_tex(&mut self, ps: &ParamSet, name: &str, default: f32, what: &str) -> R<f32> {
        if let Some((tname, loc)) = self.texture_ref(ps, name)? {
            return match self.g.float_tex.get(&tname).cloned() {
                Some(FloatTex::Const(v)) => Ok(v),
                Some(FloatTex::Unsupported(class)) => {
                    self.warn(
                        loc,
                        format!("{what}: float texture \"{tname}\" ({class}) is not supported; '{name}' uses {default}"),
                    );
                    Ok(default)
                }
                None => Err(self.err(loc, format!("{what}: unknown float texture \"{tname}\""))),
            };
        }
        self.float(ps, name, default)
    }

    // ---- materials

    /// (alpha_u, alpha_v) of a microfacet material: `uroughness`/`vroughness` override
    /// `roughness`; with `remaproughness` (default true) pbrt-v3's RoughnessToAlpha applies.
    fn alphas(&mut self, ps: &ParamSet, default: f32, what: &str, loc: Loc) -> R<(f32, f32)> {
        let r = self.float_or_tex(ps, "roughness", default, what)?;
        let u = if ps.has("uroughness") {
            self.float_or_tex(ps, "uroughness", r, what)?
        } else {
            r
        };
        let v = if ps.has("vroughness") {
            self.float_or_tex(ps, "vroughness", r, what)?
        } else {
            r
        };
        if !(u >= 0.0 && v >= 0.0) {
            return Err(self.err(loc, format!("{what}: roughness must be >= 0")));
        }
        let remap = self.boolean(ps, "remaproughness", true)?;
        let (mut au, mut av) = if remap {
            (roughness_to_alpha(u), roughness_to_alpha(v))
        } else {
            (u, v)
        };
        if au < MIN_ALPHA || av < MIN_ALPHA {
            self.warn(
                loc,
                format!("{what}: roughness below {MIN_ALPHA} is traced as GGX alpha {MIN_ALPHA} (near-specular)"),
            );
            au = au.max(MIN_ALPHA);
            av = av.max(MIN_ALPHA);
        }
        Ok((au, av))
    }

    fn isotropic(&mut self, (au, av): (f32, f32), what: &str, loc: Loc) -> f32 {
        if (au - av).abs() > 1e-6 * au.max(av) {
            self.warn(
                loc,
                format!("{what}: anisotropic roughness is not supported by our plastic; alpha sqrt(au av) used"),
            );
        }
        (au * av).sqrt()
    }

    fn default_material(&mut self) -> u32 {
        if let Some(m) = self.default_material {
            return m;
        }
        let m = self.b.add_material(Material::new(
            "pbrt default (matte, Kd 0.5)",
            MaterialKind::Lambert {
                albedo: Texture::Constant(Rgb::splat(0.5)),
            },
            true,
        ));
        self.default_material = Some(m);
        m
    }

    fn current_material(&mut self) -> u32 {
        match self.g.material {
            Some(m) => m,
            None => self.default_material(),
        }
    }

    /// Creates a material of pbrt-v3 type `ty`; returns its builder index.
    fn material(&mut self, ty: &str, ps: &ParamSet, name: &str, loc: Loc) -> R<u32> {
        let what = format!("material \"{name}\" ({ty})");
        if ps.has("bumpmap") {
            ps.find("bumpmap", &["texture", "float"]);
            self.warn(
                loc,
                format!("{what}: bump mapping is not supported and was ignored"),
            );
        }
        let kind = match ty {
            "matte" => {
                let albedo = self.spec_texture(ps, "Kd", Rgb::splat(0.5), &what)?;
                let sigma = self.float_or_tex(ps, "sigma", 0.0, &what)?;
                if sigma != 0.0 {
                    self.warn(
                        loc,
                        format!(
                            "{what}: Oren-Nayar sigma {sigma} is not supported; Lambertian used"
                        ),
                    );
                }
                MaterialKind::Lambert { albedo }
            }
            "plastic" => {
                // pbrt-v3 PlasticMaterial: Lambertian Kd plus a Trowbridge-Reitz (GGX) coat with
                // dielectric Fresnel (eta 1.5), added without energy coupling.
                let diffuse = self.spec_texture(ps, "Kd", Rgb::splat(0.25), &what)?;
                let specular = self.spec_const(ps, "Ks", Rgb::splat(0.25), &what)?;
                let a = self.alphas(ps, 0.1, &what, loc)?;
                let alpha = self.isotropic(a, &what, loc);
                MaterialKind::Plastic {
                    diffuse,
                    specular,
                    ior: 1.5,
                    alpha,
                    layered: false,
                    nonlinear: false,
                }
            }
            "substrate" => {
                // pbrt-v3 SubstrateMaterial is Ashikhmin-Shirley's FresnelBlend: a glossy coat
                // over a diffuse base with energy coupling. Our closest model is the layered
                // plastic (Mitsuba's roughplastic coupling, eta 1.5).
                let diffuse = self.spec_texture(ps, "Kd", Rgb::splat(0.5), &what)?;
                let specular = self.spec_const(ps, "Ks", Rgb::splat(0.5), &what)?;
                let a = self.alphas(ps, 0.1, &what, loc)?;
                let alpha = self.isotropic(a, &what, loc);
                self.warn(
                    loc,
                    "substrate (Ashikhmin-Shirley FresnelBlend) approximated by our layered plastic (ior 1.5, same alpha)",
                );
                MaterialKind::Plastic {
                    diffuse,
                    specular,
                    ior: 1.5,
                    alpha,
                    layered: true,
                    nonlinear: false,
                }
            }
            "metal" => {
                let eta = self.spec_const(ps, "eta", Vec3::from_array(COPPER_ETA), &what)?;
                let k = self.spec_const(ps, "k", Vec3::from_array(COPPER_K), &what)?;
                let (alpha_u, alpha_v) = self.alphas(ps, 0.01, &what, loc)?;
                MaterialKind::RoughConductor {
                    eta,
                    k,
                    alpha_u,
                    alpha_v,
                    scale: Rgb::ONE,
                }
            }
            "mirror" => MaterialKind::Mirror {
                reflectance: self.spec_const(ps, "Kr", Rgb::splat(0.9), &what)?,
            },
            "glass" => {
                let reflectance = self.spec_const(ps, "Kr", Rgb::ONE, &what)?;
                let transmittance = self.spec_const(ps, "Kt", Rgb::ONE, &what)?;
                let ior = self.glass_eta(ps, &what, loc)?;
                let u = self.float_or_tex(ps, "uroughness", 0.0, &what)?;
                let v = self.float_or_tex(ps, "vroughness", 0.0, &what)?;
                let _ = self.boolean(ps, "remaproughness", true)?;
                if u > 0.0 || v > 0.0 {
                    self.warn(
                        loc,
                        format!("{what}: rough glass is not supported; traced as smooth glass"),
                    );
                }
                MaterialKind::Dielectric {
                    ior,
                    reflectance,
                    transmittance,
                }
            }
            "uber" => {
                // pbrt-v3 UberMaterial: Kd Lambertian + Ks GGX coat (Fresnel eta) added, plus
                // specular Kr reflection and Kt transmission, all scaled by opacity.
                let kd = self.spec_texture(ps, "Kd", Rgb::splat(0.25), &what)?;
                let ks = self.spec_const(ps, "Ks", Rgb::splat(0.25), &what)?;
                let kr = self.spec_const(ps, "Kr", Rgb::ZERO, &what)?;
                let kt = self.spec_const(ps, "Kt", Rgb::ZERO, &what)?;
                let ior = self.glass_eta(ps, &what, loc)?;
                let opacity = self.spec_const(ps, "opacity", Rgb::ONE, &what)?;
                let a = self.alphas(ps, 0.1, &what, loc)?;
                if opacity != Rgb::ONE {
                    self.warn(
                        loc,
                        format!("{what}: opacity < 1 is not supported; opaque surface used"),
                    );
                }
                let has_diffuse = kd.max_value() != Rgb::ZERO || ks != Rgb::ZERO;
                if !has_diffuse && (kr != Rgb::ZERO || kt != Rgb::ZERO) {
                    // Only the specular layers: that is pbrt's smooth glass.
                    MaterialKind::Dielectric {
                        ior,
                        reflectance: kr,
                        transmittance: kt,
                    }
                } else {
                    if kr != Rgb::ZERO || kt != Rgb::ZERO {
                        self.warn(
                            loc,
                            format!("{what}: specular Kr/Kt layers together with Kd/Ks are not supported; they were dropped (additive plastic used)"),
                        );
                    }
                    let alpha = self.isotropic(a, &what, loc);
                    MaterialKind::Plastic {
                        diffuse: kd,
                        specular: ks,
                        ior,
                        alpha,
                        layered: false,
                        nonlinear: false,
                    }
                }
            }
            "mix" => {
                ps.consume_all();
                let first = self.string(ps, "namedmaterial1")?;
                if let Some(n) = first
                    && let Some(&m) = self.g.named.get(&n)
                {
                    self.warn(
                        loc,
                        format!(
                            "material \"mix\" is not supported: became its first material \"{n}\""
                        ),
                    );
                    return Ok(m);
                }
                self.warn(
                    loc,
                    "material \"mix\" is not supported: became matte (Kd 0.5)",
                );
                MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::splat(0.5)),
                }
            }
            "" | "none" | "interface" => {
                self.warn(
                    loc,
                    format!("material \"{ty}\" (no surface) is not supported: became an opaque black matte surface"),
                );
                MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::ZERO),
                }
            }
            other => {
                let albedo = self.spec_texture(ps, "Kd", Rgb::splat(0.5), &what)?;
                ps.consume_all();
                self.warn(
                    loc,
                    format!("material \"{other}\" is not supported: became matte with its Kd (default 0.5)"),
                );
                MaterialKind::Lambert { albedo }
            }
        };
        self.report_unused(ps, &what);
        Ok(self.b.add_material(Material::new(name, kind, true)))
    }

    fn glass_eta(&mut self, ps: &ParamSet, what: &str, loc: Loc) -> R<f32> {
        // pbrt-v3 reads "eta", falling back to the older "index".
        let eta = if ps.has("eta") {
            self.float_or_tex(ps, "eta", 1.5, what)?
        } else {
            self.float_or_tex(ps, "index", 1.5, what)?
        };
        if !(eta > 0.0 && eta.is_finite()) {
            return Err(self.err(
                loc,
                format!("{what}: index of refraction must be > 0, got {eta}"),
            ));
        }
        Ok(eta)
    }

    // ---- shapes

    fn shape_directive(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("Shape")?;
        let params = self.params()?;
        if !self.in_world {
            return Err(self.err(loc, "Shape outside WorldBegin/WorldEnd"));
        }
        let material = self.current_material();
        if let Some((_, calls)) = &mut self.defining {
            calls.push(ShapeCall {
                ty,
                params,
                ctm: self.g.ctm,
                material,
                reverse: self.g.reverse,
                loc,
            });
            if self.g.area.is_some() {
                self.warn(loc, "area lights inside object instances are not supported (as in pbrt-v3); the shape does not emit");
            }
            return Ok(());
        }
        let call = ShapeCall {
            ty,
            params,
            ctm: self.g.ctm,
            material,
            reverse: self.g.reverse,
            loc,
        };
        let emission = self.g.area;
        self.emit_shape(&call, Mat4::IDENTITY, emission)
    }

    /// Adds one shape, placed by `outer * call.ctm`.
    fn emit_shape(&mut self, call: &ShapeCall, outer: Mat4, emission: Option<Rgb>) -> R<()> {
        let ps = &call.params;
        let loc = call.loc;
        let what = format!("Shape \"{}\"", call.ty);
        let m = outer * call.ctm;
        let t = Transform::new(m).ok_or_else(|| {
            self.err(
                loc,
                format!("{what}: the transform is singular or not finite"),
            )
        })?;
        let mut place = if loc.file == 0 {
            format!("line {}", loc.line)
        } else {
            format!(
                "{} line {}",
                self.files[loc.file as usize].display(),
                loc.line
            )
        };
        let mesh = match call.ty.as_str() {
            "trianglemesh" => {
                let p = self
                    .vec3s(ps, "P", &["point3"])?
                    .ok_or_else(|| self.err(loc, "trianglemesh has no \"point P\""))?;
                let idx = match self.ints(ps, "indices")? {
                    Some(i) => i,
                    None if p.len() == 3 => vec![0, 1, 2],
                    None => {
                        return Err(self.err(loc, "trianglemesh has no \"integer indices\" (only allowed for exactly 3 vertices)"));
                    }
                };
                if idx.len() % 3 != 0 {
                    return Err(self.err(
                        loc,
                        format!("trianglemesh: {} indices, not a multiple of 3", idx.len()),
                    ));
                }
                if let Some(&bad) = idx.iter().find(|&&i| i < 0 || i as usize >= p.len()) {
                    return Err(self.err(
                        loc,
                        format!(
                            "trianglemesh: index {bad} out of range for {} vertices",
                            p.len()
                        ),
                    ));
                }
                let normals = self.vec3s(ps, "N", &["normal3"])?.unwrap_or_default();
                if !normals.is_empty() && normals.len() != p.len() {
                    return Err(self.err(
                        loc,
                        format!(
                            "trianglemesh: {} normals for {} vertices",
                            normals.len(),
                            p.len()
                        ),
                    ));
                }
                let uv_param = ["uv", "st"]
                    .into_iter()
                    .find_map(|n| ps.find(n, &["float", "point2"]));
                let uvs: Vec<Vec2> = match uv_param {
                    Some(param) => {
                        let v = self.nums(param)?;
                        if v.len() != 2 * p.len() {
                            return Err(self.err(
                                param.loc,
                                format!(
                                    "trianglemesh: {} uv values for {} vertices",
                                    v.len(),
                                    p.len()
                                ),
                            ));
                        }
                        v.chunks_exact(2)
                            .map(|c| Vec2::new(c[0] as f32, c[1] as f32))
                            .collect()
                    }
                    None => Vec::new(),
                };
                MeshData {
                    positions: p,
                    normals,
                    uvs,
                    indices: idx
                        .chunks_exact(3)
                        .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
                        .collect(),
                }
            }
            "plymesh" => {
                let Some(file) = self.string(ps, "filename")? else {
                    return Err(self.err(loc, "plymesh has no \"string filename\""));
                };
                let path = resolve_in_folder(&self.files[0], &file, "plymesh")
                    .map_err(|e| self.at(loc, e))?;
                // Errors in the mesh's data name its file.
                place = format!("{place} ({})", path.display());
                load_ply(&path).map_err(|e| self.err(loc, format!("{}: {e}", path.display())))?
            }
            "sphere" => {
                let radius = self.float(ps, "radius", 1.0)?;
                let zmin = self.float(ps, "zmin", -radius)?;
                let zmax = self.float(ps, "zmax", radius)?;
                let phimax = self.float(ps, "phimax", 360.0)?;
                if zmin > -radius || zmax < radius || phimax < 360.0 {
                    return Err(self.err(
                        loc,
                        "partial spheres (zmin, zmax, phimax) are not supported",
                    ));
                }
                if !(radius > 0.0 && radius.is_finite()) {
                    return Err(self.err(loc, format!("sphere radius must be > 0, got {radius}")));
                }
                let center = t.point(Vec3::ZERO);
                let scale = uniform_scale(&m).ok_or_else(|| {
                    self.err(
                        loc,
                        "a sphere under non-uniform scale or shear is not supported",
                    )
                })?;
                // pbrt-v3 flips the normal when reverseOrientation ^ transformSwapsHandedness.
                let inward = call.reverse ^ t.swaps_handedness();
                self.report_unused(ps, &what);
                return self.b.add_sphere(
                    center,
                    radius * scale,
                    inward,
                    call.material,
                    emission,
                    &place,
                );
            }
            other => {
                return Err(self.err(
                    loc,
                    format!("Shape \"{other}\" is not supported (supported: trianglemesh, plymesh, sphere)"),
                ));
            }
        };
        if ps.has("alpha") || ps.has("shadowalpha") {
            ps.find("alpha", &["float", "texture"]);
            ps.find("shadowalpha", &["float", "texture"]);
            self.warn(
                loc,
                format!("{what}: alpha cut-outs are not supported; the surface is opaque"),
            );
        }
        self.report_unused(ps, &what);
        let mut mesh = mesh;
        // Without vertex normals pbrt-v3 orients a triangle by its winding, flipped when
        // reverseOrientation ^ transformSwapsHandedness; with vertex normals the geometric normal
        // follows them (our builder does the same), and ReverseOrientation has no effect.
        if mesh.normals.is_empty() && (call.reverse ^ t.swaps_handedness()) {
            for tri in &mut mesh.indices {
                tri.swap(1, 2);
            }
        }
        if let Some(e) = emission
            && e != Rgb::ZERO
            && mesh.indices.is_empty()
        {
            self.warn(loc, format!("{what}: emitting mesh has no triangles"));
        }
        self.b.add_mesh(&mesh, &t, call.material, emission, &place)
    }

    // ---- lights

    fn area_light_directive(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("AreaLightSource")?;
        let ps = self.params()?;
        if ty != "diffuse" {
            return Err(self.err(
                loc,
                format!("AreaLightSource \"{ty}\" is not supported (only \"diffuse\")"),
            ));
        }
        let l = self.color(&ps, "L", Rgb::ONE)?;
        let scale = self.color(&ps, "scale", Rgb::ONE)?;
        if self.boolean(&ps, "twosided", false)? {
            self.warn(
                loc,
                "AreaLightSource \"diffuse\": twosided is not supported; the light emits on the front side only (half the power of pbrt's)",
            );
        }
        let _ = self.int(&ps, "samples", 1)?; // sample count: no effect on the expected image
        self.report_unused(&ps, "AreaLightSource \"diffuse\"");
        self.g.area = Some(l * scale);
        Ok(())
    }

    fn light_directive(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("LightSource")?;
        let ps = self.params()?;
        match ty.as_str() {
            "point" => {
                let i = self.color(&ps, "I", Rgb::ONE)?;
                let scale = self.color(&ps, "scale", Rgb::ONE)?;
                let from = self
                    .vec3s(&ps, "from", &["point3"])?
                    .map(|v| v.first().copied().unwrap_or(Vec3::ZERO))
                    .unwrap_or(Vec3::ZERO);
                let pos = self.g.ctm.transform_point3(from);
                self.report_unused(&ps, "LightSource \"point\"");
                if self.defining.is_some() {
                    self.warn(loc, "lights inside object definitions are ignored (as in pbrt-v3)");
                    return Ok(());
                }
                self.b
                    .add_point_light(pos, i * scale, &format!("line {}", loc.line))
                    .map_err(|e| self.at(loc, e))
            }
            other => Err(self.err(
                loc,
                format!("LightSource \"{other}\" is not supported (only \"point\" lights and \"diffuse\" area lights)"),
            )),
        }
    }

    // ---- camera

    fn build_camera(&mut self) -> R<()> {
        let (w, h) = self.resolution;
        let def = self.camera.take().unwrap_or(CameraDef {
            ty: "perspective".into(),
            params: ParamSet::default(),
            world_to_camera: Mat4::IDENTITY,
            loc: self.last_loc,
        });
        let loc = def.loc;
        if def.ty != "perspective" {
            return Err(self.err(
                loc,
                format!(
                    "Camera \"{}\" is not supported (only \"perspective\")",
                    def.ty
                ),
            ));
        }
        let ps = &def.params;
        let mut fov = self.float(ps, "fov", 90.0)?;
        if let Some(half) = self.opt_float(ps, "halffov")?
            && half > 0.0
        {
            fov = 2.0 * half;
        }
        if let Some(lr) = self.opt_float(ps, "lensradius")?
            && lr > 0.0
        {
            self.warn(
                loc,
                "Camera: depth of field (lensradius > 0) is not supported; pinhole used",
            );
        }
        let _ = self.opt_float(ps, "focaldistance")?;
        if ps.has("screenwindow") || ps.has("frameaspectratio") {
            ps.find("screenwindow", &["float"]);
            ps.find("frameaspectratio", &["float"]);
            self.warn(loc, "Camera: screenwindow / frameaspectratio are not supported; the window follows the resolution");
        }
        let _ = self.opt_float(ps, "shutteropen")?;
        let _ = self.opt_float(ps, "shutterclose")?;
        self.report_unused(ps, "Camera \"perspective\"");
        if !(fov > 0.0 && fov < 179.0) {
            return Err(self.err(
                loc,
                format!("Camera fov must be in (0, 179) degrees, got {fov}"),
            ));
        }
        // pbrt's fov spans the shorter image axis; ours is vertical.
        let vfov = if w >= h {
            fov
        } else {
            2.0 * ((0.5 * fov.to_radians()).tan() * h as f32 / w as f32)
                .atan()
                .to_degrees()
        };
        let c2w = Transform::new(def.world_to_camera)
            .ok_or_else(|| self.err(loc, "the camera transform is singular or not finite"))?;
        let c2w = Transform {
            m: c2w.inv,
            inv: c2w.m,
        };
        let position = c2w.point(Vec3::ZERO);
        let forward = c2w.vector(Vec3::Z).normalize_or_zero();
        let up = c2w.vector(Vec3::Y);
        let right_pbrt = c2w.vector(Vec3::X);
        let cam = Camera::new(position, position + forward, up, vfov, w, h)
            .map_err(|m| self.err(loc, format!("Camera: {m}")))?;
        // pbrt's raster x runs along camera +x; ours along forward x up. Mirror when they differ.
        let flip = right_pbrt.dot(cam.right()) < 0.0;
        self.b.set_camera(cam.with_flip_x(flip));
        Ok(())
    }

    // ---- the directive loop

    fn apply_transform(&mut self, m: Mat4, set: bool, loc: Loc) {
        if !self.active.0 {
            self.warn(loc, "ActiveTransform EndTime: motion blur is not supported; end-time transforms were ignored");
            return;
        }
        self.g.ctm = if set { m } else { self.g.ctm * m };
    }

    fn run(&mut self) -> R<()> {
        while let Some(t) = self.next() {
            let loc = t.loc;
            let name = match t.tok {
                Tok::Word(w) => w,
                other => {
                    return Err(self.err(
                        loc,
                        format!("expected a directive, found {}", describe(&other)),
                    ));
                }
            };
            if self.world_ended {
                self.warn(loc, "content after WorldEnd is ignored");
                // Skip the rest: pbrt-v3 would render and start over.
                while self.next().is_some() {}
                break;
            }
            self.directive(&name, loc)?;
        }
        if let Some(Frame::Attribute(_, l) | Frame::Transform(_, l)) = self.stack.last() {
            let l = *l;
            self.warn(l, "AttributeBegin/TransformBegin without a matching End");
        }
        if !self.in_world && !self.world_ended {
            return Err(self.err(self.last_loc, "the file has no WorldBegin"));
        }
        if !self.world_ended {
            self.warn(self.last_loc, "the file ended without WorldEnd");
        }
        Ok(())
    }

    fn options_only(&self, name: &str, loc: Loc) -> R<()> {
        if self.in_world {
            return Err(self.err(loc, format!("{name} is only allowed before WorldBegin")));
        }
        Ok(())
    }

    fn world_only(&self, name: &str, loc: Loc) -> R<()> {
        if !self.in_world {
            return Err(self.err(
                loc,
                format!("{name} is only allowed between WorldBegin and WorldEnd"),
            ));
        }
        Ok(())
    }

    fn directive(&mut self, name: &str, loc: Loc) -> R<()> {
        match name {
            // -- transforms
            "Identity" => self.apply_transform(Mat4::IDENTITY, true, loc),
            "Translate" => {
                let v = self.arg_nums(name, 3, loc)?;
                self.apply_transform(
                    Mat4::from_translation(Vec3::new(v[0], v[1], v[2])),
                    false,
                    loc,
                );
            }
            "Scale" => {
                let v = self.arg_nums(name, 3, loc)?;
                self.apply_transform(Mat4::from_scale(Vec3::new(v[0], v[1], v[2])), false, loc);
            }
            "Rotate" => {
                let v = self.arg_nums(name, 4, loc)?;
                let axis = Vec3::new(v[1], v[2], v[3]).normalize_or_zero();
                if axis == Vec3::ZERO {
                    return Err(self.err(loc, "Rotate: the axis is zero"));
                }
                self.apply_transform(Mat4::from_axis_angle(axis, v[0].to_radians()), false, loc);
            }
            "LookAt" => {
                let v = self.arg_nums(name, 9, loc)?;
                let m = look_at(
                    Vec3::new(v[0], v[1], v[2]),
                    Vec3::new(v[3], v[4], v[5]),
                    Vec3::new(v[6], v[7], v[8]),
                )
                .ok_or_else(|| {
                    self.err(
                        loc,
                        "LookAt: eye equals look point, or up is parallel to the view direction",
                    )
                })?;
                self.apply_transform(m, false, loc);
            }
            "Transform" | "ConcatTransform" => {
                let v = self.arg_nums(name, 16, loc)?;
                let mut a = [0f32; 16];
                a.copy_from_slice(&v);
                // The 16 numbers are the matrix column by column (pbrt-v3 transposes them).
                let m = Mat4::from_cols_array(&a);
                if !m.is_finite() {
                    return Err(self.err(loc, format!("{name}: matrix is not finite")));
                }
                self.apply_transform(m, name == "Transform", loc);
            }
            "CoordinateSystem" => {
                let n = self.arg_str(name)?;
                self.named_coords.insert(n, self.g.ctm);
            }
            "CoordSysTransform" => {
                let n = self.arg_str(name)?;
                match self.named_coords.get(&n) {
                    Some(&m) => self.apply_transform(m, true, loc),
                    None => self.warn(loc, format!("CoordSysTransform: unknown coordinate system \"{n}\" (ignored, as pbrt-v3 does)")),
                }
            }
            "ActiveTransform" => {
                let which = match self.next() {
                    Some(Token {
                        tok: Tok::Word(w), ..
                    }) => w,
                    _ => {
                        return Err(
                            self.err(loc, "ActiveTransform expects StartTime, EndTime or All")
                        );
                    }
                };
                self.active = match which.as_str() {
                    "StartTime" => (true, false),
                    "EndTime" => (false, true),
                    "All" => (true, true),
                    other => {
                        return Err(self.err(
                            loc,
                            format!(
                                "ActiveTransform expects StartTime, EndTime or All, got {other}"
                            ),
                        ));
                    }
                };
            }
            "TransformTimes" => {
                // Shutter interval of animated transforms: only the start transform is kept.
                self.arg_nums(name, 2, loc)?;
            }
            "ReverseOrientation" => self.g.reverse = !self.g.reverse,

            // -- block structure
            "AttributeBegin" => {
                self.stack
                    .push(Frame::Attribute(Box::new(self.g.clone()), loc));
            }
            "AttributeEnd" => match self.stack.pop() {
                Some(Frame::Attribute(g, _)) => self.g = *g,
                Some(Frame::Transform(_, l)) => {
                    return Err(self.err(
                        loc,
                        format!("AttributeEnd closes the TransformBegin of line {}", l.line),
                    ));
                }
                None => return Err(self.err(loc, "AttributeEnd without AttributeBegin")),
            },
            "TransformBegin" => self.stack.push(Frame::Transform(self.g.ctm, loc)),
            "TransformEnd" => match self.stack.pop() {
                Some(Frame::Transform(m, _)) => self.g.ctm = m,
                Some(Frame::Attribute(_, l)) => {
                    return Err(self.err(
                        loc,
                        format!("TransformEnd closes the AttributeBegin of line {}", l.line),
                    ));
                }
                None => return Err(self.err(loc, "TransformEnd without TransformBegin")),
            },
            "WorldBegin" => {
                self.options_only(name, loc)?;
                if !self.stack.is_empty() {
                    return Err(self.err(loc, "WorldBegin inside AttributeBegin/TransformBegin"));
                }
                self.build_camera()?;
                self.in_world = true;
                self.g.ctm = Mat4::IDENTITY;
                self.named_coords.insert("world".into(), Mat4::IDENTITY);
            }
            "WorldEnd" => {
                self.world_only(name, loc)?;
                if let Some(Frame::Attribute(_, l) | Frame::Transform(_, l)) = self.stack.last() {
                    let l = *l;
                    self.warn(
                        l,
                        "AttributeBegin/TransformBegin not closed before WorldEnd",
                    );
                }
                if self.defining.is_some() {
                    return Err(self.err(loc, "WorldEnd inside ObjectBegin"));
                }
                self.in_world = false;
                self.world_ended = true;
            }
            "Include" => {
                let rel = self.arg_str(name)?;
                if self.sources.len() > MAX_INCLUDE_DEPTH {
                    return Err(self.err(
                        loc,
                        format!("Include nested deeper than {MAX_INCLUDE_DEPTH} (a cycle?)"),
                    ));
                }
                let path = resolve_in_folder(&self.files[0], &rel, "Include")
                    .map_err(|e| self.at(loc, e))?;
                let text = std::fs::read_to_string(&path)
                    .map_err(|e| self.err(loc, format!("Include \"{rel}\": cannot read: {e}")))?;
                let idx = self.files.len();
                if idx > u16::MAX as usize {
                    return Err(self.err(loc, "too many included files"));
                }
                self.files.push(path.clone());
                let tokens = tokenize(&text, idx as u16, &path)?;
                self.sources.push(Source { tokens, pos: 0 });
            }

            // -- rendering options
            "Camera" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let params = self.params()?;
                // pbrt-v3 names the camera's coordinate system "camera" (camera-to-world).
                if let Some(inv) = Transform::new(self.g.ctm) {
                    self.named_coords.insert("camera".into(), inv.inv);
                }
                self.camera = Some(CameraDef {
                    ty,
                    params,
                    world_to_camera: self.g.ctm,
                    loc,
                });
            }
            "Film" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                if ty != "image" {
                    self.warn(loc, format!("Film \"{ty}\" treated as \"image\""));
                }
                let w = self.int(&ps, "xresolution", 640)?;
                let h = self.int(&ps, "yresolution", 480)?;
                if !(1..=65536).contains(&w) || !(1..=65536).contains(&h) {
                    return Err(self.err(
                        loc,
                        format!("Film resolution must be 1..65536, got {w}x{h}"),
                    ));
                }
                self.resolution = (w as u32, h as u32);
                let _ = self.string(&ps, "filename")?; // output name: ours comes from the command line
                let _ = self.opt_float(&ps, "diagonal")?; // physical film size: no effect on a pinhole
                if let Some(s) = self.opt_float(&ps, "scale")?
                    && s != 1.0
                {
                    self.warn(
                        loc,
                        format!("Film \"scale\" {s} is not supported; pixel values are unscaled"),
                    );
                }
                let _ = self.opt_float(&ps, "maxsampleluminance")?;
                self.report_unused(&ps, "Film");
            }
            "Sampler" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                // The sampler type does not change the expected image; only its sample count
                // becomes our default spp.
                let spp = if ty == "stratified" {
                    self.int(&ps, "xsamples", 4)? * self.int(&ps, "ysamples", 4)?
                } else {
                    self.int(&ps, "pixelsamples", 16)?
                };
                if spp < 1 {
                    return Err(self.err(
                        loc,
                        format!("Sampler: sample count must be >= 1, got {spp}"),
                    ));
                }
                self.b.defaults.spp = Some(spp.min(u32::MAX as i64) as u32);
                let _ = self.boolean(&ps, "jitter", true)?;
                let _ = self.int(&ps, "dimensions", 4)?;
                self.report_unused(&ps, &format!("Sampler \"{ty}\""));
            }
            "PixelFilter" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                ps.consume_all();
                if ty != "box" {
                    self.warn(
                        loc,
                        format!("PixelFilter \"{ty}\" is not supported; box filter used"),
                    );
                } else {
                    let xw = self.float(&ps, "xwidth", 0.5)?;
                    let yw = self.float(&ps, "ywidth", 0.5)?;
                    if xw != 0.5 || yw != 0.5 {
                        self.warn(loc, "PixelFilter \"box\": widths other than 0.5 are not supported; one-pixel box used");
                    }
                }
            }
            "Integrator" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                let depth = self.int(&ps, "maxdepth", 5)?;
                if depth < 0 {
                    return Err(self.err(
                        loc,
                        format!("Integrator: maxdepth must be >= 0, got {depth}"),
                    ));
                }
                self.b.defaults.max_depth = Some(depth.min(u32::MAX as i64) as u32);
                match ty.as_str() {
                    "path" | "volpath" | "bdpt" | "mlt" | "sppm" => {
                        if ty != "path" {
                            self.warn(loc, format!("Integrator \"{ty}\" rendered with our path tracer (the same expected image)"));
                        }
                    }
                    other => self.warn(
                        loc,
                        format!("Integrator \"{other}\" is not supported; our path tracer renders full global illumination up to maxdepth"),
                    ),
                }
                // Russian roulette and light selection do not change the expected image.
                let _ = self.opt_float(&ps, "rrthreshold")?;
                let _ = self.string(&ps, "lightsamplestrategy")?;
                if ps.has("pixelbounds") {
                    ps.find("pixelbounds", &["integer"]);
                    self.warn(
                        loc,
                        "Integrator \"pixelbounds\" is not supported; the whole image is rendered",
                    );
                }
                self.report_unused(&ps, &format!("Integrator \"{ty}\""));
            }
            "Accelerator" => {
                // The acceleration structure does not change the image.
                self.arg_str(name)?;
                self.params()?.consume_all();
            }

            // -- materials and textures
            "Material" => {
                self.world_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                let m = self.material(&ty, &ps, &format!("{ty} (line {})", loc.line), loc)?;
                self.g.material = Some(m);
            }
            "MakeNamedMaterial" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                let ps = self.params()?;
                let Some(ty) = self.string(&ps, "type")? else {
                    return Err(self.err(
                        loc,
                        format!("MakeNamedMaterial \"{n}\" has no \"string type\""),
                    ));
                };
                let m = self.material(&ty, &ps, &n, loc)?;
                Rc::make_mut(&mut self.g.named).insert(n, m);
            }
            "NamedMaterial" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                match self.g.named.get(&n) {
                    Some(&m) => self.g.material = Some(m),
                    None => {
                        return Err(
                            self.err(loc, format!("NamedMaterial: unknown material \"{n}\""))
                        );
                    }
                }
            }
            "Texture" => {
                self.world_only(name, loc)?;
                self.texture_directive(loc)?;
            }

            // -- shapes and lights
            "Shape" => self.shape_directive(loc)?,
            "AreaLightSource" => {
                self.world_only(name, loc)?;
                self.area_light_directive(loc)?;
            }
            "LightSource" => {
                self.world_only(name, loc)?;
                self.light_directive(loc)?;
            }

            // -- instancing (flattened)
            "ObjectBegin" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                if self.defining.is_some() {
                    return Err(self.err(loc, "ObjectBegin inside ObjectBegin"));
                }
                // pbrt-v3: ObjectBegin implies AttributeBegin.
                self.stack
                    .push(Frame::Attribute(Box::new(self.g.clone()), loc));
                self.defining = Some((n, Vec::new()));
            }
            "ObjectEnd" => {
                let Some((n, calls)) = self.defining.take() else {
                    return Err(self.err(loc, "ObjectEnd without ObjectBegin"));
                };
                self.objects.insert(n, calls);
                match self.stack.pop() {
                    Some(Frame::Attribute(g, _)) => self.g = *g,
                    _ => return Err(self.err(loc, "ObjectEnd does not match its ObjectBegin")),
                }
            }
            "ObjectInstance" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                if self.defining.is_some() {
                    return Err(self.err(loc, "ObjectInstance inside ObjectBegin is not supported"));
                }
                let Some(calls) = self.objects.get(&n).cloned() else {
                    return Err(self.err(loc, format!("ObjectInstance: unknown object \"{n}\"")));
                };
                let outer = self.g.ctm;
                for c in &calls {
                    self.emit_shape(c, outer, None)?;
                }
            }

            // -- media
            "MakeNamedMedium" => {
                let n = self.arg_str(name)?;
                self.params()?.consume_all();
                self.warn(
                    loc,
                    format!("participating media are not supported; medium \"{n}\" ignored"),
                );
            }
            "MediumInterface" => {
                let a = self.arg_str(name)?;
                let b = if matches!(
                    self.peek(),
                    Some(Token {
                        tok: Tok::Str(_),
                        ..
                    })
                ) {
                    self.arg_str(name)?
                } else {
                    a.clone()
                };
                if !a.is_empty() || !b.is_empty() {
                    self.warn(
                        loc,
                        "participating media are not supported; MediumInterface ignored",
                    );
                }
            }
            other => {
                let hint = match other {
                    "ColorSpace"
                    | "Option"
                    | "Attribute"
                    | "Import"
                    | "MakeNamedMaterialInstance" => {
                        " (a pbrt-v4 directive; this is a pbrt-v3 importer)"
                    }
                    _ => "",
                };
                return Err(self.err(loc, format!("unknown directive '{other}'{hint}")));
            }
        }
        Ok(())
    }
}

/// pbrt-v3 `LookAt`: the world-to-camera matrix of a camera at `eye` looking at `at`, with
/// camera-to-world columns (up x dir, dir x right, dir, eye).
fn look_at(eye: Vec3, at: Vec3, up: Vec3) -> Option<Mat4> {
    let dir = (at - eye).normalize_or_zero();
    let right = up.normalize_or_zero().cross(dir).normalize_or_zero();
    if dir == Vec3::ZERO || right == Vec3::ZERO || !eye.is_finite() {
        return None;
    }
    let new_up = dir.cross(right);
    let c2w = Mat4::from_cols(
        right.extend(0.0),
        new_up.extend(0.0),
        dir.extend(0.0),
        eye.extend(1.0),
    );
    Some(c2w.inverse())
}

/// The uniform scale factor of an affine matrix without shear, or `None`.
pub(crate) fn uniform_scale(m: &Mat4) -> Option<f32> {
    let x = m.x_axis.truncate();
    let y = m.y_axis.truncate();
    let z = m.z_axis.truncate();
    let (a, b, c) = (x.length(), y.length(), z.length());
    let s = (a + b + c) / 3.0;
    let tol = 1e-4 * s;
    let ortho = x.dot(y).abs() <= tol * s && y.dot(z).abs() <= tol * s && x.dot(z).abs() <= tol * s;
    if s > 0.0 && (a - s).abs() <= tol && (b - s).abs() <= tol && (c - s).abs() <= tol && ortho {
        Some(s)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roughness_remap_matches_pbrt() {
        // Values of pbrt-v3's RoughnessToAlpha.
        assert!((roughness_to_alpha(1.0) - 1.62142).abs() < 1e-5);
        let a = roughness_to_alpha(0.1);
        assert!(a > 0.1 && a < 0.5, "{a}");
        assert_eq!(roughness_to_alpha(0.0), roughness_to_alpha(1e-3));
    }

    #[test]
    fn tokens_carry_lines_and_kinds() {
        let t = tokenize(
            "Shape \"sphere\" # c\n  \"float radius\" [ 2.5 ]\n-1e-3",
            0,
            Path::new("x.pbrt"),
        )
        .unwrap();
        let kinds: Vec<&Tok> = t.iter().map(|t| &t.tok).collect();
        assert_eq!(
            kinds,
            vec![
                &Tok::Word("Shape".into()),
                &Tok::Str("sphere".into()),
                &Tok::Str("float radius".into()),
                &Tok::Open,
                &Tok::Num(2.5),
                &Tok::Close,
                &Tok::Num(-1e-3),
            ]
        );
        assert_eq!(
            t.iter().map(|t| t.loc.line).collect::<Vec<_>>(),
            vec![1, 1, 2, 2, 2, 2, 3]
        );
        let e = tokenize("Shape\n\n 1.2.3", 0, Path::new("x.pbrt")).unwrap_err();
        assert_eq!(e.location, "line 3");
        assert!(tokenize("\"open", 0, Path::new("x.pbrt")).is_err());
    }

    #[test]
    fn look_at_is_pbrts() {
        // pbrt-v3: camera +x = normalize(up x dir).
        let w2c = look_at(Vec3::ZERO, Vec3::Z, Vec3::Y).unwrap();
        let c2w = w2c.inverse();
        assert!((c2w.transform_vector3(Vec3::X) - Vec3::X).length() < 1e-6);
        assert!((c2w.transform_vector3(Vec3::Z) - Vec3::Z).length() < 1e-6);
        assert!(uniform_scale(&Mat4::from_scale(Vec3::splat(2.0))).is_some());
        assert!(uniform_scale(&Mat4::from_scale(Vec3::new(1.0, 2.0, 1.0))).is_none());
    }
}
