//! Scenes: bundles uploaded with POST /v1/scenes, the server's scene library (GET /v1/scenes),
//! and the bundles a job's scene becomes (a library file is packed, an inline scene wrapped).

use super::errors::{ApiError, ApiResult, bad};
use super::{AppState, is_safe_id};
use crate::bundle;
use crate::job::frames;
use crate::protocol::{SceneLibrary, SceneMeta, SceneUploadQuery};
use crate::scene::Scene;
use crate::service::upload;
use crate::service::{App, store};
use axum::Json;
use axum::body::Body;
use axum::extract::{Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use std::io::Write;

/// POST /v1/scenes: a tar bundle, written to disk as it arrives, then unpacked and its scene
/// loaded to check it (`App::validations` at a time).
pub(crate) async fn upload_scene(
    State(app): State<AppState>,
    Query(q): Query<SceneUploadQuery>,
    body: Body,
) -> ApiResult<Response> {
    let id = uuid::Uuid::new_v4().to_string();
    let dir = app.paths.scene(&id);
    tokio::fs::create_dir_all(&dir)
        .await
        .map_err(|e| ApiError::disk("cannot store the bundle", e))?;
    let stored = upload::body_to_file(body, &dir.join(BUNDLE), app.cfg.max_upload_bytes).await;
    let n = match stored {
        Ok(n) => n,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&dir);
            return Err(e.into());
        }
    };
    if n == 0 {
        let _ = std::fs::remove_dir_all(&dir);
        return Err(bad("body", "empty body; send a tar archive of the scene"));
    }
    let _permit = app.validation().await?;
    let a = app.clone();
    let (meta, _) =
        tokio::task::spawn_blocking(move || store_bundle(&a, &id, q.main.as_deref(), "body"))
            .await
            .map_err(ApiError::internal)??;
    Ok((StatusCode::CREATED, Json(meta)).into_response())
}

/// The file of a stored bundle's tar archive, in its folder.
const BUNDLE: &str = "bundle.tar";

/// The tar archive of stored bundle `id`.
pub(crate) fn bundle_path(app: &App, id: &str) -> std::path::PathBuf {
    app.paths.scene(id).join(BUNDLE)
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
pub(crate) fn hide_folder(msg: &str, dir: &std::path::Path) -> String {
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
    let (tar, main) = bundle::pack(&path, &Default::default())
        .map_err(|e| bad("scene.library", hide_folder(&e.to_string(), lib)))?;
    let id = new_bundle(app, |f| f.write_all(&tar))?;
    store_bundle(app, &id, Some(&main), "scene.library")
}

/// An inline JSON scene (its text as sent) as a bundle of one file. Runs on a blocking thread.
pub(crate) fn store_inline(
    app: &App,
    scene: &serde_json::value::RawValue,
) -> ApiResult<(SceneMeta, Scene)> {
    if !scene.get().trim_start().starts_with('{') {
        return Err(bad("scene.inline", "must be a scene object"));
    }
    let text = scene.get().as_bytes();
    let id = new_bundle(app, |f| {
        let mut tar = tar::Builder::new(f);
        let mut h = tar::Header::new_gnu();
        h.set_size(text.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        tar.append_data(&mut h, INLINE_MAIN, text)?;
        tar.finish()
    })?;
    store_bundle(app, &id, Some(INLINE_MAIN), "scene.inline")
}

/// The scene file of a bundle made from an inline scene.
const INLINE_MAIN: &str = "scene.json";

/// A new bundle's folder with its tar archive written by `write`; returns its id.
fn new_bundle(
    app: &App,
    write: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>,
) -> ApiResult<String> {
    let id = uuid::Uuid::new_v4().to_string();
    let dir = app.paths.scene(&id);
    let written = std::fs::create_dir_all(&dir)
        .and_then(|()| std::fs::File::create(dir.join(BUNDLE)))
        .and_then(|mut f| write(&mut f));
    if let Err(e) = written {
        let _ = std::fs::remove_dir_all(&dir);
        return Err(ApiError::disk("cannot store the bundle", e));
    }
    Ok(id)
}

/// Removes stored bundle `id` (a job that made it was refused).
pub(crate) fn remove_bundle(app: &App, id: &str) {
    if is_safe_id(id) {
        let _ = std::fs::remove_dir_all(app.paths.scene(id));
    }
}

/// An uploaded bundle by id, loaded. Runs on a blocking thread.
pub(crate) fn load_bundle(app: &App, id: &str) -> ApiResult<(SceneMeta, Scene)> {
    load_bundle_with(app, id, &Default::default())
}

/// A stored bundle by id, loaded with the parameter values `params` (errors name
/// `settings.defines`, whose values make the difference). Runs on a blocking thread.
pub(crate) fn load_bundle_with(
    app: &App,
    id: &str,
    params: &crate::scene::SceneParams,
) -> ApiResult<(SceneMeta, Scene)> {
    let meta = scene_meta(app, id)
        .ok_or_else(|| bad("scene.bundle", format!("no scene bundle '{id}'")))?;
    let files = app.paths.scene(id).join("files");
    let field = if params.is_empty() {
        "scene.bundle"
    } else {
        "settings.defines"
    };
    let scene = Scene::load_with(&files.join(&meta.main), params)
        .map_err(|e| bad(field, hide_folder(&e.to_string(), &files)))?;
    Ok((meta, scene))
}

/// Checks and records bundle `id`, whose tar archive is in its folder: unpacks it under `files`,
/// loads its scene to check it, writes its metadata. On any error the folder is removed. Runs
/// on a blocking thread.
fn store_bundle(
    app: &App,
    id: &str,
    main: Option<&str>,
    field: &str,
) -> ApiResult<(SceneMeta, Scene)> {
    let dir = app.paths.scene(id);
    let files_dir = dir.join("files");
    let result = (|| {
        let tar = std::fs::File::open(dir.join(BUNDLE))
            .map_err(|e| ApiError::disk("cannot read the stored bundle", e))?;
        let bytes = tar.metadata().map(|m| m.len()).unwrap_or(0);
        let files = bundle::unpack(
            std::io::BufReader::new(tar),
            &files_dir,
            app.cfg.max_upload_bytes,
        )
        .map_err(|e| match e {
            bundle::BundleError::Invalid(m) => bad(field, m),
            bundle::BundleError::Disk { path, source } => {
                ApiError::disk(&format!("cannot unpack '{path}' of the bundle"), source)
            }
        })?;
        let (main, loaded) = match main.filter(|m| frames::is_pattern(m)) {
            // A sequence's bundle: checked with its first frame's scene (the job checks every
            // frame it renders).
            Some(pattern) => {
                frames::validate_pattern(pattern, field).map_err(|e| bad(field, e.message))?;
                let first = files
                    .iter()
                    .filter_map(|f| frames::frame_of(pattern, f).map(|n| (n, f)))
                    .min()
                    .map(|(_, f)| f.clone())
                    .ok_or_else(|| {
                        bad(
                            field,
                            format!("no file of the bundle is a frame of '{pattern}'"),
                        )
                    })?;
                (pattern.to_string(), first)
            }
            None => {
                let main =
                    bundle::choose_main(&files, main).map_err(|e| bad(field, e.to_string()))?;
                (main.clone(), main)
            }
        };
        let scene = Scene::load(&files_dir.join(&loaded))
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
            id: id.to_string(),
            main,
            files,
            bytes,
            triangles: scene.stats.triangles,
            width: scene.camera.width,
            height: scene.camera.height,
            warnings: scene
                .warnings
                .iter()
                .map(|w| hide_folder(w, &files_dir))
                .collect(),
        };
        let json = serde_json::to_vec_pretty(&meta).map_err(ApiError::internal)?;
        store::write_atomic(&dir.join("meta.json"), &json)
            .map_err(|e| ApiError::disk("cannot record the bundle", e))?;
        Ok((meta, scene))
    })();
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    result
}
