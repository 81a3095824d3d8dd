//! Shapes (`trianglemesh`, `plymesh`, `sphere`) and object instancing, flattened into the scene.

use super::lexer::Loc;
use super::params::ParamSet;
use super::{Frame, Parser, R};
use crate::geometry::{Mat4, Rgb, Transform, Vec2, Vec3};
use crate::scene::MeshData;
use crate::scene::import::common::uniform_scale;
use crate::scene::import::mesh::read_ply;

/// A shape recorded inside `ObjectBegin`/`ObjectEnd`, instantiated by `ObjectInstance`.
#[derive(Clone)]
pub(super) struct ShapeCall {
    pub(super) ty: String,
    pub(super) params: ParamSet,
    pub(super) ctm: Mat4,
    pub(super) material: u32,
    pub(super) reverse: bool,
    pub(super) loc: Loc,
}

/// A polygon mesh's vertex arrays as its parameters give them, checked (`Parser::polygon_mesh`).
pub(super) struct PolygonMesh {
    pub(super) positions: Vec<Vec3>,
    /// `corners` vertex indices a polygon, each within `positions`.
    pub(super) indices: Vec<i64>,
    /// None, or one a position.
    pub(super) normals: Vec<Vec3>,
    /// None, or one a position.
    pub(super) uvs: Vec<Vec2>,
}

impl Parser {
    /// Handles `ObjectBegin`, `ObjectEnd` and `ObjectInstance`; false for any other directive.
    pub(super) fn object_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
            "ObjectBegin" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                if self.defining.is_some() {
                    return Err(self.err(loc, "ObjectBegin inside ObjectBegin"));
                }
                // pbrt-v3: ObjectBegin implies AttributeBegin.
                self.stack
                    .push(Frame::Attribute(Box::new(self.g.clone()), loc));
                self.defining = Some((n, Vec::new()));
            }
            "ObjectEnd" => {
                let Some((n, calls)) = self.defining.take() else {
                    return Err(self.err(loc, "ObjectEnd without ObjectBegin"));
                };
                self.objects.insert(n, calls);
                match self.stack.pop() {
                    Some(Frame::Attribute(g, _)) => self.g = *g,
                    _ => return Err(self.err(loc, "ObjectEnd does not match its ObjectBegin")),
                }
            }
            "ObjectInstance" => {
                self.world_only(name, loc)?;
                let n = self.arg_str(name)?;
                if self.defining.is_some() {
                    return Err(self.err(loc, "ObjectInstance inside ObjectBegin is not supported"));
                }
                let Some(calls) = self.objects.get(&n).cloned() else {
                    return Err(self.err(loc, format!("ObjectInstance: unknown object \"{n}\"")));
                };
                let outer = self.g.ctm;
                for c in &calls {
                    self.emit_shape(c, outer, None)?;
                }
            }
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// `Shape "type" params`: added now, or recorded for an object being defined.
    pub(super) fn shape(&mut self, loc: Loc) -> R<()> {
        let ty = self.arg_str("Shape")?;
        let params = self.params()?;
        if !self.in_world {
            return Err(self.err(loc, "Shape outside WorldBegin/WorldEnd"));
        }
        let Some(call) = self.shape_call(ty, params, loc, "pbrt-v3") else {
            return Ok(());
        };
        let emission = self.g.area;
        self.emit_shape(&call, Mat4::IDENTITY, emission)
    }

    /// The call of shape `ty` with `params` at `loc` in the current graphics state, to be added
    /// now; None where it is recorded for the object being defined instead (whose shapes do
    /// not emit, as in `pbrt`, which the warning names).
    pub(super) fn shape_call(
        &mut self,
        ty: String,
        params: ParamSet,
        loc: Loc,
        pbrt: &str,
    ) -> Option<ShapeCall> {
        let call = ShapeCall {
            ty,
            params,
            ctm: self.g.ctm,
            material: self.current_material(),
            reverse: self.g.reverse,
            loc,
        };
        let Some((_, calls)) = &mut self.defining else {
            return Some(call);
        };
        calls.push(call);
        if self.g.area.is_some() {
            self.warn(loc, format!("area lights inside object instances are not supported (as in {pbrt}); the shape does not emit"));
        }
        None
    }

    /// Adds one shape, placed by `outer * call.ctm`.
    pub(super) fn emit_shape(
        &mut self,
        call: &ShapeCall,
        outer: Mat4,
        emission: Option<Rgb>,
    ) -> R<()> {
        let loc = call.loc;
        let what = format!("Shape \"{}\"", call.ty);
        let m = outer * call.ctm;
        let t = Transform::new(m).ok_or_else(|| {
            self.err(
                loc,
                format!("{what}: the transform is singular or not finite"),
            )
        })?;
        let place = self.place_of(loc);
        if call.ty == "sphere" {
            return self.emit_sphere(call, &m, &t, emission, &place);
        }
        let (mesh, place) = self.mesh_of(call, place)?;
        self.add_shape_mesh(call, mesh, &t, emission, &place)
    }

    /// The place a message names: the line of `loc`, and its file when included.
    pub(super) fn place_of(&self, loc: Loc) -> String {
        if loc.file == 0 {
            format!("line {}", loc.line)
        } else {
            format!(
                "{} line {}",
                self.files[loc.file as usize].display(),
                loc.line
            )
        }
    }

    /// A `sphere` placed by `m` (`t`).
    fn emit_sphere(
        &mut self,
        call: &ShapeCall,
        m: &Mat4,
        t: &Transform,
        emission: Option<Rgb>,
        place: &str,
    ) -> R<()> {
        let ps = &call.params;
        let loc = call.loc;
        let what = format!("Shape \"{}\"", call.ty);
        let radius = self.float(ps, "radius", 1.0)?;
        let zmin = self.float(ps, "zmin", -radius)?;
        let zmax = self.float(ps, "zmax", radius)?;
        let phimax = self.float(ps, "phimax", 360.0)?;
        if zmin > -radius || zmax < radius || phimax < 360.0 {
            return Err(self.err(
                loc,
                "partial spheres (zmin, zmax, phimax) are not supported",
            ));
        }
        if !(radius > 0.0 && radius.is_finite()) {
            return Err(self.err(loc, format!("sphere radius must be > 0, got {radius}")));
        }
        let center = t.point(Vec3::ZERO);
        let scale = uniform_scale(m).ok_or_else(|| {
            self.err(
                loc,
                "a sphere under non-uniform scale or shear is not supported",
            )
        })?;
        // pbrt-v3 flips the normal when reverseOrientation ^ transformSwapsHandedness.
        let inward = call.reverse ^ t.swaps_handedness();
        self.report_unused(ps, &what);
        self.b.add_sphere(
            center,
            radius * scale,
            inward,
            call.material,
            emission,
            place,
        )
    }

    /// The vertex arrays of a polygon mesh (`trianglemesh`; pbrt-v4's `bilinearmesh`), checked:
    /// `P` (errors name its type `point`), `indices` (`corners` a polygon, every one a vertex;
    /// left out only for a single polygon), `N` (none or one a vertex) and the uvs of the first
    /// of `uv_names` given (none or two numbers a vertex).
    pub(super) fn polygon_mesh(
        &mut self,
        ps: &ParamSet,
        loc: Loc,
        shape: &str,
        point: &str,
        corners: usize,
        uv_names: &[&str],
    ) -> R<PolygonMesh> {
        let p = self
            .vec3s(ps, "P", &["point3"])?
            .ok_or_else(|| self.err(loc, format!("{shape} has no \"{point} P\"")))?;
        let idx = match self.ints(ps, "indices")? {
            Some(i) => i,
            None if p.len() == corners => (0..corners as i64).collect(),
            None => {
                return Err(self.err(
                    loc,
                    format!(
                        "{shape} has no \"integer indices\" (only allowed for exactly {corners} vertices)"
                    ),
                ));
            }
        };
        if idx.len() % corners != 0 {
            return Err(self.err(
                loc,
                format!(
                    "{shape}: {} indices, not a multiple of {corners}",
                    idx.len()
                ),
            ));
        }
        if let Some(&bad) = idx.iter().find(|&&i| i < 0 || i as usize >= p.len()) {
            return Err(self.err(
                loc,
                format!("{shape}: index {bad} out of range for {} vertices", p.len()),
            ));
        }
        let normals = self.vec3s(ps, "N", &["normal3"])?.unwrap_or_default();
        if !normals.is_empty() && normals.len() != p.len() {
            return Err(self.err(
                loc,
                format!(
                    "{shape}: {} normals for {} vertices",
                    normals.len(),
                    p.len()
                ),
            ));
        }
        let uv_param = uv_names
            .iter()
            .find_map(|n| ps.find(n, &["float", "point2"]));
        let uvs: Vec<Vec2> = match uv_param {
            Some(param) => {
                let v = self.nums(param)?;
                if v.len() != 2 * p.len() {
                    return Err(self.err(
                        param.loc,
                        format!("{shape}: {} uv values for {} vertices", v.len(), p.len()),
                    ));
                }
                v.chunks_exact(2)
                    .map(|c| Vec2::new(c[0] as f32, c[1] as f32))
                    .collect()
            }
            None => Vec::new(),
        };
        Ok(PolygonMesh {
            positions: p,
            indices: idx,
            normals,
            uvs,
        })
    }

    /// The triangles of a `trianglemesh` or `plymesh` (any other type is an error), and the
    /// place its errors name (`place`, with the mesh file's name for a `plymesh`).
    pub(super) fn mesh_of(&mut self, call: &ShapeCall, place: String) -> R<(MeshData, String)> {
        let ps = &call.params;
        let loc = call.loc;
        let mut place = place;
        let mesh = match call.ty.as_str() {
            "trianglemesh" => {
                let m = self.polygon_mesh(ps, loc, "trianglemesh", "point", 3, &["uv", "st"])?;
                MeshData {
                    positions: m.positions,
                    normals: m.normals,
                    uvs: m.uvs,
                    indices: m
                        .indices
                        .chunks_exact(3)
                        .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
                        .collect(),
                }
            }
            "plymesh" => {
                let Some(file) = self.string(ps, "filename")? else {
                    return Err(self.err(loc, "plymesh has no \"string filename\""));
                };
                let f = self
                    .b
                    .resolver()
                    .resolve(&file, "plymesh")
                    .map_err(|e| self.at(loc, e))?;
                // Errors in the mesh's data name its file.
                place = format!("{place} ({})", f.path().display());
                read_ply(&f).map_err(|e| self.err(loc, format!("{}: {e}", f.path().display())))?
            }
            other => {
                return Err(self.err(
                    loc,
                    format!("Shape \"{other}\" is not supported (supported: trianglemesh, plymesh, sphere)"),
                ));
            }
        };
        Ok((mesh, place))
    }

    /// Adds the triangles of a shape: reports its unused parameters and orients it as pbrt
    /// does.
    pub(super) fn add_shape_mesh(
        &mut self,
        call: &ShapeCall,
        mesh: MeshData,
        t: &Transform,
        emission: Option<Rgb>,
        place: &str,
    ) -> R<()> {
        let ps = &call.params;
        let loc = call.loc;
        let what = format!("Shape \"{}\"", call.ty);
        if ps.has("alpha") || ps.has("shadowalpha") {
            ps.find("alpha", &["float", "texture"]);
            ps.find("shadowalpha", &["float", "texture"]);
            self.warn(
                loc,
                format!("{what}: alpha cut-outs are not supported; the surface is opaque"),
            );
        }
        self.report_unused(ps, &what);
        let mut mesh = mesh;
        // Without vertex normals pbrt-v3 orients a triangle by its winding, flipped when
        // reverseOrientation ^ transformSwapsHandedness; with vertex normals the geometric normal
        // follows them (our builder does the same), and ReverseOrientation has no effect.
        if mesh.normals.is_empty() && (call.reverse ^ t.swaps_handedness()) {
            for tri in &mut mesh.indices {
                tri.swap(1, 2);
            }
        }
        if let Some(e) = emission
            && e != Rgb::ZERO
            && mesh.indices.is_empty()
        {
            self.warn(loc, format!("{what}: emitting mesh has no triangles"));
        }
        self.b.add_mesh(&mesh, t, call.material, emission, place)
    }
}
