//! Statistical verification of every BSDF in `omis::material`.
//!
//! * `chi2_*`: chi-square goodness of fit of `sample()` against `pdf()` (Mitsuba / pbrt style:
//!   bin the sampled directions on the sphere, integrate the pdf over each bin numerically, pool
//!   bins with fewer than 5 expected samples, Sidak-corrected significance over all chi2 tests).
//!   Also run from directions produced by `sample()` itself ("reverse" cases), which tests that
//!   `pdf(wi, wo)` is the density of sampling wo from wi.
//! * `pdf_integrates_to_sampling_probability`: integral of pdf(wo, .) = P(sample() is Some).
//! * `samples_agree_with_eval_and_pdf`: every sample's f / pdf equal eval / pdf at its direction;
//!   reciprocity (and Veach's adjoint relation with shading normals).
//! * `delta_lobes_mirror_and_dielectric`: discrete probabilities, geometry, Mode scaling, energy.
//! * `robustness_*`: no NaN / inf / negative values anywhere, including grazing, exactly normal,
//!   denormal cosines and GGX visible normals nearly perpendicular to wo.
//! * `white_furnace`: energy conservation.
//! * `chi2_has_power_against_wrong_pdfs` / `statistics_helpers_are_correct`: the machinery itself.

mod cases;
mod chi2;
mod delta;
mod furnace;
mod grid;
mod pdf_integral;
mod robustness;
mod samples;
mod stats;
mod stats_self_test;
mod support;
