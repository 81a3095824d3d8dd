//! Fresnel reflectance for dielectric and conductor interfaces.

use crate::geometry::Rgb;

/// Unpolarised Fresnel reflectance of a dielectric interface (Pharr et al., PBR 3rd ed. eq. 8.2).
/// `cos_i` >= 0 is measured on the incident side; `eta` = eta_transmitted / eta_incident.
/// Returns 1 under total internal reflection.
#[inline]
pub fn dielectric(cos_i: f32, eta: f32) -> f32 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).max(0.0).sqrt();
    let rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    let rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    (0.5 * (rs * rs + rp * rp)).clamp(0.0, 1.0)
}

/// Cosine of the refracted direction for `cos_i` and relative index `eta`, or `None` under total
/// internal reflection.
#[inline]
pub fn refracted_cos(cos_i: f32, eta: f32) -> Option<f32> {
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        None
    } else {
        Some((1.0 - sin2_t).max(0.0).sqrt())
    }
}

/// Fresnel reflectance of a conductor with complex index eta + i k, per channel
/// (Pharr et al., PBR 3rd ed. §8.2.1, FrConductor).
pub fn conductor(cos_i: f32, eta: Rgb, k: Rgb) -> Rgb {
    let f = |eta: f32, k: f32| -> f32 {
        let c = cos_i.clamp(0.0, 1.0);
        let c2 = c * c;
        let s2 = 1.0 - c2;
        let eta2 = eta * eta;
        let k2 = k * k;
        let t0 = eta2 - k2 - s2;
        let a2b2 = (t0 * t0 + 4.0 * eta2 * k2).max(0.0).sqrt();
        let t1 = a2b2 + c2;
        let a = (0.5 * (a2b2 + t0)).max(0.0).sqrt();
        let t2 = 2.0 * c * a;
        let rs = (t1 - t2) / (t1 + t2);
        let t3 = c2 * a2b2 + s2 * s2;
        let t4 = t2 * s2;
        let rp = rs * (t3 - t4) / (t3 + t4);
        let r = 0.5 * (rp + rs);
        if r.is_finite() {
            r.clamp(0.0, 1.0)
        } else {
            1.0
        }
    };
    Rgb::new(f(eta.x, k.x), f(eta.y, k.y), f(eta.z, k.z))
}

/// Hemispherical average of the dielectric Fresnel reflectance seen from inside a layer of index
/// `eta` (light leaving the layer): 2 * integral_0^1 F(mu, 1/eta) mu dmu, by quadrature.
pub fn internal_diffuse_reflectance(eta: f32) -> f32 {
    let n = 1024;
    let mut sum = 0.0f64;
    for i in 0..n {
        let mu = (i as f32 + 0.5) / n as f32;
        sum += (dielectric(mu, 1.0 / eta) * mu) as f64;
    }
    (2.0 * sum / n as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dielectric_known_values() {
        // Normal incidence: ((1 - 1.5) / (1 + 1.5))^2 = 0.04.
        assert!((dielectric(1.0, 1.5) - 0.04).abs() < 1e-5);
        assert!((dielectric(0.0, 1.5) - 1.0).abs() < 1e-5);
        // Total internal reflection from inside glass beyond the critical angle (41.8 deg).
        assert_eq!(dielectric(0.5, 1.0 / 1.5), 1.0);
        // Internal diffuse reflectance of n = 1.5 is about 0.596 (Egan & Hilgeman fit).
        let fdr = internal_diffuse_reflectance(1.5);
        assert!((fdr - 0.596).abs() < 0.01, "{fdr}");
    }

    #[test]
    fn conductor_reduces_to_dielectric_when_k_is_zero() {
        for c in [0.1f32, 0.5, 0.9, 1.0] {
            let a = conductor(c, Rgb::splat(1.5), Rgb::ZERO).x;
            assert!((a - dielectric(c, 1.5)).abs() < 1e-4, "{c}: {a}");
        }
    }
}
