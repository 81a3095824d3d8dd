//! Triangle mesh files: Wavefront OBJ (tobj) and PLY, ASCII or binary (ply-rs-bw).
//!
//! A scene's meshes are read from the [`SceneFile`]s its resolver hands out; [`load_obj`] reads
//! a standalone file that belongs to no scene (benchmarks).

use super::resolve::SceneFile;
use crate::geometry::{Vec2, Vec3};
use crate::scene::MeshData;
use rayon::prelude::*;
use std::io::BufRead;
use std::path::{Path, PathBuf};

/// Why a mesh file could not be read. Its text names the cause; the caller adds the file.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// The file could not be opened (the system's reason).
    #[error("cannot open: {0}")]
    Open(String),
    /// The file could not be read to its end (the system's reason).
    #[error("cannot read: {0}")]
    Read(String),
    /// The extension names no format we read.
    #[error("unknown mesh format '.{0}' (expected .obj or .ply)")]
    UnknownFormat(String),
    /// A gzipped PLY file that would unpack to more than `MAX_GUNZIPPED_PLY` bytes.
    #[error("the PLY file unpacks to {0} bytes, more than the {max} allowed", max = MAX_GUNZIPPED_PLY)]
    TooLarge(usize),
    /// The contents are not a mesh we read: what is wrong, and where.
    #[error("{0}")]
    Malformed(String),
}

/// Loads an OBJ or PLY file of a scene by extension. Polygons are triangulated as fans.
pub fn load_mesh(file: &SceneFile) -> Result<MeshData, MeshError> {
    let ext = file
        .path()
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "obj" => read_obj(file),
        "ply" => read_ply(file),
        other => Err(MeshError::UnknownFormat(other.to_string())),
    }
}

/// Loads a scene's OBJ file.
pub fn read_obj(file: &SceneFile) -> Result<MeshData, MeshError> {
    obj_from(&mut file.open().map_err(|e| MeshError::Open(e.to_string()))?)
        .map_err(MeshError::Malformed)
}

/// Loads a scene's PLY file.
pub fn read_ply(file: &SceneFile) -> Result<MeshData, MeshError> {
    ply_from(&mut file.open().map_err(|e| MeshError::Open(e.to_string()))?)
        .map_err(MeshError::Malformed)
}

/// Largest decompressed size of a gzipped PLY file (a hostile file cannot make us allocate
/// more).
const MAX_GUNZIPPED_PLY: usize = 1 << 30;

/// Loads a scene's gzipped PLY file (`.ply.gz`, as pbrt-v4 writes them).
pub fn read_ply_gz(file: &SceneFile) -> Result<MeshData, MeshError> {
    use std::io::Read;
    let mut packed = Vec::new();
    file.open()
        .map_err(|e| MeshError::Open(e.to_string()))?
        .take(MAX_GUNZIPPED_PLY as u64 + 1)
        .read_to_end(&mut packed)
        .map_err(|e| MeshError::Read(e.to_string()))?;
    // The gzip trailer ends with the uncompressed size modulo 2^32 (RFC 1952, section 2.3.1).
    let Some(tail) = packed.len().checked_sub(4).map(|at| &packed[at..]) else {
        return Err(MeshError::Malformed("not a gzip file (too short)".into()));
    };
    let size = u32::from_le_bytes([tail[0], tail[1], tail[2], tail[3]]) as usize;
    if size > MAX_GUNZIPPED_PLY {
        return Err(MeshError::TooLarge(size));
    }
    let mut plain = vec![0u8; size];
    let n = libdeflater::Decompressor::new()
        .gzip_decompress(&packed, &mut plain)
        .map_err(|e| MeshError::Malformed(format!("malformed gzip data: {e:?}")))?;
    plain.truncate(n);
    ply_from(&mut std::io::Cursor::new(plain)).map_err(MeshError::Malformed)
}

/// Reads `files` in parallel (PLY by extension, else OBJ): each one's path with its mesh or
/// error, for importers that read every mesh of a scene before its shapes.
pub(crate) fn read_meshes(files: Vec<SceneFile>) -> Vec<(PathBuf, Result<MeshData, MeshError>)> {
    files
        .into_par_iter()
        .map(|f| {
            let ply = f
                .path()
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
            let m = if ply { read_ply(&f) } else { read_obj(&f) };
            (f.path().to_path_buf(), m)
        })
        .collect()
}

/// Loads an OBJ file that is not part of a scene (a scene's files go through its resolver).
pub fn load_obj(path: &Path) -> Result<MeshData, MeshError> {
    let file = std::fs::File::open(path).map_err(|e| MeshError::Open(e.to_string()))?;
    obj_from(&mut std::io::BufReader::new(file)).map_err(MeshError::Malformed)
}

fn obj_from(reader: &mut impl BufRead) -> Result<MeshData, String> {
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    // Materials come from the scene file, never from .mtl files.
    let (models, _) = tobj::load_obj_buf(reader, &opts, |_| Ok(Default::default()))
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

fn ply_from(reader: &mut impl BufRead) -> Result<MeshData, String> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    let ply = Parser::<DefaultElement>::new()
        .read_ply(reader)
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
