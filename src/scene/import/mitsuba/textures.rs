//! Textures: `bitmap` and `scale`, and the colour properties that may be textured.

use super::{Ctx, Obj, R};
use crate::geometry::Rgb;
use crate::material::{Bitmap, Texture};
use crate::scene::import::xml::{Node, Props};
use std::sync::Arc;

impl Ctx {
    fn bitmap(&mut self, n: &Node, rel: &str, srgb: bool) -> R<Arc<Bitmap>> {
        let file = self
            .b
            .resolver()
            .resolve(rel, &format!("line {}", n.line))?;
        self.bitmaps
            .load(&file, srgb)
            .map_err(|e| self.err(n, e.to_string()))
    }

    /// Translates a `<texture>` element.
    pub(super) fn texture(&mut self, n: &Node) -> R<Texture> {
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
                inner_t.scaled(s)
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

    /// A colour property that may be a texture (nested, or `<ref name= id=>`).
    pub(super) fn spectrum_tex(&mut self, p: &Props, name: &str, default: Rgb) -> R<Texture> {
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
    pub(super) fn spectrum_const(
        &mut self,
        p: &Props,
        name: &str,
        default: Rgb,
        what: &str,
    ) -> R<Rgb> {
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
}
