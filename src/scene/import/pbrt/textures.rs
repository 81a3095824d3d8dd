//! `Texture` and the spectrum and float parameters that may name a texture.

use super::lexer::Loc;
use super::params::{ParamSet, Values};
use super::{Parser, R};
use crate::geometry::Rgb;
use crate::material::{Bitmap, Texture};
use std::rc::Rc;
use std::sync::Arc;

/// A spectrum texture: one we represent, or the class of one we do not.
#[derive(Clone)]
pub(super) enum SpecTex {
    Ok(Texture),
    Unsupported(String),
}

/// A float texture: only constants are represented.
#[derive(Clone)]
pub(super) enum FloatTex {
    Const(f32),
    Unsupported(String),
}

impl Parser {
    fn bitmap(&mut self, rel: &str, srgb: bool, loc: Loc) -> R<Arc<Bitmap>> {
        let file = self
            .b
            .resolver()
            .resolve(rel, "texture")
            .map_err(|e| self.at(loc, e))?;
        self.bitmaps
            .load(&file, srgb)
            .map_err(|e| self.err(loc, e.to_string()))
    }

    /// `Texture "name" "spectrum"|"float" "class" params`.
    pub(super) fn texture_directive(&mut self, loc: Loc) -> R<()> {
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
                self.image_wrap_and_filter(&ps, &what, loc)?;
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
        self.define_texture(name, is_float, spec, &class, "float image");
        Ok(())
    }

    /// An image texture's `wrap` (repeat alone; another is warned about) and its filter, which
    /// does not change the expected value at a point.
    pub(super) fn image_wrap_and_filter(&mut self, ps: &ParamSet, what: &str, loc: Loc) -> R<()> {
        if let Some(w) = self.string(ps, "wrap")?
            && w != "repeat"
        {
            self.warn(
                loc,
                format!("{what}: wrap \"{w}\" is not supported; repeat used"),
            );
        }
        let _ = self.string(ps, "filter")?;
        let _ = self.float(ps, "maxanisotropy", 8.0)?;
        Ok(())
    }

    /// Names `spec` in the graphics state: as a float texture (`is_float`) it keeps a constant
    /// alone, and a varying one of class `class` is unsupported as `"{class} ({varying})"`.
    pub(super) fn define_texture(
        &mut self,
        name: String,
        is_float: bool,
        spec: SpecTex,
        class: &str,
        varying: &str,
    ) {
        if is_float {
            let f = match spec {
                SpecTex::Ok(Texture::Constant(c)) => FloatTex::Const(c.x),
                SpecTex::Ok(_) => FloatTex::Unsupported(format!("{class} ({varying})")),
                SpecTex::Unsupported(c) => FloatTex::Unsupported(c),
            };
            Rc::make_mut(&mut self.g.float_tex).insert(name, f);
        } else {
            Rc::make_mut(&mut self.g.spec_tex).insert(name, spec);
        }
    }

    /// An operand of a `scale` texture: a value or a named texture.
    pub(super) fn tex_operand(
        &self,
        ps: &ParamSet,
        name: &str,
        is_float: bool,
    ) -> R<Option<Texture>> {
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
    pub(super) fn texture_ref(&self, ps: &ParamSet, name: &str) -> R<Option<(String, Loc)>> {
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
    pub(super) fn spec_texture(
        &mut self,
        ps: &ParamSet,
        name: &str,
        default: Rgb,
        what: &str,
    ) -> R<Texture> {
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
    pub(super) fn spec_const(
        &mut self,
        ps: &ParamSet,
        name: &str,
        default: Rgb,
        what: &str,
    ) -> R<Rgb> {
        let textured = ps
            .params
            .iter()
            .any(|p| p.name == name && p.ty == "texture");
        let loc = ps.loc_of(name).unwrap_or(self.last_loc);
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
    pub(super) fn float_or_tex(
        &mut self,
        ps: &ParamSet,
        name: &str,
        default: f32,
        what: &str,
    ) -> R<f32> {
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
}
