//! The pbrt-v3 importer's directives, from small files written to a temporary folder.

use crate::common;
use crate::common::import::{assert_has, close, load, material, warning, write_plys};
use crate::support::folder;
use omis::geometry::{Vec2, Vec3};
use omis::light::Light;
use omis::material::MaterialKind;

const PBRT_HEADER: &str = r#"# a comment line
Integrator "path" "integer maxdepth" [ 7 ]
Sampler "halton" "integer pixelsamples" 9
PixelFilter "box"
Film "image" "integer xresolution" [ 40 ] "integer yresolution" [ 20 ] "string filename" "out.exr"
LookAt 0 1 10  0 1 0  0 1 0
Camera "perspective" "float fov" [ 30 ]
"#;

#[test]
fn pbrt_options_camera_and_world_directives() {
    let d = folder("pbrt-directives");
    let p = common::write(
        &d,
        "scene.pbrt",
        &format!(
            r#"{PBRT_HEADER}
WorldBegin
  MakeNamedMaterial "white" "string type" "matte" "rgb Kd" [ 0.5 0.6 0.7 ]
  MakeNamedMaterial "shiny" "string type" [ "metal" ] "float roughness" 0.1
  MakeNamedMaterial "raw" "string type" [ "metal" ] "float roughness" 0.1 "bool remaproughness" "false"
      "rgb eta" [ 1 2 3 ] "rgb k" [ 4 5 6 ]
  MakeNamedMaterial "aniso" "string type" "metal" "float uroughness" 0.2 "float vroughness" 0.3
      "bool remaproughness" false
  MakeNamedMaterial "paint" "string type" "plastic" "rgb Kd" [ 0.3 0.2 0.1 ] "rgb Ks" [ 0.4 0.4 0.4 ]
      "float roughness" 0.05 "bool remaproughness" "false"
  MakeNamedMaterial "coat" "string type" "substrate" "rgb Kd" [ 0.3 0.3 0.3 ] "rgb Ks" [ 0.1 0.1 0.1 ]
  MakeNamedMaterial "mirror" "string type" "mirror" "rgb Kr" [ 0.8 0.8 0.8 ]
  MakeNamedMaterial "glass" "string type" "glass" "float index" 1.33
  MakeNamedMaterial "uberplastic" "string type" "uber" "rgb Kd" [ 0.2 0.2 0.2 ] "float eta" 1.4
  MakeNamedMaterial "uberglass" "string type" "uber" "rgb Kd" [ 0 0 0 ] "rgb Ks" [ 0 0 0 ] "rgb Kt" [ 1 1 1 ] "rgb Kr" [ 1 1 1 ]

  NamedMaterial "white"
  Shape "trianglemesh" "integer indices" [ 0 1 2 0 2 3 ]
      "point P" [ -5 0 -5  5 0 -5  5 0 5  -5 0 5 ]
      "normal N" [ 0 1 0 0 1 0 0 1 0 0 1 0 ]
      "float uv" [ 0 0 1 0 1 1 0 1 ]
  AttributeBegin
    Material "plastic" "rgb Kd" [ 0.1 0.2 0.3 ]
    Translate 1 0 0
    Scale 2 2 2
    Shape "sphere" "float radius" 0.5
    TransformBegin
      Rotate 90 0 0 1
      Translate 1 0 0
      NamedMaterial "mirror"
      Shape "sphere" "float radius" 0.25
    TransformEnd
    ConcatTransform [ 1 0 0 0  0 1 0 0  0 0 1 0  0 0 3 1 ]
    Shape "sphere"
  AttributeEnd
  # After AttributeEnd: identity again and the "white" material.
  Shape "sphere" "float radius" 0.125
  AttributeBegin
    Transform [ 1 0 0 0  0 1 0 0  0 0 1 0  4 5 6 1 ]
    Identity
    Translate 0 2 0
    AreaLightSource "diffuse" "rgb L" [ 10 20 30 ] "rgb scale" [ 2 2 2 ]
    Shape "sphere" "float radius" 0.3
  AttributeEnd
  LightSource "point" "rgb I" [ 5 5 5 ] "point from" [ 0 4 0 ]
WorldEnd
"#
        ),
    );
    let s = load(&p);
    // Everything here is supported; only the substrate approximation is worth a warning.
    assert_eq!(s.warnings.len(), 1, "{:#?}", s.warnings);
    assert_has(
        warning(&s, "substrate"),
        &["scene.pbrt:18", "layered plastic"],
    );
    // Integrator, Sampler, Film.
    assert_eq!(s.defaults.max_depth, Some(7));
    assert_eq!(s.defaults.spp, Some(9));
    assert_eq!((s.camera.width, s.camera.height), (40, 20));
    // Landscape: pbrt's fov is on the shorter (vertical) axis.
    assert!(
        close(s.camera.vfov_deg, 30.0, 1e-5),
        "{}",
        s.camera.vfov_deg
    );
    assert!((s.camera.position - Vec3::new(0.0, 1.0, 10.0)).length() < 1e-5);
    // A LookAt camera is a proper rotation in pbrt's left-handed camera space: mirrored for us.
    assert!(s.camera.flip_x());

    // Shapes: spheres in creation order with their CTMs.
    let sph: Vec<(Vec3, f32)> = s.spheres.iter().map(|x| (x.center, x.radius)).collect();
    let expect = [
        (Vec3::new(1.0, 0.0, 0.0), 1.0), // Translate 1 0 0, Scale 2: radius 0.5 * 2
        (Vec3::new(1.0, 2.0, 0.0), 0.5), // then Rotate 90 about z of (1, 0, 0): (0, 1, 0) * 2
        (Vec3::new(1.0, 0.0, 6.0), 2.0), // ConcatTransform translate z 3 (scaled by 2)
        (Vec3::new(0.0, 0.0, 0.0), 0.125), // AttributeEnd restored the identity
        (Vec3::new(0.0, 2.0, 0.0), 0.3), // Identity dropped the Transform
    ];
    assert_eq!(sph.len(), expect.len());
    for (i, ((c, r), (ec, er))) in sph.iter().zip(expect).enumerate() {
        assert!(
            (*c - ec).length() < 1e-4 && close(*r, er, 1e-5),
            "sphere {i}: {c:?} r {r}, expected {ec:?} r {er}"
        );
    }
    // Materials: AttributeEnd restored "white"; the TransformBegin block's NamedMaterial stays
    // until AttributeEnd.
    let mat = |i: usize| &s.materials[s.spheres[i].material as usize];
    assert!(matches!(
        mat(0).kind,
        MaterialKind::Plastic { layered: false, .. }
    ));
    assert_eq!(mat(1).name, "mirror");
    assert_eq!(mat(2).name, "mirror");
    assert_eq!(mat(3).name, "white");
    assert!(
        s.materials.iter().all(|m| m.two_sided),
        "pbrt materials are two-sided"
    );
    // The area light: L * scale, only on the sphere inside its AttributeBegin.
    assert_eq!(s.lights.len(), 2);
    assert!(s.lights.iter().any(
        |l| matches!(l, Light::Sphere { radiance, .. } if *radiance == Vec3::new(20.0, 40.0, 60.0))
    ));
    assert!(s.lights.iter().any(|l| matches!(l, Light::Point { position, intensity } if (*position - Vec3::new(0.0, 4.0, 0.0)).length() < 1e-6 && *intensity == Vec3::splat(5.0))));
    assert_eq!(s.stats.triangles, 2);
    assert!(s.uvs.iter().any(|uv| *uv == Vec2::new(1.0, 1.0)));

    // Material mappings.
    match &material(&s, "white").kind {
        MaterialKind::Lambert { albedo } => assert_eq!(albedo.average(), Vec3::new(0.5, 0.6, 0.7)),
        k => panic!("matte became {k:?}"),
    }
    match &material(&s, "shiny").kind {
        MaterialKind::RoughConductor {
            alpha_u,
            alpha_v,
            eta,
            ..
        } => {
            // pbrt-v3 RoughnessToAlpha(0.1), and the default copper.
            let a = omis::scene::pbrt::roughness_to_alpha(0.1);
            assert!(close(*alpha_u, a, 1e-6) && close(*alpha_v, a, 1e-6));
            assert!((a - 0.46176).abs() < 1e-4, "{a}");
            assert!(close(eta.x, 0.200438, 1e-5));
        }
        k => panic!("metal became {k:?}"),
    }
    match &material(&s, "raw").kind {
        MaterialKind::RoughConductor {
            alpha_u,
            eta,
            k,
            scale,
            ..
        } => {
            assert_eq!(*alpha_u, 0.1);
            assert_eq!(*eta, Vec3::new(1.0, 2.0, 3.0));
            assert_eq!(*k, Vec3::new(4.0, 5.0, 6.0));
            assert_eq!(*scale, Vec3::ONE);
        }
        k => panic!("metal became {k:?}"),
    }
    match &material(&s, "aniso").kind {
        MaterialKind::RoughConductor {
            alpha_u, alpha_v, ..
        } => assert_eq!((*alpha_u, *alpha_v), (0.2, 0.3)),
        k => panic!("metal became {k:?}"),
    }
    match &material(&s, "paint").kind {
        MaterialKind::Plastic {
            specular,
            ior,
            alpha,
            layered,
            ..
        } => {
            assert_eq!(
                (*specular, *ior, *alpha, *layered),
                (Vec3::splat(0.4), 1.5, 0.05, false)
            );
        }
        k => panic!("plastic became {k:?}"),
    }
    assert!(matches!(
        material(&s, "coat").kind,
        MaterialKind::Plastic { layered: true, .. }
    ));
    assert!(
        matches!(material(&s, "mirror").kind, MaterialKind::Mirror { reflectance } if reflectance == Vec3::splat(0.8))
    );
    assert!(
        matches!(material(&s, "glass").kind, MaterialKind::Dielectric { ior, .. } if ior == 1.33)
    );
    assert!(
        matches!(material(&s, "uberplastic").kind, MaterialKind::Plastic { ior, layered: false, .. } if ior == 1.4)
    );
    assert!(matches!(
        material(&s, "uberglass").kind,
        MaterialKind::Dielectric { .. }
    ));
}

#[test]
fn pbrt_fov_is_on_the_shorter_axis() {
    let d = folder("pbrt-fov");
    for (w, h, expect) in [
        (40u32, 20u32, 30.0f32),
        (
            20,
            40,
            2.0 * ((15.0f32).to_radians().tan() * 2.0).atan().to_degrees(),
        ),
        (30, 30, 30.0),
    ] {
        let p = common::write(
            &d,
            "fov.pbrt",
            &format!(
                "Film \"image\" \"integer xresolution\" {w} \"integer yresolution\" {h}\nCamera \"perspective\" \"float fov\" 30\nWorldBegin\nWorldEnd\n"
            ),
        );
        let s = load(&p);
        assert!(
            close(s.camera.vfov_deg, expect, 1e-5),
            "{w}x{h}: {} vs {expect}",
            s.camera.vfov_deg
        );
    }
}

#[test]
fn pbrt_camera_handedness_decides_mirroring() {
    let d = folder("pbrt-hand");
    // A camera at the origin looking down +z with +y up. In pbrt-v3, camera +x = up x dir = +x
    // is on the image's right; our right-handed camera would show -x there.
    let right_of = |prefix: &str| {
        let p = common::write(
            &d,
            "h.pbrt",
            &format!(
                "Film \"image\" \"integer xresolution\" 32 \"integer yresolution\" 32\n{prefix}\nLookAt 0 0 0  0 0 1  0 1 0\nCamera \"perspective\" \"float fov\" 40\nWorldBegin\nWorldEnd\n"
            ),
        );
        let s = load(&p);
        (s.camera.ray(Vec2::new(30.0, 16.0)).d.x, s.camera.flip_x())
    };
    let (x, flip) = right_of("");
    assert!(
        x > 0.0 && flip,
        "pbrt LookAt: +x must be on the right ({x}, flip {flip})"
    );
    // The usual trick to make a pbrt camera right-handed: the image shows -x on the right.
    let (x, flip) = right_of("Scale -1 1 1");
    assert!(
        x < 0.0 && !flip,
        "Scale -1 1 1: -x on the right ({x}, flip {flip})"
    );
}

#[test]
fn pbrt_plymesh_ascii_and_binary_include_and_instances() {
    let d = folder("pbrt-ply");
    write_plys(&d);
    common::write(
        &d,
        "geometry.pbrt",
        "# included\nShape \"plymesh\" \"string filename\" \"quad.ply\"\n",
    );
    let p = common::write(
        &d,
        "scene.pbrt",
        r#"Film "image" "integer xresolution" 8 "integer yresolution" 8
Camera "perspective"
WorldBegin
Include "geometry.pbrt"
Shape "plymesh" "string filename" [ "models/quad-bin.ply" ]
ObjectBegin "pair"
  Translate 0 0 5
  Shape "plymesh" "string filename" "quad.ply"
ObjectEnd
AttributeBegin
  Translate 10 0 0
  ObjectInstance "pair"
AttributeEnd
ObjectInstance "pair"
WorldEnd
"#,
    );
    let s = load(&p);
    assert_eq!(
        s.stats.triangles, 8,
        "2 (ASCII) + 2 (binary) + 2 instances x 2"
    );
    let (lo, hi) = s.bounds();
    assert!((lo - Vec3::ZERO).length() < 1e-6, "{lo:?}");
    assert!((hi - Vec3::new(11.0, 1.0, 5.0)).length() < 1e-6, "{hi:?}");
}

#[test]
fn pbrt_emission_side_follows_winding_normals_and_reverse_orientation() {
    let d = folder("pbrt-orient");
    // A triangle in the plane y = 1, counter-clockwise seen from below: it faces down.
    let tri =
        r#"Shape "trianglemesh" "point P" [ 0 1 0  1 1 0  0 1 1 ] "integer indices" [ 0 1 2 ]"#;
    let normal_of = |prefix: &str, extra: &str| {
        let p = common::write(
            &d,
            "o.pbrt",
            &format!(
                "Camera \"perspective\"\nWorldBegin\nAttributeBegin\n{prefix}\nAreaLightSource \"diffuse\"\n{tri} {extra}\nAttributeEnd\nWorldEnd\n"
            ),
        );
        let s = load(&p);
        match &s.lights[0] {
            Light::Triangle { n, .. } => n.y,
            l => panic!("{l:?}"),
        }
    };
    assert!(normal_of("", "") < 0.0);
    assert!(normal_of("ReverseOrientation", "") > 0.0);
    // A reflection flips the handedness, which pbrt-v3 compensates for.
    assert!(normal_of("Scale 1 1 -1", "") < 0.0);
    // Vertex normals decide, and ReverseOrientation does not change them (pbrt-v3).
    assert!(normal_of("ReverseOrientation", r#""normal N" [ 0 1 0 0 1 0 0 1 0 ]"#) > 0.0);
}
