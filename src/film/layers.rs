//! What a film accumulates besides the beauty image: strategy layers, depth layers, optimal-MIS
//! systems. One `FilmLayout` describes it for tiles, frames, the wire format and checkpoints.

use crate::mis::{Layout, Progressive};

/// (s, t) techniques kept as strategy layers: every technique of depth 0 ..= STRATEGY_DEPTH.
pub const STRATEGY_DEPTH: u32 = 3;

/// Number of strategy layers: sum over d <= 3 of (d + 2) = 14.
pub const STRATEGY_LAYERS: usize = 14;

/// Layer index of technique (s, depth) for depth <= STRATEGY_DEPTH.
#[inline]
pub fn strategy_layer(depth: u32, s: u32) -> Option<usize> {
    (depth <= STRATEGY_DEPTH).then(|| (depth * (depth + 3) / 2 + s) as usize)
}

/// Name of strategy layer `i`, e.g. "s1_t2" (depth s + t - 2).
pub fn strategy_layer_name(i: usize) -> String {
    let mut d = 0u32;
    let mut base = 0usize;
    while base + (d as usize + 2) <= i {
        base += d as usize + 2;
        d += 1;
    }
    let s = (i - base) as u32;
    format!("s{}_t{}", s, d + 2 - s)
}

/// The accumulators a film keeps per pixel, fixed for a whole job.
#[derive(Clone, Debug, PartialEq)]
pub struct FilmLayout {
    /// The weighted contribution of every (s, t) up to `STRATEGY_DEPTH`.
    pub strategy_layers: bool,
    /// Per-depth sums of depths 0 .. depth_layers (0 = none).
    pub depth_layers: usize,
    /// Optimal-MIS systems of depths 1 ..= d_opt.
    pub optimal: Option<Layout>,
    /// With `optimal`: merged films keep the progressive estimator's state (`mis::Progressive`),
    /// and their images are its unbiased estimate instead of the direct estimator's. Task
    /// results (`TaskFilm`) are the same either way.
    pub progressive: bool,
    /// Optimal MIS: regularisation strength used when solving.
    pub kappa: f64,
    /// Write the per-pixel variance of the mean as a layer (meaningful when every sample of a
    /// pixel lands in its camera sums, as for the path tracer).
    pub variance_layer: bool,
    /// Per-pixel sums of light-tracing splats (every integrator but the path tracer, which
    /// makes none: its films and checkpoints leave them out, a third of a checkpoint's bytes).
    pub splats: bool,
}

impl FilmLayout {
    /// The optimal depth of the layout, if any.
    pub fn d_opt(&self) -> Option<u32> {
        self.optimal.as_ref().map(|l| l.d_opt)
    }

    /// The optimal depth of the progressive state merged films keep, if any.
    pub fn progressive_layout(&self) -> Option<u32> {
        self.d_opt().filter(|_| self.progressive)
    }

    /// The names of the EXR layers besides the beauty: the per-pixel variance of the mean
    /// (`variance`, path tracer; BDPT's light-tracing splats have no per-pixel samples), the
    /// strategy layers `s<S>_t<T>` and the depth layers `depth<d>`, as the layout keeps them.
    pub fn extra_layer_names(&self) -> Vec<String> {
        let mut names = Vec::new();
        if self.variance_layer {
            names.push("variance".to_string());
        }
        if self.strategy_layers {
            names.extend((0..STRATEGY_LAYERS).map(strategy_layer_name));
        }
        names.extend((0..self.depth_layers).map(|d| format!("depth{d}")));
        names
    }

    /// Bytes of accumulator memory per pixel of a whole-frame film.
    pub fn bytes_per_pixel(&self) -> usize {
        // Camera sums and sums of squares (2 x 3 f64), count (u32), splat (3 f64) when kept.
        let base = 2 * 24 + 4 + if self.splats { 24 } else { 0 };
        base + self.optimal.as_ref().map_or(0, |o| o.bytes_per_pixel())
            + self
                .progressive_layout()
                .map_or(0, Progressive::bytes_per_pixel)
            + if self.strategy_layers {
                STRATEGY_LAYERS * 24
            } else {
                0
            }
            + self.depth_layers * 24
    }
}
