//! Shapes (`obj`, `ply`, `rectangle`, `cube`, `disk`, `sphere`) with their bsdfs and nested
//! area emitters, and point emitters.

use super::{Ctx, Obj, R};
use crate::geometry::{Rgb, Transform, Vec2, Vec3};
use crate::scene::MeshData;
use crate::scene::import::common::{default_lambert, mitsuba_mesh_file, uniform_scale};
use crate::scene::import::mesh::{read_meshes, read_obj, read_ply};
use crate::scene::import::xml::{Node, Props};

/// Triangles of the fan a `disk` is tessellated into.
const DISK_SEGMENTS: usize = 256;

impl Ctx {
    /// Loads every OBJ / PLY file of the scene in parallel (the slow part of big scenes).
    pub(super) fn preload_meshes(&mut self, root: &Node) -> R<()> {
        let mut paths = Vec::new();
        for c in &root.children {
            if let Some(f) = mitsuba_mesh_file(c)
                && let Ok(file) = self.b.resolver().resolve(f, "")
            {
                paths.push(file);
            }
        }
        paths.sort();
        paths.dedup();
        let loaded = read_meshes(paths);
        self.meshes.extend(loaded);
        Ok(())
    }

    pub(super) fn default_bsdf(&mut self) -> u32 {
        // Mitsuba gives shapes without a bsdf a one-sided diffuse bsdf of reflectance 0.5.
        let name = "Mitsuba default (diffuse 0.5)";
        default_lambert(&mut self.b, &mut self.default_bsdf, name, false)
    }

    /// The builder material of a shape: its nested bsdf, its `<ref>`, or the default.
    pub(super) fn shape_material(&mut self, n: &Node, p: &Props) -> R<u32> {
        for c in &n.children {
            if c.attr("name").is_some() {
                continue;
            }
            if c.tag == "bsdf" {
                p.objects("bsdf");
                let m = self.bsdf(c)?;
                if let Some(id) = c.attr("id") {
                    return self.material_index(c, id);
                }
                return Ok(self.b.add_material(m));
            }
            if c.tag == "ref" {
                p.objects("ref");
                let id = c
                    .attr("id")
                    .ok_or_else(|| self.err(c, "<ref> without id"))?;
                return self.material_index(c, id);
            }
        }
        Ok(self.default_bsdf())
    }

    pub(super) fn material_index(&mut self, n: &Node, id: &str) -> R<u32> {
        let mat = match self.ids.get(id) {
            Some(Obj::Bsdf { index: Some(i), .. }) => return Ok(*i),
            Some(Obj::Bsdf { mat, .. }) => mat.clone(),
            Some(Obj::Texture(_)) => {
                return Err(self.err(n, format!("\"{id}\" is a texture, not a bsdf")));
            }
            Some(Obj::Other(t)) => {
                return Err(self.err(n, format!("\"{id}\" is a <{t}>, not a bsdf")));
            }
            None => return Err(self.err(n, format!("unknown id \"{id}\""))),
        };
        let i = self.b.add_material(mat);
        if let Some(Obj::Bsdf { index, .. }) = self.ids.get_mut(id) {
            *index = Some(i);
        }
        Ok(i)
    }

    /// Adds a `<shape>` with its material and emission.
    pub(super) fn shape(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let what = format!("shape \"{ty}\"");
        let mut loc = format!("line {}", n.line);
        let material = self.shape_material(n, &p)?;
        let mut emission = None;
        for e in p.objects("emitter") {
            let ep = Props::new(e);
            match e.attr("type") {
                Some("area") => {
                    let r = match ep.get("radiance") {
                        Some(r) => self.color_of(r)?,
                        None => return Err(self.err(e, "area emitter has no radiance")),
                    };
                    ep.consume("samplingWeight");
                    self.report_unused(&ep, "emitter \"area\"");
                    emission = Some(r);
                }
                Some(other) => {
                    return Err(self.err(
                        e,
                        format!(
                            "emitter \"{other}\" inside a shape is not supported (only \"area\")"
                        ),
                    ));
                }
                None => return Err(self.err(e, "emitter without type")),
            }
        }
        for k in ["medium", "subsurface"] {
            if !p.any_with_tag(k).is_empty() {
                self.warn(n, format!("{what}: <{k}> is not supported and was ignored"));
            }
        }
        let to_world = self.to_world(&p)?;
        let t = Transform::new(to_world)
            .ok_or_else(|| self.err(n, format!("{what}: toWorld is singular")))?;
        let flip = self.boolean(&p, "flipNormals", false)?;
        let mut mesh = match ty {
            "obj" | "ply" => {
                let file = self
                    .string(&p, "filename")?
                    .ok_or_else(|| self.err(n, format!("{what} has no filename")))?;
                let f = self.b.resolver().resolve(&file, &loc)?;
                let path = f.path();
                // Errors in the mesh's data name its file.
                loc = format!("{loc} ({})", path.display());
                // Preloaded meshes are taken (a file used twice is read again).
                let mut mesh = match self.meshes.remove(path) {
                    Some(Ok(m)) => m,
                    Some(Err(e)) => return Err(self.err(n, format!("{}: {e}", path.display()))),
                    None => {
                        let m = if ty == "ply" {
                            read_ply(&f)
                        } else {
                            read_obj(&f)
                        };
                        m.map_err(|e| self.err(n, format!("{}: {e}", path.display())))?
                    }
                };
                let flip_tex = if ty == "obj" {
                    self.boolean(&p, "flipTexCoords", true)?
                } else {
                    false
                };
                // See the module comment: Mitsuba's OBJ default equals our convention.
                if !flip_tex {
                    for uv in &mut mesh.uvs {
                        uv.y = 1.0 - uv.y;
                    }
                }
                let face_normals = self.boolean(&p, "faceNormals", false)?;
                if face_normals {
                    mesh.normals.clear();
                } else if mesh.normals.is_empty() {
                    // Mitsuba generates smooth vertex normals for meshes without them.
                    smooth_normals(&mut mesh);
                }
                if p.has("maxSmoothAngle") {
                    p.consume("maxSmoothAngle");
                    self.warn(
                        n,
                        format!(
                            "{what}: maxSmoothAngle is not supported; the file's normals are used"
                        ),
                    );
                }
                if self.int(&p, "shapeIndex", -1)? >= 0 {
                    return Err(self.err(n, format!("{what}: shapeIndex is not supported")));
                }
                p.consume("collapse");
                p.consume("loadMaterials");
                mesh
            }
            "rectangle" => MeshData {
                positions: vec![
                    Vec3::new(-1.0, -1.0, 0.0),
                    Vec3::new(1.0, -1.0, 0.0),
                    Vec3::new(1.0, 1.0, 0.0),
                    Vec3::new(-1.0, 1.0, 0.0),
                ],
                normals: Vec::new(),
                // Mitsuba's (0,0) (1,0) (1,1) (0,1), with v flipped to our convention.
                uvs: vec![
                    Vec2::new(0.0, 1.0),
                    Vec2::new(1.0, 1.0),
                    Vec2::new(1.0, 0.0),
                    Vec2::new(0.0, 0.0),
                ],
                indices: vec![[0, 1, 2], [2, 3, 0]],
            },
            "cube" => cube(),
            "disk" => {
                self.warn(
                    n,
                    format!("disk tessellated into {DISK_SEGMENTS} triangles"),
                );
                disk()
            }
            "sphere" => {
                let center = match p.get("center") {
                    Some(c) => self.point_of(c)?,
                    None => Vec3::ZERO,
                };
                let radius = self.float(&p, "radius", 1.0)?;
                if !(radius > 0.0) {
                    return Err(self.err(n, format!("sphere radius must be > 0, got {radius}")));
                }
                let scale = uniform_scale(&to_world).ok_or_else(|| {
                    self.err(
                        n,
                        "a sphere under non-uniform scale or shear is not supported",
                    )
                })?;
                self.report_unused(&p, &what);
                return self.b.add_sphere(
                    t.point(center),
                    radius * scale,
                    flip,
                    material,
                    emission,
                    &loc,
                );
            }
            "serialized" => {
                return Err(self.err(
                    n,
                    "shape \"serialized\" is not supported (convert it to PLY or OBJ)",
                ));
            }
            other => {
                return Err(self.err(
                    n,
                    format!("shape \"{other}\" is not supported (obj, ply, rectangle, cube, disk, sphere)"),
                ));
            }
        };
        if flip {
            for tri in &mut mesh.indices {
                tri.swap(1, 2);
            }
            for nn in &mut mesh.normals {
                *nn = -*nn;
            }
        }
        self.report_unused(&p, &what);
        self.b.add_mesh(&mesh, &t, material, emission, &loc)
    }

    /// Adds a top-level `<emitter>` (point lights only).
    pub(super) fn emitter(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        match n.attr("type").unwrap_or("") {
            "point" => {
                let to_world = self.to_world(&p)?;
                let local = match p.get("position") {
                    Some(c) => self.point_of(c)?,
                    None => Vec3::ZERO,
                };
                let pos = to_world.transform_point3(local);
                let intensity = match p.get("intensity") {
                    Some(c) => self.color_of(c)?,
                    None => Rgb::ONE,
                };
                p.consume("samplingWeight");
                self.report_unused(&p, "emitter \"point\"");
                self.b.add_point_light(pos, intensity, &format!("line {}", n.line))
            }
            "area" => Err(self.err(n, "an area emitter must be nested in a <shape>")),
            other => Err(self.err(
                n,
                format!("emitter \"{other}\" is not supported (only \"point\" and area emitters in shapes)"),
            )),
        }
    }
}

/// Area-weighted vertex normals from the faces around each vertex (Mitsuba sums the unit face
/// normals of the triangles sharing a vertex).
fn smooth_normals(mesh: &mut MeshData) {
    let mut n = vec![Vec3::ZERO; mesh.positions.len()];
    for t in &mesh.indices {
        let [a, b, c] = t.map(|k| mesh.positions[k as usize]);
        let f = (b - a).cross(c - a).normalize_or_zero();
        for &k in t {
            n[k as usize] += f;
        }
    }
    for v in &mut n {
        *v = v.normalize_or_zero();
    }
    mesh.normals = n;
}

/// Mitsuba's `cube`: [-1, 1]^3 with outward faces.
fn cube() -> MeshData {
    let mut m = MeshData::default();
    // (normal, u axis, v axis) with u x v = normal, so counter-clockwise seen from outside.
    let faces = [
        (Vec3::X, Vec3::NEG_Z, Vec3::Y),
        (Vec3::NEG_X, Vec3::Z, Vec3::Y),
        (Vec3::Y, Vec3::X, Vec3::NEG_Z),
        (Vec3::NEG_Y, Vec3::X, Vec3::Z),
        (Vec3::Z, Vec3::X, Vec3::Y),
        (Vec3::NEG_Z, Vec3::NEG_X, Vec3::Y),
    ];
    for (nrm, u, v) in faces {
        let base = m.positions.len() as u32;
        for (su, sv) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            m.positions.push(nrm + u * su + v * sv);
            m.uvs.push(Vec2::new(0.5 * (su + 1.0), 0.5 * (sv + 1.0)));
        }
        m.indices.push([base, base + 1, base + 2]);
        m.indices.push([base, base + 2, base + 3]);
    }
    m
}

/// Mitsuba's `disk`: the unit disk in the xy plane facing +z, as a triangle fan.
fn disk() -> MeshData {
    let mut m = MeshData::default();
    m.positions.push(Vec3::ZERO);
    m.uvs.push(Vec2::new(0.5, 0.5));
    for i in 0..DISK_SEGMENTS {
        let a = i as f32 / DISK_SEGMENTS as f32 * std::f32::consts::TAU;
        m.positions.push(Vec3::new(a.cos(), a.sin(), 0.0));
        m.uvs
            .push(Vec2::new(0.5 + 0.5 * a.cos(), 0.5 - 0.5 * a.sin()));
        let k = i as u32 + 1;
        let next = (i as u32 + 1) % DISK_SEGMENTS as u32 + 1;
        m.indices.push([0, k, next]);
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cube_faces_point_outward() {
        let m = cube();
        for t in &m.indices {
            let [a, b, c] = t.map(|k| m.positions[k as usize]);
            let n = (b - a).cross(c - a);
            let center = (a + b + c) / 3.0;
            assert!(n.dot(center) > 0.0);
        }
        let d = disk();
        for t in &d.indices {
            let [a, b, c] = t.map(|k| d.positions[k as usize]);
            assert!((b - a).cross(c - a).z > 0.0);
        }
    }
}
