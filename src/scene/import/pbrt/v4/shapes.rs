//! pbrt-v4's shapes: those pbrt-v3 has (`trianglemesh`, `plymesh`, `sphere`), `plymesh` files
//! gzipped (`.ply.gz`), `bilinearmesh` (each patch as two triangles), and `disk` and `cylinder`
//! tessellated; area lights with a `power` scaled to the shape's area; `Attribute "shape"`
//! defaults.

use super::super::lexer::Loc;
use super::super::params::ParamSet;
use super::super::shapes::{PolygonMesh, ShapeCall};
use super::super::{Parser, R};
use crate::geometry::{Mat4, Transform, Vec2, Vec3};
use crate::scene::MeshData;
use crate::scene::import::common::uniform_scale;
use crate::scene::import::mesh::read_ply_gz;
use std::f32::consts::TAU;

/// Segments of a full circle of a tessellated `disk` or `cylinder` (as our Mitsuba importer).
const SEGMENTS: usize = 256;

/// The area of `mesh` placed by `t`.
fn world_area(mesh: &MeshData, t: &Transform) -> f32 {
    mesh.indices
        .iter()
        .map(|tri| {
            let [a, b, c] = tri.map(|k| t.point(mesh.positions[k as usize]));
            0.5 * (b - a).cross(c - a).length()
        })
        .sum()
}

/// pbrt-v4's `disk` (`height`, `radius`, `innerradius`, `phimax`) facing +z, with its normal
/// as vertex normals (a quadric's normal follows the normal transform, and ReverseOrientation
/// alone flips it).
fn disk(height: f32, radius: f32, inner: f32, phi_max: f32) -> MeshData {
    let mut m = MeshData::default();
    let segments = ((SEGMENTS as f32 * phi_max / TAU).ceil() as usize).max(1);
    for i in 0..=segments {
        let t = i as f32 / segments as f32;
        let (s, c) = (t * phi_max).sin_cos();
        for (r, v) in [(radius, 0.0), (inner, 1.0)] {
            m.positions.push(Vec3::new(r * c, r * s, height));
            m.normals.push(Vec3::Z);
            // pbrt-v4's disk: u = phi / phimax, v = (radius - r) / (radius - innerradius).
            m.uvs.push(Vec2::new(t, v));
        }
    }
    for i in 0..segments as u32 {
        let (a, b, c, d) = (2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3);
        m.indices.push([a, c, d]);
        if inner > 0.0 {
            m.indices.push([a, d, b]);
        }
    }
    m
}

/// pbrt-v4's open `cylinder` (`radius`, `zmin`, `zmax`, `phimax`) about z, normals outward.
fn cylinder(radius: f32, zmin: f32, zmax: f32, phi_max: f32) -> MeshData {
    let mut m = MeshData::default();
    let segments = ((SEGMENTS as f32 * phi_max / TAU).ceil() as usize).max(1);
    for i in 0..=segments {
        let t = i as f32 / segments as f32;
        let (s, c) = (t * phi_max).sin_cos();
        for (z, v) in [(zmin, 0.0), (zmax, 1.0)] {
            m.positions.push(Vec3::new(radius * c, radius * s, z));
            m.normals.push(Vec3::new(c, s, 0.0));
            m.uvs.push(Vec2::new(t, v));
        }
    }
    for i in 0..segments as u32 {
        let (a, b, c, d) = (2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3);
        m.indices.push([a, c, d]);
        m.indices.push([a, d, b]);
    }
    m
}

impl Parser {
    /// `Shape "type" params` of pbrt-v4: added now, or recorded for an object being defined.
    pub(super) fn v4_shape(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("Shape")?;
        let params = self.params()?;
        let params = self.with_attributes("shape", params);
        if !self.in_world {
            return Err(self.err(loc, "Shape outside WorldBegin"));
        }
        let Some(call) = self.shape_call(ty, params, loc, "pbrt-v4") else {
            return Ok(());
        };
        let emits = self.g.area.is_some();
        self.v4_emit_shape(&call, Mat4::IDENTITY, emits)
    }

    /// `ObjectInstance` of pbrt-v4 (its shapes are pbrt-v4's).
    pub(super) fn v4_object_instance(&mut self, loc: Loc) -> R<()> {
        self.world_only("ObjectInstance", loc)?;
        let n = self.arg_str("ObjectInstance")?;
        if self.defining.is_some() {
            return Err(self.err(loc, "ObjectInstance inside ObjectBegin is not supported"));
        }
        let Some(calls) = self.objects.get(&n).cloned() else {
            return Err(self.err(loc, format!("ObjectInstance: unknown object \"{n}\"")));
        };
        let outer = self.g.ctm;
        for c in &calls {
            self.v4_emit_shape(c, outer, false)?;
        }
        Ok(())
    }

    /// Adds one shape placed by `outer * call.ctm`, emitting the current area light if `emits`.
    fn v4_emit_shape(&mut self, call: &ShapeCall, outer: Mat4, emits: bool) -> R<()> {
        let ps = &call.params;
        let loc = call.loc;
        let what = format!("Shape \"{}\"", call.ty);
        let m = outer * call.ctm;
        let t = Transform::new(m).ok_or_else(|| {
            self.err(
                loc,
                format!("{what}: the transform is singular or not finite"),
            )
        })?;
        for (param, why) in [(
            "emissionfilename",
            "an image of emission on a shape is not supported",
        )] {
            if ps.has(param) {
                ps.find(param, &["string"]);
                self.refuse(loc, format!("{what}: {why}"));
            }
        }
        for param in ["displacement", "edgelength"] {
            if ps.has(param) {
                ps.find(param, &["string", "texture", "float"]);
                self.warn(
                    loc,
                    format!(
                        "{what}: displacement is not supported; the surface is left undisplaced"
                    ),
                );
            }
        }
        let place = self.place_of(loc);
        let mesh = match call.ty.as_str() {
            "sphere" => {
                // pbrt-v3's sphere (v3's reader checks it); the area for `power` only.
                let radius = self.float(ps, "radius", 1.0)?;
                let scale = uniform_scale(&m).unwrap_or(1.0);
                let area = 2.0 * TAU * (radius * scale).powi(2);
                let emission = if emits {
                    self.v4_area_radiance(area)
                } else {
                    None
                };
                return self.emit_shape(call, outer, emission);
            }
            "trianglemesh" => self.mesh_of(call, place.clone())?.0,
            "plymesh" => {
                let Some(file) = self.string(ps, "filename")? else {
                    return Err(self.err(loc, "plymesh has no \"string filename\""));
                };
                if file.to_ascii_lowercase().ends_with(".gz") {
                    let f = self
                        .b
                        .resolver()
                        .resolve(&file, "plymesh")
                        .map_err(|e| self.at(loc, e))?;
                    read_ply_gz(&f)
                        .map_err(|e| self.err(loc, format!("{}: {e}", f.path().display())))?
                } else {
                    self.mesh_of(call, place.clone())?.0
                }
            }
            "bilinearmesh" => self.bilinear_mesh(ps, loc)?,
            "disk" => {
                let height = self.float(ps, "height", 0.0)?;
                let radius = self.float(ps, "radius", 1.0)?;
                let inner = self.float(ps, "innerradius", 0.0)?;
                let phi_max = self.float(ps, "phimax", 360.0)?.clamp(0.0, 360.0);
                if !(radius > 0.0 && inner >= 0.0 && inner < radius && phi_max > 0.0) {
                    return Err(self.err(
                        loc,
                        format!("{what}: needs 0 <= innerradius < radius and phimax > 0"),
                    ));
                }
                self.reversed_quadric(disk(height, radius, inner, phi_max.to_radians()), call)
            }
            "cylinder" => {
                let radius = self.float(ps, "radius", 1.0)?;
                let zmin = self.float(ps, "zmin", -1.0)?;
                let zmax = self.float(ps, "zmax", 1.0)?;
                let phi_max = self.float(ps, "phimax", 360.0)?.clamp(0.0, 360.0);
                if !(radius > 0.0 && zmin != zmax && phi_max > 0.0) {
                    return Err(self.err(
                        loc,
                        format!("{what}: needs radius > 0, zmin != zmax and phimax > 0"),
                    ));
                }
                let (lo, hi) = (zmin.min(zmax), zmin.max(zmax));
                self.reversed_quadric(cylinder(radius, lo, hi, phi_max.to_radians()), call)
            }
            other => {
                ps.consume_all();
                self.refuse(loc, format!("Shape \"{other}\" is not supported"));
                return Ok(());
            }
        };
        let emission = if emits {
            self.v4_area_radiance(world_area(&mesh, &t))
        } else {
            None
        };
        self.add_shape_mesh(call, mesh, &t, emission, &place)
    }

    /// A tessellated quadric with its normals flipped by ReverseOrientation (pbrt-v4's quadrics
    /// face their normal transform's way otherwise).
    fn reversed_quadric(&self, mut mesh: MeshData, call: &ShapeCall) -> MeshData {
        if call.reverse {
            for n in &mut mesh.normals {
                *n = -*n;
            }
            for tri in &mut mesh.indices {
                tri.swap(1, 2);
            }
        }
        mesh
    }

    /// `bilinearmesh`: `P`, `indices` (four per patch: p00, p10, p01, p11), `N`, `uv`; each patch
    /// becomes the triangles (p00, p10, p11) and (p00, p11, p01), which face pbrt-v4's
    /// dp/du x dp/dv. Without `uv` each patch gets pbrt-v4's default (u, v) in [0, 1]^2, its
    /// vertices unshared.
    fn bilinear_mesh(&mut self, ps: &ParamSet, loc: Loc) -> R<MeshData> {
        let PolygonMesh {
            positions: p,
            indices: idx,
            normals,
            uvs,
        } = self.polygon_mesh(ps, loc, "bilinearmesh", "point3", 4, &["uv"])?;
        let quads = idx
            .chunks_exact(4)
            .map(|q| [q[0] as u32, q[1] as u32, q[2] as u32, q[3] as u32]);
        let mut m = MeshData::default();
        if uvs.is_empty() {
            let corner_uv = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)];
            for q in quads {
                let base = m.positions.len() as u32;
                for (k, &i) in q.iter().enumerate() {
                    m.positions.push(p[i as usize]);
                    if !normals.is_empty() {
                        m.normals.push(normals[i as usize]);
                    }
                    m.uvs.push(Vec2::new(corner_uv[k].0, corner_uv[k].1));
                }
                m.indices.push([base, base + 1, base + 3]);
                m.indices.push([base, base + 3, base + 2]);
            }
        } else {
            m.positions = p;
            m.normals = normals;
            m.uvs = uvs;
            for q in quads {
                m.indices.push([q[0], q[1], q[3]]);
                m.indices.push([q[0], q[3], q[2]]);
            }
        }
        Ok(m)
    }
}
