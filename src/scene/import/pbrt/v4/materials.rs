//! pbrt-v4's materials mapped onto ours (all two-sided, as pbrt-v4's are): `diffuse`,
//! `coateddiffuse`, `conductor`, `coatedconductor`, `dielectric`, `thindielectric` and `mix`;
//! the others (`interface`, `diffusetransmission`, `measured`, `hair`, `subsurface`) are
//! refused.

use super::super::lexer::Loc;
use super::super::params::ParamSet;
use super::super::{Parser, R};
use super::spectra::{SpectrumUse, is_glass};
use crate::geometry::Rgb;
use crate::material::Distribution;
use crate::material::microfacet::MIN_ALPHA;
use crate::material::{Material, MaterialKind, Texture};
use std::rc::Rc;

/// pbrt-v4's `TrowbridgeReitzDistribution::RoughnessToAlpha`: alpha = sqrt(roughness).
pub(super) fn roughness_to_alpha_v4(roughness: f32) -> f32 {
    roughness.max(0.0).sqrt()
}

/// The imaginary index of a conductor (real index 1) whose normal-incidence reflectance is `r`:
/// pbrt-v4's ConductorMaterial for `reflectance`, k = 2 sqrt(r) / sqrt(1 - r) (from the Fresnel
/// reflectance at normal incidence, ((eta - 1)^2 + k^2) / ((eta + 1)^2 + k^2), at eta = 1).
fn k_of_reflectance(r: f32) -> f32 {
    let r = r.clamp(0.0, 0.9999);
    2.0 * r.sqrt() / (1.0 - r).sqrt()
}

impl Parser {
    /// `Material` and `MakeNamedMaterial` of pbrt-v4.
    pub(super) fn v4_material_directive(&mut self, name: &str, loc: Loc) -> R<()> {
        self.world_only(name, loc)?;
        if name == "Material" {
            let ty = self.arg_str(name)?;
            let ps = self.params()?;
            let ps = self.with_attributes("material", ps);
            let m = self.v4_material(&ty, &ps, &format!("{ty} (line {})", loc.line), loc)?;
            self.g.material = Some(m);
        } else {
            let n = self.arg_str(name)?;
            let ps = self.params()?;
            let ps = self.with_attributes("material", ps);
            let Some(ty) = self.string(&ps, "type")? else {
                return Err(self.err(
                    loc,
                    format!("MakeNamedMaterial \"{n}\" has no \"string type\""),
                ));
            };
            if self.g.named.contains_key(&n) {
                self.warn(
                    loc,
                    format!(
                        "MakeNamedMaterial \"{n}\" redefines the material (the last one is used)"
                    ),
                );
            }
            let m = self.v4_material(&ty, &ps, &n, loc)?;
            Rc::make_mut(&mut self.g.named).insert(n, m);
        }
        Ok(())
    }

    /// A reflectance (a texture or a value, default `default`).
    fn v4_reflectance(
        &mut self,
        ps: &ParamSet,
        name: &str,
        default: Rgb,
        what: &str,
    ) -> R<Texture> {
        if ps
            .params
            .iter()
            .any(|p| p.name == name && p.ty == "texture")
        {
            return self.spec_texture(ps, name, default, what);
        }
        let c = self
            .v4_spectrum(ps, name, SpectrumUse::Material)?
            .unwrap_or(default);
        if c.min_element() < 0.0 {
            let loc = ps.loc_of(name).unwrap_or(self.last_loc);
            return Err(self.err(loc, format!("{what}: '{name}' must be >= 0, got {c:?}")));
        }
        Ok(Texture::Constant(c))
    }

    /// An index of refraction given as a float or a (named) spectrum: one number.
    fn v4_eta(&mut self, ps: &ParamSet, default: f32, what: &str, loc: Loc) -> R<f32> {
        let named = ps
            .params
            .iter()
            .rev()
            .find(|p| p.name == "eta")
            .and_then(|p| match &p.values {
                super::super::params::Values::Strs(v) => v.first().cloned(),
                _ => None,
            });
        let eta = if ps
            .params
            .iter()
            .any(|p| p.name == "eta" && p.ty == "texture")
        {
            self.float_or_tex(ps, "eta", default, what)?
        } else {
            match self.v4_spectrum(ps, "eta", SpectrumUse::Material)? {
                Some(c) => {
                    if let Some(n) = named.filter(|n| is_glass(n)) {
                        self.warn(
                            loc,
                            format!("{what}: the dispersion of \"{n}\" is not rendered; its mean index is used"),
                        );
                    } else if (c.max_element() - c.min_element()).abs() > 1e-6 {
                        self.warn(
                            loc,
                            format!("{what}: an index of refraction varying with wavelength is not supported; its mean is used"),
                        );
                    }
                    (c.x + c.y + c.z) / 3.0
                }
                None => default,
            }
        };
        if !(eta > 0.0 && eta.is_finite()) {
            return Err(self.err(
                loc,
                format!("{what}: index of refraction must be > 0, got {eta}"),
            ));
        }
        Ok(eta)
    }

    /// (alpha_u, alpha_v) of a microfacet material in pbrt-v4's conventions: `uroughness` and
    /// `vroughness` override `roughness` (default 0), remapped by sqrt unless
    /// `remaproughness` is false; below our smallest alpha, warned and clamped.
    fn v4_alphas(&mut self, ps: &ParamSet, what: &str, loc: Loc) -> R<(f32, f32)> {
        self.microfacet_alphas(
            ps,
            0.0,
            roughness_to_alpha_v4,
            |what| format!("{what}: roughness below GGX alpha {MIN_ALPHA} is traced as alpha {MIN_ALPHA} (near-specular)"),
            what,
            loc,
        )
    }

    /// A conductor's (eta, k): `reflectance` (pbrt-v4's artist-friendly form) or `eta` and `k`
    /// (default copper), each with `prefix` (`conductor.` in a coated conductor).
    fn v4_conductor_indices(&mut self, ps: &ParamSet, prefix: &str, what: &str) -> R<(Rgb, Rgb)> {
        let refl = format!("{prefix}reflectance");
        if ps.has(&refl) {
            let r = self.v4_reflectance(ps, &refl, Rgb::ONE, what)?;
            let r = r.average();
            return Ok((
                Rgb::ONE,
                Rgb::new(
                    k_of_reflectance(r.x),
                    k_of_reflectance(r.y),
                    k_of_reflectance(r.z),
                ),
            ));
        }
        let eta = self
            .v4_spectrum(ps, &format!("{prefix}eta"), SpectrumUse::Material)?
            .unwrap_or(Rgb::from_array(COPPER_ETA_V4));
        let k = self
            .v4_spectrum(ps, &format!("{prefix}k"), SpectrumUse::Material)?
            .unwrap_or(Rgb::from_array(COPPER_K_V4));
        Ok((eta, k))
    }

    /// Creates a material of pbrt-v4 type `ty`; returns its builder index.
    pub(super) fn v4_material(&mut self, ty: &str, ps: &ParamSet, name: &str, loc: Loc) -> R<u32> {
        let what = format!("material \"{name}\" ({ty})");
        for ignored in ["displacement", "normalmap"] {
            if ps.has(ignored) {
                ps.find(ignored, &["texture", "float", "string"]);
                self.warn(
                    loc,
                    format!("{what}: \"{ignored}\" is not supported and was ignored"),
                );
            }
        }
        let kind = match ty {
            "diffuse" => MaterialKind::Lambert {
                albedo: self.v4_reflectance(ps, "reflectance", Rgb::splat(0.5), &what)?,
            },
            "coateddiffuse" => {
                let diffuse = self.v4_reflectance(ps, "reflectance", Rgb::splat(0.5), &what)?;
                let a = self.v4_alphas(ps, &what, loc)?;
                let alpha = self.isotropic(a, &what, loc);
                let ior = self.v4_eta(ps, 1.5, &what, loc)?;
                let albedo = self.v4_spectrum(ps, "albedo", SpectrumUse::Material)?;
                let _ = self.float_or_tex(ps, "thickness", 0.01, &what)?;
                let _ = self.float_or_tex(ps, "g", 0.0, &what)?;
                let _ = self.int(ps, "maxdepth", 10)?;
                let _ = self.int(ps, "nsamples", 1)?;
                self.warn(
                    loc,
                    "coateddiffuse: pbrt-v4's stochastic layering is approximated by our layered plastic (a GGX dielectric coat over a Lambertian base, Mitsuba's roughplastic coupling with its nonlinear internal scattering)",
                );
                if albedo.is_some_and(|a| a != Rgb::ZERO) {
                    self.warn(
                        loc,
                        format!("{what}: a scattering medium between the layers (albedo) is not supported; left out"),
                    );
                }
                // Light reflected inside the coat meets the base again (kd once more each time),
                // as pbrt-v4's random walk between the layers simulates: Mitsuba's "nonlinear"
                // kd / (1 - kd Fdr) rather than kd / (1 - Fdr).
                MaterialKind::Plastic {
                    distribution: Distribution::Ggx,
                    diffuse,
                    specular: Rgb::ONE,
                    ior,
                    alpha,
                    layered: true,
                    nonlinear: true,
                }
            }
            "conductor" | "coatedconductor" => {
                let prefix = if ty == "conductor" { "" } else { "conductor." };
                let (eta, k) = self.v4_conductor_indices(ps, prefix, &what)?;
                let (alpha_u, alpha_v) = if ty == "conductor" {
                    self.v4_alphas(ps, &what, loc)?
                } else {
                    let inner = ParamSet {
                        params: ps
                            .params
                            .iter()
                            .filter_map(|p| {
                                let n = p.name.strip_prefix("conductor.")?;
                                let mut q = p.clone();
                                q.name = n.to_string();
                                p.used.set(true);
                                Some(q)
                            })
                            .filter(|p| p.name.contains("roughness"))
                            .collect(),
                    };
                    ps.consume_all();
                    self.warn(
                        loc,
                        format!("{what}: the dielectric coat is not supported; the conductor under it is rendered bare"),
                    );
                    self.v4_alphas(&inner, &what, loc)?
                };
                MaterialKind::RoughConductor {
                    distribution: Distribution::Ggx,
                    eta,
                    k,
                    alpha_u,
                    alpha_v,
                    scale: Rgb::ONE,
                }
            }
            "dielectric" | "thindielectric" => {
                let ior = self.v4_eta(ps, 1.5, &what, loc)?;
                if ty == "thindielectric" {
                    MaterialKind::ThinDielectric {
                        ior,
                        reflectance: Rgb::ONE,
                        transmittance: Rgb::ONE,
                    }
                } else {
                    let rough = ["roughness", "uroughness", "vroughness"]
                        .iter()
                        .any(|k| ps.has(k));
                    let (alpha_u, alpha_v) = if rough {
                        self.v4_alphas(ps, &what, loc)?
                    } else {
                        (0.0, 0.0)
                    };
                    // pbrt-v4 traces a dielectric whose alphas are below 1e-3 as smooth.
                    if alpha_u.max(alpha_v) > MIN_ALPHA {
                        MaterialKind::RoughDielectric {
                            distribution: Distribution::Ggx,
                            ior,
                            alpha_u,
                            alpha_v,
                            reflectance: Rgb::ONE,
                            transmittance: Rgb::ONE,
                        }
                    } else {
                        let _ = self.boolean(ps, "remaproughness", true)?;
                        MaterialKind::Dielectric {
                            ior,
                            reflectance: Rgb::ONE,
                            transmittance: Rgb::ONE,
                        }
                    }
                }
            }
            "mix" => return self.v4_mix(ps, &what, loc),
            other => {
                ps.consume_all();
                let why = match other {
                    "interface" | "" | "none" => "no surface (a medium boundary) is not supported",
                    "diffusetransmission" => "diffuse transmission is not supported",
                    "measured" => "measured BSDFs are not supported",
                    "hair" => "hair is not supported",
                    "subsurface" => "subsurface scattering is not supported",
                    _ => "unknown material type",
                };
                self.refuse(loc, format!("material \"{other}\": {why}"));
                return Ok(self.default_material());
            }
        };
        self.report_unused(ps, &what);
        Ok(self.b.add_material(Material::new(name, kind, true)))
    }

    /// `mix`: pbrt-v4 picks `materials[1]` with probability `amount` at each point; we keep
    /// the one of larger weight.
    fn v4_mix(&mut self, ps: &ParamSet, what: &str, loc: Loc) -> R<u32> {
        let names = match ps.find("materials", &["string"]) {
            Some(p) => match &p.values {
                super::super::params::Values::Strs(v) if v.len() == 2 => v.clone(),
                _ => {
                    return Err(self.err(
                        p.loc,
                        format!("{what}: \"materials\" must name 2 materials"),
                    ));
                }
            },
            None => return Err(self.err(loc, format!("{what} has no \"string materials\""))),
        };
        let amount = self.float_or_tex(ps, "amount", 0.5, what)?;
        self.report_unused(ps, what);
        let pick = usize::from(amount > 0.5);
        if amount > 0.0 && amount < 1.0 {
            self.warn(
                loc,
                format!(
                    "{what}: a stochastic mix is not supported; the material of larger weight (\"{}\", {}) is used",
                    names[pick],
                    if pick == 1 { amount } else { 1.0 - amount }
                ),
            );
        }
        match self.g.named.get(&names[pick]) {
            Some(&m) => Ok(m),
            None => Err(self.err(loc, format!("{what}: unknown material \"{}\"", names[pick]))),
        }
    }
}

/// pbrt-v4's default conductor, copper (`metal-Cu-eta`, `metal-Cu-k`), in RGB as `spectra`
/// reduces it (a unit test checks they agree).
const COPPER_ETA_V4: [f32; 3] = [0.104495, 0.97817, 1.20467];
/// See [`COPPER_ETA_V4`].
const COPPER_K_V4: [f32; 3] = [3.27334, 2.59235, 2.36924];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflectance_gives_the_conductor_that_reflects_it_at_normal_incidence() {
        for r in [0.05f32, 0.5, 0.9] {
            let k = k_of_reflectance(r);
            // Fresnel at normal incidence with eta = 1: k^2 / (4 + k^2).
            let back = k * k / (4.0 + k * k);
            assert!((back - r).abs() < 1e-5, "{r} -> {k} -> {back}");
        }
        assert_eq!(roughness_to_alpha_v4(0.25), 0.5);
    }

    #[test]
    fn the_default_copper_is_pbrt_v4s() {
        use super::super::spectra::named_spectrum;
        let eta = named_spectrum("metal-Cu-eta", SpectrumUse::Material);
        let k = named_spectrum("metal-Cu-k", SpectrumUse::Material);
        assert_eq!(eta, Some(Rgb::from_array(COPPER_ETA_V4)));
        assert_eq!(k, Some(Rgb::from_array(COPPER_K_V4)));
    }
}
