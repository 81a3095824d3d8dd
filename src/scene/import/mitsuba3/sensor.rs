//! The `<integrator>` (its depth limit) and the `<sensor>` with its film, filter and sampler,
//! in Mitsuba 3's conventions: a perspective camera looking down its local +z, its `fov` along
//! `fov_axis`, the image not mirrored.

use super::{Ctx, R, UNLIMITED_DEPTH};
use crate::geometry::{Transform, Vec3};
use crate::scene::import::common::camera_from;
use crate::scene::import::xml::{Node, Props};

impl Ctx {
    /// The default max depth from an `<integrator>` (Mitsuba's depth d is our d - 1).
    pub(super) fn integrator(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        let depth = match ty {
            "path" | "volpath" | "volpathmis" | "prb" | "prbvolpath" => {
                self.int(&p, "max_depth", -1)?
            }
            // Direct illumination: emitters seen, and one bounce toward them.
            "direct" => {
                for k in ["emitter_samples", "bsdf_samples", "shading_samples"] {
                    p.consume(k);
                }
                2
            }
            other => {
                self.warn(
                    n,
                    format!("integrator \"{other}\" is rendered as full global illumination"),
                );
                for c in &n.children {
                    if let Some(k) = c.attr("name") {
                        p.consume(k);
                    }
                }
                -1
            }
        };
        let ours = match depth {
            -1 => UNLIMITED_DEPTH,
            d if d >= 1 => (d - 1).min(u32::MAX as i64) as u32,
            d => {
                return Err(self.err(
                    n,
                    format!("max_depth {d}: Mitsuba renders nothing; use -1 or >= 1"),
                ));
            }
        };
        self.b.defaults.max_depth = Some(ours);
        // Russian roulette does not change the expected image.
        p.consume("rr_depth");
        if self.boolean(&p, "hide_emitters", false)? {
            self.refuse(
                n,
                "hide_emitters (directly visible emitters left out) is not supported",
            );
        }
        self.report_unused(&p, &format!("integrator \"{ty}\""));
        Ok(())
    }

    /// Our camera, resolution and default spp from a `<sensor>`.
    pub(super) fn sensor(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        if ty != "perspective" {
            self.refuse(
                n,
                format!("sensor \"{ty}\" is not supported (perspective only)"),
            );
            return Ok(());
        }
        let film = p.any_with_tag("film").into_iter().next().cloned();
        let (w, h) = match &film {
            Some(f) => self.film(f)?,
            None => (768, 576),
        };
        let aspect = w as f32 / h as f32;
        let hfov = match (p.get("fov"), self.string(&p, "focal_length")?) {
            (Some(_), Some(_)) => {
                return Err(self.err(n, "perspective: give fov or focal_length, not both"));
            }
            (Some(f), None) => {
                let fov = self.number(f)?;
                let half = (0.5 * fov).to_radians().tan();
                let axis = self.string(&p, "fov_axis")?.unwrap_or_else(|| "x".into());
                let x_from = |tan_half: f32| 2.0 * tan_half.atan();
                match axis.as_str() {
                    "x" => fov.to_radians(),
                    "y" => x_from(half * aspect),
                    "diagonal" => x_from(half / (1.0 + 1.0 / (aspect * aspect)).sqrt()),
                    "smaller" if aspect > 1.0 => x_from(half * aspect),
                    "smaller" => fov.to_radians(),
                    "larger" if aspect > 1.0 => fov.to_radians(),
                    "larger" => x_from(half * aspect),
                    other => return Err(self.err(n, format!("unknown fov_axis \"{other}\""))),
                }
            }
            (None, focal) => {
                let focal = focal.unwrap_or_else(|| "50mm".into());
                let mm: f32 = focal
                    .trim()
                    .strip_suffix("mm")
                    .and_then(|v| v.trim().parse().ok())
                    .filter(|v: &f32| *v > 0.0)
                    .ok_or_else(|| self.err(n, format!("malformed focal_length \"{focal}\"")))?;
                // A 35 mm film's diagonal, as the diagonal field of view.
                let diag = 2.0 * ((36.0f32 * 36.0 + 24.0 * 24.0).sqrt() / (2.0 * mm)).atan();
                let half = (0.5 * diag).tan();
                2.0 * (half / (1.0 + 1.0 / (aspect * aspect)).sqrt()).atan()
            }
        };
        let vfov = (2.0 * ((0.5 * hfov).tan() / aspect).atan()).to_degrees();
        if !(vfov > 0.0 && vfov < 179.0) {
            return Err(self.err(
                n,
                format!("the field of view gives {vfov} degrees vertically"),
            ));
        }
        let m = self.to_world(&p)?;
        let c2w = Transform::new(m).ok_or_else(|| self.err(n, "to_world is not invertible"))?;
        // Mitsuba's camera space: +z forward, +y up, +x toward the image's left.
        let cam =
            camera_from(&c2w, Vec3::NEG_X, vfov, (w, h)).map_err(|e| self.err(n, e.to_string()))?;
        self.b.set_camera(cam);
        for k in [
            "near_clip",
            "far_clip",
            "shutter_open",
            "shutter_close",
            "srf",
        ] {
            p.consume(k);
        }
        for k in ["principal_point_offset_x", "principal_point_offset_y"] {
            if self.float(&p, k, 0.0)? != 0.0 {
                self.warn(n, format!("{k} is not supported: the image is centred"));
            }
        }
        if let Some(s) = p.any_with_tag("sampler").into_iter().next().cloned() {
            let sp = Props::new(&s);
            let spp = self.int(&sp, "sample_count", 4)?;
            if spp < 1 {
                return Err(self.err(&s, format!("sample_count {spp} < 1")));
            }
            self.b.defaults.spp = Some(spp.min(u32::MAX as i64) as u32);
            // Any sampler converges to the same image.
            for c in &s.children {
                if let Some(k) = c.attr("name") {
                    sp.consume(k);
                }
            }
            self.report_unused(&sp, "sampler");
        } else {
            self.b.defaults.spp = Some(4);
        }
        self.report_unused(&p, "sensor \"perspective\"");
        Ok(())
    }

    /// The film's resolution; its reconstruction filter (ours is a box of one pixel) and crop
    /// window are checked.
    fn film(&mut self, f: &Node) -> R<(u32, u32)> {
        let p = Props::new(f);
        let ty = f.attr("type").unwrap_or("");
        if !matches!(ty, "hdrfilm" | "specfilm") {
            self.warn(f, format!("film \"{ty}\" is read as an hdrfilm"));
        }
        let dim = |cx: &Ctx, k: &str, d: i64| -> R<u32> {
            let v = cx.int(&p, k, d)?;
            u32::try_from(v)
                .ok()
                .filter(|v| *v >= 1)
                .ok_or_else(|| cx.err(f, format!("film {k} {v} < 1")))
        };
        let (w, h) = (dim(self, "width", 768)?, dim(self, "height", 576)?);
        let crop = [
            "crop_offset_x",
            "crop_offset_y",
            "crop_width",
            "crop_height",
        ]
        .iter()
        .any(|k| p.has(k));
        if crop {
            let (cx, cy) = (
                self.int(&p, "crop_offset_x", 0)?,
                self.int(&p, "crop_offset_y", 0)?,
            );
            let (cw, ch) = (
                self.int(&p, "crop_width", w as i64)?,
                self.int(&p, "crop_height", h as i64)?,
            );
            if (cx, cy, cw, ch) != (0, 0, w as i64, h as i64) {
                self.refuse(f, "a film crop window is not supported");
            }
        }
        for k in [
            "file_format",
            "pixel_format",
            "component_format",
            "sample_border",
            "banner",
            "compensate",
        ] {
            p.consume(k);
        }
        match p.any_with_tag("rfilter").into_iter().next() {
            Some(r) if r.attr("type") == Some("box") => {}
            Some(r) => {
                let t = r.attr("type").unwrap_or("").to_string();
                let r = r.clone();
                self.warn(&r, format!("rfilter \"{t}\": reconstructed with a box filter of one pixel"));
            }
            None => self.warn(
                f,
                "the film's default gaussian reconstruction filter: reconstructed with a box filter of one pixel",
            ),
        }
        self.report_unused(&p, &format!("film \"{ty}\""));
        Ok((w, h))
    }
}
