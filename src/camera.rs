//! Perspective pinhole camera: primary rays, and for light tracing the importance We, its
//! directional pdf and the raster position a direction lands on.
//!
//! A [`Scene`](crate::scene::Scene) owns one; the integrators ask it for primary rays (camera
//! subpaths) and for the pixel a light-tracing connection lands in.

use crate::geometry::{Ray, Vec2, Vec3};

/// A pinhole camera looking from `position` toward `look_at`, with an image of `width` x
/// `height` pixels (raster x right, y down).
#[derive(Clone, Debug)]
pub struct Camera {
    /// The eye point in world space.
    pub position: Vec3,
    /// The point the camera looks at.
    pub look_at: Vec3,
    /// The up direction, made orthogonal to the viewing direction (unit).
    pub up_hint: Vec3,
    /// Vertical field of view in degrees.
    pub vfov_deg: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Mirror the image horizontally (see [`Camera::with_flip_x`]).
    flip_x: bool,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    tan_x: f32,
    tan_y: f32,
    /// Area of the image rectangle on the plane at distance 1.
    plane_area: f32,
}

/// Why a camera cannot be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// A position, target or up vector with a NaN or infinite coordinate.
    #[error("camera position, look_at and up must be finite")]
    NotFinite,
    /// The target is the eye point.
    #[error("camera look_at equals its position")]
    LookAtIsPosition,
    /// The up hint is parallel to the viewing direction.
    #[error("camera up is parallel to the viewing direction")]
    UpAlongView,
    /// A vertical field of view outside (0, 179) degrees.
    #[error("camera fov must be in (0, 179) degrees, got {0}")]
    Fov(f32),
    /// A width or height of zero.
    #[error("resolution must be positive, got {0}x{1}")]
    EmptyResolution(u32, u32),
}

impl Camera {
    /// A camera from its eye point, target, up hint and vertical field of view; an error when
    /// they are not finite, `look_at` equals `position`, `up` is parallel to the view, the field
    /// of view is outside (0, 179) degrees or the resolution is empty.
    pub fn new(
        position: Vec3,
        look_at: Vec3,
        up: Vec3,
        vfov_deg: f32,
        width: u32,
        height: u32,
    ) -> Result<Camera, CameraError> {
        if !(position.is_finite() && look_at.is_finite() && up.is_finite()) {
            return Err(CameraError::NotFinite);
        }
        let forward = (look_at - position).normalize_or_zero();
        if forward == Vec3::ZERO {
            return Err(CameraError::LookAtIsPosition);
        }
        let right = forward.cross(up).normalize_or_zero();
        if right == Vec3::ZERO {
            return Err(CameraError::UpAlongView);
        }
        if !(vfov_deg > 0.0 && vfov_deg < 179.0) {
            return Err(CameraError::Fov(vfov_deg));
        }
        if width == 0 || height == 0 {
            return Err(CameraError::EmptyResolution(width, height));
        }
        let up = right.cross(forward);
        let tan_y = (vfov_deg.to_radians() * 0.5).tan();
        let tan_x = tan_y * width as f32 / height as f32;
        Ok(Camera {
            position,
            look_at,
            up_hint: up,
            vfov_deg,
            width,
            height,
            flip_x: false,
            forward,
            right,
            up,
            tan_x,
            tan_y,
            plane_area: 4.0 * tan_x * tan_y,
        })
    }

    /// The same camera at another resolution, keeping the vertical field of view (and the
    /// mirroring).
    pub fn with_resolution(&self, width: u32, height: u32) -> Result<Camera, CameraError> {
        Ok(Camera::new(
            self.position,
            self.look_at,
            self.up_hint,
            self.vfov_deg,
            width,
            height,
        )?
        .with_flip_x(self.flip_x))
    }

    /// The same camera with the image mirrored horizontally (`flip`) or not. Mirroring negates
    /// the right axis, so `ray` and `raster_of` stay inverse to each other and importance
    /// (`we`, `pdf_dir`) is unchanged.
    pub fn with_flip_x(mut self, flip: bool) -> Camera {
        if flip != self.flip_x {
            self.right = -self.right;
            self.flip_x = flip;
        }
        self
    }

    /// True when the image is mirrored: raster x grows toward `up x forward` instead of
    /// `forward x up`. Importers set it for files whose camera-to-world transform has the other
    /// handedness (pbrt-v3's left-handed camera space under a proper rotation, e.g. `LookAt`).
    pub fn flip_x(&self) -> bool {
        self.flip_x
    }

    /// Unit vector toward increasing raster x.
    pub fn right(&self) -> Vec3 {
        self.right
    }

    /// Unit viewing direction (toward `look_at`).
    pub fn forward(&self) -> Vec3 {
        self.forward
    }

    /// Primary ray through raster position (x right, y down, in pixels).
    #[inline]
    pub fn ray(&self, raster: Vec2) -> Ray {
        let sx = (2.0 * raster.x / self.width as f32 - 1.0) * self.tan_x;
        let sy = (1.0 - 2.0 * raster.y / self.height as f32) * self.tan_y;
        let d = (self.forward + sx * self.right + sy * self.up).normalize();
        Ray::new(self.position, d)
    }

    /// Raster position of world direction `d` (unit) leaving the camera, if it is on the film.
    pub fn raster_of(&self, d: Vec3) -> Option<Vec2> {
        let c = d.dot(self.forward);
        if c <= 0.0 {
            return None;
        }
        let sx = d.dot(self.right) / c / self.tan_x;
        let sy = d.dot(self.up) / c / self.tan_y;
        let x = (sx + 1.0) * 0.5 * self.width as f32;
        let y = (1.0 - sy) * 0.5 * self.height as f32;
        if x >= 0.0 && x < self.width as f32 && y >= 0.0 && y < self.height as f32 {
            Some(Vec2::new(x, y))
        } else {
            None
        }
    }

    /// Importance We(d) of the whole film, normalised so that its integral over the film's solid
    /// angle, weighted by cos, is 1: We = 1 / (A cos^4) (Veach 1997 §10.8; PBR 3rd ed. §16.1.1).
    pub fn we(&self, d: Vec3) -> f32 {
        let c = d.dot(self.forward);
        if c <= 0.0 || self.raster_of(d).is_none() {
            return 0.0;
        }
        1.0 / (self.plane_area * c * c * c * c)
    }

    /// Solid-angle density of primary ray directions when the film is sampled uniformly:
    /// 1 / (A cos^3).
    pub fn pdf_dir(&self, d: Vec3) -> f32 {
        let c = d.dot(self.forward);
        if c <= 0.0 || self.raster_of(d).is_none() {
            return 0.0;
        }
        1.0 / (self.plane_area * c * c * c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ray_and_raster_are_inverse() {
        let cam = Camera::new(
            Vec3::new(0.0, 1.0, 6.8),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::Y,
            19.5,
            64,
            48,
        )
        .unwrap();
        for (x, y) in [(0.5, 0.5), (32.0, 24.0), (63.2, 47.9), (10.0, 40.0)] {
            let r = cam.ray(Vec2::new(x, y));
            let back = cam.raster_of(r.d).unwrap();
            assert!((back.x - x).abs() < 1e-3 && (back.y - y).abs() < 1e-3);
        }
        // Center looks forward; x grows to the right, y grows downward.
        assert!((cam.ray(Vec2::new(32.0, 24.0)).d - Vec3::NEG_Z).length() < 1e-5);
        assert!(cam.ray(Vec2::new(60.0, 24.0)).d.x > 0.0);
        assert!(cam.ray(Vec2::new(32.0, 2.0)).d.y > 0.0);
    }

    #[test]
    fn flip_x_mirrors_raster_x_consistently() {
        let cam = Camera::new(Vec3::ZERO, Vec3::NEG_Z, Vec3::Y, 40.0, 64, 48).unwrap();
        let flipped = cam.clone().with_flip_x(true);
        assert!(flipped.flip_x);
        // Right-handed: looking down -z with +y up, +x is on the right; mirrored, on the left.
        assert!(cam.ray(Vec2::new(60.0, 24.0)).d.x > 0.0);
        assert!(flipped.ray(Vec2::new(60.0, 24.0)).d.x < 0.0);
        for (x, y) in [(0.5, 0.5), (32.0, 24.0), (63.2, 47.9), (10.0, 40.0)] {
            let a = cam.ray(Vec2::new(x, y)).d;
            let b = flipped.ray(Vec2::new(64.0 - x, y)).d;
            // The mirrored camera sees at (w - x, y) what the plain one sees at (x, y).
            assert!((a - b).length() < 1e-5, "{a:?} vs {b:?}");
            let back = flipped.raster_of(flipped.ray(Vec2::new(x, y)).d).unwrap();
            assert!((back.x - x).abs() < 1e-3 && (back.y - y).abs() < 1e-3);
            assert!((cam.we(a) - flipped.we(b)).abs() <= 1e-4 * cam.we(a));
        }
        // Flipping twice is the identity; a resolution change keeps the flip.
        let twice = flipped.clone().with_flip_x(false);
        assert!(
            (twice.ray(Vec2::new(60.0, 24.0)).d - cam.ray(Vec2::new(60.0, 24.0)).d).length() < 1e-6
        );
        let resized = flipped.with_resolution(32, 24).unwrap();
        assert!(resized.flip_x && resized.ray(Vec2::new(30.0, 12.0)).d.x < 0.0);
    }

    #[test]
    fn bad_cameras_are_refused() {
        assert!(Camera::new(Vec3::ZERO, Vec3::ZERO, Vec3::Y, 40.0, 8, 8).is_err());
        assert!(Camera::new(Vec3::ZERO, Vec3::Y, Vec3::Y, 40.0, 8, 8).is_err());
        assert!(Camera::new(Vec3::ZERO, Vec3::Z, Vec3::Y, 0.0, 8, 8).is_err());
        assert!(Camera::new(Vec3::ZERO, Vec3::Z, Vec3::Y, 40.0, 0, 8).is_err());
    }
}
