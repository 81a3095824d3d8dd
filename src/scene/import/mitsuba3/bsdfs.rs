//! BSDFs and textures of Mitsuba 3 files mapped onto our materials: `diffuse`, `conductor`,
//! `roughconductor`, `dielectric`, `roughdielectric`, `thindielectric`, `plastic`,
//! `roughplastic`, `twosided`, `principled`, `blendbsdf`, `mask`, `bumpmap`, `normalmap`;
//! textures `bitmap`. Mitsuba 3's defaults (its plugin reference) where a property is absent.

use super::values::ColorUse;
use super::{Ctx, R};
use crate::geometry::{Rgb, Vec3};
use crate::material::Distribution;
use crate::material::microfacet::MIN_ALPHA;
use crate::material::{Material, MaterialKind, Texture};
use crate::scene::import::xml::{Node, Props};

/// Mitsuba 3's named indices of refraction (`include/mitsuba/render/ior.h` of Mitsuba 3.9).
fn named_ior(name: &str) -> Option<f32> {
    Some(match name.to_ascii_lowercase().as_str() {
        "vacuum" => 1.0,
        "helium" => 1.000036,
        "hydrogen" => 1.000132,
        "air" => 1.000277,
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

/// The RGB complex indices of refraction Mitsuba 3.9 uses for its named conductors in its RGB
/// variants (its tabulated spectra integrated against the CIE 1931 matching functions and
/// taken through the sRGB matrix, without a white point; read back from Mitsuba 3.9.1).
/// `none` is Mitsuba's perfect mirror (eta 0, k 1).
#[allow(clippy::excessive_precision)] // The digits as Mitsuba reports them.
fn named_conductor(name: &str) -> Option<([f32; 3], [f32; 3])> {
    let base = name.strip_suffix("_palik").unwrap_or(name);
    Some(match (name, base) {
        ("Cu_palik", _) => (
            [0.213229, 0.919715, 1.102411],
            [3.921873, 2.457332, 2.136584],
        ),
        (_, "Ag") => (
            [0.155276, 0.116728, 0.138388],
            [4.828354, 3.122222, 2.146901],
        ),
        (_, "Al") => (
            [1.657501, 0.880405, 0.521244],
            [9.223811, 6.269502, 4.837004],
        ),
        (_, "Au") => (
            [0.143036, 0.375307, 1.442045],
            [3.982997, 2.385556, 1.603359],
        ),
        (_, "Cr") => (
            [4.369668, 2.916505, 1.654905],
            [5.206547, 4.231306, 3.754699],
        ),
        (_, "Cu") => (
            [0.201005, 0.923750, 1.102215],
            [3.913262, 2.453045, 2.142090],
        ),
        (_, "Hg") => (
            [2.398939, 1.440028, 0.909570],
            [6.327587, 4.371925, 3.421764],
        ),
        (_, "Ni") => (
            [2.367305, 1.663373, 1.467078],
            [4.498812, 3.050153, 2.345439],
        ),
        (_, "W") => (
            [4.370817, 3.300246, 2.998407],
            [3.500641, 2.604874, 2.273233],
        ),
        (_, "Ir") => (
            [3.086300, 2.082191, 1.617915],
            [5.592153, 4.067088, 3.267312],
        ),
        (_, "Rh") => (
            [2.585793, 1.860216, 1.554263],
            [6.782260, 4.702987, 3.976073],
        ),
        (_, "Mo") => (
            [4.483974, 3.525131, 2.776310],
            [4.111437, 3.420827, 3.150607],
        ),
        (_, "Ta") => (
            [2.062721, 2.392939, 2.627929],
            [2.408360, 1.741486, 1.947028],
        ),
        (_, "TiN") => (
            [1.648450, 1.150516, 1.379823],
            [3.368328, 1.943498, 1.102068],
        ),
        (_, "TiC") => (
            [3.700528, 2.837422, 2.582287],
            [3.265635, 2.351589, 2.172791],
        ),
        (_, "V") => (
            [4.277582, 3.512949, 2.761071],
            [3.491301, 2.889455, 3.111522],
        ),
        (_, "VC") => (
            [3.657566, 2.752736, 2.532672],
            [3.068301, 2.198687, 1.963193],
        ),
        (_, "VN") => (
            [2.865602, 2.119189, 1.940091],
            [3.032243, 2.056116, 1.616306],
        ),
        (_, "Nb") => (
            [3.420074, 2.790093, 2.395629],
            [3.441395, 2.737666, 2.579746],
        ),
        (_, "Be") => (
            [4.185012, 3.185029, 2.784061],
            [3.835466, 3.010122, 2.868994],
        ),
        (_, "K") => (
            [0.064043, 0.046410, 0.038185],
            [2.104200, 1.348940, 0.913126],
        ),
        (_, "Li") => (
            [0.265791, 0.195618, 0.220949],
            [3.540155, 2.311123, 1.668607],
        ),
        (_, "Na") => (
            [0.060269, 0.056141, 0.061988],
            [3.179273, 2.112490, 1.579041],
        ),
        (_, "a-C") => (
            [2.944046, 2.227136, 1.968162],
            [0.887465, 0.799299, 0.815290],
        ),
        (_, "d-C") => ([2.708720, 2.318826, 2.228898], [0.0, 0.0, 0.0]),
        (_, "Cu2O") => (
            [3.551773, 2.949870, 2.751875],
            [0.114207, 0.193897, 0.606134],
        ),
        (_, "CuO") => (
            [3.247541, 2.447805, 2.210220],
            [0.521090, 0.570031, 0.722179],
        ),
        (_, "HgTe") => (
            [4.779040, 3.231196, 2.659901],
            [1.631613, 1.580810, 1.729287],
        ),
        (_, "Se") => (
            [4.058311, 2.842935, 2.820853],
            [0.754050, 0.638444, 0.521808],
        ),
        (_, "Se-e") => (
            [5.722849, 4.165736, 4.081338],
            [0.871136, 1.105157, 1.565320],
        ),
        (_, "Te") => (
            [7.390234, 4.482105, 2.637106],
            [3.256022, 3.527059, 3.292054],
        ),
        (_, "Te-e") => (
            [7.508907, 4.296429, 2.369988],
            [5.583929, 4.947205, 3.997592],
        ),
        (_, "SnTe") => ([4.524250, 1.981645, 1.281591], [0.0, 0.0, 0.0]),
        (_, "SiC") => ([3.172342, 2.525972, 2.479371], [0.000001, 0.0, 0.000010]),
        (_, "TiO2") => ([3.456610, 2.801736, 2.905175], [0.000105, 0.0, 0.000653]),
        (_, "TiO2-e") => ([3.106565, 2.513168, 2.582444], [0.000030, 0.0, 0.000183]),
        (_, "AlAs") => ([3.605296, 3.232938, 2.216319], [0.000679, 0.0, 0.007513]),
        (_, "AlSb") => ([0.0, 4.139375, 4.669254], [0.0, 0.094009, 1.300570]),
        (_, "CsI") => ([2.144900, 1.702319, 1.662427], [0.0, 0.0, 0.0]),
        (_, "MgO") => ([2.089584, 1.650723, 1.594879], [0.0, 0.0, 0.0]),
        (_, "ThF4") => ([1.830714, 1.442229, 1.387648], [0.0, 0.0, 0.0]),
        ("none", _) => ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]),
        _ => return None,
    })
}

/// The extensions of image files Mitsuba reads as linear (not sRGB).
const LINEAR_IMAGES: [&str; 3] = ["exr", "hdr", "pfm"];

impl Ctx {
    /// An index of refraction: a `<float>` or a named material (`<string>`).
    fn ior(&self, p: &Props, name: &str, default: f32) -> R<f32> {
        match p.get(name) {
            None => Ok(default),
            Some(n) if n.tag == "string" => {
                let v = n.attr("value").unwrap_or("");
                named_ior(v).ok_or_else(|| {
                    self.err(n, format!("unknown index of refraction \"{v}\" for {name}"))
                })
            }
            Some(n) => {
                let v = self.number(n)?;
                if !(v > 0.0) {
                    return Err(self.err(n, format!("{name} must be > 0, got {v}")));
                }
                Ok(v)
            }
        }
    }

    /// The microfacet roughness of a rough bsdf: `alpha` or `alpha_u` and `alpha_v` (default
    /// 0.1), and its distribution (`beckmann`, Mitsuba's default, is traced as GGX of the same
    /// alpha, with a warning).
    fn roughness(&mut self, n: &Node, p: &Props, what: &str) -> R<(Distribution, f32, f32)> {
        let dist = self
            .string(p, "distribution")?
            .unwrap_or_else(|| "beckmann".into())
            .to_ascii_lowercase();
        let distribution = match dist.as_str() {
            "ggx" => Distribution::Ggx,
            "beckmann" => Distribution::Beckmann,
            other => return Err(self.err(n, format!("{what}: unknown distribution \"{other}\""))),
        };
        p.consume("sample_visible");
        let scalar = |cx: &mut Ctx, k: &str| -> R<Option<f32>> {
            match p.get(k) {
                None => Ok(None),
                Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => {
                    cx.warn(v, format!("{what}: a textured {k} is traced with its mean"));
                    let t = cx.texture_node(v)?;
                    Ok(Some(crate::geometry::luminance(t.average())))
                }
                Some(v) => Ok(Some(cx.color(v, ColorUse::Unbounded)?.element_sum() / 3.0)),
            }
        };
        let (au, av) = match (
            scalar(self, "alpha")?,
            scalar(self, "alpha_u")?,
            scalar(self, "alpha_v")?,
        ) {
            (Some(a), None, None) => (a, a),
            (None, Some(u), Some(v)) => (u, v),
            (None, None, None) => (0.1, 0.1),
            _ => {
                return Err(self.err(
                    n,
                    format!("{what}: give alpha, or both alpha_u and alpha_v"),
                ));
            }
        };
        if !(au >= 0.0 && av >= 0.0) {
            return Err(self.err(n, format!("{what}: alpha must be >= 0")));
        }
        Ok((distribution, au.max(MIN_ALPHA), av.max(MIN_ALPHA)))
    }

    /// A conductor's complex index of refraction: a named `material`, or `eta` and `k`
    /// (default: Mitsuba's perfect mirror).
    fn conductor_ior(&mut self, n: &Node, p: &Props, what: &str) -> R<(Rgb, Rgb)> {
        let material = self.string(p, "material")?;
        let has_eta = p.has("eta") || p.has("k");
        match material.as_deref() {
            Some(m) if m != "none" && has_eta => {
                Err(self.err(n, format!("{what}: give a material or eta and k, not both")))
            }
            Some(m) if m != "none" => {
                let (eta, k) = named_conductor(m).ok_or_else(|| {
                    self.err(n, format!("{what}: unknown conductor material \"{m}\""))
                })?;
                Ok((Rgb::from_array(eta), Rgb::from_array(k)))
            }
            _ if has_eta => {
                let get = |cx: &Ctx, k: &str, d: Rgb| -> R<Rgb> {
                    p.get(k).map_or(Ok(d), |v| cx.color(v, ColorUse::Unbounded))
                };
                Ok((get(self, "eta", Rgb::ZERO)?, get(self, "k", Rgb::ONE)?))
            }
            _ => Ok((Rgb::ZERO, Rgb::ONE)),
        }
    }

    /// A colour or texture property (`default` when absent).
    pub(super) fn texture_prop(
        &mut self,
        p: &Props,
        name: &str,
        default: Rgb,
        usage: ColorUse,
    ) -> R<Texture> {
        match p.get(name) {
            None => Ok(Texture::Constant(default)),
            Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => self.texture_node(v),
            Some(v) => Ok(Texture::Constant(self.color(v, usage)?)),
        }
    }

    /// A constant colour property: a texture there is traced with its mean, with a warning.
    fn color_prop(&mut self, p: &Props, name: &str, default: Rgb, what: &str) -> R<Rgb> {
        match p.get(name) {
            None => Ok(default),
            Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => {
                self.warn(
                    v,
                    format!("{what}: a textured {name} is traced with its mean"),
                );
                Ok(self.texture_node(v)?.average())
            }
            Some(v) => self.color(v, ColorUse::Bounded),
        }
    }

    /// A `<texture>` element (or a `<ref>` to one).
    pub(super) fn texture_node(&mut self, n: &Node) -> R<Texture> {
        let n: Node = self.deref(n)?.clone();
        if n.tag != "texture" {
            return Err(self.err(&n, format!("{} is not a texture", n.label())));
        }
        let p = Props::new(&n);
        let ty = n.attr("type").unwrap_or("");
        let t = match ty {
            "bitmap" => {
                let rel = self
                    .string(&p, "filename")?
                    .ok_or_else(|| self.err(&n, "bitmap has no filename"))?;
                let raw = self.boolean(&p, "raw", false)?;
                let linear = LINEAR_IMAGES
                    .iter()
                    .any(|e| rel.to_ascii_lowercase().ends_with(&format!(".{e}")));
                match self.string(&p, "filter_type")?.as_deref() {
                    None | Some("bilinear") => {}
                    Some(f) => self.warn(
                        &n,
                        format!("bitmap filter_type \"{f}\" is filtered bilinearly"),
                    ),
                }
                match self.string(&p, "wrap_mode")?.as_deref() {
                    None | Some("repeat") => {}
                    Some(w) => {
                        self.warn(&n, format!("bitmap wrap_mode \"{w}\" is wrapped as repeat"))
                    }
                }
                p.consume("format");
                p.consume("accel");
                let file = self
                    .b
                    .resolver()
                    .resolve(&rel, "bitmap")
                    .map_err(|e| self.err(&n, e.message))?;
                let image = self
                    .bitmaps
                    .load(&file, !raw && !linear)
                    .map_err(|e| self.err(&n, format!("bitmap \"{rel}\": {e}")))?;
                Texture::Bitmap {
                    image,
                    scale: Rgb::ONE,
                }
            }
            "checkerboard" => Texture::Checker {
                c0: self.checker_color(&p, "color0", 0.4)?,
                c1: self.checker_color(&p, "color1", 0.2)?,
            },
            other => {
                self.refuse(&n, format!("texture \"{other}\" is not supported"));
                Texture::Constant(Rgb::splat(0.5))
            }
        };
        let t = match p.get("to_uv") {
            Some(tn) if matches!(t, Texture::Bitmap { .. } | Texture::Checker { .. }) => {
                // Mitsuba 3 keeps the 2D affine part of the 4x4 it parses: rows 0 and 1,
                // columns 0, 1 and 3.
                let m = self.transform(tn)?;
                if m == crate::geometry::Mat4::IDENTITY {
                    t
                } else {
                    let (r0, r1) = (m.row(0), m.row(1));
                    Texture::Mapped {
                        inner: Box::new(t),
                        rows: [[r0.x, r0.y, r0.w], [r1.x, r1.y, r1.w]],
                    }
                }
            }
            _ => t,
        };
        self.report_unused(&p, &format!("texture \"{ty}\""));
        Ok(t)
    }

    /// A checkerboard's colour: Mitsuba 3 accepts a constant there (its textures would nest
    /// lookups in cells, which a checker of two values cannot hold, so they are refused).
    fn checker_color(&mut self, p: &Props, name: &str, default: f32) -> R<Rgb> {
        match p.get(name) {
            None => Ok(Rgb::splat(default)),
            Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => {
                self.refuse(
                    v,
                    format!("checkerboard: a textured {name} is not supported"),
                );
                Ok(Rgb::splat(default))
            }
            Some(v) => self.color(v, ColorUse::Bounded),
        }
    }

    /// Warns about every property of `p` nothing read.
    pub(super) fn report_unused(&mut self, p: &Props, what: &str) {
        for c in p.unused() {
            let m = match c.attr("name") {
                Some(name) => {
                    format!("{what}: property \"{name}\" is not supported and was ignored")
                }
                None => format!(
                    "{what}: nested {} is not supported and was ignored",
                    c.label()
                ),
            };
            self.warn(c, m);
        }
    }

    /// The builder material of a shape's bsdf node (nested or a `<ref>`): bsdfs with an id are
    /// added once.
    pub(super) fn material_of(&mut self, n: &Node) -> R<u32> {
        let target = self.deref(n)?.clone();
        if target.tag != "bsdf" {
            return Err(self.err(n, format!("{} is not a bsdf", target.label())));
        }
        if let Some(id) = target.attr("id")
            && let Some(&i) = self.materials.get(id)
        {
            return Ok(i);
        }
        let m = self.bsdf(&target)?;
        let i = self.b.add_material(m);
        if let Some(id) = target.attr("id") {
            self.materials.insert(id.to_string(), i);
        }
        Ok(i)
    }

    /// The nested bsdfs of a bsdf (`twosided`, `blendbsdf`, `mask`, ...), refs resolved.
    fn nested_bsdfs(&self, n: &Node, p: &Props) -> R<Vec<Node>> {
        let mut out = Vec::new();
        for c in p
            .any_with_tag("bsdf")
            .into_iter()
            .chain(p.any_with_tag("ref"))
        {
            let t: &Node = self.deref(c)?;
            if t.tag == "bsdf" {
                out.push(t.clone());
            }
        }
        out.sort_by_key(|c| c.line);
        if out.is_empty() {
            return Err(self.err(n, format!("{} has no nested bsdf", n.label())));
        }
        Ok(out)
    }

    /// Our material for a `<bsdf>`.
    pub(super) fn bsdf(&mut self, n: &Node) -> R<Material> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let name = n
            .attr("id")
            .map_or_else(|| format!("{ty} (line {})", n.line), str::to_string);
        let what = format!("bsdf \"{ty}\"");
        let one_sided = |kind| Material::new(name.clone(), kind, false);
        let m = match ty {
            "twosided" => {
                let inner = self.nested_bsdfs(n, &p)?;
                if inner.len() > 1 {
                    self.warn(n, "twosided with a different back-side bsdf: the front bsdf is used on both sides");
                }
                p.consume("allow_transmission");
                let mut m = self.bsdf(&inner[0])?;
                m.name = name.clone();
                m.two_sided = true;
                m
            }
            "diffuse" => one_sided(MaterialKind::Lambert {
                albedo: self.texture_prop(&p, "reflectance", Rgb::splat(0.5), ColorUse::Bounded)?,
            }),
            "conductor" | "roughconductor" => {
                let (eta, k) = self.conductor_ior(n, &p, &what)?;
                let (distribution, alpha_u, alpha_v) = if ty == "conductor" {
                    self.warn(
                        n,
                        format!(
                            "smooth conductor traced as GGX of alpha {MIN_ALPHA} (near-specular)"
                        ),
                    );
                    (Distribution::Ggx, MIN_ALPHA, MIN_ALPHA)
                } else {
                    self.roughness(n, &p, &what)?
                };
                let scale = self.color_prop(&p, "specular_reflectance", Rgb::ONE, &what)?;
                one_sided(MaterialKind::RoughConductor {
                    distribution,
                    eta,
                    k,
                    alpha_u,
                    alpha_v,
                    scale,
                })
            }
            "dielectric" | "roughdielectric" | "thindielectric" => {
                let rough = if ty == "roughdielectric" {
                    Some(self.roughness(n, &p, &what)?)
                } else {
                    None
                };
                let int = self.ior(&p, "int_ior", 1.5046)?;
                let ext = self.ior(&p, "ext_ior", 1.000277)?;
                let reflectance = self.color_prop(&p, "specular_reflectance", Rgb::ONE, &what)?;
                let transmittance =
                    self.color_prop(&p, "specular_transmittance", Rgb::ONE, &what)?;
                let kind = if let Some((distribution, alpha_u, alpha_v)) = rough {
                    MaterialKind::RoughDielectric {
                        distribution,
                        ior: int / ext,
                        alpha_u,
                        alpha_v,
                        reflectance,
                        transmittance,
                    }
                } else if ty == "thindielectric" {
                    MaterialKind::ThinDielectric {
                        ior: int / ext,
                        reflectance,
                        transmittance,
                    }
                } else {
                    MaterialKind::Dielectric {
                        ior: int / ext,
                        reflectance,
                        transmittance,
                    }
                };
                Material::new(name.clone(), kind, true)
            }
            "plastic" | "roughplastic" => {
                let (distribution, alpha) = if ty == "plastic" {
                    self.warn(n, format!("smooth plastic traced with a GGX coat of alpha {MIN_ALPHA} (near-specular)"));
                    (Distribution::Ggx, MIN_ALPHA)
                } else {
                    let (distribution, au, av) = self.roughness(n, &p, &what)?;
                    if au != av {
                        return Err(self.err(
                            n,
                            "roughplastic is isotropic (Mitsuba 3 refuses alpha_u != alpha_v too)",
                        ));
                    }
                    (distribution, au)
                };
                let int = self.ior(&p, "int_ior", 1.49)?;
                let ext = self.ior(&p, "ext_ior", 1.000277)?;
                let specular = self.color_prop(&p, "specular_reflectance", Rgb::ONE, &what)?;
                let diffuse = self.texture_prop(
                    &p,
                    "diffuse_reflectance",
                    Rgb::splat(0.5),
                    ColorUse::Bounded,
                )?;
                let nonlinear = self.boolean(&p, "nonlinear", false)?;
                one_sided(MaterialKind::Plastic {
                    distribution,
                    diffuse,
                    specular,
                    ior: int / ext,
                    alpha,
                    layered: true,
                    nonlinear,
                })
            }
            "principled" => self.principled(n, &p, &name)?,
            "blendbsdf" => {
                let inner = self.nested_bsdfs(n, &p)?;
                let w = match p.get("weight") {
                    Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => {
                        crate::geometry::luminance(self.texture_node(v)?.average())
                    }
                    Some(v) => self.number(v)?,
                    None => {
                        return Err(self.err(
                            n,
                            "blendbsdf needs a weight (Mitsuba 3 refuses it without one)",
                        ));
                    }
                };
                if inner.len() != 2 {
                    return Err(self.err(
                        n,
                        format!("blendbsdf needs two nested bsdfs, has {}", inner.len()),
                    ));
                }
                let pick = if w.clamp(0.0, 1.0) > 0.5 { 1 } else { 0 };
                self.warn(
                    n,
                    format!(
                        "blendbsdf (weight {w}) is traced as its {} component",
                        ["first", "second"][pick]
                    ),
                );
                let mut m = self.bsdf(&inner[pick])?;
                m.name = name.clone();
                m
            }
            "mask" | "bumpmap" | "normalmap" => {
                let inner = self.nested_bsdfs(n, &p)?;
                let msg = match ty {
                    "mask" => "an opacity mask is traced as an opaque surface",
                    _ => {
                        "bump and normal mapping are not supported: the surface is traced with its own normals"
                    }
                };
                self.warn(n, format!("{what}: {msg}"));
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                    if c.tag == "texture" {
                        p.any_with_tag("texture");
                    }
                }
                let mut m = self.bsdf(&inner[0])?;
                m.name = name.clone();
                m
            }
            "null" => {
                self.refuse(n, "the null bsdf (an invisible surface) is not supported");
                one_sided(MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::ZERO),
                })
            }
            other => {
                self.refuse(n, format!("bsdf \"{other}\" is not supported"));
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                one_sided(MaterialKind::Lambert {
                    albedo: Texture::Constant(Rgb::splat(0.5)),
                })
            }
        };
        self.report_unused(&p, &what);
        Ok(m)
    }

    /// Mitsuba 3's `principled` (the Disney principled BSDF) mapped onto the closest of our
    /// materials: mostly transmissive is a dielectric, mostly metallic a conductor whose
    /// Fresnel reflectance at normal incidence is the base colour (Gulbrandsen, "Artist friendly
    /// metallic Fresnel", JCGT 2014, with k chosen for an edge tint of the base colour), else a
    /// plastic coat of the principled index over a diffuse base. The lobes this leaves out are
    /// named in a warning.
    fn principled(&mut self, n: &Node, p: &Props, name: &str) -> R<Material> {
        let what = "bsdf \"principled\"";
        let base = self.texture_prop(p, "base_color", Rgb::splat(0.5), ColorUse::Bounded)?;
        let scalar = |cx: &mut Ctx, k: &str, d: f32| -> R<f32> {
            match p.get(k) {
                None => Ok(d),
                Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => {
                    cx.warn(v, format!("{what}: a textured {k} is traced with its mean"));
                    Ok(crate::geometry::luminance(cx.texture_node(v)?.average()))
                }
                Some(v) => cx.number(v),
            }
        };
        let roughness = scalar(self, "roughness", 0.5)?;
        let metallic = scalar(self, "metallic", 0.0)?;
        let spec_trans = scalar(self, "spec_trans", 0.0)?;
        let eta = match (p.get("eta"), p.get("specular")) {
            (Some(_), Some(_)) => {
                return Err(self.err(n, "principled: give eta or specular, not both"));
            }
            (Some(e), None) => self.number(e)?,
            (None, s) => {
                let s = match s {
                    Some(v) => self.number(v)?,
                    None => 0.5,
                };
                2.0 / (1.0 - (0.08 * s).sqrt()) - 1.0
            }
        };
        let mut left_out = Vec::new();
        for k in [
            "anisotropic",
            "spec_tint",
            "sheen",
            "sheen_tint",
            "flatness",
            "clearcoat",
            "clearcoat_gloss",
        ] {
            if scalar(self, k, 0.0)? != 0.0 {
                left_out.push(k);
            }
        }
        for k in [
            "diffuse_reflectance_sampling_rate",
            "main_specular_sampling_rate",
            "clearcoat_sampling_rate",
        ] {
            p.consume(k);
        }
        let alpha = (roughness * roughness).max(MIN_ALPHA);
        let (kind, two_sided, model) = if spec_trans > 0.5 {
            (
                MaterialKind::Dielectric {
                    ior: eta.max(1.001),
                    reflectance: Rgb::ONE,
                    transmittance: base.average().map(f32::sqrt),
                },
                true,
                "a smooth dielectric",
            )
        } else if metallic > 0.5 {
            let r = base.average().clamp(Vec3::ZERO, Vec3::splat(0.99));
            // Gulbrandsen's eqs. 3 and 4 with the edge tint g = r: n between the indices that
            // give the reflectance r with k = 0 at its two extremes, k from n and r.
            let sr = r.map(f32::sqrt);
            let n_min = (Vec3::ONE - r) / (Vec3::ONE + r);
            let n_max = (Vec3::ONE + sr) / (Vec3::ONE - sr);
            let eta_c = r * n_min + (Vec3::ONE - r) * n_max;
            let k2 = ((eta_c + Vec3::ONE) * (eta_c + Vec3::ONE) * r
                - (eta_c - Vec3::ONE) * (eta_c - Vec3::ONE))
                / (Vec3::ONE - r);
            let k = k2.max(Vec3::ZERO).map(f32::sqrt);
            (
                MaterialKind::RoughConductor {
                    distribution: Distribution::Ggx,
                    eta: eta_c,
                    k,
                    alpha_u: alpha,
                    alpha_v: alpha,
                    scale: Rgb::ONE,
                },
                false,
                "a GGX conductor",
            )
        } else {
            (
                MaterialKind::Plastic {
                    distribution: Distribution::Ggx,
                    diffuse: base,
                    specular: Rgb::ONE,
                    ior: eta.max(1.001),
                    alpha,
                    layered: true,
                    nonlinear: false,
                },
                false,
                "a plastic coat over a diffuse base",
            )
        };
        let mut msg = format!(
            "principled is traced as {model} (metallic {metallic}, spec_trans {spec_trans}, roughness {roughness})"
        );
        if !left_out.is_empty() {
            msg.push_str(&format!("; left out: {}", left_out.join(", ")));
        }
        self.warn(n, msg);
        Ok(Material::new(name.to_string(), kind, two_sided))
    }
}
