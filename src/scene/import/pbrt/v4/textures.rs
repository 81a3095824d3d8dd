//! pbrt-v4's `Texture`: `imagemap` (with `encoding` and the uv mapping's scale and offset),
//! `scale` (`tex` x `scale`), `checkerboard` (2D, constant colours) and `constant`; other classes
//! are kept by name and their users fall back to a default with a warning.

use super::super::lexer::Loc;
use super::super::params::ParamSet;
use super::super::textures::SpecTex;
use super::super::{Parser, R};
use crate::geometry::Rgb;
use crate::material::Texture;

/// pbrt-v4's `UVMapping` (s, t) = (su u + du, sv v + dv) as our `Texture::Mapped`, whose rows act
/// on Mitsuba's coordinates (u, 1 - v) and give Mitsuba's (s, 1 - t). pbrt-v4 looks images up
/// at (s, 1 - t) from the top row, that is at (s, t) from the bottom row, as we do.
fn uv_mapped(inner: Texture, (su, sv, du, dv): (f32, f32, f32, f32)) -> Texture {
    if (su, sv, du, dv) == (1.0, 1.0, 0.0, 0.0) {
        return inner;
    }
    Texture::Mapped {
        inner: Box::new(inner),
        // s = su u + du; 1 - t = 1 - sv (1 - v') - dv = sv v' + (1 - sv - dv) with v' = 1 - v.
        rows: [[su, 0.0, du], [0.0, sv, 1.0 - sv - dv]],
    }
}

impl Parser {
    /// The uv mapping of a texture: (uscale, vscale, udelta, vdelta); other mappings warned.
    fn v4_uv_mapping(&mut self, ps: &ParamSet, what: &str, loc: Loc) -> R<(f32, f32, f32, f32)> {
        if let Some(m) = self.string(ps, "mapping")?
            && m != "uv"
        {
            self.warn(
                loc,
                format!("{what}: mapping \"{m}\" is not supported; uv mapping used"),
            );
        }
        Ok((
            self.float(ps, "uscale", 1.0)?,
            self.float(ps, "vscale", 1.0)?,
            self.float(ps, "udelta", 0.0)?,
            self.float(ps, "vdelta", 0.0)?,
        ))
    }

    /// An operand of `scale` or `checkerboard`: a named texture or a value (default `default`).
    fn v4_operand(
        &mut self,
        ps: &ParamSet,
        name: &str,
        is_float: bool,
        default: f32,
    ) -> R<Option<Texture>> {
        if ps
            .params
            .iter()
            .any(|p| p.name == name && p.ty == "texture")
        {
            return self.tex_operand(ps, name, is_float);
        }
        if is_float {
            return Ok(Some(Texture::Constant(Rgb::splat(
                self.float(ps, name, default)?,
            ))));
        }
        let c = self
            .v4_spectrum(ps, name, super::spectra::SpectrumUse::Material)?
            .unwrap_or(Rgb::splat(default));
        Ok(Some(Texture::Constant(c)))
    }

    /// `Texture "name" "spectrum"|"float" "class" params`.
    pub(super) fn v4_texture(&mut self, loc: Loc) -> R<()> {
        let name = self.arg_str("Texture")?;
        let ty = self.arg_str("Texture")?;
        let class = self.arg_str("Texture")?;
        let ps = self.params()?;
        let ps = self.with_attributes("texture", ps);
        let what = format!("Texture \"{name}\" (\"{class}\")");
        let is_float = match ty.as_str() {
            "float" => true,
            "spectrum" => false,
            other => {
                return Err(self.err(
                    loc,
                    format!("Texture type must be \"float\" or \"spectrum\", got \"{other}\""),
                ));
            }
        };
        let spec = match class.as_str() {
            "imagemap" => {
                let Some(file) = self.string(&ps, "filename")? else {
                    return Err(self.err(loc, format!("{what} has no \"string filename\"")));
                };
                let lower = file.to_ascii_lowercase();
                let linear_format = [".exr", ".hdr", ".pfm"].iter().any(|e| lower.ends_with(e));
                // pbrt-v4: 8-bit images are sRGB unless `encoding` says otherwise; floating-point
                // images are linear whatever it says.
                let encoding = self
                    .string(&ps, "encoding")?
                    .unwrap_or_else(|| "sRGB".into());
                let srgb = match encoding.as_str() {
                    _ if linear_format => false,
                    "sRGB" => true,
                    "linear" => false,
                    gamma if gamma.starts_with("gamma ") => {
                        self.warn(
                            loc,
                            format!(
                                "{what}: encoding \"{gamma}\" is not supported; decoded as sRGB"
                            ),
                        );
                        true
                    }
                    other => {
                        return Err(self.err(
                            loc,
                            format!("{what}: unknown encoding \"{other}\" (sRGB, linear, gamma G)"),
                        ));
                    }
                };
                let file_ref = self
                    .b
                    .resolver()
                    .resolve(&file, "texture")
                    .map_err(|e| self.at(loc, e))?;
                let image = self
                    .bitmaps
                    .load(&file_ref, srgb)
                    .map_err(|e| self.err(loc, format!("{what}: {e}")))?;
                let scale = self.float(&ps, "scale", 1.0)?;
                if self.boolean(&ps, "invert", false)? {
                    self.warn(
                        loc,
                        format!("{what}: \"invert\" is not supported and was ignored"),
                    );
                }
                let mapping = self.v4_uv_mapping(&ps, &what, loc)?;
                self.image_wrap_and_filter(&ps, &what, loc)?;
                SpecTex::Ok(uv_mapped(
                    Texture::Bitmap {
                        image,
                        scale: Rgb::splat(scale),
                    },
                    mapping,
                ))
            }
            "constant" => SpecTex::Ok(
                self.v4_operand(&ps, "value", is_float, 1.0)?
                    .unwrap_or(Texture::Constant(Rgb::ONE)),
            ),
            "scale" => {
                let tex = self.v4_operand(&ps, "tex", is_float, 1.0)?;
                let scale = self.v4_operand(&ps, "scale", true, 1.0)?;
                match (tex, scale) {
                    (Some(t), Some(Texture::Constant(s))) => SpecTex::Ok(t.scaled(s)),
                    (Some(Texture::Constant(c)), Some(s)) => SpecTex::Ok(s.scaled(c)),
                    _ => SpecTex::Unsupported(class.clone()),
                }
            }
            "checkerboard" => {
                let dimension = self.int(&ps, "dimension", 2)?;
                let mapping = self.v4_uv_mapping(&ps, &what, loc)?;
                let one = self.v4_operand(&ps, "tex1", is_float, 1.0)?;
                let two = self.v4_operand(&ps, "tex2", is_float, 0.0)?;
                match (dimension, one, two) {
                    (2, Some(Texture::Constant(c1)), Some(Texture::Constant(c2))) => {
                        // pbrt-v4: tex1 where floor(s) + floor(t) is even, cells of one unit.
                        // Our checker has cells of half a unit in Mitsuba's (u, 1 - v), c0
                        // where both fall on the same side of 1/2: looked up at (s/2, t/2), that
                        // is where floor(s) + floor(t) is odd.
                        let (su, sv, du, dv) = mapping;
                        SpecTex::Ok(uv_mapped(
                            Texture::Checker { c0: c2, c1 },
                            (0.5 * su, 0.5 * sv, 0.5 * du, 0.5 * dv),
                        ))
                    }
                    _ => SpecTex::Unsupported(format!("{class} (3D or textured)")),
                }
            }
            _ => {
                ps.consume_all();
                SpecTex::Unsupported(class.clone())
            }
        };
        self.report_unused(&ps, &what);
        self.define_texture(name, is_float, spec, &class, "varying float");
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Vec2;

    #[test]
    fn uv_mapping_scales_and_offsets_our_uv() {
        // The rows applied to Mitsuba's (u, 1 - v) give Mitsuba's (s, 1 - t).
        let t = uv_mapped(
            Texture::Checker {
                c0: Rgb::ONE,
                c1: Rgb::ZERO,
            },
            (2.0, 3.0, 0.25, -0.5),
        );
        let Texture::Mapped { rows, .. } = &t else {
            panic!("mapped");
        };
        let (u, v) = (0.3f32, 0.6f32);
        let (mu, mv) = (u, 1.0 - v);
        let s = rows[0][0] * mu + rows[0][1] * mv + rows[0][2];
        let t_m = rows[1][0] * mu + rows[1][1] * mv + rows[1][2];
        assert!((s - (2.0 * u + 0.25)).abs() < 1e-6);
        assert!((1.0 - t_m - (3.0 * v - 0.5)).abs() < 1e-6);
    }

    #[test]
    fn checkerboard_puts_tex1_where_floor_s_plus_floor_t_is_even() {
        let t = uv_mapped(
            Texture::Checker {
                c0: Rgb::ZERO,
                c1: Rgb::ONE,
            },
            (0.5, 0.5, 0.0, 0.0),
        );
        for (u, v) in [
            (0.25f32, 0.25f32),
            (1.25, 0.25),
            (0.25, 1.25),
            (1.25, 1.25),
            (2.5, 0.5),
        ] {
            let even = (u.floor() + v.floor()) as i32 % 2 == 0;
            let want = if even { Rgb::ONE } else { Rgb::ZERO };
            assert_eq!(t.eval(Vec2::new(u, v)), want, "({u}, {v})");
        }
    }
}
