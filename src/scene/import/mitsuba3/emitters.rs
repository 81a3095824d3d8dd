//! Emitters of Mitsuba 3 files that stand on their own (not attached to a shape): `point`,
//! `spot`, `directional`, `constant` and `envmap` (the last three through the sky's dome,
//! `light::environment`), in Mitsuba 3's conventions.

use super::values::{ColorUse, FLAT_EMISSION_RGB};
use super::{Ctx, R};
use crate::geometry::{Mat4, Rgb, Vec3};
use crate::light::{Environment, Sun};
use crate::scene::import::xml::{Node, Props};

impl Ctx {
    /// A top-level `<emitter>`.
    pub(super) fn emitter(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        match ty {
            "point" => {
                let position = match (p.get("position"), p.get("to_world")) {
                    (Some(_), Some(_)) => {
                        return Err(
                            self.err(n, "point emitter: give position or to_world, not both")
                        );
                    }
                    (Some(v), None) => self.point(v)?,
                    (None, Some(t)) => self.transform(t)?.transform_point3(Vec3::ZERO),
                    (None, None) => Vec3::ZERO,
                };
                let intensity = self.emission(&p, "intensity")?;
                p.consume("sampling_weight");
                self.report_unused(&p, "emitter \"point\"");
                self.b
                    .add_point_light(position, intensity, &format!("line {}", n.line))
            }
            "area" => Err(self.err(n, "an area emitter must be attached to a shape")),
            "spot" => {
                let m = self.to_world(&p)?;
                let intensity = self.emission(&p, "intensity")?;
                let cutoff = self.float(&p, "cutoff_angle", 20.0)?;
                let beam = self.float(&p, "beam_width", 0.75 * cutoff)?;
                if p.has("texture") {
                    self.refuse(n, "a spot light's projected texture is not supported");
                }
                p.consume("sampling_weight");
                self.report_unused(&p, "emitter \"spot\"");
                // Mitsuba's spot shines along its local +z.
                self.b.add_spot_light(
                    m.transform_point3(Vec3::ZERO),
                    m.transform_vector3(Vec3::Z),
                    intensity,
                    (beam, cutoff),
                    &format!("line {}", n.line),
                )
            }
            "directional" => {
                let direction = match (p.get("direction"), p.get("to_world")) {
                    (Some(_), Some(_)) => {
                        return Err(
                            self.err(n, "directional: give direction or to_world, not both")
                        );
                    }
                    (Some(v), None) => self.point(v)?,
                    (None, Some(t)) => self.transform(t)?.transform_vector3(Vec3::Z),
                    (None, None) => Vec3::Z,
                };
                let irradiance = self.emission(&p, "irradiance")?;
                p.consume("sampling_weight");
                self.report_unused(&p, "emitter \"directional\"");
                self.warn(
                    n,
                    format!(
                        "a directional light is rendered as a sun {} degrees across",
                        2.0 * crate::light::environment::SUN_ANGULAR_RADIUS_DEG
                    ),
                );
                let sun = Sun::directional(direction, irradiance)
                    .ok_or_else(|| self.err(n, "directional: the direction is zero"))?;
                self.b.add_sun(sun, &format!("line {}", n.line))
            }
            "constant" | "envmap" => {
                if std::mem::replace(&mut self.environment_seen, true) {
                    return Err(self.err(
                        n,
                        "more than one environment emitter (Mitsuba 3 refuses it too)",
                    ));
                }
                let env = if ty == "constant" {
                    Environment::constant(self.emission(&p, "radiance")?)
                } else {
                    let rel = self
                        .string(&p, "filename")?
                        .ok_or_else(|| self.err(n, "envmap has no filename"))?;
                    let scale = self.float(&p, "scale", 1.0)?;
                    let m = self.to_world(&p)?;
                    p.consume("mis_compensation");
                    let file = self
                        .b
                        .resolver()
                        .resolve(&rel, "envmap")
                        .map_err(|e| self.err(n, e.message))?;
                    let linear = ["exr", "hdr", "pfm"]
                        .iter()
                        .any(|e| rel.to_ascii_lowercase().ends_with(&format!(".{e}")));
                    let image = self
                        .bitmaps
                        .load(&file, !linear)
                        .map_err(|e| self.err(n, format!("envmap \"{rel}\": {e}")))?;
                    Environment::image(
                        image.width,
                        image.height,
                        image.to_rgb(),
                        scale,
                        &rotation_of(&m),
                    )
                    .map_err(|e| self.err(n, format!("envmap \"{rel}\": {e}")))?
                };
                p.consume("sampling_weight");
                self.report_unused(&p, &format!("emitter \"{ty}\""));
                self.b.set_environment(env);
                Ok(())
            }
            "sunsky" | "projector" => {
                self.refuse(n, format!("emitter \"{ty}\" is not supported"));
                Ok(())
            }
            other => {
                self.refuse(n, format!("emitter \"{other}\" is not supported"));
                Ok(())
            }
        }
    }

    /// An emission property (`radiance`, `intensity`, `irradiance`): Mitsuba's default is a
    /// flat spectrum of 1; a texture is refused (the radiance would vary over the light).
    fn emission(&mut self, p: &Props, name: &str) -> R<Rgb> {
        match p.get(name) {
            None => Ok(Rgb::from_array(FLAT_EMISSION_RGB)),
            Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => {
                let v = v.clone();
                self.refuse(&v, format!("a textured {name} is not supported"));
                Ok(Rgb::ZERO)
            }
            Some(v) => self.color(v, ColorUse::Emission),
        }
    }
}

/// The rotation part of `m` (columns normalised): an environment map turns, it does not scale.
fn rotation_of(m: &Mat4) -> Mat4 {
    Mat4::from_cols(
        m.x_axis.truncate().normalize_or_zero().extend(0.0),
        m.y_axis.truncate().normalize_or_zero().extend(0.0),
        m.z_axis.truncate().normalize_or_zero().extend(0.0),
        glam::Vec4::W,
    )
}
