//! Shapes of Mitsuba 3 files (`obj`, `ply`, `serialized`, `rectangle`, `cube`, `sphere`,
//! `disk`, `cylinder`, `shapegroup` and `instance`) with their bsdfs and area emitters, in
//! Mitsuba 3's conventions (its shape plugins): normals recomputed where a mesh has none,
//! texture coordinates flipped as Mitsuba flips them, back faces of one-sided surfaces black.

use super::values::ColorUse;
use super::{Ctx, R};
use crate::geometry::{Mat4, Rgb, Transform, Vec2, Vec3};
use crate::material::{Material, MaterialKind, Texture};
use crate::scene::MeshData;
use crate::scene::import::common::{mitsuba_mesh_file, uniform_scale};
use crate::scene::import::mesh::{read_meshes, read_obj, read_ply};
use crate::scene::import::xml::{Node, Props};
use std::io::Read;

/// Segments around the circle of a tessellated `disk` or `cylinder`.
const SEGMENTS: usize = 256;

impl Ctx {
    /// Loads every OBJ and PLY file the scene names, in parallel (the slow part of big scenes).
    pub(super) fn preload_meshes(&mut self, root: &Node) {
        let mut files = Vec::new();
        let mut stack: Vec<&Node> = root.children.iter().collect();
        while let Some(n) = stack.pop() {
            stack.extend(n.children.iter());
            if let Some(f) = mitsuba_mesh_file(n)
                && let Ok(file) = self.b.resolver().resolve(f, "mesh")
            {
                files.push(file);
            }
        }
        files.sort();
        files.dedup();
        let loaded = read_meshes(files);
        self.meshes.extend(loaded);
    }

    /// Mitsuba's material of a shape without a bsdf: diffuse 0.5, or black for an emitter.
    fn default_material(&mut self, emitter: bool) -> u32 {
        let (slot, name, v) = if emitter {
            (
                &mut self.black_bsdf,
                "Mitsuba default of an emitter (black diffuse)",
                0.0,
            )
        } else {
            (&mut self.default_bsdf, "Mitsuba default (diffuse 0.5)", 0.5)
        };
        if let Some(i) = *slot {
            return i;
        }
        let m = Material::new(
            name,
            MaterialKind::Lambert {
                albedo: Texture::Constant(Rgb::splat(v)),
            },
            false,
        );
        let i = self.b.add_material(m);
        match emitter {
            true => self.black_bsdf = Some(i),
            false => self.default_bsdf = Some(i),
        }
        i
    }

    /// Adds a `<shape>` (under `parent`, an instance's transform) with its bsdf and emission.
    pub(super) fn shape(&mut self, n: &Node, parent: &Mat4) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let what = format!("shape \"{ty}\"");
        let loc = format!("line {}", n.line);
        if ty == "shapegroup" {
            // Rendered only through instances.
            for c in &n.children {
                if c.tag == "emitter" {
                    return Err(self.err(
                        c,
                        "a shapegroup may not hold emitters (Mitsuba 3 refuses it too)",
                    ));
                }
            }
            return Ok(());
        }
        let to_world = *parent * self.to_world(&p)?;
        if ty == "instance" {
            let mut groups = Vec::new();
            for c in p
                .any_with_tag("ref")
                .into_iter()
                .chain(p.any_with_tag("shape"))
            {
                groups.push(self.deref(c)?.clone());
            }
            let [group] = &groups[..] else {
                return Err(self.err(n, "an instance needs exactly one shapegroup"));
            };
            if group.attr("type") != Some("shapegroup") {
                return Err(self.err(
                    n,
                    format!("an instance of {} (not a shapegroup)", group.label()),
                ));
            }
            self.report_unused(&p, &what);
            for c in group.children.iter().filter(|c| c.tag == "shape") {
                self.shape(c, &to_world)?;
            }
            return Ok(());
        }
        let flip = self.boolean(&p, "flip_normals", false)?;
        // The bsdf and the area emitter, nested or referenced; their names do not matter.
        let mut bsdf = None;
        let mut emission = None;
        for c in n.children.iter() {
            if !matches!(c.tag.as_str(), "bsdf" | "ref" | "emitter") {
                continue;
            }
            let t = self.deref(c)?.clone();
            if let Some(name) = c.attr("name") {
                p.consume(name);
            }
            p.any_with_tag(&c.tag);
            match t.tag.as_str() {
                "bsdf" => bsdf = Some(t),
                "emitter" => emission = Some(self.area_radiance(&t)?),
                _ => {
                    return Err(self.err(c, format!("{} cannot be attached to a shape", t.label())));
                }
            }
        }
        let material = match &bsdf {
            Some(b) => self.material_of(b)?,
            None => self.default_material(emission.is_some()),
        };
        let mut mesh = match ty {
            "obj" | "ply" | "serialized" => {
                let rel = self
                    .string(&p, "filename")?
                    .ok_or_else(|| self.err(n, format!("{what} has no filename")))?;
                let file = self
                    .b
                    .resolver()
                    .resolve(&rel, "mesh")
                    .map_err(|e| self.err(n, e.message))?;
                let mut m = if ty == "serialized" {
                    let index = self.int(&p, "shape_index", 0)?;
                    let index = usize::try_from(index)
                        .map_err(|_| self.err(n, format!("shape_index {index} < 0")))?;
                    read_serialized(&file, index)
                        .map_err(|e| self.err(n, format!("serialized \"{rel}\": {e}")))?
                } else {
                    let loaded = match self.meshes.get(file.path()) {
                        Some(m) => m.clone(),
                        None if ty == "ply" => read_ply(&file),
                        None => read_obj(&file),
                    };
                    loaded.map_err(|e| self.err(n, format!("{what} \"{rel}\": {e}")))?
                };
                // Our v = 0 is an image's bottom row, Mitsuba's its top row; Mitsuba flips an OBJ's
                // v by default (so an OBJ's own coordinates are ours), nothing else's.
                let flip_uv = self.boolean(&p, "flip_tex_coords", ty == "obj")?;
                if !flip_uv {
                    for uv in &mut m.uvs {
                        uv.y = 1.0 - uv.y;
                    }
                }
                if self.boolean(&p, "face_normals", false)? {
                    m.normals.clear();
                } else if m.normals.is_empty() {
                    angle_weighted_normals(&mut m);
                }
                m
            }
            "rectangle" => rectangle(),
            "cube" => cube(),
            "disk" => disk(),
            "cylinder" => {
                let p0 = self.point_prop(&p, "p0", Vec3::ZERO)?;
                let p1 = self.point_prop(&p, "p1", Vec3::Z)?;
                let r = self.float(&p, "radius", 1.0)?;
                if !(r > 0.0) || p0 == p1 {
                    return Err(self.err(n, "a cylinder needs radius > 0 and p0 != p1"));
                }
                cylinder(p0, p1, r)
            }
            "sphere" => {
                let center = self.point_prop(&p, "center", Vec3::ZERO)?;
                let radius = self.float(&p, "radius", 1.0)?;
                if !(radius > 0.0) {
                    return Err(self.err(n, format!("sphere radius must be > 0, got {radius}")));
                }
                let m = to_world
                    * Mat4::from_translation(center)
                    * Mat4::from_scale(Vec3::splat(radius));
                let scale = uniform_scale(&m).ok_or_else(|| {
                    self.err(
                        n,
                        "a sphere under non-uniform scale or shear is not supported",
                    )
                })?;
                self.report_unused(&p, &what);
                return self.b.add_sphere(
                    m.transform_point3(Vec3::ZERO),
                    scale,
                    flip,
                    material,
                    emission,
                    &loc,
                );
            }
            other => {
                self.refuse(n, format!("shape \"{other}\" is not supported"));
                return Ok(());
            }
        };
        if flip {
            for t in &mut mesh.indices {
                t.swap(1, 2);
            }
            for v in &mut mesh.normals {
                *v = -*v;
            }
        }
        self.report_unused(&p, &what);
        let t =
            Transform::new(to_world).ok_or_else(|| self.err(n, "to_world is not invertible"))?;
        self.b.add_mesh(&mesh, &t, material, emission, &loc)
    }

    /// The radiance of an `area` emitter attached to a shape.
    fn area_radiance(&mut self, e: &Node) -> R<Rgb> {
        let ep = Props::new(e);
        match e.attr("type") {
            Some("area") => {}
            Some(other) => {
                return Err(self.err(
                    e,
                    format!("emitter \"{other}\" cannot be attached to a shape"),
                ));
            }
            None => return Err(self.err(e, "emitter without type")),
        }
        let r = match ep.get("radiance") {
            None => Rgb::from_array(super::values::FLAT_EMISSION_RGB),
            Some(v) if matches!(v.tag.as_str(), "texture" | "ref") => {
                self.refuse(e, "a textured area emitter radiance is not supported");
                Rgb::ZERO
            }
            Some(v) => self.color(v, ColorUse::Emission)?,
        };
        ep.consume("sampling_weight");
        self.report_unused(&ep, "emitter \"area\"");
        Ok(r)
    }
}

/// Vertex normals as Mitsuba computes them for a mesh without any: the unit normals of the
/// faces around a vertex, each weighted by the face's angle at the vertex (Thürmer and
/// Wüthrich, "Computing vertex normals from polygonal facets", JGT 1998).
fn angle_weighted_normals(m: &mut MeshData) {
    let mut n = vec![Vec3::ZERO; m.positions.len()];
    for t in &m.indices {
        let p = t.map(|k| m.positions[k as usize]);
        let face = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
        for i in 0..3 {
            let a = (p[(i + 1) % 3] - p[i]).normalize_or_zero();
            let b = (p[(i + 2) % 3] - p[i]).normalize_or_zero();
            let angle = a.dot(b).clamp(-1.0, 1.0).acos();
            n[t[i] as usize] += face * angle;
        }
    }
    for v in &mut n {
        let u = v.normalize_or_zero();
        *v = if u == Vec3::ZERO { Vec3::X } else { u };
    }
    m.normals = n;
}

/// Mitsuba's `rectangle`: [-1, 1]^2 in the plane z = 0, facing +z; uv (0, 0) at (-1, -1) in
/// Mitsuba's image-down convention, so ours is (u, 1 - v).
fn rectangle() -> MeshData {
    let corners = [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)];
    MeshData {
        positions: corners.iter().map(|&(x, y)| Vec3::new(x, y, 0.0)).collect(),
        normals: vec![Vec3::Z; 4],
        uvs: corners
            .iter()
            .map(|&(x, y)| Vec2::new(0.5 * (x + 1.0), 1.0 - 0.5 * (y + 1.0)))
            .collect(),
        indices: vec![[1, 2, 0], [1, 3, 2]],
    }
}

/// Mitsuba's `cube`: [-1, 1]^3, four vertices per face with the face's normal (flat shading),
/// each face mapped to the whole texture.
fn cube() -> MeshData {
    // Per face: its four corners and their uvs (Mitsuba's image-down uvs), as Mitsuba lists them.
    let faces: [[([f32; 3], [f32; 2]); 4]; 6] = [
        [
            ([1., -1., -1.], [0., 1.]),
            ([1., -1., 1.], [1., 1.]),
            ([-1., -1., 1.], [1., 0.]),
            ([-1., -1., -1.], [0., 0.]),
        ],
        [
            ([1., 1., -1.], [0., 1.]),
            ([-1., 1., -1.], [1., 1.]),
            ([-1., 1., 1.], [1., 0.]),
            ([1., 1., 1.], [0., 0.]),
        ],
        [
            ([1., -1., -1.], [0., 1.]),
            ([1., 1., -1.], [1., 1.]),
            ([1., 1., 1.], [1., 0.]),
            ([1., -1., 1.], [0., 0.]),
        ],
        [
            ([1., -1., 1.], [0., 1.]),
            ([1., 1., 1.], [1., 1.]),
            ([-1., 1., 1.], [1., 0.]),
            ([-1., -1., 1.], [0., 0.]),
        ],
        [
            ([-1., -1., 1.], [0., 1.]),
            ([-1., 1., 1.], [1., 1.]),
            ([-1., 1., -1.], [1., 0.]),
            ([-1., -1., -1.], [0., 0.]),
        ],
        [
            ([1., 1., -1.], [0., 1.]),
            ([1., -1., -1.], [1., 1.]),
            ([-1., -1., -1.], [1., 0.]),
            ([-1., 1., -1.], [0., 0.]),
        ],
    ];
    let mut m = MeshData::default();
    for face in faces {
        let base = m.positions.len() as u32;
        let [a, b, c, _] = face.map(|(p, _)| Vec3::from_array(p));
        let normal = (b - a).cross(c - a).normalize();
        for (p, uv) in face {
            m.positions.push(Vec3::from_array(p));
            m.normals.push(normal);
            m.uvs.push(Vec2::new(uv[0], 1.0 - uv[1]));
        }
        m.indices.push([base, base + 1, base + 2]);
        m.indices.push([base + 3, base, base + 2]);
    }
    m
}

/// Mitsuba's `disk`: the unit disk in the plane z = 0 facing +z, as a fan of `SEGMENTS`
/// triangles; Mitsuba's uv is (radius, angle / 2 pi).
fn disk() -> MeshData {
    let mut m = MeshData::default();
    m.positions.push(Vec3::ZERO);
    m.normals.push(Vec3::Z);
    m.uvs.push(Vec2::new(0.0, 1.0));
    for i in 0..=SEGMENTS {
        let t = i as f32 / SEGMENTS as f32;
        let a = t * std::f32::consts::TAU;
        m.positions.push(Vec3::new(a.cos(), a.sin(), 0.0));
        m.normals.push(Vec3::Z);
        m.uvs.push(Vec2::new(1.0, 1.0 - t));
    }
    for i in 0..SEGMENTS as u32 {
        m.indices.push([0, i + 1, i + 2]);
    }
    m
}

/// Mitsuba's `cylinder`: an open tube of radius `r` from `p0` to `p1`, normals outward, as
/// `SEGMENTS` quads with smooth normals; uv (angle / 2 pi, height).
fn cylinder(p0: Vec3, p1: Vec3, r: f32) -> MeshData {
    let axis = p1 - p0;
    let f = crate::geometry::Frame::from_normal(axis.normalize());
    let mut m = MeshData::default();
    for i in 0..=SEGMENTS {
        let t = i as f32 / SEGMENTS as f32;
        let a = t * std::f32::consts::TAU;
        let radial = f.s * a.cos() + f.t * a.sin();
        for h in [0.0, 1.0] {
            m.positions.push(p0 + radial * r + axis * h);
            m.normals.push(radial);
            m.uvs.push(Vec2::new(t, 1.0 - h));
        }
    }
    for i in 0..SEGMENTS as u32 {
        let (a, b, c, d) = (2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3);
        m.indices.push([a, c, d]);
        m.indices.push([a, d, b]);
    }
    m
}

/// Mesh `index` of a Mitsuba `serialized` file: meshes one after another, each a 2-byte magic
/// 0x041C, a 2-byte version (3 or 4) and a zlib stream of the mesh (flags, for version 4 a
/// name, vertex and triangle counts, positions, normals and uvs when flagged, colours skipped,
/// 32-bit indices), and at the end the table of the meshes' offsets.
fn read_serialized(
    file: &crate::scene::import::resolve::SceneFile,
    index: usize,
) -> Result<MeshData, String> {
    let mut bytes = Vec::new();
    file.open()
        .and_then(|mut f| f.read_to_end(&mut bytes))
        .map_err(|e| format!("cannot read: {e}"))?;
    let short = || "truncated file".to_string();
    let u16_at = |at: usize| -> Result<u16, String> {
        Ok(u16::from_le_bytes(
            bytes
                .get(at..at + 2)
                .ok_or_else(short)?
                .try_into()
                .map_err(|_| short())?,
        ))
    };
    let u32_at = |at: usize| -> Result<u32, String> {
        Ok(u32::from_le_bytes(
            bytes
                .get(at..at + 4)
                .ok_or_else(short)?
                .try_into()
                .map_err(|_| short())?,
        ))
    };
    let u64_at = |at: usize| -> Result<u64, String> {
        Ok(u64::from_le_bytes(
            bytes
                .get(at..at + 8)
                .ok_or_else(short)?
                .try_into()
                .map_err(|_| short())?,
        ))
    };
    if u16_at(0)? != 0x041C {
        return Err("not a serialized mesh file (bad magic)".into());
    }
    let version = u16_at(2)?;
    if !matches!(version, 3 | 4) {
        return Err(format!("version {version} (3 or 4 are read)"));
    }
    let start = if index == 0 {
        0
    } else {
        let n = bytes.len();
        let count = u32_at(n.checked_sub(4).ok_or_else(short)?)? as usize;
        if index >= count {
            return Err(format!(
                "shape_index {index}, but the file holds {count} meshes"
            ));
        }
        let at = if version == 4 {
            let table = n.checked_sub(4 + 8 * count).ok_or_else(short)?;
            u64_at(table + 8 * index)? as usize
        } else {
            let table = n.checked_sub(4 + 4 * count).ok_or_else(short)?;
            u32_at(table + 4 * index)? as usize
        };
        if u16_at(at)? != 0x041C {
            return Err(format!("mesh {index}: bad magic"));
        }
        at
    };
    // The stream inflates to at most what its counts claim; a bound keeps a bomb out.
    let limit = 64 * bytes.len().max(1 << 20);
    let raw = miniz_oxide::inflate::decompress_to_vec_zlib_with_limit(&bytes[start + 4..], limit)
        .map_err(|e| match e.status {
        miniz_oxide::inflate::TINFLStatus::HasMoreOutput => {
            "a mesh inflates past 64 times the file's size".to_string()
        }
        s => format!("a damaged zlib stream ({s:?})"),
    })?;
    let mut at = 0usize;
    let take = |at: &mut usize, n: usize| -> Result<&[u8], String> {
        let s = raw
            .get(*at..*at + n)
            .ok_or_else(|| "mesh data shorter than its counts".to_string())?;
        *at += n;
        Ok(s)
    };
    let flags = u32::from_le_bytes(take(&mut at, 4)?.try_into().map_err(|_| short())?);
    if version == 4 {
        let end = raw[at..]
            .iter()
            .position(|&b| b == 0)
            .ok_or("mesh name without its end")?;
        at += end + 1;
    }
    let nv = u64::from_le_bytes(take(&mut at, 8)?.try_into().map_err(|_| short())?) as usize;
    let nt = u64::from_le_bytes(take(&mut at, 8)?.try_into().map_err(|_| short())?) as usize;
    let double = flags & 0x2000 != 0;
    let scalar = if double { 8 } else { 4 };
    if nv.saturating_mul(3 * scalar) > raw.len() || nt.saturating_mul(12) > raw.len() {
        return Err("mesh counts larger than its data".into());
    }
    let floats = |at: &mut usize, n: usize| -> Result<Vec<f32>, String> {
        let s = take(at, n * scalar)?;
        Ok(if double {
            s.chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])) as f32)
                .collect()
        } else {
            s.chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap_or([0; 4])))
                .collect()
        })
    };
    let mut m = MeshData::default();
    let p = floats(&mut at, 3 * nv)?;
    m.positions = p
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect();
    if flags & 0x1 != 0 {
        let v = floats(&mut at, 3 * nv)?;
        m.normals = v
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect();
    }
    if flags & 0x2 != 0 {
        let v = floats(&mut at, 2 * nv)?;
        // Mitsuba's image-down v, made ours.
        m.uvs = v
            .chunks_exact(2)
            .map(|c| Vec2::new(c[0], 1.0 - c[1]))
            .collect();
    }
    if flags & 0x8 != 0 {
        floats(&mut at, 3 * nv)?;
    }
    let idx = take(&mut at, 12 * nt)?;
    m.indices = idx
        .chunks_exact(12)
        .map(|c| {
            let k = |i: usize| u32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
            [k(0), k(4), k(8)]
        })
        .collect();
    if m.normals.is_empty() {
        angle_weighted_normals(&mut m);
    }
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn built_in_shapes_face_their_normals() {
        for (name, m) in [
            ("rectangle", rectangle()),
            ("cube", cube()),
            ("disk", disk()),
        ] {
            for t in &m.indices {
                let [a, b, c] = t.map(|k| m.positions[k as usize]);
                let ng = (b - a).cross(c - a);
                for &k in t {
                    assert!(ng.dot(m.normals[k as usize]) > 0.0, "{name}");
                }
            }
        }
        let c = cylinder(Vec3::ZERO, Vec3::Z, 2.0);
        for t in &c.indices {
            let [a, b, d] = t.map(|k| c.positions[k as usize]);
            let ng = (b - a).cross(d - a);
            assert!(ng.dot(c.normals[t[0] as usize]) > 0.0);
        }
    }
}
