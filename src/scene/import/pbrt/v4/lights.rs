//! pbrt-v4's lights: `AreaLightSource "diffuse"` and `LightSource` `point`, `spot`, `distant`
//! and `infinite` (constant, or an equal-area octahedral image resampled into our sky's
//! equirectangular map), with pbrt-v4's photometric `scale`, `power` and `illuminance`, and the
//! spectra lights are given in.

use super::super::lexer::Loc;
use super::super::params::{ParamSet, Values};
use super::super::{Parser, R};
use super::spectra::{SpectrumUse, blackbody, named_spectrum};
use crate::geometry::{Rgb, Vec3};
use crate::light::{Environment, Sun};
use std::f32::consts::PI;

/// pbrt-v4's `EqualAreaSphereToSquare`: the point of [0, 1]^2 of a unit direction in an
/// equal-area octahedral map (Clarberg, "Fast Equal-Area Mapping of the (Hemi)Sphere using
/// SIMD", JGT 2008, section 3: r = sqrt(1 - |z|), phi = 2/pi atan(min/max of |x|, |y|); the
/// southern hemisphere folded over the diagonals), with atan exact.
pub(super) fn equal_area_square(d: Vec3) -> (f32, f32) {
    let (x, y, z) = (d.x.abs(), d.y.abs(), d.z.abs());
    let r = (1.0 - z).max(0.0).sqrt();
    let (a, b) = (x.max(y), x.min(y));
    let b = if a == 0.0 { 0.0 } else { b / a };
    let mut phi = b.atan() * 2.0 / PI;
    if x < y {
        phi = 1.0 - phi;
    }
    let mut v = phi * r;
    let mut u = r - v;
    if d.z < 0.0 {
        (u, v) = (1.0 - v, 1.0 - u);
    }
    (0.5 * (u.copysign(d.x) + 1.0), 0.5 * (v.copysign(d.y) + 1.0))
}

impl Parser {
    /// An `infinite` light's image: pbrt-v4's equal-area octahedral map (square; its first row
    /// is v = 0), in light space placed by the current transform, resampled once into our
    /// equirectangular sky of twice its side by its side (bilinear lookups). pbrt-v4 takes the
    /// texels as radiance (its scale divides by the colour space's illuminant, luminance 1).
    fn octahedral_environment(&mut self, rel: &str, scale: f32, loc: Loc) -> R<Environment> {
        let file = self
            .b
            .resolver()
            .resolve(rel, "LightSource \"infinite\"")
            .map_err(|e| self.at(loc, e))?;
        let lower = rel.to_ascii_lowercase();
        let linear = [".exr", ".hdr", ".pfm"].iter().any(|e| lower.ends_with(e));
        let image = self
            .bitmaps
            .load(&file, !linear)
            .map_err(|e| self.err(loc, format!("infinite light \"{rel}\": {e}")))?;
        if image.width != image.height {
            return Err(self.err(
                loc,
                format!(
                    "infinite light \"{rel}\": pbrt-v4's environment maps are square (equal-area octahedral), this one is {}x{}",
                    image.width, image.height
                ),
            ));
        }
        let side = image.width;
        let (width, height) = (2 * side, side);
        let to_light = glam::Mat3::from_mat4(self.g.ctm).inverse();
        let mut texels = Vec::with_capacity(width * height);
        for row in 0..height {
            // Our sky's map: v = acos(y) / pi from the top row, u = atan2(x, -z) / 2 pi.
            let theta = (row as f32 + 0.5) / height as f32 * PI;
            for col in 0..width {
                let phi = (col as f32 + 0.5) / width as f32 * 2.0 * PI;
                let world = Vec3::new(
                    theta.sin() * phi.sin(),
                    theta.cos(),
                    -theta.sin() * phi.cos(),
                );
                let (u, v) = equal_area_square((to_light * world).normalize_or_zero());
                // Our bitmaps' v runs up from the bottom row.
                texels.push(image.lookup(glam::Vec2::new(u, 1.0 - v)).max(Rgb::ZERO));
            }
        }
        Environment::image(width, height, texels, scale, &glam::Mat4::IDENTITY)
            .map_err(|e| self.err(loc, format!("infinite light \"{rel}\": {e}")))
    }

    /// A spectrum parameter of pbrt-v4 (`rgb`, `blackbody` of one temperature, a named
    /// spectrum, a constant `spectrum`) in linear sRGB, `usage` choosing how a named spectrum
    /// is read; `None` when absent. What we cannot convert is refused (and `Some(0)` returned).
    pub(super) fn v4_spectrum(
        &mut self,
        ps: &ParamSet,
        name: &str,
        usage: SpectrumUse,
    ) -> R<Option<Rgb>> {
        let Some(p) = ps.find(name, &["rgb", "spectrum", "blackbody", "float"]) else {
            return Ok(None);
        };
        let (loc, decl) = (p.loc, p.decl.clone());
        let c = match (p.ty.as_str(), &p.values) {
            ("rgb", Values::Nums(v)) if v.len() == 3 => {
                Rgb::new(v[0] as f32, v[1] as f32, v[2] as f32)
            }
            ("float", Values::Nums(v)) if v.len() == 1 => Rgb::splat(v[0] as f32),
            ("blackbody", Values::Nums(v)) if v.len() == 1 => match blackbody(v[0] as f32) {
                Some(c) => c,
                None => {
                    self.refuse(
                        loc,
                        format!(
                            "\"{decl}\": a blackbody of {} K is outside the supported 1000-40000 K",
                            v[0]
                        ),
                    );
                    Rgb::ZERO
                }
            },
            ("spectrum", Values::Strs(v)) if v.len() == 1 => match named_spectrum(&v[0], usage) {
                Some(c) => c,
                None => {
                    self.refuse(
                            loc,
                            format!(
                                "\"{decl}\" \"{}\": not one of pbrt-v4's named spectra for this use (spectrum files are not supported)",
                                v[0]
                            ),
                        );
                    Rgb::ZERO
                }
            },
            // (wavelength, value) pairs: only a flat spectrum has an exact RGB equivalent.
            ("spectrum", Values::Nums(v))
                if v.len() >= 2
                    && v.len() % 2 == 0
                    && v.chunks_exact(2)
                        .all(|c| (c[1] - v[1]).abs() <= 1e-6 * v[1].abs().max(1.0)) =>
            {
                Rgb::splat(v[1] as f32)
            }
            ("spectrum", _) => {
                self.refuse(
                    loc,
                    format!("\"{decl}\": sampled spectra are not supported; give an \"rgb\" value or a named spectrum"),
                );
                Rgb::ZERO
            }
            _ => {
                return Err(self.err(
                    loc,
                    format!("parameter \"{decl}\" has the wrong number of values"),
                ));
            }
        };
        if !c.is_finite() {
            return Err(self.err(loc, format!("parameter \"{decl}\" is not finite")));
        }
        Ok(Some(c))
    }

    /// An emitted spectrum (default: the colour space's illuminant, D65, which is RGB 1) times
    /// the light's `scale`; negative values are errors.
    fn v4_emission(&mut self, ps: &ParamSet, name: &str, loc: Loc) -> R<Rgb> {
        let c = self
            .v4_spectrum(ps, name, SpectrumUse::Illuminant)?
            .unwrap_or(Rgb::ONE);
        let scale = self.float(ps, "scale", 1.0)?;
        let e = c * scale;
        if e.min_element() < 0.0 {
            return Err(self.err(loc, format!("'{name}' times scale must be >= 0, got {e:?}")));
        }
        Ok(e)
    }

    /// A positive `power` or `illuminance` (pbrt-v4 ignores values <= 0).
    fn v4_positive(&self, ps: &ParamSet, name: &str) -> R<Option<f32>> {
        Ok(self.opt_float(ps, name)?.filter(|&x| x > 0.0))
    }

    /// `AreaLightSource "diffuse"`: the emission of the shapes that follow in this block.
    pub(super) fn v4_area_light(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("AreaLightSource")?;
        let ps = self.params()?;
        let ps = self.with_attributes("light", ps);
        if ty != "diffuse" {
            self.refuse(loc, format!("AreaLightSource \"{ty}\" is not supported"));
            ps.consume_all();
            return Ok(());
        }
        let l = self.v4_emission(&ps, "L", loc)?;
        let two_sided = self.boolean(&ps, "twosided", false)?;
        if two_sided {
            self.warn(
                loc,
                "AreaLightSource \"diffuse\": twosided is not supported; the light emits on the front side only",
            );
        }
        if ps.has("filename") {
            ps.find("filename", &["string"]);
            self.refuse(
                loc,
                "AreaLightSource \"diffuse\": an image of emission (\"filename\") is not supported",
            );
        }
        let power = self.v4_positive(&ps, "power")?;
        self.report_unused(&ps, "AreaLightSource \"diffuse\"");
        self.g.area = Some(l);
        self.g.area_power = power.map(|p| (p, two_sided));
        Ok(())
    }

    /// The radiance of an area light on a shape of `area` (world units): `power` spreads over
    /// the area and, as a Lambertian emitter, pi steradians (pbrt-v4's DiffuseAreaLight::Create,
    /// k_e = sides x area x pi).
    pub(super) fn v4_area_radiance(&self, area: f32) -> Option<Rgb> {
        let l = self.g.area?;
        Some(match self.g.area_power {
            Some((phi, two_sided)) if area > 0.0 => {
                let sides = if two_sided { 2.0 } else { 1.0 };
                l * (phi / (sides * area * PI))
            }
            _ => l,
        })
    }

    /// `LightSource`: point, spot, distant and infinite lights.
    pub(super) fn v4_light_source(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("LightSource")?;
        let ps = self.params()?;
        let ps = self.with_attributes("light", ps);
        let what = format!("LightSource \"{ty}\"");
        if self.defining.is_some() {
            ps.consume_all();
            self.warn(
                loc,
                "lights inside object definitions are ignored (as in pbrt-v4)",
            );
            return Ok(());
        }
        let place = format!("line {}", loc.line);
        let point = |p: &Parser, name: &str, default: Vec3| -> R<Vec3> {
            Ok(p.vec3s(&ps, name, &["point3"])?
                .and_then(|v| v.first().copied())
                .unwrap_or(default))
        };
        match ty.as_str() {
            "point" => {
                let mut i = self.v4_emission(&ps, "I", loc)?;
                if let Some(phi) = self.v4_positive(&ps, "power")? {
                    i *= phi / (4.0 * PI);
                }
                let from = point(self, "from", Vec3::ZERO)?;
                let pos = self.g.ctm.transform_point3(from);
                self.report_unused(&ps, &what);
                self.b
                    .add_point_light(pos, i, &place)
                    .map_err(|e| self.at(loc, e))?;
            }
            "spot" => {
                let mut i = self.v4_emission(&ps, "I", loc)?;
                let cone = self.float(&ps, "coneangle", 30.0)?;
                let delta = self.float(&ps, "conedeltaangle", 5.0)?;
                if !(cone > 0.0 && cone <= 90.0 && delta >= 0.0) {
                    return Err(self.err(
                        loc,
                        format!("{what}: coneangle {cone} must be in (0, 90] and conedeltaangle {delta} >= 0"),
                    ));
                }
                if let Some(phi) = self.v4_positive(&ps, "power")? {
                    // pbrt-v4's SpotLight::Create: the solid angle of full intensity plus half
                    // that of the falloff.
                    let cos_end = cone.to_radians().cos();
                    let cos_start = (cone - delta).to_radians().cos();
                    i *= phi / (2.0 * PI * ((1.0 - cos_start) + (cos_start - cos_end) / 2.0));
                }
                let from = point(self, "from", Vec3::ZERO)?;
                let to = point(self, "to", Vec3::Z)?;
                let beam = (cone - delta).max(1e-3 * cone);
                self.warn(
                    loc,
                    "LightSource \"spot\": the falloff between coneangle - conedeltaangle and coneangle is linear in angle (Mitsuba's), not pbrt-v4's smoothstep in cosine",
                );
                self.report_unused(&ps, &what);
                let m = self.g.ctm;
                self.b
                    .add_spot_light(
                        m.transform_point3(from),
                        m.transform_vector3(to - from),
                        i,
                        (beam, cone),
                        &place,
                    )
                    .map_err(|e| self.at(loc, e))?;
            }
            "distant" => {
                let mut e = self.v4_emission(&ps, "L", loc)?;
                if let Some(ev) = self.v4_positive(&ps, "illuminance")? {
                    e *= ev;
                }
                let from = point(self, "from", Vec3::ZERO)?;
                let to = point(self, "to", Vec3::Z)?;
                self.report_unused(&ps, &what);
                self.warn(
                    loc,
                    format!(
                        "a distant light is rendered as a sun {} degrees across",
                        2.0 * crate::light::environment::SUN_ANGULAR_RADIUS_DEG
                    ),
                );
                // The light travels from `from` toward `to`.
                let sun = Sun::directional(self.g.ctm.transform_vector3(to - from), e)
                    .ok_or_else(|| self.err(loc, "distant: from and to are the same point"))?;
                self.b.add_sun(sun, &place).map_err(|e| self.at(loc, e))?;
            }
            "infinite" => {
                if ps.has("portal") {
                    ps.find("portal", &["point3"]);
                    self.warn(
                        loc,
                        "LightSource \"infinite\": portals only guide sampling; ignored",
                    );
                }
                if std::mem::replace(&mut self.environment_seen, true) {
                    ps.consume_all();
                    self.refuse(loc, "more than one infinite light: our sky has one dome");
                    return Ok(());
                }
                let env = match self.string(&ps, "filename")? {
                    Some(file) => {
                        if ps.has("L") || ps.has("illuminance") {
                            ps.consume_all();
                            self.refuse(
                                loc,
                                "LightSource \"infinite\": an image with \"L\" or \"illuminance\" is not supported",
                            );
                            return Ok(());
                        }
                        let scale = self.float(&ps, "scale", 1.0)?;
                        self.octahedral_environment(&file, scale, loc)?
                    }
                    None => {
                        let mut l = self.v4_emission(&ps, "L", loc)?;
                        if let Some(ev) = self.v4_positive(&ps, "illuminance")? {
                            // The illuminance of uniform radiance on an upward-facing patch is
                            // pi L.
                            l *= ev / PI;
                        }
                        Environment::constant(l)
                    }
                };
                self.report_unused(&ps, &what);
                self.b.set_environment(env);
            }
            other => {
                ps.consume_all();
                self.refuse(loc, format!("LightSource \"{other}\" is not supported"));
            }
        }
        Ok(())
    }
}
