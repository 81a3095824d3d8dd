//! Emitters of Mitsuba 3 files that stand on their own (not attached to a shape): `point`, and
//! the ones we cannot render yet, refused by name.

use super::values::ColorUse;
use super::{Ctx, R};
use crate::geometry::{Rgb, Vec3};
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
                let intensity = match p.get("intensity") {
                    Some(v) => self.color(v, ColorUse::Emission)?,
                    None => Rgb::from_array(super::values::FLAT_EMISSION_RGB),
                };
                p.consume("sampling_weight");
                self.report_unused(&p, "emitter \"point\"");
                self.b
                    .add_point_light(position, intensity, &format!("line {}", n.line))
            }
            "area" => Err(self.err(n, "an area emitter must be attached to a shape")),
            "spot" | "directional" | "constant" | "envmap" | "sunsky" | "projector" => {
                self.refuse(n, format!("emitter \"{ty}\" is not supported yet"));
                Ok(())
            }
            other => {
                self.refuse(n, format!("emitter \"{other}\" is not supported"));
                Ok(())
            }
        }
    }
}
