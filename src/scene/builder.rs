//! [`SceneBuilder`]: what every loader fills in world space, and the validation and building of
//! the [`Scene`] (BVHs, lights, the sky's dome) from it.

use super::emitters::{coplanar_triangle_lights, one_emitter_per_ray};
use super::import::Resolver;
use super::{
    Dome, EMITTER_BVH_THRESHOLD, MAX_COORDINATE, NO_LIGHT, Scene, SceneDefaults, SceneError,
    SceneStats, Sphere, Triangle, ids, primitives,
};
use crate::accel::{Accel, SphereGeom};
use crate::camera::Camera;
use crate::geometry::{Rgb, Transform, Vec2, Vec3};
use crate::light::{Distribution1D, Light};
use crate::material::Material;
use std::path::Path;

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

    /// Refuses a primitive's `material` that is not one of the builder's, and an `emission`
    /// that is not finite and >= 0.
    fn check_surface(
        &self,
        material: u32,
        emission: Option<Rgb>,
        location: &str,
    ) -> Result<(), SceneError> {
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
        Ok(())
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
        self.check_surface(material, emission, location)?;
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
        self.check_surface(material, emission, location)?;
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
