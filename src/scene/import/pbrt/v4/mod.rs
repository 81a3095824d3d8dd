//! pbrt-v4 files (Pharr, Jakob and Humphreys, *Physically Based Rendering*, 4th ed., 2023, and
//! pbrt-v4's file format documentation), read by the pbrt-v3 parser with these directives in
//! pbrt-v4's meaning: `ColorSpace`, `Option`, `Attribute`, `Import`, the film, the materials
//! (`materials`), textures (`textures`), lights (`lights`) and shapes (`shapes`); pbrt-v4's named
//! spectra and blackbodies become RGB once (`spectra`). The rest (transforms, the camera,
//! `Include`, instancing, the sampler, the integrator's `maxdepth`) means the same in both.
//!
//! Conventions of pbrt-v4 that matter here:
//! - named materials and textures are global: `AttributeEnd` does not forget them;
//! - every light's spectrum is scaled to 1 nit before its `scale` (a float) and `power` apply,
//!   so `"rgb L" [r g b]` is radiance (r, g, b) and a blackbody or named illuminant has
//!   luminance 1;
//! - `TrowbridgeReitzDistribution::RoughnessToAlpha` is sqrt(roughness);
//! - there is no `WorldEnd`: the scene ends with the file.
//!
//! What our renderer cannot represent is a warning naming the file and line; what would change
//! the image's meaning (an emitter, a material or a colour space we do not have) is refused, and
//! every such construct of the scene is named at once.

mod lights;
mod materials;
mod shapes;
pub(super) mod spectra;
mod textures;

use super::lexer::{Loc, Tok, Token};
use super::params::ParamSet;
use super::{Parser, R};
use crate::scene::SceneError;
use std::rc::Rc;

/// The targets of `Attribute`.
const ATTRIBUTE_TARGETS: [&str; 5] = ["shape", "light", "material", "medium", "texture"];

/// `Option`s that change what the image means, refused (the others only change how it is
/// computed, or what is written besides it).
const REFUSED_OPTIONS: [&str; 1] = ["forcediffuse"];

impl Parser {
    /// Handles the directives pbrt-v4 reads differently from pbrt-v3; false for the others.
    pub(super) fn v4_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
            "ColorSpace" => {
                let space = self.arg_str(name)?;
                if space != "srgb" {
                    self.refuse(
                        loc,
                        format!(
                            "ColorSpace \"{space}\": only \"srgb\" is supported (our RGB is linear sRGB)"
                        ),
                    );
                }
            }
            "Option" => {
                let ps = self.params()?;
                ps.consume_all();
                for p in &ps.params {
                    let on = !matches!(&p.values, super::params::Values::Bools(v) if v == &[false]);
                    if REFUSED_OPTIONS.contains(&p.name.as_str()) && on {
                        self.refuse(p.loc, format!("Option \"{}\" is not supported", p.decl));
                    } else {
                        self.warn(
                            p.loc,
                            format!("Option \"{}\" has no effect here and was ignored", p.decl),
                        );
                    }
                }
            }
            "Attribute" => {
                let target = self.arg_str(name)?;
                let ps = self.params()?;
                if !ATTRIBUTE_TARGETS.contains(&target.as_str()) {
                    return Err(self.err(
                        loc,
                        format!(
                            "Attribute \"{target}\": the target must be one of {}",
                            ATTRIBUTE_TARGETS.join(", ")
                        ),
                    ));
                }
                let defaults = Rc::make_mut(&mut self.g.attributes)
                    .entry(target)
                    .or_default();
                // A later default of the same name wins (lookups take the last one).
                defaults.params.extend(ps.params);
            }
            // pbrt-v4's Import reads a file as Include does (pbrt-v4 only restricts what it
            // may contain, to parse it in parallel).
            "Import" => return self.block_directive("Include", loc),
            "AttributeEnd" | "ObjectEnd" => {
                // Named materials and textures outlive the attribute block in pbrt-v4.
                let named = self.g.named.clone();
                let float_tex = self.g.float_tex.clone();
                let spec_tex = self.g.spec_tex.clone();
                let handled = if name == "AttributeEnd" {
                    self.block_directive(name, loc)?
                } else {
                    self.object_directive(name, loc)?
                };
                self.g.named = named;
                self.g.float_tex = float_tex;
                self.g.spec_tex = spec_tex;
                return Ok(handled);
            }
            "Film" => self.v4_film(loc)?,
            "WorldBegin" => {
                if !self.filter_seen {
                    self.warn(
                        loc,
                        "pbrt-v4's default pixel filter (a Gaussian of radius 1.5) is replaced by our one-pixel box filter",
                    );
                }
                return Ok(false);
            }
            "PixelFilter" => {
                self.options_only(name, loc)?;
                self.filter_seen = true;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                ps.consume_all();
                // pbrt-v4's default filter is a Gaussian of radius 1.5.
                let radius = if ty == "box" { 0.5 } else { 1.5 };
                let (x, y) = (
                    self.float(&ps, "xradius", radius)?,
                    self.float(&ps, "yradius", radius)?,
                );
                if ty != "box" || x != 0.5 || y != 0.5 {
                    self.warn(
                        loc,
                        format!("PixelFilter \"{ty}\" of radius {x} x {y}: our one-pixel box filter is used"),
                    );
                }
            }
            "Integrator" => {
                // Integrators that render something else than the light transport.
                if let Some(Token {
                    tok: Tok::Str(ty), ..
                }) = self.peek()
                    && matches!(ty.as_str(), "ambientocclusion" | "aov")
                {
                    let ty = ty.clone();
                    self.refuse(
                        loc,
                        format!("Integrator \"{ty}\" renders no light transport; not supported"),
                    );
                }
                return Ok(false);
            }
            "Material" | "MakeNamedMaterial" => self.v4_material_directive(name, loc)?,
            "Texture" => {
                self.world_only(name, loc)?;
                self.v4_texture(loc)?;
            }
            "AreaLightSource" => {
                self.world_only(name, loc)?;
                self.v4_area_light(loc)?;
            }
            "LightSource" => {
                self.world_only(name, loc)?;
                self.v4_light_source(loc)?;
            }
            "Shape" => self.v4_shape(loc)?,
            "ObjectInstance" => self.v4_object_instance(loc)?,
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// Records a construct the scene needs and we cannot render (the load fails at the end,
    /// naming all of them).
    pub(super) fn refuse(&mut self, loc: Loc, m: impl Into<String>) {
        self.refused.push((loc, m.into()));
    }

    /// The error naming every refused construct, if any.
    pub(super) fn refuse_collected(&self) -> R<()> {
        let Some((first, _)) = self.refused.first() else {
            return Ok(());
        };
        let n = self.refused.len();
        let list = self
            .refused
            .iter()
            .map(|(loc, m)| format!("{}: {m}", self.place_of(*loc)))
            .collect::<Vec<_>>()
            .join("; ");
        Err(SceneError::new(
            &self.files[first.file as usize],
            format!("line {}", first.line),
            format!(
                "the pbrt-v4 scene cannot be rendered as the file means it ({n} reason{}): {list}",
                if n == 1 { "" } else { "s" }
            ),
        ))
    }

    /// `ps` with the `Attribute` defaults of `target` that it does not set itself (marked used:
    /// a default a directive does not read is no mistake of the file).
    pub(super) fn with_attributes(&self, target: &str, mut ps: ParamSet) -> ParamSet {
        if let Some(defaults) = self.g.attributes.get(target) {
            let own: Vec<String> = ps.params.iter().map(|p| p.name.clone()).collect();
            let mut merged: Vec<_> = defaults
                .params
                .iter()
                .filter(|d| !own.contains(&d.name))
                .cloned()
                .collect();
            for d in &merged {
                d.used.set(true);
            }
            merged.append(&mut ps.params);
            ps.params = merged;
        }
        ps
    }

    /// pbrt-v4's `Film` (`rgb`; `gbuffer` and `spectral` write the same RGB image besides their
    /// other channels): the resolution; a sensor or exposure that scales or tints the image is
    /// refused.
    fn v4_film(&mut self, loc: Loc) -> R<()> {
        self.options_only("Film", loc)?;
        let ty = self.arg_str("Film")?;
        let ps = self.params()?;
        match ty.as_str() {
            "rgb" => {}
            "gbuffer" | "spectral" => self.warn(
                loc,
                format!("Film \"{ty}\": only its RGB image is rendered (as Film \"rgb\")"),
            ),
            other => {
                self.refuse(loc, format!("Film \"{other}\" is not a pbrt-v4 film"));
            }
        }
        self.film_resolution(&ps, loc, (1280, 720))?;
        let _ = self.boolean(&ps, "savefp16", true)?;
        for (param, what) in [
            ("cropwindow", "a crop window"),
            ("pixelbounds", "pixel bounds"),
        ] {
            if ps.has(param) {
                ps.find(param, &["float", "integer"]);
                self.warn(
                    loc,
                    format!("Film: {what} is not supported; the whole image is rendered"),
                );
            }
        }
        let sensor = self
            .string(&ps, "sensor")?
            .unwrap_or_else(|| "cie1931".into());
        if sensor != "cie1931" {
            self.refuse(
                loc,
                format!(
                    "Film sensor \"{sensor}\": only the CIE 1931 sensor (pbrt-v4's default) is supported"
                ),
            );
        }
        // pbrt-v4's imaging ratio is exposure time x ISO / 100; the default is 1.
        let iso = self.float(&ps, "iso", 100.0)?;
        if iso != 100.0 {
            self.refuse(
                loc,
                format!("Film iso {iso} scales the image; only iso 100 is supported"),
            );
        }
        let white = self.float(&ps, "whitebalance", 0.0)?;
        if white != 0.0 {
            self.refuse(loc, format!("Film whitebalance {white} is not supported"));
        }
        if let Some(m) = self.opt_float(&ps, "maxcomponentvalue")?
            && m.is_finite()
        {
            self.warn(
                loc,
                format!("Film maxcomponentvalue {m}: samples are not clamped here"),
            );
        }
        self.report_unused(&ps, &format!("Film \"{ty}\""));
        Ok(())
    }
}
