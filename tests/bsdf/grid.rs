//! Spherical grid: binning of sampled directions and numerical integration of pdfs over the bins.

use super::stats::*;
use std::f64::consts::PI as PI64;

use omis::geometry::{Frame, Vec2, Vec3};
use omis::material::{Bsdf, Lobe, Mode};
use omis::sampler::Pcg32;

// ================================================================================================
// Spherical grid: binning of directions and numerical integration over the bins
// ================================================================================================

pub const N_THETA: usize = 20;
pub const N_PHI: usize = 24;
/// Sub-cells per bin and per dimension, each integrated by 2 x 2 Gauss-Legendre. (The midpoint
/// rule is not enough: it under-integrates the Phong n = 200 peak by 3e-4 of its mass, which the
/// chi2 test, with its "sample failed" cell, detects at 3e5 samples.)
pub const SUB: usize = 8;
/// Sub-cells that a horizon (a discontinuity of the pdf) crosses are split REFINE x REFINE times,
/// DEPTH times over, so the quadrature stays accurate across the cut.
pub const REFINE: usize = 8;
pub const DEPTH: u32 = 2;

/// Bins over the whole sphere in a frame whose pole is (usually) the mirror direction, where the
/// glossy lobes peak: theta edges at pi (i / N_THETA)^2 give fine rings around the peak and coarse
/// ones far from it; uniform in phi. Bins are integrated in (cos theta, phi), whose Jacobian is 1.
pub struct Grid {
    pub frame: Frame,
    /// Normals of the great circles where the pdf may jump (geometric and shading horizons).
    pub horizons: Vec<Vec3>,
}

impl Grid {
    pub fn new(pole: Vec3, horizons: &[Vec3]) -> Grid {
        Grid {
            frame: Frame::from_normal(pole.normalize()),
            horizons: horizons.to_vec(),
        }
    }

    /// Pole at the mirror direction of wo about the shading normal; for a rough dielectric at
    /// the refracted one, where most of its density lies (the rings far from the pole are too
    /// coarse for a sharp transmission lobe).
    pub fn for_bsdf(bsdf: &Bsdf, wo: Vec3) -> Grid {
        let ns = bsdf.frame.n;
        let r = 2.0 * wo.dot(ns) * ns - wo;
        let pole = match bsdf.lobe {
            Lobe::RoughDielectric { eta, .. } => {
                let cos_o = wo.dot(ns);
                let (eta, n) = if cos_o > 0.0 {
                    (eta, ns)
                } else {
                    (1.0 / eta, -ns)
                };
                let c = cos_o.abs();
                let sin2_t = (1.0 - c * c) / (eta * eta);
                if sin2_t < 1.0 {
                    -wo / eta + n * (c / eta - (1.0 - sin2_t).sqrt())
                } else {
                    r
                }
            }
            _ => r,
        };
        Grid::new(pole, &[bsdf.ng, ns])
    }

    pub fn cells(&self) -> usize {
        N_THETA * N_PHI
    }

    pub fn cos_edge(i: usize) -> f64 {
        let t = i as f64 / N_THETA as f64;
        (PI64 * t * t).cos()
    }

    pub fn phi_edge(j: usize) -> f64 {
        -PI64 + 2.0 * PI64 * j as f64 / N_PHI as f64
    }

    pub fn cell_of(&self, w: Vec3) -> usize {
        let l = self.frame.to_local(w);
        let (x, y, z) = (l.x as f64, l.y as f64, l.z as f64);
        let theta = (x * x + y * y).sqrt().atan2(z);
        let t = (theta / PI64).max(0.0).sqrt();
        let i = ((t * N_THETA as f64) as usize).min(N_THETA - 1);
        let phi = y.atan2(x);
        let j = (((phi + PI64) / (2.0 * PI64) * N_PHI as f64) as usize).min(N_PHI - 1);
        i * N_PHI + j
    }

    pub fn dir(&self, z: f64, phi: f64) -> Vec3 {
        let r = (1.0 - z * z).max(0.0).sqrt();
        let l = Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
        self.frame.to_world(l)
    }

    /// Direction at polar coordinates given as (z, sqrt(1 - z^2)) and (cos phi, sin phi).
    pub fn dir_at(&self, (z, r): (f64, f64), (c, s): (f64, f64)) -> Vec3 {
        self.frame
            .to_world(Vec3::new((r * c) as f32, (r * s) as f32, z as f32))
    }

    /// Integral of g over z in [z0, z1], phi in [p0, p1], split into n x n sub-cells with 2 x 2
    /// Gauss-Legendre each; sub-cells whose corners lie on different sides of a horizon are
    /// split again (`depth` more times).
    #[allow(clippy::too_many_arguments)]
    pub fn integrate_rect(
        &self,
        g: &impl Fn(Vec3) -> f64,
        z0: f64,
        z1: f64,
        p0: f64,
        p1: f64,
        n: usize,
        depth: u32,
    ) -> f64 {
        // 2-point Gauss-Legendre nodes at the centre +- h / (2 sqrt 3), weights h / 2.
        const D: f64 = 0.5 / 1.732_050_807_568_877_2;
        let dz = (z1 - z0) / n as f64;
        let dp = (p1 - p0) / n as f64;
        let zr = |z: f64| (z, (1.0 - z * z).max(0.0).sqrt());
        let cs = |p: f64| (p.cos(), p.sin());
        // Horizon sides of the sub-cell corners (bit k: above horizon k).
        let corner_side: Vec<u32> = if depth > 0 {
            let zs: Vec<_> = (0..=n).map(|a| zr(z0 + a as f64 * dz)).collect();
            let ps: Vec<_> = (0..=n).map(|b| cs(p0 + b as f64 * dp)).collect();
            zs.iter()
                .flat_map(|&z| ps.iter().map(move |&p| (z, p)))
                .map(|(z, p)| {
                    let d = self.dir_at(z, p);
                    self.horizons
                        .iter()
                        .enumerate()
                        .fold(0, |m, (k, h)| m | (u32::from(d.dot(*h) > 0.0) << k))
                })
                .collect()
        } else {
            Vec::new()
        };
        let zq: Vec<_> = (0..2 * n)
            .map(|k| zr(z0 + (k / 2) as f64 * dz + (0.5 + if k % 2 == 0 { -D } else { D }) * dz))
            .collect();
        let pq: Vec<_> = (0..2 * n)
            .map(|k| cs(p0 + (k / 2) as f64 * dp + (0.5 + if k % 2 == 0 { -D } else { D }) * dp))
            .collect();
        let mut sum = 0.0;
        for a in 0..n {
            for b in 0..n {
                if depth > 0 {
                    let i = a * (n + 1) + b;
                    let c = corner_side[i];
                    let straddles = corner_side[i + 1] != c
                        || corner_side[i + n + 1] != c
                        || corner_side[i + n + 2] != c;
                    if straddles {
                        let (za, pa) = (z0 + a as f64 * dz, p0 + b as f64 * dp);
                        sum += self.integrate_rect(g, za, za + dz, pa, pa + dp, REFINE, depth - 1);
                        continue;
                    }
                }
                let mut cell = 0.0;
                for &z in &zq[2 * a..2 * a + 2] {
                    for &p in &pq[2 * b..2 * b + 2] {
                        cell += g(self.dir_at(z, p));
                    }
                }
                sum += 0.25 * cell * dz * dp;
            }
        }
        sum
    }

    /// Integral of g (a density in solid angle) over every bin.
    pub fn integrate(&self, g: &impl Fn(Vec3) -> f64) -> Vec<f64> {
        let mut out = Vec::with_capacity(self.cells());
        for i in 0..N_THETA {
            // Bin i spans theta in [theta_i, theta_i+1], i.e. cos theta in [cos_edge(i+1), cos_edge(i)].
            let (z0, z1) = (Grid::cos_edge(i + 1), Grid::cos_edge(i));
            for j in 0..N_PHI {
                let (p0, p1) = (Grid::phi_edge(j), Grid::phi_edge(j + 1));
                out.push(self.integrate_rect(g, z0, z1, p0, p1, SUB, DEPTH));
            }
        }
        out
    }
}

/// Chi-square test of `sample` (a direction or None) against the density `pdf`. The outcome
/// "None" is one more cell, with probability 1 - integral of pdf.
pub fn chi2_test(
    grid: &Grid,
    n: usize,
    rng: &mut Pcg32,
    mut sample: impl FnMut(&mut Pcg32) -> Option<Vec3>,
    pdf: impl Fn(Vec3) -> f64,
) -> Result<Chi2, String> {
    let cells = grid.cells();
    let mut obs = vec![0.0f64; cells + 1];
    for _ in 0..n {
        match sample(rng) {
            Some(wi) => {
                if !wi.is_finite() {
                    return Err(format!("sampled a non-finite direction {wi}"));
                }
                obs[grid.cell_of(wi)] += 1.0
            }
            None => obs[cells] += 1.0,
        }
    }
    let mut integral = grid.integrate(&pdf);
    // A density whose support ends inside a cell on a curve that is no horizon (a rough
    // dielectric's refraction cone) can leave a sliver the quadrature misses: integrate a cell
    // that received samples but no mass again, 16 times finer in each dimension, before
    // calling its samples impossible.
    for (c, m) in integral.iter_mut().enumerate() {
        if *m == 0.0 && obs[c] > 0.0 {
            let (i, j) = (c / N_PHI, c % N_PHI);
            let (z0, z1) = (Grid::cos_edge(i + 1), Grid::cos_edge(i));
            let (p0, p1) = (Grid::phi_edge(j), Grid::phi_edge(j + 1));
            *m = grid.integrate_rect(&pdf, z0, z1, p0, p1, SUB * 16, DEPTH);
        }
    }
    let total: f64 = integral.iter().sum();
    let mut exp: Vec<f64> = integral.iter().map(|p| p * n as f64).collect();
    // The integration error can push a (near-)zero failure probability below zero; a floor of
    // 1e-3 expected samples keeps that cell in the pooled remainder instead of calling a single
    // failed sample impossible. A real surplus of failures still shows up in the statistic.
    exp.push((n as f64 * (1.0 - total)).max(1e-3));
    chi2_pooled(&obs, &exp, 5.0)
}

pub fn random_u(rng: &mut Pcg32) -> (f32, Vec2) {
    let ul = rng.next_f32();
    let u = Vec2::new(rng.next_f32(), rng.next_f32());
    (ul, u)
}

pub fn chi2_bsdf(bsdf: &Bsdf, wo: Vec3, n: usize, rng: &mut Pcg32) -> Result<Chi2, String> {
    let grid = Grid::for_bsdf(bsdf, wo);
    chi2_test(
        &grid,
        n,
        rng,
        |rng| {
            let (ul, u) = random_u(rng);
            bsdf.sample(wo, ul, u, Mode::Radiance).map(|s| s.wi)
        },
        |wi| bsdf.pdf(wo, wi) as f64,
    )
}
