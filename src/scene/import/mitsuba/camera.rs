//! The `<integrator>` (its depth limit) and the `<sensor>` with its film and sampler.

use super::{Ctx, R, UNLIMITED_DEPTH};
use crate::geometry::{Transform, Vec3};
use crate::scene::import::common::camera_from;
use crate::scene::import::xml::{Node, Props};

impl Ctx {
    /// Takes the default max depth from an `<integrator>`.
    pub(super) fn integrator(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        if matches!(ty, "adaptive" | "irrcache" | "multichannel") {
            self.warn(
                n,
                format!("integrator \"{ty}\" is not supported; its nested integrator is used"),
            );
            let inner = p.objects("integrator");
            return match inner.first() {
                Some(i) => self.integrator(i),
                None => Err(self.err(n, format!("integrator \"{ty}\" has no nested integrator"))),
            };
        }
        let depth = self.int(&p, "maxDepth", -1)?;
        let ours = match depth {
            -1 => {
                self.warn(
                    n,
                    format!("maxDepth -1 (unlimited) is rendered with max depth {UNLIMITED_DEPTH}"),
                );
                UNLIMITED_DEPTH
            }
            d if d >= 1 => {
                // Mitsuba counts the emitter hit as one more vertex: maxDepth 2 is direct light.
                if d == 1 {
                    self.warn(n, "maxDepth 1 shows only directly visible emitters in Mitsuba (our max depth 0)");
                }
                (d - 1).min(u32::MAX as i64) as u32
            }
            d => {
                return Err(self.err(
                    n,
                    format!("maxDepth {d}: Mitsuba renders nothing; use -1 or >= 1"),
                ));
            }
        };
        self.b.defaults.max_depth = Some(ours);
        match ty {
            "path" | "volpath" | "volpath_simple" | "bdpt" | "pssmlt" | "mlt" | "erpt" | "ptracer" | "sppm" | "ppm" => {
                if ty != "path" {
                    self.warn(n, format!("integrator \"{ty}\" rendered with our path tracer (the same expected image)"));
                }
            }
            other => self.warn(
                n,
                format!("integrator \"{other}\" is not supported; our path tracer renders full global illumination"),
            ),
        }
        // Russian roulette does not change the expected image. `strictNormals` stops paths
        // where geometric and shading normals disagree; our BSDFs already return nothing there.
        p.consume("rrDepth");
        p.consume("strictNormals");
        if self.boolean(&p, "hideEmitters", false)? {
            self.warn(
                n,
                "hideEmitters is not supported; directly visible emitters are shown",
            );
        }
        self.report_unused(&p, &format!("integrator \"{ty}\""));
        Ok(())
    }

    /// Our camera, resolution and default spp from a `<sensor>`.
    pub(super) fn sensor(&mut self, n: &Node) -> R<()> {
        let p = Props::new(n);
        let ty = n.attr("type").unwrap_or("");
        match ty {
            "perspective" => {}
            "thinlens" => {
                self.warn(
                    n,
                    "sensor \"thinlens\": depth of field is not supported; pinhole used",
                );
                p.consume("apertureRadius");
                p.consume("focusDistance");
            }
            other => {
                return Err(self.err(
                    n,
                    format!("sensor \"{other}\" is not supported (only \"perspective\")"),
                ));
            }
        }
        let c2w = self.to_world(&p)?;
        // Film.
        let (mut w, mut h) = (768u32, 576u32);
        if let Some(f) = p.objects("film").first() {
            let fp = Props::new(f);
            let fw = self.int(&fp, "width", 768)?;
            let fh = self.int(&fp, "height", 576)?;
            if !(1..=65536).contains(&fw) || !(1..=65536).contains(&fh) {
                return Err(self.err(f, format!("film size must be 1..65536, got {fw}x{fh}")));
            }
            (w, h) = (fw as u32, fh as u32);
            match fp.any_with_tag("rfilter").first() {
                Some(r) if r.attr("type") == Some("box") => {}
                Some(r) => {
                    let t = r.attr("type").unwrap_or("?");
                    self.warn(r, format!("rfilter \"{t}\" is not supported; box filter used"));
                }
                None => self.warn(f, "Mitsuba's default gaussian reconstruction filter is not supported; box filter used"),
            }
            for k in ["cropOffsetX", "cropOffsetY", "cropWidth", "cropHeight"] {
                if fp.has(k) {
                    fp.consume(k);
                    self.warn(
                        f,
                        "film crop window is not supported; the whole image is rendered",
                    );
                }
            }
            // Output format settings do not change the rendered radiance.
            for k in [
                "fileFormat",
                "pixelFormat",
                "componentFormat",
                "gamma",
                "banner",
                "attachLog",
                "highQualityEdges",
                "label",
                "tonemapMethod",
                "exposure",
                "key",
                "burn",
                "channelNames",
            ] {
                fp.consume(k);
            }
            self.report_unused(&fp, &format!("film \"{}\"", f.attr("type").unwrap_or("?")));
        }
        if let Some(s) = p.objects("sampler").first() {
            let sp = Props::new(s);
            let spp = self.int(&sp, "sampleCount", 4)?;
            if spp < 1 {
                return Err(self.err(s, format!("sampleCount must be >= 1, got {spp}")));
            }
            self.b.defaults.spp = Some(spp.min(u32::MAX as i64) as u32);
            // Sampler type, dimension and scramble settings do not change the expected image.
            sp.consume("dimension");
            sp.consume("scramble");
            self.report_unused(
                &sp,
                &format!("sampler \"{}\"", s.attr("type").unwrap_or("?")),
            );
        }
        // Field of view along fovAxis, or from a 35 mm-equivalent focal length (on the diagonal
        // of the 36 x 24 mm frame, as Mitsuba does).
        let axis = self.string(&p, "fovAxis")?.unwrap_or_else(|| "x".into());
        let (fov, axis) = match p.get("fov") {
            Some(f) => (self.num_of(f)?, axis),
            None => {
                let fl = self
                    .string(&p, "focalLength")?
                    .unwrap_or_else(|| "50mm".into());
                let mm = fl
                    .trim()
                    .trim_end_matches("mm")
                    .trim()
                    .parse::<f32>()
                    .ok()
                    .filter(|v| *v > 0.0)
                    .ok_or_else(|| self.err(n, format!("malformed focalLength '{fl}'")))?;
                let diag = (36.0f32 * 36.0 + 24.0 * 24.0).sqrt();
                (
                    (2.0 * (diag / (2.0 * mm)).atan()).to_degrees(),
                    "diagonal".into(),
                )
            }
        };
        if !(fov > 0.0 && fov < 180.0) {
            return Err(self.err(n, format!("fov must be in (0, 180) degrees, got {fov}")));
        }
        let (wf, hf) = (w as f32, h as f32);
        let t = (0.5 * fov.to_radians()).tan();
        // tan(vfov / 2) from tan(fov / 2) on the given axis.
        let tan_v = match axis.as_str() {
            "x" => t * hf / wf,
            "y" => t,
            "diagonal" => t * hf / (wf * wf + hf * hf).sqrt(),
            "smaller" => {
                if w < h {
                    t * hf / wf
                } else {
                    t
                }
            }
            "larger" => {
                if w > h {
                    t * hf / wf
                } else {
                    t
                }
            }
            other => return Err(self.err(n, format!("unknown fovAxis \"{other}\""))),
        };
        let vfov = 2.0 * tan_v.atan().to_degrees();
        for k in ["nearClip", "farClip", "shutterOpen", "shutterClose"] {
            p.consume(k);
        }
        self.report_unused(&p, &format!("sensor \"{ty}\""));
        let c2w =
            Transform::new(c2w).ok_or_else(|| self.err(n, "the sensor transform is singular"))?;
        // Mitsuba's raster x runs along camera -x.
        let cam = camera_from(&c2w, Vec3::NEG_X, vfov, (w, h))
            .map_err(|m| self.err(n, format!("sensor: {m}")))?;
        self.b.set_camera(cam);
        Ok(())
    }
}
