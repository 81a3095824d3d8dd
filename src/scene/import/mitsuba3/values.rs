//! Property values of Mitsuba 3 files (`<float>`, `<integer>`, `<boolean>`, `<string>`,
//! `<rgb>`, `<spectrum>`, `<point>`, `<vector>`, `<transform>`) with Mitsuba 3's rules: a
//! reflectance must lie in [0, 1], an emitter's flat `<spectrum>` becomes Mitsuba's RGB of a
//! flat spectrum, rotation axes are not normalised, matrices are row-major.

use super::{Ctx, R};
use crate::geometry::{Mat4, Rgb, Vec3};
use crate::scene::import::xml::{self, Node, Props, split_numbers};

/// How a colour property is used: Mitsuba 3 turns the same XML into different colours for a
/// reflectance, an unbounded quantity (an index of refraction) and an emission.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ColorUse {
    /// A reflectance or transmittance: an `<rgb>` outside [0, 1] is an error.
    Bounded,
    /// Any other non-negative quantity (eta, k).
    Unbounded,
    /// Radiance, intensity or irradiance.
    Emission,
}

/// The RGB Mitsuba 3 gives a flat emission spectrum of value 1 (its `<spectrum value="1">` on
/// an emitter, converted without a white point: CIE XYZ of the flat spectrum through the sRGB
/// matrix).
pub(super) const FLAT_EMISSION_RGB: [f32; 3] = [1.20479, 0.948291, 0.908916];

impl Ctx {
    fn value_of<'a>(&self, n: &'a Node) -> R<&'a str> {
        xml::value_of(&self.file, n)
    }

    /// A `<float>` or `<integer>` element's number.
    pub(super) fn number(&self, n: &Node) -> R<f32> {
        match n.tag.as_str() {
            "float" | "integer" => {
                let v = self.value_of(n)?;
                v.trim()
                    .parse::<f64>()
                    .ok()
                    .map(|x| x as f32)
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.err(n, format!("{}: malformed number '{v}'", n.label())))
            }
            _ => Err(self.err(n, format!("{} should be a <float>", n.label()))),
        }
    }

    pub(super) fn float(&self, p: &Props, name: &str, default: f32) -> R<f32> {
        p.get(name).map_or(Ok(default), |n| self.number(n))
    }

    pub(super) fn int(&self, p: &Props, name: &str, default: i64) -> R<i64> {
        xml::int_prop(&self.file, p, name, default)
    }

    pub(super) fn boolean(&self, p: &Props, name: &str, default: bool) -> R<bool> {
        match p.get(name) {
            Some(n) if n.tag == "boolean" => {
                let v = self.value_of(n)?.trim().to_ascii_lowercase();
                match v.as_str() {
                    "true" => Ok(true),
                    "false" => Ok(false),
                    _ => Err(self.err(n, format!("{}: expected true or false", n.label()))),
                }
            }
            Some(n) => Err(self.err(n, format!("{} should be a <boolean>", n.label()))),
            None => Ok(default),
        }
    }

    pub(super) fn string(&self, p: &Props, name: &str) -> R<Option<String>> {
        xml::string_prop(&self.file, p, name)
    }

    /// A colour element as Mitsuba 3 reads it for `usage`.
    pub(super) fn color(&self, n: &Node, usage: ColorUse) -> R<Rgb> {
        let c = match n.tag.as_str() {
            "float" | "integer" => Rgb::splat(self.number(n)?),
            "rgb" => {
                let v = split_numbers(self.value_of(n)?)
                    .map_err(|m| self.err(n, format!("{}: {m}", n.label())))?;
                let c = match v.len() {
                    1 => Rgb::splat(v[0]),
                    3 => Rgb::new(v[0], v[1], v[2]),
                    k => {
                        return Err(
                            self.err(n, format!("{}: expected 1 or 3 values, got {k}", n.label()))
                        );
                    }
                };
                if usage == ColorUse::Bounded && !(c.min_element() >= 0.0 && c.max_element() <= 1.0)
                {
                    return Err(self.err(
                        n,
                        format!(
                            "{}: a reflectance must lie in [0, 1], got {:?} (Mitsuba 3 refuses it too)",
                            n.label(),
                            c.to_array()
                        ),
                    ));
                }
                c
            }
            "spectrum" => {
                if n.attr("filename").is_some() || n.attr("type").is_some() {
                    return Err(self.err(
                        n,
                        format!(
                            "{}: spectrum files and spectrum plugins are not supported; give an <rgb>",
                            n.label()
                        ),
                    ));
                }
                let v = self.value_of(n)?;
                if v.contains(':') {
                    return Err(self.err(
                        n,
                        format!(
                            "{}: sampled spectra (wavelength:value) are not supported; give an <rgb>",
                            n.label()
                        ),
                    ));
                }
                let v = split_numbers(v).map_err(|m| self.err(n, format!("{}: {m}", n.label())))?;
                let [x] = v[..] else {
                    return Err(self.err(
                        n,
                        format!(
                            "{}: expected one value or wavelength:value pairs",
                            n.label()
                        ),
                    ));
                };
                if usage == ColorUse::Emission {
                    Rgb::from_array(FLAT_EMISSION_RGB) * x
                } else {
                    Rgb::splat(x)
                }
            }
            _ => {
                return Err(self.err(
                    n,
                    format!(
                        "{} should be a colour (<rgb>, <spectrum>, <float>)",
                        n.label()
                    ),
                ));
            }
        };
        if !(c.is_finite() && c.min_element() >= 0.0) {
            return Err(self.err(
                n,
                format!(
                    "{}: must be finite and >= 0, got {:?}",
                    n.label(),
                    c.to_array()
                ),
            ));
        }
        Ok(c)
    }

    /// Three numbers: `value="x, y, z"` (or one, repeated), or the attributes `x`, `y`, `z`
    /// (each defaulting to `missing`).
    fn triple(&self, n: &Node, missing: f32) -> R<Vec3> {
        if let Some(v) = n.attr("value") {
            let v = split_numbers(v).map_err(|m| self.err(n, format!("{}: {m}", n.label())))?;
            return match v[..] {
                [x, y, z] => Ok(Vec3::new(x, y, z)),
                [s] => Ok(Vec3::splat(s)),
                _ => Err(self.err(
                    n,
                    format!("{}: expected 3 values, got {}", n.label(), v.len()),
                )),
            };
        }
        let c = |k: &str| -> R<f32> {
            match n.attr(k) {
                None => Ok(missing),
                Some(s) => s
                    .trim()
                    .parse::<f32>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.err(n, format!("{}: malformed {k} '{s}'", n.label()))),
            }
        };
        Ok(Vec3::new(c("x")?, c("y")?, c("z")?))
    }

    /// A `<point>` or `<vector>` element.
    pub(super) fn point(&self, n: &Node) -> R<Vec3> {
        if !matches!(n.tag.as_str(), "point" | "vector") {
            return Err(self.err(n, format!("{} should be a <point>", n.label())));
        }
        self.triple(n, 0.0)
    }

    /// A point property, or `default`.
    pub(super) fn point_prop(&self, p: &Props, name: &str, default: Vec3) -> R<Vec3> {
        p.get(name).map_or(Ok(default), |n| self.point(n))
    }

    /// A 3-vector attribute (`origin="0, 1, 2"`).
    fn vec_attr(&self, n: &Node, k: &str) -> R<Option<Vec3>> {
        match n.attr(k) {
            None => Ok(None),
            Some(s) => {
                let v =
                    split_numbers(s).map_err(|m| self.err(n, format!("<{}> {k}: {m}", n.tag)))?;
                match v[..] {
                    [x, y, z] => Ok(Some(Vec3::new(x, y, z))),
                    _ => Err(self.err(n, format!("<{}> {k}: expected 3 values", n.tag))),
                }
            }
        }
    }

    /// A `<transform>`: its operations in document order, each multiplied on the left.
    pub(super) fn transform(&self, n: &Node) -> R<Mat4> {
        if n.tag != "transform" {
            return Err(self.err(n, format!("{} should be a <transform>", n.label())));
        }
        let mut m = Mat4::IDENTITY;
        for s in &n.children {
            let step = match s.tag.as_str() {
                "translate" => Mat4::from_translation(self.triple(s, 0.0)?),
                "scale" => Mat4::from_scale(self.triple(s, 1.0)?),
                "rotate" => {
                    let axis = self.triple(s, 0.0)?;
                    if axis == Vec3::ZERO {
                        return Err(self.err(s, "<rotate>: the axis is zero"));
                    }
                    let angle = s
                        .attr("angle")
                        .ok_or_else(|| self.err(s, "<rotate> has no angle"))?
                        .trim()
                        .parse::<f32>()
                        .map_err(|_| self.err(s, "<rotate>: malformed angle"))?;
                    rotation(axis, angle.to_radians())
                }
                "matrix" => {
                    let v = split_numbers(self.value_of(s)?)
                        .map_err(|m| self.err(s, format!("<matrix>: {m}")))?;
                    match v.len() {
                        // Row-major in the file.
                        16 => {
                            let mut a = [0f32; 16];
                            a.copy_from_slice(&v);
                            Mat4::from_cols_array(&a).transpose()
                        }
                        9 => {
                            let c = |j: usize| Vec3::new(v[j], v[3 + j], v[6 + j]).extend(0.0);
                            Mat4::from_cols(c(0), c(1), c(2), glam::Vec4::W)
                        }
                        k => {
                            return Err(
                                self.err(s, format!("<matrix> needs 16 or 9 values, got {k}"))
                            );
                        }
                    }
                }
                "lookat" => {
                    let origin = self
                        .vec_attr(s, "origin")?
                        .ok_or_else(|| self.err(s, "<lookat> has no origin"))?;
                    let target = self
                        .vec_attr(s, "target")?
                        .ok_or_else(|| self.err(s, "<lookat> has no target"))?;
                    let up = self.vec_attr(s, "up")?.filter(|u| *u != Vec3::ZERO);
                    super::super::common::mitsuba_look_at(origin, target, up)
                        .map_err(|e| self.err(s, e))?
                }
                other => return Err(self.err(s, format!("unknown transform operation <{other}>"))),
            };
            m = step * m;
        }
        if !m.is_finite() {
            return Err(self.err(n, "the transform is not finite"));
        }
        Ok(m)
    }

    /// The `to_world` property, or the identity.
    pub(super) fn to_world(&self, p: &Props) -> R<Mat4> {
        p.get("to_world")
            .map_or(Ok(Mat4::IDENTITY), |n| self.transform(n))
    }
}

/// The rotation Mitsuba 3 makes of `<rotate>`: Rodrigues' formula with the axis as written,
/// not normalised (an axis of length l also scales, as in Mitsuba).
fn rotation(a: Vec3, angle: f32) -> Mat4 {
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    let (x, y, z) = (a.x, a.y, a.z);
    Mat4::from_cols(
        glam::Vec4::new(x * x * t + c, x * y * t + z * s, x * z * t - y * s, 0.0),
        glam::Vec4::new(x * y * t - z * s, y * y * t + c, y * z * t + x * s, 0.0),
        glam::Vec4::new(x * z * t + y * s, y * z * t - x * s, z * z * t + c, 0.0),
        glam::Vec4::W,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_unit_axis_rotation_is_glams() {
        let m = rotation(Vec3::new(0.0, 0.6, 0.8), 0.7);
        let g = Mat4::from_axis_angle(Vec3::new(0.0, 0.6, 0.8), 0.7);
        assert!(m.abs_diff_eq(g, 1e-6), "{m} vs {g}");
    }
}
