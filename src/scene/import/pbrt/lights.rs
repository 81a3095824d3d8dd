//! Lights: `AreaLightSource "diffuse"` and `LightSource "point"`.

use super::lexer::Loc;
use super::{Parser, R};
use crate::geometry::{Rgb, Vec3};

impl Parser {
    /// Handles `AreaLightSource` and `LightSource`; false for any other directive.
    pub(super) fn light_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
            "AreaLightSource" => {
                self.world_only(name, loc)?;
                self.area_light(loc)?;
            }
            "LightSource" => {
                self.world_only(name, loc)?;
                self.light_source(loc)?;
            }
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// The emission that shapes get from now on in this attribute block.
    fn area_light(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("AreaLightSource")?;
        let ps = self.params()?;
        if ty != "diffuse" {
            return Err(self.err(
                loc,
                format!("AreaLightSource \"{ty}\" is not supported (only \"diffuse\")"),
            ));
        }
        let l = self.color(&ps, "L", Rgb::ONE)?;
        let scale = self.color(&ps, "scale", Rgb::ONE)?;
        if self.boolean(&ps, "twosided", false)? {
            self.warn(
                loc,
                "AreaLightSource \"diffuse\": twosided is not supported; the light emits on the front side only (half the power of pbrt's)",
            );
        }
        let _ = self.int(&ps, "samples", 1)?; // sample count: no effect on the expected image
        self.report_unused(&ps, "AreaLightSource \"diffuse\"");
        self.g.area = Some(l * scale);
        Ok(())
    }

    /// A point light, placed by the current transform.
    fn light_source(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("LightSource")?;
        let ps = self.params()?;
        match ty.as_str() {
            "point" => {
                let i = self.color(&ps, "I", Rgb::ONE)?;
                let scale = self.color(&ps, "scale", Rgb::ONE)?;
                let from = self
                    .vec3s(&ps, "from", &["point3"])?
                    .map(|v| v.first().copied().unwrap_or(Vec3::ZERO))
                    .unwrap_or(Vec3::ZERO);
                let pos = self.g.ctm.transform_point3(from);
                self.report_unused(&ps, "LightSource \"point\"");
                if self.defining.is_some() {
                    self.warn(loc, "lights inside object definitions are ignored (as in pbrt-v3)");
                    return Ok(());
                }
                self.b
                    .add_point_light(pos, i * scale, &format!("line {}", loc.line))
                    .map_err(|e| self.at(loc, e))
            }
            other => Err(self.err(
                loc,
                format!("LightSource \"{other}\" is not supported (only \"point\" lights and \"diffuse\" area lights)"),
            )),
        }
    }
}
