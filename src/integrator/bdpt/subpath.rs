//! The random walks: camera and light subpaths, each vertex with its densities in both
//! directions and, with roulette on, its continuation probability.

use super::vertex::{Kind, Vertex, continuation_at, dir_to};
use super::workspace::Workspace;
use crate::film::RayStats;
use crate::geometry::{Ray, Rgb, Vec2, Vec3};
use crate::material::{Bsdf, Mode};
use crate::sampler::Sampler;
use crate::scene::Scene;

/// Extends `path` by a random walk from `ray`. `pdf_dir` is the solid-angle density with which
/// the last vertex of `path` sampled `ray.d`.
#[allow(clippy::too_many_arguments)]
fn random_walk(
    scene: &Scene,
    mut ray: Ray,
    mut beta: Rgb,
    mut pdf_dir: f32,
    sampler: &mut Sampler,
    mode: Mode,
    roulette_from: usize,
    max_vertices: usize,
    path: &mut Vec<Vertex>,
    stats: &mut RayStats,
) {
    while path.len() < max_vertices {
        stats.closest += 1;
        let Some(hit) = scene.intersect(&ray) else {
            break;
        };
        let prev = path.len() - 1;
        let bsdf = Bsdf::new(
            &scene.materials[hit.material as usize],
            hit.ng,
            hit.ns,
            hit.uv,
        );
        let mut v = Vertex {
            kind: Kind::Surface,
            p: hit.p,
            ng: hit.ng,
            ns: hit.ns,
            bsdf,
            wo: bsdf.outgoing(dir_to(hit.p, path[prev].p).0),
            light: hit.light,
            beta,
            pdf_fwd: 0.0,
            pdf_rev: 0.0,
            q: 1.0,
            rr: if roulette_from == usize::MAX {
                1.0
            } else {
                bsdf.continuation()
            },
            delta: bsdf.is_delta(),
            delta_pos: false,
            material: hit.material,
            uv: hit.uv,
        };
        v.pdf_fwd = path[prev].area_density(pdf_dir, &v);
        v.q = continuation_at(&v, path.len(), roulette_from);
        let q = v.q;
        path.push(v);
        if bsdf.is_black() {
            break;
        }
        // Russian roulette with the vertex's albedo estimate, as SmallVCM's random walks do
        // (Georgiev et al. 2012 fold q into both directions' densities).
        if q < 1.0 && sampler.next_1d() >= q {
            break;
        }
        let wo = -ray.d;
        let u_lobe = sampler.next_1d();
        let u = sampler.next_2d();
        let Some(s) = bsdf.sample(wo, u_lobe, u, mode) else {
            break;
        };
        let cur = path.len() - 1;
        // Density of the previous vertex when this one samples toward it. A specular event's
        // solid-angle density is 1 both ways, converted to area like any other (module
        // documentation).
        let (pdf_fwd, pdf_rev) = if s.delta {
            (1.0, 1.0)
        } else {
            (s.pdf, s.pdf_rev)
        };
        path[prev].pdf_rev = path[cur].to_area(pdf_rev, &path[prev]);
        beta *= s.f * (s.wi.dot(hit.ns).abs() / (s.pdf * q));
        if beta == Rgb::ZERO {
            break;
        }
        pdf_dir = pdf_fwd;
        ray = Scene::spawn_ray(hit.p, hit.ng, s.wi);
    }
}

/// Traces the camera subpath of a primary ray through raster position `raster`.
pub fn camera_subpath(
    scene: &Scene,
    raster: Vec2,
    sampler: &mut Sampler,
    max_depth: u32,
    ws: &mut Workspace,
    stats: &mut RayStats,
) {
    let cam = &scene.camera;
    let ray = cam.ray(raster);
    ws.cam.clear();
    ws.cam.push(Vertex::endpoint(
        Kind::Camera,
        cam.position,
        Vec3::ZERO,
        Rgb::ONE,
        1.0,
    ));
    let pdf_dir = cam.pdf_dir(ray.d);
    random_walk(
        scene,
        ray,
        Rgb::ONE,
        pdf_dir,
        sampler,
        Mode::Radiance,
        ws.roulette_from,
        max_depth as usize + 2,
        &mut ws.cam,
        stats,
    );
}

/// Traces a light subpath: a light chosen by power, an emitted ray, a random walk.
pub fn light_subpath(
    scene: &Scene,
    sampler: &mut Sampler,
    max_depth: u32,
    ws: &mut Workspace,
    stats: &mut RayStats,
) {
    ws.light.clear();
    let u_light = sampler.next_1d();
    let u_pos = sampler.next_2d();
    let u_dir = sampler.next_2d();
    let Some((li, pmf)) = scene.sample_light(u_light) else {
        return;
    };
    let light = &scene.lights[li as usize];
    let Some(e) = light.sample_le(u_pos, u_dir) else {
        return;
    };
    let mut y0 = Vertex::endpoint(
        Kind::Light,
        e.p,
        e.n,
        Rgb::splat(1.0 / (pmf * e.pdf_pos)),
        pmf * e.pdf_pos,
    );
    y0.light = li;
    y0.delta_pos = light.is_delta();
    ws.light.push(y0);
    let beta = e.le * (y0.abs_cos_ng(e.dir) / (pmf * e.pdf_pos * e.pdf_dir));
    if beta == Rgb::ZERO {
        return;
    }
    let ray = Scene::spawn_ray(e.p, e.n, e.dir);
    random_walk(
        scene,
        ray,
        beta,
        e.pdf_dir,
        sampler,
        Mode::Importance,
        ws.roulette_from,
        max_depth as usize + 1,
        &mut ws.light,
        stats,
    );
}

/// The camera subpath of a pixel sample: a raster position in `pixel`, then the walk.
pub(crate) fn pixel_camera_subpath(
    scene: &Scene,
    pixel: (u32, u32),
    sampler: &mut Sampler,
    max_depth: u32,
    ws: &mut Workspace,
    stats: &mut RayStats,
) {
    let film = sampler.next_2d();
    let raster = Vec2::new(pixel.0 as f32 + film.x, pixel.1 as f32 + film.y);
    camera_subpath(scene, raster, sampler, max_depth, ws, stats);
}
