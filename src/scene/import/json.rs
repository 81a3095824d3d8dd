//! The native scene format: JSON, documented in scenes/README.md.

use super::common::Bitmaps;
use super::resolve::Resolver;
pub(crate) use super::resolve::scene_folder;
use crate::camera::Camera;
use crate::geometry::{Mat4, Rgb, Transform, Vec2, Vec3};
use crate::material::Distribution;
use crate::material::{Material, MaterialKind, Texture};
use crate::scene::{MeshData, SceneBuilder, SceneError};
use serde::Deserialize;
use serde::de::DeserializeOwned;
use serde_json::value::RawValue;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    camera: CameraDesc,
    #[serde(default)]
    render: RenderDesc,
    /// Typed per entry (see [`typed`]) so that errors keep their JSON path. Kept as text until
    /// then: a tree of JSON values would take tens of times the memory of an inline mesh.
    #[serde(default)]
    materials: BTreeMap<String, Box<RawValue>>,
    #[serde(default)]
    shapes: Vec<Box<RawValue>>,
    #[serde(default)]
    lights: Vec<Box<RawValue>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraDesc {
    position: [f32; 3],
    look_at: [f32; 3],
    #[serde(default = "default_up")]
    up: [f32; 3],
    /// Vertical field of view in degrees.
    fov: f32,
    resolution: [u32; 2],
}

fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RenderDesc {
    spp: Option<u32>,
    max_depth: Option<u32>,
}

/// A colour: one grey value or [r, g, b].
#[derive(Deserialize, Clone, Copy)]
#[serde(untagged)]
enum Color {
    Grey(f32),
    Rgb([f32; 3]),
}

impl Color {
    fn rgb(self) -> Rgb {
        match self {
            Color::Grey(g) => Rgb::splat(g),
            Color::Rgb(c) => Rgb::from_array(c),
        }
    }
}

#[derive(Deserialize, Clone)]
#[serde(untagged)]
enum ColorOrTexture {
    Color(Color),
    Texture {
        texture: String,
        #[serde(default)]
        scale: Option<Color>,
    },
}

fn one() -> Color {
    Color::Grey(1.0)
}
fn ior_default() -> f32 {
    1.5
}
fn ext_ior_default() -> f32 {
    1.0
}
fn yes() -> bool {
    true
}
fn alpha_default() -> f32 {
    0.1
}

enum MaterialDesc {
    Lambert(LambertMaterial),
    Phong(PhongMaterial),
    Mirror(MirrorMaterial),
    Dielectric(DielectricMaterial),
    RoughDielectric(RoughDielectricMaterial),
    RoughConductor(RoughConductorMaterial),
    Plastic(PlasticMaterial),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LambertMaterial {
    #[serde(rename = "type")]
    _type: String,
    albedo: ColorOrTexture,
    #[serde(default = "yes")]
    two_sided: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PhongMaterial {
    #[serde(rename = "type")]
    _type: String,
    kd: Color,
    ks: Color,
    exponent: f32,
    #[serde(default = "yes")]
    two_sided: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MirrorMaterial {
    #[serde(rename = "type")]
    _type: String,
    #[serde(default = "one")]
    reflectance: Color,
    #[serde(default = "yes")]
    two_sided: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct DielectricMaterial {
    #[serde(rename = "type")]
    _type: String,
    #[serde(default = "ior_default")]
    ior: f32,
    #[serde(default = "ext_ior_default")]
    ext_ior: f32,
    #[serde(default = "one")]
    reflectance: Color,
    #[serde(default = "one")]
    transmittance: Color,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RoughDielectricMaterial {
    #[serde(rename = "type")]
    _type: String,
    #[serde(default = "ior_default")]
    ior: f32,
    #[serde(default = "ext_ior_default")]
    ext_ior: f32,
    #[serde(default)]
    alpha: Option<f32>,
    #[serde(default)]
    alpha_u: Option<f32>,
    #[serde(default)]
    alpha_v: Option<f32>,
    #[serde(default = "one")]
    reflectance: Color,
    #[serde(default = "one")]
    transmittance: Color,
    #[serde(default)]
    distribution: Distribution,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RoughConductorMaterial {
    #[serde(rename = "type")]
    _type: String,
    eta: Color,
    k: Color,
    #[serde(default)]
    alpha: Option<f32>,
    #[serde(default)]
    alpha_u: Option<f32>,
    #[serde(default)]
    alpha_v: Option<f32>,
    #[serde(default = "one")]
    scale: Color,
    #[serde(default = "yes")]
    two_sided: bool,
    #[serde(default)]
    distribution: Distribution,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PlasticMaterial {
    #[serde(rename = "type")]
    _type: String,
    diffuse: ColorOrTexture,
    #[serde(default = "one")]
    specular: Color,
    #[serde(default = "ior_default")]
    ior: f32,
    #[serde(default = "alpha_default")]
    alpha: f32,
    #[serde(default = "yes")]
    layered: bool,
    #[serde(default)]
    nonlinear: bool,
    #[serde(default = "yes")]
    two_sided: bool,
    #[serde(default)]
    distribution: Distribution,
}

#[derive(Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
enum TransformOp {
    Translate([f32; 3]),
    Scale(Color),
    Rotate {
        axis: [f32; 3],
        degrees: f32,
    },
    /// 16 numbers, row-major, acting on column vectors.
    Matrix([f32; 16]),
}

enum ShapeDesc {
    Mesh(MeshShape),
    Triangles(TrianglesShape),
    Quad(QuadShape),
    Sphere(SphereShape),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MeshShape {
    #[serde(rename = "type")]
    _type: String,
    file: String,
    material: String,
    #[serde(default)]
    emission: Option<Color>,
    #[serde(default)]
    transform: Vec<TransformOp>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TrianglesShape {
    #[serde(rename = "type")]
    _type: String,
    positions: Vec<[f32; 3]>,
    indices: Vec<[u32; 3]>,
    #[serde(default)]
    normals: Vec<[f32; 3]>,
    #[serde(default)]
    uvs: Vec<[f32; 2]>,
    material: String,
    #[serde(default)]
    emission: Option<Color>,
    #[serde(default)]
    transform: Vec<TransformOp>,
}

/// Parallelogram corner, corner + edge1, corner + edge1 + edge2, corner + edge2; it faces
/// (and emits toward) edge1 x edge2.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct QuadShape {
    #[serde(rename = "type")]
    _type: String,
    corner: [f32; 3],
    edge1: [f32; 3],
    edge2: [f32; 3],
    material: String,
    #[serde(default)]
    emission: Option<Color>,
    #[serde(default)]
    transform: Vec<TransformOp>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SphereShape {
    #[serde(rename = "type")]
    _type: String,
    center: [f32; 3],
    radius: f32,
    material: String,
    #[serde(default)]
    emission: Option<Color>,
    #[serde(default)]
    inward: bool,
}

enum LightDesc {
    Point(PointLight),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PointLight {
    #[serde(rename = "type")]
    _type: String,
    position: [f32; 3],
    intensity: Color,
}

fn build_transform(ops: &[TransformOp], file: &Path, loc: &str) -> Result<Transform, SceneError> {
    let mut t = Transform::IDENTITY;
    for (i, op) in ops.iter().enumerate() {
        let m = match op {
            TransformOp::Translate(v) => Mat4::from_translation(Vec3::from_array(*v)),
            TransformOp::Scale(c) => Mat4::from_scale(c.rgb()),
            TransformOp::Rotate { axis, degrees } => {
                let a = Vec3::from_array(*axis).normalize_or_zero();
                if a == Vec3::ZERO {
                    return Err(SceneError::new(
                        file,
                        format!("{loc}.transform[{i}].rotate.axis"),
                        "rotation axis is zero",
                    ));
                }
                Mat4::from_axis_angle(a, degrees.to_radians())
            }
            TransformOp::Matrix(m) => Mat4::from_cols_array(m).transpose(),
        };
        let step = Transform::new(m).ok_or_else(|| {
            SceneError::new(
                file,
                format!("{loc}.transform[{i}]"),
                "transform is singular or not finite",
            )
        })?;
        t = t.then(&step);
    }
    Ok(t)
}

struct Loader<'a> {
    file: &'a Path,
    textures: Bitmaps,
}

impl Loader<'_> {
    fn texture(
        &mut self,
        resolver: &mut Resolver,
        v: &ColorOrTexture,
        loc: &str,
    ) -> Result<Texture, SceneError> {
        match v {
            ColorOrTexture::Color(c) => {
                let c = c.rgb();
                check_color(self.file, loc, c)?;
                Ok(Texture::Constant(c))
            }
            ColorOrTexture::Texture { texture, scale } => {
                let at = format!("{loc}.texture");
                let f = resolver.resolve(texture, &at)?;
                let image = self
                    .textures
                    .load(&f, true)
                    .map_err(|e| SceneError::new(self.file, at, e.to_string()))?;
                let scale = scale.map(Color::rgb).unwrap_or(Rgb::ONE);
                check_color(self.file, &format!("{loc}.scale"), scale)?;
                Ok(Texture::Bitmap { image, scale })
            }
        }
    }
}

fn check_color(file: &Path, loc: &str, c: Rgb) -> Result<(), SceneError> {
    if c.is_finite() && c.min_element() >= 0.0 {
        Ok(())
    } else {
        Err(SceneError::new(
            file,
            loc,
            format!("must be finite and >= 0, got {c:?}"),
        ))
    }
}

fn check_positive(file: &Path, loc: &str, v: f32) -> Result<(), SceneError> {
    if v > 0.0 && v.is_finite() {
        Ok(())
    } else {
        Err(SceneError::new(file, loc, format!("must be > 0, got {v}")))
    }
}

fn material(
    loader: &mut Loader,
    resolver: &mut Resolver,
    name: &str,
    desc: &MaterialDesc,
) -> Result<Material, SceneError> {
    let file = loader.file;
    let loc = format!("materials.{name}");
    let at = |f: &str| format!("{loc}.{f}");
    let (kind, two_sided) = match desc {
        MaterialDesc::Lambert(LambertMaterial {
            albedo, two_sided, ..
        }) => (
            MaterialKind::Lambert {
                albedo: loader.texture(resolver, albedo, &at("albedo"))?,
            },
            *two_sided,
        ),
        MaterialDesc::Phong(PhongMaterial {
            kd,
            ks,
            exponent,
            two_sided,
            ..
        }) => {
            check_color(file, &at("kd"), kd.rgb())?;
            check_color(file, &at("ks"), ks.rgb())?;
            if !(*exponent >= 0.0 && exponent.is_finite()) {
                return Err(SceneError::new(
                    file,
                    at("exponent"),
                    "must be finite and >= 0",
                ));
            }
            let sum = kd.rgb() + ks.rgb();
            if sum.max_element() > 1.0 {
                return Err(SceneError::new(
                    file,
                    at("ks"),
                    "kd + ks must not exceed 1 in any channel (energy conservation)",
                ));
            }
            (
                MaterialKind::Phong {
                    kd: kd.rgb(),
                    ks: ks.rgb(),
                    exponent: *exponent,
                },
                *two_sided,
            )
        }
        MaterialDesc::Mirror(MirrorMaterial {
            reflectance,
            two_sided,
            ..
        }) => {
            check_color(file, &at("reflectance"), reflectance.rgb())?;
            (
                MaterialKind::Mirror {
                    reflectance: reflectance.rgb(),
                },
                *two_sided,
            )
        }
        MaterialDesc::Dielectric(DielectricMaterial {
            ior,
            ext_ior,
            reflectance,
            transmittance,
            ..
        }) => {
            check_positive(file, &at("ior"), *ior)?;
            check_positive(file, &at("ext_ior"), *ext_ior)?;
            check_color(file, &at("reflectance"), reflectance.rgb())?;
            check_color(file, &at("transmittance"), transmittance.rgb())?;
            (
                MaterialKind::Dielectric {
                    ior: ior / ext_ior,
                    reflectance: reflectance.rgb(),
                    transmittance: transmittance.rgb(),
                },
                true,
            )
        }
        MaterialDesc::RoughDielectric(RoughDielectricMaterial {
            ior,
            ext_ior,
            alpha,
            alpha_u,
            alpha_v,
            reflectance,
            transmittance,
            distribution,
            ..
        }) => {
            let au = alpha_u.or(*alpha).unwrap_or(0.1);
            let av = alpha_v.or(*alpha).unwrap_or(au);
            check_positive(file, &at("ior"), *ior)?;
            check_positive(file, &at("ext_ior"), *ext_ior)?;
            check_positive(file, &at("alpha"), au)?;
            check_positive(file, &at("alpha"), av)?;
            check_color(file, &at("reflectance"), reflectance.rgb())?;
            check_color(file, &at("transmittance"), transmittance.rgb())?;
            (
                MaterialKind::RoughDielectric {
                    distribution: *distribution,
                    ior: ior / ext_ior,
                    alpha_u: au,
                    alpha_v: av,
                    reflectance: reflectance.rgb(),
                    transmittance: transmittance.rgb(),
                },
                true,
            )
        }
        MaterialDesc::RoughConductor(RoughConductorMaterial {
            eta,
            k,
            alpha,
            alpha_u,
            alpha_v,
            scale,
            two_sided,
            distribution,
            ..
        }) => {
            let au = alpha_u.or(*alpha).unwrap_or(0.1);
            let av = alpha_v.or(*alpha).unwrap_or(au);
            check_positive(file, &at("alpha"), au)?;
            check_positive(file, &at("alpha"), av)?;
            check_color(file, &at("eta"), eta.rgb())?;
            check_color(file, &at("k"), k.rgb())?;
            check_color(file, &at("scale"), scale.rgb())?;
            (
                MaterialKind::RoughConductor {
                    distribution: *distribution,
                    eta: eta.rgb(),
                    k: k.rgb(),
                    alpha_u: au,
                    alpha_v: av,
                    scale: scale.rgb(),
                },
                *two_sided,
            )
        }
        MaterialDesc::Plastic(PlasticMaterial {
            diffuse,
            specular,
            ior,
            alpha,
            layered,
            nonlinear,
            two_sided,
            distribution,
            ..
        }) => {
            check_positive(file, &at("ior"), *ior)?;
            check_positive(file, &at("alpha"), *alpha)?;
            check_color(file, &at("specular"), specular.rgb())?;
            (
                MaterialKind::Plastic {
                    distribution: *distribution,
                    diffuse: loader.texture(resolver, diffuse, &at("diffuse"))?,
                    specular: specular.rgb(),
                    ior: *ior,
                    alpha: *alpha,
                    layered: *layered,
                    nonlinear: *nonlinear,
                },
                *two_sided,
            )
        }
    };
    Ok(Material::new(name, kind, two_sided))
}

/// Deserialises one JSON value, naming `loc` + the inner JSON path in errors.
fn typed<T: DeserializeOwned>(file: &Path, loc: &str, v: &RawValue) -> Result<T, SceneError> {
    let de = &mut serde_json::Deserializer::from_str(v.get());
    serde_path_to_error::deserialize(de).map_err(|e| {
        let inner = e.path().to_string();
        let location = if inner == "." || inner.is_empty() {
            loc.to_string()
        } else {
            format!("{loc}.{inner}")
        };
        SceneError::new(file, location, without_position(&e.into_inner()))
    })
}

/// A JSON error's message without its line and column (which would count within the entry's
/// text, not the file's).
fn without_position(e: &serde_json::Error) -> String {
    let m = e.to_string();
    let suffix = format!(" at line {} column {}", e.line(), e.column());
    match m.strip_suffix(&suffix) {
        Some(m) => m.to_string(),
        None => m,
    }
}

/// The `"type"` of an entry, read without building anything of the rest of it.
fn type_tag(file: &Path, loc: &str, v: &RawValue) -> Result<String, SceneError> {
    #[derive(Deserialize)]
    struct Tag {
        #[serde(rename = "type")]
        ty: Option<serde_json::Value>,
    }
    let missing = || SceneError::new(file, format!("{loc}.type"), "missing \"type\"");
    let tag: Tag = serde_json::from_str(v.get()).map_err(|e| {
        if e.is_data() {
            missing()
        } else {
            SceneError::new(file, loc, without_position(&e))
        }
    })?;
    match tag.ty {
        Some(serde_json::Value::String(t)) => Ok(t),
        _ => Err(missing()),
    }
}

fn unknown_type(file: &Path, loc: &str, t: &str, known: &str) -> SceneError {
    SceneError::new(
        file,
        format!("{loc}.type"),
        format!("unknown type '{t}' (expected one of: {known})"),
    )
}

fn material_desc(file: &Path, loc: &str, v: &RawValue) -> Result<MaterialDesc, SceneError> {
    Ok(match type_tag(file, loc, v)?.as_str() {
        "lambert" => MaterialDesc::Lambert(typed(file, loc, v)?),
        "phong" => MaterialDesc::Phong(typed(file, loc, v)?),
        "mirror" => MaterialDesc::Mirror(typed(file, loc, v)?),
        "dielectric" => MaterialDesc::Dielectric(typed(file, loc, v)?),
        "rough_dielectric" => MaterialDesc::RoughDielectric(typed(file, loc, v)?),
        "rough_conductor" => MaterialDesc::RoughConductor(typed(file, loc, v)?),
        "plastic" => MaterialDesc::Plastic(typed(file, loc, v)?),
        t => {
            return Err(unknown_type(
                file,
                loc,
                t,
                "lambert, phong, mirror, dielectric, rough_dielectric, rough_conductor, plastic",
            ));
        }
    })
}

fn shape_desc(file: &Path, loc: &str, v: &RawValue) -> Result<ShapeDesc, SceneError> {
    Ok(match type_tag(file, loc, v)?.as_str() {
        "mesh" => ShapeDesc::Mesh(typed(file, loc, v)?),
        "triangles" => ShapeDesc::Triangles(typed(file, loc, v)?),
        "quad" => ShapeDesc::Quad(typed(file, loc, v)?),
        "sphere" => ShapeDesc::Sphere(typed(file, loc, v)?),
        t => return Err(unknown_type(file, loc, t, "mesh, triangles, quad, sphere")),
    })
}

fn light_desc(file: &Path, loc: &str, v: &RawValue) -> Result<LightDesc, SceneError> {
    Ok(match type_tag(file, loc, v)?.as_str() {
        "point" => LightDesc::Point(typed(file, loc, v)?),
        t => return Err(unknown_type(file, loc, t, "point")),
    })
}

fn v3(a: [f32; 3]) -> Vec3 {
    Vec3::from_array(a)
}

/// Parses JSON scene text; `file` names the source in errors and anchors relative paths (the
/// builder's resolver records the files the text names).
pub fn parse(text: &str, file: &Path) -> Result<SceneBuilder, SceneError> {
    parse_with(text, Resolver::new(file))
}

/// Parses JSON scene text, reading the files it names through `resolver`.
pub(crate) fn parse_with(text: &str, resolver: Resolver) -> Result<SceneBuilder, SceneError> {
    let file = &resolver.scene_file().to_path_buf();
    let de = &mut serde_json::Deserializer::from_str(text);
    let desc: SceneFile = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let location = if path == "." || path.is_empty() {
            format!("line {}", inner.line())
        } else {
            format!("{path} (line {})", inner.line())
        };
        SceneError::new(file, location, inner.to_string())
    })?;
    let mut b = SceneBuilder::new(resolver);
    b.defaults.spp = desc.render.spp;
    b.defaults.max_depth = desc.render.max_depth;
    if desc.render.spp == Some(0) {
        return Err(SceneError::new(file, "render.spp", "must be >= 1"));
    }

    let c = &desc.camera;
    let cam = Camera::new(
        v3(c.position),
        v3(c.look_at),
        v3(c.up),
        c.fov,
        c.resolution[0],
        c.resolution[1],
    )
    .map_err(|m| SceneError::new(file, "camera", m.to_string()))?;
    b.set_camera(cam);

    let mut loader = Loader {
        file,
        textures: Bitmaps::default(),
    };
    let mut ids: HashMap<&str, u32> = HashMap::new();
    for (name, v) in &desc.materials {
        let m = material_desc(file, &format!("materials.{name}"), v)?;
        let mat = material(&mut loader, b.resolver(), name, &m)?;
        ids.insert(name.as_str(), b.add_material(mat));
    }
    let lookup = |name: &str, loc: &str| -> Result<u32, SceneError> {
        ids.get(name).copied().ok_or_else(|| {
            SceneError::new(
                file,
                format!("{loc}.material"),
                format!("unknown material '{name}'"),
            )
        })
    };
    let emission = |e: &Option<Color>, loc: &str| -> Result<Option<Rgb>, SceneError> {
        match e {
            None => Ok(None),
            Some(c) => {
                check_color(file, &format!("{loc}.emission"), c.rgb())?;
                Ok(Some(c.rgb()))
            }
        }
    };

    for (i, v) in desc.shapes.iter().enumerate() {
        let loc = format!("shapes[{i}]");
        match &shape_desc(file, &loc, v)? {
            ShapeDesc::Mesh(MeshShape {
                file: mesh_file,
                material,
                emission: e,
                transform,
                ..
            }) => {
                let m = lookup(material, &loc)?;
                let f = b.resolver().resolve(mesh_file, &format!("{loc}.file"))?;
                let path = f.path().display();
                let mesh = super::mesh::load_mesh(&f).map_err(|msg| {
                    SceneError::new(file, format!("{loc}.file"), format!("{path}: {msg}"))
                })?;
                let t = build_transform(transform, file, &loc)?;
                let e = emission(e, &loc)?;
                b.add_mesh(&mesh, &t, m, e, &format!("{loc} ({path})"))?;
            }
            ShapeDesc::Triangles(TrianglesShape {
                positions,
                indices,
                normals,
                uvs,
                material,
                emission: e,
                transform,
                ..
            }) => {
                let m = lookup(material, &loc)?;
                let mesh = MeshData {
                    positions: positions.iter().map(|p| v3(*p)).collect(),
                    normals: normals.iter().map(|p| v3(*p)).collect(),
                    uvs: uvs.iter().map(|p| Vec2::from_array(*p)).collect(),
                    indices: indices.clone(),
                };
                let t = build_transform(transform, file, &loc)?;
                let e = emission(e, &loc)?;
                b.add_mesh(&mesh, &t, m, e, &loc)?;
            }
            ShapeDesc::Quad(QuadShape {
                corner,
                edge1,
                edge2,
                material,
                emission: e,
                transform,
                ..
            }) => {
                let m = lookup(material, &loc)?;
                let (c, e1, e2) = (v3(*corner), v3(*edge1), v3(*edge2));
                if !(e1.cross(e2).length_squared() > 0.0) {
                    return Err(SceneError::new(
                        file,
                        loc,
                        "quad edges are parallel or zero",
                    ));
                }
                let mesh = MeshData {
                    positions: vec![c, c + e1, c + e1 + e2, c + e2],
                    normals: Vec::new(),
                    uvs: vec![
                        Vec2::new(0.0, 0.0),
                        Vec2::new(1.0, 0.0),
                        Vec2::new(1.0, 1.0),
                        Vec2::new(0.0, 1.0),
                    ],
                    indices: vec![[0, 1, 2], [0, 2, 3]],
                };
                let t = build_transform(transform, file, &loc)?;
                let e = emission(e, &loc)?;
                b.add_mesh(&mesh, &t, m, e, &loc)?;
            }
            ShapeDesc::Sphere(SphereShape {
                center,
                radius,
                material,
                emission: e,
                inward,
                ..
            }) => {
                let m = lookup(material, &loc)?;
                if !(*radius > 0.0 && radius.is_finite()) {
                    return Err(SceneError::new(
                        file,
                        format!("{loc}.radius"),
                        format!("radius must be > 0, got {radius}"),
                    ));
                }
                let e = emission(e, &loc)?;
                b.add_sphere(v3(*center), *radius, *inward, m, e, &loc)?;
            }
        }
    }
    for (i, v) in desc.lights.iter().enumerate() {
        let loc = format!("lights[{i}]");
        match &light_desc(file, &loc, v)? {
            LightDesc::Point(PointLight {
                position,
                intensity,
                ..
            }) => b.add_point_light(v3(*position), intensity.rgb(), &loc)?,
        }
    }
    Ok(b)
}
