//! BSDFs: Mitsuba 0.5's bsdf plugins mapped onto our materials, and the named indices of
//! refraction and conductors they may give.

use super::{Ctx, Obj, R};
use crate::geometry::{Rgb, Vec3};
use crate::material::Distribution;
use crate::material::microfacet::MIN_ALPHA;
use crate::material::{Material, MaterialKind, Texture};
use crate::scene::import::common::{COPPER_ETA, COPPER_K};
use crate::scene::import::xml::{Node, Props};

/// Mitsuba's named indices of refraction (Mitsuba 0.5 documentation, table of IOR values).
fn named_ior(name: &str) -> Option<f32> {
    Some(match name.to_ascii_lowercase().as_str() {
        "vacuum" => 1.0,
        "helium" => 1.00004,
        "hydrogen" => 1.00013,
        "air" => 1.00028,
        "carbon dioxide" => 1.00045,
        "water" => 1.3330,
        "acetone" => 1.36,
        "ethanol" => 1.361,
        "carbon tetrachloride" => 1.461,
        "glycerol" => 1.4729,
        "benzene" => 1.501,
        "silicone oil" => 1.52045,
        "bromine" => 1.661,
        "water ice" => 1.31,
        "fused quartz" => 1.458,
        "pyrex" => 1.470,
        "acrylic glass" => 1.49,
        "polypropylene" => 1.49,
        "bk7" => 1.5046,
        "sodium chloride" => 1.544,
        "amber" => 1.55,
        "pet" => 1.5750,
        "diamond" => 2.419,
        _ => return None,
    })
}

/// RGB complex IORs of Mitsuba's named conductors, as Bitterli's scene exports give them
/// (veach-mis, staircase, veach-bidir); `none` is Mitsuba's ideal mirror.
fn named_conductor(name: &str) -> Option<(Rgb, Rgb)> {
    Some(match name {
        "Cu" => (Vec3::from_array(COPPER_ETA), Vec3::from_array(COPPER_K)),
        "Au" => (
            Vec3::new(0.143119, 0.374957, 1.44248),
            Vec3::new(3.98316, 2.38572, 1.60322),
        ),
        "Al" => (
            Vec3::new(1.65746, 0.880369, 0.521229),
            Vec3::new(9.22387, 6.26952, 4.837),
        ),
        "CuZn" => (
            Vec3::new(2.8656, 2.11918, 1.94008),
            Vec3::new(3.03233, 2.05611, 1.61629),
        ),
        "none" => (Vec3::ZERO, Vec3::ONE),
        _ => return None,
    })
}

impl Ctx {
    /// An IOR: a number or one of Mitsuba's named materials.
    pub(super) fn ior(&self, p: &Props, name: &str, default: f32) -> R<f32> {
        match p.get(name) {
            None => Ok(default),
            Some(n) if n.tag == "string" => {
                let v = self.value_attr(n)?;
                named_ior(v).ok_or_else(|| self.err(n, format!("unknown IOR name \"{v}\"")))
            }
            Some(n) => {
                let v = self.num_of(n)?;
                if !(v > 0.0) {
                    return Err(self.err(n, format!("{}: must be > 0", n.label())));
                }
                Ok(v)
            }
        }
    }

    /// Translates a `<bsdf>` element, registering its id and the ids nested in it.
    pub(super) fn bsdf(&mut self, n: &Node) -> R<Material> {
        let m = self.bsdf_inner(n)?;
        if let Some(id) = n.attr("id") {
            self.register(
                n,
                id,
                Obj::Bsdf {
                    mat: m.clone(),
                    index: None,
                },
            )?;
        }
        Ok(m)
    }

    /// The material of a nested `<bsdf>` or `<ref>` child.
    pub(super) fn child_bsdf(&mut self, n: &Node, p: &Props) -> R<Option<Material>> {
        for c in &n.children {
            let named = c.attr("name").is_some();
            if c.tag == "bsdf" && !named {
                p.objects("bsdf");
                return Ok(Some(self.bsdf(c)?));
            }
            if c.tag == "ref" && !named {
                p.objects("ref");
                let id = c
                    .attr("id")
                    .ok_or_else(|| self.err(c, "<ref> without id"))?;
                return match self.ids.get(id) {
                    Some(Obj::Bsdf { mat, .. }) => Ok(Some(mat.clone())),
                    Some(_) => Err(self.err(c, format!("\"{id}\" is not a bsdf"))),
                    None => Err(self.err(c, format!("unknown id \"{id}\""))),
                };
            }
        }
        Ok(None)
    }

    pub(super) fn alpha(&mut self, n: &Node, p: &Props, what: &str) -> R<(f32, f32)> {
        let dist = self
            .string(p, "distribution")?
            .unwrap_or_else(|| "beckmann".into());
        match dist.as_str() {
            "ggx" => {}
            "beckmann" => self.warn(n, "beckmann approximated by ggx (same alpha)"),
            "phong" => self.warn(n, "phong microfacet distribution approximated by ggx (same alpha)"),
            "as" => self.warn(n, "Ashikhmin-Shirley microfacet distribution approximated by anisotropic ggx (same alphas)"),
            other => return Err(self.err(n, format!("{what}: unknown distribution \"{other}\""))),
        }
        let a = self.float(p, "alpha", 0.1)?;
        let au = self.float(p, "alphaU", a)?;
        let av = self.float(p, "alphaV", a)?;
        if !(au >= 0.0 && av >= 0.0) {
            return Err(self.err(n, format!("{what}: alpha must be >= 0")));
        }
        if au < MIN_ALPHA || av < MIN_ALPHA {
            self.warn(
                n,
                format!("{what}: alpha below {MIN_ALPHA} is traced as GGX alpha {MIN_ALPHA}"),
            );
        }
        p.consume("sampleVisible");
        Ok((au.max(MIN_ALPHA), av.max(MIN_ALPHA)))
    }

    /// Conductor eta and k, relative to the exterior IOR `extEta`.
    pub(super) fn conductor_ior(&mut self, n: &Node, p: &Props, what: &str) -> R<(Rgb, Rgb)> {
        let (mut eta, mut k) = (Vec3::from_array(COPPER_ETA), Vec3::from_array(COPPER_K));
        if let Some(name) = self.string(p, "material")? {
            (eta, k) = named_conductor(&name).ok_or_else(|| {
                self.err(n, format!("{what}: conductor material \"{name}\" is not known here (Cu, Au, Al, CuZn, none); give eta and k"))
            })?;
        }
        if let Some(e) = p.get("eta") {
            eta = self.color_of(e)?;
        }
        if let Some(e) = p.get("k") {
            k = self.color_of(e)?;
        }
        let ext = self.ior(p, "extEta", 1.00028)?;
        Ok((eta / ext, k / ext))
    }

    pub(super) fn bsdf_inner(&mut self, n: &Node) -> R<Material> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let name = n
            .attr("id")
            .map_or_else(|| format!("{ty} (line {})", n.line), str::to_string);
        let what = format!("bsdf \"{ty}\"");
        let one_sided = |kind| Material::new(name.clone(), kind, false);
        let m = match ty {
            "twosided" => {
                let inner: Vec<&Node> = n
                    .children
                    .iter()
                    .filter(|c| c.tag == "bsdf" || c.tag == "ref")
                    .collect();
                if inner.len() > 1 {
                    self.warn(n, "twosided with a different back-side bsdf is not supported; the front bsdf is used on both sides");
                }
                p.any_with_tag("bsdf");
                p.any_with_tag("ref");
                let Some(first) = inner.first() else {
                    return Err(self.err(n, "twosided has no nested bsdf"));
                };
                let mut m = if first.tag == "bsdf" {
                    self.bsdf(first)?
                } else {
                    let id = first
                        .attr("id")
                        .ok_or_else(|| self.err(first, "<ref> without id"))?;
                    match self.ids.get(id) {
                        Some(Obj::Bsdf { mat, .. }) => mat.clone(),
                        _ => return Err(self.err(first, format!("unknown bsdf id \"{id}\""))),
                    }
                };
                for extra in inner.iter().skip(1) {
                    if extra.tag == "bsdf" {
                        self.bsdf(extra)?;
                    }
                }
                m.name = name.clone();
                m.two_sided = true;
                m
            }
            "diffuse" | "roughdiffuse" => {
                if ty == "roughdiffuse" {
                    self.warn(
                        n,
                        "roughdiffuse (Oren-Nayar) approximated by a Lambertian diffuse bsdf",
                    );
                    p.consume("alpha");
                    p.consume("useFastApprox");
                }
                one_sided(MaterialKind::Lambert {
                    albedo: self.spectrum_tex(&p, "reflectance", Rgb::splat(0.5))?,
                })
            }
            "dielectric" | "roughdielectric" => {
                if ty == "roughdielectric" {
                    self.warn(n, "roughdielectric approximated by a smooth dielectric");
                    let _ = self.alpha(n, &p, &what)?;
                }
                let int = self.ior(&p, "intIOR", 1.5046)?;
                let ext = self.ior(&p, "extIOR", 1.00028)?;
                let reflectance =
                    self.spectrum_const(&p, "specularReflectance", Rgb::ONE, &what)?;
                let transmittance =
                    self.spectrum_const(&p, "specularTransmittance", Rgb::ONE, &what)?;
                Material::new(
                    name.clone(),
                    MaterialKind::Dielectric {
                        ior: int / ext,
                        reflectance,
                        transmittance,
                    },
                    true,
                )
            }
            "conductor" | "roughconductor" => {
                let (eta, k) = self.conductor_ior(n, &p, &what)?;
                let (alpha_u, alpha_v) = if ty == "conductor" {
                    self.warn(
                        n,
                        format!("smooth conductor traced as GGX alpha {MIN_ALPHA} (near-specular)"),
                    );
                    (MIN_ALPHA, MIN_ALPHA)
                } else {
                    self.alpha(n, &p, &what)?
                };
                // Mitsuba's specularReflectance multiplies the Fresnel reflectance: our `scale`.
                let scale = self.spectrum_const(&p, "specularReflectance", Rgb::ONE, &what)?;
                one_sided(MaterialKind::RoughConductor {
                    distribution: Distribution::Ggx,
                    eta,
                    k,
                    alpha_u,
                    alpha_v,
                    scale,
                })
            }
            "plastic" | "roughplastic" => {
                let alpha = if ty == "plastic" {
                    // Smooth plastic: a delta coat. Our coat is GGX; the smallest alpha we trace
                    // keeps the highlights sharp and the (identical) diffuse coupling exact.
                    self.warn(n, format!("smooth plastic traced with a GGX coat of alpha {MIN_ALPHA} (near-specular)"));
                    MIN_ALPHA
                } else {
                    let (au, av) = self.alpha(n, &p, &what)?;
                    if au != av {
                        self.warn(n, "anisotropic roughplastic is not supported; alpha sqrt(alphaU alphaV) used");
                    }
                    (au * av).sqrt()
                };
                let int = self.ior(&p, "intIOR", 1.49)?;
                let ext = self.ior(&p, "extIOR", 1.00028)?;
                let specular = self.spectrum_const(&p, "specularReflectance", Rgb::ONE, &what)?;
                let diffuse = self.spectrum_tex(&p, "diffuseReflectance", Rgb::splat(0.5))?;
                let nonlinear = self.boolean(&p, "nonlinear", false)?;
                one_sided(MaterialKind::Plastic {
                    distribution: Distribution::Ggx,
                    diffuse,
                    specular,
                    ior: int / ext,
                    alpha,
                    layered: true,
                    nonlinear,
                })
            }
            "phong" => {
                // Mitsuba's phong is the energy-normalised modified Phong model we implement.
                let mut kd =
                    self.spectrum_const(&p, "diffuseReflectance", Rgb::splat(0.5), &what)?;
                let mut ks =
                    self.spectrum_const(&p, "specularReflectance", Rgb::splat(0.2), &what)?;
                let exponent = self.float(&p, "exponent", 30.0)?;
                let sum = (kd + ks).max_element();
                if sum > 1.0 {
                    self.warn(
                        n,
                        format!(
                            "{what}: diffuse + specular reflectance {sum} > 1 scaled down to 1"
                        ),
                    );
                    kd /= sum;
                    ks /= sum;
                }
                one_sided(MaterialKind::Phong { kd, ks, exponent })
            }
            "bumpmap" | "normalmap" | "mask" | "coating" | "roughcoating" => {
                let m = self
                    .child_bsdf(n, &p)?
                    .ok_or_else(|| self.err(n, format!("{what} has no nested bsdf")))?;
                let msg = match ty {
                    "bumpmap" | "normalmap" => "bump mapping is not supported and was ignored",
                    "mask" => "opacity masks are not supported; the surface is opaque",
                    _ => "coating layers are not supported; the base bsdf is used",
                };
                self.warn(n, format!("{what}: {msg}"));
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                m
            }
            "blendbsdf" | "mixturebsdf" => {
                let m = self
                    .child_bsdf(n, &p)?
                    .ok_or_else(|| self.err(n, format!("{what} has no nested bsdf")))?;
                for c in &n.children {
                    if c.tag == "bsdf" && c.attr("name").is_none() && c.attr("id").is_some() {
                        // Register the other components' ids too.
                        if !self.ids.contains_key(c.attr("id").unwrap_or("")) {
                            self.bsdf(c)?;
                        }
                    }
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                p.any_with_tag("bsdf");
                p.any_with_tag("ref");
                self.warn(
                    n,
                    format!("{what} is not supported: became its first component"),
                );
                m
            }
            "null" => {
                self.warn(
                    n,
                    "null bsdf (pass-through) is not supported: became an opaque black surface",
                );
                Material::new(
                    name.clone(),
                    MaterialKind::Lambert {
                        albedo: Texture::Constant(Rgb::ZERO),
                    },
                    true,
                )
            }
            other => {
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                p.any_with_tag("bsdf");
                self.warn(
                    n,
                    format!(
                        "bsdf \"{other}\" is not supported: became diffuse with reflectance 0.5"
                    ),
                );
                one_sided(MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::splat(0.5)),
                })
            }
        };
        self.report_unused(&p, &what);
        Ok(m)
    }
}
