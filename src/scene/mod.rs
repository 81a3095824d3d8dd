//! The scene model (world-space triangles, spheres, materials, lights, camera); its loaders are
//! in [`import`].
//!
//! Every loader (JSON, pbrt-v3, Mitsuba 0.5) feeds a [`SceneBuilder`]; [`SceneBuilder::build`]
//! validates, builds the BVHs and the light-selection distribution.

pub mod import;

use import::Resolver;
pub(crate) use import::mesh;
pub use import::{json, pbrt};

use crate::accel::{Accel, Prim, SphereGeom};
use crate::camera::Camera;
use crate::geometry::{Ray, Rgb, Transform, Vec2, Vec3, offset_origin};
use crate::light::{Distribution1D, Light};
use crate::material::Material;
use glam::{DVec2, DVec3};
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
    /// No ray meets two emitters (see [`one_emitter_per_ray`]).
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

/// Mesh data in object space, as a loader reads it.
#[derive(Clone, Debug, Default)]
pub struct MeshData {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Vertex normals (empty or one per position).
    pub normals: Vec<Vec3>,
    /// Vertex uvs (empty or one per position).
    pub uvs: Vec<Vec2>,
    /// Triangles, as indices into `positions`.
    pub indices: Vec<[u32; 3]>,
}

/// Collects geometry, materials and lights in world space; `build` makes the [`Scene`], whose
/// `files` are those the builder's `Resolver` handed out.
pub struct SceneBuilder {
    resolver: Resolver,
    camera: Option<Camera>,
    materials: Vec<Material>,
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    uvs: Vec<Vec2>,
    triangles: Vec<Triangle>,
    tri_emission: Vec<Rgb>,
    spheres: Vec<Sphere>,
    sphere_emission: Vec<Rgb>,
    point_lights: Vec<Light>,
    environment: Option<std::sync::Arc<crate::light::Environment>>,
    sun: Option<crate::light::Sun>,
    /// Settings the scene file suggests.
    pub defaults: SceneDefaults,
    warnings: Vec<String>,
}

impl SceneBuilder {
    /// An empty builder for the scene whose files `resolver` resolves.
    pub(crate) fn new(resolver: Resolver) -> Self {
        SceneBuilder {
            resolver,
            camera: None,
            materials: Vec::new(),
            positions: Vec::new(),
            normals: Vec::new(),
            uvs: Vec::new(),
            triangles: Vec::new(),
            tri_emission: Vec::new(),
            spheres: Vec::new(),
            sphere_emission: Vec::new(),
            point_lights: Vec::new(),
            environment: None,
            sun: None,
            defaults: SceneDefaults::default(),
            warnings: Vec::new(),
        }
    }

    /// Records a warning once (identical messages are kept once).
    pub fn warn(&mut self, message: impl Into<String>) {
        let m = message.into();
        if !self.warnings.contains(&m) {
            self.warnings.push(m);
        }
    }

    /// The scene file (for messages).
    pub fn file(&self) -> &Path {
        self.resolver.scene_file()
    }

    /// The resolver through which every file the scene reads is reached.
    pub(crate) fn resolver(&mut self) -> &mut Resolver {
        &mut self.resolver
    }

    /// Sets the camera (the last call wins).
    pub fn set_camera(&mut self, camera: Camera) {
        self.camera = Some(camera);
    }

    /// Adds a material; its index, for primitives.
    pub fn add_material(&mut self, m: Material) -> u32 {
        self.materials.push(m);
        (self.materials.len() - 1) as u32
    }

    /// Materials added so far.
    pub fn material_count(&self) -> usize {
        self.materials.len()
    }

    fn err(&self, location: &str, message: impl Into<String>) -> SceneError {
        SceneError::new(self.file(), location, message)
    }

    /// Adds a mesh transformed to world space. `location` names it in errors.
    ///
    /// Vertices must lie within `MAX_COORDINATE` of the origin.
    pub fn add_mesh(
        &mut self,
        mesh: &MeshData,
        transform: &Transform,
        material: u32,
        emission: Option<Rgb>,
        location: &str,
    ) -> Result<(), SceneError> {
        let nv = mesh.positions.len();
        if let Some(i) = mesh.positions.iter().position(|p| !p.is_finite()) {
            return Err(self.err(
                location,
                format!("vertex {i} is not finite: {:?}", mesh.positions[i]),
            ));
        }
        let has_normals = !mesh.normals.is_empty();
        let has_uvs = !mesh.uvs.is_empty();
        if has_normals && mesh.normals.len() != nv {
            return Err(self.err(
                location,
                format!("{} normals for {} vertices", mesh.normals.len(), nv),
            ));
        }
        if has_uvs && mesh.uvs.len() != nv {
            return Err(self.err(
                location,
                format!("{} uvs for {} vertices", mesh.uvs.len(), nv),
            ));
        }
        if let Some(i) = mesh.normals.iter().position(|n| !n.is_finite()) {
            return Err(self.err(location, format!("normal {i} is not finite")));
        }
        if let Some(i) = mesh.uvs.iter().position(|n| !n.is_finite()) {
            return Err(self.err(location, format!("uv {i} is not finite")));
        }
        if let Some((f, idx)) = mesh
            .indices
            .iter()
            .enumerate()
            .find(|(_, t)| t.iter().any(|&k| k as usize >= nv))
        {
            return Err(self.err(
                location,
                format!(
                    "face {f} has index {:?} out of range for {nv} vertices",
                    idx
                ),
            ));
        }
        if let Some(e) = emission
            && !(e.is_finite() && e.min_element() >= 0.0)
        {
            return Err(self.err(
                location,
                format!("emission must be finite and >= 0, got {e:?}"),
            ));
        }
        if material as usize >= self.materials.len() {
            return Err(self.err(location, "material index out of range"));
        }
        let base = self.positions.len() as u32;
        for (i, &p) in mesh.positions.iter().enumerate() {
            let w = transform.point(p);
            if !w.is_finite() {
                return Err(self.err(location, "transformed vertex is not finite"));
            }
            if !within_world(w) {
                return Err(self.err(location, beyond_world(&format!("vertex {i}"), w)));
            }
            self.positions.push(w);
            self.normals.push(Vec3::ZERO);
            self.uvs.push(Vec2::ZERO);
        }
        if has_normals {
            for (k, &n) in mesh.normals.iter().enumerate() {
                self.normals[base as usize + k] = transform.normal(n).normalize_or_zero();
            }
        }
        if has_uvs {
            for (k, &uv) in mesh.uvs.iter().enumerate() {
                self.uvs[base as usize + k] = uv;
            }
        }
        let emission = emission.filter(|e| *e != Rgb::ZERO);
        for idx in &mesh.indices {
            let v = idx.map(|k| k + base);
            let [a, b, c] = v.map(|k| self.positions[k as usize]);
            let ng = (b - a).cross(c - a);
            if !(ng.length_squared() > 0.0) {
                continue; // degenerate: can never be hit
            }
            let mut flip = false;
            if has_normals {
                let ns = self.normals[v[0] as usize]
                    + self.normals[v[1] as usize]
                    + self.normals[v[2] as usize];
                flip = ns.dot(ng) < 0.0;
            }
            let ng = ng.normalize();
            let ng = if flip { -ng } else { ng };
            // Normals that are the geometric normal to within float noise (1e-5 rad) shade as
            // it does: interpolating and normalising them is left out.
            let flat = |n: Vec3| n.as_dvec3().dot(ng.as_dvec3()) >= 1.0 - 5e-11;
            let curved = has_normals && !v.iter().all(|&k| flat(self.normals[k as usize]));
            self.triangles.push(Triangle {
                v,
                material,
                light: NO_LIGHT,
                has_normals: curved,
                has_uvs: has_uvs && self.materials[material as usize].uses_uv(),
                ng,
            });
            self.tri_emission.push(emission.unwrap_or(Rgb::ZERO));
        }
        Ok(())
    }

    /// Adds a sphere; `location` names it in errors. An `emission` makes it an area light.
    pub fn add_sphere(
        &mut self,
        center: Vec3,
        radius: f32,
        inward: bool,
        material: u32,
        emission: Option<Rgb>,
        location: &str,
    ) -> Result<(), SceneError> {
        if !center.is_finite() {
            return Err(self.err(location, "sphere center is not finite"));
        }
        if !(radius > 0.0 && radius.is_finite()) {
            return Err(self.err(location, format!("sphere radius must be > 0, got {radius}")));
        }
        if !within_world(center.abs() + radius) {
            return Err(self.err(location, beyond_world("the sphere", center.abs() + radius)));
        }
        if let Some(e) = emission
            && !(e.is_finite() && e.min_element() >= 0.0)
        {
            return Err(self.err(
                location,
                format!("emission must be finite and >= 0, got {e:?}"),
            ));
        }
        if material as usize >= self.materials.len() {
            return Err(self.err(location, "material index out of range"));
        }
        self.spheres.push(Sphere {
            center,
            radius,
            inward,
            material,
            light: NO_LIGHT,
        });
        self.sphere_emission.push(emission.unwrap_or(Rgb::ZERO));
        Ok(())
    }

    /// Adds an isotropic point light of radiant `intensity`.
    pub fn add_point_light(
        &mut self,
        position: Vec3,
        intensity: Rgb,
        location: &str,
    ) -> Result<(), SceneError> {
        if !position.is_finite() {
            return Err(self.err(location, "point light position is not finite"));
        }
        if !within_world(position) {
            return Err(self.err(location, beyond_world("the point light", position)));
        }
        if !(intensity.is_finite() && intensity.min_element() >= 0.0) {
            return Err(self.err(location, "intensity must be finite and >= 0"));
        }
        self.point_lights.push(Light::Point {
            position,
            intensity,
        });
        Ok(())
    }

    /// Adds a spot light at `position` pointing along `axis` (Mitsuba 3's `spot`): `intensity`
    /// on the axis, full within `beam` degrees, falling off linearly to 0 at `cutoff` degrees.
    pub fn add_spot_light(
        &mut self,
        position: Vec3,
        axis: Vec3,
        intensity: Rgb,
        (beam, cutoff): (f32, f32),
        location: &str,
    ) -> Result<(), SceneError> {
        if !position.is_finite() || !within_world(position) {
            return Err(self.err(location, beyond_world("the spot light", position)));
        }
        let axis = axis.normalize_or_zero();
        if axis == Vec3::ZERO || !axis.is_finite() {
            return Err(self.err(location, "the spot light has no direction"));
        }
        if !(intensity.is_finite() && intensity.min_element() >= 0.0) {
            return Err(self.err(location, "intensity must be finite and >= 0"));
        }
        if !(cutoff > 0.0 && cutoff <= 90.0 && beam > 0.0 && beam <= cutoff) {
            return Err(self.err(
                location,
                format!("the spot's cutoff {cutoff} and beam {beam} must be 0 < beam <= cutoff <= 90 degrees"),
            ));
        }
        let cutoff = cutoff.to_radians();
        self.point_lights.push(Light::Spot {
            position,
            frame: crate::geometry::Frame::from_normal(axis),
            intensity,
            beam: beam.to_radians().min(cutoff),
            cutoff,
            cos_cutoff: cutoff.cos(),
        });
        Ok(())
    }

    /// Sets the environment (at most one: the last call wins).
    pub fn set_environment(&mut self, env: crate::light::Environment) {
        self.environment = Some(std::sync::Arc::new(env));
    }

    /// Adds a distant sun (at most one: a second is an error).
    pub fn add_sun(&mut self, sun: crate::light::Sun, location: &str) -> Result<(), SceneError> {
        if self.sun.is_some() {
            return Err(self.err(location, "more than one directional light is not supported"));
        }
        if !(sun.radiance.is_finite() && sun.radiance.min_element() >= 0.0) {
            return Err(self.err(location, "irradiance must be finite and >= 0"));
        }
        self.sun = Some(sun);
        Ok(())
    }

    /// Validates and builds the scene: lights, the light-selection distribution and the BVHs.
    pub fn build(mut self) -> Result<Scene, SceneError> {
        let camera = self
            .camera
            .take()
            .ok_or_else(|| self.err("camera", "the scene has no camera"))?;
        let mut lights = Vec::new();
        let mut area_lights = Vec::new();
        let mut emit_tris = Vec::new();
        let mut emit_tri_ids = Vec::new();
        let mut emit_spheres = Vec::new();
        let mut emit_sphere_ids = Vec::new();
        for (i, tri) in self.triangles.iter_mut().enumerate() {
            let e = self.tri_emission[i];
            if e == Rgb::ZERO {
                continue;
            }
            let [a, b, c] = tri.v.map(|k| self.positions[k as usize]);
            if let Some(l) = Light::triangle(a, b, c, tri.ng, e) {
                tri.light = lights.len() as u32;
                area_lights.push(tri.light);
                emit_tris.push([a, b, c]);
                emit_tri_ids.push(tri.light);
                lights.push(l);
            }
        }
        for (i, s) in self.spheres.iter_mut().enumerate() {
            let e = self.sphere_emission[i];
            if e == Rgb::ZERO {
                continue;
            }
            s.light = lights.len() as u32;
            area_lights.push(s.light);
            emit_spheres.push(SphereGeom {
                center: s.center,
                radius: s.radius,
            });
            emit_sphere_ids.push(s.light);
            lights.push(Light::Sphere {
                center: s.center,
                radius: s.radius,
                inward: s.inward,
                radiance: e,
            });
        }
        lights.append(&mut self.point_lights);
        let dome = self.dome(&camera, lights.len() as u32).map(|(d, light)| {
            lights.push(light);
            d
        });
        let powers: Vec<f32> = lights.iter().map(|l| l.power()).collect();
        let light_select = Distribution1D::new(&powers);

        let (tri_geom, sphere_geom) = primitives(&self.positions, &self.triangles, &self.spheres);
        // The builder (obvhs) asserts what it assumes of its input: whatever input passed the
        // checks above and still trips it is refused, not a crash of the coordinator.
        let build = |what: &str, f: &dyn Fn() -> Accel| {
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|p| {
                let why = p
                    .downcast_ref::<String>()
                    .map(String::as_str)
                    .or_else(|| p.downcast_ref::<&str>().copied())
                    .unwrap_or("a panic");
                self.err(
                    "shapes",
                    format!("the {what} BVH could not be built: {why}"),
                )
            })
        };
        let accel = build("scene's", &|| {
            Accel::build(&tri_geom, &ids(&tri_geom), &sphere_geom, &ids(&sphere_geom))
        })?;
        let emitter_accel = if area_lights.len() > EMITTER_BVH_THRESHOLD {
            Some(build("emitters'", &|| {
                Accel::build(&emit_tris, &emit_tri_ids, &emit_spheres, &emit_sphere_ids)
            })?)
        } else {
            None
        };
        let coplanar = coplanar_triangle_lights(&lights, &area_lights);
        // The dome stands behind every other emitter.
        let emitters_occlude = !coplanar || (dome.is_some() && !area_lights.is_empty());
        let one_emitter_per_ray = if dome.is_some() {
            area_lights.is_empty()
        } else {
            one_emitter_per_ray(&lights, &area_lights, coplanar)
        };
        let stats = SceneStats {
            triangles: self.triangles.len(),
            spheres: self.spheres.len(),
            lights: lights.len(),
            bvh_build_seconds: accel.stats.seconds,
        };
        Ok(Scene {
            camera,
            materials: self.materials,
            positions: self.positions,
            normals: self.normals,
            uvs: self.uvs,
            triangles: self.triangles,
            spheres: self.spheres,
            lights,
            light_select,
            defaults: self.defaults,
            stats,
            warnings: self.warnings,
            files: self.resolver.files(),
            accel,
            emitter_accel,
            area_lights,
            emitters_occlude,
            one_emitter_per_ray,
            dome,
        })
    }

    /// The dome of the scene's sky, if it has one, around its primitives and `camera`, with its
    /// light (index `light`) and a black material.
    fn dome(&mut self, camera: &Camera, light: u32) -> Option<(Dome, Light)> {
        if self.environment.is_none() && self.sun.is_none() {
            return None;
        }
        let (lo, hi) = bounds_of(&self.positions, &self.spheres);
        let (lo, hi) = (lo.min(camera.position), hi.max(camera.position));
        let center = 0.5 * (lo + hi);
        let r = (0.5 * (hi - lo).length()).max(1e-3 * center.length().max(1.0));
        let env = self.environment.take();
        let sun = self.sun.take();
        // Light sampling splits between sun and environment by their irradiance.
        let sun_prob = match (&env, &sun) {
            (Some(e), Some(s)) => {
                let (a, b) = (s.irradiance(), crate::geometry::PI * e.mean_luminance());
                if a + b > 0.0 {
                    (a / (a + b)).clamp(0.05, 0.95)
                } else {
                    0.5
                }
            }
            _ => 0.0,
        };
        let material = self.add_material(Material::new(
            "the sky's dome (black)",
            crate::material::MaterialKind::Lambert {
                albedo: crate::material::Texture::Constant(Rgb::ZERO),
            },
            true,
        ));
        let radius = r * crate::light::DOME_MARGIN;
        let sky = crate::light::Sky { env, sun, sun_prob };
        Some((
            Dome {
                center,
                radius,
                light,
                material,
            },
            Light::Dome {
                center,
                radius,
                sky: std::sync::Arc::new(sky),
            },
        ))
    }
}

/// The bounds of triangle vertices and spheres (a point at the origin when there are none).
fn bounds_of(positions: &[Vec3], spheres: &[Sphere]) -> (Vec3, Vec3) {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for p in positions {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    for s in spheres {
        lo = lo.min(s.center - s.radius);
        hi = hi.max(s.center + s.radius);
    }
    if lo.x > hi.x {
        return (Vec3::ZERO, Vec3::ZERO);
    }
    (lo, hi)
}

/// The most coplanar triangle lights whose interiors are checked pair by pair for
/// [`one_emitter_per_ray`]; past it the light-sampling density sums over the lights a ray meets.
const ONE_EMITTER_CHECK_MAX: usize = 64;

/// True when no ray meets two emitters (except on a set of measure zero): at most one area light,
/// or triangles in one plane (`coplanar`, from [`coplanar_triangle_lights`]) no two of which
/// overlap. A ray crosses the plane once, so it meets at most one of them.
fn one_emitter_per_ray(lights: &[Light], area: &[u32], coplanar: bool) -> bool {
    if area.len() <= 1 {
        return true;
    }
    if !coplanar || area.len() > ONE_EMITTER_CHECK_MAX {
        return false;
    }
    let corners: Vec<[DVec3; 3]> = area
        .iter()
        .filter_map(|&l| match &lights[l as usize] {
            Light::Triangle { p0, e1, e2, .. } => {
                let p0 = p0.as_dvec3();
                Some([p0, p0 + e1.as_dvec3(), p0 + e2.as_dvec3()])
            }
            _ => None,
        })
        .collect();
    if corners.len() != area.len() {
        return false;
    }
    // The plane's axes, from the first triangle (the rest lie in its plane).
    let [a, b, c] = corners[0];
    let (s, t) = (b - a).cross(c - a).normalize().any_orthonormal_pair();
    let flat: Vec<[DVec2; 3]> = corners
        .iter()
        .map(|tri| tri.map(|p| DVec2::new(p.dot(s), p.dot(t))))
        .collect();
    let scale = flat
        .iter()
        .flatten()
        .fold(0.0f64, |m, p| m.max(p.abs().max_element()));
    for (i, a) in flat.iter().enumerate() {
        if flat[i + 1..].iter().any(|b| interiors_overlap(a, b, scale)) {
            return false;
        }
    }
    true
}

/// Separating-axis test of two triangles in a plane: true unless an edge normal of either
/// separates them (touching along an edge or at a corner, to within rounding, is separate).
/// `scale` is the largest coordinate.
fn interiors_overlap(a: &[DVec2; 3], b: &[DVec2; 3], scale: f64) -> bool {
    let range = |tri: &[DVec2; 3], axis: DVec2| {
        let d = tri.map(|p| p.dot(axis));
        (d[0].min(d[1]).min(d[2]), d[0].max(d[1]).max(d[2]))
    };
    for tri in [a, b] {
        for k in 0..3 {
            let e = tri[(k + 1) % 3] - tri[k];
            let axis = e.perp();
            let tol = 1e-10 * axis.length() * scale;
            let (a_lo, a_hi) = range(a, axis);
            let (b_lo, b_hi) = range(b, axis);
            if a_hi <= b_lo + tol || b_hi <= a_lo + tol {
                return false;
            }
        }
    }
    true
}

/// True when there is at most one area light, or all are triangles in one plane.
fn coplanar_triangle_lights(lights: &[Light], area: &[u32]) -> bool {
    let mut plane: Option<(Vec3, Vec3)> = None;
    for &l in area {
        let Light::Triangle { p0, e1, e2, .. } = &lights[l as usize] else {
            return area.len() <= 1;
        };
        let n = e1.cross(*e2).normalize();
        match plane {
            None => plane = Some((*p0, n)),
            Some((q, m)) => {
                let scale = 1e-5 * (1.0 + q.abs().max_element() + p0.abs().max_element());
                let pts = [*p0, *p0 + *e1, *p0 + *e2];
                if n.dot(m).abs() < 1.0 - 1e-6 || pts.iter().any(|p| (*p - q).dot(m).abs() > scale)
                {
                    return false;
                }
            }
        }
    }
    true
}

/// The largest magnitude of a world-space coordinate. Beyond it a float has less precision than
/// a ray test needs (at 1e12 its step is 65536 units), and the BVH builder's surface areas
/// (squares of extents) overflow to infinity, which it does not survive.
pub const MAX_COORDINATE: f32 = 1e12;

/// Whether every coordinate of `p` is within `MAX_COORDINATE` of the origin.
fn within_world(p: Vec3) -> bool {
    p.abs().max_element() <= MAX_COORDINATE
}

/// The error for `what` reaching `p`, beyond `MAX_COORDINATE`.
fn beyond_world(what: &str, p: Vec3) -> String {
    format!(
        "{what} reaches {:?}, beyond the largest world coordinate {MAX_COORDINATE:e} (no ray \
         test keeps its precision there; scale the scene down)",
        p.to_array()
    )
}
