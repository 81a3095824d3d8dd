//! Triangle mesh files: Wavefront OBJ (tobj) and PLY, ASCII or binary (ply-rs-bw).

use super::MeshData;
use crate::geometry::{Vec2, Vec3};
use std::path::Path;

/// Loads an OBJ or PLY file by extension. Polygons are triangulated as fans.
pub fn load_mesh(path: &Path) -> Result<MeshData, String> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "obj" => load_obj(path),
        "ply" => load_ply(path),
        other => Err(format!(
            "unknown mesh format '.{other}' (expected .obj or .ply)"
        )),
    }
}

pub fn load_obj(path: &Path) -> Result<MeshData, String> {
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let file = std::fs::File::open(path).map_err(|e| format!("cannot open: {e}"))?;
    let mut reader = std::io::BufReader::new(file);
    // Materials come from the scene file, never from .mtl files.
    let (models, _) = tobj::load_obj_buf(&mut reader, &opts, |_| Ok(Default::default()))
        .map_err(|e| format!("malformed OBJ: {e}"))?;
    let mut out = MeshData::default();
    let all_normals = models
        .iter()
        .all(|m| !m.mesh.normals.is_empty() || m.mesh.positions.is_empty());
    let all_uvs = models
        .iter()
        .all(|m| !m.mesh.texcoords.is_empty() || m.mesh.positions.is_empty());
    for m in &models {
        let mesh = &m.mesh;
        let base = out.positions.len() as u32;
        out.positions.extend(
            mesh.positions
                .chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2])),
        );
        if all_normals {
            out.normals.extend(
                mesh.normals
                    .chunks_exact(3)
                    .map(|c| Vec3::new(c[0], c[1], c[2])),
            );
        }
        if all_uvs {
            out.uvs.extend(
                mesh.texcoords
                    .chunks_exact(2)
                    .map(|c| Vec2::new(c[0], c[1])),
            );
        }
        out.indices.extend(
            mesh.indices
                .chunks_exact(3)
                .map(|c| [c[0] + base, c[1] + base, c[2] + base]),
        );
    }
    if out.indices.is_empty() {
        return Err("OBJ file has no faces".into());
    }
    Ok(out)
}

pub fn load_ply(path: &Path) -> Result<MeshData, String> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    let file = std::fs::File::open(path).map_err(|e| format!("cannot open: {e}"))?;
    let mut reader = std::io::BufReader::new(file);
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut reader)
        .map_err(|e| format!("malformed PLY: {e}"))?;
    let verts = ply
        .payload
        .get("vertex")
        .ok_or("PLY file has no 'vertex' element")?;
    let faces = ply
        .payload
        .get("face")
        .ok_or("PLY file has no 'face' element")?;
    let scalar = |e: &DefaultElement, k: &str| e.get(k).and_then(Property::to_f32_lossy);
    let mut out = MeshData::default();
    let has_n = verts.first().is_some_and(|v| scalar(v, "nx").is_some());
    let uv_keys = [("u", "v"), ("s", "t"), ("texture_u", "texture_v")]
        .into_iter()
        .find(|(a, _)| verts.first().is_some_and(|v| scalar(v, a).is_some()));
    for (i, v) in verts.iter().enumerate() {
        let p = (|| Some(Vec3::new(scalar(v, "x")?, scalar(v, "y")?, scalar(v, "z")?)))()
            .ok_or_else(|| format!("vertex {i} lacks x, y or z"))?;
        out.positions.push(p);
        if has_n {
            let n = (|| {
                Some(Vec3::new(
                    scalar(v, "nx")?,
                    scalar(v, "ny")?,
                    scalar(v, "nz")?,
                ))
            })()
            .ok_or_else(|| format!("vertex {i} lacks nx, ny or nz"))?;
            out.normals.push(n);
        }
        if let Some((ku, kv)) = uv_keys {
            let uv = (|| Some(Vec2::new(scalar(v, ku)?, scalar(v, kv)?)))()
                .ok_or_else(|| format!("vertex {i} lacks {ku} or {kv}"))?;
            out.uvs.push(uv);
        }
    }
    for (f, face) in faces.iter().enumerate() {
        let idx = face
            .get("vertex_indices")
            .or_else(|| face.get("vertex_index"))
            .and_then(Property::to_u32_list)
            .ok_or_else(|| format!("face {f} has no vertex_indices list"))?;
        if idx.len() < 3 {
            return Err(format!("face {f} has {} vertices", idx.len()));
        }
        for k in 1..idx.len() - 1 {
            out.indices.push([idx[0], idx[k], idx[k + 1]]);
        }
    }
    if out.indices.is_empty() {
        return Err("PLY file has no faces".into());
    }
    Ok(out)
}
