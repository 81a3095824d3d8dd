//! The properties of an object element (`<float name="radius" value="2"/>`, ...) and their
//! typed values: numbers, colours, points and transforms.

use super::{Ctx, R};
use crate::geometry::{Mat4, Rgb, Vec3};
use crate::material::texture::srgb_to_linear;
use crate::scene::import::xml::{self, Node, Props, split_numbers};

impl Ctx {
    pub(super) fn value_attr<'a>(&self, n: &'a Node) -> R<&'a str> {
        xml::value_of(&self.file, n)
    }

    pub(super) fn num_of(&self, n: &Node) -> R<f32> {
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

    pub(super) fn float(&self, p: &Props, name: &str, default: f32) -> R<f32> {
        match p.get(name) {
            Some(n) => self.num_of(n),
            None => Ok(default),
        }
    }

    pub(super) fn int(&self, p: &Props, name: &str, default: i64) -> R<i64> {
        xml::int_prop(&self.file, p, name, default)
    }

    pub(super) fn boolean(&self, p: &Props, name: &str, default: bool) -> R<bool> {
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

    pub(super) fn string(&self, p: &Props, name: &str) -> R<Option<String>> {
        xml::string_prop(&self.file, p, name)
    }

    /// A colour element: `rgb`, `srgb`, `spectrum` (uniform or flat), or a plain `float`.
    pub(super) fn color_of(&self, n: &Node) -> R<Rgb> {
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

    pub(super) fn point_of(&self, n: &Node) -> R<Vec3> {
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

    pub(super) fn vec_attr(&self, n: &Node, k: &str) -> R<Option<Vec3>> {
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
    pub(super) fn transform_of(&self, n: &Node) -> R<Mat4> {
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
                    let up = self.vec_attr(s, "up")?;
                    super::super::common::mitsuba_look_at(origin, target, up)
                        .map_err(|e| self.err(s, e))?
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

    pub(super) fn to_world(&self, p: &Props) -> R<Mat4> {
        match p.get("toWorld") {
            Some(n) => self.transform_of(n),
            None => Ok(Mat4::IDENTITY),
        }
    }
}
