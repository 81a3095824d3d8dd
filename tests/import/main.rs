//! The pbrt-v3 importer: every directive from small files written to a temporary folder,
//! errors that name file and line; the pbrt dialects and the files a scene reads; and the public
//! scenes in `../shared/scenes` loaded, rendered and compared with our own scenes and between
//! formats. The Mitsuba 0.5 importer's elements are in `import_mitsuba.rs`.

#[path = "../common/mod.rs"]
mod common;
mod dialects;
mod pbrt_directives;
mod pbrt_errors;
mod shared_scenes;
mod support;
