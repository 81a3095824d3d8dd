//! The camera and the other rendering options before `WorldBegin`: `Camera`, `Film`,
//! `Sampler`, `PixelFilter`, `Integrator`, `Accelerator`.

use super::lexer::Loc;
use super::params::ParamSet;
use super::{Parser, R};
use crate::geometry::{Mat4, Transform, Vec3};
use crate::scene::import::common::camera_from;

/// The `Camera` directive, kept until `WorldBegin` (when the film resolution is known).
pub(super) struct CameraDef {
    pub(super) ty: String,
    pub(super) params: ParamSet,
    pub(super) world_to_camera: Mat4,
    pub(super) loc: Loc,
}

impl Parser {
    /// Handles the rendering options (`Camera`, `Film`, `Sampler`, `PixelFilter`, `Integrator`,
    /// `Accelerator`); false for any other directive.
    pub(super) fn option_directive(&mut self, name: &str, loc: Loc) -> R<bool> {
        match name {
            "Camera" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let params = self.params()?;
                // pbrt-v3 names the camera's coordinate system "camera" (camera-to-world).
                if let Some(inv) = Transform::new(self.g.ctm) {
                    self.named_coords.insert("camera".into(), inv.inv);
                }
                self.camera = Some(CameraDef {
                    ty,
                    params,
                    world_to_camera: self.g.ctm,
                    loc,
                });
            }
            "Film" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                if ty != "image" {
                    self.warn(loc, format!("Film \"{ty}\" treated as \"image\""));
                }
                self.film_resolution(&ps, loc, (640, 480))?;
                if let Some(s) = self.opt_float(&ps, "scale")?
                    && s != 1.0
                {
                    self.warn(
                        loc,
                        format!("Film \"scale\" {s} is not supported; pixel values are unscaled"),
                    );
                }
                let _ = self.opt_float(&ps, "maxsampleluminance")?;
                self.report_unused(&ps, "Film");
            }
            "Sampler" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                // The sampler type does not change the expected image; only its sample count
                // becomes our default spp.
                let spp = if ty == "stratified" {
                    self.int(&ps, "xsamples", 4)? * self.int(&ps, "ysamples", 4)?
                } else {
                    self.int(&ps, "pixelsamples", 16)?
                };
                if spp < 1 {
                    return Err(self.err(
                        loc,
                        format!("Sampler: sample count must be >= 1, got {spp}"),
                    ));
                }
                self.b.defaults.spp = Some(spp.min(u32::MAX as i64) as u32);
                let _ = self.boolean(&ps, "jitter", true)?;
                let _ = self.int(&ps, "dimensions", 4)?;
                self.report_unused(&ps, &format!("Sampler \"{ty}\""));
            }
            "PixelFilter" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                ps.consume_all();
                if ty != "box" {
                    self.warn(
                        loc,
                        format!("PixelFilter \"{ty}\" is not supported; box filter used"),
                    );
                } else {
                    let xw = self.float(&ps, "xwidth", 0.5)?;
                    let yw = self.float(&ps, "ywidth", 0.5)?;
                    if xw != 0.5 || yw != 0.5 {
                        self.warn(loc, "PixelFilter \"box\": widths other than 0.5 are not supported; one-pixel box used");
                    }
                }
            }
            "Integrator" => {
                self.options_only(name, loc)?;
                let ty = self.arg_str(name)?;
                let ps = self.params()?;
                let depth = self.int(&ps, "maxdepth", 5)?;
                if depth < 0 {
                    return Err(self.err(
                        loc,
                        format!("Integrator: maxdepth must be >= 0, got {depth}"),
                    ));
                }
                self.b.defaults.max_depth = Some(depth.min(u32::MAX as i64) as u32);
                match ty.as_str() {
                    "path" | "volpath" | "bdpt" | "mlt" | "sppm" => {
                        if ty != "path" {
                            self.warn(loc, format!("Integrator \"{ty}\" rendered with our path tracer (the same expected image)"));
                        }
                    }
                    other => self.warn(
                        loc,
                        format!("Integrator \"{other}\" is not supported; our path tracer renders full global illumination up to maxdepth"),
                    ),
                }
                // Russian roulette and light selection do not change the expected image.
                let _ = self.opt_float(&ps, "rrthreshold")?;
                let _ = self.string(&ps, "lightsamplestrategy")?;
                if ps.has("pixelbounds") {
                    ps.find("pixelbounds", &["integer"]);
                    self.warn(
                        loc,
                        "Integrator \"pixelbounds\" is not supported; the whole image is rendered",
                    );
                }
                self.report_unused(&ps, &format!("Integrator \"{ty}\""));
            }
            "Accelerator" => {
                // The acceleration structure does not change the image.
                self.arg_str(name)?;
                self.params()?.consume_all();
            }
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// The `Film`'s `xresolution` and `yresolution` (`default` where left out) as the scene's
    /// resolution; its output name and physical size, which change no pixel, read and left.
    pub(super) fn film_resolution(
        &mut self,
        ps: &ParamSet,
        loc: Loc,
        default: (i64, i64),
    ) -> R<()> {
        let w = self.int(ps, "xresolution", default.0)?;
        let h = self.int(ps, "yresolution", default.1)?;
        if !(1..=65536).contains(&w) || !(1..=65536).contains(&h) {
            return Err(self.err(
                loc,
                format!("Film resolution must be 1..65536, got {w}x{h}"),
            ));
        }
        self.resolution = (w as u32, h as u32);
        let _ = self.string(ps, "filename")?; // output name: ours comes from the command line
        let _ = self.opt_float(ps, "diagonal")?; // physical film size: no effect on a pinhole
        Ok(())
    }

    /// Our camera from the `Camera` directive (or pbrt's default) and the film resolution.
    pub(super) fn build_camera(&mut self) -> R<()> {
        let (w, h) = self.resolution;
        let def = self.camera.take().unwrap_or(CameraDef {
            ty: "perspective".into(),
            params: ParamSet::default(),
            world_to_camera: Mat4::IDENTITY,
            loc: self.last_loc,
        });
        let loc = def.loc;
        if def.ty != "perspective" {
            return Err(self.err(
                loc,
                format!(
                    "Camera \"{}\" is not supported (only \"perspective\")",
                    def.ty
                ),
            ));
        }
        let ps = &def.params;
        let mut fov = self.float(ps, "fov", 90.0)?;
        if let Some(half) = self.opt_float(ps, "halffov")?
            && half > 0.0
        {
            fov = 2.0 * half;
        }
        if let Some(lr) = self.opt_float(ps, "lensradius")?
            && lr > 0.0
        {
            self.warn(
                loc,
                "Camera: depth of field (lensradius > 0) is not supported; pinhole used",
            );
        }
        let _ = self.opt_float(ps, "focaldistance")?;
        if ps.has("screenwindow") || ps.has("frameaspectratio") {
            ps.find("screenwindow", &["float"]);
            ps.find("frameaspectratio", &["float"]);
            self.warn(loc, "Camera: screenwindow / frameaspectratio are not supported; the window follows the resolution");
        }
        let _ = self.opt_float(ps, "shutteropen")?;
        let _ = self.opt_float(ps, "shutterclose")?;
        self.report_unused(ps, "Camera \"perspective\"");
        if !(fov > 0.0 && fov < 179.0) {
            return Err(self.err(
                loc,
                format!("Camera fov must be in (0, 179) degrees, got {fov}"),
            ));
        }
        // pbrt's fov spans the shorter image axis; ours is vertical.
        let vfov = if w >= h {
            fov
        } else {
            2.0 * ((0.5 * fov.to_radians()).tan() * h as f32 / w as f32)
                .atan()
                .to_degrees()
        };
        let c2w = Transform::new(def.world_to_camera)
            .ok_or_else(|| self.err(loc, "the camera transform is singular or not finite"))?;
        let c2w = Transform {
            m: c2w.inv,
            inv: c2w.m,
        };
        // pbrt's raster x runs along camera +x; ours along forward x up. Mirror when they differ.
        let cam = camera_from(&c2w, Vec3::X, vfov, (w, h))
            .map_err(|m| self.err(loc, format!("Camera: {m}")))?;
        self.b.set_camera(cam);
        Ok(())
    }
}

/// pbrt-v3 `LookAt`: the world-to-camera matrix of a camera at `eye` looking at `at`, with
/// camera-to-world columns (up x dir, dir x right, dir, eye).
pub(super) fn look_at(eye: Vec3, at: Vec3, up: Vec3) -> Option<Mat4> {
    let dir = (at - eye).normalize_or_zero();
    let right = up.normalize_or_zero().cross(dir).normalize_or_zero();
    if dir == Vec3::ZERO || right == Vec3::ZERO || !eye.is_finite() {
        return None;
    }
    let new_up = dir.cross(right);
    let c2w = Mat4::from_cols(
        right.extend(0.0),
        new_up.extend(0.0),
        dir.extend(0.0),
        eye.extend(1.0),
    );
    Some(c2w.inverse())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_is_pbrts() {
        // pbrt-v3: camera +x = normalize(up x dir).
        let w2c = look_at(Vec3::ZERO, Vec3::Z, Vec3::Y).unwrap();
        let c2w = w2c.inverse();
        assert!((c2w.transform_vector3(Vec3::X) - Vec3::X).length() < 1e-6);
        assert!((c2w.transform_vector3(Vec3::Z) - Vec3::Z).length() < 1e-6);
    }
}
