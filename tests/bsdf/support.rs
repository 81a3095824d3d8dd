//! Checks shared by the BSDF tests: closeness and validity of values, one sample against
//! eval and pdf, mirror reflection, albedo, and the grid integration tolerance.

use crate::grid::*;
use omis::geometry::{Rgb, Vec3};
use omis::material::{Bsdf, BsdfSample, Mode};
use omis::sampler::Pcg32;

/// Absolute error allowed for the grid integration of a pdf over the sphere.
/// `statistics_helpers_are_correct` measures the grid on a cosine lobe and on a uniform
/// hemisphere whose horizon cuts the bins diagonally (a jump, the worst case here) at a few 1e-7;
/// 1e-4 leaves a wide margin and is still small next to the sampling tolerance (5 standard
/// errors, 1e-3 to 8e-3 at 1e5 samples).
pub const INTEGRATION_TOL: f64 = 1e-4;

pub fn rel_close(a: f32, b: f32, rel: f32) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()) + 1e-30
}

pub fn rgb_close(a: Rgb, b: Rgb, rel: f32) -> bool {
    rel_close(a.x, b.x, rel) && rel_close(a.y, b.y, rel) && rel_close(a.z, b.z, rel)
}

pub fn valid_rgb(c: Rgb) -> bool {
    c.is_finite() && c.min_element() >= 0.0
}

/// Checks one sample against the BSDF's own eval / pdf / delta_pdf; returns a description of the
/// first inconsistency.
pub fn check_sample(bsdf: &Bsdf, wo: Vec3, s: &BsdfSample, mode: Mode) -> Result<(), String> {
    if !(s.wi.is_finite() && (s.wi.length() - 1.0).abs() < 1e-4) {
        return Err(format!("wi {} is not a unit vector", s.wi));
    }
    if !(s.pdf > 0.0 && s.pdf.is_finite()) {
        return Err(format!("pdf {}", s.pdf));
    }
    if !valid_rgb(s.f) {
        return Err(format!("f {}", s.f));
    }
    if s.delta != bsdf.is_delta() {
        return Err(format!(
            "delta flag {} on a lobe with is_delta {}",
            s.delta,
            bsdf.is_delta()
        ));
    }
    if s.delta {
        let dp = bsdf.delta_pdf(wo, s.wi);
        if !rel_close(dp, s.pdf, 1e-5) {
            return Err(format!("delta_pdf {dp} != sampled probability {}", s.pdf));
        }
        let (f, p) = (bsdf.eval(wo, s.wi, mode), bsdf.pdf(wo, s.wi));
        if f != Rgb::ZERO || p != 0.0 {
            return Err(format!("delta lobe has eval {f} / pdf {p} != 0"));
        }
    } else {
        let p = bsdf.pdf(wo, s.wi);
        if !rel_close(p, s.pdf, 1e-3) {
            return Err(format!("sampled pdf {} != pdf(wo, wi) {p}", s.pdf));
        }
        let f = bsdf.eval(wo, s.wi, mode);
        if !rgb_close(f, s.f, 1e-3) {
            return Err(format!("sampled f {} != eval(wo, wi) {f}", s.f));
        }
        if bsdf.delta_pdf(wo, s.wi) != 0.0 {
            return Err("delta_pdf != 0 on a non-delta lobe".into());
        }
    }
    Ok(())
}

pub fn reflect(w: Vec3, n: Vec3) -> Vec3 {
    2.0 * w.dot(n) * n - w
}

/// Mean and standard error of f cos / pdf per channel over n samples (failures count as 0).
pub fn albedo(bsdf: &Bsdf, wo: Vec3, n: usize, rng: &mut Pcg32) -> ([f64; 3], [f64; 3]) {
    let mut sum = [0.0f64; 3];
    let mut sum2 = [0.0f64; 3];
    let ns = bsdf.frame.n;
    for _ in 0..n {
        let (ul, u) = random_u(rng);
        if let Some(s) = bsdf.sample(wo, ul, u, Mode::Radiance) {
            let w = s.f * s.wi.dot(ns).abs() / s.pdf;
            for (c, v) in w.to_array().iter().enumerate() {
                sum[c] += *v as f64;
                sum2[c] += (*v as f64).powi(2);
            }
        }
    }
    let nf = n as f64;
    let mean = sum.map(|s| s / nf);
    let se = std::array::from_fn(|ch| ((sum2[ch] / nf - mean[ch] * mean[ch]).max(0.0) / nf).sqrt());
    (mean, se)
}
