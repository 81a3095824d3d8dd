//! What the importers share: warnings reported once with their place, conductor constants, the
//! bitmap cache, and the geometric conversions both foreign formats need.

use super::resolve::SceneFile;
use super::xml::Node;
use crate::camera::Camera;
use crate::geometry::{Frame, Mat4, Rgb, Transform, Vec3};
use crate::material::{Bitmap, Material, MaterialKind, Texture};
use crate::scene::SceneBuilder;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;

/// pbrt-v3's default `metal` is copper; these are the RGB values of its complex index of
/// refraction used by Bitterli's scene exports (and by Mitsuba's `Cu`).
pub(crate) const COPPER_ETA: [f32; 3] = [0.200438, 0.924033, 1.102212];
/// The imaginary part (absorption) of copper's index of refraction; see [`COPPER_ETA`].
pub(crate) const COPPER_K: [f32; 3] = [3.912949, 2.452848, 2.142188];

/// Collects warnings, each message once with the place of its first occurrence and a count.
#[derive(Default)]
pub(crate) struct Warnings {
    entries: Vec<(String, String, usize)>,
    index: HashMap<String, usize>,
}

impl Warnings {
    /// Records `message` seen at `place` ("file:line").
    pub(crate) fn add(&mut self, place: String, message: impl Into<String>) {
        let m = message.into();
        match self.index.get(&m) {
            Some(&i) => self.entries[i].2 += 1,
            None => {
                self.index.insert(m.clone(), self.entries.len());
                self.entries.push((m, place, 1));
            }
        }
    }

    /// Hands the warnings to the scene builder, one line each.
    pub(crate) fn flush(self, b: &mut SceneBuilder) {
        for (m, place, n) in self.entries {
            if n > 1 {
                b.warn(format!("{place}: {m} ({n} occurrences)"));
            } else {
                b.warn(format!("{place}: {m}"));
            }
        }
    }
}

/// Decoded images by file and encoding: a file a scene uses several times is read once.
#[derive(Default)]
pub(crate) struct Bitmaps {
    cache: HashMap<(PathBuf, bool), Arc<Bitmap>>,
}

impl Bitmaps {
    /// The image of `file`, decoded as sRGB (`srgb`) or linear.
    pub(crate) fn load(
        &mut self,
        file: &SceneFile,
        srgb: bool,
    ) -> Result<Arc<Bitmap>, crate::material::texture::TextureError> {
        let key = (file.path().to_path_buf(), srgb);
        if let Some(b) = self.cache.get(&key) {
            return Ok(b.clone());
        }
        let b = Arc::new(Bitmap::load_with(file.path(), srgb)?);
        self.cache.insert(key, b.clone());
        Ok(b)
    }
}

/// The index of an importer's default material, a Lambertian of albedo 0.5 called `name`, added
/// to `b` on first use (`slot` remembers it).
pub(crate) fn default_lambert(
    b: &mut SceneBuilder,
    slot: &mut Option<u32>,
    name: &str,
    two_sided: bool,
) -> u32 {
    *slot.get_or_insert_with(|| {
        b.add_material(Material::new(
            name,
            MaterialKind::Lambert {
                albedo: Texture::Constant(Rgb::splat(0.5)),
            },
            two_sided,
        ))
    })
}

/// The uniform scale factor of an affine matrix without shear, or `None`.
pub(crate) fn uniform_scale(m: &Mat4) -> Option<f32> {
    let x = m.x_axis.truncate();
    let y = m.y_axis.truncate();
    let z = m.z_axis.truncate();
    let (a, b, c) = (x.length(), y.length(), z.length());
    let s = (a + b + c) / 3.0;
    let tol = 1e-4 * s;
    let ortho = x.dot(y).abs() <= tol * s && y.dot(z).abs() <= tol * s && x.dot(z).abs() <= tol * s;
    if s > 0.0 && (a - s).abs() <= tol && (b - s).abs() <= tol && (c - s).abs() <= tol && ortho {
        Some(s)
    } else {
        None
    }
}

/// Our camera for a camera-to-world transform whose camera space looks down +z with +y up,
/// `vfov` degrees vertically: mirrored horizontally when the format's raster x (the camera-space
/// direction `raster_x`) runs against ours (forward x up).
pub(crate) fn camera_from(
    c2w: &Transform,
    raster_x: Vec3,
    vfov: f32,
    (w, h): (u32, u32),
) -> Result<Camera, crate::camera::CameraError> {
    let position = c2w.point(Vec3::ZERO);
    let forward = c2w.vector(Vec3::Z).normalize_or_zero();
    let up = c2w.vector(Vec3::Y);
    let cam = Camera::new(position, position + forward, up, vfov, w, h)?;
    let flip = c2w.vector(raster_x).dot(cam.right()) < 0.0;
    Ok(cam.with_flip_x(flip))
}

/// The file a Mitsuba `<shape type="obj">` or `<shape type="ply">` names (either version's
/// files), where it names one.
pub(crate) fn mitsuba_mesh_file(n: &Node) -> Option<&str> {
    if n.tag != "shape" || !matches!(n.attr("type"), Some("obj" | "ply")) {
        return None;
    }
    n.children
        .iter()
        .find(|k| k.attr("name") == Some("filename"))
        .and_then(|k| k.attr("value"))
}

/// Mitsuba's `<lookat>` (0.5 and 3 alike): +z toward the target, +x = up x z, at `origin`; with
/// no `up`, some perpendicular one (as Mitsuba picks). The error says what is degenerate.
pub(crate) fn mitsuba_look_at(
    origin: Vec3,
    target: Vec3,
    up: Option<Vec3>,
) -> Result<Mat4, &'static str> {
    let dir = (target - origin).normalize_or_zero();
    if dir == Vec3::ZERO {
        return Err("<lookat>: origin equals target");
    }
    let up = up.unwrap_or_else(|| Frame::from_normal(dir).s);
    let left = up.cross(dir).normalize_or_zero();
    if left == Vec3::ZERO {
        return Err("<lookat>: up is parallel to the view direction");
    }
    let new_up = dir.cross(left);
    Ok(Mat4::from_cols(
        left.extend(0.0),
        new_up.extend(0.0),
        dir.extend(0.0),
        origin.extend(1.0),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_scale_needs_equal_axes_without_shear() {
        assert!(uniform_scale(&Mat4::from_scale(Vec3::splat(2.0))).is_some());
        assert!(uniform_scale(&Mat4::from_scale(Vec3::new(1.0, 2.0, 1.0))).is_none());
    }
}
