//! The scene model (world-space triangles, spheres, materials, lights, camera); its loaders are
//! in [`import`].
//!
//! Every loader (JSON, pbrt-v3, Mitsuba 0.5) feeds a [`SceneBuilder`]; [`SceneBuilder::build`]
//! validates, builds the BVHs and the light-selection distribution.

mod builder;
mod emitters;
pub mod import;

pub use builder::{MeshData, SceneBuilder};

pub(crate) use import::mesh;
pub use import::{json, pbrt};

use crate::accel::{Accel, Prim, SphereGeom};
use crate::camera::Camera;
use crate::geometry::{Ray, Vec2, Vec3, offset_origin};
use crate::light::{Distribution1D, Light};
use crate::material::Material;
use std::path::{Path, PathBuf};

/// The `light` index of a primitive that does not emit.
pub const NO_LIGHT: u32 = u32::MAX;

/// A load error that names the file and the place in it (JSON path, line, or element).
#[derive(Debug, thiserror::Error)]
#[error("{file}: {location}: {message}")]
pub struct SceneError {
    /// The scene file.
    pub file: PathBuf,
    /// Where in the file: a JSON path, a line, or an element.
    pub location: String,
    /// What is wrong.
    pub message: String,
}

impl SceneError {
    /// An error at `location` in `file`.
    pub fn new(file: &Path, location: impl Into<String>, message: impl Into<String>) -> Self {
        SceneError {
            file: file.to_path_buf(),
            location: location.into(),
            message: message.into(),
        }
    }
}

/// Settings a scene file may suggest; command-line flags override them.
#[derive(Clone, Debug, Default)]
pub struct SceneDefaults {
    /// Suggested samples per pixel.
    pub spp: Option<u32>,
    /// Suggested maximum path depth in bounces.
    pub max_depth: Option<u32>,
}

/// A world-space triangle: three indices into the scene's vertex arrays, its material and light.
#[derive(Clone, Copy, Debug)]
pub struct Triangle {
    /// Indices into [`Scene::positions`] (and `normals`, `uvs` when present).
    pub v: [u32; 3],
    /// Index into [`Scene::materials`].
    pub material: u32,
    /// Index into [`Scene::lights`], or [`NO_LIGHT`].
    pub light: u32,
    /// Vertex normals are present for this triangle's mesh and some differ from the geometric
    /// normal (else hits take the geometric normal as the shading one: a flat mesh's normals
    /// change nothing but the hit's cost).
    pub has_normals: bool,
    /// Vertex uvs are present for this triangle's mesh and its material reads them (a texture).
    pub has_uvs: bool,
    /// Unit geometric normal, (p1 - p0) x (p2 - p0) normalised, turned to agree with the vertex
    /// normals where they exist (as pbrt does): made once here, not per hit.
    pub ng: Vec3,
}

/// A world-space sphere.
#[derive(Clone, Copy, Debug)]
pub struct Sphere {
    /// Centre in world space.
    pub center: Vec3,
    /// Radius (> 0).
    pub radius: f32,
    /// Normals point into the sphere (an enclosure seen from inside).
    pub inward: bool,
    /// Index into [`Scene::materials`].
    pub material: u32,
    /// Index into [`Scene::lights`], or [`NO_LIGHT`].
    pub light: u32,
}

/// A ray-surface intersection with everything shading needs.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceHit {
    /// The hit point in world space.
    pub p: Vec3,
    /// Distance along the ray (in units of the ray direction's length).
    pub t: f32,
    /// Geometric normal (unit); the side it points to is the emitting side of area lights.
    pub ng: Vec3,
    /// Shading normal (unit), on the same side as `ng`.
    pub ns: Vec3,
    /// Surface parameterisation (mesh uvs, barycentrics without them, or spherical coordinates;
    /// zero on a sphere whose material reads no texture).
    pub uv: Vec2,
    /// Index into [`Scene::materials`].
    pub material: u32,
    /// Light index, or `NO_LIGHT`.
    pub light: u32,
    /// The primitive hit.
    pub prim: Prim,
}

impl SurfaceHit {
    /// True when the surface is an area light.
    pub fn is_emitter(&self) -> bool {
        self.light != NO_LIGHT
    }
}

/// Counters a loader can report.
#[derive(Clone, Debug, Default)]
pub struct SceneStats {
    /// Triangles in the scene.
    pub triangles: usize,
    /// Spheres in the scene.
    pub spheres: usize,
    /// Lights (area and point).
    pub lights: usize,
    /// Seconds spent building the BVHs.
    pub bvh_build_seconds: f64,
}

/// A loaded, validated scene: world-space geometry with its BVHs, materials, lights and camera.
/// Built by [`SceneBuilder::build`]; read-only while rendering.
pub struct Scene {
    /// The camera.
    pub camera: Camera,
    /// Materials, indexed by the primitives' `material`.
    pub materials: Vec<Material>,
    /// Triangle vertex positions (world space).
    pub positions: Vec<Vec3>,
    /// Triangle vertex normals (world space), one per position (zero where a mesh has none).
    pub normals: Vec<Vec3>,
    /// Triangle vertex uvs, one per position (zero where a mesh has none).
    pub uvs: Vec<Vec2>,
    /// Every triangle of every mesh.
    pub triangles: Vec<Triangle>,
    /// Every sphere.
    pub spheres: Vec<Sphere>,
    /// Area lights then point lights, indexed by the primitives' `light`.
    pub lights: Vec<Light>,
    /// Light selection proportional to power; None when the scene has no light.
    pub light_select: Option<Distribution1D>,
    /// Settings the scene file suggests.
    pub defaults: SceneDefaults,
    /// Load counters.
    pub stats: SceneStats,
    /// What the loader could not represent exactly (each reported once, with its location).
    pub warnings: Vec<String>,
    /// Every file besides the scene file that the loader read (meshes, textures, includes),
    /// canonical paths inside the scene's folder, as its `Resolver` handed them out: with the
    /// scene file, a complete bundle.
    pub files: Vec<PathBuf>,
    accel: Accel,
    /// BVH over the emitting primitives only, for summing light pdfs along a ray.
    emitter_accel: Option<Accel>,
    /// Indices of the area lights (scanned directly when there are few).
    area_lights: Vec<u32>,
    emitters_occlude: bool,
    /// No ray meets two emitters (see [`emitters::one_emitter_per_ray`]).
    one_emitter_per_ray: bool,
    /// The dome that carries the sky's light, outside every primitive (`Light::Dome`).
    dome: Option<Dome>,
}

/// The sphere a scene's sky shines in from: a ray that leaves the scene hits its inside.
#[derive(Clone, Copy, Debug)]
struct Dome {
    center: Vec3,
    radius: f32,
    /// Its light (`Light::Dome`).
    light: u32,
    /// Its material: black, so that a path that reaches the sky ends there.
    material: u32,
}

/// The world-space geometry of the triangles and spheres, in the scene's order.
fn primitives(
    positions: &[Vec3],
    triangles: &[Triangle],
    spheres: &[Sphere],
) -> (Vec<[Vec3; 3]>, Vec<SphereGeom>) {
    let tris = triangles
        .iter()
        .map(|t| t.v.map(|k| positions[k as usize]))
        .collect();
    let spheres = spheres
        .iter()
        .map(|s| SphereGeom {
            center: s.center,
            radius: s.radius,
        })
        .collect();
    (tris, spheres)
}

/// Indices 0 .. n of a primitive list.
fn ids<T>(list: &[T]) -> Vec<u32> {
    (0..list.len() as u32).collect()
}

/// Above this many area lights the light-pdf sum of a direction uses the emitter BVH.
const EMITTER_BVH_THRESHOLD: usize = 8;

/// Values of a scene file's parameters (Mitsuba's `$name`), by name: given with
/// `--define name=value` or a job's `defines`, they win over the file's `<default>`s.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(transparent)]
pub struct SceneParams(std::collections::BTreeMap<String, String>);

impl SceneParams {
    /// Parameters of the given values.
    pub fn new(values: std::collections::BTreeMap<String, String>) -> SceneParams {
        SceneParams(values)
    }

    /// The values by name.
    pub fn values(&self) -> &std::collections::BTreeMap<String, String> {
        &self.0
    }

    /// Whether no parameter is given.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

impl Scene {
    /// Loads a scene file, choosing the loader by extension (and the pbrt dialect by contents);
    /// see `import::load`.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        import::load(path, &SceneParams::default())
    }

    /// `load` with values for the file's parameters (only Mitsuba 2/3 files have parameters).
    pub fn load_with(path: &Path, params: &SceneParams) -> Result<Scene, SceneError> {
        import::load(path, params)
    }

    /// The closest surface hit along `ray`, if any: a primitive, or where the ray leaves
    /// through the dome when the scene has a sky.
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<SurfaceHit> {
        match self.accel.intersect(ray) {
            Some(h) => Some(self.surface_hit(ray, h.prim, h.t, h.bary)),
            None => self.dome_hit(ray),
        }
    }

    /// Where `ray` (from inside) leaves through the dome.
    fn dome_hit(&self, ray: &Ray) -> Option<SurfaceHit> {
        let d = self.dome.as_ref()?;
        let len = ray.d.length();
        let t = crate::light::dome_exit(d.center, d.radius, ray.o, ray.d / len)? / len;
        let n = (d.center - ray.at(t)).normalize();
        Some(SurfaceHit {
            p: d.center - n * d.radius,
            t,
            ng: n,
            ns: n,
            uv: Vec2::ZERO,
            material: d.material,
            light: d.light,
            prim: Prim::Sphere(u32::MAX),
        })
    }

    /// The sphere around the scene the sky shines in from, if the scene has a sky: (centre,
    /// radius).
    pub fn dome(&self) -> Option<(Vec3, f32)> {
        self.dome.map(|d| (d.center, d.radius))
    }

    fn surface_hit(&self, ray: &Ray, prim: Prim, t: f32, bary: Vec2) -> SurfaceHit {
        match prim {
            Prim::Triangle(i) => {
                let tri = &self.triangles[i as usize];
                let [a, b, c] = tri.v.map(|k| k as usize);
                let (p0, p1, p2) = (self.positions[a], self.positions[b], self.positions[c]);
                let (b1, b2) = (bary.x, bary.y);
                let b0 = 1.0 - b1 - b2;
                let p = p0 * b0 + p1 * b1 + p2 * b2;
                let ng = tri.ng;
                let mut ns = ng;
                if tri.has_normals {
                    let n = self.normals[a] * b0 + self.normals[b] * b1 + self.normals[c] * b2;
                    let n = n.normalize_or_zero();
                    if n != Vec3::ZERO {
                        ns = if n.dot(ng) < 0.0 { -n } else { n };
                    }
                }
                let uv = if tri.has_uvs {
                    self.uvs[a] * b0 + self.uvs[b] * b1 + self.uvs[c] * b2
                } else {
                    Vec2::new(b1, b2)
                };
                SurfaceHit {
                    p,
                    t,
                    ng,
                    ns,
                    uv,
                    material: tri.material,
                    light: tri.light,
                    prim,
                }
            }
            Prim::Sphere(i) => {
                let s = &self.spheres[i as usize];
                let p = ray.at(t);
                let mut n = (p - s.center).normalize();
                // Re-project onto the surface to remove the intersection's error.
                let p = s.center + n * s.radius;
                // Spherical coordinates cost an atan2 and an acos: only textures read them.
                let uv = if self.materials[s.material as usize].uses_uv() {
                    Vec2::new(
                        0.5 + n.z.atan2(n.x) * crate::geometry::INV_2PI,
                        n.y.clamp(-1.0, 1.0).acos() * crate::geometry::INV_PI,
                    )
                } else {
                    Vec2::ZERO
                };
                if s.inward {
                    n = -n;
                }
                SurfaceHit {
                    p,
                    t,
                    ng: n,
                    ns: n,
                    uv,
                    material: s.material,
                    light: s.light,
                    prim,
                }
            }
        }
    }

    /// True when something blocks the open segment from `from` to `to` (world points), with the
    /// origin lifted off the surface of normal `n_from` and the end pulled back from `to`'s
    /// surface (normal `n_to`, zero for a point light).
    #[inline]
    pub fn occluded(&self, from: Vec3, n_from: Vec3, to: Vec3, n_to: Vec3) -> bool {
        Ray::between(from, n_from, to, n_to).is_some_and(|ray| self.accel.occluded(&ray))
    }

    /// Ray leaving surface point `p` (geometric normal `ng`) in direction `d`.
    #[inline]
    pub fn spawn_ray(p: Vec3, ng: Vec3, d: Vec3) -> Ray {
        Ray::new(offset_origin(p, ng, d), d)
    }

    /// The BVH over all primitives.
    pub fn accel(&self) -> &Accel {
        &self.accel
    }

    /// Builds the acceleration structure again, flat (every primitive tested) or a BVH, for
    /// benchmarks that compare the two ([`Accel::build`] chooses by the primitive count).
    pub fn rebuild_accel(&mut self, flat: bool) {
        let (tris, spheres) = primitives(&self.positions, &self.triangles, &self.spheres);
        self.accel = Accel::build_with(&tris, &ids(&tris), &spheres, &ids(&spheres), flat);
    }

    /// Probability of selecting light `l`.
    #[inline]
    pub fn light_pmf(&self, l: u32) -> f32 {
        match &self.light_select {
            Some(d) => d.pmf(l as usize),
            None => 0.0,
        }
    }

    /// Chooses a light proportionally to power: (index, probability).
    #[inline]
    pub fn sample_light(&self, u: f32) -> Option<(u32, f32)> {
        let d = self.light_select.as_ref()?;
        let (i, p) = d.sample(u);
        if p > 0.0 { Some((i as u32, p)) } else { None }
    }

    /// Solid-angle density with which light sampling (select by power, then sample the light)
    /// produces direction `wi` from `p`: the sum over every light the ray meets ("Demystifying multiple importance sampling").
    pub fn light_pdf_dir(&self, p: Vec3, wi: Vec3) -> f32 {
        let Some(sel) = &self.light_select else {
            return 0.0;
        };
        let mut sum = 0.0f32;
        match &self.emitter_accel {
            None => {
                for &l in &self.area_lights {
                    let pmf = sel.pmf(l as usize);
                    if pmf > 0.0 {
                        sum += pmf * self.lights[l as usize].pdf_li(p, wi);
                    }
                }
            }
            Some(acc) => {
                acc.for_each_candidate(&Ray::new(p, wi), |prim| {
                    let l = match prim {
                        Prim::Triangle(l) | Prim::Sphere(l) => l,
                    };
                    let pmf = sel.pmf(l as usize);
                    if pmf > 0.0 {
                        sum += pmf * self.lights[l as usize].pdf_li(p, wi);
                    }
                });
            }
        }
        // Every ray leaves through the dome.
        if let Some(d) = &self.dome {
            let pmf = sel.pmf(d.light as usize);
            if pmf > 0.0 {
                sum += pmf * self.lights[d.light as usize].pdf_li(p, wi);
            }
        }
        sum
    }

    /// [`Scene::light_pdf_dir`] of a direction that light sampling produced by choosing a light
    /// with probability `pmf` and sampling it with solid-angle density `pdf`. Where no ray meets
    /// two emitters the sum over the lights the ray meets has that one term: no light is
    /// intersected.
    #[inline]
    pub fn light_pdf_sampled(&self, p: Vec3, wi: Vec3, pmf: f32, pdf: f32) -> f32 {
        if self.one_emitter_per_ray {
            pmf * pdf
        } else {
            self.light_pdf_dir(p, wi)
        }
    }

    /// [`Scene::light_pdf_dir`] of a direction whose ray from `p` reaches light `l` first. Where no
    /// ray meets two emitters only `l`'s term is computed.
    #[inline]
    pub fn light_pdf_hit(&self, p: Vec3, wi: Vec3, l: u32) -> f32 {
        if self.one_emitter_per_ray {
            self.light_pmf(l) * self.lights[l as usize].pdf_li(p, wi)
        } else {
            self.light_pdf_dir(p, wi)
        }
    }

    /// True when no ray meets two emitters, except on a set of rays of measure zero: at most one
    /// area light, or triangles in one plane whose interiors do not overlap.
    pub fn one_emitter_per_ray(&self) -> bool {
        self.one_emitter_per_ray
    }

    /// False when no emitter can stand between a point and another emitter (at most one area
    /// light, or all area lights are coplanar triangles): an occluded light sample then has no
    /// emitted radiance to find.
    #[inline]
    pub fn emitters_may_occlude_each_other(&self) -> bool {
        self.emitters_occlude
    }

    /// Axis-aligned bounds of all geometry (min, max).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for t in &self.triangles {
            for &v in &t.v {
                lo = lo.min(self.positions[v as usize]);
                hi = hi.max(self.positions[v as usize]);
            }
        }
        for s in &self.spheres {
            lo = lo.min(s.center - Vec3::splat(s.radius));
            hi = hi.max(s.center + Vec3::splat(s.radius));
        }
        (lo, hi)
    }
}

/// The largest magnitude of a world-space coordinate. Beyond it a float has less precision than
/// a ray test needs (at 1e12 its step is 65536 units), and the BVH builder's surface areas
/// (squares of extents) overflow to infinity, which it does not survive.
pub const MAX_COORDINATE: f32 = 1e12;
