//! Where the importer tests write their files.

use crate::common;
use std::path::PathBuf;

pub fn folder(name: &str) -> PathBuf {
    common::folder("import", name)
}
