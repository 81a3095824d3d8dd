//! Which pbrt dialect a file is written in, told from its contents: pbrt-v4 files end in `.pbrt`
//! too, and much of pbrt-v4 would read as something else to a pbrt-v3 importer.
//!
//! pbrt-v4 (Pharr, Jakob and Humphreys, *Physically Based Rendering*, 4th ed., 2023; the
//! pbrt-v4 file format documentation, and the v3-to-v4 conversion of pbrt-v4's `--upgrade`)
//! adds directives, renames every material, the film and most samplers, and changes the type or
//! the meaning of some shared parameters. [`v4_constructs`] finds the constructs that only
//! pbrt-v4 has:
//!
//! - the directives `ColorSpace`, `Option`, `Attribute` and `Import`;
//! - the material types `diffuse`, `coateddiffuse`, `coatedconductor`, `conductor`,
//!   `dielectric`, `thindielectric`, `diffusetransmission` and `measured` (pbrt-v3 has `matte`,
//!   `plastic`, `metal`, `glass`, ...); `displacement` and `normalmap` on any material (pbrt-v3:
//!   `bumpmap`); `materials` on `mix` (pbrt-v3: `namedmaterial1`/`2`, in the other order);
//! - the shape `bilinearmesh`; `emissionfilename`, `displacement` and `edgelength` on shapes;
//! - the films `rgb`, `gbuffer`, `spectral` (pbrt-v3: `image`); the samplers `independent`,
//!   `paddedsobol`, `pmj02bn`, `zsobol`; the integrators `lightpath`, `randomwalk`,
//!   `simplepath`, `simplevolpath` and the parameter `regularize`; the camera `spherical`; the
//!   filter radii `xradius`, `yradius` (pbrt-v3: `xwidth`, `ywidth`);
//! - a `float scale`, `power` or `illuminance` on a light, and `filename` on an area light
//!   (pbrt-v3's `scale` is a spectrum; it has no photometric settings);
//! - the `directionmix` texture, `tex` on a `scale` texture (pbrt-v3: `tex1`, `tex2`),
//!   `encoding` on `imagemap` (pbrt-v3: `gamma`);
//! - a spectrum given by the name of one of pbrt-v4's built-in spectra (`"spectrum eta"
//!   "metal-Cu-eta"`; pbrt-v3 reads a string there as the name of an SPD file);
//! - a `blackbody` of one value (pbrt-v3's take a temperature and a scale);
//! - the media `uniformgrid`, `rgbgrid`, `cloud`, `nanovdb`.
//!
//! Declarations both dialects read alike are no sign: `"rgb L"` on a `diffuse` area light, for
//! one, is pbrt-v3 as much as pbrt-v4. A file with none of the above means the same in both
//! dialects for everything this importer reads.

use super::lexer::{Loc, Tok, Token};

const V4_DIRECTIVES: [&str; 4] = ["ColorSpace", "Option", "Attribute", "Import"];
const V4_MATERIALS: [&str; 8] = [
    "diffuse",
    "coateddiffuse",
    "coatedconductor",
    "conductor",
    "dielectric",
    "thindielectric",
    "diffusetransmission",
    "measured",
];
const V4_FILMS: [&str; 3] = ["rgb", "gbuffer", "spectral"];
const V4_SAMPLERS: [&str; 4] = ["independent", "paddedsobol", "pmj02bn", "zsobol"];
const V4_INTEGRATORS: [&str; 4] = ["lightpath", "randomwalk", "simplepath", "simplevolpath"];
const V4_MEDIA: [&str; 4] = ["uniformgrid", "rgbgrid", "cloud", "nanovdb"];
/// How pbrt-v4's built-in spectra are named (`metal-Au-eta`, `glass-BK7`, `stdillum-D65`,
/// `illum-acesD60`).
const NAMED_SPECTRA: [&str; 4] = ["metal-", "glass-", "stdillum-", "illum-"];

/// One parameter of a directive as the scan sees it.
struct Decl<'t> {
    ty: &'t str,
    name: &'t str,
    values: &'t [Token],
    loc: Loc,
}

impl Decl<'_> {
    fn first_str(&self) -> Option<&str> {
        self.values.iter().find_map(|t| match &t.tok {
            Tok::Str(s) => Some(s.as_str()),
            _ => None,
        })
    }
}

/// The places and descriptions of the first `most` directives in `tokens` that only pbrt-v4
/// has (one construct each, in file order), and how many such directives there are in all: none
/// for a file that reads the same as pbrt-v3 (see the module documentation). Malformed text is
/// left to the parser.
pub(super) fn v4_constructs(tokens: &[Token], most: usize) -> (Vec<(Loc, String)>, usize) {
    let mut found = Vec::new();
    let mut count = 0;
    let mut note = |f: (Loc, String)| {
        count += 1;
        if found.len() < most {
            found.push(f);
        }
    };
    let mut i = 0;
    while i < tokens.len() {
        let Token {
            tok: Tok::Word(directive),
            loc,
        } = &tokens[i]
        else {
            i += 1;
            continue;
        };
        i += 1;
        let directive = directive.as_str();
        let nargs = match directive {
            "Texture" => 3,
            "Material" | "MakeNamedMaterial" | "Shape" | "LightSource" | "AreaLightSource"
            | "Film" | "Sampler" | "Integrator" | "Camera" | "PixelFilter" | "MakeNamedMedium"
            | "Accelerator" | "ColorSpace" | "Option" | "Attribute" | "Import" => 1,
            _ => 0,
        };
        let mut args = Vec::new();
        while args.len() < nargs {
            match tokens.get(i) {
                Some(Token {
                    tok: Tok::Str(s), ..
                }) => {
                    args.push(s.as_str());
                    i += 1;
                }
                _ => break,
            }
        }
        if V4_DIRECTIVES.contains(&directive) {
            let what = match args.first() {
                Some(a) => format!("{directive} \"{a}\""),
                None => directive.to_string(),
            };
            note((*loc, what));
            continue;
        }
        let mut decls = Vec::new();
        if nargs > 0 {
            i = scan_params(tokens, i, &mut decls);
        }
        if let Some(f) = v4_in(directive, *loc, &args, &decls) {
            note(f);
        }
    }
    (found, count)
}

/// Reads the parameter list that starts at `i` into `decls`; returns the index after it.
fn scan_params<'t>(tokens: &'t [Token], mut i: usize, decls: &mut Vec<Decl<'t>>) -> usize {
    while let Some(Token {
        tok: Tok::Str(decl),
        loc,
    }) = tokens.get(i)
    {
        i += 1;
        let values = match tokens.get(i).map(|t| &t.tok) {
            Some(Tok::Open) => {
                let close = tokens[i..]
                    .iter()
                    .position(|t| t.tok == Tok::Close)
                    .map_or(tokens.len(), |k| i + k);
                let v = &tokens[i + 1..close];
                i = (close + 1).min(tokens.len());
                v
            }
            Some(Tok::Num(_) | Tok::Str(_)) => {
                i += 1;
                &tokens[i - 1..i]
            }
            Some(Tok::Word(w)) if w == "true" || w == "false" => {
                i += 1;
                &tokens[i - 1..i]
            }
            _ => &[],
        };
        let mut parts = decl.split_whitespace();
        if let (Some(ty), Some(name), None) = (parts.next(), parts.next(), parts.next()) {
            decls.push(Decl {
                ty,
                name,
                values,
                loc: *loc,
            });
        }
    }
    i
}

/// The pbrt-v4 construct of one directive, if any.
fn v4_in(directive: &str, loc: Loc, args: &[&str], decls: &[Decl]) -> Option<(Loc, String)> {
    let arg = args.first().copied().unwrap_or("");
    let typed = |list: &[&str]| {
        list.contains(&arg)
            .then(|| (loc, format!("{directive} \"{arg}\"")))
    };
    let param = |d: &Decl| {
        Some((
            d.loc,
            format!("{directive} \"{arg}\": \"{} {}\"", d.ty, d.name),
        ))
    };
    let found = match directive {
        "Film" => typed(&V4_FILMS),
        "Sampler" => typed(&V4_SAMPLERS),
        "Integrator" => typed(&V4_INTEGRATORS),
        "Camera" => typed(&["spherical"]),
        "Shape" => typed(&["bilinearmesh"]),
        "Material" => typed(&V4_MATERIALS),
        "Texture" => (args.get(2) == Some(&"directionmix"))
            .then(|| (loc, "Texture class \"directionmix\"".to_string())),
        _ => None,
    };
    if found.is_some() {
        return found;
    }
    // A material's or medium's type is a parameter of `MakeNamedMaterial` / `MakeNamedMedium`.
    let ty = decls
        .iter()
        .rev()
        .find(|d| d.ty == "string" && d.name == "type")
        .and_then(|d| d.first_str().map(|t| (d, t)));
    if let Some((d, t)) = ty {
        let list: &[&str] = match directive {
            "MakeNamedMaterial" => &V4_MATERIALS,
            "MakeNamedMedium" => &V4_MEDIA,
            _ => &[],
        };
        if list.contains(&t) {
            return Some((d.loc, format!("{directive} \"{arg}\" of type \"{t}\"")));
        }
    }
    let material_type = match directive {
        "Material" => Some(arg),
        "MakeNamedMaterial" => ty.map(|(_, t)| t),
        _ => None,
    };
    for d in decls {
        let v4 = match directive {
            "Material" | "MakeNamedMaterial" => {
                matches!(d.name, "displacement" | "normalmap")
                    || (material_type == Some("mix") && d.name == "materials")
            }
            "Shape" => matches!(d.name, "emissionfilename" | "displacement" | "edgelength"),
            "LightSource" | "AreaLightSource" => {
                (d.name == "scale" && d.ty == "float")
                    || matches!(d.name, "power" | "illuminance")
                    || (directive == "AreaLightSource" && d.name == "filename")
            }
            "Integrator" => d.name == "regularize",
            "PixelFilter" => matches!(d.name, "xradius" | "yradius"),
            "Texture" => {
                let class = args.get(2).copied().unwrap_or("");
                (class == "scale" && d.name == "tex")
                    || (class == "imagemap" && d.name == "encoding")
            }
            _ => false,
        };
        if v4 {
            return param(d);
        }
        if d.ty == "spectrum"
            && let Some(s) = d.first_str()
            && NAMED_SPECTRA.iter().any(|p| s.starts_with(p))
        {
            return Some((d.loc, format!("named spectrum \"{s}\"")));
        }
        if d.ty == "blackbody" && d.values.len() == 1 {
            return Some((d.loc, format!("\"{} {}\" of one value", d.ty, d.name)));
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::super::lexer::tokenize;
    use super::*;
    use std::path::Path;

    fn scan(text: &str) -> Option<(u32, String)> {
        let tokens = tokenize(text, 0, Path::new("t.pbrt")).expect("tokens");
        v4_constructs(&tokens, 1)
            .0
            .into_iter()
            .next()
            .map(|(l, w)| (l.line, w))
    }

    #[test]
    fn pbrt_v4_constructs_are_found_with_their_line() {
        let cases = [
            ("ColorSpace \"srgb\"", "ColorSpace \"srgb\""),
            ("Option \"bool disablepixeljitter\" true", "Option"),
            (
                "Attribute \"shape\" \"float radius\" 2",
                "Attribute \"shape\"",
            ),
            ("Import \"geometry.pbrt\"", "Import"),
            ("Film \"rgb\" \"integer xresolution\" 8", "Film \"rgb\""),
            ("Sampler \"zsobol\"", "Sampler \"zsobol\""),
            ("Integrator \"simplepath\"", "Integrator \"simplepath\""),
            (
                "Integrator \"path\" \"bool regularize\" true",
                "\"bool regularize\"",
            ),
            ("Camera \"spherical\"", "Camera \"spherical\""),
            (
                "PixelFilter \"box\" \"float xradius\" 0.5",
                "\"float xradius\"",
            ),
            ("Material \"coateddiffuse\"", "Material \"coateddiffuse\""),
            (
                "MakeNamedMaterial \"m\" \"string type\" [ \"diffuse\" ]",
                "MakeNamedMaterial \"m\" of type \"diffuse\"",
            ),
            (
                "Material \"matte\" \"texture displacement\" \"bumps\"",
                "\"texture displacement\"",
            ),
            (
                "Material \"mix\" \"string materials\" [ \"a\" \"b\" ]",
                "\"string materials\"",
            ),
            ("Shape \"bilinearmesh\"", "Shape \"bilinearmesh\""),
            (
                "Shape \"plymesh\" \"string displacement\" \"d.png\"",
                "\"string displacement\"",
            ),
            ("LightSource \"point\" \"float scale\" 2", "\"float scale\""),
            (
                "LightSource \"point\" \"float power\" 100",
                "\"float power\"",
            ),
            (
                "AreaLightSource \"diffuse\" \"float power\" 5",
                "\"float power\"",
            ),
            (
                "Texture \"t\" \"spectrum\" \"scale\" \"texture tex\" \"u\"",
                "\"texture tex\"",
            ),
            (
                "Texture \"t\" \"spectrum\" \"imagemap\" \"string encoding\" \"linear\"",
                "\"string encoding\"",
            ),
            (
                "Texture \"t\" \"float\" \"directionmix\"",
                "\"directionmix\"",
            ),
            (
                "Material \"metal\" \"spectrum eta\" \"metal-Cu-eta\"",
                "named spectrum \"metal-Cu-eta\"",
            ),
            (
                "Material \"glass\" \"spectrum eta\" [ \"glass-BK7\" ]",
                "named spectrum \"glass-BK7\"",
            ),
            (
                "LightSource \"point\" \"blackbody I\" [ 3000 ]",
                "of one value",
            ),
            (
                "MakeNamedMedium \"fog\" \"string type\" \"uniformgrid\"",
                "of type \"uniformgrid\"",
            ),
        ];
        for (text, what) in cases {
            let found = scan(&format!("# header\n\n{text}\n"));
            let Some((line, desc)) = found else {
                panic!("'{text}' should be found");
            };
            assert_eq!(line, 3, "{text}");
            assert!(
                desc.contains(what),
                "'{text}': '{desc}' should mention '{what}'"
            );
        }
    }

    #[test]
    fn pbrt_v3_text_is_not_taken_for_pbrt_v4() {
        let v3 = r#"
            LookAt 0 0 5  0 0 0  0 1 0
            Camera "perspective" "float fov" 40
            Film "image" "integer xresolution" 8 "integer yresolution" 8
            Sampler "halton" "integer pixelsamples" 4
            Integrator "path" "integer maxdepth" 5
            PixelFilter "box" "float xwidth" 0.5
            WorldBegin
            Texture "t" "spectrum" "scale" "texture tex1" "u" "rgb tex2" [ 1 1 1 ]
            Texture "i" "color" "imagemap" "string filename" "a.png" "bool gamma" "true"
            MakeNamedMaterial "gold" "string type" "metal" "spectrum eta" "spds/Au.eta.spd"
            Material "matte" "rgb Kd" [ 0.5 0.5 0.5 ] "texture bumpmap" "b"
            Material "mix" "string namedmaterial1" "gold" "string namedmaterial2" "gold"
            AttributeBegin
              AreaLightSource "diffuse" "rgb L" [ 10 10 10 ] "rgb scale" [ 2 2 2 ]
              Shape "trianglemesh" "point P" [ 0 0 0 1 0 0 0 1 0 ] "integer indices" [ 0 1 2 ]
            AttributeEnd
            LightSource "point" "blackbody I" [ 3000 1 ] "spectrum scale" [ 400 1 700 1 ]
            Shape "sphere" "float radius" 1 "string type" "diffuse"
            Material "metal" "spectrum eta" "spds/Cu_eta"
            WorldEnd
        "#;
        assert_eq!(scan(v3), None);
        // Strings and names that merely look like pbrt-v4 words are not directives.
        assert_eq!(
            scan("WorldBegin\nNamedMaterial \"ColorSpace\"\nShape \"Option\"\nWorldEnd"),
            None
        );
    }
}
