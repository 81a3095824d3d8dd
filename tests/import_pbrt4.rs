//! The pbrt-v4 importer: the twins of `scenes/pbrt-v4/` render as their Mitsuba 3 originals
//! (`scenes/mitsuba3/`) do; every refusal and warning names its file and line; PLY meshes
//! ASCII, binary and gzipped; lights' photometric settings.

mod common;

use common::import::{assert_has, load, load_err, warning};
use omis::film::Image;
use omis::geometry::Vec3;
use omis::integrator::{IntegratorKind, RenderSettings};
use omis::light::Light;
use omis::material::MaterialKind;
use omis::sampler::SamplerKind;
use omis::scene::Scene;

/// Pixels of the twin renders (small: the comparison is of means over the image and its
/// quarters).
const RES: u32 = 32;
/// Samples per pixel of one render.
const SPP: u32 = 64;
/// Independent renders (seeds) of each twin: the standard error of the mean comes from their
/// spread.
const SEEDS: u64 = 8;

/// `SEEDS` renders of `scene` by the path tracer at its own max depth.
fn renders(scene: &Scene, first_seed: u64) -> Vec<Image> {
    (0..SEEDS)
        .map(|k| {
            let s = RenderSettings {
                integrator: IntegratorKind::Pt,
                sample_block: SPP,
                max_depth: scene.defaults.max_depth.unwrap_or(5),
                sampler: SamplerKind::Independent,
                seed: first_seed + k,
                ..Default::default()
            };
            common::render(scene, &s, 8).image()
        })
        .collect()
}

/// The whole image, then its quarters (a mirrored or misplaced shape changes those).
fn regions(w: usize, h: usize) -> Vec<(usize, usize, usize, usize)> {
    let mut r = vec![(0, 0, w, h)];
    for (qx, qy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        r.push((qx * w / 2, qy * h / 2, (qx + 1) * w / 2, (qy + 1) * h / 2));
    }
    r
}

/// The twins, with the largest relative difference of their means (over the image and over
/// each quarter, per channel) we accept beyond the noise (4 standard errors): 0 where the scenes
/// are the same, else about twice the difference the import makes on purpose, as measured
/// (scenes/README.md, "pbrt-v4").
const TWINS: [(&str, f64); 9] = [
    ("cbox-diffuse", 0.0),
    ("instances", 0.0),
    ("point", 0.0),
    ("spot", 0.0),
    // The Mitsuba scene's checkerboard panels are one-sided; pbrt-v4's materials are two-sided
    // (measured: up to 1.6 % in a quarter, 0.4 % over the image).
    ("textures", 0.03),
    // pbrt-v4's gold and copper reduced from its spectra vs Mitsuba 3's RGB values (measured:
    // up to 3.0 % in the gold sphere's quarter, 0.4 % over the image).
    ("conductors", 0.06),
    // pbrt-v4's BK7 (1.5184) vs Mitsuba's bk7 over air (1.5042) (measured: up to 2.0 % in a
    // quarter, 0.4 % over the image).
    ("dielectric", 0.04),
    // pbrt-v4's coateddiffuse is our nonlinear layered plastic; one sphere of the Mitsuba
    // scene is linear (measured: up to 10.6 % in its quarter, 1.9 % over the image).
    ("plastic", 0.2),
    // pbrt-v4's aluminium reduced from its spectra vs Mitsuba 3's RGB values (measured: up to
    // 0.2 %).
    ("environment-constant", 0.01),
];

#[test]
fn pbrt_v4_twins_render_as_their_mitsuba_3_originals() {
    let repo = common::repo();
    let mut report = Vec::new();
    for (name, allowed) in TWINS {
        let mut mitsuba = load(&repo.join(format!("scenes/mitsuba3/{name}.xml")));
        let mut pbrt = load(&repo.join(format!("scenes/pbrt-v4/{name}.pbrt")));
        assert_eq!(
            mitsuba.defaults.max_depth, pbrt.defaults.max_depth,
            "{name}: Mitsuba's max_depth 6 is pbrt's maxdepth 5"
        );
        assert_eq!(mitsuba.defaults.spp, pbrt.defaults.spp, "{name}: spp");
        for s in [&mut mitsuba, &mut pbrt] {
            s.camera = s.camera.with_resolution(RES, RES).expect("resolution");
        }
        let a = renders(&mitsuba, 1);
        let b = renders(&pbrt, 1000);
        for (k, r) in regions(RES as usize, RES as usize).into_iter().enumerate() {
            for c in 0..3 {
                let ((ma, sa), (mb, sb)) = (common::region(&a, r, c), common::region(&b, r, c));
                let se = (sa * sa + sb * sb).sqrt();
                let rel = (ma - mb).abs() / ma.abs().max(1e-9);
                let line = format!(
                    "{name} region {r:?} channel {c}: mitsuba3 {ma:.5} pbrt-v4 {mb:.5} relative difference {rel:.4} ({:.1} standard errors)",
                    (ma - mb).abs() / se.max(1e-12)
                );
                assert!(
                    (ma - mb).abs() <= 4.0 * se + allowed * ma.abs(),
                    "{line} (se {se}, allowed {allowed})\n{}",
                    report.join("\n")
                );
                let _ = k;
                report.push(line);
            }
        }
    }
    eprintln!("{}", report.join("\n"));
}

/// A pbrt-v4 scene: a camera looking down -z at 8 x 8 pixels, then `body` in the world.
fn scene(body: &str) -> String {
    format!(
        "ColorSpace \"srgb\"\nLookAt 0 0 0  0 0 -1  0 1 0\nCamera \"perspective\" \"float fov\" 40\n\
         Film \"rgb\" \"integer xresolution\" 8 \"integer yresolution\" 8\nWorldBegin\n{body}"
    )
}

#[test]
fn every_refusal_is_named_at_once_with_its_file_and_line() {
    let d = common::folder("pbrt4", "refusals");
    common::write(
        &d,
        "part.pbrt",
        "# included\nMaterial \"interface\"\nShape \"sphere\"\n",
    );
    let p = common::write(
        &d,
        "refused.pbrt",
        &scene(
            "LightSource \"goniometric\" \"string filename\" \"g.exr\"\n\
             Import \"part.pbrt\"\n\
             LightSource \"projection\" \"string filename\" \"p.exr\"\n\
             Material \"diffuse\" \"spectrum reflectance\" [ 400 0.1 700 0.9 ]\n\
             Shape \"curve\"\n",
        ),
    );
    let e = load_err(&p);
    assert_has(
        &e,
        &[
            "refused.pbrt",
            "line 6",
            "(5 reasons)",
            "line 6: LightSource \"goniometric\" is not supported",
            "part.pbrt line 2: material \"interface\"",
            "line 8: LightSource \"projection\" is not supported",
            "line 9: \"spectrum reflectance\": sampled spectra",
            "line 10: Shape \"curve\"",
        ],
    );
    // A colour space other than sRGB, a film that tints the image, an AOV integrator.
    let p = common::write(
        &d,
        "space.pbrt",
        "ColorSpace \"aces2065-1\"\nIntegrator \"ambientocclusion\"\nCamera \"perspective\"\n\
         Film \"rgb\" \"string sensor\" \"canon_eos_5d\"\nWorldBegin\n",
    );
    assert_has(
        &load_err(&p),
        &[
            "space.pbrt",
            "line 1: ColorSpace \"aces2065-1\"",
            "line 2: Integrator \"ambientocclusion\"",
            "line 4: Film sensor \"canon_eos_5d\"",
        ],
    );
}

#[test]
fn every_approximation_is_warned_with_its_file_and_line() {
    let d = common::folder("pbrt4", "warnings");
    let p = common::write(
        &d,
        "warned.pbrt",
        &scene(
            "Option \"bool disablepixeljitter\" true\n\
             MakeNamedMaterial \"a\" \"string type\" \"diffuse\"\n\
             MakeNamedMaterial \"b\" \"string type\" \"coateddiffuse\" \"float roughness\" 0.1\n\
             Material \"mix\" \"string materials\" [ \"a\" \"b\" ] \"float amount\" 0.7\n\
             Shape \"sphere\" \"point3 ignored\" [ 0 0 0 ]\n\
             LightSource \"spot\" \"point3 to\" [ 0 0 -1 ]\n\
             Material \"dielectric\" \"spectrum eta\" \"glass-F11\" \"float roughness\" 0.2\n\
             Shape \"sphere\"\n",
        ),
    );
    let s = load(&p);
    assert_has(
        warning(&s, "Option"),
        &["warned.pbrt:6", "disablepixeljitter"],
    );
    assert_has(warning(&s, "stochastic layering"), &["warned.pbrt:8"]);
    assert_has(warning(&s, "stochastic mix"), &["warned.pbrt:9", "\"b\""]);
    assert_has(warning(&s, "point3 ignored"), &["warned.pbrt:10"]);
    assert_has(warning(&s, "smoothstep"), &["warned.pbrt:11"]);
    assert_has(warning(&s, "dispersion"), &["warned.pbrt:12", "glass-F11"]);
    // A rough dielectric is frosted glass of alpha sqrt(roughness).
    match &s.materials[s.spheres[1].material as usize].kind {
        MaterialKind::RoughDielectric {
            ior,
            alpha_u,
            alpha_v,
            ..
        } => {
            assert!((ior - 1.7909).abs() < 1e-3, "{ior}");
            assert!((alpha_u - 0.2f32.sqrt()).abs() < 1e-6 && alpha_u == alpha_v);
        }
        other => panic!("rough dielectric imported as {other:?}"),
    }
    // The mix is its heavier material, the coated diffuse (our layered plastic, alpha sqrt(0.1)).
    let mixed = s.materials[s.spheres[0].material as usize].kind.clone();
    match mixed {
        MaterialKind::Plastic {
            layered: true,
            alpha,
            ior,
            ..
        } => {
            assert!((alpha - 0.1f32.sqrt()).abs() < 1e-6, "{alpha}");
            assert_eq!(ior, 1.5);
        }
        k => panic!("{k:?}"),
    }
}

#[test]
fn lights_follow_pbrt_v4s_photometric_scale_and_power() {
    let d = common::folder("pbrt4", "lights");
    let p = common::write(
        &d,
        "lights.pbrt",
        &scene(
            "LightSource \"point\" \"rgb I\" [ 1 2 3 ] \"float scale\" 2\n\
             LightSource \"point\" \"blackbody I\" 6504 \"float power\" 100\n\
             AttributeBegin\n\
             AreaLightSource \"diffuse\" \"spectrum L\" \"stdillum-D65\" \"float power\" 10\n\
             Translate 0 0 -3\n\
             Shape \"bilinearmesh\" \"point3 P\" [ -1 -1 0  1 -1 0  -1 1 0  1 1 0 ]\n\
             AttributeEnd\n\
             LightSource \"infinite\" \"rgb L\" [ 0.5 0.5 0.5 ] \"float illuminance\" 3.14159265\n",
        ),
    );
    let s = load(&p);
    let points: Vec<Vec3> = s
        .lights
        .iter()
        .filter_map(|l| match l {
            Light::Point { intensity, .. } => Some(*intensity),
            _ => None,
        })
        .collect();
    assert_eq!(points[0], Vec3::new(2.0, 4.0, 6.0));
    // 100 W over 4 pi sr, a blackbody of luminance 1 near white.
    let want = 100.0 / (4.0 * std::f32::consts::PI);
    assert!(
        (points[1] - Vec3::splat(want)).abs().max_element() < 0.05 * want,
        "{:?}",
        points[1]
    );
    // 10 W from a 2 x 2 quad, one-sided Lambertian: L = 10 / (4 pi).
    let area: Vec<Vec3> = s
        .lights
        .iter()
        .filter_map(|l| match l {
            Light::Triangle { radiance, n, .. } => {
                assert!(n.z > 0.99, "the patch faces dp/du x dp/dv: {n:?}");
                Some(*radiance)
            }
            _ => None,
        })
        .collect();
    assert_eq!(area.len(), 2, "one bilinear patch is two triangles");
    let want = 10.0 / (4.0 * std::f32::consts::PI);
    assert!(
        (area[0] - Vec3::splat(want)).abs().max_element() < 1e-3 * want,
        "{:?}",
        area[0]
    );
    // Illuminance pi from a uniform sky is radiance 1, times the colour (0.5).
    let sky = s
        .lights
        .iter()
        .find_map(|l| match l {
            Light::Dome { sky, .. } => Some(sky.radiance(Vec3::Y)),
            _ => None,
        })
        .expect("the sky");
    assert!(
        (sky - Vec3::splat(0.5)).abs().max_element() < 1e-5,
        "{sky:?}"
    );
}

/// A quad as PLY: `format` is "ascii" or "binary_little_endian".
fn ply(format: &str) -> Vec<u8> {
    let header = format!(
        "ply\nformat {format} 1.0\nelement vertex 4\nproperty float x\nproperty float y\n\
         property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    );
    let mut out = header.into_bytes();
    let corners = [
        [-1.0f32, -1.0, 0.0],
        [1.0, -1.0, 0.0],
        [1.0, 1.0, 0.0],
        [-1.0, 1.0, 0.0],
    ];
    if format == "ascii" {
        for c in corners {
            out.extend(format!("{} {} {}\n", c[0], c[1], c[2]).bytes());
        }
        out.extend(b"4 0 1 2 3\n");
    } else {
        for c in corners {
            for x in c {
                out.extend(x.to_le_bytes());
            }
        }
        out.push(4);
        for i in [0i32, 1, 2, 3] {
            out.extend(i.to_le_bytes());
        }
    }
    out
}

#[test]
fn plymesh_reads_ascii_binary_and_gzipped_files() {
    let d = common::folder("pbrt4", "ply");
    std::fs::write(d.join("ascii.ply"), ply("ascii")).expect("ply");
    std::fs::write(d.join("binary.ply"), ply("binary_little_endian")).expect("ply");
    let mut gz = libdeflater::Compressor::new(libdeflater::CompressionLvl::default());
    let raw = ply("binary_little_endian");
    let mut packed = vec![0u8; gz.gzip_compress_bound(raw.len())];
    let n = gz.gzip_compress(&raw, &mut packed).expect("gzip");
    packed.truncate(n);
    std::fs::write(d.join("packed.ply.gz"), &packed).expect("gz");
    std::fs::write(d.join("broken.ply.gz"), &packed[..n / 2]).expect("gz");
    // A gzip trailer claiming more than 1 GiB is refused before anything is allocated.
    let mut bomb = packed.clone();
    bomb[n - 4..].copy_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(d.join("bomb.ply.gz"), &bomb).expect("gz");
    let body = |file: &str| {
        scene(&format!(
            "Translate 0 0 -3\nShape \"plymesh\" \"string filename\" \"{file}\"\n"
        ))
    };
    for file in ["ascii.ply", "binary.ply", "packed.ply.gz"] {
        let s = load(&common::write(&d, "mesh.pbrt", &body(file)));
        assert_eq!(s.triangles.len(), 2, "{file}");
        assert_eq!(s.positions[0], Vec3::new(-1.0, -1.0, -3.0), "{file}");
    }
    // An `Import`ed file and the mesh it names are in the scene's file list, which is what
    // `omis submit` and `omis render --server` pack into the bundle.
    common::write(
        &d,
        "geometry.pbrt",
        "Translate 0 0 -3\nShape \"plymesh\" \"string filename\" \"packed.ply.gz\"\n",
    );
    let s = load(&common::write(
        &d,
        "imports.pbrt",
        &scene("Import \"geometry.pbrt\"\n"),
    ));
    let names: Vec<String> = s
        .files
        .iter()
        .filter_map(|f| Some(f.file_name()?.to_str()?.to_string()))
        .collect();
    assert_eq!(names, ["geometry.pbrt", "packed.ply.gz"]);
    let e = load_err(&common::write(&d, "broken.pbrt", &body("broken.ply.gz")));
    assert_has(&e, &["broken.pbrt", "line 7", "broken.ply.gz", "gzip"]);
    let e = load_err(&common::write(&d, "bomb.pbrt", &body("bomb.ply.gz")));
    assert_has(
        &e,
        &[
            "bomb.pbrt",
            "line 7",
            "bomb.ply.gz",
            "more than the 1073741824 allowed",
        ],
    );
}

#[test]
fn an_equal_area_octahedral_sky_is_resampled_in_pbrt_v4s_orientation() {
    // pbrt-v4's map puts light-space +z at the centre, +x at the middle of the right edge and +y
    // at the middle of the bottom edge (rows counted from the top): blue, red and green there.
    let d = common::folder("pbrt4", "sky");
    let n = 64;
    let colour = |x: usize, y: usize| {
        let (u, v) = ((x as f32 + 0.5) / n as f32, (y as f32 + 0.5) / n as f32);
        let mid = |t: f32| (0.25..0.75).contains(&t);
        if mid(u) && mid(v) {
            (0.0, 0.0, 1.0)
        } else if u > 0.75 && mid(v) {
            (1.0, 0.0, 0.0)
        } else if mid(u) && v > 0.75 {
            (0.0, 1.0, 0.0)
        } else {
            (0.0, 0.0, 0.0)
        }
    };
    exr::prelude::write_rgb_file(d.join("sky.exr"), n, n, colour).expect("exr");
    let s = load(&common::write(
        &d,
        "sky.pbrt",
        &scene("LightSource \"infinite\" \"string filename\" \"sky.exr\" \"float scale\" 2\n"),
    ));
    let sky = |w: Vec3| {
        s.lights
            .iter()
            .find_map(|l| match l {
                Light::Dome { sky, .. } => Some(sky.radiance(w.normalize())),
                _ => None,
            })
            .expect("the sky")
    };
    for (w, want) in [
        (Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, 0.0, 2.0)),
        (Vec3::new(1.0, 0.0, 0.3), Vec3::new(2.0, 0.0, 0.0)),
        (Vec3::new(0.0, 1.0, 0.3), Vec3::new(0.0, 2.0, 0.0)),
        (Vec3::new(0.0, 0.0, -1.0), Vec3::ZERO),
    ] {
        let got = sky(w);
        assert!(
            (got - want).abs().max_element() < 0.05,
            "toward {w}: {got} (want {want})"
        );
    }
    // A non-square image is not one of pbrt-v4's maps.
    exr::prelude::write_rgb_file(d.join("wide.exr"), 8, 4, |_, _| (1.0, 1.0, 1.0)).expect("exr");
    let e = load_err(&common::write(
        &d,
        "wide.pbrt",
        &scene("LightSource \"infinite\" \"string filename\" \"wide.exr\"\n"),
    ));
    assert_has(&e, &["wide.pbrt", "line 6", "square"]);
}
