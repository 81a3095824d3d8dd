//! Scenes: bundles uploaded with POST /v1/scenes, the server's scene library (GET /v1/scenes),
//! and the bundles a job's scene becomes (a library file is packed, an inline scene wrapped).

use super::errors::{ApiError, ApiResult, bad};
use super::{AppState, is_safe_id};
use crate::scene::Scene;
use crate::service::protocol::{SceneLibrary, SceneMeta, SceneUploadQuery};
use crate::service::{App, bundle, store};
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

/// POST /v1/scenes: a tar bundle.
pub(crate) async fn upload_scene(
    State(app): State<AppState>,
    Query(q): Query<SceneUploadQuery>,
    body: Bytes,
) -> ApiResult<Response> {
    if body.is_empty() {
        return Err(bad("body", "empty body; send a tar archive of the scene"));
    }
    let a = app.clone();
    let (meta, _) =
        tokio::task::spawn_blocking(move || store_bundle(&a, &body, q.main.as_deref(), "body"))
            .await
            .map_err(ApiError::internal)??;
    Ok((StatusCode::CREATED, Json(meta)).into_response())
}

/// GET /v1/scenes: the library's scene names.
pub(crate) async fn list_scenes(State(app): State<AppState>) -> Json<SceneLibrary> {
    Json(SceneLibrary {
        library: library_names(&app),
    })
}

/// The metadata of a stored bundle, if there is one with this id.
pub(crate) fn scene_meta(app: &App, id: &str) -> Option<SceneMeta> {
    if !is_safe_id(id) {
        return None;
    }
    let bytes = std::fs::read(app.paths.scene(id).join("meta.json")).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// The extensions of scene files.
const SCENE_EXTENSIONS: [&str; 3] = [".json", ".pbrt", ".xml"];

/// A library scene file by name: `name.json|.pbrt|.xml`, or `name` itself when it has one of
/// those extensions, directly in the library (what GET /v1/scenes lists, nothing else).
fn library_file(app: &App, name: &str) -> ApiResult<std::path::PathBuf> {
    let lib = app
        .cfg
        .library
        .as_ref()
        .ok_or_else(|| bad("scene.library", "this server has no scene library"))?;
    if !is_safe_id(name) {
        return Err(bad(
            "scene.library",
            format!("'{name}' is not a scene name (letters, digits, - _ . only; no paths)"),
        ));
    }
    let has_extension = SCENE_EXTENSIONS
        .iter()
        .any(|e| name.to_ascii_lowercase().ends_with(e));
    let candidates: Vec<String> = if has_extension {
        vec![name.to_string()]
    } else {
        SCENE_EXTENSIONS
            .iter()
            .map(|e| format!("{name}{e}"))
            .collect()
    };
    candidates
        .iter()
        .map(|c| lib.join(c))
        .find(|p| p.is_file())
        .ok_or_else(|| {
            bad(
                "scene.library",
                format!("no scene '{name}' in the library (GET /v1/scenes lists them)"),
            )
        })
}

/// `msg` without the server's folder `dir` (errors name files relative to it).
fn hide_folder(msg: &str, dir: &std::path::Path) -> String {
    let d = dir.display().to_string();
    msg.replace(&format!("{d}/"), "").replace(&d, ".")
}

fn library_names(app: &App) -> Vec<String> {
    let Some(lib) = &app.cfg.library else {
        return Vec::new();
    };
    let mut v: Vec<String> = std::fs::read_dir(lib)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| e.file_name().to_str().map(str::to_string))
                .filter_map(|n| {
                    SCENE_EXTENSIONS
                        .iter()
                        .find_map(|ext| n.strip_suffix(ext).map(str::to_string))
                })
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// A library scene packed into a new bundle. Runs on a blocking thread.
pub(crate) fn store_library(app: &App, name: &str) -> ApiResult<(SceneMeta, Scene)> {
    let path = library_file(app, name)?;
    let lib = path.parent().unwrap_or(&path);
    let (tar, main) =
        bundle::pack(&path).map_err(|e| bad("scene.library", hide_folder(&e, lib)))?;
    store_bundle(app, &tar, Some(&main), "scene.library")
}

/// An inline JSON scene as a bundle of one file. Runs on a blocking thread.
pub(crate) fn store_inline(app: &App, scene: &serde_json::Value) -> ApiResult<(SceneMeta, Scene)> {
    if !scene.is_object() {
        return Err(bad("scene.inline", "must be a scene object"));
    }
    let text = serde_json::to_vec_pretty(scene).map_err(ApiError::internal)?;
    let mut tar = tar::Builder::new(Vec::new());
    let mut h = tar::Header::new_gnu();
    h.set_size(text.len() as u64);
    h.set_mode(0o644);
    h.set_cksum();
    tar.append_data(&mut h, "scene.json", text.as_slice())
        .map_err(ApiError::internal)?;
    let bytes = tar.into_inner().map_err(ApiError::internal)?;
    store_bundle(app, &bytes, Some("scene.json"), "scene.inline")
}

/// An uploaded bundle by id, loaded. Runs on a blocking thread.
pub(crate) fn load_bundle(app: &App, id: &str) -> ApiResult<(SceneMeta, Scene)> {
    let meta = scene_meta(app, id)
        .ok_or_else(|| bad("scene.bundle", format!("no scene bundle '{id}'")))?;
    let files = app.paths.scene(id).join("files");
    let scene = Scene::load(&files.join(&meta.main))
        .map_err(|e| bad("scene.bundle", hide_folder(&e.to_string(), &files)))?;
    Ok((meta, scene))
}

/// Stores a bundle: unpacks it under `scenes/<id>/files`, loads it to check it, keeps the tar for
/// workers. Runs on a blocking thread.
fn store_bundle(
    app: &App,
    tar: &[u8],
    main: Option<&str>,
    field: &str,
) -> ApiResult<(SceneMeta, Scene)> {
    let id = uuid::Uuid::new_v4().to_string();
    let dir = app.paths.scene(&id);
    let files_dir = dir.join("files");
    let result = (|| {
        let files =
            bundle::unpack(tar, &files_dir, app.cfg.max_upload_bytes).map_err(|e| bad(field, e))?;
        let main = bundle::choose_main(&files, main).map_err(|e| bad(field, e))?;
        let scene = Scene::load(&files_dir.join(&main))
            // Name the file inside the bundle, not the server's path.
            .map_err(|e| bad(field, hide_folder(&e.to_string(), &files_dir)))?;
        if scene.stats.triangles > app.cfg.limits.max_triangles {
            return Err(bad(
                field,
                format!(
                    "{} triangles exceed the limit of {}",
                    scene.stats.triangles, app.cfg.limits.max_triangles
                ),
            ));
        }
        let meta = SceneMeta {
            id: id.clone(),
            main,
            files,
            bytes: tar.len() as u64,
            triangles: scene.stats.triangles,
            width: scene.camera.width,
            height: scene.camera.height,
            warnings: scene.warnings.clone(),
        };
        std::fs::write(dir.join("bundle.tar"), tar).map_err(ApiError::internal)?;
        let json = serde_json::to_vec_pretty(&meta).map_err(ApiError::internal)?;
        store::write_atomic(&dir.join("meta.json"), &json).map_err(ApiError::internal)?;
        Ok((meta, scene))
    })();
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    result
}
