//! Parameter lists (`"type name" value` or `"type name" [ values ]`) and their typed lookup,
//! which marks what was read so that the rest can be reported as unsupported.

use super::lexer::{Loc, Tok, Token, describe};
use super::{Parser, R};
use crate::geometry::{Rgb, Vec3};
use std::cell::Cell;

/// The values of one parameter.
#[derive(Clone, Debug)]
pub(super) enum Values {
    Nums(Vec<f64>),
    Strs(Vec<String>),
    Bools(Vec<bool>),
}

/// One parameter of a directive.
#[derive(Clone, Debug)]
pub(super) struct Param {
    /// Declared type with pbrt-v3's synonyms folded (`point` = `point3`, `color` = `rgb`, ...).
    pub(super) ty: String,
    /// The declaration as written, for messages.
    pub(super) decl: String,
    pub(super) name: String,
    pub(super) values: Values,
    pub(super) loc: Loc,
    pub(super) used: Cell<bool>,
}

/// The parameters of one directive, in order (a repeated name: the last one counts).
#[derive(Clone, Debug, Default)]
pub(super) struct ParamSet {
    pub(super) params: Vec<Param>,
}

impl ParamSet {
    /// The last parameter `name` of one of `types`, marked used.
    pub(super) fn find(&self, name: &str, types: &[&str]) -> Option<&Param> {
        let p = self
            .params
            .iter()
            .rev()
            .find(|p| p.name == name && types.contains(&p.ty.as_str()))?;
        p.used.set(true);
        Some(p)
    }

    /// Where the last parameter called `name` (of any type) was written.
    pub(super) fn loc_of(&self, name: &str) -> Option<Loc> {
        self.params
            .iter()
            .rev()
            .find(|p| p.name == name)
            .map(|p| p.loc)
    }

    /// Whether any parameter is called `name` (of any type).
    pub(super) fn has(&self, name: &str) -> bool {
        self.params.iter().any(|p| p.name == name)
    }

    /// Marks every parameter used (for directives whose parameters are all ignored at once).
    pub(super) fn consume_all(&self) {
        for p in &self.params {
            p.used.set(true);
        }
    }
}

/// A declared type with pbrt-v3's synonyms folded, or `None` for an unknown type.
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

impl Parser {
    /// The parameter list after a directive's arguments: `"type name" value` or
    /// `"type name" [ values ]`, until the next directive.
    pub(super) fn params(&mut self) -> R<ParamSet> {
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

    pub(super) fn param_values(
        &self,
        ty: &str,
        decl: &str,
        loc: Loc,
        items: Vec<Token>,
    ) -> R<Values> {
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

    pub(super) fn nums<'p>(&self, p: &'p Param) -> R<&'p [f64]> {
        match &p.values {
            Values::Nums(v) => Ok(v),
            _ => Err(self.err(p.loc, format!("parameter \"{}\" expects numbers", p.decl))),
        }
    }

    pub(super) fn one_num(&self, p: &Param) -> R<f64> {
        let v = self.nums(p)?;
        if v.len() != 1 {
            return Err(self.err(
                p.loc,
                format!("parameter \"{}\" expects 1 value, got {}", p.decl, v.len()),
            ));
        }
        Ok(v[0])
    }

    pub(super) fn float(&self, ps: &ParamSet, name: &str, default: f32) -> R<f32> {
        match ps.find(name, &["float"]) {
            Some(p) => Ok(self.one_num(p)? as f32),
            None => Ok(default),
        }
    }

    pub(super) fn opt_float(&self, ps: &ParamSet, name: &str) -> R<Option<f32>> {
        match ps.find(name, &["float"]) {
            Some(p) => Ok(Some(self.one_num(p)? as f32)),
            None => Ok(None),
        }
    }

    pub(super) fn int(&self, ps: &ParamSet, name: &str, default: i64) -> R<i64> {
        match ps.find(name, &["integer"]) {
            Some(p) => Ok(self.one_num(p)? as i64),
            None => Ok(default),
        }
    }

    pub(super) fn ints(&self, ps: &ParamSet, name: &str) -> R<Option<Vec<i64>>> {
        match ps.find(name, &["integer"]) {
            Some(p) => Ok(Some(self.nums(p)?.iter().map(|&x| x as i64).collect())),
            None => Ok(None),
        }
    }

    pub(super) fn boolean(&self, ps: &ParamSet, name: &str, default: bool) -> R<bool> {
        match ps.find(name, &["bool"]) {
            Some(p) => match &p.values {
                Values::Bools(v) if v.len() == 1 => Ok(v[0]),
                _ => Err(self.err(p.loc, format!("parameter \"{}\" expects 1 value", p.decl))),
            },
            None => Ok(default),
        }
    }

    pub(super) fn string(&self, ps: &ParamSet, name: &str) -> R<Option<String>> {
        self.string_of(ps, name, &["string"])
    }

    pub(super) fn string_of(&self, ps: &ParamSet, name: &str, types: &[&str]) -> R<Option<String>> {
        match ps.find(name, types) {
            Some(p) => match &p.values {
                Values::Strs(v) if v.len() == 1 => Ok(Some(v[0].clone())),
                _ => Err(self.err(p.loc, format!("parameter \"{}\" expects 1 string", p.decl))),
            },
            None => Ok(None),
        }
    }

    /// Triples of a point / vector / normal parameter.
    pub(super) fn vec3s(&self, ps: &ParamSet, name: &str, types: &[&str]) -> R<Option<Vec<Vec3>>> {
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
    pub(super) fn rgb(&self, ps: &ParamSet, name: &str) -> R<Option<Rgb>> {
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

    pub(super) fn color(&self, ps: &ParamSet, name: &str, default: Rgb) -> R<Rgb> {
        let c = self.rgb(ps, name)?.unwrap_or(default);
        if c.min_element() < 0.0 {
            let loc = ps.loc_of(name).unwrap_or(self.last_loc);
            return Err(self.err(loc, format!("'{name}' must be >= 0, got {c:?}")));
        }
        Ok(c)
    }

    /// Warns about every parameter of `ps` nothing looked at.
    pub(super) fn report_unused(&mut self, ps: &ParamSet, what: &str) {
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
}
