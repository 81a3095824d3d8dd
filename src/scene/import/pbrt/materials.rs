//! Materials: pbrt-v3's material types mapped onto ours (`Material`, `MakeNamedMaterial`,
//! `NamedMaterial`), with `Texture` dispatched to the textures module.

use super::lexer::Loc;
use super::params::ParamSet;
use super::{Parser, R};
use crate::geometry::{Rgb, Vec3};
use crate::material::Distribution;
use crate::material::microfacet::MIN_ALPHA;
use crate::material::{Material, MaterialKind, Texture};
use crate::scene::import::common::{COPPER_ETA, COPPER_K, default_lambert};
use std::rc::Rc;

/// pbrt-v3's `TrowbridgeReitzDistribution::RoughnessToAlpha`: maps the perceptual `roughness`
/// of `remaproughness true` materials to the GGX alpha (a quartic fit in log roughness).
pub fn roughness_to_alpha(roughness: f32) -> f32 {
    let x = roughness.max(1e-3).ln();
    1.62142 + 0.819955 * x + 0.1734 * x * x + 0.0171201 * x * x * x + 0.000640711 * x * x * x * x
}

impl Parser {
    /// Handles `Material`, `MakeNamedMaterial`, `NamedMaterial` and `Texture`; false for any
    /// other directive.
    pub(super) fn material_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
            "Material" => {
                self.world_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                let m = self.material(&ty, &ps, &format!("{ty} (line {})", loc.line), loc)?;
                self.g.material = Some(m);
            }
            "MakeNamedMaterial" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                let ps = self.params()?;
                let Some(ty) = self.string(&ps, "type")? else {
                    return Err(self.err(
                        loc,
                        format!("MakeNamedMaterial \"{n}\" has no \"string type\""),
                    ));
                };
                let m = self.material(&ty, &ps, &n, loc)?;
                Rc::make_mut(&mut self.g.named).insert(n, m);
            }
            "NamedMaterial" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                match self.g.named.get(&n) {
                    Some(&m) => self.g.material = Some(m),
                    None => {
                        return Err(
                            self.err(loc, format!("NamedMaterial: unknown material \"{n}\""))
                        );
                    }
                }
            }
            "Texture" => {
                self.world_only(name, loc)?;
                self.texture_directive(loc)?;
            }
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// (alpha_u, alpha_v) of a microfacet material: `uroughness`/`vroughness` override
    /// `roughness`; with `remaproughness` (default true) pbrt-v3's RoughnessToAlpha applies.
    pub(super) fn alphas(
        &mut self,
        ps: &ParamSet,
        default: f32,
        what: &str,
        loc: Loc,
    ) -> R<(f32, f32)> {
        self.microfacet_alphas(
            ps,
            default,
            roughness_to_alpha,
            |what| format!("{what}: roughness below {MIN_ALPHA} is traced as GGX alpha {MIN_ALPHA} (near-specular)"),
            what,
            loc,
        )
    }

    /// (alpha_u, alpha_v) of a microfacet material, as pbrt's versions read it: `uroughness`
    /// and `vroughness` override `roughness` (`default`), `remap` turns them into alphas unless
    /// `remaproughness` is false; below our smallest alpha they are clamped with the warning
    /// `clamped` words for `what`.
    pub(super) fn microfacet_alphas(
        &mut self,
        ps: &ParamSet,
        default: f32,
        remap: fn(f32) -> f32,
        clamped: fn(&str) -> String,
        what: &str,
        loc: Loc,
    ) -> R<(f32, f32)> {
        let r = self.float_or_tex(ps, "roughness", default, what)?;
        let u = if ps.has("uroughness") {
            self.float_or_tex(ps, "uroughness", r, what)?
        } else {
            r
        };
        let v = if ps.has("vroughness") {
            self.float_or_tex(ps, "vroughness", r, what)?
        } else {
            r
        };
        if !(u >= 0.0 && v >= 0.0) {
            return Err(self.err(loc, format!("{what}: roughness must be >= 0")));
        }
        let (mut au, mut av) = if self.boolean(ps, "remaproughness", true)? {
            (remap(u), remap(v))
        } else {
            (u, v)
        };
        if au < MIN_ALPHA || av < MIN_ALPHA {
            self.warn(loc, clamped(what));
            au = au.max(MIN_ALPHA);
            av = av.max(MIN_ALPHA);
        }
        Ok((au, av))
    }

    pub(super) fn isotropic(&mut self, (au, av): (f32, f32), what: &str, loc: Loc) -> f32 {
        if (au - av).abs() > 1e-6 * au.max(av) {
            self.warn(
                loc,
                format!("{what}: anisotropic roughness is not supported by our plastic; alpha sqrt(au av) used"),
            );
        }
        (au * av).sqrt()
    }

    /// pbrt's default material, `matte` with Kd 0.5 (two-sided, as all pbrt-v3 materials).
    pub(super) fn default_material(&mut self) -> u32 {
        let name = "pbrt default (matte, Kd 0.5)";
        default_lambert(&mut self.b, &mut self.default_material, name, true)
    }

    pub(super) fn current_material(&mut self) -> u32 {
        match self.g.material {
            Some(m) => m,
            None => self.default_material(),
        }
    }

    /// Creates a material of pbrt-v3 type `ty`; returns its builder index.
    pub(super) fn material(&mut self, ty: &str, ps: &ParamSet, name: &str, loc: Loc) -> R<u32> {
        let what = format!("material \"{name}\" ({ty})");
        if ps.has("bumpmap") {
            ps.find("bumpmap", &["texture", "float"]);
            self.warn(
                loc,
                format!("{what}: bump mapping is not supported and was ignored"),
            );
        }
        let kind = match ty {
            "matte" => {
                let albedo = self.spec_texture(ps, "Kd", Rgb::splat(0.5), &what)?;
                let sigma = self.float_or_tex(ps, "sigma", 0.0, &what)?;
                if sigma != 0.0 {
                    self.warn(
                        loc,
                        format!(
                            "{what}: Oren-Nayar sigma {sigma} is not supported; Lambertian used"
                        ),
                    );
                }
                MaterialKind::Lambert { albedo }
            }
            "plastic" => {
                // pbrt-v3 PlasticMaterial: Lambertian Kd plus a Trowbridge-Reitz (GGX) coat with
                // dielectric Fresnel (eta 1.5), added without energy coupling.
                let diffuse = self.spec_texture(ps, "Kd", Rgb::splat(0.25), &what)?;
                let specular = self.spec_const(ps, "Ks", Rgb::splat(0.25), &what)?;
                let a = self.alphas(ps, 0.1, &what, loc)?;
                let alpha = self.isotropic(a, &what, loc);
                MaterialKind::Plastic {
                    distribution: Distribution::Ggx,
                    diffuse,
                    specular,
                    ior: 1.5,
                    alpha,
                    layered: false,
                    nonlinear: false,
                }
            }
            "substrate" => {
                // pbrt-v3 SubstrateMaterial is Ashikhmin-Shirley's FresnelBlend: a glossy coat
                // over a diffuse base with energy coupling. Our closest model is the layered
                // plastic (Mitsuba's roughplastic coupling, eta 1.5).
                let diffuse = self.spec_texture(ps, "Kd", Rgb::splat(0.5), &what)?;
                let specular = self.spec_const(ps, "Ks", Rgb::splat(0.5), &what)?;
                let a = self.alphas(ps, 0.1, &what, loc)?;
                let alpha = self.isotropic(a, &what, loc);
                self.warn(
                    loc,
                    "substrate (Ashikhmin-Shirley FresnelBlend) approximated by our layered plastic (ior 1.5, same alpha)",
                );
                MaterialKind::Plastic {
                    distribution: Distribution::Ggx,
                    diffuse,
                    specular,
                    ior: 1.5,
                    alpha,
                    layered: true,
                    nonlinear: false,
                }
            }
            "metal" => {
                let eta = self.spec_const(ps, "eta", Vec3::from_array(COPPER_ETA), &what)?;
                let k = self.spec_const(ps, "k", Vec3::from_array(COPPER_K), &what)?;
                let (alpha_u, alpha_v) = self.alphas(ps, 0.01, &what, loc)?;
                MaterialKind::RoughConductor {
                    distribution: Distribution::Ggx,
                    eta,
                    k,
                    alpha_u,
                    alpha_v,
                    scale: Rgb::ONE,
                }
            }
            "mirror" => MaterialKind::Mirror {
                reflectance: self.spec_const(ps, "Kr", Rgb::splat(0.9), &what)?,
            },
            "glass" => {
                let reflectance = self.spec_const(ps, "Kr", Rgb::ONE, &what)?;
                let transmittance = self.spec_const(ps, "Kt", Rgb::ONE, &what)?;
                let ior = self.glass_eta(ps, &what, loc)?;
                let u = self.float_or_tex(ps, "uroughness", 0.0, &what)?;
                let v = self.float_or_tex(ps, "vroughness", 0.0, &what)?;
                let _ = self.boolean(ps, "remaproughness", true)?;
                if u > 0.0 || v > 0.0 {
                    self.warn(
                        loc,
                        format!("{what}: rough glass is not supported; traced as smooth glass"),
                    );
                }
                MaterialKind::Dielectric {
                    ior,
                    reflectance,
                    transmittance,
                }
            }
            "uber" => {
                // pbrt-v3 UberMaterial: Kd Lambertian + Ks GGX coat (Fresnel eta) added, plus
                // specular Kr reflection and Kt transmission, all scaled by opacity.
                let kd = self.spec_texture(ps, "Kd", Rgb::splat(0.25), &what)?;
                let ks = self.spec_const(ps, "Ks", Rgb::splat(0.25), &what)?;
                let kr = self.spec_const(ps, "Kr", Rgb::ZERO, &what)?;
                let kt = self.spec_const(ps, "Kt", Rgb::ZERO, &what)?;
                let ior = self.glass_eta(ps, &what, loc)?;
                let opacity = self.spec_const(ps, "opacity", Rgb::ONE, &what)?;
                let a = self.alphas(ps, 0.1, &what, loc)?;
                if opacity != Rgb::ONE {
                    self.warn(
                        loc,
                        format!("{what}: opacity < 1 is not supported; opaque surface used"),
                    );
                }
                let has_diffuse = kd.max_value() != Rgb::ZERO || ks != Rgb::ZERO;
                if !has_diffuse && (kr != Rgb::ZERO || kt != Rgb::ZERO) {
                    // Only the specular layers: that is pbrt's smooth glass.
                    MaterialKind::Dielectric {
                        ior,
                        reflectance: kr,
                        transmittance: kt,
                    }
                } else {
                    if kr != Rgb::ZERO || kt != Rgb::ZERO {
                        self.warn(
                            loc,
                            format!("{what}: specular Kr/Kt layers together with Kd/Ks are not supported; they were dropped (additive plastic used)"),
                        );
                    }
                    let alpha = self.isotropic(a, &what, loc);
                    MaterialKind::Plastic {
                        distribution: Distribution::Ggx,
                        diffuse: kd,
                        specular: ks,
                        ior,
                        alpha,
                        layered: false,
                        nonlinear: false,
                    }
                }
            }
            "mix" => {
                ps.consume_all();
                let first = self.string(ps, "namedmaterial1")?;
                if let Some(n) = first
                    && let Some(&m) = self.g.named.get(&n)
                {
                    self.warn(
                        loc,
                        format!(
                            "material \"mix\" is not supported: became its first material \"{n}\""
                        ),
                    );
                    return Ok(m);
                }
                self.warn(
                    loc,
                    "material \"mix\" is not supported: became matte (Kd 0.5)",
                );
                MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::splat(0.5)),
                }
            }
            "" | "none" | "interface" => {
                self.warn(
                    loc,
                    format!("material \"{ty}\" (no surface) is not supported: became an opaque black matte surface"),
                );
                MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::ZERO),
                }
            }
            other => {
                let albedo = self.spec_texture(ps, "Kd", Rgb::splat(0.5), &what)?;
                ps.consume_all();
                self.warn(
                    loc,
                    format!("material \"{other}\" is not supported: became matte with its Kd (default 0.5)"),
                );
                MaterialKind::Lambert { albedo }
            }
        };
        self.report_unused(ps, &what);
        Ok(self.b.add_material(Material::new(name, kind, true)))
    }

    pub(super) fn glass_eta(&mut self, ps: &ParamSet, what: &str, loc: Loc) -> R<f32> {
        // pbrt-v3 reads "eta", falling back to the older "index".
        let eta = if ps.has("eta") {
            self.float_or_tex(ps, "eta", 1.5, what)?
        } else {
            self.float_or_tex(ps, "index", 1.5, what)?
        };
        if !(eta > 0.0 && eta.is_finite()) {
            return Err(self.err(
                loc,
                format!("{what}: index of refraction must be > 0, got {eta}"),
            ));
        }
        Ok(eta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roughness_remap_matches_pbrt() {
        // Values of pbrt-v3's RoughnessToAlpha.
        assert!((roughness_to_alpha(1.0) - 1.62142).abs() < 1e-5);
        let a = roughness_to_alpha(0.1);
        assert!(a > 0.1 && a < 0.5, "{a}");
        assert_eq!(roughness_to_alpha(0.0), roughness_to_alpha(1e-3));
    }
}
