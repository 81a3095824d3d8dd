//! The techniques (s, t) of a pixel sample's traced subpaths: hitting an emitter (s = 0),
//! next-event estimation (s = 1), connecting two subpath vertices, and light tracing (t = 1).

use super::SampleSink;
use super::vertex::{Kind, Vertex, dir_to};
use super::weights::{Connection, report, report_alone};
use super::workspace::Workspace;
use crate::camera::Camera;
use crate::film::RayStats;
use crate::geometry::{Rgb, Vec3};
use crate::material::Mode;
use crate::sampler::Sampler;
use crate::scene::{NO_LIGHT, Scene};

/// Every technique of the traced (or loaded) subpaths of a pixel sample, reported to `sink`;
/// `cam_sampler` gives next-event estimation its numbers.
pub(crate) fn connect_all<S: SampleSink + ?Sized>(
    scene: &Scene,
    pixel: (u32, u32),
    max_depth: u32,
    cam_sampler: &mut Sampler,
    ws: &mut Workspace,
    sink: &mut S,
    stats: &mut RayStats,
) {
    ws.prepare(scene, sink.heuristic());
    let n_c = ws.cam.len();
    let n_l = ws.light.len();
    let max_d = max_depth as usize;
    for t in 1..=max_d + 2 {
        for s in 0..=max_d + 2 - t {
            if s + t < 2 {
                continue;
            }
            let depth = (s + t - 2) as u32;
            let zero = sink.wants_zero_samples(depth);
            if t == 1 {
                if s <= n_l {
                    connect_to_camera(scene, ws, s, depth, sink, stats);
                }
                continue;
            }
            if t > n_c {
                if zero {
                    sink.unsampled(pixel, depth, s as u32);
                }
                continue;
            }
            let produced = match s {
                0 => hit_emitter(scene, ws, t, depth, pixel, zero, sink),
                1 => next_event(scene, ws, t, depth, pixel, cam_sampler, zero, sink, stats),
                _ => s <= n_l && connect(scene, ws, s, t, depth, pixel, zero, sink, stats),
            };
            if !produced && zero {
                sink.unsampled(pixel, depth, s as u32);
            }
        }
    }
}

/// Technique (0, t): z_{t-1} lies on an emitter. Returns whether the technique produced a path
/// (a camera subpath ending on a non-emitter is a zero-contribution sample only this technique
/// could make).
pub(super) fn hit_emitter<S: SampleSink + ?Sized>(
    scene: &Scene,
    ws: &mut Workspace,
    t: usize,
    depth: u32,
    pixel: (u32, u32),
    zero: bool,
    sink: &mut S,
) -> bool {
    let z = &ws.cam[t - 1];
    let zp = &ws.cam[t - 2];
    let w_out = z.wo.w;
    let contribution = if z.light == NO_LIGHT {
        Rgb::ZERO
    } else {
        z.beta * scene.lights[z.light as usize].le(z.ng, w_out)
    };
    if contribution == Rgb::ZERO {
        // A camera subpath that does not end on (the front of) an emitter: a zero-contribution
        // sample only this technique could make (Cailleau et al. §V-C, Fig. 4 bottom left).
        if zero {
            report_alone(ws, sink, 0, t, depth, pixel);
        }
        return true;
    }
    let light = &scene.lights[z.light as usize];
    let pmf = scene.light_pmf(z.light) as f64;
    let (pdf_pos, pdf_dir) = light.pdf_le(z.ng, w_out);
    // The camera-side vertex treated as a light vertex: emission densities from the light side.
    let mut v0 = *z;
    v0.kind = Kind::Light;
    v0.q = 1.0;
    v0.pdf_fwd = (pmf * pdf_pos as f64) as f32;
    let c = Connection {
        pe_y1: 0.0,
        pe_y2: 0.0,
        pl_z1: v0.pdf_fwd,
        pl_z2: v0.area_density(pdf_dir, zp),
        q1: if t >= 3 {
            let (wi, _) = dir_to(zp.p, z.p);
            (pmf as f32) * zp.to_area(light.pdf_li(zp.p, wi), z)
        } else {
            0.0
        },
    };
    // v_0 is cam[t-1]; its own light-side density is pl_z1 (set above), pe is its pdf_fwd.
    report(ws, sink, None, 0, t, &c, depth, pixel, contribution);
    true
}

/// Technique (1, t >= 2): next-event estimation at z_{t-1}.
#[allow(clippy::too_many_arguments)]
pub(super) fn next_event<S: SampleSink + ?Sized>(
    scene: &Scene,
    ws: &mut Workspace,
    t: usize,
    depth: u32,
    pixel: (u32, u32),
    sampler: &mut Sampler,
    zero: bool,
    sink: &mut S,
    stats: &mut RayStats,
) -> bool {
    let z = &ws.cam[t - 1];
    if z.delta || z.bsdf.is_black() {
        return false;
    }
    let u_light = sampler.next_1d();
    let u = sampler.next_2d();
    let Some((li, pmf)) = scene.sample_light(u_light) else {
        return false;
    };
    let light = &scene.lights[li as usize];
    let Some(ls) = light.sample_li(z.p, u) else {
        return false;
    };
    let zp = &ws.cam[t - 2];
    let (f, dirs) = z.bsdf.eval_local(&z.wo, ls.wi, Mode::Radiance);
    let contribution = z.beta * f * ls.le * (ls.wi.dot(z.ns).abs() / (pmf * ls.pdf));
    // Zero-contribution samples (occluded, or a zero BSDF / emission) are weighted as paths only
    // this technique could make (W = e_s): exact for occluded connections (every other technique
    // would have stopped at the occluder), and for the rest it keeps E[A] 1 = n, which is what
    // the direct estimator's consistency needs, without a visibility ray or densities.
    let visible = contribution != Rgb::ZERO && {
        stats.shadow += 1;
        !scene.occluded(z.p, z.ng, ls.p, ls.n)
    };
    if !visible {
        if zero {
            report_alone(ws, sink, 1, t, depth, pixel);
        }
        return true;
    }
    let (pdf_fwd, pdf_rev) = z.bsdf.pdfs(dirs.as_ref());
    let mut v0 = Vertex::endpoint(Kind::Light, ls.p, ls.n, Rgb::ONE, 0.0);
    v0.light = li;
    v0.delta_pos = ls.delta;
    let (pdf_pos, pdf_dir) = light.pdf_le(ls.n, -ls.wi);
    v0.pdf_fwd = pmf * pdf_pos;
    let c = Connection {
        pe_y1: if ls.delta {
            0.0
        } else {
            z.area_density(pdf_fwd, &v0)
        },
        pe_y2: 0.0,
        pl_z1: v0.area_density(pdf_dir, z),
        pl_z2: ws.q_as(z, 1) * z.to_area(pdf_rev, zp),
        q1: if ls.delta {
            pmf
        } else {
            z.to_area(pmf * ls.pdf, &v0)
        },
    };
    ws.last_nee = Some(v0);
    report(ws, sink, Some(&v0), 1, t, &c, depth, pixel, contribution);
    true
}

/// Technique (s >= 2, t >= 2): connect y_{s-1} and z_{t-1}.
#[allow(clippy::too_many_arguments)]
pub(super) fn connect<S: SampleSink + ?Sized>(
    scene: &Scene,
    ws: &mut Workspace,
    s: usize,
    t: usize,
    depth: u32,
    pixel: (u32, u32),
    zero: bool,
    sink: &mut S,
    stats: &mut RayStats,
) -> bool {
    let y = &ws.light[s - 1];
    let z = &ws.cam[t - 1];
    if y.delta || z.delta || y.bsdf.is_black() || z.bsdf.is_black() {
        return false;
    }
    let yp = &ws.light[s - 2];
    let zp = &ws.cam[t - 2];
    let (w_yz, d2) = dir_to(y.p, z.p);
    if !(d2 > 0.0) {
        return false;
    }
    let (fy, y_dirs) = y.bsdf.eval_local(&y.wo, w_yz, Mode::Importance);
    let (fz, z_dirs) = z.bsdf.eval_local(&z.wo, -w_yz, Mode::Radiance);
    let g = w_yz.dot(y.ns).abs() * w_yz.dot(z.ns).abs() / d2;
    let contribution = y.beta * fy * fz * z.beta * g;
    // Zero-contribution samples (occluded, or a zero BSDF / emission) are weighted as paths only
    // this technique could make (W = e_s): exact for occluded connections (every other technique
    // would have stopped at the occluder), and for the rest it keeps E[A] 1 = n, which is what
    // the direct estimator's consistency needs, without a visibility ray or densities.
    let visible = contribution != Rgb::ZERO && {
        stats.shadow += 1;
        !scene.occluded(y.p, y.ng, z.p, z.ng)
    };
    if !visible {
        if zero {
            report_alone(ws, sink, s, t, depth, pixel);
        }
        return true;
    }
    // y's densities toward z and back, z's likewise.
    let (y_to_z, y_back) = y.bsdf.pdfs(y_dirs.as_ref());
    let (z_to_y, z_back) = z.bsdf.pdfs(z_dirs.as_ref());
    let c = Connection {
        pe_y1: z.area_density(z_to_y, y),
        // y samples y_{s-2} as camera vertex t, z samples z_{t-2} as light vertex s.
        pe_y2: ws.q_as(y, t) * y.to_area(y_back, yp),
        pl_z1: y.area_density(y_to_z, z),
        pl_z2: ws.q_as(z, s) * z.to_area(z_back, zp),
        q1: ws.q1,
    };
    report(ws, sink, None, s, t, &c, depth, pixel, contribution);
    true
}

/// Technique (s >= 1, 1): connect y_{s-1} to the camera and report it for the pixel it lands in.
pub(super) fn connect_to_camera<S: SampleSink + ?Sized>(
    scene: &Scene,
    ws: &mut Workspace,
    s: usize,
    depth: u32,
    sink: &mut S,
    stats: &mut RayStats,
) {
    let y = &ws.light[s - 1];
    // A point light seen directly through the pinhole, (1, 1) with y_0 a delta in position, is a
    // path of two fixed points: no other technique can make it (the camera cannot hit a point,
    // so the path tracer and (0, t) never see point lights), and it would put the light's
    // intensity into one pixel that only light tracing brightens. Point lights are invisible to
    // the camera, as in pbrt-v3, whose BDPT never runs (1, 1) (PBR 3rd ed. §16.3).
    if y.delta || y.delta_pos || (s >= 2 && y.bsdf.is_black()) {
        return;
    }
    let cam: &Camera = &scene.camera;
    let (w_cy, d2) = dir_to(cam.position, y.p);
    let Some(raster) = cam.raster_of(w_cy) else {
        return;
    };
    let pixel = (
        (raster.x as u32).min(cam.width - 1),
        (raster.y as u32).min(cam.height - 1),
    );
    let we = cam.we(w_cy);
    let cos_cam = w_cy.dot(cam.forward());
    let w_yc = -w_cy;
    // y's value toward the camera, and (s >= 2) its directions for the density back.
    let (f, cos_y, y_dirs) = if s == 1 {
        let light = &scene.lights[y.light as usize];
        (light.le(y.ng, w_yc), y.abs_cos_ng(w_yc), None)
    } else {
        let (f, dirs) = y.bsdf.eval_local(&y.wo, w_yc, Mode::Importance);
        (f, w_yc.dot(y.ns).abs(), dirs)
    };
    let contribution = y.beta * f * (cos_y * we * cos_cam / d2);
    // A zero-contribution light-tracing sample (occluded, or a zero BSDF) is weighted as a path
    // only light tracing could make (see `connect`): for the pixel it is one of the N_L - h light
    // paths that did not reach it, which the solver counts.
    if contribution == Rgb::ZERO {
        return;
    }
    stats.shadow += 1;
    if scene.occluded(y.p, y.ng, cam.position, Vec3::ZERO) {
        return;
    }
    let z0 = &ws.cam[0];
    let pe_y1 = z0.area_density(cam.pdf_dir(w_cy), y);
    let pe_y2 = if s >= 2 {
        ws.q_as(y, 1) * y.to_area(y.bsdf.pdf_back(y_dirs.as_ref()), &ws.light[s - 2])
    } else {
        0.0
    };
    let q1 = if s >= 2 { ws.q1 } else { 0.0 };
    let c = Connection {
        pe_y1,
        pe_y2,
        pl_z1: 0.0,
        pl_z2: 0.0,
        q1,
    };
    report(ws, sink, None, s, 1, &c, depth, pixel, contribution);
}
