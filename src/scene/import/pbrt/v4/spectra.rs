//! pbrt-v4's spectra as the RGB our renderer works in: its named spectra (measured data of
//! pbrt-v4's `src/pbrt/util/spectrum.cpp`, Pharr, Jakob and Humphreys, *Physically Based
//! Rendering*, 4th ed., reduced once to the constants below) and its blackbody emitters.
//!
//! The reduction (a script outside the repository, over pbrt-v4's 1 nm CIE 1931 tables,
//! 360-830 nm, the spectra interpolated linearly as pbrt-v4 does):
//! - an index of refraction or absorption (metals' `eta`, `k`) is weighted by CIE D65 and the
//!   colour matching functions, XYZ = ∫ s D65 cmf / ∫ D65 ȳ, and XYZ goes to linear sRGB, so a
//!   constant spectrum keeps its value in every channel (what an RGB renderer does with it);
//! - a glass's index is one number, the D65·ȳ-weighted mean (within 3e-4 of its value at
//!   550 nm): pbrt-v4 renders dispersion, we cannot;
//! - an illuminant (and a blackbody) is normalised to luminance Y = 1, as pbrt-v4 scales every
//!   light's spectrum to 1 nit before `scale` and `power` apply (`SpectrumToPhotometric`), and
//!   converted to linear sRGB.

use crate::geometry::Rgb;

/// (name without `-eta`/`-k`, eta, k) of pbrt-v4's `metal-*` spectra.
const METALS: [(&str, [f32; 3], [f32; 3]); 7] = [
    (
        "metal-Ag",
        [0.12847, 0.123528, 0.150892],
        [4.06489, 3.28632, 2.39175],
    ),
    (
        "metal-Al",
        [1.40742, 0.926654, 0.584035],
        [7.74042, 6.6026, 5.36029],
    ),
    (
        "metal-Au",
        [0.0800507, 0.404654, 1.56135],
        [3.39047, 2.50377, 1.77089],
    ),
    (
        "metal-Cu",
        [0.104495, 0.97817, 1.20467],
        [3.27334, 2.59235, 2.36924],
    ),
    (
        "metal-CuZn",
        [0.418445, 0.519917, 1.12313],
        [3.66777, 2.68076, 1.77103],
    ),
    (
        "metal-MgO",
        [1.73372, 1.74094, 1.75354],
        [2.14124e-12, -1.77722e-12, 1.23317e-11],
    ),
    (
        "metal-TiO2",
        [2.86039, 2.95648, 3.18553],
        [8.87423e-05, -7.77682e-05, 0.000551262],
    ),
];

/// pbrt-v4's `glass-*` spectra: the mean index (see the module documentation).
const GLASSES: [(&str, f32); 7] = [
    ("glass-BK7", 1.51842),
    ("glass-BAF10", 1.67288),
    ("glass-FK51A", 1.48771),
    ("glass-LASF9", 1.85556),
    ("glass-F5", 1.6769),
    ("glass-F10", 1.73341),
    ("glass-F11", 1.79088),
];

/// pbrt-v4's `stdillum-*` and `illum-*` spectra at luminance 1, linear sRGB.
const ILLUMINANTS: [(&str, [f32; 3]); 16] = [
    ("stdillum-A", [1.84505, 0.826068, 0.233373]),
    ("stdillum-D50", [1.08659, 0.999511, 0.749709]),
    ("stdillum-D65", [1.0, 0.999999, 0.999998]),
    ("stdillum-F1", [0.95426, 1.01929, 0.943665]),
    ("stdillum-F2", [1.34007, 0.942989, 0.562851]),
    ("stdillum-F3", [1.5764, 0.891073, 0.380886]),
    ("stdillum-F4", [1.80626, 0.834202, 0.26707]),
    ("stdillum-F5", [0.915395, 1.03623, 0.890316]),
    ("stdillum-F6", [1.31609, 0.957826, 0.486499]),
    ("stdillum-F7", [1.00032, 1.00017, 0.9974]),
    ("stdillum-F8", [1.17666, 0.975714, 0.720086]),
    ("stdillum-F9", [1.37682, 0.931402, 0.569351]),
    ("stdillum-F10", [1.17756, 0.975621, 0.718363]),
    ("stdillum-F11", [1.41209, 0.924728, 0.531564]),
    ("stdillum-F12", [1.76843, 0.845071, 0.270848]),
    ("illum-acesD60", [1.04692, 0.994574, 0.915527]),
];

/// Lowest temperature of [`BLACKBODY`] (kelvin).
const BLACKBODY_MIN_K: f32 = 1000.0;
/// Highest temperature of [`BLACKBODY`] (kelvin).
const BLACKBODY_MAX_K: f32 = 40000.0;
/// Planck's law at luminance 1 in linear sRGB (negative where outside the gamut), at
/// temperatures spaced evenly in log T from [`BLACKBODY_MIN_K`] to [`BLACKBODY_MAX_K`];
/// linear interpolation in log T is within 1 % of the integral.
const BLACKBODY: [[f32; 3]; 48] = [
    [4.59945, 0.0395996, -0.0900265],
    [4.3211, 0.122415, -0.0904079],
    [4.05024, 0.202802, -0.0888195],
    [3.78908, 0.280051, -0.0846996],
    [3.5393, 0.353598, -0.077447],
    [3.30213, 0.423018, -0.0664459],
    [3.07835, 0.488017, -0.0510966],
    [2.86838, 0.548414, -0.0308476],
    [2.67234, 0.604127, -0.00522696],
    [2.4901, 0.655159, 0.0261304],
    [2.32132, 0.701581, 0.0634622],
    [2.16555, 0.743523, 0.106865],
    [2.02223, 0.781158, 0.15629],
    [1.89072, 0.81469, 0.211545],
    [1.77035, 0.844353, 0.272303],
    [1.66046, 0.870392, 0.338114],
    [1.56035, 0.893066, 0.408427],
    [1.46936, 0.912637, 0.482601],
    [1.38686, 0.929368, 0.55993],
    [1.31221, 0.943521, 0.63966],
    [1.24483, 0.955349, 0.721013],
    [1.18413, 0.965103, 0.8032],
    [1.12959, 0.973022, 0.885452],
    [1.08068, 0.979335, 0.96703],
    [1.0369, 0.984257, 1.04725],
    [0.997788, 0.987991, 1.1255],
    [0.962895, 0.990723, 1.20126],
    [0.931804, 0.992621, 1.27407],
    [0.904125, 0.993835, 1.34359],
    [0.879498, 0.994498, 1.40959],
    [0.857591, 0.994726, 1.47189],
    [0.838101, 0.994615, 1.53041],
    [0.820756, 0.994248, 1.58515],
    [0.805309, 0.993694, 1.63617],
    [0.791541, 0.993006, 1.68355],
    [0.779257, 0.99223, 1.72744],
    [0.768283, 0.9914, 1.76799],
    [0.758467, 0.990544, 1.8054],
    [0.749675, 0.989683, 1.83984],
    [0.741788, 0.988831, 1.87152],
    [0.734703, 0.988001, 1.90063],
    [0.728329, 0.9872, 1.92735],
    [0.722586, 0.986433, 1.95186],
    [0.717404, 0.985704, 1.97436],
    [0.712722, 0.985015, 1.99498],
    [0.708485, 0.984366, 2.01389],
    [0.704647, 0.983757, 2.03124],
    [0.701165, 0.983188, 2.04714],
];

/// What a named spectrum stands for where it is used.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) enum SpectrumUse {
    /// A material's: an index of refraction or absorption (`eta`, `k`), or a reflectance.
    Material,
    /// Emission (`L`, `I`).
    Illuminant,
}

/// The RGB of pbrt-v4's named spectrum `name` used as `usage`; `None` for an unknown name or
/// one of another kind (a glass's index as emission, say).
pub(super) fn named_spectrum(name: &str, usage: SpectrumUse) -> Option<Rgb> {
    match usage {
        SpectrumUse::Material => {
            if let Some((_, eta)) = GLASSES.iter().find(|(n, _)| *n == name) {
                return Some(Rgb::splat(*eta));
            }
            let (metal, part) = name.rsplit_once('-')?;
            let (_, eta, k) = METALS.iter().find(|(n, _, _)| *n == metal)?;
            match part {
                "eta" => Some(Rgb::from_array(*eta)),
                "k" => Some(Rgb::from_array(*k).max(Rgb::ZERO)),
                _ => None,
            }
        }
        SpectrumUse::Illuminant => ILLUMINANTS
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, c)| Rgb::from_array(*c)),
    }
}

/// Whether `name` is one of pbrt-v4's glasses (a single index of refraction).
pub(super) fn is_glass(name: &str) -> bool {
    GLASSES.iter().any(|(n, _)| *n == name)
}

/// A blackbody emitter of `kelvin` at luminance 1 in linear sRGB, the components that fall
/// outside the gamut clamped to 0; `None` outside 1000-40000 K.
pub(super) fn blackbody(kelvin: f32) -> Option<Rgb> {
    if !(BLACKBODY_MIN_K..=BLACKBODY_MAX_K).contains(&kelvin) {
        return None;
    }
    let steps = (BLACKBODY.len() - 1) as f32;
    let x = (kelvin / BLACKBODY_MIN_K).ln() / (BLACKBODY_MAX_K / BLACKBODY_MIN_K).ln() * steps;
    let i = (x.floor() as usize).min(BLACKBODY.len() - 2);
    let t = x - i as f32;
    let a = Rgb::from_array(BLACKBODY[i]);
    let b = Rgb::from_array(BLACKBODY[i + 1]);
    Some((a + (b - a) * t).max(Rgb::ZERO))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn d65_is_white_and_named_spectra_are_found_by_use() {
        let d65 = named_spectrum("stdillum-D65", SpectrumUse::Illuminant).expect("D65");
        assert!((d65 - Rgb::ONE).abs().max_element() < 1e-5, "{d65:?}");
        let au = named_spectrum("metal-Au-eta", SpectrumUse::Material).expect("gold");
        assert!(au.x < au.z, "gold's eta rises toward blue: {au:?}");
        assert!(named_spectrum("glass-BK7", SpectrumUse::Illuminant).is_none());
        assert!(
            (named_spectrum("glass-BK7", SpectrumUse::Material)
                .expect("BK7")
                .x
                - 1.5184)
                .abs()
                < 1e-3
        );
        assert!(named_spectrum("metal-Xx-eta", SpectrumUse::Material).is_none());
    }

    #[test]
    fn blackbody_is_white_near_d65_and_red_when_cool() {
        // Planck at 6504 K is close to D65 (its correlated colour temperature).
        let w = blackbody(6504.0).expect("in range");
        assert!((w - Rgb::ONE).abs().max_element() < 0.05, "{w:?}");
        let warm = blackbody(2700.0).expect("in range");
        assert!(warm.x > warm.y && warm.y > warm.z, "{warm:?}");
        // Luminance 1 (Rec. 709 / sRGB luminance weights).
        let y = 0.2126 * warm.x + 0.7152 * warm.y + 0.0722 * warm.z;
        assert!((y - 1.0).abs() < 0.01, "{y}");
        assert!(blackbody(500.0).is_none());
    }
}
