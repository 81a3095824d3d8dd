//! pbrt-v3 scene importer: a tokenizer whose tokens carry file and line (`lexer`), parameter
//! lists (`params`), and a parser for the subset of the format that maps onto our scene model
//! (see `scenes/README.md`, "Importers"): camera and options, materials, textures, shapes,
//! lights, one module each. pbrt-v4 files, which share the extension, are told from their
//! contents (`dialect`): from the first file (the scene or an included one) with a construct
//! only pbrt-v4 has, the directives are read as pbrt-v4 reads them (`v4/`); a file without
//! any goes through the pbrt-v3 path unchanged.
//!
//! Conventions of pbrt-v3 that matter here (Pharr, Jakob, Humphreys, *Physically Based
//! Rendering*, 3rd ed., and the pbrt-v3 sources):
//! - `Transform` and `ConcatTransform` give a 4x4 matrix column by column (pbrt transposes the
//!   16 numbers it reads); every other transform directive post-multiplies the current
//!   transformation matrix (CTM).
//! - At `Camera` the CTM is world-to-camera. Camera space is left-handed: x right, y up, z
//!   forward. Our camera is right-handed (right = forward x up), so when the camera-to-world
//!   transform maps x to `up x forward` (a proper rotation, e.g. from `LookAt`) we mirror raster x
//!   ([`crate::camera::Camera::with_flip_x`]); exporters that write a reflection (Tungsten/Bitterli files,
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

mod camera;
mod dialect;
mod lexer;
mod lights;
mod materials;
mod params;
mod shapes;
mod textures;
mod v4;

pub use materials::roughness_to_alpha;

use super::common::{Bitmaps, Warnings};
use super::resolve::Resolver;
use crate::geometry::{Mat4, Rgb, Vec3};
use crate::scene::{SceneBuilder, SceneError};
use camera::{CameraDef, look_at};
use lexer::{Loc, Tok, Token, describe, tokenize};
use shapes::ShapeCall;
use std::collections::HashMap;
use std::path::PathBuf;
use std::rc::Rc;
use textures::{FloatTex, SpecTex};

/// Nesting limit for `Include` (guards against include cycles).
const MAX_INCLUDE_DEPTH: usize = 16;

// ------------------------------------------------------------------------------------------
// Graphics state.

/// What `AttributeBegin` saves and `AttributeEnd` restores.
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
    /// pbrt-v4 only: the `power` of the current `AreaLightSource` and its `twosided` (the
    /// radiance is scaled to that power once the shape's area is known).
    area_power: Option<(f32, bool)>,
    /// pbrt-v4 only: `Attribute` defaults by target (`shape`, `light`, `material`, ...).
    attributes: Rc<HashMap<String, params::ParamSet>>,
}

enum Frame {
    Attribute(Box<GState>, Loc),
    Transform(Mat4, Loc),
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
    bitmaps: Bitmaps,
    default_material: Option<u32>,
    objects: HashMap<String, Vec<ShapeCall>>,
    defining: Option<(String, Vec<ShapeCall>)>,
    /// `ActiveTransform`: whether transform directives update the start / end transform.
    active: (bool, bool),
    last_loc: Loc,
    /// Read as pbrt-v4: set by the first file with a pbrt-v4 construct (`dialect`).
    v4: bool,
    /// pbrt-v4: what the scene needs and we cannot render, (place, reason), reported together.
    refused: Vec<(Loc, String)>,
    /// pbrt-v4: an `infinite` light was read (our sky has one dome).
    environment_seen: bool,
    /// pbrt-v4: a `PixelFilter` was read (its default is a Gaussian, not our box).
    filter_seen: bool,
}

type R<T> = Result<T, SceneError>;

/// Parses pbrt-v3 or pbrt-v4 text, reading the files it names through `resolver`.
pub(crate) fn parse_with(text: &str, resolver: Resolver) -> Result<SceneBuilder, SceneError> {
    let file = resolver.scene_file().to_path_buf();
    let tokens = tokenize(text, 0, &file)?;
    let v4 = is_v4(&tokens);
    let mut p = Parser {
        files: vec![file],
        sources: vec![Source { tokens, pos: 0 }],
        b: SceneBuilder::new(resolver),
        warn: Warnings::default(),
        g: GState {
            ctm: Mat4::IDENTITY,
            material: None,
            area: None,
            reverse: false,
            named: Rc::default(),
            float_tex: Rc::default(),
            spec_tex: Rc::default(),
            area_power: None,
            attributes: Rc::default(),
        },
        stack: Vec::new(),
        in_world: false,
        world_ended: false,
        camera: None,
        resolution: (640, 480),
        named_coords: HashMap::new(),
        bitmaps: Bitmaps::default(),
        default_material: None,
        objects: HashMap::new(),
        defining: None,
        active: (true, true),
        last_loc: Loc { file: 0, line: 1 },
        v4,
        refused: Vec::new(),
        environment_seen: false,
        filter_seen: false,
    };
    // pbrt-v4's film is 1280 x 720 unless the file says otherwise.
    if v4 {
        p.resolution = (1280, 720);
    }
    // pbrt-v3's (and pbrt-v4's) defaults when the file names no Integrator / Sampler: path,
    // maxdepth 5; 16 spp.
    p.b.defaults.max_depth = Some(5);
    p.b.defaults.spp = Some(16);
    p.run()?;
    p.refuse_collected()?;
    let Parser { mut b, warn, .. } = p;
    warn.flush(&mut b);
    Ok(b)
}

/// Whether `tokens` have a construct only pbrt-v4 has (see `dialect`).
fn is_v4(tokens: &[Token]) -> bool {
    !dialect::v4_constructs(tokens, 1).0.is_empty()
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
            if self.world_ended && !self.v4 {
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
        // pbrt-v4 has no WorldEnd: its scenes end with the file.
        if !self.world_ended && !self.v4 {
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
        if self.v4 && self.v4_directive(name, loc)? {
            return Ok(());
        }
        if name == "Shape" {
            return self.shape(loc);
        }
        let handled = self.transform_directive(name, loc)?
            || self.block_directive(name, loc)?
            || self.option_directive(name, loc)?
            || self.material_directive(name, loc)?
            || self.light_directive(name, loc)?
            || self.object_directive(name, loc)?
            || self.medium_directive(name, loc)?;
        if !handled {
            return Err(self.err(loc, format!("unknown directive '{name}'")));
        }
        Ok(())
    }

    /// Handles the transform directives; false for any other directive.
    fn transform_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
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
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// Handles the block structure (`AttributeBegin`, `WorldBegin`, ...) and `Include`; false
    /// for any other directive.
    fn block_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
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
                let file = self
                    .b
                    .resolver()
                    .resolve(&rel, "Include")
                    .map_err(|e| self.at(loc, e))?;
                let text = file
                    .read_to_string()
                    .map_err(|e| self.err(loc, format!("Include \"{rel}\": cannot read: {e}")))?;
                let idx = self.files.len();
                if idx > u16::MAX as usize {
                    return Err(self.err(loc, "too many included files"));
                }
                let path = file.path().to_path_buf();
                self.files.push(path.clone());
                let tokens = tokenize(&text, idx as u16, &path)?;
                // From the first pbrt-v4 file on, the scene is read as pbrt-v4.
                self.v4 |= is_v4(&tokens);
                self.sources.push(Source { tokens, pos: 0 });
            }
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// Handles the media directives (not supported: warned); false for any other
    /// directive.
    fn medium_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
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
            _ => return Ok(false),
        }
        Ok(true)
    }
}
